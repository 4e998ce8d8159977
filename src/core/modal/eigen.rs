//! The eigen-solver interface ([`EigenSolver`]): the eigenpairs it returns, the warm-start
//! block a tracker's solves carry from one θ to the next, and the residual targets.
//! Implementations: [`super::dense::DenseEigen`] for small models and
//! [`super::krylov::SparseEigen`] for large ones.

use faer::Mat;

use super::ModalError;
use crate::core::model::Model;

/// Modes computed beyond those asked for, so the Rayleigh–Ritz step converges the wanted
/// ones fast (error factor λ_q / λ_{q+guard+1} per step).
pub(super) const GUARD_MODES: usize = 8;

/// The lowest eigenpairs, ascending, mass-normalized.
#[derive(Debug, Clone)]
pub struct EigenPairs {
    /// Eigenvalues λ = ω², rad²/s².
    pub lambda: Vec<f64>,
    /// Mode shapes as columns (n_dof × n_modes), `φᵀ M φ = 1`.
    pub phi: Mat<f64>,
}

impl EigenPairs {
    /// Natural frequency of mode `k` in Hz.
    pub fn frequency_hz(&self, k: usize) -> f64 {
        self.lambda[k].sqrt() / (2.0 * std::f64::consts::PI)
    }
}

/// Solves `K(θ) φ = λ M φ` for the lowest modes of a model. Implementations keep their
/// factorizations and buffers between calls; a sparse shift-invert solver can implement it
/// for large models.
pub trait EigenSolver {
    /// The lowest `n_modes` eigenpairs at θ, ascending, mass-normalized.
    fn solve(
        &mut self,
        model: &Model,
        theta: &[f64],
        n_modes: usize,
    ) -> Result<EigenPairs, ModalError>;

    /// The lowest `n_modes` eigenpairs at θ of which only the first `strict` must be
    /// exact, for a fit that uses a few modes and searches the others for pairing
    /// ([`TargetedPairs`]). `None` when the solver has no cheaper way to that than
    /// [`EigenSolver::solve`] (the dense solver's is exact at once). Deterministic, like
    /// `solve`.
    fn solve_relaxed(
        &mut self,
        _model: &Model,
        _theta: &[f64],
        _n_modes: usize,
        _strict: usize,
    ) -> Result<Option<TargetedPairs>, ModalError> {
        Ok(None)
    }

    /// Turns warm starts on or off (off by default). A solver that has none ignores it.
    fn set_warm(&mut self, _on: bool) {}

    /// A warm solve from the last solve's block, when warm starts are on, a block exists
    /// and θ is near its θ ([`TargetedPairs`]). `None` when that does not hold (solve cold
    /// instead).
    fn solve_warm(
        &mut self,
        _model: &Model,
        _theta: &[f64],
        _n_modes: usize,
        _strict: usize,
    ) -> Result<Option<TargetedPairs>, ModalError> {
        Ok(None)
    }

    /// The block the next warm solve starts from.
    fn warm_block(&self) -> Option<&WarmBlock> {
        None
    }

    /// Replaces that block (a restored checkpoint).
    fn set_warm_block(&mut self, _block: Option<WarmBlock>) {}
}

/// Eigenpairs with each pair's relative residual `‖Kφ − λMφ‖ / ‖Kφ‖`, the first `strict`
/// of them below [`STRICT_RESIDUAL`] and all below [`LOOSE_RESIDUAL`]: what a warm or a
/// relaxed solve returns. The evaluator accepts it when every paired mode is below
/// `STRICT_RESIDUAL`, and solves in full otherwise.
pub type TargetedPairs = (EigenPairs, Vec<f64>);

/// Relative residual a warm-solved or relaxed-solved mode must reach when it is used for
/// the fit. The
/// eigenvector's error is about the residual (the slowest error component, along the first
/// guard mode, gives a residual of its own size) and the eigenvalue's its square: 1e-7
/// puts shapes within 1e-7 and frequencies within 1e-14 of the exact pencil, far inside
/// any measurement's uncertainty (1 % frequency CoV, 5 % NSD).
pub const STRICT_RESIDUAL: f64 = 1e-7;

/// Relative residual every warm-solved or relaxed-solved mode must reach: enough for
/// pairing by MAC
/// (MAC error about the residual squared).
pub const LOOSE_RESIDUAL: f64 = 1e-3;

/// Largest change `|ln θ_i − ln θ_i,block|` for a warm start (a factor of 2): beyond it
/// the block is too far from the new modes to converge in a few steps. Within it a tracked
/// set's 4σ jumps of its softest connections still start warm (at 0.3, 1.5 % of the lab
/// frame's healthy sets fell back to a cold solve); the residual and Sturm checks keep any
/// warm result exact.
pub(super) const WARM_MAX_LOG_CHANGE: f64 = 0.7;

/// Inverse-iteration steps a warm solve may take before giving up (and solving cold).
pub(super) const WARM_MAX_STEPS: usize = 8;

/// Steps of a warm solve before the first Rayleigh–Ritz and residual check: on the lab
/// frame the strict residuals pass after four solves in most tracked sets (each divides
/// the error of mode 9 by about λ₂₈/λ₉ ≈ 27).
pub(super) const WARM_PLAIN_STEPS: usize = 3;

/// The Ritz block of the last solve (the wanted modes and the guard modes), from which a
/// warm solve at a nearby θ starts.
#[derive(Debug, Clone, PartialEq)]
pub struct WarmBlock {
    pub theta: Vec<f64>,
    /// Modes the solve was asked for (the first columns of `x`).
    pub n_modes: usize,
    /// Ritz values, ascending.
    pub lambda: Vec<f64>,
    /// Ritz vectors (n_dof × (n_modes + guard modes)), mass-normalized.
    pub x: Mat<f64>,
}

impl WarmBlock {
    /// The eigenpairs the solve returned: the first `n_modes`, with the sign convention.
    pub fn pairs(&self) -> EigenPairs {
        let mut phi = self.x.subcols(0, self.n_modes).to_owned();
        sign_convention(&mut phi);
        EigenPairs {
            lambda: self.lambda[..self.n_modes].to_vec(),
            phi,
        }
    }
}

/// Deterministic sign: the largest-magnitude entry of each column is positive.
pub(crate) fn sign_convention(phi: &mut Mat<f64>) {
    for k in 0..phi.ncols() {
        let mut best = 0.0_f64;
        for i in 0..phi.nrows() {
            if phi[(i, k)].abs() > best.abs() {
                best = phi[(i, k)];
            }
        }
        if best < 0.0 {
            for i in 0..phi.nrows() {
                phi[(i, k)] = -phi[(i, k)];
            }
        }
    }
}

pub(crate) fn symmetrize(a: &mut Mat<f64>) {
    for i in 0..a.nrows() {
        for j in 0..i {
            let v = 0.5 * (a[(i, j)] + a[(j, i)]);
            a[(i, j)] = v;
            a[(j, i)] = v;
        }
    }
}

/// `n_modes` must not exceed the model's `n` DOFs.
pub(crate) fn check_mode_count(n_modes: usize, n: usize) -> Result<(), ModalError> {
    if n_modes > n {
        return Err(ModalError::TooManyModes {
            asked: n_modes,
            available: n,
        });
    }
    Ok(())
}

/// Every eigenvalue must be finite and positive (K(θ) positive definite).
pub(crate) fn check_positive(lambda: &[f64]) -> Result<(), ModalError> {
    match lambda.iter().position(|v| !(v.is_finite() && *v > 0.0)) {
        Some(k) => Err(ModalError::NotPositive {
            index: k + 1,
            value: lambda[k],
        }),
        None => Ok(()),
    }
}
