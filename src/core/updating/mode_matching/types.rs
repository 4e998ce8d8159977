//! The options of mode matching ([`super::ModeMatching`]) and the result it returns: step
//! control, stopping tests, bounds; the estimate, its covariance (15), why the iteration
//! stopped, and the history of accepted iterates.

use faer::Mat;

use super::gauss_newton::FirstOrder;
use crate::core::updating::bounds::AtBound;
use crate::core::updating::residual::Evaluation;

/// How each step is chosen.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum StepControl {
    /// Levenberg–Marquardt in ln θ (default).
    LevenbergMarquardt,
    /// Paper (20): θ_{k+1} = θ_k + κ Δθ_k with the Gauss–Newton step (19).
    FixedKappa(f64),
}

/// Options of [`super::ModeMatching`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ModeMatchingOptions {
    pub step: StepControl,
    /// Stop when every |Δθ_i|/θ_i is below this (paper: 1e-5).
    pub tol: f64,
    pub max_iterations: usize,
    /// Levenberg–Marquardt: what to do with the undamped step that passed the stopping
    /// test.
    pub final_step: FinalStep,
    /// Also stop when every undamped step `|Δ ln θ_i|` is below this many standard
    /// deviations of `ln θ_i` by (15) at the current θ: the remaining change is then
    /// negligible against the estimate's own uncertainty, whatever its relative size. For
    /// trackers, whose estimate of every set is only known to its std.
    pub sigma_tol: Option<f64>,
    /// Also stop when the undamped step's predicted decrease of ε, `−δᵀg` (the
    /// Gauss–Newton model's distance to its minimum), is below this: ε is then known to
    /// that accuracy, which is all a profile of ε needs, while θ may still creep along a
    /// flat valley for dozens of iterations.
    pub eps_tol: Option<f64>,
    /// Also stop when the distance from the extrapolated θ (the current θ plus the
    /// undamped step) to the minimum, estimated from this fit's own contraction, is below
    /// this many standard deviations of (15): with `r_k` the largest `|Δ ln θ_i| / σ_i` of
    /// the undamped step at iterate `k` and `Θ = r_k / r_{k−1}` (after a step that was the
    /// undamped one), the steps left sum to about `Θ / (1 − Θ) · r_k` (the a-posteriori
    /// error estimate of a linearly convergent iteration; Deuflhard, *Newton Methods for
    /// Nonlinear Problems*, 2004, ch. 2 and §4.2). Needs a previous step, so it applies
    /// from the second iterate on. For trackers, with [`FinalStep::Extrapolate`].
    pub error_tol: Option<f64>,
    /// Levenberg–Marquardt: keep every θ_i within `[lo, hi] ×` its nominal value. A
    /// parameter the data cannot pin down (a connection already far stiffer than what the
    /// measured modes load) otherwise runs off towards 0 or ∞ while ε barely changes, and
    /// the fit stalls there; bounded, it stops at the bound and the others converge
    /// ([`ModeMatchingResult::at_bound`] names it). `None`: unbounded (θ > 0 only). A
    /// parameter's own `lower` and `upper` ([`crate::core::model::Parameter`]) hold as
    /// well, whichever is tighter.
    pub bounds: Option<(f64, f64)>,
    /// Levenberg–Marquardt: how a damped step that would take a parameter across its bound
    /// is brought within the bounds.
    pub bound_step: BoundStep,
}

/// How a damped step that crosses a bound is brought within the bounds
/// ([`ModeMatchingOptions::bound_step`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum BoundStep {
    /// Each crossing component is cut at its bound after the step is solved and scaled to
    /// the step cap (the default: the updates' and the trackers' path).
    #[default]
    Cut,
    /// A crossing component is held on its bound and the others are solved again, until
    /// none crosses: the minimum of the damped model within the bounds. For fits whose
    /// insensitive parameters run to a bound (the diagnosis's), where cutting leaves the
    /// others at the scale of the crossing component's step. Not the default: on the lab
    /// frame's crossing-mode truths (`tests/suite/crossing.rs`) it led one of 50 updates
    /// from nominal θ to a local minimum that the cut path avoids.
    Hold,
}

impl Default for ModeMatchingOptions {
    fn default() -> Self {
        Self {
            step: StepControl::LevenbergMarquardt,
            tol: 1e-5,
            max_iterations: 200,
            final_step: FinalStep::Evaluate,
            sigma_tol: None,
            eps_tol: None,
            error_tol: None,
            bounds: None,
            bound_step: BoundStep::Cut,
        }
    }
}

/// The last (converged) Levenberg–Marquardt step.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FinalStep {
    /// Take it and evaluate there (one more eigen solve, and a Jacobian at the new θ for
    /// (15)); the step is kept only if ε does not rise. The default.
    Evaluate,
    /// Stop at the current θ, which is within the tolerance of the minimum.
    Stop,
    /// Take it without evaluating: the result's θ is the Gauss–Newton point
    /// `θ · exp(Δ ln θ)`, while its `last` evaluation, ε and covariance (15) stay at the θ
    /// the step was computed from. The error left is the iteration's contraction times the
    /// step (on the lab frame about a tenth of it). For trackers, whose steps are bounded
    /// by [`ModeMatchingOptions::sigma_tol`].
    Extrapolate,
}

/// Why the iteration stopped.
#[derive(Debug, Clone, PartialEq)]
pub enum Termination {
    Converged,
    MaxIterations,
    /// No step reduces ε (damping exhausted) before the convergence test holds.
    Stalled,
    /// Fixed-κ Gauss–Newton left θ > 0 or produced a non-finite step.
    Diverged(String),
}

/// One accepted iterate.
#[derive(Debug, Clone)]
pub struct IterationRecord {
    pub theta: Vec<f64>,
    pub epsilon: f64,
    /// Model mode (1-based) paired with each measured mode.
    pub pairing: Vec<usize>,
}

/// Outcome of a mode-matching update.
#[derive(Debug, Clone)]
pub struct ModeMatchingResult {
    /// The estimate: `last.theta`, or the Gauss–Newton point beyond it
    /// ([`FinalStep::Extrapolate`]).
    pub theta: Vec<f64>,
    /// Covariance (15) (scaled by ε/(N−N_θ) under weighting (9)); `None` if SᵀWS is singular.
    pub covariance: Option<Mat<f64>>,
    pub termination: Termination,
    /// Accepted steps (Jacobian evaluations).
    pub iterations: usize,
    /// Residual evaluations (eigen solves), including rejected trials.
    pub evaluations: usize,
    /// The final residual.
    pub last: Evaluation,
    /// θ, ε and pairing at the start and after every accepted step.
    pub history: Vec<IterationRecord>,
    /// Per parameter, the bound it ended at, if any: the data then only say that θ_i is
    /// beyond it (a bound the fit pressed against, not an estimate).
    pub at_bound: Vec<Option<AtBound>>,
    /// The first-order conditions of the bounded problem at the final evaluation.
    pub first_order: FirstOrder,
}

impl ModeMatchingResult {
    pub fn converged(&self) -> bool {
        self.termination == Termination::Converged
    }
    pub fn epsilon(&self) -> f64 {
        self.last.epsilon
    }
    /// Standard deviations: square roots of the covariance diagonal (NaN if unavailable).
    pub fn std(&self) -> Vec<f64> {
        (0..self.theta.len())
            .map(|i| {
                self.covariance
                    .as_ref()
                    .map_or(f64::NAN, |c| c[(i, i)].sqrt())
            })
            .collect()
    }
}

/// Called after every accepted iterate (and once at the start, iteration 0) with the
/// iteration count and the iterate: a progress display for long updates (the large model's
/// iterations take seconds).
pub type ProgressFn = Box<dyn FnMut(usize, &IterationRecord) + Send>;
