//! Mode matching (paper §2.2, §2.6.1): minimize ε(θ) (5) over θ > 0.
//!
//! Default step control: Levenberg–Marquardt in `u = ln θ` (θ stays positive whatever the
//! step; Marquardt's diagonal scaling; damping updated from the gain ratio as in Nielsen,
//! "Damping parameter in Marquardt's method", IMM-REP-1999-05). It needs no tuning. The
//! paper's Gauss–Newton (18)–(20) with a fixed κ is kept as [`StepControl::FixedKappa`] to
//! reproduce it. Both stop when every `|Δθ_i| / θ_i < tol` (1e-5 in the paper); for
//! Levenberg–Marquardt that test is applied to the undamped Gauss–Newton step, so heavy
//! damping cannot fake convergence. The covariance is (15), `(Sᵀ Σ_M⁻¹ S)⁻¹`, at the final θ.
//!
//! Pairing (29) is redone at every evaluation, so ε(θ) is piecewise smooth; a trial is
//! accepted only if ε decreases.

use faer::linalg::solvers::{Llt, Solve};
use faer::{Mat, Side};

use super::UpdateError;
use super::data::{MeasuredData, Weighting};
use super::residual::{Evaluation, Evaluator};
use crate::core::model::Model;

/// Largest change of ln θ_i in one Levenberg–Marquardt step (a factor e² ≈ 7.4): a safety cap
/// on top of the damping, so one wild linearization cannot send θ to 1e±30.
const MAX_LOG_STEP: f64 = 2.0;

/// Levenberg–Marquardt also stops when the undamped step's predicted decrease of ε, `−δᵀg`,
/// is below this fraction of ε: below what an evaluation of ε resolves (eigenpairs to a
/// relative residual of ~1e-10 leave ε uncertain in about its 11th digit), so no step can
/// be verified to descend and the damping would only climb to a stall. Such a step is far
/// inside the estimate's uncertainty (a step of one standard deviation lowers ε by about
/// 1). On the four-bay solid frame (seed 7) the fit reached this after 7 iterations with a
/// predicted decrease of 3e-9 (8e-12 of ε) and steps of 1.4e-5, just above `tol`.
const EPS_RESOLUTION: f64 = 1e-10;

/// When no damped step lowers ε (the evaluations no longer resolve a descent) but the
/// undamped step is below this fraction of every parameter's standard deviation, the fit
/// is converged, not stalled: the minimum is known far inside its uncertainty. Measured on
/// the scipy-built 200-DOF beam of `import::a_scipy_built_model_is_updated_with_calibrated_sigma`
/// (a stiffness that cancels to ~1e-9 of its entries in the first mode, so ε carries
/// rounding in its 7th digit), set 79: ε = 165.9039 after 4 iterations, every damped step
/// rejected.
const STALL_WITHIN_STD: f64 = 0.01;

/// How each step is chosen.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum StepControl {
    /// Levenberg–Marquardt in ln θ (default).
    LevenbergMarquardt,
    /// Paper (20): θ_{k+1} = θ_k + κ Δθ_k with the Gauss–Newton step (19).
    FixedKappa(f64),
}

/// Options of [`ModeMatching`].
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
    /// Levenberg–Marquardt: keep every θ_i within `[lo, hi] ×` its nominal value. A
    /// parameter the data cannot pin down (a connection already far stiffer than what the
    /// measured modes load) otherwise runs off towards 0 or ∞ while ε barely changes, and
    /// the fit stalls there; bounded, it stops at the bound and the others converge
    /// ([`ModeMatchingResult::at_bound`] names it). `None`: unbounded (θ > 0 only). A
    /// parameter's own `lower` and `upper` ([`crate::core::model::Parameter`]) hold as
    /// well, whichever is tighter.
    pub bounds: Option<(f64, f64)>,
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
            bounds: None,
        }
    }
}

/// Which bound a parameter ended at ([`ModeMatchingOptions::bounds`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum AtBound {
    Lower,
    Upper,
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

/// The mode-matching solver for one model; reuses its evaluator across updates.
pub struct ModeMatching {
    pub evaluator: Evaluator,
    progress: Option<ProgressFn>,
}

impl ModeMatching {
    pub fn new(evaluator: Evaluator) -> Self {
        Self {
            evaluator,
            progress: None,
        }
    }

    /// Reports every accepted iterate to `f` (see [`ProgressFn`]).
    pub fn set_progress(&mut self, f: ProgressFn) {
        self.progress = Some(f);
    }

    fn report(&mut self, iteration: usize, rec: &IterationRecord) {
        if let Some(f) = &mut self.progress {
            f(iteration, rec);
        }
    }

    /// Minimizes ε from `theta0`.
    pub fn run(
        &mut self,
        model: &Model,
        data: &MeasuredData,
        theta0: &[f64],
        opts: &ModeMatchingOptions,
    ) -> Result<ModeMatchingResult, UpdateError> {
        check_theta(model, theta0)?;
        if let StepControl::FixedKappa(k) = opts.step
            && !(k.is_finite() && k > 0.0)
        {
            return Err(UpdateError::Option {
                name: "kappa",
                value: k,
                reason: "must be a finite number > 0",
            });
        }
        if !(opts.tol.is_finite() && opts.tol > 0.0) {
            return Err(UpdateError::Option {
                name: "tol",
                value: opts.tol,
                reason: "must be a finite number > 0",
            });
        }
        for (name, v) in [("sigma_tol", opts.sigma_tol), ("eps_tol", opts.eps_tol)] {
            if let Some(v) = v
                && !(v.is_finite() && v > 0.0)
            {
                return Err(UpdateError::Option {
                    name,
                    value: v,
                    reason: "must be a finite number > 0",
                });
            }
        }
        if let Some((lo, hi)) = opts.bounds
            && !(lo.is_finite() && hi.is_finite() && lo > 0.0 && lo < 1.0 && hi > 1.0)
        {
            return Err(UpdateError::Option {
                name: "bounds",
                value: if lo > 0.0 && lo < 1.0 { hi } else { lo },
                reason: "need finite factors 0 < lo < 1 < hi of the nominal θ",
            });
        }
        let p = model.n_params();
        // Bounds of u = ln θ (±∞ if unbounded).
        let (u_lo, u_hi): (Vec<f64>, Vec<f64>) = model
            .parameters()
            .iter()
            .map(|par| {
                let (lo, hi) = match opts.bounds {
                    Some((lo, hi)) => (lo * par.nominal, hi * par.nominal),
                    None => (0.0, f64::INFINITY),
                };
                (
                    par.lower.map_or(lo, |v| v.max(lo)).ln(),
                    par.upper.map_or(hi, |v| v.min(hi)).ln(),
                )
            })
            .unzip();
        let theta0: Vec<f64> = (0..p)
            .map(|i| theta0[i].clamp(u_lo[i].exp(), u_hi[i].exp()))
            .collect();
        let theta0 = theta0.as_slice();
        let mut ev = self.evaluator.evaluate(model, data, theta0)?;
        let mut evaluations = 1;
        let mut history = vec![record(&ev)];
        self.report(0, &history[0]);
        let mut iterations = 0;
        let mut mu = 1e-3;
        let mut nu = 2.0;
        // Set once releasing a parameter from its bound (descent pointing inwards) failed
        // to lower ε: from then on every parameter at a bound is held there.
        let mut hold_bounded = false;
        // The Jacobian of the last iteration, reused for (15) if θ did not move after it.
        let mut last_jac: Option<(Vec<f64>, Mat<f64>)> = None;
        // The Gauss–Newton point of FinalStep::Extrapolate.
        let mut extrapolated: Option<Vec<f64>> = None;
        let termination = loop {
            if iterations >= opts.max_iterations {
                break Termination::MaxIterations;
            }
            let theta = ev.theta.clone();
            let jac = &last_jac
                .insert((theta.clone(), self.evaluator.jacobian(model, data, &ev)?))
                .1;
            match opts.step {
                StepControl::FixedKappa(kappa) => {
                    let Some(step) = gauss_newton_step(jac, &ev.r) else {
                        break Termination::Diverged("SᵀWS is singular".into());
                    };
                    let new: Vec<f64> = (0..p).map(|i| theta[i] + kappa * step[i]).collect();
                    if let Some(i) = new.iter().position(|v| !(v.is_finite() && *v > 0.0)) {
                        break Termination::Diverged(format!(
                            "θ{} = {} after step {}",
                            i + 1,
                            new[i],
                            iterations + 1
                        ));
                    }
                    let done = (0..p).all(|i| (new[i] - theta[i]).abs() / theta[i] < opts.tol);
                    ev = self.evaluator.evaluate(model, data, &new)?;
                    evaluations += 1;
                    iterations += 1;
                    history.push(record(&ev));
                    self.report(iterations, history.last().expect("just pushed"));
                    if done {
                        break Termination::Converged;
                    }
                }
                StepControl::LevenbergMarquardt => {
                    // In u = ln θ: J_u = J diag(θ).
                    let mut ju = jac.clone();
                    for l in 0..p {
                        for i in 0..ju.nrows() {
                            ju[(i, l)] *= theta[l];
                        }
                    }
                    let mut a = ju.transpose() * &ju;
                    let mut g = ju.transpose() * faer::ColRef::from_slice(&ev.r);
                    // A parameter at a bound that descent would push beyond is held there
                    // (and, after a failed release, any parameter at a bound): its row
                    // and column of the normal matrix become the identity's and its
                    // gradient zero, so every step leaves it.
                    for i in 0..p {
                        let u = theta[i].ln();
                        let held = (u >= u_hi[i] - 1e-12 && (g[i] < 0.0 || hold_bounded))
                            || (u <= u_lo[i] + 1e-12 && (g[i] > 0.0 || hold_bounded));
                        if held {
                            for j in 0..p {
                                a[(i, j)] = 0.0;
                                a[(j, i)] = 0.0;
                            }
                            a[(i, i)] = 1.0;
                            g[i] = 0.0;
                        }
                    }
                    // Steps are cut at the bounds.
                    let clip = |i: usize, d: f64| {
                        let u = theta[i].ln();
                        (u + d).clamp(u_lo[i], u_hi[i]) - u
                    };
                    // Convergence test on the undamped step (A factored once for the step
                    // and the standard deviations).
                    let normal = a.llt(Side::Lower).ok();
                    if let Some(llt) = &normal
                        && let Some(gn) = step_from(llt, &g)
                        && let gn = (0..p).map(|i| clip(i, gn[i])).collect::<Vec<f64>>()
                        && (gn.iter().all(|d| d.exp_m1().abs() < opts.tol)
                            || opts
                                .sigma_tol
                                .is_some_and(|t| within_std(llt, &gn, t, data, &ev))
                            || {
                                let pred =
                                    -gn.iter().zip(g.iter()).map(|(d, gi)| d * gi).sum::<f64>();
                                pred < EPS_RESOLUTION * ev.epsilon
                                    || opts.eps_tol.is_some_and(|t| pred < t)
                            })
                    {
                        let new: Vec<f64> = (0..p).map(|i| theta[i] * gn[i].exp()).collect();
                        match opts.final_step {
                            FinalStep::Stop => break Termination::Converged,
                            FinalStep::Extrapolate => {
                                extrapolated = Some(new);
                                break Termination::Converged;
                            }
                            FinalStep::Evaluate => {}
                        }
                        let trial = self.evaluator.evaluate(model, data, &new)?;
                        evaluations += 1;
                        if trial.epsilon <= ev.epsilon * (1.0 + 1e-12) {
                            ev = trial;
                            iterations += 1;
                            history.push(record(&ev));
                            self.report(iterations, history.last().expect("just pushed"));
                        }
                        break Termination::Converged;
                    }
                    // Whether the undamped step is negligible against the uncertainty,
                    // should no damped step verify a descent (`STALL_WITHIN_STD`).
                    let resolved = normal.as_ref().is_some_and(|llt| {
                        step_from(llt, &g).is_some_and(|gn| {
                            let gn: Vec<f64> = (0..p).map(|i| clip(i, gn[i])).collect();
                            within_std(llt, &gn, STALL_WITHIN_STD, data, &ev)
                        })
                    });
                    let dmax = (0..p).map(|i| a[(i, i)]).fold(0.0_f64, f64::max);
                    let mut accepted = false;
                    while mu < 1e16 {
                        let mut damped = a.clone();
                        for i in 0..p {
                            damped[(i, i)] += mu * a[(i, i)].max(1e-12 * dmax);
                        }
                        let Ok(llt) = damped.llt(Side::Lower) else {
                            mu *= nu;
                            nu *= 2.0;
                            continue;
                        };
                        let mut step = -g.clone();
                        llt.solve_in_place(step.as_mat_mut());
                        let cap = (0..p).map(|i| step[i].abs()).fold(0.0, f64::max);
                        if cap > MAX_LOG_STEP {
                            step *= faer::Scale(MAX_LOG_STEP / cap);
                        }
                        for i in 0..p {
                            step[i] = clip(i, step[i]);
                        }
                        let new: Vec<f64> = (0..p).map(|i| theta[i] * step[i].exp()).collect();
                        // Predicted decrease ‖r‖² − ‖r + J δ‖² = −(2δᵀg + δᵀAδ).
                        let ad = &a * &step;
                        let pred = -(2.0 * (step.transpose() * &g) + step.transpose() * &ad);
                        let trial = match self.evaluator.evaluate(model, data, &new) {
                            Ok(t) => t,
                            // A trial θ the solver cannot handle is just a bad step.
                            Err(_) => {
                                evaluations += 1;
                                mu *= nu;
                                nu *= 2.0;
                                continue;
                            }
                        };
                        evaluations += 1;
                        let actual = ev.epsilon - trial.epsilon;
                        if actual > 0.0 && pred > 0.0 {
                            let rho = actual / pred;
                            mu *= (1.0 / 3.0_f64).max(1.0 - (2.0 * rho - 1.0).powi(3));
                            nu = 2.0;
                            ev = trial;
                            accepted = true;
                            break;
                        }
                        mu *= nu;
                        nu *= 2.0;
                    }
                    if !accepted {
                        let bounded = (0..p).any(|i| {
                            let u = theta[i].ln();
                            u >= u_hi[i] - 1e-12 || u <= u_lo[i] + 1e-12
                        });
                        if bounded && !hold_bounded {
                            // The linear model promised a decrease from moving a parameter
                            // back from its bound (ε is flat there) that did not come:
                            // hold it and go on with the others.
                            hold_bounded = true;
                            mu = 1e-3;
                            nu = 2.0;
                            continue;
                        }
                        break if resolved {
                            Termination::Converged
                        } else {
                            Termination::Stalled
                        };
                    }
                    iterations += 1;
                    history.push(record(&ev));
                    self.report(iterations, history.last().expect("just pushed"));
                }
            }
        };
        let covariance = match last_jac {
            Some((t, jac)) if t == ev.theta => covariance_from_jacobian(&jac, data, &ev),
            _ => self.covariance(model, data, &ev)?,
        };
        let theta = extrapolated.unwrap_or_else(|| ev.theta.clone());
        let at_bound = (0..p)
            .map(|i| {
                let u = theta[i].ln();
                if u >= u_hi[i] - 1e-9 {
                    Some(AtBound::Upper)
                } else if u <= u_lo[i] + 1e-9 {
                    Some(AtBound::Lower)
                } else {
                    None
                }
            })
            .collect();
        Ok(ModeMatchingResult {
            theta,
            at_bound,
            covariance,
            termination,
            iterations,
            evaluations,
            last: ev,
            history,
        })
    }

    /// Covariance (15) at an evaluation: `(JᵀJ)⁻¹` with the whitened Jacobian `J`, formed by
    /// solving against the identity with a Cholesky factorization (it is the inverse that is
    /// wanted here). Under weighting (9) it is scaled by `ε/(N − N_θ)`.
    pub fn covariance(
        &mut self,
        model: &Model,
        data: &MeasuredData,
        ev: &Evaluation,
    ) -> Result<Option<Mat<f64>>, UpdateError> {
        let jac = self.evaluator.jacobian(model, data, ev)?;
        Ok(covariance_from_jacobian(&jac, data, ev))
    }
}

fn record(ev: &Evaluation) -> IterationRecord {
    IterationRecord {
        theta: ev.theta.clone(),
        epsilon: ev.epsilon,
        pairing: ev.pairing.iter().map(|k| k + 1).collect(),
    }
}

/// The Gauss–Newton step (19), `(JᵀJ) Δ = −Jᵀ r`, by Cholesky; `None` if singular.
/// Covariance (15) from the whitened Jacobian at `ev` (see [`ModeMatching::covariance`]).
fn covariance_from_jacobian(
    jac: &Mat<f64>,
    data: &MeasuredData,
    ev: &Evaluation,
) -> Option<Mat<f64>> {
    let a = jac.transpose() * jac;
    let llt = a.llt(Side::Lower).ok()?;
    let p = a.nrows();
    let mut cov = Mat::<f64>::identity(p, p);
    llt.solve_in_place(cov.as_mut());
    if let Weighting::Heuristic { .. } = data.weighting {
        let dof = data.n_data().saturating_sub(p).max(1) as f64;
        cov *= faer::Scale(ev.epsilon / dof);
    }
    Some(cov)
}

/// Whether every `|step_i|` is below `t` standard deviations `√(A⁻¹)_ii` of (15) (scaled
/// by `ε/(N − N_θ)` under weighting (9), as the covariance is), for the Cholesky factor of
/// the normal matrix `A` of the same parameterization as the step.
fn within_std(llt: &Llt<f64>, step: &[f64], t: f64, data: &MeasuredData, ev: &Evaluation) -> bool {
    let p = step.len();
    let mut inv = Mat::<f64>::identity(p, p);
    llt.solve_in_place(inv.as_mut());
    let scale = match data.weighting {
        Weighting::Heuristic { .. } => ev.epsilon / data.n_data().saturating_sub(p).max(1) as f64,
        _ => 1.0,
    };
    (0..p).all(|i| step[i].abs() < t * (inv[(i, i)] * scale).sqrt())
}

/// Gauss–Newton step (19)–(20) with κ = 1: `−(JᵀJ)⁻¹ Jᵀ r`.
fn gauss_newton_step(jac: &Mat<f64>, r: &[f64]) -> Option<Vec<f64>> {
    let a = jac.transpose() * jac;
    let g = jac.transpose() * faer::ColRef::from_slice(r);
    step_from(&a.llt(Side::Lower).ok()?, &g)
}

/// `−A⁻¹ g` for the normal matrix `A = JᵀJ` and gradient `g = Jᵀr`, from the Cholesky
/// factor of `A` (None if the step is not finite).
fn step_from(llt: &Llt<f64>, g: &faer::Col<f64>) -> Option<Vec<f64>> {
    let mut step = -g;
    llt.solve_in_place(step.as_mat_mut());
    let v: Vec<f64> = (0..step.nrows()).map(|i| step[i]).collect();
    v.iter().all(|x| x.is_finite()).then_some(v)
}

fn check_theta(model: &Model, theta: &[f64]) -> Result<(), UpdateError> {
    if theta.len() != model.n_params() {
        return Err(UpdateError::ThetaLength {
            expected: model.n_params(),
            got: theta.len(),
        });
    }
    if let Some(i) = theta.iter().position(|v| !(v.is_finite() && *v > 0.0)) {
        return Err(UpdateError::ThetaNotPositive {
            index: i + 1,
            value: theta[i],
        });
    }
    Ok(())
}
