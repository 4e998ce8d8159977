//! Mode matching (paper §2.2, §2.6.1): minimize ε(θ) (5) over θ > 0 within bounds.
//!
//! Default step control: Levenberg–Marquardt in `u = ln θ` (θ stays positive whatever the
//! step; Marquardt's diagonal scaling; damping updated from the gain ratio as in Nielsen,
//! "Damping parameter in Marquardt's method", IMM-REP-1999-05). It needs no tuning. The
//! paper's Gauss–Newton (18)–(20) with a fixed κ is kept as [`StepControl::FixedKappa`] to
//! reproduce it. Both stop when every `|Δθ_i| / θ_i < tol` (1e-5 in the paper); for
//! Levenberg–Marquardt that test is applied to the undamped Gauss–Newton step, so heavy
//! damping cannot fake convergence. The covariance is (15), `(Sᵀ Σ_M⁻¹ S)⁻¹`, at the final θ.
//!
//! Bounds ([`LogBounds`]) hold every step: a parameter on a bound whose descent direction
//! points out of the box is held there, the others step. The undamped step is taken over
//! the free parameters, by the pseudo-inverse where the normal matrix is singular (more
//! parameters than the data resolve is normal in the field), so it is zero exactly at a
//! point where the bounded first-order (KKT) conditions hold, and a step that predicts no
//! decrease (a singular step cut at a bound) is never taken for convergence. The result
//! reports those conditions ([`FirstOrder`]).
//!
//! Pairing (29), or by least misfit ([`super::Pairing`]), is redone at every evaluation,
//! so ε(θ) is piecewise smooth; a trial is accepted only if ε decreases.

use faer::linalg::solvers::{Llt, Solve};
use faer::{Mat, Side};

use super::UpdateError;
use super::bounds::{AtBound, LogBounds};
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
        let bounds = LogBounds::new(model, opts.bounds);
        let theta0 = bounds.clamp(theta0);
        let ev = self.evaluator.evaluate(model, data, &theta0)?;
        let mut st = Iterate {
            history: vec![record(&ev)],
            ev,
            evaluations: 1,
            iterations: 0,
            mu: 1e-3,
            nu: 2.0,
            hold_bounded: false,
            last_jac: None,
            last_first_order: None,
            extrapolated: None,
        };
        self.report(0, &st.history[0].clone());
        let termination = loop {
            if st.iterations >= opts.max_iterations {
                break Termination::MaxIterations;
            }
            let jac = self.evaluator.jacobian(model, data, &st.ev)?;
            st.last_jac = Some((st.ev.theta.clone(), jac));
            let stop = match opts.step {
                StepControl::FixedKappa(kappa) => {
                    self.kappa_step(model, data, kappa, opts, &mut st)?
                }
                StepControl::LevenbergMarquardt => {
                    self.lm_step(model, data, opts, &bounds, &mut st)?
                }
            };
            if let Some(t) = stop {
                break t;
            }
        };
        self.finish(model, data, &bounds, termination, st)
    }

    /// Paper (20): one fixed-κ Gauss–Newton step; `Some` when the iteration ends.
    fn kappa_step(
        &mut self,
        model: &Model,
        data: &MeasuredData,
        kappa: f64,
        opts: &ModeMatchingOptions,
        st: &mut Iterate,
    ) -> Result<Option<Termination>, UpdateError> {
        let theta = st.ev.theta.clone();
        let jac = &st.last_jac.as_ref().expect("set by the caller").1;
        let Some(step) = gauss_newton_step(jac, &st.ev.r) else {
            return Ok(Some(Termination::Diverged("SᵀWS is singular".into())));
        };
        let new: Vec<f64> = (0..theta.len())
            .map(|i| theta[i] + kappa * step[i])
            .collect();
        if let Some(i) = new.iter().position(|v| !(v.is_finite() && *v > 0.0)) {
            return Ok(Some(Termination::Diverged(format!(
                "θ{} = {} after step {}",
                i + 1,
                new[i],
                st.iterations + 1
            ))));
        }
        let done = (0..theta.len()).all(|i| (new[i] - theta[i]).abs() / theta[i] < opts.tol);
        st.ev = self.evaluator.evaluate(model, data, &new)?;
        st.evaluations += 1;
        self.accept(st);
        Ok(done.then_some(Termination::Converged))
    }

    /// One Levenberg–Marquardt iteration in `u = ln θ` within the bounds; `Some` when the
    /// iteration ends.
    fn lm_step(
        &mut self,
        model: &Model,
        data: &MeasuredData,
        opts: &ModeMatchingOptions,
        bounds: &LogBounds,
        st: &mut Iterate,
    ) -> Result<Option<Termination>, UpdateError> {
        let theta = st.ev.theta.clone();
        let jac = &st.last_jac.as_ref().expect("set by the caller").1;
        let (a, g) = normal_equations(jac, &st.ev.r, &theta, bounds, st.hold_bounded);
        let undamped = free_gauss_newton(&a, &g);
        // The first-order check of this θ, for the result if the iteration ends here.
        st.last_first_order = (!st.hold_bounded).then(|| {
            let fo = FirstOrder::of(&g, undamped.as_ref());
            (theta.clone(), fo)
        });
        if let Some(fs) = &undamped
            && let Some(t) = self.converged_step(model, data, opts, bounds, fs, &g, st)?
        {
            return Ok(Some(t));
        }
        // Whether the undamped step is negligible against the uncertainty, should no
        // damped step verify a descent (`STALL_WITHIN_STD`).
        let resolved = undamped.as_ref().is_some_and(|fs| {
            let gn = clipped(bounds, &theta, &fs.step);
            within_std(fs, &gn, STALL_WITHIN_STD, data, &st.ev)
        });
        if self.damped_step(model, data, bounds, &a, &g, st)? {
            self.accept(st);
            return Ok(None);
        }
        let bounded = (0..theta.len()).any(|i| bounds.side(i, theta[i].ln(), 1e-12).is_some());
        if bounded && !st.hold_bounded {
            // The linear model promised a decrease from moving a parameter back from its
            // bound (ε is flat there) that did not come: hold it and go on with the others.
            st.hold_bounded = true;
            st.mu = 1e-3;
            st.nu = 2.0;
            return Ok(None);
        }
        Ok(Some(if resolved {
            Termination::Converged
        } else {
            Termination::Stalled
        }))
    }

    /// The convergence tests on the undamped step over the free parameters (a first-order
    /// point of the bounded problem: the step is the projected gradient's Gauss–Newton
    /// image, so it vanishes exactly there); takes the final step as `opts.final_step`
    /// says and returns `Some(Converged)` when they hold.
    #[allow(clippy::too_many_arguments)]
    fn converged_step(
        &mut self,
        model: &Model,
        data: &MeasuredData,
        opts: &ModeMatchingOptions,
        bounds: &LogBounds,
        fs: &FreeStep,
        g: &faer::Col<f64>,
        st: &mut Iterate,
    ) -> Result<Option<Termination>, UpdateError> {
        let theta = &st.ev.theta;
        let gn = clipped(bounds, theta, &fs.step);
        let dot = -gn.iter().zip(g.iter()).map(|(d, gi)| d * gi).sum::<f64>();
        // The predicted decrease of ε; a step cut at a bound has its own. A step that
        // predicts no decrease is not a descent step and proves nothing (the shear frame's
        // singular step cut at the bounds predicted an increase, once taken for
        // convergence).
        let pred = if gn == fs.step {
            dot
        } else {
            let ad = fs.normal_times(&gn);
            2.0 * dot - gn.iter().zip(&ad).map(|(d, x)| d * x).sum::<f64>()
        };
        let done = pred >= 0.0
            && (gn.iter().all(|d| d.exp_m1().abs() < opts.tol)
                || opts
                    .sigma_tol
                    .is_some_and(|t| within_std(fs, &gn, t, data, &st.ev))
                || pred < EPS_RESOLUTION * st.ev.epsilon
                || opts.eps_tol.is_some_and(|t| pred < t));
        if !done {
            return Ok(None);
        }
        let new: Vec<f64> = (0..theta.len()).map(|i| theta[i] * gn[i].exp()).collect();
        match opts.final_step {
            FinalStep::Stop => {}
            FinalStep::Extrapolate => st.extrapolated = Some(new),
            FinalStep::Evaluate => {
                // Kept only if ε does not rise; a θ the solver cannot handle (a step along a
                // direction the data hardly see) is not taken.
                st.evaluations += 1;
                if let Ok(trial) = self.evaluator.evaluate(model, data, &new)
                    && trial.epsilon <= st.ev.epsilon * (1.0 + 1e-12)
                {
                    st.ev = trial;
                    self.accept(st);
                }
            }
        }
        Ok(Some(Termination::Converged))
    }

    /// Levenberg–Marquardt trials with growing damping until one lowers ε (Nielsen's
    /// update of μ from the gain ratio); `true` if one did (then `st.ev` is its evaluation).
    fn damped_step(
        &mut self,
        model: &Model,
        data: &MeasuredData,
        bounds: &LogBounds,
        a: &Mat<f64>,
        g: &faer::Col<f64>,
        st: &mut Iterate,
    ) -> Result<bool, UpdateError> {
        let p = g.nrows();
        let theta = st.ev.theta.clone();
        let dmax = (0..p).map(|i| a[(i, i)]).fold(0.0_f64, f64::max);
        while st.mu < 1e16 {
            let mut damped = a.clone();
            for i in 0..p {
                damped[(i, i)] += st.mu * a[(i, i)].max(1e-12 * dmax);
            }
            let Ok(llt) = damped.llt(Side::Lower) else {
                st.mu *= st.nu;
                st.nu *= 2.0;
                continue;
            };
            let mut step = -g.clone();
            llt.solve_in_place(step.as_mat_mut());
            let cap = (0..p).map(|i| step[i].abs()).fold(0.0, f64::max);
            if cap > MAX_LOG_STEP {
                step *= faer::Scale(MAX_LOG_STEP / cap);
            }
            for i in 0..p {
                step[i] = bounds.clip(i, theta[i].ln(), step[i]);
            }
            let new: Vec<f64> = (0..p).map(|i| theta[i] * step[i].exp()).collect();
            // Predicted decrease ‖r‖² − ‖r + J δ‖² = −(2δᵀg + δᵀAδ).
            let ad = a * &step;
            let pred = -(2.0 * (step.transpose() * g) + step.transpose() * &ad);
            st.evaluations += 1;
            // A trial θ the solver cannot handle is just a bad step.
            if let Ok(trial) = self.evaluator.evaluate(model, data, &new) {
                let actual = st.ev.epsilon - trial.epsilon;
                if actual > 0.0 && pred > 0.0 {
                    let rho = actual / pred;
                    st.mu *= (1.0 / 3.0_f64).max(1.0 - (2.0 * rho - 1.0).powi(3));
                    st.nu = 2.0;
                    st.ev = trial;
                    return Ok(true);
                }
            }
            st.mu *= st.nu;
            st.nu *= 2.0;
        }
        Ok(false)
    }

    /// Counts an accepted iterate and reports it.
    fn accept(&mut self, st: &mut Iterate) {
        st.iterations += 1;
        st.history.push(record(&st.ev));
        let rec = st.history.last().expect("just pushed").clone();
        self.report(st.iterations, &rec);
    }

    /// The result: covariance (15) and the first-order check at the final θ.
    fn finish(
        &mut self,
        model: &Model,
        data: &MeasuredData,
        bounds: &LogBounds,
        termination: Termination,
        st: Iterate,
    ) -> Result<ModeMatchingResult, UpdateError> {
        let ev = st.ev;
        let jac = match st.last_jac {
            Some((t, jac)) if t == ev.theta => jac,
            _ => self.evaluator.jacobian(model, data, &ev)?,
        };
        let covariance = covariance_from_jacobian(&jac, data, &ev);
        let first_order = match st.last_first_order {
            Some((t, fo)) if t == ev.theta => fo,
            _ => FirstOrder::at(&jac, &ev, bounds),
        };
        let theta = st.extrapolated.unwrap_or_else(|| ev.theta.clone());
        Ok(ModeMatchingResult {
            at_bound: bounds.at_bound(&theta),
            theta,
            covariance,
            termination,
            iterations: st.iterations,
            evaluations: st.evaluations,
            last: ev,
            history: st.history,
            first_order,
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

/// Whether every `|step_i|` is below `t` standard deviations of (15) (the undamped step's
/// `(A⁺)_ii`, scaled by `ε/(N − N_θ)` under weighting (9), as the covariance is).
fn within_std(fs: &FreeStep, step: &[f64], t: f64, data: &MeasuredData, ev: &Evaluation) -> bool {
    let p = step.len();
    let scale = match data.weighting {
        Weighting::Heuristic { .. } => ev.epsilon / data.n_data().saturating_sub(p).max(1) as f64,
        _ => 1.0,
    };
    (0..p).all(|i| step[i].abs() < t * (fs.var[i] * scale).sqrt())
}

/// The state of one iteration.
struct Iterate {
    ev: Evaluation,
    evaluations: usize,
    iterations: usize,
    history: Vec<IterationRecord>,
    /// Levenberg–Marquardt damping and its growth factor.
    mu: f64,
    nu: f64,
    /// Set once releasing a parameter from its bound (descent pointing inwards) failed to
    /// lower ε: from then on every parameter at a bound is held there.
    hold_bounded: bool,
    /// The Jacobian of the last iteration, reused for (15) if θ did not move after it.
    last_jac: Option<(Vec<f64>, Mat<f64>)>,
    /// The first-order check made at a θ by its iteration (reused by the result if θ did
    /// not move after it).
    last_first_order: Option<(Vec<f64>, FirstOrder)>,
    /// The Gauss–Newton point of [`FinalStep::Extrapolate`].
    extrapolated: Option<Vec<f64>>,
}

/// The normal matrix `A = J_uᵀJ_u` and gradient `g = J_uᵀr` (half that of ε) in
/// `u = ln θ` (`J_u = J diag(θ)`), with every held parameter decoupled: a parameter at a
/// bound that descent would push beyond (and, after a failed release, any parameter at a
/// bound) gets the identity's row and column and a zero gradient, so no step moves it.
fn normal_equations(
    jac: &Mat<f64>,
    r: &[f64],
    theta: &[f64],
    bounds: &LogBounds,
    hold_bounded: bool,
) -> (Mat<f64>, faer::Col<f64>) {
    let p = theta.len();
    let mut ju = jac.clone();
    for l in 0..p {
        for i in 0..ju.nrows() {
            ju[(i, l)] *= theta[l];
        }
    }
    let mut a = ju.transpose() * &ju;
    let mut g = ju.transpose() * faer::ColRef::from_slice(r);
    for i in 0..p {
        if held(bounds, i, theta[i].ln(), g[i], hold_bounded) {
            for j in 0..p {
                a[(i, j)] = 0.0;
                a[(j, i)] = 0.0;
            }
            a[(i, i)] = 1.0;
            g[i] = 0.0;
        }
    }
    (a, g)
}

/// Whether parameter `i` at `u = ln θ_i` is held at its bound: on it with the descent
/// direction `−g_i` pointing out (or any parameter on a bound once `hold_bounded`).
fn held(bounds: &LogBounds, i: usize, u: f64, g: f64, hold_bounded: bool) -> bool {
    match bounds.side(i, u, 1e-12) {
        Some(AtBound::Upper) => g < 0.0 || hold_bounded,
        Some(AtBound::Lower) => g > 0.0 || hold_bounded,
        None => false,
    }
}

/// Below this ratio of a Cholesky pivot to its diagonal entry (`L_ii² / A_ii`: the share
/// of column i of the Jacobian not explained by the columns before it), the normal matrix
/// is taken as singular and the step is the minimum-norm one; the pseudo-inverse drops
/// eigenvalues of the scaled matrix below it. 1e-12 on `A` is 1e-6 on the Jacobian's
/// columns. At 100 roundings instead, the Cholesky step of a nearly singular matrix
/// passed the convergence test with a step of e^1000 along a direction the data hardly
/// see (the diagnosis of two hidden effects on the lab frame met θ = NaN there).
const RANK_TOL: f64 = 1e-12;

/// The undamped Gauss–Newton step (19) `δ = −A⁺g` on the free parameters, with `A⁺` the
/// inverse of the normal matrix, or, where it is singular (more parameters than data
/// resolve, normal in the field), its pseudo-inverse in Marquardt's scaling: the smallest
/// step that reaches the linear model's minimum. Its predicted decrease `gᵀA⁺g` (the
/// Gauss–Newton decrement) is zero exactly at a first-order point.
struct FreeStep {
    step: Vec<f64>,
    /// `(A⁺)_ii`: the variance of `ln θ_i` by (15) where the data determine it.
    var: Vec<f64>,
    /// `A` itself, for the predicted decrease of a step cut at a bound.
    a: Mat<f64>,
}

impl FreeStep {
    fn normal_times(&self, x: &[f64]) -> Vec<f64> {
        let ax = &self.a * faer::ColRef::from_slice(x);
        (0..x.len()).map(|i| ax[i]).collect()
    }
}

/// [`FreeStep`] for the normal equations `A`, `g` (held parameters already decoupled):
/// Cholesky when `A` is numerically of full rank, else an eigendecomposition of
/// `D^{-1/2} A D^{-1/2}` (`D = diag A`) with eigenvalues below [`RANK_TOL`] of the largest
/// dropped. `None` if the step is not finite.
fn free_gauss_newton(a: &Mat<f64>, g: &faer::Col<f64>) -> Option<FreeStep> {
    let p = g.nrows();
    let full_rank = a.llt(Side::Lower).ok().filter(|llt| {
        let l = llt.L();
        (0..p).all(|i| l[(i, i)] * l[(i, i)] >= RANK_TOL * a[(i, i)])
    });
    let (step, var) = match full_rank {
        Some(llt) => {
            let step = step_from(&llt, g)?;
            let mut inv = Mat::<f64>::identity(p, p);
            llt.solve_in_place(inv.as_mut());
            (step, (0..p).map(|i| inv[(i, i)]).collect())
        }
        None => {
            let pinv = scaled_pseudo_inverse(a)?;
            let s = &pinv * g;
            (
                (0..p).map(|i| -s[i]).collect(),
                (0..p).map(|i| pinv[(i, i)]).collect(),
            )
        }
    };
    step.iter().all(|x| x.is_finite()).then(|| FreeStep {
        step,
        var,
        a: a.clone(),
    })
}

/// `A⁺ = D^{-1/2} (D^{-1/2} A D^{-1/2})⁺ D^{-1/2}` with `D = diag A` (a zero diagonal is
/// taken as 1), eigenvalues below [`RANK_TOL`] of the largest dropped.
fn scaled_pseudo_inverse(a: &Mat<f64>) -> Option<Mat<f64>> {
    let p = a.nrows();
    let d: Vec<f64> = (0..p)
        .map(|i| {
            if a[(i, i)] > 0.0 {
                a[(i, i)].sqrt()
            } else {
                1.0
            }
        })
        .collect();
    let scaled = Mat::from_fn(p, p, |i, j| a[(i, j)] / (d[i] * d[j]));
    let evd = scaled.self_adjoint_eigen(Side::Lower).ok()?;
    let (u, s) = (evd.U(), evd.S());
    let top = (0..p).map(|k| s[k]).fold(0.0_f64, f64::max);
    Some(Mat::from_fn(p, p, |i, j| {
        let sum: f64 = (0..p)
            .filter(|&k| s[k] > RANK_TOL * top)
            .map(|k| u[(i, k)] * u[(j, k)] / s[k])
            .sum();
        sum / (d[i] * d[j])
    }))
}

/// Each step entry cut at the bounds.
fn clipped(bounds: &LogBounds, theta: &[f64], step: &[f64]) -> Vec<f64> {
    (0..step.len())
        .map(|i| bounds.clip(i, theta[i].ln(), step[i]))
        .collect()
}

/// The first-order (KKT) conditions of the bounded problem at the final θ.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FirstOrder {
    /// The largest `|∂ε/∂ln θ_i|` over the parameters free to move that way (a parameter
    /// on a bound with descent pointing out of the box counts 0): the projected gradient.
    pub projected_gradient: f64,
    /// The Gauss–Newton decrement `gᵀA⁺g` on those parameters: the decrease of ε the
    /// linear model still promises (0 at a first-order point).
    pub decrement: f64,
}

impl FirstOrder {
    fn at(jac: &Mat<f64>, ev: &Evaluation, bounds: &LogBounds) -> Self {
        let (a, g) = normal_equations(jac, &ev.r, &ev.theta, bounds, false);
        Self::of(&g, free_gauss_newton(&a, &g).as_ref())
    }

    /// From the gradient (held parameters zeroed) and the undamped step over the free ones.
    fn of(g: &faer::Col<f64>, fs: Option<&FreeStep>) -> Self {
        let projected_gradient = (0..g.nrows()).map(|i| 2.0 * g[i].abs()).fold(0.0, f64::max);
        let decrement = fs.map_or(f64::NAN, |fs| {
            -fs.step
                .iter()
                .zip(g.iter())
                .map(|(d, gi)| d * gi)
                .sum::<f64>()
        });
        Self {
            projected_gradient,
            decrement,
        }
    }
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

#[cfg(test)]
mod tests {
    use super::*;

    /// A singular normal matrix (three parameters, rank 2: the third column of J is the sum
    /// of the first two): the step is the minimum-norm one in Marquardt's scaling, it
    /// reaches the linear model's minimum (`A δ = −g` holds, to rounding), its predicted
    /// decrease is `gᵀA⁺g`, and with `g` in the range of `A` it is 0 exactly where g is.
    #[test]
    fn a_singular_normal_matrix_gives_the_minimum_norm_step() {
        let j = Mat::from_fn(4, 3, |i, l| match l {
            0 => [1.0, 2.0, 0.0, 1.0][i],
            1 => [0.0, 1.0, 3.0, 1.0][i],
            _ => [1.0, 3.0, 3.0, 2.0][i],
        });
        let r = faer::col![0.5, -1.0, 2.0, 0.25];
        let a = j.transpose() * &j;
        let g = j.transpose() * &r;
        // Cholesky of this A "succeeds" on rounding; its last pivot is ~1e-16 of A_33.
        let fs = free_gauss_newton(&a, &g).expect("a finite step");
        let ad = fs.normal_times(&fs.step);
        for i in 0..3 {
            assert!(
                (ad[i] + g[i]).abs() < 1e-12 * g.norm_l2(),
                "A δ ≠ −g: {ad:?}"
            );
        }
        // Minimum norm in the scaled metric: no component along the null vector (1, 1, −1)
        // scaled by D^{1/2} = diag(√A_ii).
        let d: Vec<f64> = (0..3).map(|i| a[(i, i)].sqrt()).collect();
        let null = [d[0], d[1], -d[2]];
        let along: f64 = (0..3).map(|i| d[i] * fs.step[i] * null[i]).sum();
        assert!(along.abs() < 1e-12, "step has a null-space part {along}");
        // The Gauss–Newton decrement is the squared projection of r on range(J).
        let dec: f64 = -(0..3).map(|i| fs.step[i] * g[i]).sum::<f64>();
        let qr = j.qr();
        let q = qr.compute_thin_Q();
        let proj = q.transpose() * &r;
        // range(J) has dimension 2: the projection on its first two columns of Q.
        let expected = proj[0] * proj[0] + proj[1] * proj[1];
        assert!(
            (dec - expected).abs() < 1e-12 * expected,
            "{dec} vs {expected}"
        );
        // At a first-order point (g = 0) the step and decrement are 0.
        let zero = faer::Col::<f64>::zeros(3);
        let fs0 = free_gauss_newton(&a, &zero).unwrap();
        assert!(fs0.step.iter().all(|v| *v == 0.0));
    }
}
