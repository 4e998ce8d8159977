//! The MAP by a trust-region Newton method on the reduced objective `F(λ, θ)`, with σ_c
//! continuation for small σ_c (module docs of [`super`]).

use super::*;
use crate::core::updating::AtBound;

/// Newton iterations allowed to a warm-started stage of the σ_c continuation before it
/// counts as failed (a warm stage needs 4–25 on the reference structures).
pub const CONTINUATION_STAGE_ITERATIONS: usize = 50;
/// Newton iterations allowed to a cold start (from `λ̂`, `θ0`) before the continuation
/// gives it up and climbs to a larger σ_c.
pub const COLD_START_ITERATIONS: usize = 30;
/// A cold start is given up early, after this many iterations, if the trust-region
/// multiplier `μ` (relative to the largest diagonal entry of the scaled Hessian) has not
/// once fallen below [`STALL_DAMPING`]: its steps are still gradient-like, the sign of a
/// start stuck on the wall of the narrow valley of a small σ_c.
pub const STALL_PROBE_ITERATIONS: usize = 6;
/// See [`STALL_PROBE_ITERATIONS`].
pub const STALL_DAMPING: f64 = 1e-2;
/// Stopping rule of the intermediate continuation stages (the next stage re-converges, so
/// these need only bring the start into Newton's quadratic region): every component of the
/// step below this relative, or the predicted decrease below 1e-9 of `F`.
pub const STAGE_STEP_TOL: f64 = 1e-6;
/// Cold starts the continuation tries above the target σ_c (at `10σ_c, 100σ_c, …`) before
/// it concludes that a larger σ_c does not help. On the reference structures the first
/// converging cold start is at most 1000σ_c.
pub const CONTINUATION_CLIMBS: usize = 6;
/// Factor between the σ_c of two warm-started continuation stages.
pub const CONTINUATION_RATIO: f64 = 3.162_277_660_168_379_5;

/// Stopping rule of the Newton solver: every component of the undamped step below this,
/// relative to `max(|y_i|, 1e-12·max|y|)`.
pub const NEWTON_STEP_TOL: f64 = 1e-11;
/// Stopping rule of the Newton solver: the predicted decrease of `F` relative to `F`.
pub const NEWTON_DECREMENT_TOL: f64 = 1e-14;
/// Relative resolution of an evaluation of `F`: a step predicted to lower `F` by less
/// than this that does not lower it ends the solve (at the minimum if the Hessian is
/// positive definite there). `F` is a sum of squares with cancellation inside the model
/// term: on the four-bay solid frame (σ_c = 1e3) evaluations next to its MAP scatter by up
/// to ~5e-10 relative.
pub const NEWTON_RESOLUTION: f64 = 1e-10;
/// Initial trust radius of the Newton solver (relative change of `(λ, θ)`, 2-norm).
pub const TRUST_INITIAL_RADIUS: f64 = 0.5;
/// Largest trust radius: below 1, so a step keeps every λ and θ positive.
pub const TRUST_MAX_RADIUS: f64 = 0.9;
/// Trust radius below which no step can lower `F` measurably: the solver stops.
pub const TRUST_MIN_RADIUS: f64 = 1e-15;
/// A step is accepted when it achieves this fraction of the predicted decrease.
pub const TRUST_ACCEPT: f64 = 1e-4;

/// When [`BayesProblem::newton`] stops.
#[derive(Debug, Clone, Copy)]
pub(super) struct NewtonStop {
    /// Every step component below this relative to `max(|y_i|, 1e-12·max|y|)`.
    step_tol: f64,
    /// Predicted decrease below this relative to `F`.
    decrement_tol: f64,
    /// Give up after [`STALL_PROBE_ITERATIONS`] if the relative trust-region multiplier
    /// never fell below [`STALL_DAMPING`].
    stall_probe: bool,
}

impl NewtonStop {
    /// The solver's own stopping rule: converged to machine precision.
    const FINAL: Self = Self {
        step_tol: NEWTON_STEP_TOL,
        decrement_tol: NEWTON_DECREMENT_TOL,
        stall_probe: false,
    };
    /// A trial of the automatic σ_c: the misfit to well within the rule's tolerance
    /// ([`super::AUTO_MISFIT_TOL`], 1 % of ν), not to machine precision; the next trial and
    /// the final MAP start from its `(λ, θ)` and converge fully. On the four-bay frame
    /// (seed 1) the six trials' misfits equal those of full-precision trials to the 0.1
    /// printed, and the lab frame's bottom trial's misfit moved by 6e-6.
    pub(super) const TRIAL: Self = Self {
        step_tol: STAGE_STEP_TOL,
        decrement_tol: 1e-7,
        stall_probe: false,
    };
    /// An intermediate warm stage of the continuation.
    const STAGE: Self = Self {
        step_tol: STAGE_STEP_TOL,
        decrement_tol: 1e-9,
        stall_probe: false,
    };

    /// Whether the undamped Newton step at `y` meets this rule: every component below
    /// `step_tol` relative (to `max(|y_i|, 1e-12·scale_y)`), or the predicted decrease
    /// −gᵀΔ/2 below `decrement_tol` of `F` (`value`). Never where `hessian` is not positive
    /// definite.
    fn converged_at(
        &self,
        hessian: &Mat<f64>,
        gradient: &[f64],
        y: &[f64],
        scale_y: f64,
        value: f64,
    ) -> bool {
        let ny = y.len();
        if let Ok(llt) = hessian.llt(Side::Lower) {
            let g = Col::from_fn(ny, |i| -gradient[i]);
            let step = llt.solve(g.as_mat());
            let decrement: f64 = 0.5 * (0..ny).map(|i| g[i] * step[(i, 0)]).sum::<f64>();
            if (0..ny)
                .all(|i| step[(i, 0)].abs() <= self.step_tol * y[i].abs().max(1e-12 * scale_y))
                || decrement <= self.decrement_tol * value.abs()
            {
                return true;
            }
        }
        false
    }
}

/// A σ_c continuation under way ([`BayesProblem::solve_newton_continued`]): its target
/// σ_c and budgets, the stages so far and the iterations they used.
struct Continuation {
    target: f64,
    /// The stopping rule at the target σ_c.
    last: NewtonStop,
    /// Iterations allowed to all stages together.
    max_iterations: usize,
    /// Iterations allowed to a warm-started stage.
    budget: usize,
    /// Iterations allowed to a cold start.
    cold_budget: usize,
    stages: Vec<ContinuationStage>,
    used: usize,
}

impl Continuation {
    /// Counts a stage at `sigma_c` that ended in `r`.
    fn record(&mut self, sigma_c: f64, r: &BayesResult) {
        self.used += r.iterations;
        self.stages.push(ContinuationStage {
            sigma_c,
            iterations: r.iterations,
            converged: r.converged,
        })
    }

    /// The continuation's outcome: `r` with the iterations and stages of all stages, and
    /// `prob` weighted at the target σ_c again.
    fn finish(self, prob: &mut BayesProblem, mut r: BayesResult) -> BayesResult {
        prob.inv_s2 = 1.0 / (self.target * self.target);
        r.iterations = self.used;
        r.stages = self.stages;
        r
    }
}

/// Where the Newton iteration stands: `y = (λ, θ)`, `F` there, the trust radius `Δ`, and
/// the least relative multiplier `μ` of an accepted step so far (see [`STALL_DAMPING`]).
struct Iterate {
    y: Vec<f64>,
    cur: Reduced,
    delta: f64,
    least_mu: f64,
}

/// The quadratic model of `F` at `y` in relative coordinates `y_i = d_i (1 + z_i)`.
struct ScaledModel {
    /// The scaling `d`.
    d: Vec<f64>,
    /// `D H D`.
    h: Mat<f64>,
    /// `D g`.
    g: Vec<f64>,
    /// The largest diagonal entry of `D H D` in magnitude.
    h_diag: f64,
}

impl ScaledModel {
    /// The model for the (free) `hessian` and `gradient` at `y`, where `scale_y` is the
    /// largest `|y_i|`.
    fn at(y: &[f64], hessian: &Mat<f64>, gradient: &[f64], scale_y: f64) -> Self {
        let ny = y.len();
        let d: Vec<f64> = y.iter().map(|v| v.abs().max(1e-12 * scale_y)).collect();
        let h_scaled = Mat::from_fn(ny, ny, |i, j| d[i] * hessian[(i, j)] * d[j]);
        let g_scaled: Vec<f64> = (0..ny).map(|i| d[i] * gradient[i]).collect();
        let h_diag = (0..ny).map(|i| h_scaled[(i, i)].abs()).fold(0.0, f64::max);
        Self {
            d,
            h: h_scaled,
            g: g_scaled,
            h_diag,
        }
    }
}

impl BayesProblem {
    /// Damped Newton on `F(λ, θ)` from `λ = λ̂`, `θ = theta0`: a trust-region method on
    /// the exact Hessian, in relative coordinates (see [`trust`]). A step is accepted when it
    /// achieves [`TRUST_ACCEPT`] of the decrease its quadratic model predicts; the radius
    /// doubles (up to [`TRUST_MAX_RADIUS`]) after a boundary step the model predicted well,
    /// and shrinks after a poor one. Near a minimum with a positive definite Hessian the
    /// steps are Newton's.
    pub fn solve_newton(
        &self,
        theta0: &[f64],
        max_iterations: usize,
    ) -> Result<BayesResult, BayesError> {
        self.solve_newton_from(&self.lambda_hat(), theta0, max_iterations)
    }

    /// Newton made robust for small σ_c. A small σ_c makes `F(λ, θ)` a narrow curved
    /// valley (the model equation is nearly a constraint), and a cold start from `λ̂`, `θ0`
    /// can stall far from it. So: a cold start at the target σ_c; if it does not converge
    /// within [`COLD_START_ITERATIONS`], or stalls (see [`STALL_PROBE_ITERATIONS`]), cold
    /// starts at `10σ_c, 100σ_c, …` until one converges (at most [`CONTINUATION_CLIMBS`];
    /// if none does, the first cold start carries on), then warm-started stages back down
    /// to the target, each σ_c [`CONTINUATION_RATIO`] below the last (if one fails, the
    /// first cold start carries on). Stages above the target stop at the
    /// looser [`STAGE_STEP_TOL`]; the last converges to the solver's full precision.
    /// `max_iterations` bounds the iterations of all stages together.
    pub fn solve_newton_continued(
        &mut self,
        theta0: &[f64],
        max_iterations: usize,
    ) -> Result<BayesResult, BayesError> {
        self.solve_newton_continued_to(theta0, max_iterations, NewtonStop::FINAL)
    }

    /// [`Self::solve_newton_continued`] with the stopping rule `last` at the target σ_c
    /// (the stages above it keep theirs).
    pub(super) fn solve_newton_continued_to(
        &mut self,
        theta0: &[f64],
        max_iterations: usize,
        last: NewtonStop,
    ) -> Result<BayesResult, BayesError> {
        let target = self.sigma_c();
        let mut run = Continuation {
            target,
            last,
            max_iterations,
            budget: CONTINUATION_STAGE_ITERATIONS.min(max_iterations),
            cold_budget: COLD_START_ITERATIONS.min(max_iterations),
            stages: Vec::new(),
            used: 0,
        };
        let lambda_hat = self.lambda_hat();
        let cold = NewtonStop {
            stall_probe: true,
            ..last
        };
        let direct = self.newton(&lambda_hat, theta0, run.cold_budget, cold)?;
        run.record(target, &direct);
        if direct.converged || run.cold_budget == max_iterations {
            // Converged, or the caller allowed no more than one stage.
            return Ok(run.finish(self, direct));
        }
        let Some((sigma, good)) = self.climb(&mut run, &lambda_hat, theta0)? else {
            return self.carry_on(run, &direct, None);
        };
        self.descend(run, &direct, sigma, good)
    }

    /// Climbs until a cold start converges: cold starts from `(λ̂, θ0)` at `10σ_c, 100σ_c, …`
    /// (at most [`CONTINUATION_CLIMBS`], within the budget), each a stage to the looser
    /// rule but stall-probed. The σ_c and result of the first that converges.
    fn climb(
        &mut self,
        run: &mut Continuation,
        lambda_hat: &[f64],
        theta0: &[f64],
    ) -> Result<Option<(f64, BayesResult)>, BayesError> {
        let mut sigma = run.target;
        for _ in 0..CONTINUATION_CLIMBS {
            sigma *= 10.0;
            if run.used >= run.max_iterations {
                break;
            }
            self.inv_s2 = 1.0 / (sigma * sigma);
            // Above the target: a stage, to the looser rule, but stall-probed.
            let stop = NewtonStop {
                stall_probe: true,
                ..NewtonStop::STAGE
            };
            let r = self.newton(
                lambda_hat,
                theta0,
                run.cold_budget.min(run.max_iterations - run.used),
                stop,
            )?;
            run.record(sigma, &r);
            if r.converged {
                return Ok(Some((sigma, r)));
            }
        }
        Ok(None)
    }

    /// Descends from the converged cold start `good` at `sigma` with warm starts, each
    /// σ_c [`CONTINUATION_RATIO`] below the last; only the last stage, at the target,
    /// converges fully. A stage that fails hands over to [`Self::carry_on`].
    fn descend(
        &mut self,
        mut run: Continuation,
        direct: &BayesResult,
        mut sigma: f64,
        mut good: BayesResult,
    ) -> Result<BayesResult, BayesError> {
        let target = run.target;
        while sigma > target {
            if run.used >= run.max_iterations {
                // Budget spent above the target: report the last stage at the target σ_c,
                // not converged.
                self.inv_s2 = 1.0 / (target * target);
                let mut r = self.solve_newton_from(&good.state.lambda, &good.state.theta, 0)?;
                r.converged = false;
                return Ok(run.finish(self, r));
            }
            let next = (sigma / CONTINUATION_RATIO).max(target);
            self.inv_s2 = 1.0 / (next * next);
            let stop = if next > target {
                NewtonStop::STAGE
            } else {
                run.last
            };
            // A stage that meets a point where the φ substep cannot be solved (see
            // `carry_on`) fails like one that does not converge.
            let Ok(r) = self.newton(
                &good.state.lambda,
                &good.state.theta,
                run.budget.min(run.max_iterations - run.used),
                stop,
            ) else {
                return self.carry_on(run, direct, None);
            };
            run.record(next, &r);
            if !r.converged {
                // A stage above the target is at another σ_c: its J_p is not comparable.
                return self.carry_on(run, direct, (next == target).then_some(&r));
            }
            sigma = next;
            good = r;
        }
        Ok(run.finish(self, good))
    }

    /// If no cold start converged up to 10^CONTINUATION_CLIMBS σ_c, or a warm stage
    /// fails on the way down, the trouble is not the narrow valley of a small σ_c
    /// (typically θ runs against the boundary θ > 0): carry on at the target, with the
    /// budget left, from where the first cold start (`direct`) stopped or from where the
    /// `failed` stage at the target stopped, whichever is lower in J_p. (Four-bay frame,
    /// seed 3, σ_c = 1: the cold start stalls at J_p = 5.1e4, the stage at the target
    /// reaches 377.2 and stops on a Hessian that is not positive definite; carrying on from
    /// the cold start ended at 2.6e4.)
    fn carry_on(
        &mut self,
        mut run: Continuation,
        direct: &BayesResult,
        failed: Option<&BayesResult>,
    ) -> Result<BayesResult, BayesError> {
        let target = run.target;
        self.inv_s2 = 1.0 / (target * target);
        let budget = run.max_iterations.saturating_sub(run.used);
        let last = run.last;
        let from_direct =
            |prob: &Self| prob.newton(&direct.state.lambda, &direct.state.theta, budget, last);
        let more = match failed {
            // A point that low can sit on an eigenvalue of the model to rounding (σ_c
            // small: the model equation nearly holds), where a large model's φ substep
            // cannot be solved (four-bay frame, seed 1, σ_c = 1): then, as before, from
            // the cold start.
            Some(r) if r.terms.total < direct.terms.total => self
                .newton(&r.state.lambda, &r.state.theta, budget, last)
                .or_else(|_| from_direct(self))?,
            _ => from_direct(self)?,
        };
        run.record(target, &more);
        Ok(run.finish(self, more))
    }

    /// [`Self::solve_newton`] from any `(λ0, θ0)`, e.g. the MAP at a neighbouring σ_c.
    pub fn solve_newton_from(
        &self,
        lambda0: &[f64],
        theta0: &[f64],
        max_iterations: usize,
    ) -> Result<BayesResult, BayesError> {
        self.newton(lambda0, theta0, max_iterations, NewtonStop::FINAL)
    }

    /// The damped Newton iteration behind [`Self::solve_newton_from`], with its stopping
    /// rule as a parameter.
    pub(super) fn newton(
        &self,
        lambda0: &[f64],
        theta0: &[f64],
        max_iterations: usize,
        stop: NewtonStop,
    ) -> Result<BayesResult, BayesError> {
        let nm = self.modes.len();
        let mut y: Vec<f64> = lambda0.to_vec();
        y.extend_from_slice(&self.bounds.clamp(theta0));
        let cur = self.reduced(&y[..nm], &y[nm..])?;
        let mut it = Iterate {
            y,
            cur,
            delta: TRUST_INITIAL_RADIUS,
            least_mu: f64::INFINITY,
        };
        let mut iterations = 0;
        let mut converged = false;
        let mut stuck = false;
        while iterations < max_iterations {
            if stop.stall_probe
                && iterations >= STALL_PROBE_ITERATIONS
                && it.least_mu >= STALL_DAMPING
            {
                break;
            }
            let scale_y = it.y.iter().fold(0.0_f64, |a, v| a.max(v.abs()));
            // A θ on a bound with descent pointing out of the box is held there: the steps
            // and the stopping test are those of the free variables (the bounded
            // first-order conditions).
            let (hessian, gradient) = self.free_part(&it.cur, &it.y[nm..]);
            if stop.converged_at(&hessian, &gradient, &it.y, scale_y, it.cur.value) {
                converged = true;
                break;
            }
            let accepted = self.trust_step(&mut it, &hessian, &gradient, scale_y);
            iterations += 1;
            self.report(iterations, it.cur.value, &it.y[nm..]);
            if !accepted {
                // No descent possible at machine precision: at the minimum if the Hessian
                // is positive definite there, otherwise stuck (a saddle or a boundary).
                converged = hessian.llt(Side::Lower).is_ok();
                stuck = !converged;
                break;
            }
        }
        let state = BayesState {
            lambda: it.y[..nm].to_vec(),
            phi: it.cur.phi,
            theta: it.y[nm..].to_vec(),
        };
        Ok(BayesResult {
            terms: self.objective(&state),
            state,
            iterations,
            converged,
            stuck,
            solver: BayesSolver::Newton,
            stages: Vec::new(),
        })
    }

    /// One trust-region step from `it` on the free `hessian` and `gradient`: trial steps
    /// of shrinking radius until one lowers `F` by [`TRUST_ACCEPT`] of its predicted
    /// decrease (then `it` moves there and its radius adapts; `true`), or none can
    /// (`false`).
    fn trust_step(
        &self,
        it: &mut Iterate,
        hessian: &Mat<f64>,
        gradient: &[f64],
        scale_y: f64,
    ) -> bool {
        let ny = it.y.len();
        // Trust-region step in relative coordinates `y_i = d_i (1 + z_i)`: the region
        // `‖z‖ ≤ Δ < 1` keeps every λ and θ positive, and scales the modes' eigenvalues
        // (~1e5) and the parameters (~1) alike.
        let model = ScaledModel::at(&it.y, hessian, gradient, scale_y);
        let d = &model.d;
        while it.delta >= TRUST_MIN_RADIUS {
            let Some(step) = trust::trust_region_step(&model.h, &model.g, it.delta) else {
                break;
            };
            let mut trial_y: Vec<f64> = (0..ny).map(|i| it.y[i] + d[i] * step.z[i]).collect();
            let length = step.z.iter().map(|v| v * v).sum::<f64>().sqrt();
            // Cut at the bounds; a cut step predicts its own decrease.
            let predicted = self
                .cut_at_bounds(&it.y, &mut trial_y, d, &model.h, &model.g)
                .unwrap_or(step.predicted);
            let Some(trial) = self.trial(&trial_y) else {
                it.delta = 0.25 * length.min(it.delta);
                continue;
            };
            // Ratio of the actual to the predicted decrease.
            let rho = (it.cur.value - trial.value) / predicted;
            if trial.value < it.cur.value && rho > TRUST_ACCEPT {
                if rho > 0.75 && step.on_boundary {
                    it.delta = (2.0 * it.delta).min(TRUST_MAX_RADIUS);
                } else if rho < 0.25 {
                    it.delta = 0.25 * length;
                }
                it.y = trial_y;
                it.cur = trial;
                it.least_mu = it
                    .least_mu
                    .min(step.mu / model.h_diag.max(f64::MIN_POSITIVE));
                return true;
            }
            // A rejected step whose predicted decrease F cannot even resolve: the
            // minimum is reached to F's rounding (shrinking the radius would only spend
            // evaluations on rounding noise).
            if predicted <= NEWTON_RESOLUTION * it.cur.value.abs() {
                break;
            }
            it.delta = 0.25 * length.min(it.delta);
        }
        false
    }

    /// `F` at a trial `y`, or `None` where it is treated like a step that ascends.
    fn trial(&self, trial_y: &[f64]) -> Option<Reduced> {
        let nm = self.modes.len();
        // θ > 0 and λ > 0 (K positive definite, modes of a stable structure); the
        // radius keeps them, a trial outside is treated like one that ascends.
        if trial_y.iter().all(|v| *v > 0.0) {
            self.reduced(&trial_y[..nm], &trial_y[nm..]).ok()
        } else {
            None
        }
    }
}

impl BayesProblem {
    /// The Hessian and gradient of `F` with every held θ decoupled (identity row and
    /// column, zero gradient): held is a θ on a bound whose descent direction points out of
    /// the box. Without bounds, or with none active, `cur`'s own.
    fn free_part(&self, cur: &Reduced, theta: &[f64]) -> (Mat<f64>, Vec<f64>) {
        let nm = self.modes.len();
        let mut h = cur.hessian.clone();
        let mut g = cur.gradient.clone();
        for (l, t) in theta.iter().enumerate() {
            let i = nm + l;
            let held = match self.bounds.side(l, t.ln(), 1e-12) {
                Some(AtBound::Upper) => g[i] < 0.0,
                Some(AtBound::Lower) => g[i] > 0.0,
                None => false,
            };
            if held {
                for j in 0..h.nrows() {
                    h[(i, j)] = 0.0;
                    h[(j, i)] = 0.0;
                }
                h[(i, i)] = 1.0;
                g[i] = 0.0;
            }
        }
        (h, g)
    }

    /// Cuts the θ part of `trial` at the bounds; if anything was cut, the decrease the
    /// quadratic model (scaled `h`, `g` at `y`, scaling `d`) predicts for the cut step.
    fn cut_at_bounds(
        &self,
        y: &[f64],
        trial: &mut [f64],
        d: &[f64],
        h: &Mat<f64>,
        g: &[f64],
    ) -> Option<f64> {
        let nm = self.modes.len();
        let cut = self.bounds.clamp(&trial[nm..]);
        if cut == trial[nm..] {
            return None;
        }
        trial[nm..].copy_from_slice(&cut);
        let z: Vec<f64> = (0..y.len()).map(|i| (trial[i] - y[i]) / d[i]).collect();
        let hz = h * faer::ColRef::from_slice(&z);
        let quad: f64 = (0..z.len()).map(|i| z[i] * hz[i]).sum();
        Some(-(dot(g, &z) + 0.5 * quad))
    }
}
