//! `boltwatch.update.v1` (DESIGN §2): the result of one full update from θ0. The
//! mode-matching document; the Bayesian one adds its `bayesian` block
//! (`commands::bayes`).

use serde::{Deserialize, Serialize};

use super::stiffness::{Method, ModeComparison, Termination};
use super::wire::{Message, Schema};
use crate::core::updating::variance::Rescaled;

/// A mode-matching update (module docs).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ModeMatchingDoc {
    pub schema: Schema<ModeMatchingDoc>,
    pub method: Method,
    pub structure: String,
    /// The modal set's time as it was given (RFC 3339, seconds as precise as needed).
    pub time: String,
    pub converged: bool,
    /// `Diverged` (a fixed-κ run that left θ > 0) with its reason in the command's output.
    pub termination: Termination,
    pub iterations: usize,
    pub evaluations: usize,
    /// Where the answer was found from (`theta0`, or a restart).
    pub start: String,
    pub chi2_bound: f64,
    pub epsilon: f64,
    pub n_data: usize,
    /// `covariance (8)` or `heuristic (9)`.
    pub weighting: String,
    pub parameters: Vec<ParameterResult>,
    pub modes: Vec<ModeResult>,
    /// Why the iteration stopped, in words (added to v1: absent from older results).
    #[serde(default)]
    pub stop_reason: String,
    /// The first-order (KKT) conditions of the bounded problem at the result.
    #[serde(default)]
    pub first_order: Option<FirstOrderDoc>,
    /// How measured modes were paired: `misfit` or `mac` (29).
    #[serde(default)]
    pub pairing: String,
    /// The global search, when one ran.
    #[serde(default)]
    pub search: Option<SearchDoc>,
    /// Set when the best fit is still above its χ² bound: what that means and what to do.
    #[serde(default)]
    pub above_bound: Option<String>,
    /// The weighting the fit used: the stated σ, or σ rescaled per data group.
    #[serde(default)]
    pub weights: Option<WeightsDoc>,
}

/// How the data were weighted in the fit (`epsilon` above is always under the stated σ).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct WeightsDoc {
    /// `stated` or `rescaled`.
    pub rule: String,
    /// Why the σ were rescaled, when they were.
    pub reason: Option<String>,
    /// ε under the rescaled σ.
    pub epsilon_rescaled: Option<f64>,
    /// What the fit minimized and minima are compared by: ε under the stated σ, or
    /// `J_w = Σ_g ε_g/s_g² + n_g ln s_g²` (minus twice the log-likelihood at the factors).
    pub objective: f64,
    pub groups: Vec<GroupDoc>,
}

impl WeightsDoc {
    /// The weighting of `fit`: rescaled (and why) when `reason` is given, else stated.
    pub fn of(fit: &Rescaled, reason: Option<String>) -> Self {
        Self {
            rule: if reason.is_some() {
                "rescaled"
            } else {
                "stated"
            }
            .into(),
            epsilon_rescaled: reason.as_ref().map(|_| fit.result.epsilon()),
            reason,
            objective: fit.objective,
            groups: (fit.groups.iter())
                .map(|g| GroupDoc {
                    name: g.name.clone(),
                    n: g.n,
                    misfit: g.misfit,
                    scale: fit.scales[g.group],
                })
                .collect(),
        }
    }
}

/// One data group: its misfit under the stated σ and the factor its σ were multiplied by.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GroupDoc {
    pub name: String,
    pub n: usize,
    pub misfit: f64,
    pub scale: f64,
}

/// The first-order conditions at the result.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FirstOrderDoc {
    /// The largest `|∂ε/∂ln θ_i|` over the parameters free to move (projected gradient).
    pub projected_gradient: f64,
    /// The decrease of ε the Gauss–Newton model still promises.
    pub decrement: Option<f64>,
}

/// A global search over the bounds: its design and the distinct minima it found.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SearchDoc {
    /// Why it ran.
    pub reason: String,
    pub starts: usize,
    pub seed: u32,
    /// Starts polished to convergence after screening.
    pub polished: usize,
    /// Index into `minima` of the one returned.
    pub chosen: usize,
    pub minima: Vec<MinimumDoc>,
}

/// One distinct minimum of a global search.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MinimumDoc {
    pub theta: Vec<f64>,
    /// ε under the stated σ.
    pub epsilon: f64,
    /// What the minima are ranked by: ε, or `J_w` with rescaled σ.
    pub objective: f64,
    pub converged: bool,
    /// (model − measured)/measured frequency per measured mode.
    pub frequency_errors: Vec<f64>,
    pub mac: Vec<Option<f64>>,
    /// How many polished starts ended here.
    pub starts: usize,
    /// Whether the run from θ0 ended here.
    pub from_theta0: bool,
}

impl Message for ModeMatchingDoc {
    const SCHEMA: &'static str = "boltwatch.update.v1";
}

/// One parameter of an update.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ParameterResult {
    pub name: String,
    pub theta: f64,
    pub std: Option<f64>,
    /// `upper` or `lower` when θ ends at a bound (the data only say it is stiffer, or
    /// softer).
    pub at_bound: Option<Bound>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Bound {
    Lower,
    Upper,
}

/// A measured mode against its paired model mode, with the relative frequency error.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ModeResult {
    #[serde(flatten)]
    pub pair: ModeComparison,
    /// (model − measured)/measured frequency.
    pub error: f64,
}

impl ModeResult {
    pub fn new(pair: ModeComparison) -> Self {
        let error = (pair.model_hz - pair.measured_hz) / pair.measured_hz;
        Self { pair, error }
    }
}

/// A Bayesian update (`method: bayesian`): the MAP of (14), its uncertainty and the
/// mode-matching θ beside it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BayesDoc {
    pub schema: Schema<ModeMatchingDoc>,
    pub method: Method,
    pub structure: String,
    pub time: String,
    pub converged: bool,
    pub termination: BayesTermination,
    pub iterations: usize,
    /// Wall-clock time of the solve.
    pub seconds: f64,
    pub solver: Solver,
    /// `theta0`, or `stage I` (the two-stage update).
    pub start: String,
    /// ε (5) at the MAP θ.
    pub epsilon: f64,
    pub n_data: usize,
    pub bayesian: BayesBlock,
    pub stage1: Option<StageOneDoc>,
    pub parameters: Vec<BayesParameter>,
    pub modes: Vec<BayesModeDoc>,
}

/// How a MAP solve ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum BayesTermination {
    Converged,
    /// No step lowers J_p and the Hessian is not positive definite there: the minimum lies
    /// outside θ > 0, λ > 0, or at a saddle.
    Boundary,
    MaxIterations,
}

/// The minimizer of (14).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Solver {
    Newton,
    Alternating,
}

/// The terms of (14) at the MAP, σ_c and how it was chosen, the continuation and the TSVD.
#[allow(non_snake_case)]
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BayesBlock {
    pub sigma_c: f64,
    pub sigma_c_auto: Option<AutoSigmaDoc>,
    pub prior_std: Vec<f64>,
    pub J_p: f64,
    pub measurement_misfit: f64,
    pub modelling_error: f64,
    pub prior_term: f64,
    pub misfit_dof: f64,
    pub continuation: Vec<StageDoc>,
    pub tsvd: Option<TsvdDoc>,
}

/// The automatic σ_c (discrepancy rule).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AutoSigmaDoc {
    pub rule: String,
    pub nu: f64,
    pub misfit: f64,
    pub met: bool,
    pub trials: Vec<SigmaMisfit>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SigmaMisfit {
    pub sigma_c: f64,
    pub misfit: f64,
}

/// One Newton solve of a σ_c continuation.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StageDoc {
    pub sigma_c: f64,
    pub iterations: usize,
    pub converged: bool,
}

/// The TSVD covariance (24)–(25) and its L-curve.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TsvdDoc {
    pub s_tol: f64,
    pub kept: usize,
    pub of: usize,
    pub condition: f64,
    pub corner_rule: String,
    pub l_curve: Vec<LCurveDoc>,
}

#[allow(non_snake_case)]
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LCurveDoc {
    pub s_tol: f64,
    pub E: f64,
    pub norm: f64,
    pub negative_variance: bool,
}

/// Stage I of the two-stage update.
#[allow(non_snake_case)]
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StageOneDoc {
    pub model: String,
    pub modes: usize,
    pub sigma_c: f64,
    pub sigma_c_auto: Option<AutoSigmaDoc>,
    pub iterations: usize,
    pub J_p: f64,
    pub parameters: Vec<NamedTheta>,
    pub mapping: Vec<Mapping>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct NamedTheta {
    pub name: String,
    pub theta: f64,
}

/// A fine parameter's start and the coarse parameter it came from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Mapping {
    pub name: String,
    pub theta0: f64,
    pub from: Option<String>,
}

/// One parameter of a Bayesian update.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BayesParameter {
    pub name: String,
    pub theta: f64,
    /// Posterior standard deviation (threshold-free).
    pub std: Option<f64>,
    pub sampling_std: Option<f64>,
    pub tsvd_std: Option<f64>,
    pub mode_matching_theta: Option<f64>,
    /// `upper` or `lower` when the MAP θ is on a bound (added to v1).
    #[serde(default)]
    pub at_bound: Option<Bound>,
}

/// One measured mode against the most probable mode and the model at the MAP θ.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BayesModeDoc {
    pub measured_hz: f64,
    pub most_probable_lambda: f64,
    pub most_probable_lambda_std: Option<f64>,
    pub most_probable_hz: f64,
    pub mac_most_probable_to_measured: f64,
    pub model_hz: f64,
    pub model_mac: Option<f64>,
}
