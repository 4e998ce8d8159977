//! A sparse eigen solver for the lowest modes: restarted block shift-invert Krylov
//! iteration with Rayleigh–Ritz on the pencil `(K, M)`.
//!
//! With the sparse Cholesky factorization `K = LLᵀ` (symbolic part once per model), the
//! operator `K⁻¹M` is self-adjoint in the `M`-inner product and its dominant eigenvalues
//! `1/λ` belong to the lowest modes. Each cycle builds an `M`-orthonormal basis
//! `V = [K⁻¹MX, (K⁻¹M)²X, …]` of a block Krylov subspace (block classical Gram–Schmidt
//! with reorthogonalization in the `M`-inner product), solves the projected problem
//! `(VᵀKV) u = λ u` densely, and restarts from the lowest `q` Ritz vectors (Bathe, *Finite
//! Element Procedures*, §11.6, for the subspace iteration this generalizes; Saad, *Numerical
//! Methods for Large Eigenvalue Problems*, 2nd ed., §6.3, for block Krylov projection).
//! Only `K` is factorized: `M` may be singular (massless DOFs); every basis vector lies in
//! `range(K⁻¹M)`, on which the `M`-inner product is definite.
//! The basis and its orthogonalization are in the child module `basis`.
//!
//! `KV` is never formed by multiplying with `K`: every basis vector is `K⁻¹` of a known
//! vector, so `K v = M u` follows exactly and is carried through the orthogonalization. A
//! product `K v` in double precision is only good to `ε‖|K||v|‖`, which for a frame's rigid
//! sway (where axial stiffnesses of ~1e9 N/m cancel) exceeds 1e-10 of `‖Kv‖`; carried this
//! way, the residuals of the lowest modes reach ~1e-10 like the dense solver's.
//!
//! A full solve ([`EigenSolver::solve`]) builds a space of `3q` vectors from a seeded
//! pseudo-random block of `q/4` (degree 12 in `K⁻¹M` rather than 3 for the same solves:
//! fewer restarts); restarts are single subspace-iteration steps. On the four-bay solid
//! frame (16 modes, q = 24) the first cycle leaves the wanted modes at 0.4–9e-10, a floor
//! of the carried `KV`, and the restart takes them to ≤ 4e-12. A relaxed solve
//! ([`EigenSolver::solve_relaxed`], the evaluator's: only the measured modes exact, the
//! other candidates for pairing) builds `2.5q` and stops after that cycle when its targets
//! hold (see `RELAXED_COLD_HALVES`). Starting instead from the last call's Ritz vectors (θ
//! 1 % away) was slower: they are converged enough that a Krylov block built on them is
//! dropped as dependent, and what is left converges only linearly, by subspace iteration.
//! Results are deterministic.
//!
//! Cost. On a model this size every step is memory-bound: a solve reads the factor (3.9M
//! entries on the four-bay frame) twice, a mass product reads `M`, the orthogonalization
//! reads the basis. So the solves and mass products take whole blocks
//! (`spmm_symmetric` reads `M` once per block, split by rows), a block is orthonormalized
//! within itself by SVQB (two small Gram eigenproblems and three products, not column by
//! column), `KW` is updated once with both passes' coefficients, and buffers are kept
//! between calls. `K(θ)` is factorized on the model's pattern reordered once
//! ([`Model::reordered`]): faer then does not permute the matrix on every call (45 →
//! 27.5 ms per factorization); the block solves permute their columns in and out. The
//! factorization and the triangular solves run sequentially, the block's columns split
//! over the cores: faer's parallel versions took 92–112 ms against 43–49 ms for the
//! factorization and twice as long per column for the solves. Per solve of 16 modes
//! (`cargo bench --bench solid -- eigen_solve`): 1.0–1.2 s before the blocking, 0.43–0.48 s
//! after (on a slower day), 0.31–0.34 s with the reordering and row-split mass products;
//! relaxed 0.23–0.26 s.

use faer::dyn_stack::{MemBuffer, MemStack, StackReq};
use faer::linalg::cholesky::llt::factor::LltRegularization;
use faer::linalg::solvers::SelfAdjointEigen;
use faer::sparse::SparseColMatRef;
use faer::sparse::linalg::cholesky::LltRef;
use faer::{Mat, Par, Side};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::eigen::{
    EigenPairs, EigenSolver, LOOSE_RESIDUAL, STRICT_RESIDUAL, TargetedPairs, check_mode_count,
    check_positive, sign_convention, symmetrize,
};
use super::{ModalError, col_slice};
use crate::core::model::sparse::Csc;
use crate::core::model::{Model, Reordered};

mod basis;

use basis::{Basis, Operators, SolveScratch, dot, mass_split, workers};

/// Block columns beyond the wanted modes: `max(MIN_GUARD, n_modes / 2)`.
const MIN_GUARD: usize = 8;
/// Krylov space of the first cycle, in multiples of the `q` Ritz vectors kept (built from a
/// block of `q/4` columns, see `cold_block`). On the four-bay solid frame, 16 modes: 3 took
/// 0.43–0.46 s, 4 took 0.48–0.65 s (a deeper space, the same two cycles), 2 took nine
/// cycles.
const COLD_DEPTH: usize = 3;
/// Krylov blocks of a restart within one solve: one, a subspace-iteration step. After the
/// first cycle the lowest modes are within ~1e-9 of their residual target and the carried
/// `KV` limits what a deeper space can add (a second block is dropped as dependent, see
/// `basis::DEPENDENT`: measured on the four-bay solid frame, 20 solves for one kept column).
const RESTART_DEPTH: usize = 1;
/// Krylov space of the first cycle of a relaxed solve ([`EigenSolver::solve_relaxed`]), in
/// halves of `q`: 2.5q. On the four-bay solid frame (16 modes, q = 24, θ = 1) this one
/// cycle leaves modes 1–9 at ≤ 1.4e-10, 10–16 at ≤ 1.6e-6 (the relaxed targets are 1e-7
/// and 1e-3), against 2q: mode 16 at 3.2e-3, a second cycle.
const RELAXED_COLD_HALVES: usize = 5;
/// Cycles before giving up.
const MAX_CYCLES: usize = 40;
/// Relative residual `‖Kφ − λMφ‖ / ‖Kφ‖` every wanted mode must reach (with `Kφ` carried
/// exactly, see the module documentation).
pub const RESIDUAL_TOL: f64 = 1e-10;
/// Seed of the cold-start block (fixed: results are reproducible).
const COLD_SEED: u64 = 0x626f_6c74;

/// Sparse shift-invert block Krylov solver; keeps the factor's storage and the basis
/// buffers of one model between calls (the ordering and symbolic factorization are the
/// model's, [`Model::reordered`]).
pub struct SparseEigen {
    l_values: Vec<f64>,
    /// `K(θ)`, lower triangle in the reordered numbering.
    k_values: Vec<f64>,
    /// Scratch of the numeric factorization.
    factor_mem: MemBuffer,
    /// Scratch of the triangular solves, one per worker thread.
    solve_mem: Vec<SolveScratch>,
    /// Columns `solve_mem` is sized for.
    solve_cols: usize,
    basis: Basis,
    last_cycles: usize,
}

impl SparseEigen {
    /// Buffers for the model's reordered pattern (computed here if it was not yet).
    pub fn new(model: &Model) -> Result<Self, ModalError> {
        let order = super::reordered(model)?;
        let symbolic = &order.symbolic;
        let factor_mem = MemBuffer::new(
            symbolic.factorize_numeric_llt_scratch::<f64>(Par::Seq, Default::default()),
        );
        Ok(Self {
            l_values: vec![0.0; symbolic.len_val()],
            k_values: vec![0.0; order.len()],
            factor_mem,
            solve_mem: Vec::new(),
            solve_cols: 0,
            basis: Basis::new(model.n_dof(), 0),
            last_cycles: 0,
        })
    }

    /// Cycles the last call needed.
    pub fn last_cycles(&self) -> usize {
        self.last_cycles
    }

    /// Sizes the solve scratch for blocks of up to `cols` columns over `workers()` threads.
    fn reserve_solves(&mut self, order: &Reordered, cols: usize) {
        let w = workers();
        let per = cols.div_ceil(w).max(1);
        if self.solve_cols < per || self.solve_mem.len() != w {
            let req: StackReq = order.symbolic.solve_in_place_scratch::<f64>(per, Par::Seq);
            self.solve_mem = (0..w)
                .map(|_| SolveScratch::new(req, order.fwd.len(), per))
                .collect();
            self.solve_cols = per;
        }
    }
}

/// Relative residual `‖Kφ − λMφ‖ / ‖Kφ‖` from `Kφ` and `Mφ`.
fn relative_residual(k_phi: &[f64], m_phi: &[f64], lambda: f64) -> f64 {
    let r: f64 = k_phi
        .iter()
        .zip(m_phi)
        .map(|(k, m)| (k - lambda * m).powi(2))
        .sum::<f64>()
        .sqrt();
    r / dot(k_phi, k_phi).sqrt()
}

/// What a solve must reach: relative residuals of `strict_tol` for the first `strict`
/// modes and `loose_tol` for the rest, from a first Krylov space of `cold_halves · q / 2`
/// vectors.
#[derive(Debug, Clone, Copy)]
struct Target {
    strict: usize,
    strict_tol: f64,
    loose_tol: f64,
    cold_halves: usize,
}

impl Target {
    /// The worst residual relative to its mode's target.
    fn worst(&self, residual: &[f64]) -> f64 {
        residual
            .iter()
            .enumerate()
            .map(|(j, r)| {
                r / if j < self.strict {
                    self.strict_tol
                } else {
                    self.loose_tol
                }
            })
            .fold(0.0, f64::max)
    }
}

impl EigenSolver for SparseEigen {
    /// Every mode to [`RESIDUAL_TOL`].
    fn solve(
        &mut self,
        model: &Model,
        theta: &[f64],
        n_modes: usize,
    ) -> Result<EigenPairs, ModalError> {
        let target = Target {
            strict: n_modes,
            strict_tol: RESIDUAL_TOL,
            loose_tol: RESIDUAL_TOL,
            cold_halves: 2 * COLD_DEPTH,
        };
        Ok(self.solve_to(model, theta, n_modes, target)?.0)
    }

    /// The first `strict` modes to [`STRICT_RESIDUAL`], the others to [`LOOSE_RESIDUAL`],
    /// usually in one cycle on a smaller first space (see `RELAXED_COLD_HALVES`): on the
    /// four-bay solid frame 0.25 against 0.33 s for 16 modes (`cargo bench --bench solid --
    /// eigen_solve`).
    fn solve_relaxed(
        &mut self,
        model: &Model,
        theta: &[f64],
        n_modes: usize,
        strict: usize,
    ) -> Result<Option<TargetedPairs>, ModalError> {
        let target = Target {
            strict,
            strict_tol: STRICT_RESIDUAL,
            loose_tol: LOOSE_RESIDUAL,
            cold_halves: RELAXED_COLD_HALVES,
        };
        self.solve_to(model, theta, n_modes, target).map(Some)
    }
}

impl SparseEigen {
    /// The lowest `n_modes` pairs to `target`, and each one's relative residual: `K(θ)`
    /// factorized, a cold Krylov space from a seeded block, then per cycle Rayleigh–Ritz,
    /// the residuals against `target`, and a restart from the Ritz vectors until they hold.
    fn solve_to(
        &mut self,
        model: &Model,
        theta: &[f64],
        n_modes: usize,
        target: Target,
    ) -> Result<TargetedPairs, ModalError> {
        let n = model.n_dof();
        check_mode_count(n_modes, model.n_finite_modes())?;
        let q = (n_modes + MIN_GUARD.max(n_modes / 2)).min(model.n_finite_modes());
        let order = super::reordered(model)?;
        model.shifted_stiffness_reordered(order, theta, 0.0, &mut self.k_values);
        let b = cold_block(q);
        self.reserve_solves(order, q.max(b));
        let llt = factorize(
            order,
            &self.k_values,
            &mut self.l_values,
            &mut self.factor_mem,
        )?;
        let ops = Operators {
            mass: model.mass(),
            llt,
            order,
        };
        let basis = &mut self.basis;
        let mem = &mut self.solve_mem;

        let mut rhs = cold_rhs(ops.mass, n, b);
        let mut depth = (target.cold_halves * q / (2 * b)).max(1);
        let mut worst_prev = f64::INFINITY;
        for cycle in 1..=MAX_CYCLES {
            krylov_basis(basis, ops, mem, rhs, depth, n);
            let m = basis.len;
            if m < q {
                return Err(ModalError::EigenFailed(format!(
                    "Krylov basis collapsed to {m} vectors, fewer than the {q} needed"
                )));
            }
            let ritz = Ritz::of(basis, q, n_modes)?;
            let worst = target.worst(&ritz.residual);
            // Converged, exact (the basis spans the space), or stagnated within 16× of the
            // target (rounding noise).
            let stagnated = worst <= 16.0 && worst > 0.5 * worst_prev;
            if worst <= 1.0 || stagnated || m >= n {
                check_positive(&ritz.lambda[..n_modes])?;
                self.last_cycles = cycle;
                return Ok(ritz.pairs(basis, n_modes));
            }
            worst_prev = worst;
            // Restart from the q Ritz vectors X = V u: the next block is M X = (MV) u.
            rhs = ritz.m_phi;
            depth = RESTART_DEPTH;
        }
        Err(ModalError::EigenFailed(format!(
            "shift-invert Krylov iteration did not converge in {MAX_CYCLES} cycles \
             (worst residual {worst_prev:.1e} times its target)"
        )))
    }
}

/// The numeric factorization `K = LLᵀ` of the values `k_values` on the reordered pattern,
/// into `l_values`; `K` not positive definite is [`ModalError::NotPositive`].
fn factorize<'a>(
    order: &'a Reordered,
    k_values: &[f64],
    l_values: &'a mut [f64],
    factor_mem: &mut MemBuffer,
) -> Result<LltRef<'a, usize, f64>, ModalError> {
    let k = SparseColMatRef::new(order.lower.as_ref(), k_values);
    // Sequential: faer's parallel factorization took 92–112 ms against 43–49 ms here.
    order
        .symbolic
        .factorize_numeric_llt(
            l_values,
            k,
            Side::Lower,
            LltRegularization::default(),
            Par::Seq,
            MemStack::new(factor_mem),
            Default::default(),
        )
        .map_err(|_| ModalError::NotPositive {
            index: 1,
            value: f64::NAN,
        })
}

/// The first cycle's block `M X`, from the seeded start block `X` of `b` columns.
fn cold_rhs(mass: &Csc, n: usize, b: usize) -> Mat<f64> {
    let x0 = cold_start(n, b);
    let mut rhs = Mat::zeros(n, b);
    mass_split(mass, x0.as_ref(), rhs.as_mut());
    rhs
}

/// The basis of span{K⁻¹MX, (K⁻¹M)²X, …} of up to `depth` blocks (and `n` vectors), from
/// the block `MX` in `rhs`: each block after the first solved from `M` times the last.
fn krylov_basis(
    basis: &mut Basis,
    ops: Operators<'_>,
    mem: &mut [SolveScratch],
    rhs: Mat<f64>,
    depth: usize,
    n: usize,
) {
    basis.reset((depth * rhs.ncols()).min(n));
    basis.push_solved(ops, mem, rhs);
    let mut block_start = 0;
    for _ in 1..depth {
        let block_end = basis.len;
        if block_end >= n || block_start == block_end {
            break;
        }
        let next = basis
            .mv
            .subcols(block_start, block_end - block_start)
            .to_owned();
        basis.push_solved(ops, mem, next);
        block_start = block_end;
    }
}

/// One cycle's Rayleigh–Ritz solution on the basis: the eigen decomposition of `VᵀKV`
/// (`VᵀMV = I`), its lowest `q` values, `M` times their Ritz vectors (the next block), and
/// the relative residuals of the wanted pairs.
struct Ritz {
    evd: SelfAdjointEigen<f64>,
    lambda: Vec<f64>,
    m_phi: Mat<f64>,
    residual: Vec<f64>,
}

impl Ritz {
    /// Rayleigh–Ritz, `(VᵀKV) u = λ u` on the basis, the lowest `q` pairs kept, with the
    /// residuals of the first `n_modes` from the carried `KV` and `MV`.
    fn of(basis: &Basis, q: usize, n_modes: usize) -> Result<Self, ModalError> {
        let m = basis.len;
        // Rayleigh–Ritz: (VᵀKV) u = λ u, VᵀMV = I.
        let v = basis.v.subcols(0, m);
        let mv = basis.mv.subcols(0, m);
        let kv = basis.kv.subcols(0, m);
        let mut h = v.transpose() * kv;
        symmetrize(&mut h);
        let evd = h
            .self_adjoint_eigen(Side::Lower)
            .map_err(|e| ModalError::EigenFailed(format!("{e:?}")))?;
        let u = evd.U().subcols(0, q);
        let lambda: Vec<f64> = (0..q).map(|j| evd.S().column_vector()[j]).collect();

        let k_phi = kv * u.subcols(0, n_modes);
        let m_phi = mv * u;
        let residual: Vec<f64> = (0..n_modes)
            .map(|j| {
                relative_residual(
                    col_slice(k_phi.as_ref(), j),
                    col_slice(m_phi.as_ref(), j),
                    lambda[j],
                )
            })
            .collect();
        Ok(Self {
            evd,
            lambda,
            m_phi,
            residual,
        })
    }

    /// The first `n_modes` pairs, `φ = V u` with the sign convention, and their residuals.
    fn pairs(self, basis: &Basis, n_modes: usize) -> TargetedPairs {
        let v = basis.v.subcols(0, basis.len);
        let u = self.evd.U().subcols(0, self.lambda.len());
        let mut out = v * u.subcols(0, n_modes);
        sign_convention(&mut out);
        let pairs = EigenPairs {
            lambda: self.lambda[..n_modes].to_vec(),
            phi: out,
        };
        (pairs, self.residual)
    }
}

/// Columns of the cold-start block for `q` wanted Ritz vectors. The cold cycle builds a
/// Krylov space of `COLD_DEPTH · q` vectors either way; a narrower block reaches a higher
/// polynomial degree in `K⁻¹M` with the same number of solves, and converges the lowest
/// modes further before the first restart.
fn cold_block(q: usize) -> usize {
    q.div_ceil(4).max(1)
}

/// Seeded pseudo-random start block, uniform in [−1, 1].
fn cold_start(n: usize, q: usize) -> Mat<f64> {
    let mut rng = ChaCha8Rng::seed_from_u64(COLD_SEED);
    Mat::from_fn(n, q, |_, _| rng.random_range(-1.0..1.0))
}
