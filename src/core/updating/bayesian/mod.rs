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
//! Small models (below [`SPARSE_FROM_DOF`] DOFs): each φ substep is a Householder QR of
//! `C_m = [σ_c⁻¹ A_m; W^{1/2} L_o]` (sparse, [`sparse_qr`]), and the Hessian of `F` is
//! assembled from `Qᵀ J_y` and `R⁻ᵀ E` so that the large terms of the Schur complement
//! cancel analytically, not in floating point (see [`BayesProblem::reduced`]). Large models
//! use sparse φ substeps: the same least-squares problems through the sparse `LDLᵀ` of the
//! shifted stiffness `K(θ) − λ_m M` and the Woodbury identity for the rank-`n_o` data term,
//! refined against the augmented system's exact residual ([`shifted`]); where that matrix
//! is singular to working precision, the augmented system factored by a sparse LU
//! ([`augmented`]) instead.

use faer::linalg::solvers::Solve;
use faer::{Col, Mat, Side};

mod alternating;
mod augmented;
mod covariance;
mod memory;
mod newton;
mod reduced;
mod shifted;
mod sparse_qr;
mod sweep;
mod trust;
mod workflow;
pub use alternating::ALTERNATING_TOL;
pub use covariance::{LCurvePoint, ThresholdFree, Tsvd, l_curve_corner};
pub use memory::map_memory_bytes;
pub use newton::{
    COLD_START_ITERATIONS, CONTINUATION_CLIMBS, CONTINUATION_RATIO, CONTINUATION_STAGE_ITERATIONS,
    NEWTON_DECREMENT_TOL, NEWTON_RESOLUTION, NEWTON_STEP_TOL, STAGE_STEP_TOL, STALL_DAMPING,
    STALL_PROBE_ITERATIONS, TRUST_ACCEPT, TRUST_INITIAL_RADIUS, TRUST_MAX_RADIUS, TRUST_MIN_RADIUS,
};
pub use sweep::{
    AUTO_BRACKET_STEP, AUTO_BRACKET_STEP_MAX, AUTO_FIRST_TRIAL, AUTO_LOPSIDED, AUTO_MISFIT_TOL,
    AlternatingRun, AutoSigma, SigmaTrial, SweepError, SweepPoint, SweepSettings,
    discrepancy_choice, log_grid, sweep_sigma,
};
pub use workflow::{
    AUTO_SIGMA_TOL, AUTO_TRIAL_ITERATIONS, BayesOptions, BayesUpdate, Observers, SigmaChoice,
    StageOne, WorkflowError, bayesian_update, choose_sigma_c, stage_one,
};

use super::bounds::LogBounds;
use super::data::MeasuredData;
use crate::core::modal::SPARSE_FROM_DOF;
use crate::core::model::Model;
use crate::core::model::sparse::{Csc, spmv_add};
use augmented::{AugmentedFactor, AugmentedSymbolic};
pub use reduced::AUGMENTED_FALLBACK_MAX_DOF;
use shifted::ShiftedFactor;
pub use shifted::{REFINE_ACCEPT, REFINE_MAX_STEPS, REFINE_TOL};
use sparse_qr::{PhiQrSymbolic, SparsePhiFactor};

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
    #[error(
        "mode {mode}: K(θ) − λM is singular to working precision at this (λ, θ), and the \
         augmented least-squares system that would replace it is not factored above {limit} \
         DOFs (this model has {n_dof}): it would need gigabytes"
    )]
    ShiftedSingular {
        mode: usize,
        n_dof: usize,
        limit: usize,
    },
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
    /// Dense `M` of a small model, whose φ substeps are QR factorizations ([`sparse_qr`])
    /// and whose Hessian (16) can be formed for the TSVD; `None` for a large model, whose
    /// φ substeps go through the shifted stiffness ([`shifted`]).
    m_dense: Option<Mat<f64>>,
    /// Per mode, the symbolic QR of its `C_m` (the pattern depends on the mode's measured
    /// rows only), analysed on first use.
    phi_qr: Vec<std::sync::OnceLock<Option<PhiQrSymbolic>>>,
    /// Symbolic analyses of the augmented systems, the fallback of the sparse φ substeps.
    augmented: AugmentedSymbolic,
    /// Sparse φ substeps that fell back to the augmented system's LU.
    fallbacks: std::sync::atomic::AtomicUsize,
    modes: Vec<BayesMode>,
    inv_s2: f64,
    prior_mean: Vec<f64>,
    prior_w: Vec<f64>,
    /// The box θ is kept within (the model's own bounds unless [`BayesProblem::set_bounds`]).
    bounds: LogBounds,
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

/// `A x` for a sparse `A`, into a new vector.
fn spmv(a: &Csc, x: &[f64]) -> Vec<f64> {
    let mut y = vec![0.0; a.nrows()];
    spmv_add(a, x, 1.0, &mut y);
    y
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

fn dot_self(a: &[f64]) -> f64 {
    dot(a, a)
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
            phi_qr: (0..modes.len()).map(|_| Default::default()).collect(),
            fallbacks: 0.into(),
            progress: std::sync::Mutex::new(None),
            model: model.clone(),
            modes,
            inv_s2: 1.0 / (settings.sigma_c * settings.sigma_c),
            prior_mean: settings.prior_mean.clone(),
            prior_w: settings.prior_std.iter().map(|s| 1.0 / (s * s)).collect(),
            bounds: LogBounds::new(model, None),
        })
    }

    /// Keeps θ within `bounds` (as mode matching's `--bounds` with the model's own): the
    /// Newton solver holds a parameter on a bound while descent points out of the box and
    /// cuts steps at the bounds; the alternating solver projects each θ substep (23) onto
    /// the box.
    pub fn set_bounds(&mut self, bounds: LogBounds) {
        self.bounds = bounds;
    }

    /// The box θ is kept within.
    pub fn bounds(&self) -> &LogBounds {
        &self.bounds
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

    /// Sparse φ substeps solved by the augmented system's LU since this problem was set up,
    /// because the shifted stiffness was singular to working precision (see [`shifted`]).
    pub fn augmented_fallbacks(&self) -> usize {
        self.fallbacks.load(std::sync::atomic::Ordering::Relaxed)
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
