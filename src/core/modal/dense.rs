//! The dense eigen solver for small models.
//!
//! [`DenseEigen`] solves `K φ = λ M φ` in its inverse form: with the Cholesky factor
//! `K = L Lᵀ`, the lowest modes are the dominant eigenvalues `μ = 1/λ` of the symmetric
//! `B = L⁻¹ M L⁻ᵀ`, `φ ∝ L⁻ᵀ z` (Golub & Van Loan, *Matrix Computations*, 4th ed., §8.7.1,
//! with the roles of the two matrices exchanged). Reducing with `K` rather than `M` matters
//! here: the frame's member-end rotations have tiny rotary mass, so `L_M⁻¹ K L_M⁻ᵀ` spans
//! ~10⁸ and its lowest eigenvectors come out with residuals near 1 (seen on the lab frame).
//! It also needs only `K` definite: a singular `M` (massless DOFs) gives `μ = 0` for the
//! infinite eigenvalues, which no solve asks for, and every iterate `K⁻¹MX` lies in
//! `range(K⁻¹M)`, where `M` is definite and the massless DOFs are those of static
//! condensation.
//! The reduction still loses a few digits to the conditioning of `K`, so the wanted modes
//! plus a few guard modes are refined by one step of block inverse iteration,
//! `X = K⁻¹ M Φ`, and a Rayleigh–Ritz solve on `span X` (Bathe, *Finite Element
//! Procedures*, §11.6), which works on `K` and `M` directly and restores residuals
//! `‖Kφ − λMφ‖/‖Kφ‖` near machine precision. Eigenvectors are mass-normalized. Only the
//! wanted eigenvectors of `B` are computed: by a Krylov–Schur iteration when they are few
//! against its size (a few hundred DOFs and up), below that by tridiagonalization and
//! inverse iteration ([`super::tridiag`]).
//!
//! **Warm solves** (a tracker's, [`EigenSolver::solve_warm`]): from the Ritz block of the
//! last solve at a nearby θ, subspace iteration with the sparse Cholesky factor of `K(θ)`
//! (three M-orthonormalized steps, then Rayleigh–Ritz steps until the residuals of the
//! modes in use are below [`STRICT_RESIDUAL`] and of the others below [`LOOSE_RESIDUAL`]),
//! then a Sturm count (inertia of `K − σM`) proving no mode slipped past the block. Any
//! failure falls back to the cold solve. Lab frame: 0.33 ms against 1.12 ms cold
//! (`cargo bench --bench update`, `lab_frame_evaluate_warm` / `lab_frame_evaluate`). The
//! factor's numeric step keeps its symbolic work ([`super::up_looking`]), and `K⁻¹` and
//! `M` are applied to the block row by row ([`super::rows`]): faer's arithmetic, the same
//! bits.

use faer::dyn_stack::{MemBuffer, MemStack};
use faer::linalg::cholesky::ldlt::factor as ldlt_factor;
use faer::linalg::cholesky::ldlt::factor::LdltRegularization;
use faer::linalg::solvers::{Llt, Solve};
use faer::sparse::SparseColMatRef;
use faer::sparse::linalg::cholesky::{SymbolicCholesky, SymbolicCholeskyRaw};
use faer::{Mat, Par, Side};

use super::ModalError;
use super::eigen::*;
use super::rows::WarmFactor;
use super::tridiag::PartialSymEvd;
use super::up_looking::{Kind, UpLooking};
use crate::core::model::Model;

/// Dense solver (for models up to a few thousand DOFs).
pub struct DenseEigen {
    m: Mat<f64>,
    k: Mat<f64>,
    partial: PartialSymEvd,
    /// Keep the Ritz block of each solve and start the next from it (see [`WarmBlock`]).
    warm: bool,
    block: Option<WarmBlock>,
    /// `K − σM` of the Sturm count: the sparse `LDLᵀ` (symbolic once, AMD ordering), or
    /// in place in a dense matrix when that symbolic factorization is supernodal.
    sturm_symbolic: SymbolicCholesky<usize>,
    sturm_up_looking: Option<UpLooking>,
    sturm_values: Vec<f64>,
    sturm_l: Vec<f64>,
    sturm_mem: MemBuffer,
    shifted: Mat<f64>,
    /// Sparse `K(θ)` on the model's union pattern and its symbolic Cholesky factorization
    /// (warm solves: a few nonzeros per row make the solves several times cheaper).
    k_values: Vec<f64>,
    k_factor: WarmFactor,
    ldlt_mem: MemBuffer,
}

impl DenseEigen {
    /// Densifies `M` once; `M` does not depend on θ. Only `K(θ)` is factorized, so `M`
    /// may be singular (massless DOFs, [`Model::massless_dofs`]).
    pub fn new(model: &Model) -> Result<Self, ModalError> {
        let m = model.mass_dense();
        let n = model.n_dof();
        let sturm_symbolic = super::union_symbolic_cholesky(model)?;
        Ok(Self {
            m,
            k: Mat::zeros(n, n),
            partial: PartialSymEvd::new(n, n),
            warm: false,
            block: None,
            sturm_l: vec![0.0; sturm_symbolic.len_val()],
            sturm_mem: MemBuffer::new(
                sturm_symbolic.factorize_numeric_ldlt_scratch::<f64>(Par::Seq, Default::default()),
            ),
            sturm_up_looking: UpLooking::new(
                &sturm_symbolic,
                model.union_pattern().pattern.symbolic(),
                Side::Lower,
            ),
            sturm_symbolic,
            sturm_values: vec![0.0; model.union_pattern().pattern.val().len()],
            shifted: Mat::zeros(n, n),
            k_values: vec![0.0; model.union_pattern().pattern.val().len()],
            k_factor: WarmFactor::new(model)?,
            ldlt_mem: MemBuffer::new(ldlt_factor::cholesky_in_place_scratch::<f64>(
                n,
                Par::Seq,
                Default::default(),
            )),
        })
    }
}

impl EigenSolver for DenseEigen {
    fn solve(
        &mut self,
        model: &Model,
        theta: &[f64],
        n_modes: usize,
    ) -> Result<EigenPairs, ModalError> {
        check_mode_count(n_modes, model.n_finite_modes())?;
        let q = (n_modes + GUARD_MODES).min(model.n_finite_modes());
        model.stiffness_dense_into(theta, self.k.as_mut());
        let llt: Llt<f64> = self
            .k
            .llt(Side::Lower)
            .map_err(|_| ModalError::NotPositive {
                index: 1,
                value: f64::NAN,
            })?;
        let l = llt.L();

        // B = L⁻¹ M L⁻ᵀ by two triangular solves; its q largest eigenpairs.
        let mut c = self.m.clone();
        l.solve_lower_triangular_in_place(c.as_mut());
        let mut b = c.transpose().to_owned();
        l.solve_lower_triangular_in_place(b.as_mut());
        let mut phi0 = top_eigenvectors(&b, q, &mut self.partial)?;
        l.transpose().solve_upper_triangular_in_place(phi0.as_mut());

        let mphi0 = model.mass() * &phi0;
        let mut solve = |b: &Mat<f64>| {
            let mut x = b.clone();
            llt.solve_in_place(x.as_mut());
            let mx = model.mass() * &x;
            (x, mx)
        };
        let RitzStep { lambda, phi: x, .. } = inverse_iteration_step(&mut solve, mphi0, 0)?;
        check_positive(&lambda[..n_modes])?;
        let block = WarmBlock {
            theta: theta.to_vec(),
            n_modes,
            lambda,
            x,
        };
        let pairs = block.pairs();
        if self.warm {
            self.block = Some(block);
        }
        Ok(pairs)
    }

    fn set_warm(&mut self, on: bool) {
        self.warm = on;
        if !on {
            self.block = None;
        }
    }

    fn warm_block(&self) -> Option<&WarmBlock> {
        self.block.as_ref()
    }

    fn set_warm_block(&mut self, block: Option<WarmBlock>) {
        self.block = block;
    }

    /// Subspace iteration from the last block: block inverse iteration and Rayleigh–Ritz
    /// steps (`inverse_iteration_step`) until the residuals hold, then a Sturm count —
    /// the inertia of `K − σM` (`LDLᵀ`, Sylvester's law) — with σ in the widest gap above
    /// the wanted modes, so that no mode slipped past the block (Ritz values bound the
    /// eigenvalues from above, so `k` Ritz values below σ and `k` negative pivots mean the
    /// lowest `k` modes are all there).
    fn solve_warm(
        &mut self,
        model: &Model,
        theta: &[f64],
        n_modes: usize,
        strict: usize,
    ) -> Result<Option<TargetedPairs>, ModalError> {
        let Some(block) = self
            .block
            .as_ref()
            .filter(|b| self.warm && starts_warm(b, theta, n_modes))
        else {
            return Ok(None);
        };
        check_mode_count(n_modes, model.n_finite_modes())?;
        model.shifted_stiffness_values(theta, 0.0, &mut self.k_values);
        if !self.k_factor.factorize(model, &self.k_values) {
            return Ok(None);
        }
        let factor = &self.k_factor;
        let mut solve = |b: &Mat<f64>| factor.solve_and_mass(model, b);
        let strict = strict.min(n_modes);
        // The first solves only advance the subspace (K⁻¹M)ᵏ span Φ, kept M-orthonormal;
        // the Rayleigh–Ritz steps that follow extract its best pairs from the same subspace
        // (the span, hence the result, is that of a Rayleigh–Ritz at every step, at a
        // fraction of the cost).
        let Some(mphi) = plain_steps(&mut solve, super::rows::mass_product(model, &block.x)) else {
            return Ok(None);
        };
        let mut residual = vec![f64::INFINITY; n_modes];
        let Some(RitzStep { lambda, phi, .. }) =
            ritz_steps(&mut solve, model, mphi, n_modes, strict, &mut residual)?
        else {
            return Ok(None);
        };
        if !self.sturm_confirms(model, theta, &lambda, n_modes) {
            return Ok(None);
        }
        self.block = Some(WarmBlock {
            theta: theta.to_vec(),
            n_modes,
            lambda,
            x: phi,
        });
        let pairs = self.block.as_ref().expect("set above").pairs();
        Ok(Some((pairs, residual)))
    }
}

/// Whether a warm solve may start from the block `b`: θ of the same length and within
/// `WARM_MAX_LOG_CHANGE` of the block's in every component, and enough columns for the
/// wanted modes and their guard modes.
fn starts_warm(b: &WarmBlock, theta: &[f64], n_modes: usize) -> bool {
    b.theta.len() == theta.len()
        && b.x.ncols() >= n_modes + GUARD_MODES.min(b.x.nrows() - n_modes)
        && b.theta
            .iter()
            .zip(theta)
            .all(|(a, t)| (t / a).ln().abs() <= WARM_MAX_LOG_CHANGE)
}

/// `B ↦ (K⁻¹ B, M K⁻¹ B)`: what each step of a solve applies to its block.
type SolveMass<'a> = dyn FnMut(&Mat<f64>) -> (Mat<f64>, Mat<f64>) + 'a;

/// The plain steps of a warm solve: `WARM_PLAIN_STEPS` block inverse iterations from
/// `M Φ` (`mphi`), each made M-orthonormal; `M X` of the last, or `None` if the block lost
/// its rank.
fn plain_steps(solve: &mut SolveMass<'_>, mut mphi: Mat<f64>) -> Option<Mat<f64>> {
    for _ in 0..WARM_PLAIN_STEPS {
        mphi = orthonormal_inverse_iteration(solve, mphi)?;
    }
    Some(mphi)
}

/// The Rayleigh–Ritz steps of a warm solve (up to `WARM_MAX_STEPS` in all), from `M Φ`
/// (`mphi`), until the residuals (into `residual`, one per wanted mode) of the first
/// `strict` modes are below [`STRICT_RESIDUAL`] and of all below [`LOOSE_RESIDUAL`]: that
/// step, or `None` if no step got there.
fn ritz_steps(
    solve: &mut SolveMass<'_>,
    model: &Model,
    mut mphi: Mat<f64>,
    n_modes: usize,
    strict: usize,
    residual: &mut [f64],
) -> Result<Option<RitzStep>, ModalError> {
    let n = model.n_dof();
    for _ in WARM_PLAIN_STEPS..WARM_MAX_STEPS {
        let step = inverse_iteration_step(solve, mphi, n_modes)?;
        relative_residuals(&step.k_phi, &step.m_phi, &step.lambda, n, residual);
        if residual[..strict].iter().all(|&r| r <= STRICT_RESIDUAL)
            && residual.iter().all(|&r| r <= LOOSE_RESIDUAL)
        {
            return Ok(Some(step));
        }
        mphi = step.m_phi;
    }
    Ok(None)
}

/// ρ_k = ‖Kφ − λMφ‖ / ‖Kφ‖ for the wanted modes (the first `residual.len()` columns of
/// `kphi` and `mphi`, `n` rows).
fn relative_residuals(
    kphi: &Mat<f64>,
    mphi: &Mat<f64>,
    lambda: &[f64],
    n: usize,
    residual: &mut [f64],
) {
    for k in 0..residual.len() {
        let (mut num, mut den) = (0.0, 0.0);
        for i in 0..n {
            num += (kphi[(i, k)] - lambda[k] * mphi[(i, k)]).powi(2);
            den += kphi[(i, k)].powi(2);
        }
        residual[k] = (num / den).sqrt();
    }
}

impl DenseEigen {
    /// The Sturm check of a warm solve: with σ in the widest gap among the guard modes of
    /// the Ritz values `lambda`, as many eigenvalues below σ as Ritz values (and the wanted
    /// ones positive). False also when there is no guard mode or the count fails.
    fn sturm_confirms(
        &mut self,
        model: &Model,
        theta: &[f64],
        lambda: &[f64],
        n_modes: usize,
    ) -> bool {
        let q = lambda.len();
        // Sturm count in the widest gap among the guard modes.
        let Some(k) = (n_modes..q)
            .max_by(|&a, &b| (lambda[a] / lambda[a - 1]).total_cmp(&(lambda[b] / lambda[b - 1])))
        else {
            return false;
        };
        let sigma = (lambda[k - 1] * lambda[k]).sqrt();
        let Some(below) = self.count_below(model, theta, sigma) else {
            return false;
        };
        below == k && check_positive(&lambda[..n_modes]).is_ok()
    }

    /// The number of eigenvalues below σ: the negative pivots of `K − σM = LDLᵀ` (Sylvester's
    /// law of inertia), for the `K(θ)` whose union-pattern values are in `self.k_values`
    /// (the warm solve's; the dense fallback builds `K(θ)` from θ). `None` if the
    /// unpivoted factorization meets a zero pivot (σ on an eigenvalue).
    fn count_below(&mut self, model: &Model, theta: &[f64], sigma: f64) -> Option<usize> {
        // Sparse when the symbolic factorization is simplicial (D is then the first entry
        // of each column of the factor); the inertia does not depend on the fill-reducing
        // permutation.
        if let SymbolicCholeskyRaw::Simplicial(simplicial) = self.sturm_symbolic.raw() {
            self.sturm_values.copy_from_slice(&self.k_values);
            model.subtract_mass_values(sigma, &mut self.sturm_values);
            let factorized = match &mut self.sturm_up_looking {
                Some(up) => up.factorize(&self.sturm_values, Kind::Ldlt, &mut self.sturm_l),
                None => self
                    .sturm_symbolic
                    .factorize_numeric_ldlt(
                        &mut self.sturm_l,
                        SparseColMatRef::new(
                            model.union_pattern().pattern.symbolic(),
                            &self.sturm_values,
                        ),
                        Side::Lower,
                        LdltRegularization::default(),
                        Par::Seq,
                        MemStack::new(&mut self.sturm_mem),
                        Default::default(),
                    )
                    .is_ok(),
            };
            if !factorized {
                return None;
            }
            let col_ptr = simplicial.col_ptr();
            let n = model.n_dof();
            return Some((0..n).filter(|&j| self.sturm_l[col_ptr[j]] < 0.0).count());
        }
        self.count_below_dense(model, theta, sigma)
    }

    /// [`DenseEigen::count_below`] by a dense `LDLᵀ`.
    fn count_below_dense(&mut self, model: &Model, theta: &[f64], sigma: f64) -> Option<usize> {
        model.stiffness_dense_into(theta, self.shifted.as_mut());
        let m = model.mass();
        let sym = m.symbolic();
        for j in 0..m.ncols() {
            for (&i, &v) in sym.row_idx_of_col_raw(j).iter().zip(m.val_of_col(j)) {
                self.shifted[(i, j)] -= sigma * v;
            }
        }
        ldlt_factor::cholesky_in_place(
            self.shifted.as_mut(),
            Default::default(),
            Par::Seq,
            MemStack::new(&mut self.ldlt_mem),
            Default::default(),
        )
        .ok()?;
        let n = self.shifted.nrows();
        Some((0..n).filter(|&i| self.shifted[(i, i)] < 0.0).count())
    }
}

/// One block inverse iteration `X = K⁻¹ M Φ0`, made M-orthonormal (columns scaled to unit
/// M-norm, then Cholesky QR in the M inner product): `M X`, all the next step needs.
/// `None` if the Gram matrix is not positive definite (the block lost its rank).
fn orthonormal_inverse_iteration(solve: &mut SolveMass<'_>, mphi0: Mat<f64>) -> Option<Mat<f64>> {
    let (x, _, mut mx) = solve_m_normalized(solve, mphi0);
    let mut g = x.transpose() * &mx;
    symmetrize(&mut g);
    let l = g.llt(Side::Lower).ok()?;
    // M X ← M X L⁻ᵀ: solve L Yᵀ = (M X)ᵀ on the transposed view, in place.
    l.L()
        .solve_lower_triangular_in_place(mx.as_mut().transpose_mut());
    Some(mx)
}

/// `X = K⁻¹ M Φ0` with its columns scaled to unit M-norm, returned with `K X` (= `M Φ0`,
/// scaled alike) and `M X`. `solve` applies `K⁻¹` and `M`; `mphi0` is `M Φ0`.
fn solve_m_normalized(
    solve: &mut SolveMass<'_>,
    mphi0: Mat<f64>,
) -> (Mat<f64>, Mat<f64>, Mat<f64>) {
    let (n, q) = (mphi0.nrows(), mphi0.ncols());
    let (mut x, mut mx) = solve(&mphi0);
    let mut kx = mphi0;
    for j in 0..q {
        let s = 1.0 / (x.col(j).transpose() * mx.col(j)).sqrt();
        for i in 0..n {
            x[(i, j)] *= s;
            kx[(i, j)] *= s;
            mx[(i, j)] *= s;
        }
    }
    (x, kx, mx)
}

/// One block inverse iteration `X = K⁻¹ M Φ0` (columns scaled to unit M-norm) and a
/// Rayleigh–Ritz solve `(Xᵀ K X) a = λ (Xᵀ M X) a` on its span: all Ritz values ascending
/// and the mass-normalized Ritz vectors `X a`, with `M X a` for all of them (the next
/// step's `M Φ0`) and `K X a` for the first `n_k` (residuals). `solve` applies `K⁻¹`
/// and `M`; `mphi0` is `M Φ0`. The products with M use its sparse form.
fn inverse_iteration_step(
    solve: &mut SolveMass<'_>,
    mphi0: Mat<f64>,
    n_k: usize,
) -> Result<RitzStep, ModalError> {
    let q = mphi0.ncols();
    let (x, kx, mx) = solve_m_normalized(solve, mphi0);
    let mut kr = x.transpose() * &kx;
    let mut mr = x.transpose() * &mx;
    symmetrize(&mut kr);
    symmetrize(&mut mr);
    let lr = mr.llt(Side::Lower).map_err(|_| {
        ModalError::EigenFailed("Rayleigh–Ritz mass is not positive definite".into())
    })?;
    let lrl = lr.L();
    lrl.solve_lower_triangular_in_place(kr.as_mut());
    let mut cr = kr.transpose().to_owned();
    lrl.solve_lower_triangular_in_place(cr.as_mut());
    symmetrize(&mut cr);
    let evr = cr
        .self_adjoint_eigen(Side::Lower)
        .map_err(|e| ModalError::EigenFailed(format!("{e:?}")))?;
    let mut a = evr.U().to_owned();
    lrl.transpose().solve_upper_triangular_in_place(a.as_mut());
    let s = evr.S().column_vector();
    Ok(RitzStep {
        lambda: (0..q).map(|k| s[k]).collect(),
        phi: &x * &a,
        k_phi: &kx * a.subcols(0, n_k.min(q)),
        m_phi: &mx * &a,
    })
}

/// Ritz values (ascending) and vectors of one [`inverse_iteration_step`], with the vectors'
/// products with `M` and (the first few) with `K`, from those of the iterate without
/// another product.
struct RitzStep {
    lambda: Vec<f64>,
    phi: Mat<f64>,
    k_phi: Mat<f64>,
    m_phi: Mat<f64>,
}

/// The eigenvectors of the `q` largest eigenvalues of the symmetric positive definite `b`,
/// by the tridiagonal reduction and the partial tridiagonal solve of [`PartialSymEvd`].
///
/// faer's matrix-free Krylov–Schur (`partial_self_adjoint_eigen`) was used here above a
/// quarter of its subspace size: cheaper per solve, but on the space frame (596 DOF) at
/// some θ its Lanczos reorthogonalization never ended. `b = L⁻¹ M L⁻ᵀ` has eigenvalues
/// `1/λ` that fall off by many orders within a few dozen, so its Krylov space turns
/// numerically invariant, the new vector's norm sinks to round-off, and the relative
/// reorthogonalization test it loops on cannot be met. The full reduction is `O(n³)` but
/// bounded: 0.03 s per `modes` of the space frame; above
/// [`super::SPARSE_FROM_DOF`] the sparse solver takes over.
fn top_eigenvectors(
    b: &Mat<f64>,
    q: usize,
    partial: &mut PartialSymEvd,
) -> Result<Mat<f64>, ModalError> {
    Ok(partial.largest(b, q)?.1)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The Sturm count of the warm solve: with σ between consecutive eigenvalues of the
    /// lab frame (from a cold solve), the number of negative pivots of `K − σM` is the
    /// number of eigenvalues below σ.
    #[test]
    fn sturm_count_is_the_number_of_eigenvalues_below_the_shift() {
        let model = crate::core::model::lab_frame();
        let theta = model.nominal_theta();
        let mut solver = DenseEigen::new(&model).unwrap();
        let pairs = solver.solve(&model, &theta, 30).unwrap();
        // The lab frame takes the sparse path; the dense one must agree.
        assert!(matches!(
            solver.sturm_symbolic.raw(),
            SymbolicCholeskyRaw::Simplicial(_)
        ));
        model.shifted_stiffness_values(&theta, 0.0, &mut solver.k_values);
        for k in [1, 5, 9, 19, 27, 29] {
            let sigma = (pairs.lambda[k - 1] * pairs.lambda[k]).sqrt();
            assert_eq!(
                solver.count_below(&model, &theta, sigma),
                Some(k),
                "σ above mode {k}"
            );
            assert_eq!(solver.count_below_dense(&model, &theta, sigma), Some(k));
        }
        assert_eq!(
            solver.count_below(&model, &theta, 0.5 * pairs.lambda[0]),
            Some(0)
        );
    }
}
