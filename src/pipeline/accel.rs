//! From raw vibration blocks to modal sets (issue 26), sans-I/O like the tracker: one
//! [`AccelFront`] per structure takes `boltwatch.accel.v1` payloads in stream order, cuts
//! the stream into windows of `[identify] window_s` and identifies each full window
//! ([`crate::core::oma::identify`]); the modal set of a window then enters the tracker
//! exactly as a published one does. `replay` and `run` drive the same front.
//!
//! **Stream rules.** A block continues the window when it starts where the previous block
//! ended (within half a sample interval) with the same rate, channels and units. A block
//! that starts later (a gap) or changes the stream ends the window unfinished: the samples
//! gathered are dropped and reported (a window is never stitched across a gap). A block
//! that starts before the end of the previous one (a repeat or a clock step back) is
//! rejected and the window goes on. Nothing is dropped silently: every block rejected is a
//! [`FrontEvent::Refused`], every window left unfinished a [`FrontEvent::Dropped`], and
//! the driver publishes both on `rejected`.
//!
//! **Identity.** Each window's modes are labelled across windows ([`ModeTrack`]): after the
//! model's modes when the front has the model ([`AccelFront::for_model`]), and the modes
//! seen before and not found are listed in the set's `missing`.
//!
//! Memory is bounded by one window (and one block) per structure.

use chrono::{DateTime, TimeDelta, Utc};

use crate::contract::accel::{AccelBlock, parse_accel};
use crate::contract::modal_set::{
    MeasuredMode, ModalSet, Rejection, SpectrumPeak, UNCERTAINTY_FLOOR,
};
use crate::core::oma::identify::{IdentifiedMode, IdentifyOptions, identify_all};
use crate::core::oma::spectrum::Peak;
use crate::core::oma::track::{Gate, ModeTrack};
use crate::core::oma::{Quantity, Record};
use crate::io::driver::StructureModel;
use faer::Mat;
use serde::{Deserialize, Serialize};

/// `[identify]`: how raw data become modal sets.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct IdentifySettings {
    /// Window length, s: one modal set per window.
    pub window_s: f64,
    /// Largest model order of the stabilization diagram (absent: from the record).
    #[serde(default)]
    pub order_max: Option<usize>,
    /// Block rows of the Hankel matrix (absent: from the record).
    #[serde(default)]
    pub block_rows: Option<usize>,
    /// Decimation factor (absent: from the band's top; 1: none).
    #[serde(default)]
    pub decimate: Option<usize>,
    /// Blocks a window is cut into for the uncertainties.
    pub blocks: usize,
    /// Band of interest `[lo, hi]`, Hz (empty: 0 to 0.45 of the sampling rate).
    pub band_hz: Vec<f64>,
}

impl IdentifySettings {
    pub fn validate(&self) -> anyhow::Result<()> {
        let key = "configuration key identify";
        if !(self.window_s.is_finite() && self.window_s > 0.0) {
            anyhow::bail!("{key}.window_s: {} must be > 0", self.window_s);
        }
        let too_small = |v: Option<usize>| v.is_some_and(|v| v < 2);
        if too_small(self.order_max) || too_small(self.block_rows) || self.blocks < 2 {
            anyhow::bail!("{key}: order_max, block_rows and blocks must be at least 2");
        }
        if self.decimate == Some(0) {
            anyhow::bail!("{key}.decimate: must be at least 1 (1: no decimation)");
        }
        match self.band_hz[..] {
            [] => {}
            [lo, hi] if lo >= 0.0 && hi > lo && hi.is_finite() => {}
            _ => anyhow::bail!(
                "{key}.band_hz: {:?} must be [] or [lo, hi] with 0 ≤ lo < hi",
                self.band_hz
            ),
        }
        Ok(())
    }

    /// The identification options at sampling rate `rate_hz`.
    pub fn options(&self, rate_hz: f64) -> IdentifyOptions {
        let mut o = IdentifyOptions::default();
        o.requested.order_max = self.order_max;
        o.requested.block_rows = self.block_rows;
        o.requested.decimate = self.decimate;
        o.blocks = self.blocks;
        o.requested.band_hz = match self.band_hz[..] {
            [lo, hi] => Some((lo, hi)),
            _ => None,
        };
        let _ = rate_hz;
        o
    }
}

/// What [`AccelFront::handle`] gives the driver.
#[derive(Debug, Clone, PartialEq)]
pub enum FrontEvent {
    /// The modal set of a full window.
    Set(Box<ModalSet>),
    /// A block rejected, with why (the driver publishes it with the block's payload).
    Refused(Rejection),
    /// A window left unfinished, its samples dropped, with why (no payload is to blame).
    Dropped(Rejection),
}

/// The window being filled.
#[derive(Debug, Clone)]
struct Partial {
    /// Time of sample 0 of the stream segment (blocks joined without a gap).
    origin: DateTime<Utc>,
    /// Samples of the segment before the window's first.
    offset: u64,
    rate_hz: f64,
    channels: Vec<String>,
    quantities: Vec<Quantity>,
    /// Row-major samples of the window so far.
    values: Vec<f64>,
}

impl Partial {
    fn len(&self) -> usize {
        self.values.len() / self.channels.len()
    }

    /// Time of segment sample `k`.
    fn time(&self, k: u64) -> DateTime<Utc> {
        self.origin + TimeDelta::nanoseconds((k as f64 / self.rate_hz * 1e9).round() as i64)
    }

    /// Where the next block must start.
    fn expected(&self) -> DateTime<Utc> {
        self.time(self.offset + self.len() as u64)
    }
}

/// One structure's windowing and identification (module docs).
pub struct AccelFront {
    structure: String,
    model_channels: Vec<String>,
    settings: IdentifySettings,
    partial: Option<Partial>,
    /// The model the modes are paired with and named after ([`ModeTrack::from_model`]).
    model: Option<StructureModel>,
    /// Mode identities across windows (made at the first window, when the band is known).
    track: Option<ModeTrack>,
}

impl AccelFront {
    /// A front for `structure` whose blocks may carry `model_channels`; modes are labelled
    /// in the order they first appear.
    pub fn new(structure: &str, model_channels: &[String], settings: IdentifySettings) -> Self {
        Self {
            structure: structure.to_string(),
            model_channels: model_channels.to_vec(),
            settings,
            partial: None,
            model: None,
            track: None,
        }
    }

    /// A front for a watched structure: its modes are paired with the model's and named
    /// after them (`mode k`).
    pub fn for_model(model: StructureModel, settings: IdentifySettings) -> Self {
        let m = &model.1;
        let channels: Vec<String> = m.channels().iter().map(|c| c.name.clone()).collect();
        let mut f = Self::new(&m.name, &channels, settings);
        f.model = Some(model);
        f
    }

    /// Takes one payload (module docs).
    pub fn handle(&mut self, payload: &[u8]) -> Vec<FrontEvent> {
        match parse_accel(payload).and_then(|b| self.check(b)) {
            Ok(b) => self.push(b),
            Err(r) => vec![FrontEvent::Refused(r)],
        }
    }

    /// The input has ended: the samples gathered towards a window that will not be
    /// completed, reported.
    pub fn finish(&mut self) -> Option<FrontEvent> {
        self.partial
            .as_ref()
            .is_some_and(|p| p.len() > 0)
            .then(|| self.drop_partial("the input ended"))
    }

    /// The samples gathered towards the next window (reported when a run ends with them).
    pub fn pending_samples(&self) -> usize {
        self.partial.as_ref().map_or(0, Partial::len)
    }

    fn check(&self, b: AccelBlock) -> Result<AccelBlock, Rejection> {
        if b.structure != self.structure {
            return Err(Rejection {
                field: "structure".into(),
                reason: format!("`{}` is not `{}`", b.structure, self.structure),
            });
        }
        if let Some((i, c)) = b
            .channels
            .iter()
            .enumerate()
            .find(|(_, c)| !self.model_channels.contains(c))
        {
            return Err(Rejection {
                field: format!("channels[{i}]"),
                reason: format!("`{c}` is not a channel of the model of {}", self.structure),
            });
        }
        Ok(b)
    }

    fn push(&mut self, b: AccelBlock) -> Vec<FrontEvent> {
        let mut out = Vec::new();
        if let Some(p) = &self.partial {
            let half = 0.5 / p.rate_hz;
            let lag = (b.start - p.expected()).as_seconds_f64();
            let same =
                p.rate_hz == b.rate_hz && p.channels == b.channels && p.quantities == b.quantities;
            if same && lag < -half {
                return vec![FrontEvent::Refused(Rejection {
                    field: "start".into(),
                    reason: format!(
                        "the block starts {:.6} s before the end of the previous one (a repeat or a clock step back); the window goes on without it",
                        -lag
                    ),
                })];
            }
            if (!same || lag > half) && p.len() == 0 {
                // A new burst after a window that ended with its block: nothing to drop.
                self.partial = None;
            } else if !same || lag > half {
                let why = if same {
                    format!(
                        "a gap of {lag:.6} s before the block at {}",
                        crate::contract::rfc3339(b.start)
                    )
                } else {
                    "the rate, channels or units changed".to_string()
                };
                out.push(self.drop_partial(&why));
            }
        }
        let p = self.partial.get_or_insert_with(|| Partial {
            origin: b.start,
            offset: 0,
            rate_hz: b.rate_hz,
            channels: b.channels.clone(),
            quantities: b.quantities.clone(),
            values: Vec::new(),
        });
        p.values.extend_from_slice(&b.values);
        let window = (self.settings.window_s * p.rate_hz).round().max(1.0) as usize;
        while self.partial.as_ref().is_some_and(|p| p.len() >= window) {
            let p = self.partial.as_mut().expect("checked");
            let r = p.channels.len();
            let rest = p.values.split_off(window * r);
            let values = std::mem::replace(&mut p.values, rest);
            let start = p.time(p.offset);
            p.offset += window as u64;
            let record = Record {
                channels: p.channels.clone(),
                rate_hz: p.rate_hz,
                samples: Mat::from_fn(window, r, |k, c| values[k * r + c]),
                quantities: p.quantities.clone(),
            };
            drop(values);
            out.push(self.identify_window(&record, start));
        }
        out
    }

    fn drop_partial(&mut self, why: &str) -> FrontEvent {
        let p = self.partial.take().expect("a partial window");
        FrontEvent::Dropped(Rejection {
            field: "start".into(),
            reason: format!(
                "window from {} left unfinished ({why}): its {} samples ({:.3} s) are dropped",
                crate::contract::rfc3339(p.time(p.offset)),
                p.len(),
                p.len() as f64 / p.rate_hz
            ),
        })
    }

    fn identify_window(&mut self, record: &Record, start: DateTime<Utc>) -> FrontEvent {
        let mut opts = self.settings.options(record.rate_hz);
        let when = crate::contract::rfc3339(start);
        let band_hi = opts
            .requested
            .band_hz
            .map_or(0.45 * record.rate_hz, |b| b.1);
        // The model's lowest mode sets the lags, as `identify --model` does.
        let has_model = self.model.is_some();
        let lowest = self.track(band_hi).refs.first().map(|r| r.frequency_hz);
        opts.requested.model_lowest_hz = lowest.filter(|_| has_model);
        match identify_all(record, &opts) {
            Ok(found) if !found.modes.is_empty() => {
                let mut set = modal_set(
                    &self.structure,
                    start,
                    &record.channels,
                    &found.modes,
                    format!(
                        "boltwatch SSI-COV, window of {:.3} s from {when}",
                        record.duration_s()
                    ),
                );
                set.unexplained_peaks = spectrum_peaks(&found.unexplained_peaks);
                label(&mut set, self.track(band_hi));
                FrontEvent::Set(Box::new(set))
            }
            Ok(_) => FrontEvent::Refused(Rejection {
                field: String::new(),
                reason: format!("window from {when}: no mode identified"),
            }),
            Err(e) => FrontEvent::Refused(Rejection {
                field: String::new(),
                reason: format!("window from {when}: identification failed: {e}"),
            }),
        }
    }

    /// The mode identities, made at the first window (when the band is known): from the
    /// model's modes up to `band_hi` when there is a model.
    fn track(&mut self, band_hi: f64) -> &mut ModeTrack {
        let model = self.model.clone();
        self.track.get_or_insert_with(|| {
            model
                .and_then(|m| {
                    ModeTrack::from_model(&m.1, band_hi, Gate::default())
                        .map_err(|e| {
                            tracing::warn!(
                                structure = m.1.name,
                                "the model's modes cannot be computed to name the identified ones ({e}): modes are labelled as they appear"
                            )
                        })
                        .ok()
                })
                .unwrap_or_else(|| ModeTrack::new(Gate::default()))
        })
    }
}

/// The spectrum's peaks as the modal-set contract carries them.
pub fn spectrum_peaks(peaks: &[Peak]) -> Vec<SpectrumPeak> {
    peaks
        .iter()
        .map(|p| SpectrumPeak {
            frequency_hz: p.frequency_hz,
            prominence_db: p.prominence_db,
        })
        .collect()
}

/// Labels the modes of `set` ([`ModeTrack::assign`]) and lists the missing ones.
pub fn label(set: &mut ModalSet, track: &mut ModeTrack) {
    let shapes: Vec<Vec<f64>> = set
        .modes
        .iter()
        .map(|m| {
            m.shape
                .as_ref()
                .map(|s| s.iter().map(|v| v.unwrap_or(0.0)).collect())
                .unwrap_or_default()
        })
        .collect();
    let modes: Vec<(f64, &[f64])> = set
        .modes
        .iter()
        .zip(&shapes)
        .map(|(m, s)| (m.frequency_hz, s.as_slice()))
        .collect();
    let a = track.assign(&set.channels, &modes);
    for (m, l) in set.modes.iter_mut().zip(a.labels) {
        m.label = Some(l);
    }
    set.missing = a.missing;
}

/// The modal set of identified modes: shapes as identified (unit norm), `frequency_cov` =
/// σ_f/f, `shape_std` per entry and `shape_nsd` (27) = RMS of the entry stds over the RMS
/// of the shape, each uncertainty at least the contract's floor.
pub fn modal_set(
    structure: &str,
    time: DateTime<Utc>,
    channels: &[String],
    modes: &[IdentifiedMode],
    source: String,
) -> ModalSet {
    let floor = |x: f64| x.max(UNCERTAINTY_FLOOR);
    let rms = |v: &[f64]| (v.iter().map(|x| x * x).sum::<f64>() / v.len() as f64).sqrt();
    ModalSet {
        structure: structure.to_string(),
        time,
        channels: channels.to_vec(),
        modes: modes
            .iter()
            .map(|m| MeasuredMode {
                frequency_hz: m.frequency_hz,
                frequency_cov: Some(floor(m.frequency_std / m.frequency_hz)),
                shape: Some(m.shape.iter().map(|&v| Some(v)).collect()),
                shape_nsd: Some(floor(rms(&m.shape_std) / rms(&m.shape))),
                shape_std: Some(m.shape_std.iter().map(|&v| Some(v.max(0.0))).collect()),
                damping_ratio: Some(m.damping.clamp(0.0, 0.999)),
                damping_std: Some(floor(m.damping_std)),
                label: None,
            })
            .collect(),
        temperature_c: None,
        source: Some(source),
        missing: Vec::new(),
        unexplained_peaks: Vec::new(),
        covariates: Default::default(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::contract::accel::Accel;

    fn t(s: f64) -> DateTime<Utc> {
        DateTime::from_timestamp_nanos((s * 1e9) as i64 + 1_700_000_000_000_000_000)
    }

    /// Blocks of a two-channel AR(2) stream (a 5 Hz mode) at 100 Hz.
    fn blocks(n_blocks: usize, per: usize, seed: u64) -> Vec<(f64, Vec<f64>)> {
        let rec = crate::core::oma::ssi::ar2_record(
            100.0,
            &[(5.0, 0.02, [1.0, -0.5, 0.0])],
            n_blocks * per,
            seed,
            0.1,
        );
        (0..n_blocks)
            .map(|b| {
                let mut v = Vec::new();
                for k in b * per..(b + 1) * per {
                    v.extend([rec.samples[(k, 0)], rec.samples[(k, 1)]]);
                }
                ((b * per) as f64 / 100.0, v)
            })
            .collect()
    }

    fn payload(start: f64, values: &[f64]) -> Vec<u8> {
        crate::contract::to_wire(&Accel::encode(
            "s",
            t(start),
            100.0,
            &["a".into(), "b".into()],
            &["m/s^2".into(), "m/s^2".into()],
            values,
        ))
    }

    fn front() -> AccelFront {
        AccelFront::new(
            "s",
            &["a".into(), "b".into(), "c".into()],
            IdentifySettings {
                window_s: 60.0,
                order_max: Some(8),
                block_rows: Some(10),
                decimate: None,
                blocks: 10,
                band_hz: vec![],
            },
        )
    }

    /// 150 s of contiguous one-second blocks give two windows, stamped at 0 and 60 s, each
    /// with the 5 Hz mode; 30 s wait for the next window.
    #[test]
    fn contiguous_blocks_make_windows() {
        let mut f = front();
        let mut sets = Vec::new();
        for (start, v) in blocks(150, 100, 1) {
            for e in f.handle(&payload(start, &v)) {
                match e {
                    FrontEvent::Set(s) => sets.push(s),
                    FrontEvent::Refused(r) | FrontEvent::Dropped(r) => panic!("{r:?}"),
                }
            }
        }
        assert_eq!(sets.len(), 2);
        assert_eq!(sets[0].time, t(0.0));
        assert_eq!(sets[1].time, t(60.0));
        for s in &sets {
            assert!(
                s.modes
                    .iter()
                    .any(|m| (m.frequency_hz / 5.0 - 1.0).abs() < 0.01),
                "{:?}",
                s.modes
            );
        }
        assert_eq!(f.pending_samples(), 3000);
    }

    /// A gap drops the unfinished window (reported with its samples), a repeated block is
    /// rejected and the window goes on, a block of another structure or channel is
    /// rejected by field; the windows after the gap are stamped from the block after it.
    #[test]
    fn gaps_repeats_and_strangers_are_reported() {
        let mut f = front();
        let bl = blocks(200, 100, 2);
        let mut events = Vec::new();
        for (i, (start, v)) in bl.iter().enumerate() {
            if (40..50).contains(&i) {
                continue; // a 10 s gap after 40 s
            }
            events.extend(f.handle(&payload(*start, v)));
            if i == 60 {
                events.extend(f.handle(&payload(*start, v))); // the same block again
            }
        }
        let refused: Vec<&Rejection> = events
            .iter()
            .filter_map(|e| match e {
                FrontEvent::Refused(r) | FrontEvent::Dropped(r) => Some(r),
                _ => None,
            })
            .collect();
        assert_eq!(refused.len(), 2, "{refused:?}");
        assert!(refused[0].reason.contains("gap of 10.000000 s"));
        assert!(refused[0].reason.contains("4000 samples"));
        assert!(
            refused[1]
                .reason
                .contains("before the end of the previous one")
        );
        let sets: Vec<&ModalSet> = events
            .iter()
            .filter_map(|e| match e {
                FrontEvent::Set(s) => Some(&**s),
                _ => None,
            })
            .collect();
        assert_eq!(
            sets.iter().map(|s| s.time).collect::<Vec<_>>(),
            vec![t(50.0), t(110.0)]
        );
        let mut other: Accel = serde_json::from_slice(&payload(300.0, &bl[0].1)).unwrap();
        other.structure = "t".into();
        let e = f.handle(&serde_json::to_vec(&other).unwrap());
        assert!(matches!(&e[..], [FrontEvent::Refused(r)] if r.field == "structure"));
        other.structure = "s".into();
        other.channels = vec!["a".into(), "x".into()];
        let e = f.handle(&serde_json::to_vec(&other).unwrap());
        assert!(matches!(&e[..], [FrontEvent::Refused(r)] if r.field == "channels[1]"));
    }
}
