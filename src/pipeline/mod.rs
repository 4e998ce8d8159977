//! The tracker (DESIGN §1, §7) as a sans-I/O state machine: raw modal-set payloads in,
//! [`Action`]s out (publish an estimate, an alert or a rejection; run a cross-check; write a
//! checkpoint). No clocks, files or network: the live daemon and `replay` drive the same
//! [`Tracker`], so a replay is deterministic.
//!
//! Per accepted set: a warm-started mode-matching update from the last θ (the model's
//! eigen solver, Nelson buffers and factorization pattern reused), falling back to a
//! globalized cold start from the baseline when the pairing collapses, the fit does not
//! converge or ε jumps; a [`drift::DriftFilter`] per parameter; loosening alerts per
//! connection parameter and a model-inadequacy alert on ε ([`alerts`]). A set that fails
//! validation is published as rejected and leaves the state unchanged.

pub mod accel;
pub mod advice;
pub mod alerts;
mod config;
pub mod crosscheck;
pub mod detectability;
pub mod drift;
mod fit;
pub mod normalise;
mod outputs;
mod set;
pub mod verdict;

use chrono::{DateTime, Utc};
use serde::{Deserialize, Serialize};

use crate::contract::modal_set::{
    ModalSet, Rejection, Screened, ValidationContext, modal_set_object, screen_modal_set,
};
use crate::contract::{Checkpoint, EigenBlock, Output, Rejected, Schema, digest};
use crate::core::model::{Model, ParameterKind};
use crate::core::updating::data::RawMode;
use crate::core::updating::plausibility::EigenRange;
use crate::core::updating::residual::candidate_count;
use crate::core::updating::{
    Evaluator, FinalStep, LogBounds, MeasuredData, ModeMatching, ModeMatchingOptions,
};
use alerts::{InadequacyState, LooseningState};
pub use config::{PairingRule, TrackerConfig, TrackerError, Weights};
use drift::DriftFilter;
use fit::SetFit;

/// Something the driver must do.
#[derive(Debug, Clone, PartialEq)]
pub enum Action {
    /// Publish this output on `boltwatch/<structure>/<topic>`; its log time is
    /// [`Output::time`].
    Publish(Output),
    /// Run the Bayesian cross-check on this set, off the tracking path, and publish its
    /// result ([`crosscheck`]) on `crosscheck`.
    Crosscheck(Box<CrosscheckRequest>),
    /// Persist [`Tracker::checkpoint`] (atomically); [`Tracker::restore`] resumes from it.
    Checkpoint,
    /// Run the discrepancy workflow on the set that raised the model-inadequacy warning,
    /// off the tracking path, and publish its verdict on `alerts`
    /// ([`verdict::diagnosis_alert`]).
    Diagnose(Box<DiagnoseRequest>),
}

/// What the diagnosis of a model-inadequacy warning needs.
#[derive(Debug, Clone, PartialEq)]
pub struct DiagnoseRequest {
    pub set: ModalSet,
    /// ε of the set's update and its χ² bound.
    pub epsilon: f64,
    pub epsilon_bound: f64,
}

/// What a cross-check needs: the set and the tracked estimate it is compared with.
#[derive(Debug, Clone, PartialEq)]
pub struct CrosscheckRequest {
    pub set: ModalSet,
    pub theta: Vec<f64>,
    pub std: Vec<f64>,
    pub iterations: usize,
}

/// The persistent state of a tracker (the checkpoint's contents).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrackerState {
    pub structure: String,
    /// Time of the last accepted set.
    pub last_time: Option<DateTime<Utc>>,
    /// Time origin of the drift filters (the first accepted set).
    pub origin: Option<DateTime<Utc>>,
    /// θ and its std after the last converged update.
    pub theta: Option<Vec<f64>>,
    /// Where that update last evaluated the model (its last Gauss–Newton step is taken
    /// without a further eigen solve): the next update starts there, where the eigenpairs
    /// and sensitivities are at hand.
    #[serde(default)]
    pub linearized_at: Option<Vec<f64>>,
    pub std: Option<Vec<f64>>,
    /// Covariance (15) of that θ, row by row.
    #[serde(default)]
    pub covariance: Option<Vec<Vec<f64>>>,
    /// ε of the last update.
    pub epsilon: Option<f64>,
    /// Baseline θ, once the commissioning sets are in.
    pub baseline: Option<Vec<f64>>,
    /// Mean per-set σ (15) of each parameter over the commissioning sets.
    #[serde(default)]
    pub baseline_std: Option<Vec<f64>>,
    /// Σσ of each parameter and the number of sets summed, until the baseline is in.
    #[serde(default)]
    pub commissioning_std_sum: Vec<f64>,
    #[serde(default)]
    pub commissioning_sets: u64,
    /// The most modes a commissioning set carried, and every channel one named (what the
    /// advice on connections with alerts off plans with).
    #[serde(default)]
    pub commissioning_modes: usize,
    #[serde(default)]
    pub commissioning_channels: Vec<String>,
    pub filters: Vec<DriftFilter>,
    pub loosening: Vec<LooseningState>,
    pub inadequacy: InadequacyState,
    pub accepted: u64,
    pub rejected: u64,
    /// Accepted sets whose update did not converge (estimate published, filters not fed).
    pub unconverged: u64,
    pub cold_starts: u64,
    pub last_crosscheck: Option<(u64, DateTime<Utc>)>,
    /// Payloads skipped because they had been handled already (a re-delivery).
    #[serde(default)]
    pub duplicates: u64,
    /// Content digests of the last [`DEDUP_WINDOW`] payloads handled, oldest first (in
    /// hex: JSON numbers do not hold 128 bits).
    #[serde(default, with = "digests")]
    pub seen: std::collections::VecDeque<u128>,
    /// The data groups' σ factors of the last fit that rescaled them (the next such fit
    /// starts from them); absent while the stated σ explain the data.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub scales: Option<Vec<f64>>,
    /// The normalisation's models, filters and environment readings.
    #[serde(default)]
    pub normalisation: normalise::NormalisationState,
    /// Environment readings kept (rejected ones count in `rejected`).
    #[serde(default)]
    pub environment_readings: u64,
}

/// How many handled payloads the tracker remembers to recognise a re-delivery (a sensor's
/// advanced publisher re-sends its cache to a restarted daemon): at least the cache of any
/// publisher feeding it. An older re-delivery is rejected as out of order, never re-used.
pub const DEDUP_WINDOW: usize = 1024;

/// What [`Tracker::handle`] makes of a payload before it looks at the tracker's state: its
/// content digest (the re-delivery check) and its validation by every rule that does not
/// depend on that state ([`crate::contract::modal_set::screen_modal_set`]). Pure, so a
/// driver may make it ahead on another thread ([`SetScreen::prepare`]).
pub struct Prepared<'a> {
    payload: &'a [u8],
    digest: u128,
    screened: Result<Screened, Rejection>,
}

/// What a tracker validates a set against before it looks at its state: its structure's
/// name and its model's channels. A copy, for a driver to prepare payloads on another
/// thread ([`Tracker::screen`]).
#[derive(Debug, Clone)]
pub struct SetScreen {
    structure: String,
    channels: Vec<String>,
}

impl SetScreen {
    /// The digest and the screening of `payload` ([`Prepared`]).
    pub fn prepare<'a>(&self, payload: &'a [u8]) -> Prepared<'a> {
        let structures = [self.structure.as_str()];
        let ctx = self.context(&structures);
        Prepared {
            payload,
            digest: digest(payload),
            screened: modal_set_object(payload).map(|obj| screen_modal_set(&obj, &ctx)),
        }
    }

    /// A validation context with no state in it (no last time, no clock).
    fn context<'s>(&'s self, structures: &'s [&'s str]) -> ValidationContext<'s> {
        ValidationContext {
            structures,
            model_channels: &self.channels,
            last_time: None,
            allow_equal_time: false,
            max_future: None,
        }
    }
}

/// Per parameter, why it gets no loosening alert, if so: a connection whose mean per-set σ
/// over the commissioning sets is above `max_std` of its baseline ([`alerts::AlertThresholds::max_std`]).
fn alerts_off(
    thresholds: &alerts::AlertThresholds,
    is_connection: &[bool],
    st: &TrackerState,
) -> Vec<Option<String>> {
    let (Some(b), Some(s)) = (&st.baseline, &st.baseline_std) else {
        return vec![None; is_connection.len()];
    };
    (0..is_connection.len())
        .map(|l| {
            let rel = s[l] / b[l].abs();
            (is_connection[l] && (rel.is_nan() || rel > thresholds.max_std)).then(|| {
                format!(
                    "mean per-set σ {rel:.2} of the baseline over the commissioning sets \
                     (> max_std {}): the data do not resolve this connection on its own; \
                     alerts come on with a per-set σ {:.1} times smaller, from more sensors \
                     or modes (`boltwatch plan` names which)",
                    thresholds.max_std,
                    rel / thresholds.max_std
                )
            })
        })
        .collect()
}

/// One structure's tracker.
pub struct Tracker {
    model: Model,
    cfg: TrackerConfig,
    mm: ModeMatching,
    state: TrackerState,
    opts: ModeMatchingOptions,
    /// Parameter `l` is a group of connections (eligible for loosening alerts).
    is_connection: Vec<bool>,
    /// Nominal rotational stiffness of parameter `l` (N·m/rad), when its connections share one.
    k_nominal: Vec<Option<f64>>,
    /// The structure's name and the model's channel names, in model order (validation).
    screen: SetScreen,
    /// How far ahead of its reception a set may be stamped (live only).
    max_future: Option<chrono::TimeDelta>,
    /// The model's eigenvalue range over the bounds, for the lowest `.0` modes, computed at
    /// the first set that needs it (`None` inside: no range claimed).
    eigen_range: Option<(usize, Option<EigenRange>)>,
}

impl Tracker {
    /// A fresh tracker for `model`.
    pub fn new(model: Model, cfg: TrackerConfig) -> Result<Self, TrackerError> {
        cfg.validate()?;
        let nominal = model.nominal_theta();
        let state = TrackerState {
            structure: model.name.clone(),
            last_time: None,
            origin: None,
            theta: None,
            linearized_at: None,
            std: None,
            covariance: None,
            epsilon: None,
            baseline: None,
            baseline_std: None,
            commissioning_std_sum: Vec::new(),
            commissioning_sets: 0,
            commissioning_modes: 0,
            commissioning_channels: Vec::new(),
            filters: nominal
                .iter()
                .map(|&v| DriftFilter::new(v, cfg.drift))
                .collect(),
            loosening: vec![LooseningState::default(); nominal.len()],
            inadequacy: InadequacyState::default(),
            accepted: 0,
            rejected: 0,
            unconverged: 0,
            cold_starts: 0,
            last_crosscheck: None,
            duplicates: 0,
            seen: Default::default(),
            scales: None,
            normalisation: Default::default(),
            environment_readings: 0,
        };
        Self::with_state(model, cfg, state)
    }

    /// A tracker resumed from a checkpoint ([`Tracker::checkpoint`]).
    pub fn restore(
        model: Model,
        cfg: TrackerConfig,
        checkpoint: Checkpoint<TrackerState>,
    ) -> Result<Self, TrackerError> {
        cfg.validate()?;
        let Checkpoint {
            state, eigen_block, ..
        } = checkpoint;
        if state.structure != model.name {
            return Err(TrackerError::Checkpoint(format!(
                "written for structure {}, not {}",
                state.structure, model.name
            )));
        }
        let p = model.n_params();
        if state.filters.len() != p || state.loosening.len() != p {
            return Err(TrackerError::Checkpoint(format!(
                "has {} parameters, the model {p}",
                state.filters.len()
            )));
        }
        let block = eigen_block
            .map(|b| b.into_warm_block(model.n_dof(), p))
            .transpose()
            .map_err(|why| TrackerError::Checkpoint(format!("eigen_block: {why}")))?;
        let mut tracker = Self::with_state(model, cfg, state)?;
        if let Some(b) = block {
            tracker.mm.evaluator.restore_warm_state(b);
        }
        Ok(tracker)
    }

    fn with_state(
        model: Model,
        cfg: TrackerConfig,
        state: TrackerState,
    ) -> Result<Self, TrackerError> {
        let is_connection = model
            .parameters()
            .iter()
            .map(|p| matches!(p.kind, ParameterKind::Connections(_)))
            .collect();
        let k_nominal = (0..model.n_params())
            .map(|l| model.connection_stiffness(l))
            .collect();
        let screen = SetScreen {
            structure: model.name.clone(),
            channels: model.channels().iter().map(|c| c.name.clone()).collect(),
        };
        let mut evaluator = Evaluator::new(&model)?;
        evaluator.set_warm_start(true);
        evaluator.set_pairing(cfg.pairing.into());
        let mm = ModeMatching::new(evaluator);
        let opts = ModeMatchingOptions {
            sigma_tol: Some(cfg.step_tolerance),
            eps_tol: None,
            error_tol: Some(cfg.error_tolerance),
            final_step: FinalStep::Extrapolate,
            bounds: cfg.bounds_pair(),
            ..Default::default()
        };
        Ok(Self {
            model,
            cfg,
            mm,
            state,
            opts,
            is_connection,
            k_nominal,
            screen,
            max_future: None,
            eigen_range: None,
        })
    }

    /// Why a set's frequencies cannot come from the model within its bounds, before any
    /// fit ([`EigenRange`]: two eigen solves once, then a comparison per set).
    fn implausible(&mut self, data: &MeasuredData) -> Option<String> {
        let n =
            candidate_count(data.modes.len(), self.model.n_dof()).min(self.model.n_finite_modes());
        if self.eigen_range.as_ref().is_none_or(|(have, _)| *have < n) {
            let bounds = LogBounds::new(&self.model, self.opts.bounds);
            // A failed solve claims no range: the fit then reports what went wrong.
            let range = EigenRange::new(&self.model, &bounds, n).ok().flatten();
            self.eigen_range = Some((n, range));
        }
        let (_, range) = self.eigen_range.as_ref()?;
        range.as_ref()?.implausible(data, n)
    }

    /// Rejects sets stamped more than `limit` after their reception (the live daemon's
    /// `daemon.max_future_s`; a replay has no clock to compare with).
    pub fn set_max_future(&mut self, limit: Option<chrono::TimeDelta>) {
        self.max_future = limit;
    }

    pub fn max_future(&self) -> Option<chrono::TimeDelta> {
        self.max_future
    }

    pub fn model(&self) -> &Model {
        &self.model
    }

    pub fn config(&self) -> &TrackerConfig {
        &self.cfg
    }

    pub fn state(&self) -> &TrackerState {
        &self.state
    }

    /// The connections whose alerts are off after commissioning, each with why and what
    /// would turn them on (empty before the baseline is set).
    pub fn alerts_off(&self) -> Vec<(String, String)> {
        alerts_off(&self.cfg.alerts, &self.is_connection, &self.state)
            .into_iter()
            .enumerate()
            .filter_map(|(l, why)| Some((self.model.parameters()[l].name.clone(), why?)))
            .collect()
    }

    /// The checkpoint of the current state, with the eigen solver's warm-start block: a
    /// resume continues bit for bit.
    pub fn checkpoint(&self) -> Checkpoint<TrackerState> {
        Checkpoint {
            schema: Schema::new(),
            state: self.state.clone(),
            eigen_block: self.mm.evaluator.warm_state().map(|b| EigenBlock::from(&b)),
            wal: None,
            fleet: None,
        }
    }

    /// Whether a payload of this content digest was handled within the last
    /// [`DEDUP_WINDOW`]: [`Tracker::handle`] would skip it as a re-delivery.
    pub fn has_seen(&self, digest: u128) -> bool {
        self.state.seen.contains(&digest)
    }

    /// Handles one raw payload received at `received` (the driver's clock or the
    /// recording's log time; used in rejections, and live as the clock `time` may not be
    /// far ahead of). A payload handled before (the same bytes, within the last
    /// [`DEDUP_WINDOW`]) is skipped and counted in [`TrackerState::duplicates`]: no output.
    pub fn handle(&mut self, received: DateTime<Utc>, payload: &[u8]) -> Vec<Action> {
        self.handle_prepared(received, self.screen.prepare(payload))
    }

    /// What this tracker validates a set against before it looks at its state, for a
    /// driver that prepares payloads ahead ([`Tracker::handle_prepared`]).
    pub fn screen(&self) -> &SetScreen {
        &self.screen
    }

    /// [`Tracker::handle`] of a payload prepared beforehand by this tracker's
    /// [`Tracker::screen`] (a replay prepares them on another thread, ahead of the
    /// tracking): the same outputs.
    pub fn handle_prepared(&mut self, received: DateTime<Utc>, p: Prepared<'_>) -> Vec<Action> {
        let Prepared {
            payload,
            digest,
            screened,
        } = p;
        if self.state.seen.contains(&digest) {
            self.state.duplicates += 1;
            return Vec::new();
        }
        if self.state.seen.len() >= DEDUP_WINDOW {
            self.state.seen.pop_front();
        }
        self.state.seen.push_back(digest);
        let structures = [self.screen.structure.as_str()];
        let ctx = ValidationContext {
            last_time: self.state.last_time,
            allow_equal_time: self.cfg.allow_equal_time,
            max_future: self.max_future.map(|ahead| (received, ahead)),
            ..self.screen.context(&structures)
        };
        match screened.and_then(|s| s.finish(&ctx)) {
            Ok(set) => self.handle_set(set, received, payload),
            Err(rej) => vec![Action::Publish(self.refuse(
                received,
                &rej,
                payload,
                payload.len(),
                digest,
            ))],
        }
    }

    /// Judges by the normalisation models of a law file from now on
    /// ([`normalise::NormalisationState::adopt`]); whether anything changed.
    pub fn adopt_normalisation(&mut self, law: &normalise::NormalisationState) -> bool {
        self.state.normalisation.adopt(law)
    }

    /// Handles one environment reading (`boltwatch.environment.v1`) received at
    /// `received`: kept for joining to the sets near it in time ([`normalise`]), or
    /// rejected (published, counted) with the field and the reason. No output when kept.
    pub fn handle_environment(&mut self, received: DateTime<Utc>, payload: &[u8]) -> Vec<Action> {
        let structures = [self.model.name.as_str()];
        match crate::contract::environment::parse_environment(payload, &structures) {
            Ok(r) => {
                self.state.environment_readings += 1;
                self.state.normalisation.add_reading(r.time, r.conditions);
                Vec::new()
            }
            Err(rej) => {
                let rej = Rejection {
                    field: rej.field,
                    reason: format!("environment reading: {}", rej.reason),
                };
                self.reject(received, &rej, payload)
            }
        }
    }

    /// Rejects `payload` for `rej`: counted, published, the state otherwise unchanged.
    pub fn reject(
        &mut self,
        received: DateTime<Utc>,
        rej: &Rejection,
        payload: &[u8],
    ) -> Vec<Action> {
        self.state.rejected += 1;
        vec![Action::Publish(Output::Rejected(Box::new(
            Rejected::payload(&self.model.name, received, &rej.field, &rej.reason, payload),
        )))]
    }

    /// Rejects a payload the driver did not keep whole (an oversized one): `size` bytes
    /// with content digest `digest`, of which `head` was kept.
    pub fn refuse(
        &mut self,
        received: DateTime<Utc>,
        rej: &Rejection,
        head: &[u8],
        size: usize,
        digest: u128,
    ) -> Output {
        self.state.rejected += 1;
        Output::Rejected(Box::new(Rejected::cut(
            &self.model.name,
            received,
            &rej.field,
            &rej.reason,
            head,
            size,
            digest,
        )))
    }
}

/// The updating data of a validated set: channels mapped onto the model, `null` entries
/// dropped, Σ_M from the set's uncertainties by (28), else weighting (9) with `w_psi`.
pub fn measured_data(set: &ModalSet, model: &Model, w_psi: f64) -> MeasuredData {
    let idx: Vec<usize> = set
        .channels
        .iter()
        .map(|c| model.channel_index(c).expect("validated: channel exists"))
        .collect();
    let raw: Vec<RawMode> = set
        .modes
        .iter()
        .map(|m| RawMode {
            frequency_hz: m.frequency_hz,
            frequency_cov: m.frequency_cov,
            shape: m.shape.as_ref().map(|s| {
                s.iter()
                    .zip(&idx)
                    .filter_map(|(v, &c)| v.map(|v| (c, v)))
                    .collect()
            }),
            shape_nsd: m.shape_nsd,
            shape_std: m
                .shape
                .as_ref()
                .zip(m.shape_std.as_ref())
                .map(|(s, std)| s.iter().zip(std).filter_map(|(v, sd)| v.and(*sd)).collect()),
        })
        .collect();
    MeasuredData::new(&raw, w_psi)
}

/// Serde for [`TrackerState::seen`]: each digest as 32 hex digits.
mod digests {
    use std::collections::VecDeque;

    use serde::de::Error;
    use serde::{Deserialize, Deserializer, Serializer};

    pub fn serialize<S: Serializer>(v: &VecDeque<u128>, s: S) -> Result<S::Ok, S::Error> {
        s.collect_seq(v.iter().map(|d| format!("{d:032x}")))
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<VecDeque<u128>, D::Error> {
        Vec::<String>::deserialize(d)?
            .iter()
            .map(|h| {
                u128::from_str_radix(h, 16)
                    .map_err(|e| D::Error::custom(format!("digest `{h}`: {e}")))
            })
            .collect()
    }
}
