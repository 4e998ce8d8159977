//! The Bayesian MAP of Yuen et al. without mode matching, paper (10)–(14), and two ways to
//! reach it: the alternating substeps (21)–(23) as published, and a damped Newton method on
//! the reduced objective in `(λ, θ)` (φ eliminated), which reaches the same minimum in a
//! few iterations.
//!
//! Objective (14) without its constant: with `A_m = K(θ) − λ_m M`,
//! `J_p = Σ_m w_λm (λ̂_m − λ_m)² + (ψ̂_m − L_o φ_m)ᵀ W_m (ψ̂_m − L_o φ_m)
//!        + σ_c⁻² Σ_m ‖A_m φ_m‖² + (θ − θ0)ᵀ Σ_θ⁻¹ (θ − θ0)`,
//! where `Σ_M = diag(1/w)` (28) is diagonal, so the paper's `[Σ_M⁻¹]_{λφ}` blocks vanish.
//!
//! **Reduced problem.** For fixed `y = (λ, θ)` the objective is quadratic in each `φ_m`,
//! minimized by `N_m φ_m = L_oᵀ W_m ψ̂_m` with `N_m = σ_c⁻² A_m² + L_oᵀ W_m L_o` — the
//! substep (21). Let `F(y) = J_p(λ, φ*(y), θ)`. By the envelope theorem `∇F = ∂J_p/∂y` at
//! `φ*`, and `∇²F` is the Schur complement `J_yy − Σ_m J_yφm J_φmφm⁻¹ J_φmy` of the full
//! Hessian (16): Newton on `F` needs one Cholesky factorization of each `N_m` per iteration,
//! and the same Schur complement, inverted, is a θ covariance with no truncation threshold.
//!
//! The paper's substeps (22) and (23) carry two typos, corrected here from `∂J_p = 0`:
//! in (22) `σ_c⁻¹ g_λ` is `σ_c⁻² g_λ`, and in (23) `G_θᵀ g_θ` is `σ_c⁻² G_θᵀ g_θ`.
//!
//! Linear algebra is dense (models up to a few hundred DOFs): each φ substep is a
//! Householder QR of `C_m = [σ_c⁻¹ A_m; W^{1/2} L_o]`, and the Hessian of `F` is assembled
//! from `Qᵀ J_y` and `R⁻ᵀ E` so that the large terms of the Schur complement cancel
//! analytically, not in floating point (see [`BayesProblem::reduced`]). The large model
//! (issue 7) needs sparse φ-substeps.

use faer::linalg::solvers::Solve;
use faer::{Col, Mat, Side};

use super::data::MeasuredData;
use crate::core::model::Model;

/// Failures of the Bayesian solver.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum BayesError {
    #[error("mode {mode}: σ_c⁻²A² + L_oᵀWL_o is not positive definite (too few measured DOFs?)")]
    PhiSystemSingular { mode: usize },
    #[error("measured mode {mode} has no shape: the Bayesian MAP needs mode shapes")]
    NoShape { mode: usize },
    #[error("{name} must be a finite number > 0 (got {value})")]
    Setting { name: &'static str, value: f64 },
    #[error("prior has {got} entries but the model has {expected} parameters")]
    PriorLength { expected: usize, got: usize },
}

/// The weights of (14) beyond the data: `σ_c` and the prior `θ0`, `Σ_θ = diag(prior_std²)`.
#[derive(Debug, Clone, PartialEq)]
pub struct BayesSettings {
    pub sigma_c: f64,
    pub prior_mean: Vec<f64>,
    pub prior_std: Vec<f64>,
}

/// The three terms of (14) and their sum.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ObjectiveTerms {
    /// `e_Mᵀ Σ_M⁻¹ e_M`.
    pub measurement: f64,
    /// `e_Cᵀ e_C` (without the factor σ_c⁻²).
    pub modelling: f64,
    /// `e_θᵀ Σ_θ⁻¹ e_θ`.
    pub prior: f64,
    /// `J_p` = measurement + σ_c⁻² modelling + prior.
    pub total: f64,
}

/// One measured mode in the form (10) uses.
#[derive(Debug, Clone)]
struct BayesMode {
    lambda_hat: f64,
    w_lambda: f64,
    /// `L_oᵀ W ψ̂` (n).
    ltw_psi: Col<f64>,
    /// `L_oᵀ W L_o` (n × n).
    ltwl: Mat<f64>,
    /// Rows of `L_o` with the measured entries.
    rows: Vec<ShapeRow>,
}

/// One measured shape entry: its row of `L_o` (DOF, coefficient), `ψ̂_i` and weight `w_i`.
#[derive(Debug, Clone)]
struct ShapeRow {
    dofs: Vec<(usize, f64)>,
    psi: f64,
    w: f64,
}

/// Per mode: `A_m = K(θ) − λ_m M`, the full `Q` and the `n × n` triangle `R` of the QR
/// factorization of `C_m = [σ_c⁻¹ A_m; W^{1/2} L_o]` (so `N_m = C_mᵀ C_m = RᵀR`).
struct PhiFactor {
    a: Mat<f64>,
    q: Mat<f64>,
    r: Mat<f64>,
}

/// The Bayesian MAP problem for one model and one modal set.
pub struct BayesProblem {
    n: usize,
    p: usize,
    m: Mat<f64>,
    k_params: Vec<Mat<f64>>,
    k0: Mat<f64>,
    modes: Vec<BayesMode>,
    inv_s2: f64,
    prior_mean: Vec<f64>,
    prior_w: Vec<f64>,
}

/// The state `(λ, φ, θ)`.
#[derive(Debug, Clone, PartialEq)]
pub struct BayesState {
    pub lambda: Vec<f64>,
    /// `φ_m` as columns (n × N_m), on the scale of the measured shapes.
    pub phi: Mat<f64>,
    pub theta: Vec<f64>,
}

/// Reduced objective at `y = (λ, θ)`: value, gradient and Hessian (all with respect to
/// `y`, λ first), with the optimal φ.
#[derive(Debug, Clone)]
pub struct Reduced {
    pub value: f64,
    pub gradient: Vec<f64>,
    pub hessian: Mat<f64>,
    pub phi: Mat<f64>,
}

impl BayesProblem {
    /// Sets up (14) for `model` and `data` (every mode must carry a shape).
    pub fn new(
        model: &Model,
        data: &MeasuredData,
        settings: &BayesSettings,
    ) -> Result<Self, BayesError> {
        let n = model.n_dof();
        let p = model.n_params();
        if !(settings.sigma_c.is_finite() && settings.sigma_c > 0.0) {
            return Err(BayesError::Setting {
                name: "σ_c",
                value: settings.sigma_c,
            });
        }
        for v in [&settings.prior_mean, &settings.prior_std] {
            if v.len() != p {
                return Err(BayesError::PriorLength {
                    expected: p,
                    got: v.len(),
                });
            }
        }
        if let Some(&s) = settings
            .prior_std
            .iter()
            .find(|s| !(s.is_finite() && **s > 0.0))
        {
            return Err(BayesError::Setting {
                name: "prior std",
                value: s,
            });
        }
        let m = model.mass_dense();
        let mut k0 = Mat::zeros(n, n);
        model.stiffness_dense_into(&vec![0.0; p], k0.as_mut());
        let k_params = (0..p)
            .map(|l| {
                let mut unit = vec![0.0; p];
                unit[l] = 1.0;
                let mut kl = Mat::zeros(n, n);
                model.stiffness_dense_into(&unit, kl.as_mut());
                &kl - &k0
            })
            .collect();
        let channels = model.channels();
        let mut modes = Vec::with_capacity(data.modes.len());
        for (i, mode) in data.modes.iter().enumerate() {
            let shape = mode
                .shape
                .as_ref()
                .ok_or(BayesError::NoShape { mode: i + 1 })?;
            let mut ltwl = Mat::zeros(n, n);
            let mut ltw_psi = Col::zeros(n);
            let mut rows = Vec::with_capacity(shape.channels.len());
            for ((&c, &psi), &sd) in shape.channels.iter().zip(&shape.values).zip(&shape.sigma) {
                let w = 1.0 / (sd * sd);
                let dofs = channels[c].dofs.clone();
                for &(a, ca) in &dofs {
                    ltw_psi[a] += w * psi * ca;
                    for &(b, cb) in &dofs {
                        ltwl[(a, b)] += w * ca * cb;
                    }
                }
                rows.push(ShapeRow { dofs, psi, w });
            }
            modes.push(BayesMode {
                lambda_hat: mode.lambda,
                w_lambda: 1.0 / (mode.sigma_lambda * mode.sigma_lambda),
                ltw_psi,
                ltwl,
                rows,
            });
        }
        Ok(Self {
            n,
            p,
            m,
            k_params,
            k0,
            modes,
            inv_s2: 1.0 / (settings.sigma_c * settings.sigma_c),
            prior_mean: settings.prior_mean.clone(),
            prior_w: settings.prior_std.iter().map(|s| 1.0 / (s * s)).collect(),
        })
    }

    pub fn n_modes(&self) -> usize {
        self.modes.len()
    }

    pub fn n_params(&self) -> usize {
        self.p
    }

    /// Measured eigenvalues λ̂.
    pub fn lambda_hat(&self) -> Vec<f64> {
        self.modes.iter().map(|m| m.lambda_hat).collect()
    }

    fn stiffness(&self, theta: &[f64]) -> Mat<f64> {
        let mut k = self.k0.clone();
        for (kl, &t) in self.k_params.iter().zip(theta) {
            k += kl * faer::Scale(t);
        }
        k
    }

    /// `(ψ̂ − L_oφ)ᵀ W (ψ̂ − L_oφ)` for mode `m`.
    fn shape_misfit(&self, m: usize, phi: faer::ColRef<'_, f64>) -> f64 {
        self.modes[m]
            .rows
            .iter()
            .map(|row| {
                let r = row.psi - row.dofs.iter().map(|&(i, c)| c * phi[i]).sum::<f64>();
                row.w * r * r
            })
            .sum()
    }

    /// The terms of (14) at a state.
    pub fn objective(&self, s: &BayesState) -> ObjectiveTerms {
        let k = self.stiffness(&s.theta);
        let mut measurement = 0.0;
        let mut modelling = 0.0;
        for (m, mode) in self.modes.iter().enumerate() {
            let dl = mode.lambda_hat - s.lambda[m];
            measurement += mode.w_lambda * dl * dl + self.shape_misfit(m, s.phi.col(m));
            let a = &k - &self.m * faer::Scale(s.lambda[m]);
            let r = &a * s.phi.col(m);
            modelling += r.squared_norm_l2();
        }
        let prior: f64 = (0..self.p)
            .map(|l| self.prior_w[l] * (s.theta[l] - self.prior_mean[l]).powi(2))
            .sum();
        ObjectiveTerms {
            measurement,
            modelling,
            prior,
            total: measurement + self.inv_s2 * modelling + prior,
        }
    }

    /// Gradient of `J_p` with respect to `(λ, φ (column-major), θ)`.
    pub fn gradient(&self, s: &BayesState) -> Vec<f64> {
        let (n, nm, p) = (self.n, self.modes.len(), self.p);
        let k = self.stiffness(&s.theta);
        let mut g = vec![0.0; nm + n * nm + p];
        for (m, mode) in self.modes.iter().enumerate() {
            let phi = s.phi.col(m);
            let a = &k - &self.m * faer::Scale(s.lambda[m]);
            let aphi = &a * phi;
            let mphi = &self.m * phi;
            g[m] = -2.0 * mode.w_lambda * (mode.lambda_hat - s.lambda[m])
                - 2.0 * self.inv_s2 * (mphi.transpose() * &aphi);
            // ∂/∂φ: 2σ⁻² A(Aφ) − 2 L_oᵀW(ψ̂ − L_oφ) = 2σ⁻² A²φ + 2(L_oᵀWL_o φ − L_oᵀWψ̂).
            let gphi = (&a * &aphi) * faer::Scale(2.0 * self.inv_s2)
                + (&mode.ltwl * phi - &mode.ltw_psi) * faer::Scale(2.0);
            for i in 0..n {
                g[nm + m * n + i] = gphi[i];
            }
            for (l, kl) in self.k_params.iter().enumerate() {
                let klphi = kl * phi;
                g[nm + n * nm + l] += 2.0 * self.inv_s2 * (klphi.transpose() * &aphi);
            }
        }
        for l in 0..p {
            g[nm + n * nm + l] += 2.0 * self.prior_w[l] * (s.theta[l] - self.prior_mean[l]);
        }
        g
    }

    /// The optimal φ for fixed `(λ, θ)`, substep (21), and the factorizations. `φ_m`
    /// minimizes `‖C_m φ − [0; W^{1/2} ψ̂]‖²`, solved by Householder QR of `C_m` rather than
    /// through `N_m = C_mᵀC_m`, whose condition number (~1e14 for σ_c = 10 on the
    /// cantilever) is the square of `C_m`'s.
    fn phi_star(
        &self,
        lambda: &[f64],
        k: &Mat<f64>,
    ) -> Result<(Mat<f64>, Vec<PhiFactor>), BayesError> {
        let n = self.n;
        let sigma_inv = self.inv_s2.sqrt();
        let mut phi = Mat::zeros(n, self.modes.len());
        let mut facts = Vec::with_capacity(self.modes.len());
        for (m, mode) in self.modes.iter().enumerate() {
            let a = k - &self.m * faer::Scale(lambda[m]);
            let no = mode.rows.len();
            let mut c = Mat::zeros(n + no, n);
            let mut d = Col::<f64>::zeros(n + no);
            c.submatrix_mut(0, 0, n, n)
                .copy_from(&a * faer::Scale(sigma_inv));
            for (i, row) in mode.rows.iter().enumerate() {
                let sw = row.w.sqrt();
                for &(j, cj) in &row.dofs {
                    c[(n + i, j)] += sw * cj;
                }
                d[n + i] = sw * row.psi;
            }
            let qr = c.qr();
            let q = qr.compute_Q();
            let r = qr.thin_R().to_owned();
            if (0..n).any(|i| !(r[(i, i)].abs() > 0.0 && r[(i, i)].is_finite())) {
                return Err(BayesError::PhiSystemSingular { mode: m + 1 });
            }
            let mut x = q.subcols(0, n).transpose() * &d;
            r.as_ref().solve_upper_triangular_in_place(x.as_mat_mut());
            phi.col_mut(m).copy_from(&x);
            facts.push(PhiFactor { a, q, r });
        }
        Ok((phi, facts))
    }

    /// The optimal φ at `(λ, θ)` (substep (21)).
    pub fn optimal_phi(&self, lambda: &[f64], theta: &[f64]) -> Result<Mat<f64>, BayesError> {
        Ok(self.phi_star(lambda, &self.stiffness(theta))?.0)
    }

    /// Reduced objective `F(λ, θ)` with its exact gradient and Hessian, the Schur complement
    /// of (16) with φ eliminated (twice the paper's `H`, which is the Hessian of `J_p/2`).
    ///
    /// Per mode, with `r_C = σ_c⁻¹ A φ` linear in `y` for fixed φ, `J_y = ∂[r_C; r_ψ]/∂y =
    /// [σ_c⁻¹(−Mφ | K_lφ); 0]`, `C = QR` and `E = [−σ_c⁻² M A φ | σ_c⁻² K_l A φ]` (the
    /// second-order coupling `Σ r_i ∂²r_i/∂φ∂y`): `J_φφ = 2CᵀC`, `J_φy = 2(CᵀJ_y + E)`,
    /// `J_yy = 2J_yᵀJ_y` (+ `2w_λ` and the prior), and with `X₁ = Q₁ᵀJ_y`, `X₂ = Q₂ᵀJ_y`,
    /// `Y = R⁻ᵀE` the Schur complement is `2[X₂ᵀX₂ − X₁ᵀY − YᵀX₁ − YᵀY]`.
    pub fn reduced(&self, lambda: &[f64], theta: &[f64]) -> Result<Reduced, BayesError> {
        let (nm, p) = (self.modes.len(), self.p);
        let k = self.stiffness(theta);
        let (phi, facts) = self.phi_star(lambda, &k)?;
        // J_p (14) at (λ, φ*, θ), accumulated below from the per-mode products.
        let mut value: f64 = (0..p)
            .map(|l| self.prior_w[l] * (theta[l] - self.prior_mean[l]).powi(2))
            .sum();
        let ny = nm + p;
        let mut g = vec![0.0; ny];
        let mut h = Mat::zeros(ny, ny);
        let s2 = self.inv_s2;
        for (m, mode) in self.modes.iter().enumerate() {
            let a = &facts[m].a;
            let ph = phi.col(m);
            let aphi = a * ph;
            let mphi = &self.m * ph;
            let klphi: Vec<Col<f64>> = self.k_params.iter().map(|kl| kl * ph).collect();
            let dl = mode.lambda_hat - lambda[m];
            value +=
                mode.w_lambda * dl * dl + self.shape_misfit(m, ph) + s2 * aphi.squared_norm_l2();
            // Gradient.
            g[m] = -2.0 * mode.w_lambda * dl - 2.0 * s2 * (mphi.transpose() * &aphi);
            for l in 0..p {
                g[nm + l] += 2.0 * s2 * (klphi[l].transpose() * &aphi);
            }
            // Hessian of F per mode, 2[‖Q₂ᵀJ_y‖² − X₁ᵀY − YᵀX₁ − YᵀY] (module docs), with
            // J_y = [σ_c⁻¹(−Mφ | K_lφ); 0], X₁ = Q₁ᵀJ_y, Y = R⁻ᵀE,
            // E = [−σ_c⁻² M A φ | σ_c⁻² K_l A φ]. The λ_m–λ_m entry also gets 2 w_λm.
            let PhiFactor { a: _, q, r } = &facts[m];
            let n = self.n;
            let rows = q.nrows();
            let sig = s2.sqrt();
            let mut jy = Mat::zeros(rows, 1 + p);
            let mut e = Mat::zeros(n, 1 + p);
            let maphi = &self.m * &aphi;
            for i in 0..n {
                jy[(i, 0)] = -sig * mphi[i];
                e[(i, 0)] = -s2 * maphi[i];
            }
            for (l, (kl, klp)) in self.k_params.iter().zip(&klphi).enumerate() {
                let klaphi = kl * &aphi;
                for i in 0..n {
                    jy[(i, 1 + l)] = sig * klp[i];
                    e[(i, 1 + l)] = s2 * klaphi[i];
                }
            }
            let qtj = q.transpose() * &jy;
            let x1 = qtj.subrows(0, n);
            let x2 = qtj.subrows(n, rows - n);
            let mut y = e;
            r.transpose().solve_lower_triangular_in_place(y.as_mut());
            let block =
                x2.transpose() * x2 - x1.transpose() * &y - y.transpose() * x1 - y.transpose() * &y;
            let idx = |j: usize| if j == 0 { m } else { nm + j - 1 };
            for i in 0..=p {
                for j in 0..=p {
                    h[(idx(i), idx(j))] += 2.0 * block[(i, j)];
                }
            }
            h[(m, m)] += 2.0 * mode.w_lambda;
        }
        for l in 0..p {
            g[nm + l] += 2.0 * self.prior_w[l] * (theta[l] - self.prior_mean[l]);
            h[(nm + l, nm + l)] += 2.0 * self.prior_w[l];
        }
        Ok(Reduced {
            value,
            gradient: g,
            hessian: h,
            phi,
        })
    }
}

/// Which minimizer reached the MAP.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BayesSolver {
    /// Damped Newton on the reduced objective `F(λ, θ)` (default).
    Newton,
    /// The paper's alternating substeps (21)–(23).
    Alternating,
}

/// The outcome of a MAP solve.
#[derive(Debug, Clone)]
pub struct BayesResult {
    pub state: BayesState,
    pub terms: ObjectiveTerms,
    pub iterations: usize,
    pub converged: bool,
    pub solver: BayesSolver,
}

/// Stopping rule of the Newton solver: every component of the undamped step below this,
/// relative to `max(|y_i|, 1e-12·max|y|)`.
pub const NEWTON_STEP_TOL: f64 = 1e-11;
/// Stopping rule of the Newton solver: the predicted decrease of `F` relative to `F`.
pub const NEWTON_DECREMENT_TOL: f64 = 1e-14;
/// Stopping rule of the alternating solver, as published: every `|Δθ_l| < 1e-9`.
pub const ALTERNATING_TOL: f64 = 1e-9;

impl BayesProblem {
    /// Damped Newton (Levenberg–Marquardt on the exact Hessian) on `F(λ, θ)` from
    /// `λ = λ̂`, `θ = theta0`. A step is accepted when it lowers `F`; the damping `μ` scales
    /// `diag(H)` and is raised until `H + μ diag(H)` is positive definite and the step
    /// descends.
    pub fn solve_newton(
        &self,
        theta0: &[f64],
        max_iterations: usize,
    ) -> Result<BayesResult, BayesError> {
        let nm = self.modes.len();
        let mut y: Vec<f64> = self.lambda_hat();
        y.extend_from_slice(theta0);
        let mut cur = self.reduced(&y[..nm], &y[nm..])?;
        let mut mu = 1e-6;
        let mut iterations = 0;
        let mut converged = false;
        while iterations < max_iterations {
            let ny = y.len();
            let scale_y = y.iter().fold(0.0_f64, |a, v| a.max(v.abs()));
            // Undamped Newton step for the stopping test: converged when every component is
            // below NEWTON_STEP_TOL relative, or the predicted decrease −gᵀΔ/2 is below
            // NEWTON_DECREMENT_TOL of F (F cannot be lowered measurably any more).
            if let Ok(llt) = cur.hessian.llt(Side::Lower) {
                let g = Col::from_fn(ny, |i| -cur.gradient[i]);
                let step = llt.solve(g.as_mat());
                let decrement: f64 = 0.5 * (0..ny).map(|i| g[i] * step[(i, 0)]).sum::<f64>();
                if (0..ny).all(|i| {
                    step[(i, 0)].abs() <= NEWTON_STEP_TOL * y[i].abs().max(1e-12 * scale_y)
                }) || decrement <= NEWTON_DECREMENT_TOL * cur.value.abs()
                {
                    converged = true;
                    break;
                }
            }
            let mut accepted = false;
            while mu < 1e20 {
                let mut damped = cur.hessian.clone();
                let dmax = (0..ny).map(|i| damped[(i, i)].abs()).fold(0.0, f64::max);
                for i in 0..ny {
                    damped[(i, i)] += mu * cur.hessian[(i, i)].abs().max(1e-12 * dmax);
                }
                let Ok(llt) = damped.llt(Side::Lower) else {
                    mu = (mu * 10.0).max(1e-6);
                    continue;
                };
                let g = Col::from_fn(ny, |i| -cur.gradient[i]);
                let step = llt.solve(g.as_mat());
                let trial_y: Vec<f64> = (0..ny).map(|i| y[i] + step[(i, 0)]).collect();
                match self.reduced(&trial_y[..nm], &trial_y[nm..]) {
                    Ok(trial) if trial.value < cur.value => {
                        y = trial_y;
                        cur = trial;
                        mu = (mu / 10.0).max(1e-12);
                        accepted = true;
                        break;
                    }
                    _ => mu = (mu * 10.0).max(1e-6),
                }
            }
            iterations += 1;
            if !accepted {
                // No descent possible at machine precision: at the minimum.
                converged = true;
                break;
            }
        }
        let state = BayesState {
            lambda: y[..nm].to_vec(),
            phi: cur.phi,
            theta: y[nm..].to_vec(),
        };
        Ok(BayesResult {
            terms: self.objective(&state),
            state,
            iterations,
            converged,
            solver: BayesSolver::Newton,
        })
    }

    /// The paper's alternating minimization (21)–(23) from `λ = λ̂`, `θ = theta0`, until every
    /// `|Δθ_l| < 1e-9` or `max_iterations`.
    pub fn solve_alternating(
        &self,
        theta0: &[f64],
        max_iterations: usize,
    ) -> Result<BayesResult, BayesError> {
        let (n, nm, p) = (self.n, self.modes.len(), self.p);
        let mut lambda = self.lambda_hat();
        let mut theta = theta0.to_vec();
        let mut phi = Mat::zeros(n, nm);
        let mut iterations = 0;
        let mut converged = false;
        while iterations < max_iterations {
            iterations += 1;
            // (21) φ for (λ_k, θ_k).
            let k = self.stiffness(&theta);
            phi = self.phi_star(&lambda, &k)?.0;
            // (22) λ for (φ_{k+1}, θ_k).
            for (m, mode) in self.modes.iter().enumerate() {
                let ph = phi.col(m);
                let mphi = &self.m * ph;
                let kphi = &k * ph;
                let g_lambda: f64 = mphi.transpose() * &kphi;
                lambda[m] = (self.inv_s2 * g_lambda + mode.w_lambda * mode.lambda_hat)
                    / (self.inv_s2 * mphi.squared_norm_l2() + mode.w_lambda);
            }
            // (23) θ for (λ_{k+1}, φ_{k+1}).
            let mut lhs = Mat::<f64>::zeros(p, p);
            let mut rhs = Col::<f64>::zeros(p);
            for (m, &lambda_m) in lambda.iter().enumerate() {
                let ph = phi.col(m);
                let klphi: Vec<Col<f64>> = self.k_params.iter().map(|kl| kl * ph).collect();
                let g_theta = &self.m * ph * faer::Scale(lambda_m) - &self.k0 * ph;
                for l in 0..p {
                    rhs[l] += self.inv_s2 * (klphi[l].transpose() * &g_theta);
                    for q in 0..p {
                        lhs[(l, q)] += self.inv_s2 * (klphi[l].transpose() * &klphi[q]);
                    }
                }
            }
            for l in 0..p {
                lhs[(l, l)] += self.prior_w[l];
                rhs[l] += self.prior_w[l] * self.prior_mean[l];
            }
            let new: Mat<f64> = match lhs.llt(Side::Lower) {
                Ok(llt) => llt.solve(rhs.as_mat()),
                Err(_) => break,
            };
            let step = (0..p)
                .map(|l| (new[(l, 0)] - theta[l]).abs())
                .fold(0.0, f64::max);
            for (l, t) in theta.iter_mut().enumerate() {
                *t = new[(l, 0)];
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
            solver: BayesSolver::Alternating,
        })
    }
}
