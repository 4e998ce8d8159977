//! `boltwatch.stiffness.v1` (DESIGN §3.3): the tracker's estimate for one modal set, and
//! the per-mode comparison it shares with `boltwatch.update.v1`.

use chrono::{DateTime, Utc};
use serde::{Deserialize, Serialize};

use super::update::WeightsDoc;
use super::wire::{Message, Schema, time};
use crate::core::updating::{Evaluation, Termination as FitTermination};

/// One estimate (module docs).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Estimate {
    pub schema: Schema<Estimate>,
    /// Stable id ([`super::output_id`]); absent (empty) in messages written before ids.
    #[serde(default)]
    pub id: String,
    pub structure: String,
    /// Time of the modal set.
    #[serde(with = "time")]
    pub time: DateTime<Utc>,
    pub method: Method,
    pub converged: bool,
    pub termination: Termination,
    pub iterations: usize,
    pub warm_start: bool,
    /// Why the fit started cold (`first set`, a failed warm start).
    pub cold_start_reason: Option<String>,
    /// ε (6) at the estimate, under the set's stated σ.
    pub epsilon: f64,
    /// Its χ² bound.
    pub epsilon_bound: f64,
    /// The temperature the set was judged under, °C (its own, else an environment
    /// reading's).
    pub temperature_c: Option<f64>,
    /// The other covariates it was judged under; absent when none.
    #[serde(default, skip_serializing_if = "std::collections::BTreeMap::is_empty")]
    pub covariates: std::collections::BTreeMap<String, f64>,
    /// How the parameters were normalised for the conditions; absent when normalisation
    /// is off.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub normalisation: Option<NormalisationDoc>,
    pub parameters: Vec<ParameterEstimate>,
    pub modes: Vec<ModeComparison>,
    /// Present when the fit weighed the data by σ rescaled per data group (ε under the
    /// stated σ above its χ² bound): the groups, their misfits and factors, and why.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub weights: Option<WeightsDoc>,
}

impl Message for Estimate {
    const SCHEMA: &'static str = "boltwatch.stiffness.v1";
}

/// The updating method of an estimate.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Method {
    ModeMatching,
    Bayesian,
}

/// How a fit ended. On the wire as the names `Converged`, `MaxIterations`, `Stalled`,
/// `Diverged` (the v1 names).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum Termination {
    Converged,
    MaxIterations,
    Stalled,
    /// Fixed-κ Gauss–Newton left θ > 0 (only with a fixed κ, which the tracker never uses;
    /// the reason is in the command's own output).
    Diverged,
}

impl From<&FitTermination> for Termination {
    fn from(t: &FitTermination) -> Self {
        match t {
            FitTermination::Converged => Self::Converged,
            FitTermination::MaxIterations => Self::MaxIterations,
            FitTermination::Stalled => Self::Stalled,
            FitTermination::Diverged(_) => Self::Diverged,
        }
    }
}

/// One parameter of an estimate.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ParameterEstimate {
    pub name: String,
    pub theta: f64,
    /// Standard deviation from the covariance (15); `null` if it is not finite.
    pub std: Option<f64>,
    pub lower95: Option<f64>,
    pub upper95: Option<f64>,
    /// θ at commissioning, once the baseline sets are in.
    pub baseline: Option<f64>,
    /// (θ − baseline)/baseline.
    pub change: Option<f64>,
    /// k_R·θ (N·m/rad), when the parameter's connections share one nominal k_R.
    pub stiffness: Option<f64>,
    pub filtered: FilteredLevel,
    /// Why the parameter raises no loosening alert, when it does not (a connection the
    /// data do not resolve on its own); absent otherwise.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub alerts_off: Option<String>,
    /// θ against what a healthy structure is expected to have under this set's conditions;
    /// absent when normalisation is off or has no expectation yet.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub normalised: Option<NormalisedLevel>,
}

/// Which model gave the expectations of an estimate.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum NormalisationSource {
    /// The regression on the measured covariates.
    Covariates,
    /// The variation all parameters share, without covariates.
    OutputOnly,
}

/// How an estimate was normalised for its conditions.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct NormalisationDoc {
    /// The model of the expectations; `null` when there was none (see `unavailable`).
    pub source: Option<NormalisationSource>,
    /// The models were still learning (the training period).
    pub learning: bool,
    /// Why the conditions are outside what the model learned, when they are: the band is
    /// the model's extrapolation.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub extrapolated: Option<String>,
    /// Why the covariates could not be used, when the output-only model stood in.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub note: Option<String>,
    /// Why no expectation was available for this set (its connections are judged against
    /// the baseline).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub unavailable: Option<String>,
}

/// One parameter against its expectation.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct NormalisedLevel {
    /// θ a healthy structure is expected to have under these conditions, and the 95 %
    /// band of a healthy θ there.
    pub expected: f64,
    pub expected_lower95: f64,
    pub expected_upper95: f64,
    /// This set's standardised residual against the expectation.
    pub z: f64,
    /// Filtered loss against the expectation, `1 − θ/expected`, and its 95 % band.
    pub loss: f64,
    pub loss_lower95: f64,
    pub loss_upper95: f64,
}

/// The drift filter's view of a parameter after this set.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FilteredLevel {
    pub level: f64,
    pub trend_per_day: f64,
    pub std: f64,
    pub lower95: f64,
    pub upper95: f64,
    pub change: Option<f64>,
}

/// A measured mode against the model mode paired with it (29).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ModeComparison {
    pub measured_hz: f64,
    pub model_hz: f64,
    /// MAC (26) of the pair; `null` for a frequency-only mode.
    pub mac: Option<f64>,
    /// 1-based index of the paired model mode.
    pub paired_with: usize,
}

impl ModeComparison {
    /// Measured mode `m` (at `measured_hz`) in a fit's iterate.
    pub fn of(last: &Evaluation, m: usize, measured_hz: f64) -> Self {
        Self {
            measured_hz,
            model_hz: last.model_hz(m),
            mac: super::wire::finite(last.mac[m]),
            paired_with: last.pairing[m] + 1,
        }
    }
}
