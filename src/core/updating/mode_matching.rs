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

mod gauss_newton;
pub(crate) use gauss_newton::covariance_from_jacobian;
mod types;

use faer::Mat;

use super::UpdateError;
use super::bounds::LogBounds;
use super::data::MeasuredData;
use super::residual::{Evaluation, Evaluator};
use crate::core::model::Model;
pub use gauss_newton::FirstOrder;
use gauss_newton::{
    FreeStep, cholesky_step, clipped, free_gauss_newton, gauss_newton_step, normal_equations,
    step_in_std, step_within_bounds, within_std,
};
pub use types::{
    BoundStep, FinalStep, IterationRecord, ModeMatchingOptions, ModeMatchingResult, ProgressFn,
    StepControl, Termination,
};

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
        check_options(opts)?;
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
            last_step_in_std: None,
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
        let previous = st.last_step_in_std.take();
        if let Some(fs) = &undamped
            && let Some(t) = self.converged_step(model, data, opts, bounds, fs, previous, &g, st)?
        {
            return Ok(Some(t));
        }
        // Whether the undamped step is negligible against the uncertainty, should no
        // damped step verify a descent (`STALL_WITHIN_STD`).
        let resolved = undamped.as_ref().is_some_and(|fs| {
            let gn = clipped(bounds, &theta, &fs.step);
            within_std(fs, &gn, STALL_WITHIN_STD, data, &st.ev)
        });
        if self.damped_step(model, data, (bounds, opts.bound_step), &a, &g, st)? {
            // The contraction of the next iterate is measured against this step only if
            // the step taken was (within 10 %) the undamped one.
            let undamped_taken = undamped.as_ref().is_some_and(|fs| {
                let gn = clipped(bounds, &theta, &fs.step);
                let size = gn.iter().fold(0.0_f64, |m, d| m.max(d.abs()));
                (0..theta.len())
                    .all(|i| ((st.ev.theta[i] / theta[i]).ln() - gn[i]).abs() <= 0.1 * size)
            });
            if !undamped_taken {
                st.last_step_in_std = None;
            }
            self.accept(st);
            return Ok(None);
        }
        st.last_step_in_std = None;
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
        previous: Option<f64>,
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
        let size = step_in_std(fs, &gn, data, &st.ev);
        let done = pred >= 0.0
            && (gn.iter().all(|d| d.exp_m1().abs() < opts.tol)
                || opts
                    .sigma_tol
                    .is_some_and(|t| within_std(fs, &gn, t, data, &st.ev))
                || opts
                    .error_tol
                    .is_some_and(|t| error_left(previous, size) < t)
                || pred < EPS_RESOLUTION * st.ev.epsilon
                || opts.eps_tol.is_some_and(|t| pred < t));
        if !done {
            st.last_step_in_std = Some(size);
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
        (bounds, rule): (&LogBounds, BoundStep),
        a: &Mat<f64>,
        g: &faer::Col<f64>,
        st: &mut Iterate,
    ) -> Result<bool, UpdateError> {
        let p = g.nrows();
        let theta = st.ev.theta.clone();
        let u: Vec<f64> = theta.iter().map(|t| t.ln()).collect();
        let dmax = (0..p).map(|i| a[(i, i)]).fold(0.0_f64, f64::max);
        while st.mu < 1e16 {
            let mut damped = a.clone();
            for i in 0..p {
                damped[(i, i)] += st.mu * a[(i, i)].max(1e-12 * dmax);
            }
            let solved = match rule {
                BoundStep::Cut => cholesky_step(&damped, g),
                BoundStep::Hold => step_within_bounds(&damped, g, bounds, &u),
            };
            let Some(mut step) = solved else {
                st.mu *= st.nu;
                st.nu *= 2.0;
                continue;
            };
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
    /// The size of the last iteration's undamped step (largest `|Δ ln θ_i| / σ_i`), when
    /// the step taken was that step: the denominator of the contraction of
    /// [`ModeMatchingOptions::error_tol`].
    last_step_in_std: Option<f64>,
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

/// Checks the options, in this order: κ of [`StepControl::FixedKappa`], `tol`, `sigma_tol`
/// and `eps_tol` (finite and > 0), and `bounds` (finite, `0 < lo < 1 < hi`).
fn check_options(opts: &ModeMatchingOptions) -> Result<(), UpdateError> {
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
    for (name, v) in [
        ("sigma_tol", opts.sigma_tol),
        ("eps_tol", opts.eps_tol),
        ("error_tol", opts.error_tol),
    ] {
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
    Ok(())
}

/// The distance left from the extrapolated θ to the minimum, in standard deviations, of
/// [`ModeMatchingOptions::error_tol`]: `Θ / (1 − Θ) · r` with the contraction
/// `Θ = r / r_prev` of the last two undamped steps; infinite without a previous step or
/// when the steps did not shrink.
fn error_left(previous: Option<f64>, size: f64) -> f64 {
    match previous {
        Some(r_prev) if size < r_prev => {
            let contraction = size / r_prev;
            contraction / (1.0 - contraction) * size
        }
        _ => f64::INFINITY,
    }
}
