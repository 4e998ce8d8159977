//! Configuration of a structure's tracker (`[tracker]`) and the tracker's own errors.

use serde::{Deserialize, Serialize};

use super::alerts::AlertThresholds;
use super::drift::DriftNoise;
use super::normalise::NormalisationConfig;
use crate::core::modal::ModalError;
use crate::core::updating::{Pairing, UpdateError};

/// Configuration of one structure's tracker (`[tracker]` of the configuration).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TrackerConfig {
    pub alerts: AlertThresholds,
    pub drift: DriftNoise,
    /// Accepted sets whose filtered θ becomes the baseline (no loosening alerts before).
    pub baseline_sets: u32,
    /// A warm-started fit whose ε exceeds both its χ² bound and this multiple of the last
    /// ε is redone from a cold start.
    pub epsilon_jump: f64,
    /// Cross-check every this many accepted sets (0: never) ...
    pub crosscheck_every_sets: u64,
    /// ... or when this much recording time has passed since the last one, s (0: never).
    pub crosscheck_every_s: f64,
    /// Checkpoint every this many accepted sets (and on shutdown). A checkpoint costs three
    /// fsyncs (output, checkpoint file, directory; about 9 ms on this machine): at 1000 sets
    /// a replay redoes at most about a second of work after a crash and spends under 1 % of
    /// its time checkpointing (8 % at 100).
    pub checkpoint_every_sets: u64,
    /// Accept a set with the same time as the last accepted one (replays).
    pub allow_equal_time: bool,
    /// Shape weight w_ψ of weighting (9), for sets without uncertainties.
    pub shape_weight: f64,
    /// Mode matching stops when every Gauss–Newton step |Δ ln θ_i| is below this many of
    /// the estimate's standard deviations (15), and takes that step without another eigen
    /// solve ([`crate::core::updating::FinalStep::Extrapolate`]). What is left is the
    /// iteration's contraction times the step: on the lab frame at 0.5 the published θ is
    /// on average 0.004 σ and at most 0.09 σ from the converged minimum (150 healthy sets,
    /// tested), while nearly every set needs a single model evaluation.
    pub step_tolerance: f64,
    /// Mode matching also stops, from its second model evaluation on, when the distance
    /// left from the published θ to the converged minimum, estimated from the fit's own
    /// contraction (the ratio of its last two Gauss–Newton steps), is below this many
    /// standard deviations ([`crate::core::updating::ModeMatchingOptions::error_tol`]). At
    /// 0.15 it ends the fits that the step test alone would take through a second
    /// iteration for a step just above `step_tolerance`, at the accuracy that test already
    /// gives (tested: every published θ within 0.15 σ of the converged minimum).
    pub error_tolerance: f64,
    /// Mode matching keeps every θ_i within `[lo, hi]` times its nominal value, as `update`
    /// does by default (a model's own per-parameter bounds, when tighter, hold too); empty:
    /// unbounded. A connection the data resolve only in combination with others otherwise
    /// drifts along the flat valley of ε in a warm fit until the step control stalls, and
    /// every such set costs a cold, globalized restart: 12 of 600 healthy space-frame
    /// sets without bounds, none with them.
    pub bounds: Vec<f64>,
    /// The σ a fit weighs a set by: `auto` rescales each mode's shape σ to its misfit when ε
    /// under the stated σ ends above its χ² bound, as `update` does (the estimate's ε and
    /// the model-inadequacy verdict stay under the stated σ); `stated` never rescales.
    pub weights: Weights,
    /// How measured modes are paired with model modes: `misfit` (the candidate adding least
    /// to ε, continuous through a crossing or a veering) or `mac` (paper (29)).
    pub pairing: PairingRule,
    /// Judging each connection against the stiffness expected under the set's conditions
    /// (`[tracker.normalisation]`, [`super::normalise`]).
    pub normalisation: NormalisationConfig,
}

/// [`TrackerConfig::weights`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Weights {
    #[default]
    Auto,
    Stated,
}

/// [`TrackerConfig::pairing`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum PairingRule {
    #[default]
    Misfit,
    Mac,
}

impl From<PairingRule> for Pairing {
    fn from(p: PairingRule) -> Self {
        match p {
            PairingRule::Misfit => Pairing::Misfit,
            PairingRule::Mac => Pairing::Mac,
        }
    }
}

impl Default for TrackerConfig {
    fn default() -> Self {
        Self {
            alerts: AlertThresholds::default(),
            drift: DriftNoise::default(),
            baseline_sets: 20,
            epsilon_jump: 4.0,
            crosscheck_every_sets: 1000,
            crosscheck_every_s: 86_400.0,
            checkpoint_every_sets: 1000,
            allow_equal_time: false,
            shape_weight: 1.0,
            step_tolerance: 0.5,
            error_tolerance: 0.15,
            bounds: vec![1e-3, 1e3],
            weights: Weights::Auto,
            pairing: PairingRule::Misfit,
            normalisation: NormalisationConfig::default(),
        }
    }
}

impl TrackerConfig {
    /// Checks every value; the error names the key.
    pub fn validate(&self) -> Result<(), TrackerError> {
        let bad = |key: &str, reason: &str| {
            Err(TrackerError::Config {
                key: format!("tracker.{key}"),
                reason: reason.into(),
            })
        };
        if let Err((key, reason)) = self.alerts.validate() {
            return bad(&format!("alerts.{key}"), &reason);
        }
        if let Err((key, reason)) = self.normalisation.validate() {
            return bad(&format!("normalisation.{key}"), &reason);
        }
        if let Err((key, reason)) = self.drift.validate() {
            return bad(&format!("drift.{key}"), &reason);
        }
        let nonneg = |v: f64| v.is_finite() && v >= 0.0;
        if self.baseline_sets == 0 {
            return bad("baseline_sets", "must be at least 1");
        }
        if !(self.epsilon_jump.is_finite() && self.epsilon_jump > 1.0) {
            return bad("epsilon_jump", "must be a finite number > 1");
        }
        if !nonneg(self.crosscheck_every_s) {
            return bad("crosscheck_every_s", "must be a finite number ≥ 0");
        }
        if self.checkpoint_every_sets == 0 {
            return bad("checkpoint_every_sets", "must be at least 1");
        }
        if !(self.shape_weight.is_finite() && self.shape_weight > 0.0) {
            return bad("shape_weight", "must be a finite number > 0");
        }
        if !(self.step_tolerance.is_finite()
            && self.step_tolerance > 0.0
            && self.step_tolerance <= 1.0)
        {
            return bad("step_tolerance", "must be in (0, 1] (standard deviations)");
        }
        if !(self.error_tolerance.is_finite()
            && self.error_tolerance > 0.0
            && self.error_tolerance <= 1.0)
        {
            return bad("error_tolerance", "must be in (0, 1] (standard deviations)");
        }
        match self.bounds[..] {
            [] => {}
            [lo, hi] if lo > 0.0 && lo < 1.0 && hi > 1.0 && hi.is_finite() => {}
            _ => {
                return bad(
                    "bounds",
                    "must be [lo, hi] with 0 < lo < 1 < hi (factors of the nominal θ), or []",
                );
            }
        }
        Ok(())
    }

    /// [`Self::bounds`] as mode matching takes them.
    pub fn bounds_pair(&self) -> Option<(f64, f64)> {
        match self.bounds[..] {
            [lo, hi] => Some((lo, hi)),
            _ => None,
        }
    }
}

/// Failures of the tracker itself (not of an input, which is rejected instead).
#[derive(Debug, thiserror::Error)]
pub enum TrackerError {
    #[error("configuration key {key}: {reason}")]
    Config { key: String, reason: String },
    #[error("checkpoint: {0}")]
    Checkpoint(String),
    #[error(transparent)]
    Update(#[from] UpdateError),
    #[error(transparent)]
    Modal(#[from] ModalError),
}
