//! The linear algebra of a mode-matching step: the normal equations in `u = ln θ` with the
//! parameters held at their bounds decoupled, the undamped Gauss–Newton step (19) by
//! Cholesky or, where the normal matrix is singular, by its scaled pseudo-inverse, the
//! step cut at the bounds, the first-order (KKT) conditions of the bounded problem, and the
//! covariance (15) from the Jacobian.

use faer::linalg::solvers::{Llt, Solve};
use faer::{Mat, Side};

use crate::core::updating::bounds::{AtBound, LogBounds};
use crate::core::updating::data::{MeasuredData, Weighting};
use crate::core::updating::residual::Evaluation;

/// Covariance (15) from the whitened Jacobian at `ev` (see
/// [`super::ModeMatching::covariance`]).
pub(crate) fn covariance_from_jacobian(
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
pub(super) fn within_std(
    fs: &FreeStep,
    step: &[f64],
    t: f64,
    data: &MeasuredData,
    ev: &Evaluation,
) -> bool {
    let scale = variance_scale(data, ev, step.len());
    (0..step.len()).all(|i| step[i].abs() < t * (fs.var[i] * scale).sqrt())
}

/// The factor of `(A⁺)_ii` in the variance of (15): `ε/(N − N_θ)` under weighting (9), else 1.
fn variance_scale(data: &MeasuredData, ev: &Evaluation, p: usize) -> f64 {
    match data.weighting {
        Weighting::Heuristic { .. } => ev.epsilon / data.n_data().saturating_sub(p).max(1) as f64,
        _ => 1.0,
    }
}

/// The largest `|step_i|` in standard deviations of (15), scaled as in [`within_std`].
pub(super) fn step_in_std(
    fs: &FreeStep,
    step: &[f64],
    data: &MeasuredData,
    ev: &Evaluation,
) -> f64 {
    let scale = variance_scale(data, ev, step.len());
    (0..step.len()).fold(0.0_f64, |m, i| {
        m.max(step[i].abs() / (fs.var[i] * scale).sqrt())
    })
}

/// The normal matrix `A = J_uᵀJ_u` and gradient `g = J_uᵀr` (half that of ε) in
/// `u = ln θ` (`J_u = J diag(θ)`), with every held parameter decoupled: a parameter at a
/// bound that descent would push beyond (and, after a failed release, any parameter at a
/// bound) gets the identity's row and column and a zero gradient, so no step moves it.
pub(super) fn normal_equations(
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
pub(super) struct FreeStep {
    pub(super) step: Vec<f64>,
    /// `(A⁺)_ii`: the variance of `ln θ_i` by (15) where the data determine it.
    var: Vec<f64>,
    /// `A` itself, for the predicted decrease of a step cut at a bound.
    a: Mat<f64>,
}

impl FreeStep {
    /// `A x`.
    pub(super) fn normal_times(&self, x: &[f64]) -> Vec<f64> {
        let ax = &self.a * faer::ColRef::from_slice(x);
        (0..x.len()).map(|i| ax[i]).collect()
    }
}

/// [`FreeStep`] for the normal equations `A`, `g` (held parameters already decoupled):
/// Cholesky when `A` is numerically of full rank, else an eigendecomposition of
/// `D^{-1/2} A D^{-1/2}` (`D = diag A`) with eigenvalues below [`RANK_TOL`] of the largest
/// dropped. `None` if the step is not finite.
pub(super) fn free_gauss_newton(a: &Mat<f64>, g: &faer::Col<f64>) -> Option<FreeStep> {
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

/// The damped step `(A + μD) δ = −g`, by Cholesky; `None` when the matrix is not definite.
pub(super) fn cholesky_step(damped: &Mat<f64>, g: &faer::Col<f64>) -> Option<faer::Col<f64>> {
    let mut step = -g.clone();
    damped
        .llt(Side::Lower)
        .ok()?
        .solve_in_place(step.as_mat_mut());
    Some(step)
}

/// The damped step `(A + μD) δ = −g` within the bounds ([`super::BoundStep::Hold`]): a component the solve would take
/// across its bound is held on it and the others are solved again with it fixed, until no
/// free component crosses (`u = ln θ` the current point). When none crosses, this is the
/// plain solve. Cutting each crossing component afterwards instead
/// left the others at the scale of a step along a direction the data hardly see: a
/// parameter on its bound whose free step pointed out by 5e5 in ln θ had the whole step
/// scaled to [`super::MAX_LOG_STEP`] and then cut to nothing, and the fit crept on for 100
/// iterations. `None` when a system is not definite.
pub(super) fn step_within_bounds(
    damped: &Mat<f64>,
    g: &faer::Col<f64>,
    bounds: &LogBounds,
    u: &[f64],
) -> Option<faer::Col<f64>> {
    let p = g.nrows();
    let mut fixed: Vec<Option<f64>> = vec![None; p];
    loop {
        let free: Vec<usize> = (0..p).filter(|&i| fixed[i].is_none()).collect();
        let mut step = faer::Col::from_fn(p, |i| fixed[i].unwrap_or(0.0));
        if free.len() == p {
            step = cholesky_step(damped, g)?;
        } else if !free.is_empty() {
            let sub = Mat::from_fn(free.len(), free.len(), |a, b| damped[(free[a], free[b])]);
            let mut rhs = faer::Col::from_fn(free.len(), |a| -g[free[a]]);
            for (a, &i) in free.iter().enumerate() {
                for j in (0..p).filter(|&j| fixed[j].is_some_and(|d| d != 0.0)) {
                    rhs[a] -= damped[(i, j)] * step[j];
                }
            }
            let llt = sub.llt(Side::Lower).ok()?;
            llt.solve_in_place(rhs.as_mat_mut());
            for (a, &i) in free.iter().enumerate() {
                step[i] = rhs[a];
            }
        }
        let mut crossed = false;
        for &i in &free {
            let to = u[i] + step[i];
            if to > bounds.hi[i] || to < bounds.lo[i] {
                fixed[i] = Some(bounds.clip(i, u[i], step[i]));
                crossed = true;
            }
        }
        if !crossed {
            return Some(step);
        }
    }
}

/// Each step entry cut at the bounds.
pub(super) fn clipped(bounds: &LogBounds, theta: &[f64], step: &[f64]) -> Vec<f64> {
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
    /// The conditions at `ev`, from its Jacobian `jac` (no parameter held but by its
    /// descent direction).
    pub(super) fn at(jac: &Mat<f64>, ev: &Evaluation, bounds: &LogBounds) -> Self {
        let (a, g) = normal_equations(jac, &ev.r, &ev.theta, bounds, false);
        Self::of(&g, free_gauss_newton(&a, &g).as_ref())
    }

    /// From the gradient (held parameters zeroed) and the undamped step over the free ones.
    pub(super) fn of(g: &faer::Col<f64>, fs: Option<&FreeStep>) -> Self {
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
pub(super) fn gauss_newton_step(jac: &Mat<f64>, r: &[f64]) -> Option<Vec<f64>> {
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

#[cfg(test)]
mod tests {
    use super::*;

    /// `A = [[2, 1], [1, 2]]`, `g = (−4, 2)`: the free solve is `δ = (10/3, −8/3)`. With the
    /// second parameter's `ln θ` bounded below at −1 it crosses and is held there (`δ₂ = −1`),
    /// and the first solves `2 δ₁ = 4 − 1 · (−1)`, `δ₁ = 5/2` (not the 10/3 that cutting
    /// alone would keep, nor the 3/8 of it that scaling would); within wide bounds the step
    /// is the free solve.
    #[test]
    fn a_step_that_crosses_a_bound_is_held_there_and_the_rest_solved_again() {
        let a = Mat::from_fn(2, 2, |i, j| if i == j { 2.0 } else { 1.0 });
        let g = faer::Col::from_fn(2, |i| [-4.0, 2.0][i]);
        let bounds = |lo: f64| LogBounds {
            lo: vec![-10.0, lo],
            hi: vec![10.0, 10.0],
        };
        let free = step_within_bounds(&a, &g, &bounds(-10.0), &[0.0, 0.0]).unwrap();
        assert!((free[0] - 10.0 / 3.0).abs() < 1e-14 && (free[1] + 8.0 / 3.0).abs() < 1e-14);
        let held = step_within_bounds(&a, &g, &bounds(-1.0), &[0.0, 0.0]).unwrap();
        assert!((held[0] - 2.5).abs() < 1e-14, "{:?}", held);
        assert_eq!(held[1], -1.0);
    }

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
