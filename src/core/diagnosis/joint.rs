//! An effect's value fitted jointly with θ: one Levenberg–Marquardt problem in `(ln θ, t)`,
//! `t` the effect's search coordinate (`ln u` for effects of one sign, `u / h` otherwise).
//! It finds the minimum of the profile `ε(u) = min_θ ε(θ, u)` in one fit where the profile
//! search needs 10–25 (module docs of [`super::refit`]).
//!
//! The θ columns of the Jacobian are Nelson's, at the model with the effect at `u`; the `t`
//! column is a forward difference (one more model and eigen solve per iteration). A step of
//! `t` that changes the mode pairing (a measured mode moved across a close neighbour) has no
//! such column, in either direction: the fit then gives up, and the caller searches the
//! profile instead.

use faer::Side;
use faer::linalg::solvers::Solve;

use super::*;
use crate::core::updating::LogBounds;

/// The joint fit stops once the undamped step predicts a decrease of ε below this: the
/// inner fits' tolerance (`fit::mm_options`), which is 0.03 σ of the value at the minimum.
const EPS_TOL: f64 = 1e-3;

/// Iterations at most; a fit still going then is handed to the profile search.
const MAX_ITERATIONS: usize = 60;

/// Largest change of `ln θ_i` or of `ln u` in one step (as mode matching's cap).
const MAX_LOG_STEP: f64 = 2.0;

/// The effect's search coordinate `t` and its value `u`.
#[derive(Clone, Copy)]
pub(super) struct Coordinate {
    pub(super) sign: Sign,
    /// The effect's finite-difference step at `u = 0`.
    pub(super) h: f64,
}

impl Coordinate {
    pub(super) fn u(&self, t: f64) -> f64 {
        match self.sign {
            Sign::Positive => t.exp(),
            Sign::Any => t * self.h,
        }
    }

    /// The start of the search from the screened value, and the profile bracket's step.
    pub(super) fn start(&self, u_linear: f64) -> (f64, f64) {
        match self.sign {
            Sign::Positive => (u_linear.max(self.h * 1e-3).ln(), 0.7),
            Sign::Any => (u_linear / self.h, (u_linear.abs() / self.h / 2.0).max(1.0)),
        }
    }

    /// The forward-difference step of `t` for the Jacobian's column: 0.1 % of `u`, or a
    /// thousandth of the effect's step near `u = 0`.
    fn difference_step(&self, t: f64) -> f64 {
        match self.sign {
            Sign::Positive => 1e-3,
            Sign::Any => 1e-3 * t.abs().max(1.0),
        }
    }

    /// The cap on one step of `t`: [`MAX_LOG_STEP`] in `ln u`, and in `u / h` as large a
    /// relative change, or 10 effect steps near zero.
    fn max_step(&self, t: f64) -> f64 {
        match self.sign {
            Sign::Positive => MAX_LOG_STEP,
            Sign::Any => (MAX_LOG_STEP * t.abs()).max(10.0),
        }
    }
}

/// One candidate's joint problem: the model class, the effect at its location, the data.
pub(super) struct Joint<'a> {
    pub(super) spec: &'a Description,
    pub(super) effect: &'a dyn Effect,
    pub(super) location: &'a str,
    pub(super) data: &'a MeasuredData,
    pub(super) coord: Coordinate,
}

/// The model with the effect at `t`, and the residual at θ there.
struct Point {
    t: f64,
    model: Model,
    evaluator: Evaluator,
    ev: Evaluation,
}

/// Where the joint fit ended.
pub(super) struct JointMinimum {
    pub(super) t: f64,
    pub(super) epsilon: f64,
    pub(super) theta: Vec<f64>,
}

impl Joint<'_> {
    /// The joint Levenberg–Marquardt fit from `(θ0, t0)`; `None` when the `t` column cannot
    /// be formed (a pairing change both ways), a model fails to build or evaluate, or the
    /// fit has not converged within [`MAX_ITERATIONS`].
    pub(super) fn fit(&self, theta0: &[f64], t0: f64) -> Option<JointMinimum> {
        let mut cur = self.point(t0, theta0)?;
        let bounds = LogBounds::new(&cur.model, Some(THETA_RANGE));
        let mut mu = 1e-3;
        let mut nu = 2.0;
        for _ in 0..MAX_ITERATIONS {
            let (a, g) = self.normal_equations(&mut cur)?;
            if predicted_decrease(&a, &g, &self.box_of(&cur, &bounds, false))
                .is_some_and(|d| d < EPS_TOL)
            {
                return Some(cur.minimum());
            }
            match self.damped_step(&cur, &bounds, &a, &g, &mut mu, &mut nu) {
                Some(next) => cur = next,
                // No damped step lowers ε: the evaluations no longer resolve a descent.
                None => return Some(cur.minimum()),
            }
        }
        None
    }

    /// The model with the effect at `t`, evaluated at θ.
    fn point(&self, t: f64, theta: &[f64]) -> Option<Point> {
        let (model, mut evaluator) =
            with_effect(self.spec, self.effect, self.location, self.coord.u(t))?;
        let ev = evaluator.evaluate(&model, self.data, theta).ok()?;
        Some(Point {
            t,
            model,
            evaluator,
            ev,
        })
    }

    /// `JᵀJ` and `Jᵀr` in `(ln θ, t)`: Nelson's columns scaled by θ, and the forward
    /// difference in `t` (backward if forward changes the pairing).
    fn normal_equations(&self, cur: &mut Point) -> Option<(Mat<f64>, faer::Col<f64>)> {
        let jac = cur
            .evaluator
            .jacobian(&cur.model, self.data, &cur.ev)
            .ok()?;
        let column = self.t_column(cur)?;
        let (n, p) = (jac.nrows(), jac.ncols());
        let j = Mat::from_fn(n, p + 1, |i, l| {
            if l < p {
                jac[(i, l)] * cur.ev.theta[l]
            } else {
                column[i]
            }
        });
        let a = j.transpose() * &j;
        let g = j.transpose() * faer::ColRef::from_slice(&cur.ev.r);
        Some((a, g))
    }

    /// `∂r/∂t` at the current point by a one-sided difference with the pairing unchanged.
    fn t_column(&self, cur: &Point) -> Option<Vec<f64>> {
        let dt = self.coord.difference_step(cur.t);
        for step in [dt, -dt] {
            let Some(other) = self.point(cur.t + step, &cur.ev.theta) else {
                continue;
            };
            if other.ev.pairing == cur.ev.pairing && other.ev.r.len() == cur.ev.r.len() {
                let col = other
                    .ev
                    .r
                    .iter()
                    .zip(&cur.ev.r)
                    .map(|(a, b)| (a - b) / step)
                    .collect();
                return Some(col);
            }
        }
        None
    }

    /// Levenberg–Marquardt trials with growing damping (Marquardt's diagonal scaling,
    /// Nielsen's update of μ from the gain ratio) until one lowers ε.
    fn damped_step(
        &self,
        cur: &Point,
        bounds: &LogBounds,
        a: &Mat<f64>,
        g: &faer::Col<f64>,
        mu: &mut f64,
        nu: &mut f64,
    ) -> Option<Point> {
        let p = g.nrows() - 1;
        let theta = &cur.ev.theta;
        let dmax = (0..=p).map(|i| a[(i, i)]).fold(0.0_f64, f64::max);
        while *mu < 1e16 {
            let mut damped = a.clone();
            for i in 0..=p {
                damped[(i, i)] += *mu * a[(i, i)].max(1e-12 * dmax);
            }
            let Some(step) = boxed_minimum(&damped, g, &self.box_of(cur, bounds, true)) else {
                (*mu, *nu) = (*mu * *nu, *nu * 2.0);
                continue;
            };
            let pred = -(2.0 * (step.transpose() * g) + step.transpose() * (a * &step));
            let new: Vec<f64> = (0..p).map(|i| theta[i] * step[i].exp()).collect();
            if let Some(trial) = self.point(cur.t + step[p], &new) {
                let actual = cur.ev.epsilon - trial.ev.epsilon;
                if actual > 0.0 && pred > 0.0 {
                    let rho = actual / pred;
                    *mu *= (1.0 / 3.0_f64).max(1.0 - (2.0 * rho - 1.0).powi(3));
                    *nu = 2.0;
                    return Some(trial);
                }
            }
            (*mu, *nu) = (*mu * *nu, *nu * 2.0);
        }
        None
    }

    /// The box a step from `cur` stays in: `ln θ` within `bounds`, and with `capped` each
    /// component within its cap ([`MAX_LOG_STEP`], [`Coordinate::max_step`]).
    fn box_of(&self, cur: &Point, bounds: &LogBounds, capped: bool) -> StepBox {
        let theta = &cur.ev.theta;
        let cap = |c: f64| if capped { c } else { f64::INFINITY };
        let (mut lo, mut hi): (Vec<f64>, Vec<f64>) = theta
            .iter()
            .enumerate()
            .map(|(i, th)| {
                let u = th.ln();
                (
                    (bounds.lo[i] - u).max(-cap(MAX_LOG_STEP)),
                    (bounds.hi[i] - u).min(cap(MAX_LOG_STEP)),
                )
            })
            .unzip();
        let t_cap = cap(self.coord.max_step(cur.t));
        lo.push(-t_cap);
        hi.push(t_cap);
        StepBox { lo, hi }
    }
}

/// Per-component limits of a step.
struct StepBox {
    lo: Vec<f64>,
    hi: Vec<f64>,
}

/// The minimum of the quadratic model `2gᵀs + sᵀAs` within `b`, by active sets: the free
/// components solved with the fixed ones moved to the right-hand side, and every free
/// component found outside its limits fixed at the limit it crossed, until none is. A
/// component that wants far beyond its limit (a θ whose effect has vanished, whose column
/// of the Jacobian is nearly zero) is so held at the limit while the others take their
/// full step: scaling the whole step down to its cap would stall them. `None` when `A` is
/// not definite on the free components.
fn boxed_minimum(a: &Mat<f64>, g: &faer::Col<f64>, b: &StepBox) -> Option<faer::Col<f64>> {
    let n = g.nrows();
    let mut fixed: Vec<Option<f64>> = vec![None; n];
    loop {
        let free: Vec<usize> = (0..n).filter(|&i| fixed[i].is_none()).collect();
        let mut step = faer::Col::from_fn(n, |i| fixed[i].unwrap_or(0.0));
        if !free.is_empty() {
            let af = Mat::from_fn(free.len(), free.len(), |r, c| a[(free[r], free[c])]);
            let mut rhs = Mat::from_fn(free.len(), 1, |r, _| {
                let i = free[r];
                -g[i]
                    - (0..n)
                        .map(|j| a[(i, j)] * fixed[j].unwrap_or(0.0))
                        .sum::<f64>()
            });
            af.llt(Side::Lower).ok()?.solve_in_place(rhs.as_mut());
            for (r, &i) in free.iter().enumerate() {
                step[i] = rhs[(r, 0)];
            }
        }
        let crossed: Vec<usize> = free
            .iter()
            .copied()
            .filter(|&i| step[i] < b.lo[i] || step[i] > b.hi[i])
            .collect();
        if crossed.is_empty() {
            return Some(step);
        }
        for i in crossed {
            fixed[i] = Some(step[i].clamp(b.lo[i], b.hi[i]));
        }
    }
}

impl Point {
    fn minimum(&self) -> JointMinimum {
        JointMinimum {
            t: self.t,
            epsilon: self.ev.epsilon,
            theta: self.ev.theta.clone(),
        }
    }
}

/// The decrease of ε the undamped Gauss–Newton step predicts within `b` (`ln θ` within its
/// bounds), `−(2gᵀs + sᵀAs)` (`None` when `A` is singular to a tiny regularization). A θ
/// held at its bound drops out: its promised decrease cannot be had.
fn predicted_decrease(a: &Mat<f64>, g: &faer::Col<f64>, b: &StepBox) -> Option<f64> {
    let n = g.nrows();
    let dmax = (0..n).map(|i| a[(i, i)]).fold(0.0_f64, f64::max);
    let mut reg = a.clone();
    for i in 0..n {
        reg[(i, i)] += 1e-12 * dmax;
    }
    let s = boxed_minimum(&reg, g, b)?;
    let pred = -(2.0 * (s.transpose() * g) + s.transpose() * (a * &s));
    Some(pred.max(0.0))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::diagnosis::fixtures::{NOISE, lab, spread_theta};
    use crate::core::simulate::simulated_measured_data;

    /// Noise-free data of the lab frame with `kind@location = truth` and its bolts at θ
    /// scaled from nominal; the joint fit from the nominal θ and `u0` recovers the value and
    /// θ, with ε at rounding level.
    fn recovers(kind: &str, location: &str, truth: f64, u0: f64) {
        let spec = lab();
        let effect = effects::by_kind(kind).unwrap();
        let mut with = spec.clone();
        effect.apply(&mut with, location, truth).unwrap();
        let model = with.build().unwrap();
        let theta = spread_theta(&model);
        let data = simulated_measured_data(&model, &theta, 9, NOISE, false, 1).unwrap();
        let coord = Coordinate {
            sign: effect.sign(),
            h: effect.step(&spec, location),
        };
        let joint = Joint {
            spec: &spec,
            effect: effect.as_ref(),
            location,
            data: &data,
            coord,
        };
        let (t0, _) = coord.start(u0);
        let nominal = spec.build().unwrap().nominal_theta();
        let m = joint.fit(&nominal, t0).expect("the joint fit converges");
        let u = coord.u(m.t);
        // Noise-free data: ε is rounding (eigenpairs to ~1e-10 relative, residuals in units
        // of a 1 % σ) plus the 1e-3 stop; the value to what such an ε allows.
        assert!(m.epsilon < 1e-3, "{kind}@{location}: ε = {}", m.epsilon);
        assert!(
            (u - truth).abs() <= 1e-3 * truth.abs(),
            "{kind}@{location}: u = {u}, truth {truth}"
        );
        for (i, (a, b)) in m.theta.iter().zip(&theta).enumerate() {
            assert!((a / b - 1.0).abs() < 1e-2, "θ{}: {a} against {b}", i + 1);
        }
    }

    /// The boxed step is the minimum of the quadratic model within the box: unconstrained
    /// `s = −A⁻¹g = (5, −4)`; with `s₀ ≤ 1` it is `(1, −2)` (∂q/∂s₁ = 0 and ∂q/∂s₀ < 0
    /// at the bound: the KKT point), not the scaled step `(1, −0.8)`; a wide box leaves it
    /// unconstrained. Exact arithmetic on small integers: tolerances of rounding.
    #[test]
    fn the_boxed_step_holds_a_component_at_its_limit_and_solves_the_rest() {
        let a = Mat::from_fn(2, 2, |i, j| if i == j { 2.0 } else { 1.0 });
        let g = faer::Col::from_fn(2, |i| [-6.0, 3.0][i]);
        let wide = StepBox {
            lo: vec![-10.0; 2],
            hi: vec![10.0; 2],
        };
        let s = boxed_minimum(&a, &g, &wide).unwrap();
        assert!(
            (s[0] - 5.0).abs() < 1e-12 && (s[1] + 4.0).abs() < 1e-12,
            "{s:?}"
        );
        let capped = StepBox {
            lo: vec![-10.0; 2],
            hi: vec![1.0, 10.0],
        };
        let s = boxed_minimum(&a, &g, &capped).unwrap();
        assert!(
            (s[0] - 1.0).abs() < 1e-12 && (s[1] + 2.0).abs() < 1e-12,
            "{s:?}"
        );
        // Both limits crossed: both components held on them.
        let both = StepBox {
            lo: vec![-10.0, -1.5],
            hi: vec![1.0, 10.0],
        };
        let s = boxed_minimum(&a, &g, &both).unwrap();
        assert!(
            (s[0] - 1.0).abs() < 1e-12 && (s[1] + 1.5).abs() < 1e-12,
            "{s:?}"
        );
        // The predicted decrease is that of the step within the box, −(2gᵀs + sᵀAs) at
        // (1, −2), not the unconstrained gᵀA⁻¹g = 42.
        let pred = predicted_decrease(&a, &g, &capped).unwrap();
        assert!((pred - 18.0).abs() < 1e-9, "{pred}");
    }

    /// An effect of one sign, fitted in `ln u`, from half its value.
    #[test]
    fn a_mass_and_theta_are_recovered_jointly() {
        recovers("added-mass", "B2.3", 1.0, 0.5);
    }

    /// An effect of either sign, fitted in `u / h`, from a tenth of its value.
    #[test]
    fn a_stiffness_change_and_theta_are_recovered_jointly() {
        recovers("member-stiffness", "C1L", -0.3, -0.03);
    }
}
