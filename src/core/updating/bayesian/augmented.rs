//! The sparse φ substep (21) for large models.
//!
//! Substep (21) is the least-squares problem `min_φ ‖C φ − d‖²` with
//! `C = [σ_c⁻¹ A; W^{1/2} L_o]` (`A = K(θ) − λ_m M`, `(n + n_o) × n`). The dense solver
//! factors `C` by Householder QR, which fills in completely. Here it is solved through the
//! augmented system (Björck, *Numerical Methods for Least Squares Problems*, SIAM 1996,
//! §2.5 and §7.6), which keeps `A`'s sparsity:
//!
//! ```text
//! [ αI   C ] [ s/α ]   [ b   ]          s + C u = b
//! [ Cᵀ   0 ] [ u   ] = [ c/α ]   ⇔      Cᵀ s    = c
//! ```
//!
//! so `u = N⁻¹(Cᵀb − c)` with `N = CᵀC = σ_c⁻²A² + L_oᵀWL_o`, and `s = b − Cu`. With
//! `b = d`, `c = 0`, `u` is φ*. For the Hessian of the reduced objective the same
//! factorization gives, with `b = J_y` and `c = −E` (see [`super::BayesProblem::reduced`]),
//! `u = N⁻¹(CᵀJ_y + E)` and `s = P⊥J_y − C N⁻¹E` (`P⊥ = I − C N⁻¹ Cᵀ`), from which the
//! Schur complement is `J_yᵀ s − Eᵀ u`: the large terms `J_yᵀ P J_y` cancel inside `s`,
//! which the augmented system delivers as an unknown, not as a difference. `N` itself,
//! whose condition number is the square of `C`'s, is never formed.
//!
//! The matrix (`2n + n_o` square, symmetric indefinite) is factored by faer's sparse LU
//! with partial pivoting; its symbolic analysis depends only on the pattern of `A` and the
//! measured channels, and is done once per mode. `α` is the largest entry of `W^{1/2}L_o`
//! (the data block), so both blocks of the first row are on the data's scale; one step of
//! iterative refinement follows every solve.

use std::sync::Mutex;

use faer::linalg::solvers::Solve;
use faer::sparse::linalg::solvers::{Lu, SymbolicLu};
use faer::sparse::{SparseColMat, SymbolicSparseColMat};
use faer::{Mat, MatRef};

use super::{BayesError, ShapeRow};
use crate::core::model::Model;
use crate::core::model::sparse::spmv_add;

/// The pattern of one mode's augmented matrix and its symbolic LU.
type Symbolic = (SymbolicSparseColMat<usize>, SymbolicLu<usize>);

/// Per-mode symbolic analyses of the augmented systems, made on first use.
pub(super) struct AugmentedSymbolic {
    per_mode: Mutex<Vec<Option<Symbolic>>>,
}

impl AugmentedSymbolic {
    pub fn new(n_modes: usize) -> Self {
        Self {
            per_mode: Mutex::new(vec![None; n_modes]),
        }
    }
}

/// One factored augmented system (one mode at one `(λ_m, θ)`).
pub(super) struct AugmentedFactor {
    matrix: SparseColMat<usize, f64>,
    lu: Lu<usize, f64>,
    n: usize,
    n_o: usize,
    alpha: f64,
}

/// Entries of the augmented matrix of one mode, column by column (rows ascending).
/// `a_vals` are the values of `K(θ) − λ_m M` on the model's union pattern.
fn entries(
    model: &Model,
    a_vals: &[f64],
    sigma_inv: f64,
    rows: &[ShapeRow],
    alpha: f64,
) -> (Vec<usize>, Vec<usize>, Vec<f64>) {
    let n = model.n_dof();
    let n_o = rows.len();
    let off_u = n + n_o;
    let sym = model.union_pattern().pattern.symbolic();
    // Rows of W^{1/2}L_o, each with its DOFs merged and sorted, and the same by DOF.
    let l_rows = super::shifted::weighted_rows(rows);
    let mut l_cols: Vec<Vec<(usize, f64)>> = vec![Vec::new(); n];
    for (r, d) in l_rows.iter().enumerate() {
        for &(j, v) in d {
            l_cols[j].push((r, v));
        }
    }
    let nnz = 2 * a_vals.len() + 2 * l_rows.iter().map(Vec::len).sum::<usize>() + off_u;
    let mut col_ptr = Vec::with_capacity(off_u + n + 1);
    let mut row_idx = Vec::with_capacity(nnz);
    let mut vals = Vec::with_capacity(nnz);
    col_ptr.push(0);
    let a_col = |j: usize| {
        let base = sym.col_ptr()[j];
        sym.row_idx_of_col_raw(j)
            .iter()
            .enumerate()
            .map(move |(k, &i)| (i, a_vals[base + k]))
    };
    // Columns of s₁ (the model-equation rows): αI over σ⁻¹A.
    for j in 0..n {
        row_idx.push(j);
        vals.push(alpha);
        for (i, v) in a_col(j) {
            row_idx.push(off_u + i);
            vals.push(sigma_inv * v);
        }
        col_ptr.push(row_idx.len());
    }
    // Columns of s₂ (the measured entries): αI over (W^{1/2}L_o)ᵀ.
    for (r, d) in l_rows.iter().enumerate() {
        row_idx.push(n + r);
        vals.push(alpha);
        for &(j, v) in d {
            row_idx.push(off_u + j);
            vals.push(v);
        }
        col_ptr.push(row_idx.len());
    }
    // Columns of u: C.
    for (j, lc) in l_cols.iter().enumerate() {
        for (i, v) in a_col(j) {
            row_idx.push(i);
            vals.push(sigma_inv * v);
        }
        for &(r, v) in lc {
            row_idx.push(n + r);
            vals.push(v);
        }
        col_ptr.push(row_idx.len());
    }
    (col_ptr, row_idx, vals)
}

impl AugmentedFactor {
    /// Factors the augmented system of mode `m` (`rows` its measured entries) with
    /// `a_vals = K(θ) − λ_m M` on the union pattern.
    pub fn new(
        model: &Model,
        symbolic: &AugmentedSymbolic,
        m: usize,
        a_vals: &[f64],
        sigma_inv: f64,
        rows: &[ShapeRow],
    ) -> Result<Self, BayesError> {
        let n = model.n_dof();
        let n_o = rows.len();
        let alpha = rows
            .iter()
            .flat_map(|row| row.dofs.iter().map(move |&(_, c)| (row.w.sqrt() * c).abs()))
            .fold(0.0, f64::max);
        if !(alpha > 0.0 && alpha.is_finite()) {
            return Err(BayesError::PhiSystemSingular { mode: m + 1 });
        }
        let (col_ptr, row_idx, vals) = entries(model, a_vals, sigma_inv, rows, alpha);
        let dim = 2 * n + n_o;
        let mut cache = symbolic.per_mode.lock().expect("no panic while holding it");
        // A mode's pattern depends only on the model and its measured entries: analysed
        // once per problem.
        let (sym, lu_sym) = match &cache[m] {
            Some((s, l)) => (s.clone(), l.clone()),
            None => {
                let s = SymbolicSparseColMat::new_checked(dim, dim, col_ptr, None, row_idx);
                let l = SymbolicLu::try_new(s.as_ref())
                    .map_err(|_| BayesError::PhiSystemSingular { mode: m + 1 })?;
                cache[m] = Some((s.clone(), l.clone()));
                (s, l)
            }
        };
        drop(cache);
        let matrix = SparseColMat::new(sym, vals);
        let lu = Lu::try_new_with_symbolic(lu_sym, matrix.as_ref())
            .map_err(|_| BayesError::PhiSystemSingular { mode: m + 1 })?;
        Ok(Self {
            matrix,
            lu,
            n,
            n_o,
            alpha,
        })
    }

    /// Solves `s + C u = b`, `Cᵀ s = c` for each column of `b` (`(n + n_o) × k`) and `c`
    /// (`n × k`, or `None` for zero): returns `(s, u)`.
    pub fn solve(&self, b: MatRef<'_, f64>, c: Option<MatRef<'_, f64>>) -> (Mat<f64>, Mat<f64>) {
        let (n, n_o, alpha) = (self.n, self.n_o, self.alpha);
        let k = b.ncols();
        let dim = 2 * n + n_o;
        let mut rhs = Mat::<f64>::zeros(dim, k);
        rhs.submatrix_mut(0, 0, n + n_o, k).copy_from(b);
        if let Some(c) = c {
            rhs.submatrix_mut(n + n_o, 0, n, k)
                .copy_from(c * faer::Scale(1.0 / alpha));
        }
        let mut x = self.lu.solve(&rhs);
        // One step of iterative refinement: x += Aug⁻¹ (rhs − Aug x).
        let mut res = rhs;
        let (mut xj, mut ax) = (vec![0.0; dim], vec![0.0; dim]);
        for j in 0..k {
            xj.iter_mut()
                .zip(x.col(j).iter())
                .for_each(|(a, b)| *a = *b);
            ax.iter_mut().for_each(|v| *v = 0.0);
            spmv_add(&self.matrix, &xj, 1.0, &mut ax);
            for (i, v) in ax.iter().enumerate() {
                res[(i, j)] -= v;
            }
        }
        self.lu.solve_in_place(res.as_mut());
        x += &res;
        let s = x.subrows(0, n + n_o) * faer::Scale(alpha);
        let u = x.subrows(n + n_o, n).to_owned();
        (s, u)
    }
}
