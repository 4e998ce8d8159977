//! The paper's alternating substeps (21)–(23), as published; with bounds, each θ substep
//! (23) is projected onto the box.

use super::*;

/// Stopping rule of the alternating solver, as published: every `|Δθ_l| < 1e-9`.
pub const ALTERNATING_TOL: f64 = 1e-9;

impl BayesProblem {
    /// The paper's alternating minimization (21)–(23) from `λ = λ̂`, `θ = theta0`, until every
    /// `|Δθ_l| < 1e-9` or `max_iterations`.
    pub fn solve_alternating(
        &self,
        theta0: &[f64],
        max_iterations: usize,
    ) -> Result<BayesResult, BayesError> {
        let (n, nm, p) = (self.n, self.modes.len(), self.p);
        let mut lambda = self.lambda_hat();
        let mut theta = self.bounds.clamp(theta0);
        let mut phi = Mat::zeros(n, nm);
        let mut iterations = 0;
        let mut converged = false;
        while iterations < max_iterations {
            iterations += 1;
            // (21) φ for (λ_k, θ_k).
            phi = self.phi_star(&lambda, &theta)?;
            let (lhs, rhs) = self.alternating_normal_equations(&phi, &mut lambda, &theta);
            let Some(new) = self.alternating_theta_step(&lhs, &rhs) else {
                break;
            };
            let step = (0..p)
                .map(|l| (new[l] - theta[l]).abs())
                .fold(0.0, f64::max);
            theta = new;
            if self.progress.lock().is_ok_and(|g| g.is_some()) {
                let state = BayesState {
                    lambda: lambda.clone(),
                    phi: phi.clone(),
                    theta: theta.clone(),
                };
                self.report(iterations, self.objective(&state).total, &theta);
            }
            if step < ALTERNATING_TOL {
                converged = true;
                break;
            }
        }
        // φ consistent with the final (λ, θ).
        phi = self.optimal_phi(&lambda, &theta).unwrap_or(phi);
        let state = BayesState { lambda, phi, theta };
        Ok(BayesResult {
            terms: self.objective(&state),
            state,
            iterations,
            converged,
            stuck: false,
            solver: BayesSolver::Alternating,
            stages: Vec::new(),
        })
    }

    /// Substep (22) for every mode, updating `lambda` in place, and the normal equations
    /// `(lhs, rhs)` of substep (23) for θ at the new λ and `phi`, prior included.
    fn alternating_normal_equations(
        &self,
        phi: &Mat<f64>,
        lambda: &mut [f64],
        theta: &[f64],
    ) -> (Mat<f64>, Col<f64>) {
        let p = self.p;
        let mut lhs = Mat::<f64>::zeros(p, p);
        let mut rhs = Col::<f64>::zeros(p);
        for (m, mode) in self.modes.iter().enumerate() {
            let ph: Vec<f64> = phi.col(m).iter().copied().collect();
            let pr = self.products(lambda[m], &ph, theta);
            // (22) λ for (φ_{k+1}, θ_k): with Aφ = Kφ − λMφ, g_λ = φᵀMKφ.
            let g_lambda = dot(&pr.mphi, &pr.aphi) + lambda[m] * dot_self(&pr.mphi);
            lambda[m] = (self.inv_s2 * g_lambda + mode.w_lambda * mode.lambda_hat)
                / (self.inv_s2 * dot_self(&pr.mphi) + mode.w_lambda);
            // (23) θ for (λ_{k+1}, φ_{k+1}): g_θ = λMφ − K0φ.
            let k0phi = spmv(self.model.k0(), &ph);
            let g_theta: Vec<f64> = pr
                .mphi
                .iter()
                .zip(&k0phi)
                .map(|(mp, kp)| lambda[m] * mp - kp)
                .collect();
            for l in 0..p {
                rhs[l] += self.inv_s2 * dot(&pr.klphi[l], &g_theta);
                for q in 0..p {
                    lhs[(l, q)] += self.inv_s2 * dot(&pr.klphi[l], &pr.klphi[q]);
                }
            }
        }
        for l in 0..p {
            lhs[(l, l)] += self.prior_w[l];
            rhs[l] += self.prior_w[l] * self.prior_mean[l];
        }
        (lhs, rhs)
    }

    /// Substep (23): θ solved from its normal equations by Cholesky and projected onto the
    /// bounds (no-op without them); `None` when `lhs` is not positive definite.
    fn alternating_theta_step(&self, lhs: &Mat<f64>, rhs: &Col<f64>) -> Option<Vec<f64>> {
        let p = self.p;
        let llt = lhs.llt(Side::Lower).ok()?;
        let new: Mat<f64> = llt.solve(rhs.as_mat());
        // Projected onto the bounds (no-op without them).
        let new = self
            .bounds
            .clamp(&(0..p).map(|l| new[(l, 0)]).collect::<Vec<f64>>());
        Some(new)
    }
}
