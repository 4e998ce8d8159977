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
//! Small models (below [`SPARSE_FROM_DOF`] DOFs) use dense linear algebra: each φ substep
//! is a Householder QR of `C_m = [σ_c⁻¹ A_m; W^{1/2} L_o]`, and the Hessian of `F` is
//! assembled from `Qᵀ J_y` and `R⁻ᵀ E` so that the large terms of the Schur complement
//! cancel analytically, not in floating point (see [`BayesProblem::reduced`]). Large models
//! use sparse φ substeps: the same least-squares problems through their augmented systems,
//! factored by a sparse LU ([`augmented`]), which deliver the cancelled quantities directly.

use faer::dyn_stack::{MemBuffer, MemStack};
use faer::linalg::householder;
use faer::linalg::solvers::{Qr, Solve};
use faer::{Col, Conj, Mat, MatMut, Par, Side};

mod augmented;
mod covariance;
mod sweep;
mod trust;
pub use covariance::{LCurvePoint, ThresholdFree, Tsvd, l_curve_corner};
pub use sweep::{
    AlternatingRun, AutoSigma, SigmaTrial, SweepError, SweepPoint, SweepSettings,
    discrepancy_choice, log_grid, sweep_sigma,
};

use super::data::MeasuredData;
use crate::core::modal::SPARSE_FROM_DOF;
use crate::core::model::Model;
use crate::core::model::sparse::{Csc, spmv_add};
use augmented::{AugmentedFactor, AugmentedSymbolic};

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
    #[error("the Hessian of the reduced objective is not positive definite: not at a minimum")]
    NotAMinimum,
    #[error(
        "{what} is dense in the {n_dof} DOFs of the model; it is only available below {limit} DOFs"
    )]
    TooLarge {
        what: &'static str,
        n_dof: usize,
        limit: usize,
    },
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

/// Householder QR of `C_m = [σ_c⁻¹ A_m; W^{1/2} L_o]` (`(n + n_o) × n`), so that
/// `N_m = C_mᵀ C_m = RᵀR`; `Q` is kept as its reflectors and applied, never formed.
struct PhiFactor {
    qr: Qr<f64>,
}

impl PhiFactor {
    /// `rhs ← Qᵀ rhs` (rhs has `n + n_o` rows).
    fn apply_qt(&self, rhs: MatMut<'_, f64>) {
        let basis = self.qr.Q_basis();
        let coeff = self.qr.Q_coeff();
        let mut mem = MemBuffer::new(
            householder::apply_block_householder_sequence_transpose_on_the_left_in_place_scratch::<
                f64,
            >(basis.nrows(), coeff.nrows(), rhs.ncols()),
        );
        householder::apply_block_householder_sequence_transpose_on_the_left_in_place_with_conj(
            basis,
            coeff,
            Conj::No,
            rhs,
            Par::Seq,
            MemStack::new(&mut mem),
        );
    }

    /// The `n × n` triangle `R`.
    fn r(&self) -> faer::MatRef<'_, f64> {
        let n = self.qr.thin_R().ncols();
        self.qr.thin_R().submatrix(0, 0, n, n)
    }
}

/// Called after every iteration of a solver with the σ_c being solved for, the iteration
/// (counted within a continuation stage), the objective (`F` for Newton, `J_p` for the
/// alternating substeps) and θ: a progress display for the large model, whose iterations
/// take seconds.
pub type BayesProgress = Box<dyn FnMut(f64, usize, f64, &[f64]) + Send>;

/// The Bayesian MAP problem for one model and one modal set.
pub struct BayesProblem {
    progress: std::sync::Mutex<Option<BayesProgress>>,
    n: usize,
    p: usize,
    model: Model,
    /// Dense `M`, for forming `A_m` in the φ substep's QR; `None` for a large model, whose
    /// φ substeps are sparse.
    m_dense: Option<Mat<f64>>,
    /// Symbolic analyses of the sparse φ substeps (large models).
    augmented: AugmentedSymbolic,
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
    /// Sensitivity of the gradient to the data, `∂²F/∂y∂d` weighted by the data's standard
    /// deviations: `cov(d) = Σ_M`, so `B Bᵀ` with `B = ∂²F/∂y∂d Σ_M^{1/2}` is the covariance
    /// of the gradient under measurement noise (`ny × ny`).
    pub data_sensitivity: Mat<f64>,
    pub phi: Mat<f64>,
}

/// `K(θ)` for the φ substeps of one θ.
enum ThetaMatrices {
    Dense(Mat<f64>),
    /// Values on the model's union pattern.
    Sparse(Vec<f64>),
}

/// The factorization of one mode's φ substep.
enum ModeFactor {
    Dense(PhiFactor),
    Sparse(Box<AugmentedFactor>),
}

impl ModeFactor {
    /// The per-mode block of the reduced Hessian (before the factor 2) and
    /// `Z = N⁻¹(CᵀJ_y + E)`, from `J_y` (`(n + n_o) × (1 + p)`) and `E` (`n × (1 + p)`); see
    /// [`BayesProblem::reduced`].
    fn schur_block(&self, mut jy: Mat<f64>, e: Mat<f64>) -> (Mat<f64>, Mat<f64>) {
        match self {
            ModeFactor::Dense(fact) => {
                let n = e.nrows();
                fact.apply_qt(jy.as_mut());
                let x1 = jy.subrows(0, n);
                let x2 = jy.subrows(n, jy.nrows() - n);
                let mut y = e;
                fact.r()
                    .transpose()
                    .solve_lower_triangular_in_place(y.as_mut());
                let block = x2.transpose() * x2
                    - x1.transpose() * &y
                    - y.transpose() * x1
                    - y.transpose() * &y;
                let mut z = x1 + &y;
                fact.r().solve_upper_triangular_in_place(z.as_mut()); // R⁻¹(X₁ + Y)
                (block, z)
            }
            ModeFactor::Sparse(fact) => {
                // s = P⊥J_y − C N⁻¹E, u = N⁻¹(CᵀJ_y + E): J_yᵀs − Eᵀu is the block.
                let minus_e = &e * faer::Scale(-1.0);
                let (s, u) = fact.solve(jy.as_ref(), Some(minus_e.as_ref()));
                let b = jy.transpose() * &s - e.transpose() * &u;
                let block = (&b + b.transpose()) * faer::Scale(0.5);
                (block, u)
            }
        }
    }
}

/// `A x` for a sparse `A`, into a new vector.
fn spmv(a: &Csc, x: &[f64]) -> Vec<f64> {
    let mut y = vec![0.0; a.nrows()];
    spmv_add(a, x, 1.0, &mut y);
    y
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

/// Per mode at `(λ_m, φ_m, θ)`: `Mφ`, `K_lφ` and `Aφ = K(θ)φ − λ_m Mφ`, all sparse products.
struct ModeProducts {
    mphi: Vec<f64>,
    klphi: Vec<Vec<f64>>,
    aphi: Vec<f64>,
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
        let channels = model.channels();
        let mut modes = Vec::with_capacity(data.modes.len());
        for (i, mode) in data.modes.iter().enumerate() {
            let shape = mode
                .shape
                .as_ref()
                .ok_or(BayesError::NoShape { mode: i + 1 })?;
            let rows = shape
                .channels
                .iter()
                .zip(&shape.values)
                .zip(&shape.sigma)
                .map(|((&c, &psi), &sd)| ShapeRow {
                    dofs: channels[c].dofs.clone(),
                    psi,
                    w: 1.0 / (sd * sd),
                })
                .collect();
            modes.push(BayesMode {
                lambda_hat: mode.lambda,
                w_lambda: 1.0 / (mode.sigma_lambda * mode.sigma_lambda),
                rows,
            });
        }
        Ok(Self {
            n,
            p,
            m_dense: (n < SPARSE_FROM_DOF).then(|| model.mass_dense()),
            augmented: AugmentedSymbolic::new(data.modes.len()),
            progress: std::sync::Mutex::new(None),
            model: model.clone(),
            modes,
            inv_s2: 1.0 / (settings.sigma_c * settings.sigma_c),
            prior_mean: settings.prior_mean.clone(),
            prior_w: settings.prior_std.iter().map(|s| 1.0 / (s * s)).collect(),
        })
    }

    /// Uses the sparse φ substeps ([`augmented`]) whatever the model's size (they are
    /// chosen automatically from [`SPARSE_FROM_DOF`] DOFs): for comparing the two paths on
    /// a small model. The TSVD covariance needs the dense path.
    pub fn force_sparse(&mut self) {
        self.m_dense = None;
    }

    /// Reports every iteration to `f` (see [`BayesProgress`]).
    pub fn set_progress(&mut self, f: BayesProgress) {
        self.progress = std::sync::Mutex::new(Some(f));
    }

    fn report(&self, iteration: usize, value: f64, theta: &[f64]) {
        if let Ok(mut g) = self.progress.lock()
            && let Some(f) = g.as_mut()
        {
            f(self.sigma_c(), iteration, value, theta);
        }
    }

    /// Whether the φ substeps are sparse.
    pub fn is_sparse(&self) -> bool {
        self.m_dense.is_none()
    }

    pub fn n_modes(&self) -> usize {
        self.modes.len()
    }

    pub fn n_params(&self) -> usize {
        self.p
    }

    /// Number of measured scalars: one eigenvalue and the shape entries per mode.
    pub fn n_data(&self) -> usize {
        self.modes.iter().map(|m| 1 + m.rows.len()).sum()
    }

    /// MAC (26) of each most probable shape at the measured channels, `L_oφ_m`, to the
    /// measured `ψ̂_m`.
    pub fn mac_to_measured(&self, phi: &Mat<f64>) -> Vec<f64> {
        self.modes
            .iter()
            .enumerate()
            .map(|(m, mode)| {
                let lphi: Vec<f64> = mode
                    .rows
                    .iter()
                    .map(|row| row.dofs.iter().map(|&(i, c)| c * phi[(i, m)]).sum())
                    .collect();
                let psi: Vec<f64> = mode.rows.iter().map(|row| row.psi).collect();
                crate::core::modal::mac::mac(&lphi, &psi)
            })
            .collect()
    }

    /// The expected measurement misfit `e_Mᵀ Σ_M⁻¹ e_M` at the MAP when the model class is
    /// right and `σ_c → 0`: the χ² degrees of freedom `N_data − N_θ − N_m` (each φ_m's
    /// scale is free, as the scale factor (7) of mode matching).
    pub fn misfit_dof(&self) -> f64 {
        self.n_data()
            .saturating_sub(self.p + self.modes.len())
            .max(1) as f64
    }

    /// Runs the chosen solver from `λ = λ̂`, `θ = theta0`: Newton with σ_c continuation
    /// ([`Self::solve_newton_continued`]), or the paper's alternating substeps.
    pub fn solve(
        &mut self,
        solver: BayesSolver,
        theta0: &[f64],
        max_iterations: usize,
    ) -> Result<BayesResult, BayesError> {
        match solver {
            BayesSolver::Newton => self.solve_newton_continued(theta0, max_iterations),
            BayesSolver::Alternating => self.solve_alternating(theta0, max_iterations),
        }
    }

    /// The weight σ_c of the model-equation residual (14).
    pub fn sigma_c(&self) -> f64 {
        self.inv_s2.sqrt().recip()
    }

    /// Re-weights (14) for another σ_c, keeping the model, data and prior.
    pub fn set_sigma_c(&mut self, sigma_c: f64) -> Result<(), BayesError> {
        if !(sigma_c.is_finite() && sigma_c > 0.0) {
            return Err(BayesError::Setting {
                name: "σ_c",
                value: sigma_c,
            });
        }
        self.inv_s2 = 1.0 / (sigma_c * sigma_c);
        Ok(())
    }

    /// Measured eigenvalues λ̂.
    pub fn lambda_hat(&self) -> Vec<f64> {
        self.modes.iter().map(|m| m.lambda_hat).collect()
    }

    /// `M φ`, `K_l φ` and `A φ` for one mode.
    fn products(&self, lambda: f64, phi: &[f64], theta: &[f64]) -> ModeProducts {
        let mphi = spmv(self.model.mass(), phi);
        let klphi: Vec<Vec<f64>> = (0..self.p)
            .map(|l| spmv(self.model.k_param(l), phi))
            .collect();
        let mut aphi = spmv(self.model.k0(), phi);
        for (kp, &t) in klphi.iter().zip(theta) {
            aphi.iter_mut().zip(kp).for_each(|(a, k)| *a += t * k);
        }
        aphi.iter_mut()
            .zip(&mphi)
            .for_each(|(a, m)| *a -= lambda * m);
        ModeProducts { mphi, klphi, aphi }
    }

    /// `A x = K(θ)x − λ M x`.
    fn apply_a(&self, lambda: f64, theta: &[f64], x: &[f64]) -> Vec<f64> {
        let mut y = spmv(self.model.k0(), x);
        for (l, &t) in theta.iter().enumerate() {
            spmv_add(self.model.k_param(l), x, t, &mut y);
        }
        spmv_add(self.model.mass(), x, -lambda, &mut y);
        y
    }

    /// `(ψ̂ − L_oφ)ᵀ W (ψ̂ − L_oφ)` for mode `m`.
    fn shape_misfit(&self, m: usize, phi: &[f64]) -> f64 {
        self.modes[m]
            .rows
            .iter()
            .map(|row| {
                let r = row.psi - row.dofs.iter().map(|&(i, c)| c * phi[i]).sum::<f64>();
                row.w * r * r
            })
            .sum()
    }

    fn prior_term(&self, theta: &[f64]) -> f64 {
        (0..self.p)
            .map(|l| self.prior_w[l] * (theta[l] - self.prior_mean[l]).powi(2))
            .sum()
    }

    /// The terms of (14) at a state.
    pub fn objective(&self, s: &BayesState) -> ObjectiveTerms {
        let mut measurement = 0.0;
        let mut modelling = 0.0;
        for (m, mode) in self.modes.iter().enumerate() {
            let phi: Vec<f64> = s.phi.col(m).iter().copied().collect();
            let dl = mode.lambda_hat - s.lambda[m];
            measurement += mode.w_lambda * dl * dl + self.shape_misfit(m, &phi);
            modelling += dot_self(&self.apply_a(s.lambda[m], &s.theta, &phi));
        }
        let prior = self.prior_term(&s.theta);
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
        let mut g = vec![0.0; nm + n * nm + p];
        for (m, mode) in self.modes.iter().enumerate() {
            let phi: Vec<f64> = s.phi.col(m).iter().copied().collect();
            let pr = self.products(s.lambda[m], &phi, &s.theta);
            g[m] = -2.0 * mode.w_lambda * (mode.lambda_hat - s.lambda[m])
                - 2.0 * self.inv_s2 * dot(&pr.mphi, &pr.aphi);
            // ∂/∂φ: 2σ⁻² A(Aφ) − 2 L_oᵀW(ψ̂ − L_oφ).
            let a_aphi = self.apply_a(s.lambda[m], &s.theta, &pr.aphi);
            let gphi = &mut g[nm + m * n..nm + (m + 1) * n];
            for (gi, v) in gphi.iter_mut().zip(&a_aphi) {
                *gi = 2.0 * self.inv_s2 * v;
            }
            for row in &mode.rows {
                let r = row.psi - row.dofs.iter().map(|&(i, c)| c * phi[i]).sum::<f64>();
                for &(i, c) in &row.dofs {
                    gphi[i] -= 2.0 * row.w * r * c;
                }
            }
            for l in 0..p {
                g[nm + n * nm + l] += 2.0 * self.inv_s2 * dot(&pr.klphi[l], &pr.aphi);
            }
        }
        for l in 0..p {
            g[nm + n * nm + l] += 2.0 * self.prior_w[l] * (s.theta[l] - self.prior_mean[l]);
        }
        g
    }

    /// Dense `K(θ)`.
    fn stiffness(&self, theta: &[f64]) -> Mat<f64> {
        let mut k = Mat::zeros(self.n, self.n);
        self.model.stiffness_dense_into(theta, k.as_mut());
        k
    }

    /// `K(θ)` for the φ substeps at one θ: dense, or its values on the union pattern.
    fn theta_matrices(&self, theta: &[f64]) -> ThetaMatrices {
        if self.m_dense.is_some() {
            ThetaMatrices::Dense(self.stiffness(theta))
        } else {
            let mut v = vec![0.0; self.model.union_pattern().pattern.val().len()];
            self.model.shifted_stiffness_values(theta, 0.0, &mut v);
            ThetaMatrices::Sparse(v)
        }
    }

    /// The optimal `φ_m` for fixed `(λ_m, θ)`, substep (21), and its factorization. `φ_m`
    /// minimizes `‖C_m φ − [0; W^{1/2} ψ̂]‖²`, solved by Householder QR of `C_m` (dense) or
    /// through the augmented system (sparse), rather than through `N_m = C_mᵀC_m`, whose
    /// condition number (~1e14 for σ_c = 10 on the cantilever) is the square of `C_m`'s.
    fn mode_factor(
        &self,
        k: &ThetaMatrices,
        m: usize,
        lambda: f64,
    ) -> Result<(Vec<f64>, ModeFactor), BayesError> {
        let n = self.n;
        let mode = &self.modes[m];
        let no = mode.rows.len();
        let sigma_inv = self.inv_s2.sqrt();
        let mut d = Mat::<f64>::zeros(n + no, 1);
        for (i, row) in mode.rows.iter().enumerate() {
            d[(n + i, 0)] = row.w.sqrt() * row.psi;
        }
        match k {
            ThetaMatrices::Dense(k) => {
                let m_dense = self.m_dense.as_ref().expect("dense K goes with dense M");
                let mut c = Mat::zeros(n + no, n);
                c.submatrix_mut(0, 0, n, n)
                    .copy_from((k - m_dense * faer::Scale(lambda)) * faer::Scale(sigma_inv));
                for (i, row) in mode.rows.iter().enumerate() {
                    let sw = row.w.sqrt();
                    for &(j, cj) in &row.dofs {
                        c[(n + i, j)] += sw * cj;
                    }
                }
                let fact = PhiFactor { qr: c.qr() };
                let r = fact.r();
                if (0..n).any(|i| !(r[(i, i)].abs() > 0.0 && r[(i, i)].is_finite())) {
                    return Err(BayesError::PhiSystemSingular { mode: m + 1 });
                }
                fact.apply_qt(d.as_mut());
                let mut x = d.subrows(0, n).to_owned();
                r.solve_upper_triangular_in_place(x.as_mut());
                Ok((x.col(0).iter().copied().collect(), ModeFactor::Dense(fact)))
            }
            ThetaMatrices::Sparse(kv) => {
                let mut a = kv.clone();
                self.model.subtract_mass_values(lambda, &mut a);
                let fact = AugmentedFactor::new(
                    &self.model,
                    &self.augmented,
                    m,
                    &a,
                    sigma_inv,
                    &mode.rows,
                )?;
                let (_, u) = fact.solve(d.as_ref(), None);
                let phi: Vec<f64> = u.col(0).iter().copied().collect();
                if !phi.iter().all(|v| v.is_finite()) {
                    return Err(BayesError::PhiSystemSingular { mode: m + 1 });
                }
                Ok((phi, ModeFactor::Sparse(Box::new(fact))))
            }
        }
    }

    /// The optimal φ for fixed `(λ, θ)`, substep (21), every mode.
    fn phi_star(&self, lambda: &[f64], theta: &[f64]) -> Result<Mat<f64>, BayesError> {
        let k = self.theta_matrices(theta);
        let mut phi = Mat::zeros(self.n, self.modes.len());
        let cols = self.per_mode(|m| Ok(self.mode_factor(&k, m, lambda[m])?.0))?;
        for (m, ph) in cols.into_iter().enumerate() {
            phi.col_mut(m)
                .iter_mut()
                .zip(&ph)
                .for_each(|(a, b)| *a = *b);
        }
        Ok(phi)
    }

    /// The optimal φ at `(λ, θ)` (substep (21)).
    pub fn optimal_phi(&self, lambda: &[f64], theta: &[f64]) -> Result<Mat<f64>, BayesError> {
        self.phi_star(lambda, theta)
    }

    /// Reduced objective `F(λ, θ)` with its exact gradient and Hessian, the Schur complement
    /// of (16) with φ eliminated (twice the paper's `H`, which is the Hessian of `J_p/2`).
    ///
    /// Per mode, with `r_C = σ_c⁻¹ A φ` linear in `y` for fixed φ, `J_y = ∂[r_C; r_ψ]/∂y =
    /// [σ_c⁻¹(−Mφ | K_lφ); 0]`, `C = QR` and `E = [−σ_c⁻² M A φ | σ_c⁻² K_l A φ]` (the
    /// second-order coupling `Σ r_i ∂²r_i/∂φ∂y`): `J_φφ = 2CᵀC`, `J_φy = 2(CᵀJ_y + E)`,
    /// `J_yy = 2J_yᵀJ_y` (+ `2w_λ` and the prior), and with `X₁ = Q₁ᵀJ_y`, `X₂ = Q₂ᵀJ_y`,
    /// `Y = R⁻ᵀE` the Schur complement is `2[X₂ᵀX₂ − X₁ᵀY − YᵀX₁ − YᵀY]`. That is
    /// `2[J_yᵀP⊥J_y − J_yᵀCN⁻¹E − EᵀN⁻¹CᵀJ_y − EᵀN⁻¹E]`, which the sparse path evaluates as
    /// `2[J_yᵀs − Eᵀu]` from the augmented system's `s` and `u` ([`augmented`]).
    ///
    /// The data sensitivity: `∂F/∂y = ∂J_p/∂y` at `φ*` (envelope theorem) and
    /// `∂φ*/∂ψ̂ = N⁻¹L_oᵀW`, so `∂²F/∂y∂ψ̂ = J_yφ N⁻¹ L_oᵀ W = 2 (X₁ + Y)ᵀ R⁻ᵀ L_oᵀ W`;
    /// weighted by `Σ_ψ^{1/2} = W^{-1/2}` it is `2 (X₁ + Y)ᵀ R⁻ᵀ L_oᵀ W^{1/2}`. For the
    /// eigenvalues `∂²F/∂λ_m∂λ̂_m = −2 w_λm`, weighted by `σ_λ = w_λ^{-1/2}`.
    pub fn reduced(&self, lambda: &[f64], theta: &[f64]) -> Result<Reduced, BayesError> {
        let (n, nm, p) = (self.n, self.modes.len(), self.p);
        let kt = self.theta_matrices(theta);
        let parts = self.per_mode(|m| self.reduced_mode(&kt, m, lambda[m], theta))?;
        let mut phi = Mat::zeros(n, nm);
        // J_p (14) at (λ, φ*, θ), accumulated from the per-mode parts in mode order.
        let mut value = self.prior_term(theta);
        let ny = nm + p;
        let mut g = vec![0.0; ny];
        let mut h = Mat::zeros(ny, ny);
        let mut sens = Mat::zeros(ny, self.n_data());
        let mut col0 = 0;
        let idx = |m: usize, j: usize| if j == 0 { m } else { nm + j - 1 };
        for (m, (mode, part)) in self.modes.iter().zip(parts).enumerate() {
            phi.col_mut(m)
                .iter_mut()
                .zip(&part.phi)
                .for_each(|(a, b)| *a = *b);
            value += part.value;
            g[m] = part.g_lambda;
            for l in 0..p {
                g[nm + l] += part.g_theta[l];
            }
            for i in 0..=p {
                for j in 0..=p {
                    h[(idx(m, i), idx(m, j))] += 2.0 * part.block[(i, j)];
                }
            }
            h[(m, m)] += 2.0 * mode.w_lambda;
            // Data sensitivity: λ̂_m, then ψ̂_m's entries: 2 (X₁+Y)ᵀ R⁻ᵀ L_oᵀ W^{1/2}.
            sens[(m, col0)] = -2.0 * mode.w_lambda.sqrt();
            for (i, row) in mode.rows.iter().enumerate() {
                let sw = row.w.sqrt();
                for j in 0..=p {
                    let v: f64 = row.dofs.iter().map(|&(d, c)| c * part.z[(d, j)]).sum();
                    sens[(idx(m, j), col0 + 1 + i)] = 2.0 * sw * v;
                }
            }
            col0 += 1 + mode.rows.len();
        }
        for l in 0..p {
            g[nm + l] += 2.0 * self.prior_w[l] * (theta[l] - self.prior_mean[l]);
            h[(nm + l, nm + l)] += 2.0 * self.prior_w[l];
        }
        Ok(Reduced {
            value,
            gradient: g,
            hessian: h,
            data_sensitivity: sens,
            phi,
        })
    }

    /// `f(m)` for every mode, in mode order. Large models run two modes at a time: a sparse
    /// φ substep is only partly parallel inside (on the four-bay frame two at once took an
    /// evaluation from 15.0 to 7.2 s), and not more than two, as each factorization there
    /// holds ~1.9 GB (peak RSS of an update 2.6 GB one at a time, 4.5 GB two at a time).
    fn per_mode<T: Send>(
        &self,
        f: impl Fn(usize) -> Result<T, BayesError> + Sync,
    ) -> Result<Vec<T>, BayesError> {
        let nm = self.modes.len();
        if self.m_dense.is_some() || nm < 2 {
            return (0..nm).map(f).collect();
        }
        use rayon::prelude::*;
        (0..nm)
            .into_par_iter()
            .with_min_len(nm.div_ceil(MODES_AT_ONCE))
            .map(&f)
            .collect()
    }

    /// One mode's share of [`Self::reduced`]: `φ*_m`, its terms of `J_p`, of the gradient
    /// and of the Hessian (the Schur block, before the factor 2), and `Z` for the data
    /// sensitivity.
    fn reduced_mode(
        &self,
        kt: &ThetaMatrices,
        m: usize,
        lambda: f64,
        theta: &[f64],
    ) -> Result<ModePart, BayesError> {
        let (n, p) = (self.n, self.p);
        let mode = &self.modes[m];
        let s2 = self.inv_s2;
        let sig = s2.sqrt();
        let (ph, fact) = self.mode_factor(kt, m, lambda)?;
        let pr = self.products(lambda, &ph, theta);
        let dl = mode.lambda_hat - lambda;
        let value = mode.w_lambda * dl * dl + self.shape_misfit(m, &ph) + s2 * dot_self(&pr.aphi);
        let g_lambda = -2.0 * mode.w_lambda * dl - 2.0 * s2 * dot(&pr.mphi, &pr.aphi);
        let g_theta = (0..p)
            .map(|l| 2.0 * s2 * dot(&pr.klphi[l], &pr.aphi))
            .collect();
        // Hessian of F per mode (see `reduced`).
        let rows = n + mode.rows.len();
        let mut jy = Mat::zeros(rows, 1 + p);
        let mut e = Mat::zeros(n, 1 + p);
        let maphi = spmv(self.model.mass(), &pr.aphi);
        for i in 0..n {
            jy[(i, 0)] = -sig * pr.mphi[i];
            e[(i, 0)] = -s2 * maphi[i];
        }
        for l in 0..p {
            let klaphi = spmv(self.model.k_param(l), &pr.aphi);
            for i in 0..n {
                jy[(i, 1 + l)] = sig * pr.klphi[l][i];
                e[(i, 1 + l)] = s2 * klaphi[i];
            }
        }
        let (block, z) = fact.schur_block(jy, e);
        Ok(ModePart {
            phi: ph,
            value,
            g_lambda,
            g_theta,
            block,
            z,
        })
    }
}

/// One mode's share of the reduced objective, its gradient and Hessian.
struct ModePart {
    phi: Vec<f64>,
    value: f64,
    g_lambda: f64,
    g_theta: Vec<f64>,
    block: Mat<f64>,
    z: Mat<f64>,
}

/// Modes whose sparse φ substeps run at once (see [`BayesProblem::per_mode`]).
const MODES_AT_ONCE: usize = 2;

fn dot_self(a: &[f64]) -> f64 {
    dot(a, a)
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
    /// Iterations of every stage together.
    pub iterations: usize,
    pub converged: bool,
    /// Newton stopped because no step lowers `F` although the Hessian there is not
    /// positive definite: a saddle, or (the usual case) a minimum outside the admissible
    /// region `θ > 0, λ > 0`, against whose boundary the iteration came to rest. Data far
    /// noisier than σ_c allows can put the unconstrained MAP there.
    pub stuck: bool,
    pub solver: BayesSolver,
    /// The σ_c continuation that led here (Newton), last stage at the target σ_c; one
    /// stage when the cold start converged directly, empty for the alternating solver.
    pub stages: Vec<ContinuationStage>,
}

/// One Newton solve of a σ_c continuation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ContinuationStage {
    pub sigma_c: f64,
    pub iterations: usize,
    pub converged: bool,
}

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
/// Stopping rule of the alternating solver, as published: every `|Δθ_l| < 1e-9`.
pub const ALTERNATING_TOL: f64 = 1e-9;

/// When [`BayesProblem::newton`] stops.
#[derive(Debug, Clone, Copy)]
struct NewtonStop {
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
    /// A cold start of the continuation.
    const COLD: Self = Self {
        stall_probe: true,
        ..Self::FINAL
    };
    /// An intermediate warm stage of the continuation.
    const STAGE: Self = Self {
        step_tol: STAGE_STEP_TOL,
        decrement_tol: 1e-9,
        stall_probe: false,
    };
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
        let target = self.sigma_c();
        let budget = CONTINUATION_STAGE_ITERATIONS.min(max_iterations);
        let cold_budget = COLD_START_ITERATIONS.min(max_iterations);
        let mut stages = Vec::new();
        let mut used = 0;
        let finish =
            |prob: &mut Self, mut r: BayesResult, stages: Vec<ContinuationStage>, used: usize| {
                prob.inv_s2 = 1.0 / (target * target);
                r.iterations = used;
                r.stages = stages;
                r
            };
        let record = |stages: &mut Vec<ContinuationStage>, s: f64, r: &BayesResult| {
            stages.push(ContinuationStage {
                sigma_c: s,
                iterations: r.iterations,
                converged: r.converged,
            })
        };
        let lambda_hat = self.lambda_hat();
        let direct = self.newton(&lambda_hat, theta0, cold_budget, NewtonStop::COLD)?;
        used += direct.iterations;
        record(&mut stages, target, &direct);
        if direct.converged || cold_budget == max_iterations {
            // Converged, or the caller allowed no more than one stage.
            return Ok(finish(self, direct, stages, used));
        }
        // Climb until a cold start converges.
        let mut sigma = target;
        let mut good: Option<BayesResult> = None;
        for _ in 0..CONTINUATION_CLIMBS {
            sigma *= 10.0;
            if used >= max_iterations {
                break;
            }
            self.inv_s2 = 1.0 / (sigma * sigma);
            // Above the target: a stage, to the looser rule, but stall-probed.
            let stop = NewtonStop {
                stall_probe: true,
                ..NewtonStop::STAGE
            };
            let r = self.newton(
                &lambda_hat,
                theta0,
                cold_budget.min(max_iterations - used),
                stop,
            )?;
            used += r.iterations;
            record(&mut stages, sigma, &r);
            if r.converged {
                good = Some(r);
                break;
            }
        }
        // If no cold start converged up to 10^CONTINUATION_CLIMBS σ_c, or a warm stage
        // fails on the way down, the trouble is not the narrow valley of a small σ_c
        // (typically θ runs against the boundary θ > 0): carry on at the target from where
        // the first cold start stopped, with the budget left.
        let carry_on = |prob: &mut Self, mut stages: Vec<ContinuationStage>, mut used: usize| {
            prob.inv_s2 = 1.0 / (target * target);
            let more = prob.newton(
                &direct.state.lambda,
                &direct.state.theta,
                max_iterations.saturating_sub(used),
                NewtonStop::FINAL,
            )?;
            used += more.iterations;
            record(&mut stages, target, &more);
            Ok(finish(prob, more, stages, used))
        };
        let Some(mut good) = good else {
            return carry_on(self, stages, used);
        };
        // Descend with warm starts; only the last stage, at the target, converges fully.
        while sigma > target {
            if used >= max_iterations {
                // Budget spent above the target: report the last stage at the target σ_c,
                // not converged.
                self.inv_s2 = 1.0 / (target * target);
                let mut r = self.solve_newton_from(&good.state.lambda, &good.state.theta, 0)?;
                r.converged = false;
                return Ok(finish(self, r, stages, used));
            }
            let next = (sigma / CONTINUATION_RATIO).max(target);
            self.inv_s2 = 1.0 / (next * next);
            let stop = if next > target {
                NewtonStop::STAGE
            } else {
                NewtonStop::FINAL
            };
            let r = self.newton(
                &good.state.lambda,
                &good.state.theta,
                budget.min(max_iterations - used),
                stop,
            )?;
            used += r.iterations;
            record(&mut stages, next, &r);
            if !r.converged {
                return carry_on(self, stages, used);
            }
            sigma = next;
            good = r;
        }
        Ok(finish(self, good, stages, used))
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
    fn newton(
        &self,
        lambda0: &[f64],
        theta0: &[f64],
        max_iterations: usize,
        stop: NewtonStop,
    ) -> Result<BayesResult, BayesError> {
        let nm = self.modes.len();
        let mut y: Vec<f64> = lambda0.to_vec();
        y.extend_from_slice(theta0);
        let mut cur = self.reduced(&y[..nm], &y[nm..])?;
        let mut delta = TRUST_INITIAL_RADIUS;
        let mut least_mu = f64::INFINITY;
        let mut iterations = 0;
        let mut converged = false;
        let mut stuck = false;
        while iterations < max_iterations {
            if stop.stall_probe && iterations >= STALL_PROBE_ITERATIONS && least_mu >= STALL_DAMPING
            {
                break;
            }
            let ny = y.len();
            let scale_y = y.iter().fold(0.0_f64, |a, v| a.max(v.abs()));
            // Undamped Newton step for the stopping test: converged when every component is
            // below `step_tol` relative, or the predicted decrease −gᵀΔ/2 is below
            // `decrement_tol` of F (F cannot be lowered measurably any more).
            if let Ok(llt) = cur.hessian.llt(Side::Lower) {
                let g = Col::from_fn(ny, |i| -cur.gradient[i]);
                let step = llt.solve(g.as_mat());
                let decrement: f64 = 0.5 * (0..ny).map(|i| g[i] * step[(i, 0)]).sum::<f64>();
                if (0..ny)
                    .all(|i| step[(i, 0)].abs() <= stop.step_tol * y[i].abs().max(1e-12 * scale_y))
                    || decrement <= stop.decrement_tol * cur.value.abs()
                {
                    converged = true;
                    break;
                }
            }
            // Trust-region step in relative coordinates `y_i = d_i (1 + z_i)`: the region
            // `‖z‖ ≤ Δ < 1` keeps every λ and θ positive, and scales the modes' eigenvalues
            // (~1e5) and the parameters (~1) alike.
            let d: Vec<f64> = y.iter().map(|v| v.abs().max(1e-12 * scale_y)).collect();
            let h_scaled = Mat::from_fn(ny, ny, |i, j| d[i] * cur.hessian[(i, j)] * d[j]);
            let g_scaled: Vec<f64> = (0..ny).map(|i| d[i] * cur.gradient[i]).collect();
            let h_diag = (0..ny).map(|i| h_scaled[(i, i)].abs()).fold(0.0, f64::max);
            let mut accepted = false;
            while delta >= TRUST_MIN_RADIUS {
                let Some(step) = trust::trust_region_step(&h_scaled, &g_scaled, delta) else {
                    break;
                };
                let trial_y: Vec<f64> = (0..ny).map(|i| y[i] + d[i] * step.z[i]).collect();
                let length = step.z.iter().map(|v| v * v).sum::<f64>().sqrt();
                // θ > 0 and λ > 0 (K positive definite, modes of a stable structure); the
                // radius keeps them, a trial outside is treated like one that ascends.
                let trial = if trial_y.iter().all(|v| *v > 0.0) {
                    self.reduced(&trial_y[..nm], &trial_y[nm..]).ok()
                } else {
                    None
                };
                let Some(trial) = trial else {
                    delta = 0.25 * length.min(delta);
                    continue;
                };
                // Ratio of the actual to the predicted decrease.
                let rho = (cur.value - trial.value) / step.predicted;
                if trial.value < cur.value && rho > TRUST_ACCEPT {
                    if rho > 0.75 && step.on_boundary {
                        delta = (2.0 * delta).min(TRUST_MAX_RADIUS);
                    } else if rho < 0.25 {
                        delta = 0.25 * length;
                    }
                    y = trial_y;
                    cur = trial;
                    least_mu = least_mu.min(step.mu / h_diag.max(f64::MIN_POSITIVE));
                    accepted = true;
                    break;
                }
                // A rejected step whose predicted decrease F cannot even resolve: the
                // minimum is reached to F's rounding (shrinking the radius would only spend
                // evaluations on rounding noise).
                if step.predicted <= NEWTON_RESOLUTION * cur.value.abs() {
                    break;
                }
                delta = 0.25 * length.min(delta);
            }
            iterations += 1;
            self.report(iterations, cur.value, &y[nm..]);
            if !accepted {
                // No descent possible at machine precision: at the minimum if the Hessian
                // is positive definite there, otherwise stuck (a saddle or a boundary).
                converged = cur.hessian.llt(Side::Lower).is_ok();
                stuck = !converged;
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
            stuck,
            solver: BayesSolver::Newton,
            stages: Vec::new(),
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
            phi = self.phi_star(&lambda, &theta)?;
            let mut lhs = Mat::<f64>::zeros(p, p);
            let mut rhs = Col::<f64>::zeros(p);
            for (m, mode) in self.modes.iter().enumerate() {
                let ph: Vec<f64> = phi.col(m).iter().copied().collect();
                let pr = self.products(lambda[m], &ph, &theta);
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
}
