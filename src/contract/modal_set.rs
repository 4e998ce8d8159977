//! The `boltwatch.modal_set.v1` message (DESIGN §3.2): one set of measured modes (natural
//! frequencies, optional mode shapes on named channels, optional uncertainties) of a watched
//! structure at one time.
//!
//! This module owns the contract: the Rust types, the strict validation of incoming payloads
//! ([`parse_modal_set`]) and the canonical JSON encoding ([`ModalSet::to_json`]). Every
//! rejection names the offending field as a JSON path (`modes[2].shape[5]`) and says why,
//! with the data. Payloads from Python's `json.dumps` may carry bare `NaN`, `Infinity` and
//! `-Infinity`; these are recognised (outside string literals only) and rejected by field.

use chrono::{DateTime, Utc};
use serde_json::{Map, Value};

pub use super::fields::capped;
use super::fields::{
    format_time, json_object, kind, no_unknown_fields, number, positive, reject, required, string,
    time_field,
};
use super::nonfinite::nonfinite_token;

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

/// Fields of one mode.
const MODE_FIELDS: &[&str] = &[
    "frequency_hz",
    "frequency_cov",
    "shape",
    "shape_nsd",
    "shape_std",
    "damping_ratio",
    "damping_std",
    "label",
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

/// An uncertainty (a CoV or an NSD): a finite number ≥ [`UNCERTAINTY_FLOOR`].
fn uncertainty(v: &Value, field: &str) -> Result<f64, Rejection> {
    let x = positive(v, field)?;
    if x >= UNCERTAINTY_FLOOR {
        Ok(x)
    } else {
        Err(reject(
            field,
            format!(
                "{x:e} is below the floor {UNCERTAINTY_FLOOR:e} (no identification resolves a mode that finely; the weights of (9) would be meaningless)"
            ),
        ))
    }
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
/// - `modes[i].shape_std`: see `shape_std` (the function);
/// - `modes[i].shape`: empty, all null, or not as long as `channels`.
///
/// `null` is accepted only as a shape entry: an optional field is either present with a
/// value or absent.
pub fn parse_modal_set(payload: &[u8], ctx: &ValidationContext) -> Result<ModalSet, Rejection> {
    let obj = json_object(payload)?;

    // schema
    let schema = required(&obj, "schema", "schema")?;
    if schema.as_str() != Some(MODAL_SET_SCHEMA) {
        let got = match schema.as_str() {
            Some(s) if nonfinite_token(schema).is_none() => format!("{s:?}"),
            _ => kind(schema),
        };
        return Err(reject(
            "schema",
            format!("expected {MODAL_SET_SCHEMA:?}, got {got}"),
        ));
    }
    no_unknown_fields(&obj, TOP_FIELDS, "")?;

    // structure
    let structure = string(required(&obj, "structure", "structure")?, "structure")?;
    if !ctx.structures.contains(&structure) {
        return Err(reject(
            "structure",
            format!(
                "{structure:?} is not a watched structure (watched: {:?})",
                ctx.structures
            ),
        ));
    }

    // time
    let time = time_field(&obj)?;
    if let Some((now, ahead)) = ctx.max_future
        && time > now + ahead
    {
        return Err(reject(
            "time",
            format!(
                "{} is {:.0} s ahead of the receiver's clock ({}); at most {} s allowed (daemon.max_future_s)",
                format_time(&time),
                (time - now).as_seconds_f64(),
                format_time(&now),
                ahead.num_seconds()
            ),
        ));
    }
    if let Some(last) = ctx.last_time {
        if time < last {
            return Err(reject(
                "time",
                format!(
                    "{} is earlier than the last accepted set's {}",
                    format_time(&time),
                    format_time(&last)
                ),
            ));
        }
        if time == last && !ctx.allow_equal_time {
            return Err(reject(
                "time",
                format!(
                    "{} equals the last accepted set's {} (equal times allowed only in replays)",
                    format_time(&time),
                    format_time(&last)
                ),
            ));
        }
    }

    // channels
    let mut channels: Vec<String> = Vec::new();
    if let Some(v) = obj.get("channels") {
        let Value::Array(items) = v else {
            return Err(reject(
                "channels",
                format!("expected an array, got {}", kind(v)),
            ));
        };
        for (j, item) in items.iter().enumerate() {
            let field = || format!("channels[{j}]");
            let name = match item.as_str() {
                Some(s) if nonfinite_token(item).is_none() => s,
                _ => string(item, &field())?,
            };
            if !ctx.model_channels.iter().any(|c| c == name) {
                return Err(reject(
                    field(),
                    format!("unknown channel {name:?} (not a channel of the model)"),
                ));
            }
            if let Some(k) = channels.iter().position(|c| c == name) {
                return Err(reject(
                    field(),
                    format!("duplicate channel {name:?} (also channels[{k}])"),
                ));
            }
            channels.push(name.to_string());
        }
    }

    // modes
    let modes_value = required(&obj, "modes", "modes")?;
    let Value::Array(items) = modes_value else {
        return Err(reject(
            "modes",
            format!("expected an array, got {}", kind(modes_value)),
        ));
    };
    if items.is_empty() {
        return Err(reject("modes", "must not be empty"));
    }
    if items.len() > MAX_MODES {
        return Err(reject(
            "modes",
            format!(
                "{} modes, more than the {MAX_MODES} a set may carry",
                items.len()
            ),
        ));
    }
    let modes = items
        .iter()
        .enumerate()
        .map(|(i, v)| parse_mode(i, v, channels.len()))
        .collect::<Result<Vec<_>, _>>()?;
    check_frequency_order(&modes)?;
    check_uncertainty_consistency(&modes)?;

    let super::environment::Conditions {
        temperature_c,
        covariates,
    } = super::environment::Conditions::parse(&obj)?;
    let source = obj
        .get("source")
        .map(|v| string(v, "source").map(str::to_string))
        .transpose()?;
    let mut labels = std::collections::HashSet::new();
    for (i, m) in modes.iter().enumerate() {
        if let Some(l) = &m.label
            && !labels.insert(l.as_str())
        {
            return Err(reject(
                format!("modes[{i}].label"),
                format!("`{}` labels an earlier mode too", capped(l, 64)),
            ));
        }
    }
    let missing = match obj.get("missing") {
        None => Vec::new(),
        Some(Value::Array(items)) => {
            let mut out = Vec::with_capacity(items.len());
            for (i, v) in items.iter().enumerate() {
                let path = format!("missing[{i}]");
                let l = label(v, &path)?;
                if labels.contains(l) {
                    return Err(reject(path, format!("`{l}` labels a mode of this set")));
                }
                out.push(l.to_string());
            }
            out
        }
        Some(other) => {
            return Err(reject(
                "missing",
                format!("expected an array of labels, got {}", kind(other)),
            ));
        }
    };

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

/// `unexplained_peaks`: absent, or an array of `{frequency_hz, prominence_db}`, both > 0.
fn parse_peaks(v: Option<&Value>) -> Result<Vec<SpectrumPeak>, Rejection> {
    let items = match v {
        None => return Ok(Vec::new()),
        Some(Value::Array(items)) => items,
        Some(other) => {
            return Err(reject(
                "unexplained_peaks",
                format!("expected an array of peaks, got {}", kind(other)),
            ));
        }
    };
    items
        .iter()
        .enumerate()
        .map(|(i, item)| {
            let path = format!("unexplained_peaks[{i}]");
            let Value::Object(o) = item else {
                return Err(reject(
                    &path,
                    format!("expected an object, got {}", kind(item)),
                ));
            };
            if let Some(k) = o
                .keys()
                .find(|k| !["frequency_hz", "prominence_db"].contains(&k.as_str()))
            {
                return Err(reject(format!("{path}.{}", capped(k, 64)), "unknown field"));
            }
            let field = |name: &str| {
                let f = format!("{path}.{name}");
                o.get(name)
                    .ok_or_else(|| reject(&f, "missing (required)"))
                    .and_then(|v| positive(v, &f))
            };
            Ok(SpectrumPeak {
                frequency_hz: field("frequency_hz")?,
                prominence_db: field("prominence_db")?,
            })
        })
        .collect()
}

/// Parses and validates `modes[i]` on its own; `n_channels` is the length of `channels`.
fn parse_mode(i: usize, v: &Value, n_channels: usize) -> Result<MeasuredMode, Rejection> {
    let path = format!("modes[{i}]");
    let Value::Object(obj) = v else {
        return Err(reject(path, format!("expected an object, got {}", kind(v))));
    };
    no_unknown_fields(obj, MODE_FIELDS, &format!("{path}."))?;

    let f_path = format!("{path}.frequency_hz");
    let frequency_hz = positive(required(obj, "frequency_hz", &f_path)?, &f_path)?;
    let frequency_cov = obj
        .get("frequency_cov")
        .map(|v| uncertainty(v, &format!("{path}.frequency_cov")))
        .transpose()?;

    let shape = match obj.get("shape") {
        None => None,
        Some(v) => {
            let s_path = format!("{path}.shape");
            let Value::Array(entries) = v else {
                return Err(reject(
                    s_path,
                    format!("expected an array, got {}", kind(v)),
                ));
            };
            let mut shape = Vec::with_capacity(entries.len());
            for (k, e) in entries.iter().enumerate() {
                // The common case first, without building the entry's path.
                if let Some(x) = e.as_f64().filter(|x| x.is_finite()) {
                    shape.push(Some(x));
                    continue;
                }
                shape.push(match e {
                    Value::Null => None,
                    other => Some(number(other, &format!("{s_path}[{k}]")).map_err(|r| {
                        if other.is_number() || nonfinite_token(other).is_some() {
                            r
                        } else {
                            reject(
                                r.field,
                                format!("expected a number or null, got {}", kind(other)),
                            )
                        }
                    })?),
                });
            }
            if shape.is_empty() {
                return Err(reject(
                    s_path,
                    "must not be empty (omit it for a frequency-only mode)",
                ));
            }
            if shape.len() != n_channels {
                return Err(reject(
                    s_path,
                    format!("has {} entries but channels has {n_channels}", shape.len()),
                ));
            }
            if shape.iter().all(Option::is_none) {
                return Err(reject(
                    s_path,
                    format!(
                        "all {} entries are null (omit it for a frequency-only mode)",
                        shape.len()
                    ),
                ));
            }
            check_normalizable(&shape, &s_path)?;
            Some(shape)
        }
    };

    let nsd_path = format!("{path}.shape_nsd");
    let shape_nsd = obj
        .get("shape_nsd")
        .map(|v| uncertainty(v, &nsd_path))
        .transpose()?;
    if shape_nsd.is_some() && shape.is_none() {
        return Err(reject(nsd_path, "present on a mode without a shape"));
    }
    let shape_std = match obj.get("shape_std") {
        None => None,
        Some(v) => Some(shape_std(
            v,
            shape.as_deref(),
            &format!("{path}.shape_std"),
        )?),
    };

    let z_path = format!("{path}.damping_ratio");
    let damping_ratio = match obj.get("damping_ratio") {
        None => None,
        Some(v) => {
            let z = number(v, &z_path)?;
            if !(0.0..1.0).contains(&z) {
                return Err(reject(
                    z_path,
                    format!("{z} is not a damping ratio (a fraction in [0, 1))"),
                ));
            }
            Some(z)
        }
    };
    let zs_path = format!("{path}.damping_std");
    let damping_std = obj
        .get("damping_std")
        .map(|v| positive(v, &zs_path))
        .transpose()?;
    if damping_std.is_some() && damping_ratio.is_none() {
        return Err(reject(zs_path, "present on a mode without damping_ratio"));
    }
    let label = obj
        .get("label")
        .map(|v| label(v, &format!("{path}.label")).map(str::to_string))
        .transpose()?;

    Ok(MeasuredMode {
        frequency_hz,
        frequency_cov,
        shape,
        shape_nsd,
        shape_std,
        damping_ratio,
        damping_std,
        label,
    })
}

/// The longest mode label, in bytes.
pub const LABEL_LIMIT: usize = 64;

/// A mode label: a non-empty string of at most [`LABEL_LIMIT`] bytes.
fn label<'v>(v: &'v Value, path: &str) -> Result<&'v str, Rejection> {
    let l = string(v, path)?;
    if l.is_empty() || l.len() > LABEL_LIMIT {
        return Err(reject(
            path,
            format!(
                "a label has 1 to {LABEL_LIMIT} bytes, `{}` has {}",
                capped(l, LABEL_LIMIT),
                l.len()
            ),
        ));
    }
    Ok(l)
}

/// Rule: `shape_std` belongs to a mode with a shape, has one entry per shape entry, `null`
/// exactly where the shape is, numbers finite and ≥ 0, and at least one > 0 (a zero is the
/// reference entry of a normalized shape, floored later); the median of the positive ones
/// is at least [`UNCERTAINTY_FLOOR`] times the shape's RMS (below it the weights lose
/// their meaning, as for `shape_nsd`).
fn shape_std(
    v: &Value,
    shape: Option<&[Option<f64>]>,
    path: &str,
) -> Result<Vec<Option<f64>>, Rejection> {
    let Some(shape) = shape else {
        return Err(reject(path, "present on a mode without a shape"));
    };
    let Value::Array(entries) = v else {
        return Err(reject(path, format!("expected an array, got {}", kind(v))));
    };
    if entries.len() != shape.len() {
        return Err(reject(
            path,
            format!(
                "has {} entries but the shape has {}",
                entries.len(),
                shape.len()
            ),
        ));
    }
    let mut out = Vec::with_capacity(entries.len());
    for (k, (e, s)) in entries.iter().zip(shape).enumerate() {
        let field = format!("{path}[{k}]");
        out.push(match (e, s) {
            (Value::Null, None) => None,
            (Value::Null, Some(_)) => {
                return Err(reject(field, "null where the shape entry is a number"));
            }
            (_, None) => {
                return Err(reject(field, "a number where the shape entry is null"));
            }
            (e, Some(_)) => {
                let x = number(e, &field)?;
                if x < 0.0 {
                    return Err(reject(field, format!("{x} is negative")));
                }
                Some(x)
            }
        });
    }
    let Some(median) = crate::core::updating::data::positive_median(out.iter().flatten()) else {
        return Err(reject(path, "every entry is 0 (at least one must be > 0)"));
    };
    let measured: Vec<f64> = shape.iter().flatten().copied().collect();
    let rms = (measured.iter().map(|x| x * x).sum::<f64>() / measured.len() as f64).sqrt();
    if median < UNCERTAINTY_FLOOR * rms {
        return Err(reject(
            path,
            format!(
                "the median of its positive entries, {median:e}, is below {UNCERTAINTY_FLOOR:e} \
                 times the shape's RMS {rms:e} (the weights of (28) would be meaningless)"
            ),
        ));
    }
    Ok(out)
}

/// Rule: a shape has a direction that can be normalized: not all zero, and its norm and
/// the norm's reciprocal finite (entries of 1e-310 or 1e200 would overflow the MAC and the
/// scaling of (9)).
fn check_normalizable(shape: &[Option<f64>], path: &str) -> Result<(), Rejection> {
    let largest = shape.iter().flatten().fold(0.0_f64, |m, x| m.max(x.abs()));
    if largest == 0.0 {
        return Err(reject(
            path,
            "all measured entries are zero (a mode shape has a direction; omit it for a frequency-only mode)",
        ));
    }
    let norm = largest
        * shape
            .iter()
            .flatten()
            .map(|x| (x / largest).powi(2))
            .sum::<f64>()
            .sqrt();
    let sum_sq = norm * norm;
    if !(sum_sq.is_normal() && (1.0 / sum_sq).is_normal()) {
        return Err(reject(
            path,
            format!(
                "cannot be normalized: its norm {norm:e} is out of the range of f64 arithmetic (scale the entries to order 1)"
            ),
        ));
    }
    Ok(())
}

/// Rule: frequencies increase, equality within [`FREQUENCY_ORDER_TOLERANCE`] accepted
/// (close modes), but not a mode repeated: the same frequency and the same shape.
fn check_frequency_order(modes: &[MeasuredMode]) -> Result<(), Rejection> {
    for (i, pair) in modes.windows(2).enumerate() {
        let (prev, cur) = (pair[0].frequency_hz, pair[1].frequency_hz);
        if cur < prev * (1.0 - FREQUENCY_ORDER_TOLERANCE) {
            return Err(reject(
                format!("modes[{}].frequency_hz", i + 1),
                format!("frequencies must increase: {cur} after modes[{i}].frequency_hz = {prev}"),
            ));
        }
        if cur <= prev * (1.0 + FREQUENCY_ORDER_TOLERANCE) && pair[0].shape == pair[1].shape {
            return Err(reject(
                format!("modes[{}]", i + 1),
                format!("repeats modes[{i}] (the same frequency {cur} Hz and the same shape)"),
            ));
        }
    }
    Ok(())
}

/// Rule: `frequency_cov` on all modes or none; `shape_nsd` on all modes with a shape or none.
fn check_uncertainty_consistency(modes: &[MeasuredMode]) -> Result<(), Rejection> {
    let mixed = |i: usize, name: &str, first: usize, first_has: bool| {
        let (here, there) = if first_has {
            ("absent", "present")
        } else {
            ("present", "absent")
        };
        reject(
            format!("modes[{i}].{name}"),
            format!(
                "present on some modes but not others ({here} here, {there} on modes[{first}])"
            ),
        )
    };
    if let Some(first) = modes.first() {
        let has = first.frequency_cov.is_some();
        if let Some(i) = modes.iter().position(|m| m.frequency_cov.is_some() != has) {
            return Err(mixed(i, "frequency_cov", 0, has));
        }
    }
    let mut shaped = modes.iter().enumerate().filter(|(_, m)| m.shape.is_some());
    if let Some((first, m0)) = shaped.next() {
        let has = m0.has_shape_uncertainty();
        if let Some((i, m)) = shaped.find(|(_, m)| m.has_shape_uncertainty() != has) {
            // A mode's shape uncertainty is its shape_nsd or its shape_std.
            let name = if m.shape_nsd.is_none() && m.shape_std.is_some() {
                "shape_std"
            } else {
                "shape_nsd"
            };
            return Err(mixed(i, name, first, has));
        }
    }
    Ok(())
}

impl ModalSet {
    /// The set as a `boltwatch.modal_set.v1` JSON value (absent optionals omitted, unmeasured entries `null`), which parse_modal_set accepts back unchanged. time formatted RFC 3339 with `Z`, seconds precision unless sub-seconds are present.
    ///
    /// `channels` is omitted when empty. Numbers are written with the shortest
    /// The measurement's own conditions (temperature and covariates).
    pub fn conditions(&self) -> super::environment::Conditions {
        super::environment::Conditions {
            temperature_c: self.temperature_c,
            covariates: self.covariates.clone(),
        }
    }

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
