//! The trust-region subproblem of the Newton solver on `F(λ, θ)`.
//!
//! `min_z gᵀz + ½ zᵀHz` subject to `‖z‖ ≤ Δ`, solved exactly (Moré & Sorensen, "Computing a
//! trust region step", SIAM J. Sci. Stat. Comput. 4, 1983; Nocedal & Wright, *Numerical
//! Optimization*, 2nd ed., §4.3) through the eigendecomposition of `H`, which is small
//! (one row per mode and per parameter). The solution is `z = −(H + μI)⁻¹g` with `μ ≥ 0`,
//! `H + μI` positive semidefinite and `μ(Δ − ‖z‖) = 0`; where `H` is indefinite the step
//! follows its negative curvature to the boundary instead of being damped into a short
//! gradient step, which is what lets the solver cross the non-convex region of `F` far from
//! the MAP in a few iterations.

use faer::{Mat, Side};

/// A solution of the trust-region subproblem.
#[derive(Debug, Clone)]
pub(super) struct TrustStep {
    /// The step `z`.
    pub z: Vec<f64>,
    /// The multiplier `μ` (0 for the interior Newton step).
    pub mu: f64,
    /// The model's predicted decrease `−(gᵀz + ½ zᵀHz)` (≥ 0).
    pub predicted: f64,
    /// Whether the step lies on the boundary `‖z‖ = Δ`.
    pub on_boundary: bool,
}

/// Solves the subproblem for symmetric `h` (its lower triangle is read), gradient `g` and
/// radius `delta > 0`. `None` if the eigendecomposition fails or `h`, `g` are not finite.
pub(super) fn trust_region_step(h: &Mat<f64>, g: &[f64], delta: f64) -> Option<TrustStep> {
    let n = g.len();
    let evd = h.self_adjoint_eigen(Side::Lower).ok()?;
    let s: Vec<f64> = evd.S().column_vector().iter().copied().collect();
    let u = evd.U();
    // g in the eigenbasis.
    let a: Vec<f64> = (0..n)
        .map(|i| (0..n).map(|k| u[(k, i)] * g[k]).sum())
        .collect();
    if !s.iter().chain(&a).all(|v| v.is_finite()) {
        return None;
    }
    // Coefficients of z in the eigenbasis, and whether the step is on the boundary.
    let (c, mu, on_boundary) = Eigenbasis::new(n, &s, &a).solve(delta);
    let predicted = -(0..n)
        .map(|i| a[i] * c[i] + 0.5 * s[i] * c[i] * c[i])
        .sum::<f64>();
    let z = (0..n)
        .map(|k| (0..n).map(|i| u[(k, i)] * c[i]).sum())
        .collect();
    Some(TrustStep {
        z,
        mu,
        predicted,
        on_boundary,
    })
}

/// The subproblem in the eigenbasis of `H`: its eigenvalues `s` and `g`'s coordinates `a`.
struct Eigenbasis<'a> {
    n: usize,
    s: &'a [f64],
    a: &'a [f64],
    /// The smallest eigenvalue `λ_min`.
    lmin: f64,
    /// The largest eigenvalue in magnitude.
    smax: f64,
    /// Eigenvalues within rounding of the smallest count as its eigenspace.
    tie: f64,
}

impl<'a> Eigenbasis<'a> {
    /// The subproblem for eigenvalues `s` and gradient coordinates `a` (`n` of each).
    fn new(n: usize, s: &'a [f64], a: &'a [f64]) -> Self {
        let lmin = s.iter().copied().fold(f64::INFINITY, f64::min);
        let smax = s.iter().fold(0.0_f64, |m, v| m.max(v.abs()));
        // Eigenvalues within rounding of the smallest count as its eigenspace.
        let tie = 1e-12 * smax.max(f64::MIN_POSITIVE);
        Self {
            n,
            s,
            a,
            lmin,
            smax,
            tie,
        }
    }

    /// `‖z(μ)‖ = ‖(H + μI)⁻¹g‖`.
    fn norm_at(&self, mu: f64) -> f64 {
        self.a
            .iter()
            .zip(self.s)
            .map(|(ai, si)| (ai / (si + mu)).powi(2))
            .sum::<f64>()
            .sqrt()
    }

    /// The coefficients of `z`, `μ` and whether `z` is on the boundary: the Newton step
    /// where `H` is positive definite and that step is within `delta`, else a boundary step.
    fn solve(&self, delta: f64) -> (Vec<f64>, f64, bool) {
        if self.lmin > self.tie && self.norm_at(0.0) <= delta {
            (
                self.a.iter().zip(self.s).map(|(ai, si)| -ai / si).collect(),
                0.0,
                false,
            )
        } else {
            self.on_boundary(delta)
        }
    }

    /// A step on the boundary `‖z‖ = delta`: the hard case if `g` has no component along
    /// the smallest eigenspace and the step at `μ = −λ_min` is inside, else the easy case.
    fn on_boundary(&self, delta: f64) -> (Vec<f64>, f64, bool) {
        let lo0 = (-self.lmin).max(0.0);
        // Part of g outside the smallest eigenspace decides between the easy and hard case.
        let in_min: f64 = self
            .a
            .iter()
            .zip(self.s)
            .filter(|(_, si)| **si - self.lmin <= self.tie)
            .map(|(ai, _)| ai * ai)
            .sum::<f64>()
            .sqrt();
        let gnorm = self.a.iter().map(|v| v * v).sum::<f64>().sqrt();
        if in_min <= 1e-14 * gnorm.max(f64::MIN_POSITIVE) && self.rest() < delta {
            (self.hard_case(delta), lo0, true)
        } else {
            let mu = self.easy_case(delta, lo0, gnorm);
            (
                self.a
                    .iter()
                    .zip(self.s)
                    .map(|(ai, si)| -ai / (si + mu))
                    .collect(),
                mu,
                true,
            )
        }
    }

    /// Length of the step at μ = −λ_min without the smallest eigenspace.
    fn rest(&self) -> f64 {
        self.a
            .iter()
            .zip(self.s)
            .filter(|(_, si)| **si - self.lmin > self.tie)
            .map(|(ai, si)| (ai / (si - self.lmin)).powi(2))
            .sum::<f64>()
            .sqrt()
    }

    /// Hard case: g has no component along the smallest eigenvector, and even at
    /// μ = −λ_min the step is inside; complete it to the boundary along that vector.
    fn hard_case(&self, delta: f64) -> Vec<f64> {
        let (s, lmin, tie) = (self.s, self.lmin, self.tie);
        let mut c: Vec<f64> = self
            .a
            .iter()
            .zip(s)
            .map(|(ai, si)| {
                if *si - lmin > tie {
                    -ai / (si - lmin)
                } else {
                    0.0
                }
            })
            .collect();
        let len2: f64 = c.iter().map(|v| v * v).sum();
        let i0 = (0..self.n)
            .min_by(|&i, &j| s[i].total_cmp(&s[j]))
            .expect("n ≥ 1");
        c[i0] = (delta * delta - len2).max(0.0).sqrt();
        c
    }

    /// Easy case: ‖z(μ)‖ decreases from above Δ (at μ → lo0) to 0; bracket and bisect (n
    /// is small, and bisection cannot fail). The `μ` with `‖z(μ)‖ ≤ delta`, to rounding.
    fn easy_case(&self, delta: f64, lo0: f64, gnorm: f64) -> f64 {
        let mut lo = lo0;
        let mut hi = lo0 + gnorm / delta + self.smax.max(f64::MIN_POSITIVE);
        while self.norm_at(hi) > delta {
            hi *= 2.0;
        }
        for _ in 0..200 {
            let mid = 0.5 * (lo + hi);
            if mid <= lo || mid >= hi {
                break;
            }
            if self.norm_at(mid) > delta {
                lo = mid;
            } else {
                hi = mid;
            }
        }
        hi
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn apply(h: &Mat<f64>, z: &[f64]) -> Vec<f64> {
        (0..z.len())
            .map(|i| (0..z.len()).map(|j| h[(i, j)] * z[j]).sum())
            .collect()
    }

    fn norm(z: &[f64]) -> f64 {
        z.iter().map(|v| v * v).sum::<f64>().sqrt()
    }

    /// The optimality conditions (Moré & Sorensen, Lemma 2.1): `(H + μI)z = −g`, `μ ≥ 0`,
    /// `‖z‖ ≤ Δ`, `μ(Δ − ‖z‖) = 0`, and the predicted decrease is the model's. Tolerances:
    /// rounding of a 3×3 eigendecomposition (1e-12 relative) and of the bisection.
    fn check_optimal(h: &Mat<f64>, g: &[f64], delta: f64, st: &TrustStep) {
        let hz = apply(h, &st.z);
        let res: Vec<f64> = (0..g.len())
            .map(|i| hz[i] + st.mu * st.z[i] + g[i])
            .collect();
        assert!(norm(&res) < 1e-10 * norm(g), "stationarity {res:?}");
        assert!(st.mu >= 0.0);
        assert!(norm(&st.z) <= delta * (1.0 + 1e-12));
        if st.mu > 0.0 {
            assert!(
                (norm(&st.z) - delta).abs() < 1e-10 * delta,
                "not on the boundary"
            );
        }
        let model: f64 = (0..g.len())
            .map(|i| g[i] * st.z[i] + 0.5 * st.z[i] * hz[i])
            .sum();
        assert!((st.predicted + model).abs() < 1e-12 * st.predicted.abs().max(1e-300));
    }

    fn mat(rows: [[f64; 3]; 3]) -> Mat<f64> {
        Mat::from_fn(3, 3, |i, j| rows[i][j])
    }

    #[test]
    fn interior_newton_step_when_positive_definite_and_short() {
        let h = mat([[4.0, 1.0, 0.0], [1.0, 3.0, 0.5], [0.0, 0.5, 2.0]]);
        let g = [0.1, -0.2, 0.3];
        let st = trust_region_step(&h, &g, 10.0).unwrap();
        assert_eq!(st.mu, 0.0);
        assert!(!st.on_boundary);
        check_optimal(&h, &g, 10.0, &st);
    }

    #[test]
    fn boundary_step_when_newton_is_too_long_or_curvature_negative() {
        let pd = mat([[4.0, 1.0, 0.0], [1.0, 3.0, 0.5], [0.0, 0.5, 2.0]]);
        let g = [1.0, -2.0, 3.0];
        let st = trust_region_step(&pd, &g, 0.1).unwrap();
        assert!(st.on_boundary && st.mu > 0.0);
        check_optimal(&pd, &g, 0.1, &st);
        // Indefinite: the step follows the negative curvature to the boundary, with
        // μ > −λ_min = 2 so that H + μI is positive definite.
        let ind = mat([[-2.0, 0.0, 0.0], [0.0, 1.0, 0.3], [0.0, 0.3, 5.0]]);
        let st = trust_region_step(&ind, &g, 0.5).unwrap();
        assert!(st.on_boundary && st.mu > 2.0);
        check_optimal(&ind, &g, 0.5, &st);
        // The model decreases more than along the steepest descent to the same radius.
        let sd: Vec<f64> = g.iter().map(|v| -0.5 * v / norm(&g)).collect();
        let hz = apply(&ind, &sd);
        let sd_pred = -(0..3)
            .map(|i| g[i] * sd[i] + 0.5 * sd[i] * hz[i])
            .sum::<f64>();
        assert!(st.predicted >= sd_pred);
    }

    #[test]
    fn hard_case_completes_along_the_smallest_eigenvector() {
        // g ⟂ e₁ (the eigenvector of −2): no μ > 2 reaches the boundary, μ = 2 exactly.
        let h = mat([[-2.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 5.0]]);
        let g = [0.0, 0.3, 0.5];
        let st = trust_region_step(&h, &g, 1.0).unwrap();
        assert!(st.on_boundary);
        assert!((st.mu - 2.0).abs() < 1e-12);
        assert!(st.z[0].abs() > 0.9);
        check_optimal(&h, &g, 1.0, &st);
    }
}
