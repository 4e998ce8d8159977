//! The `boltwatch.modal_set.v1` message (DESIGN §3.2): one set of measured modes (natural
//! frequencies, optional mode shapes on named channels, optional uncertainties) of a watched
//! structure at one time.
//!
//! This module owns the contract: the Rust types, the strict validation of incoming payloads
//! ([`parse_modal_set`]) and the canonical JSON encoding ([`ModalSet::to_json`]). Every
//! rejection names the offending field as a JSON path (`modes[2].shape[5]`) and says why,
//! with the data. Payloads from Python's `json.dumps` may carry bare `NaN`, `Infinity` and
//! `-Infinity`; these are recognised (outside string literals only) and rejected by field.

mod envelope;
mod mode;
mod modes;

use chrono::{DateTime, Utc};
use serde_json::{Map, Value};

pub use super::fields::capped;
use super::fields::{format_time, json_object, no_unknown_fields, time_field};
use envelope::{
    check_schema, check_time, parse_channels, parse_peaks, parse_source, watched_structure,
};
use modes::{parse_missing, parse_modes, unique_labels};

/// The value of the `schema` field of every modal set.
pub const MODAL_SET_SCHEMA: &str = "boltwatch.modal_set.v1";

/// Relative tolerance of the increasing-frequency rule.
pub const FREQUENCY_ORDER_TOLERANCE: f64 = 1e-6;

/// The smallest `frequency_cov` and `shape_nsd` accepted. A frequency known to 1 ppm needs
/// about 10⁶ periods of record (28 hours at 10 Hz), beyond any identification this daemon
/// is fed; below it the weights 1/σ² of (9) reach 10¹² and ε loses its meaning, and at
/// 1e-300 they overflow.
pub const UNCERTAINTY_FLOOR: f64 = 1e-6;

/// The most modes a set may carry. Identifications deliver tens; each mode costs the
/// update an eigenpair and its sensitivities, so a set of thousands (a fuzzed one carried
/// 1,534 copies of one mode) would hold up tracking for seconds.
pub const MAX_MODES: usize = 100;

/// The longest reason a rejection carries, in bytes: a reason quotes the offending data,
/// which an attacker chooses.
pub const REASON_LIMIT: usize = 512;

/// The longest field path a rejection names, in bytes (an unknown key is named by itself).
pub const FIELD_LIMIT: usize = 128;

/// The longest mode label, in bytes.
pub const LABEL_LIMIT: usize = 64;

/// Top-level fields of the contract.
const TOP_FIELDS: &[&str] = &[
    "schema",
    "structure",
    "time",
    "channels",
    "modes",
    "temperature_c",
    "source",
    "missing",
    "unexplained_peaks",
    "covariates",
];

/// One measured modal set, validated.
#[derive(Debug, Clone, PartialEq)]
pub struct ModalSet {
    /// Name of the structure the set was measured on.
    pub structure: String,
    /// Time of the measurement.
    pub time: DateTime<Utc>,
    /// Names of the mode-shape entries, in order; channels of the model, no duplicates.
    /// Empty only when no mode carries a shape.
    pub channels: Vec<String>,
    /// The modes, by increasing frequency (within [`FREQUENCY_ORDER_TOLERANCE`]).
    pub modes: Vec<MeasuredMode>,
    /// Temperature of the structure during the measurement, °C (within
    /// [`super::environment::TEMPERATURE_RANGE_C`]).
    pub temperature_c: Option<f64>,
    /// Other conditions of the measurement by name (humidity, traffic RMS, …;
    /// [`super::environment::Conditions`]). Empty when not given.
    pub covariates: std::collections::BTreeMap<String, f64>,
    /// Free-text provenance (e.g. the identification run).
    pub source: Option<String>,
    /// Labels of modes identified in earlier sets of this source and not in this one
    /// (tracking across windows, issue 26): reported missing, not renumbered. Empty when
    /// not given.
    pub missing: Vec<String>,
    /// Peaks of the record's spectrum that no mode of the set explains (an
    /// identification's cross-check, [`crate::core::oma::identify::unexplained_peaks`]).
    /// Empty when not given.
    pub unexplained_peaks: Vec<SpectrumPeak>,
}

/// A peak of the first singular value of a record's spectrum.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SpectrumPeak {
    /// Frequency, Hz (finite, > 0).
    pub frequency_hz: f64,
    /// Height above the higher of its two valleys, dB (finite, > 0).
    pub prominence_db: f64,
}

/// One measured mode.
#[derive(Debug, Clone, PartialEq)]
pub struct MeasuredMode {
    /// Natural frequency, Hz (finite, > 0).
    pub frequency_hz: f64,
    /// Coefficient of variation of the frequency (> 0).
    pub frequency_cov: Option<f64>,
    /// Mode shape, one entry per channel of the set; `None` entries were not measured.
    /// Never empty and never all `None`.
    pub shape: Option<Vec<Option<f64>>>,
    /// Normalized standard deviation of the shape (> 0); only on modes with a shape.
    pub shape_nsd: Option<f64>,
    /// Absolute standard deviation of each shape entry (≥ 0, in the scale of `shape`),
    /// `None` exactly where the shape entry is; used instead of `shape_nsd` when present
    /// (entries of ~0 std are floored, [`crate::core::updating::data::floored_shape_std`]).
    pub shape_std: Option<Vec<Option<f64>>>,
    /// Modal damping ratio, a fraction in `[0, 1)` (as an identification reports it; the
    /// updating uses frequencies and shapes only).
    pub damping_ratio: Option<f64>,
    /// Standard deviation of `damping_ratio` (> 0); only with it.
    pub damping_std: Option<f64>,
    /// The mode's identity across sets of one source (`mode 3`: paired with the model's
    /// third mode); unique within the set.
    pub label: Option<String>,
}

/// Why a modal set was rejected: the offending field (a JSON path such as `modes[2].shape[5]`) and the reason.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{field}: {reason}")]
pub struct Rejection {
    /// JSON path of the offending field (`payload` when the payload as a whole is bad).
    pub field: String,
    /// Why, with the offending data.
    pub reason: String,
}

/// What the receiver knows when validating.
pub struct ValidationContext<'a> {
    /// Structures this process watches (a set is rejected if its `structure` is not one of them).
    pub structures: &'a [&'a str],
    /// Channel names of the model, in model order.
    pub model_channels: &'a [String],
    /// Time of the last accepted set, if any.
    pub last_time: Option<DateTime<Utc>>,
    /// Replays may allow a set with the same time as the last accepted one.
    pub allow_equal_time: bool,
    /// Live: the receiver's clock and how far ahead of it a set may be stamped; a set
    /// stamped later is rejected (a sensor clock glitch must not become the last accepted
    /// time, which would reject every later, correct set).
    pub max_future: Option<(DateTime<Utc>, chrono::TimeDelta)>,
}

/// Parses and validates a payload. Never panics on any input bytes.
///
/// Rejections (field / reason):
/// - `payload`: not UTF-8, not JSON (with the parser's message) or not an object;
/// - `schema`: missing or not [`MODAL_SET_SCHEMA`];
/// - an unknown top-level or mode field, named by its path;
/// - `structure`: missing, not a string, or not one of `ctx.structures`;
/// - `time`: missing, not RFC 3339, earlier than `ctx.last_time` (or equal to it unless
///   `ctx.allow_equal_time`);
/// - `channels[j]`: not a string, not a channel of the model, or a duplicate;
/// - `modes`: missing, not an array or empty; `modes[i]` not an object;
/// - any number (`frequency_hz`, `frequency_cov`, shape entries, `shape_nsd`,
///   `temperature_c`, covariates) not finite (bare `NaN`/`Infinity`, overflow) or of the
///   wrong type;
/// - `temperature_c` outside [`super::environment::TEMPERATURE_RANGE_C`]; `covariates` not
///   an object of named numbers ([`super::environment::Conditions`]);
/// - `modes[i].frequency_hz`: ≤ 0, or below the previous mode's frequency by more than
///   [`FREQUENCY_ORDER_TOLERANCE`] (relative);
/// - `modes[i].frequency_cov`, `modes[i].shape_nsd`: ≤ 0, or present on some modes (with a
///   shape, for `shape_nsd`) but not others; `shape_nsd` on a mode without a shape (a mode
///   with `shape_std` counts as one with `shape_nsd`);
/// - `modes[i].shape_std`: see the rule `shape_std` (in `mode.rs`);
/// - `modes[i].shape`: empty, all null, or not as long as `channels`.
///
/// `null` is accepted only as a shape entry: an optional field is either present with a
/// value or absent.
pub fn parse_modal_set(payload: &[u8], ctx: &ValidationContext) -> Result<ModalSet, Rejection> {
    validate_modal_set(&modal_set_object(payload)?, ctx)
}

/// The first step of [`parse_modal_set`], which depends on the payload alone: its JSON
/// object (UTF-8, JSON with the non-finite spellings rewritten, an object at the top).
pub fn modal_set_object(payload: &[u8]) -> Result<Map<String, Value>, Rejection> {
    json_object(payload)
}

/// The rest of [`parse_modal_set`]: the object of [`modal_set_object`] validated in `ctx`.
pub fn validate_modal_set(
    obj: &Map<String, Value>,
    ctx: &ValidationContext,
) -> Result<ModalSet, Rejection> {
    screen_modal_set(obj, ctx).finish(ctx)
}

/// A modal set checked by every rule that does not depend on the receiver's state
/// ([`screen_modal_set`]); [`Screened::finish`] adds the rules that do (the time against
/// the receiver's clock and the last accepted set) in their place in the order of the
/// rules, so the same payload gets the same verdict as from [`validate_modal_set`].
#[derive(Debug)]
pub struct Screened {
    /// The set's time, when every rule before the time's passed (its checks against the
    /// receiver's state are still to come).
    time: Option<DateTime<Utc>>,
    outcome: Result<ModalSet, Rejection>,
}

/// The rules of [`validate_modal_set`] that depend on the payload, the watched structures
/// (`ctx.structures`) and the model's channels (`ctx.model_channels`) alone, so that a
/// driver may run them ahead on another thread; `ctx.last_time` and `ctx.max_future` are
/// not used here.
pub fn screen_modal_set(obj: &Map<String, Value>, ctx: &ValidationContext) -> Screened {
    let head = check_schema(obj)
        .and_then(|()| no_unknown_fields(obj, TOP_FIELDS, ""))
        .and_then(|()| watched_structure(obj, ctx))
        .and_then(|structure| Ok((structure, time_field(obj)?)));
    match head {
        Ok((structure, time)) => Screened {
            time: Some(time),
            outcome: screen_body(obj, ctx, structure, time),
        },
        Err(rej) => Screened {
            time: None,
            outcome: Err(rej),
        },
    }
}

/// The fields after the time, for [`screen_modal_set`].
fn screen_body(
    obj: &Map<String, Value>,
    ctx: &ValidationContext,
    structure: &str,
    time: DateTime<Utc>,
) -> Result<ModalSet, Rejection> {
    let channels = parse_channels(obj, ctx.model_channels)?;
    let modes = parse_modes(obj, channels.len())?;
    let super::environment::Conditions {
        temperature_c,
        covariates,
    } = super::environment::Conditions::parse(obj)?;
    let source = parse_source(obj)?;
    let labels = unique_labels(&modes)?;
    let missing = parse_missing(obj.get("missing"), &labels)?;
    let unexplained_peaks = parse_peaks(obj.get("unexplained_peaks"))?;
    Ok(ModalSet {
        structure: structure.to_string(),
        time,
        channels,
        modes,
        temperature_c,
        covariates,
        source,
        missing,
        unexplained_peaks,
    })
}

impl Screened {
    /// The verdict in `ctx`: the time's rules against the receiver's state where they
    /// come, then the rest of the screening's.
    pub fn finish(self, ctx: &ValidationContext) -> Result<ModalSet, Rejection> {
        if let Some(time) = self.time {
            check_time(time, ctx)?;
        }
        self.outcome
    }
}

impl ModalSet {
    /// The measurement's own conditions (temperature and covariates).
    pub fn conditions(&self) -> super::environment::Conditions {
        super::environment::Conditions {
            temperature_c: self.temperature_c,
            covariates: self.covariates.clone(),
        }
    }

    /// The set as a `boltwatch.modal_set.v1` JSON value (absent optionals omitted, unmeasured entries `null`), which parse_modal_set accepts back unchanged. time formatted RFC 3339 with `Z`, seconds precision unless sub-seconds are present.
    ///
    /// `channels` is omitted when empty. Numbers are written with the shortest
    /// representation that reads back to the same `f64`.
    pub fn to_json(&self) -> Value {
        let mut obj = Map::new();
        obj.insert("schema".into(), MODAL_SET_SCHEMA.into());
        obj.insert("structure".into(), self.structure.clone().into());
        obj.insert("time".into(), format_time(&self.time).into());
        if !self.channels.is_empty() {
            obj.insert("channels".into(), self.channels.clone().into());
        }
        let modes = self
            .modes
            .iter()
            .map(|m| {
                let mut mode = Map::new();
                mode.insert("frequency_hz".into(), m.frequency_hz.into());
                if let Some(cov) = m.frequency_cov {
                    mode.insert("frequency_cov".into(), cov.into());
                }
                if let Some(shape) = &m.shape {
                    let entries = shape
                        .iter()
                        .map(|e| e.map_or(Value::Null, Value::from))
                        .collect();
                    mode.insert("shape".into(), Value::Array(entries));
                }
                if let Some(nsd) = m.shape_nsd {
                    mode.insert("shape_nsd".into(), nsd.into());
                }
                if let Some(std) = &m.shape_std {
                    let entries = std
                        .iter()
                        .map(|e| e.map_or(Value::Null, Value::from))
                        .collect();
                    mode.insert("shape_std".into(), Value::Array(entries));
                }
                if let Some(z) = m.damping_ratio {
                    mode.insert("damping_ratio".into(), z.into());
                }
                if let Some(z) = m.damping_std {
                    mode.insert("damping_std".into(), z.into());
                }
                if let Some(l) = &m.label {
                    mode.insert("label".into(), l.clone().into());
                }
                Value::Object(mode)
            })
            .collect();
        obj.insert("modes".into(), Value::Array(modes));
        self.conditions().write(&mut obj);
        if let Some(s) = &self.source {
            obj.insert("source".into(), s.clone().into());
        }
        if !self.missing.is_empty() {
            obj.insert("missing".into(), self.missing.clone().into());
        }
        if !self.unexplained_peaks.is_empty() {
            let peaks = self
                .unexplained_peaks
                .iter()
                .map(|p| {
                    serde_json::json!({
                        "frequency_hz": p.frequency_hz,
                        "prominence_db": p.prominence_db,
                    })
                })
                .collect();
            obj.insert("unexplained_peaks".into(), Value::Array(peaks));
        }
        Value::Object(obj)
    }

    /// True when every mode carries `frequency_cov` and every mode with a shape carries `shape_nsd` or `shape_std` (weighting by the measurement covariance); false when none does.
    ///
    /// Also false for a set without modes, and for a set whose frequencies carry
    /// uncertainties but whose shapes do not (the covariance weighting needs both).
    pub fn has_uncertainties(&self) -> bool {
        !self.modes.is_empty()
            && self.modes.iter().all(|m| {
                m.frequency_cov.is_some() && (m.shape.is_none() || m.has_shape_uncertainty())
            })
    }
}

impl MeasuredMode {
    /// Whether the shape's uncertainty is given, by `shape_nsd` or `shape_std`.
    pub fn has_shape_uncertainty(&self) -> bool {
        self.shape_nsd.is_some() || self.shape_std.is_some()
    }
}
