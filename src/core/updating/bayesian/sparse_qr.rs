//! The φ substep (21) of a small model by a sparse Householder QR of
//! `C_m = [σ_c⁻¹A_m; W^{1/2}L_o]` (`A_m = K(θ) − λ_m M`): the dense path's method (QR of
//! `C_m`, never its normal matrix, whose condition number is the square of `C_m`'s), on
//! the matrix's few nonzeros per row. faer's simplicial sparse QR with a COLAMD column
//! order factors `C_m P = Q R`; `Q` is kept as its Householder reflectors, applied here
//! with the rows of `Qᵀx` beyond R's (the least-squares residual's) kept, which the
//! Schur block needs.

use faer::dyn_stack::{MemBuffer, MemStack};
use faer::sparse::linalg::SupernodalThreshold;
use faer::sparse::linalg::qr::{QrSymbolicParams, SymbolicQr, factorize_symbolic_qr};
use faer::sparse::linalg::triangular_solve::{
    solve_upper_triangular_in_place, solve_upper_triangular_transpose_in_place,
};
use faer::sparse::{SparseColMatRef, SymbolicSparseColMatRef};
use faer::{Conj, Mat, MatRef, Par};

use super::ShapeRow;
use crate::core::model::Model;

/// The symbolic QR of one mode's `C_m` (its pattern: the model's union pattern over the
/// measured rows), with its column order, and the values of the measured rows, which do
/// not depend on `(λ, θ)` (zero where `σ_c⁻¹A` goes).
pub(in crate::core::updating::bayesian) struct PhiQrSymbolic {
    symbolic: SymbolicQr<usize>,
    col_ptr: Vec<usize>,
    row_idx: Vec<usize>,
    measured_values: Vec<f64>,
}

impl PhiQrSymbolic {
    /// `None` if faer cannot analyse the pattern.
    pub(super) fn new(model: &Model, rows: &[ShapeRow]) -> Option<Self> {
        let n = model.n_dof();
        let (col_ptr, row_idx, measured_values) = pattern_of_c(model, rows);
        let sym = SymbolicSparseColMatRef::new_checked(n + rows.len(), n, &col_ptr, None, &row_idx);
        let symbolic = factorize_symbolic_qr(
            sym,
            QrSymbolicParams {
                supernodal_flop_ratio_threshold: SupernodalThreshold::FORCE_SIMPLICIAL,
                ..Default::default()
            },
        )
        .ok()?;
        Some(Self {
            symbolic,
            col_ptr,
            row_idx,
            measured_values,
        })
    }

    /// The values of `C_m` for the shifted stiffness `a` (on the union pattern): the
    /// measured rows' and `σ_c⁻¹a` at the top of each column.
    fn values(&self, model: &Model, a: &[f64], sigma_inv: f64) -> Vec<f64> {
        let pattern = model.union_pattern().pattern.symbolic();
        let mut val = self.measured_values.clone();
        for j in 0..model.n_dof() {
            let start = self.col_ptr[j];
            for (k, p) in pattern.col_range(j).enumerate() {
                val[start + k] = sigma_inv * a[p];
            }
        }
        val
    }
}

/// `C_m P = Q R` (module docs).
pub(super) struct SparsePhiFactor {
    /// Rows of `C_m` (`n + n_o`) and columns (`n`).
    m: usize,
    n: usize,
    /// Factor column `j` is column `fwd[j]` of `C_m`; `inv` the inverse.
    fwd: Vec<usize>,
    inv: Vec<usize>,
    r_col_ptr: Vec<usize>,
    r_row_idx: Vec<usize>,
    r_val: Vec<f64>,
    h_col_ptr: Vec<usize>,
    h_row_idx: Vec<usize>,
    h_val: Vec<f64>,
    tau: Vec<f64>,
    /// The row of `Qᵀx` that holds row `j` of `R`'s part (the first row of reflector `j`).
    pivot_row: Vec<usize>,
    /// The other rows: the residual part of `Qᵀx`.
    rest_rows: Vec<usize>,
}

impl SparsePhiFactor {
    /// Factors the mode's `C_m` (analysed in `analysis`) for the shifted stiffness `a`
    /// (values on the model's union pattern) and `σ_c⁻¹`. `None` if the factorization fails
    /// or `R` has a zero or non-finite pivot.
    pub(super) fn new(
        analysis: &PhiQrSymbolic,
        model: &Model,
        a: &[f64],
        sigma_inv: f64,
    ) -> Option<Self> {
        let n = model.n_dof();
        let m = analysis.symbolic.nrows();
        let val = analysis.values(model, a, sigma_inv);
        let sym =
            SymbolicSparseColMatRef::new_checked(m, n, &analysis.col_ptr, None, &analysis.row_idx);
        let c = SparseColMatRef::new(sym, &val);
        let symbolic = &analysis.symbolic;
        let mut idx = vec![0usize; symbolic.len_idx()];
        let mut values = vec![0.0; symbolic.len_val()];
        let mut mem = MemBuffer::new(
            symbolic.factorize_numeric_qr_scratch::<f64>(Par::Seq, Default::default()),
        );
        symbolic.factorize_numeric_qr(
            &mut idx,
            &mut values,
            c,
            Par::Seq,
            MemStack::new(&mut mem),
            Default::default(),
        );
        let (fwd, inv) = symbolic.col_perm().arrays();
        let (fwd, inv) = (fwd.to_vec(), inv.to_vec());
        // The simplicial layout of faer's factor: indices `[R col_ptr (n + 1) | R rows |
        // H col_ptr (n + 1) | H rows]`, values `[R | H | τ (n)]`.
        let r_col_ptr = idx[..=n].to_vec();
        let len_r = r_col_ptr[n];
        let r_row_idx = idx[n + 1..n + 1 + len_r].to_vec();
        let h_col_ptr = idx[n + 1 + len_r..n + 2 + len_r + n].to_vec();
        let len_h = h_col_ptr[n];
        let h_row_idx = idx[n + 2 + len_r + n..n + 2 + len_r + n + len_h].to_vec();
        let r_val = values[..len_r].to_vec();
        let h_val = values[len_r..len_r + len_h].to_vec();
        let tau = values[len_r + len_h..len_r + len_h + n].to_vec();
        let mut pivot_row = Vec::with_capacity(n);
        let mut is_pivot = vec![false; m];
        for j in 0..n {
            let first = *h_row_idx[h_col_ptr[j]..h_col_ptr[j + 1]].first()?;
            if is_pivot[first] {
                return None;
            }
            is_pivot[first] = true;
            pivot_row.push(first);
        }
        let rest_rows = (0..m).filter(|&i| !is_pivot[i]).collect();
        let f = Self {
            m,
            n,
            fwd,
            inv,
            r_col_ptr,
            r_row_idx,
            r_val,
            h_col_ptr,
            h_row_idx,
            h_val,
            tau,
            pivot_row,
            rest_rows,
        };
        f.pivots_are_regular().then_some(f)
    }

    /// Every diagonal entry of `R` nonzero and finite.
    fn pivots_are_regular(&self) -> bool {
        (0..self.n).all(|j| {
            let (lo, hi) = (self.r_col_ptr[j], self.r_col_ptr[j + 1]);
            self.r_row_idx[lo..hi]
                .iter()
                .zip(&self.r_val[lo..hi])
                .any(|(&i, &v)| i == j && v != 0.0 && v.is_finite())
        })
    }

    fn r(&self) -> SparseColMatRef<'_, usize, f64> {
        SparseColMatRef::new(
            SymbolicSparseColMatRef::new_unsorted_checked(
                self.n,
                self.n,
                &self.r_col_ptr,
                None,
                &self.r_row_idx,
            ),
            &self.r_val,
        )
    }

    /// `Qᵀx` for `x` (`n + n_o` rows): its first `n` rows (`R`'s part, factor order) and the
    /// others (the residual's, in no particular order: only their inner products are used).
    pub(super) fn apply_qt(&self, x: MatRef<'_, f64>) -> (Mat<f64>, Mat<f64>) {
        let k = x.ncols();
        let mut x1 = Mat::zeros(self.n, k);
        let mut x2 = Mat::zeros(self.m - self.n, k);
        let mut col = vec![0.0; self.m];
        for c in 0..k {
            col.iter_mut()
                .zip(x.col(c).iter())
                .for_each(|(a, b)| *a = *b);
            for j in 0..self.n {
                let (lo, hi) = (self.h_col_ptr[j], self.h_col_ptr[j + 1]);
                let (rows, h) = (&self.h_row_idx[lo..hi], &self.h_val[lo..hi]);
                let dot: f64 = rows.iter().zip(h).map(|(&i, v)| v * col[i]).sum();
                let s = dot / self.tau[j];
                for (&i, v) in rows.iter().zip(h) {
                    col[i] -= s * v;
                }
            }
            for (j, &i) in self.pivot_row.iter().enumerate() {
                x1[(j, c)] = col[i];
            }
            for (j, &i) in self.rest_rows.iter().enumerate() {
                x2[(j, c)] = col[i];
            }
        }
        (x1, x2)
    }

    /// `R⁻ᵀ Pᵀ e` (`e` in the model's DOF order, result in factor order).
    pub(super) fn solve_rt(&self, e: MatRef<'_, f64>) -> Mat<f64> {
        let mut y = Mat::from_fn(self.n, e.ncols(), |j, c| e[(self.fwd[j], c)]);
        solve_upper_triangular_transpose_in_place(self.r(), Conj::No, y.as_mut(), Par::Seq);
        y
    }

    /// `P R⁻¹ x` (`x` in factor order, result in the model's DOF order).
    pub(super) fn solve_r(&self, mut x: Mat<f64>) -> Mat<f64> {
        solve_upper_triangular_in_place(self.r(), Conj::No, x.as_mut(), Par::Seq);
        Mat::from_fn(self.n, x.ncols(), |i, c| x[(self.inv[i], c)])
    }
}

/// The pattern of `C_m` in compressed columns: column `j` holds `σ_c⁻¹A`'s entries (union
/// pattern rows, ascending; value 0 here) and then the measured rows' (`n + i`, ascending,
/// with their values, duplicates summed).
fn pattern_of_c(model: &Model, rows: &[ShapeRow]) -> (Vec<usize>, Vec<usize>, Vec<f64>) {
    let n = model.n_dof();
    let pattern = model.union_pattern().pattern.symbolic();
    let mut g_cols: Vec<Vec<(usize, f64)>> = vec![Vec::new(); n];
    for (i, row) in rows.iter().enumerate() {
        let sw = row.w.sqrt();
        for &(j, cj) in &row.dofs {
            match g_cols[j].last_mut() {
                Some((r, v)) if *r == n + i => *v += sw * cj,
                _ => g_cols[j].push((n + i, sw * cj)),
            }
        }
    }
    let mut col_ptr = vec![0usize; n + 1];
    let nnz = pattern.compute_nnz() + rows.len();
    let mut row_idx = Vec::with_capacity(nnz);
    let mut val = Vec::with_capacity(nnz);
    for j in 0..n {
        for &i in pattern.row_idx_of_col_raw(j) {
            row_idx.push(i);
            val.push(0.0);
        }
        for &(i, v) in &g_cols[j] {
            row_idx.push(i);
            val.push(v);
        }
        col_ptr[j + 1] = row_idx.len();
    }
    (col_ptr, row_idx, val)
}
