//! A block of vectors stored row by row, for the warm solves' sparse work.
//!
//! A warm solve applies `K⁻¹` (a sparse Cholesky factor `P K Pᵀ = L Lᵀ`) and `M` to a
//! block of ~30 vectors at every step. faer's sparse routines walk the block one column
//! (or four) at a time, so every nonzero of `L` or `M` costs a scattered load and store
//! per vector. Stored row by row, the `q` values of one DOF are contiguous and each
//! nonzero updates a whole row at once, a loop the compiler vectorizes.
//!
//! The arithmetic is faer's, operation for operation and in the same order for every
//! vector (forward: `x_j ← x_j · (1/l_jj)`, then `x_i −= l_ij x_j` down column `j`;
//! backward: `x_j ← (x_j − Σ l_ij x_i) · (1/l_jj)`, the sum taken up the column from
//! zero; product: `y_i += m_ij x_j` over columns `j` in order), so the results are bit
//! for bit those of `LltRef::solve_in_place_with_conj` and of `M * X`: tested below.

use faer::dyn_stack::{MemBuffer, MemStack};
use faer::sparse::SparseColMatRef;
use faer::sparse::linalg::cholesky::{LltRef, SymbolicCholesky, SymbolicCholeskyRaw};
use faer::{Conj, Mat, MatMut, MatRef, Par, Side};

use super::ModalError;
use super::up_looking::{Kind, UpLooking};
use crate::core::model::Model;

/// The sparse Cholesky factor of `K(θ)` on the model's union pattern (symbolic once,
/// [`super::union_symbolic_cholesky`]: AMD, the ordering faer's `SymbolicLlt` chooses by
/// default), applied with `M` to the warm solves' blocks.
pub(crate) struct WarmFactor {
    symbolic: SymbolicCholesky<usize>,
    /// Its numeric step with the symbolic work done once (`None`: supernodal).
    up_looking: Option<UpLooking>,
    l: Vec<f64>,
    mem: MemBuffer,
}

impl WarmFactor {
    pub(crate) fn new(model: &Model) -> Result<Self, ModalError> {
        let symbolic = super::union_symbolic_cholesky(model)?;
        Ok(Self {
            up_looking: UpLooking::new(
                &symbolic,
                model.union_pattern().pattern.symbolic(),
                Side::Lower,
            ),
            l: vec![0.0; symbolic.len_val()],
            mem: MemBuffer::new(
                symbolic.factorize_numeric_llt_scratch::<f64>(Par::Seq, Default::default()),
            ),
            symbolic,
        })
    }

    /// Factorizes `K(θ)` given by its union-pattern values; false if it is not positive
    /// definite.
    pub(crate) fn factorize(&mut self, model: &Model, k_values: &[f64]) -> bool {
        if let Some(up) = &mut self.up_looking {
            return up.factorize(k_values, Kind::Llt, &mut self.l);
        }
        let k = SparseColMatRef::new(model.union_pattern().pattern.symbolic(), k_values);
        self.symbolic
            .factorize_numeric_llt(
                &mut self.l,
                k,
                Side::Lower,
                Default::default(),
                Par::Seq,
                MemStack::new(&mut self.mem),
                Default::default(),
            )
            .is_ok()
    }

    /// `X = K⁻¹ B` and `M X` for the `K(θ)` last factorized: row-wise when the factor is
    /// simplicial (small models), faer's supernodal solve otherwise.
    pub(crate) fn solve_and_mass(&self, model: &Model, b: &Mat<f64>) -> (Mat<f64>, Mat<f64>) {
        let (SymbolicCholeskyRaw::Simplicial(simplicial), Some(perm)) =
            (self.symbolic.raw(), self.symbolic.perm())
        else {
            let mut x = b.clone();
            let mut mem = MemBuffer::new(
                self.symbolic
                    .solve_in_place_scratch::<f64>(b.ncols(), Par::Seq),
            );
            LltRef::new(&self.symbolic, &self.l).solve_in_place_with_conj(
                Conj::No,
                x.as_mut(),
                Par::Seq,
                MemStack::new(&mut mem),
            );
            let mx = model.mass() * &x;
            return (x, mx);
        };
        let (fwd, inv) = perm.arrays();
        let l = SparseColMatRef::new(simplicial.factor(), &self.l);
        let y = Rows::gather(b.as_ref(), Some(fwd));
        let (x, mx) = solve_and_mass_rows(y, l, inv, model.mass().as_ref());
        (x.to_mat(), mx.to_mat())
    }
}

/// `M X` row-wise: bit for bit faer's `M * X` (module docs), without its column-by-column
/// walk of the sparse `M`; with AVX2 where the processor has it.
pub(crate) fn mass_product(model: &Model, x: &Mat<f64>) -> Mat<f64> {
    let m = model.mass().as_ref();
    let rows = Rows::gather(x.as_ref(), None);
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the processor has AVX2, checked just above.
        return unsafe { product_avx2(&rows, m) }.to_mat();
    }
    rows.product(m).to_mat()
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn product_avx2(rows: &Rows, m: SparseColMatRef<'_, usize, f64>) -> Rows {
    rows.product(m)
}

/// `X ← L⁻ᵀ D⁻¹ L⁻¹ X` in place for the simplicial `LDLᵀ` factor `l` of an unpermuted
/// matrix (Nelson's solves): faer's `SimplicialLdltRef` solve, row-wise.
pub(crate) fn solve_ldlt_in_place(l: SparseColMatRef<'_, usize, f64>, x: MatMut<'_, f64>) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the processor has AVX2, checked just above.
        return unsafe { solve_ldlt_avx2(l, x) };
    }
    solve_ldlt_steps(l, x)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn solve_ldlt_avx2(l: SparseColMatRef<'_, usize, f64>, x: MatMut<'_, f64>) {
    solve_ldlt_steps(l, x)
}

#[inline(always)]
fn solve_ldlt_steps(l: SparseColMatRef<'_, usize, f64>, x: MatMut<'_, f64>) {
    let mut y = Rows::gather(x.as_ref(), None);
    y.solve_unit_lower(l);
    y.solve_scaled_lower_transpose(l);
    y.scatter_into(x);
}

/// `X = Pᵀ L⁻ᵀ L⁻¹ Y` (rows `inv` of the solution) and `M X`, row-wise; with AVX2 where
/// the processor has it (multiplications and additions as without it: no fused
/// multiply-add, so the same bits).
fn solve_and_mass_rows(
    y: Rows,
    l: SparseColMatRef<'_, usize, f64>,
    inv: &[usize],
    m: SparseColMatRef<'_, usize, f64>,
) -> (Rows, Rows) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the processor has AVX2, checked just above.
        return unsafe { solve_and_mass_avx2(y, l, inv, m) };
    }
    solve_and_mass_steps(y, l, inv, m)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn solve_and_mass_avx2(
    y: Rows,
    l: SparseColMatRef<'_, usize, f64>,
    inv: &[usize],
    m: SparseColMatRef<'_, usize, f64>,
) -> (Rows, Rows) {
    solve_and_mass_steps(y, l, inv, m)
}

#[inline(always)]
fn solve_and_mass_steps(
    mut y: Rows,
    l: SparseColMatRef<'_, usize, f64>,
    inv: &[usize],
    m: SparseColMatRef<'_, usize, f64>,
) -> (Rows, Rows) {
    y.solve_lower(l);
    y.solve_lower_transpose(l);
    let x = y.permuted(inv);
    let mx = x.product(m);
    (x, mx)
}

/// `n` rows of `q` values each, row `i` at `data[i q .. (i + 1) q]`: `width` vectors,
/// padded with zero columns to a multiple of four, so that the row updates run in whole
/// AVX2 lanes (a padding column stays zero: every update of it adds a product with zero).
pub(crate) struct Rows {
    q: usize,
    width: usize,
    data: Vec<f64>,
}

impl Rows {
    /// The rows of `a`, row `i` of the result being row `order[i]` of `a` (all rows in
    /// order when `order` is `None`).
    pub(crate) fn gather(a: MatRef<'_, f64>, order: Option<&[usize]>) -> Self {
        let (n, q) = (a.nrows(), a.ncols());
        // Row after row into the capacity, each from the columns' slices (filling a zeroed
        // block column by column cost four times as much).
        let cols: Vec<&[f64]> = (0..q)
            .map(|c| {
                a.col(c)
                    .try_as_col_major()
                    .expect("the blocks' columns are contiguous")
                    .as_slice()
            })
            .collect();
        let width = q;
        let q = width.next_multiple_of(4);
        let mut data = Vec::with_capacity(n * q);
        let mut push_row = |i: usize| {
            data.extend(cols.iter().map(|col| col[i]));
            data.extend(std::iter::repeat_n(0.0, q - width));
        };
        match order {
            Some(o) => o.iter().for_each(|&i| push_row(i)),
            None => (0..n).for_each(push_row),
        }
        Self { q, width, data }
    }

    /// These rows permuted: row `i` of the result is row `order[i]` of these.
    #[inline(always)]
    pub(crate) fn permuted(&self, order: &[usize]) -> Self {
        let q = self.q;
        let mut data = Vec::with_capacity(self.data.len());
        for &o in order {
            data.extend_from_slice(&self.data[o * q..(o + 1) * q]);
        }
        Self {
            q,
            width: self.width,
            data,
        }
    }

    /// As a column-major matrix.
    pub(crate) fn to_mat(&self) -> Mat<f64> {
        let q = self.q;
        let n = self.data.len() / q.max(1);
        Mat::from_fn(n, self.width, |i, c| self.data[i * q + c])
    }

    /// Row `i`.
    #[inline(always)]
    fn row(&self, i: usize) -> &[f64] {
        &self.data[i * self.q..(i + 1) * self.q]
    }

    /// Rows `j` (shared) and `i` (mutable), `j < i`.
    #[inline(always)]
    fn pair_mut(&mut self, j: usize, i: usize) -> (&[f64], &mut [f64]) {
        debug_assert!(j < i);
        let q = self.q;
        let (head, tail) = self.data.split_at_mut(i * q);
        (&head[j * q..(j + 1) * q], &mut tail[..q])
    }

    /// `X ← L⁻¹ X` for the lower-triangular `l`, the diagonal first in each column.
    #[inline(always)]
    pub(crate) fn solve_lower(&mut self, l: SparseColMatRef<'_, usize, f64>) {
        for j in 0..l.ncols() {
            let (rows, vals) = (l.row_idx_of_col_raw(j), l.val_of_col(j));
            debug_assert_eq!(rows[0], j);
            let d = vals[0].recip();
            let q = self.q;
            for x in &mut self.data[j * q..(j + 1) * q] {
                *x *= d;
            }
            for (&i, &lij) in rows.iter().zip(vals).skip(1) {
                let (xj, xi) = self.pair_mut(j, i);
                for (yi, &yj) in xi.iter_mut().zip(xj) {
                    *yi -= lij * yj;
                }
            }
        }
    }

    /// `X ← L⁻ᵀ X` for the lower-triangular `l`, the diagonal first in each column.
    #[inline(always)]
    pub(crate) fn solve_lower_transpose(&mut self, l: SparseColMatRef<'_, usize, f64>) {
        let q = self.q;
        let mut acc = vec![0.0; q];
        for j in (0..l.ncols()).rev() {
            let (rows, vals) = (l.row_idx_of_col_raw(j), l.val_of_col(j));
            debug_assert_eq!(rows[0], j);
            acc.fill(0.0);
            for (&i, &lij) in rows[1..].iter().zip(&vals[1..]).rev() {
                for (a, &xi) in acc.iter_mut().zip(self.row(i)) {
                    *a += lij * xi;
                }
            }
            let d = vals[0].recip();
            for (x, &a) in self.data[j * q..(j + 1) * q].iter_mut().zip(&acc) {
                *x = (*x - a) * d;
            }
        }
    }

    /// `X ← L⁻¹ X` for the unit lower-triangular `l` of an `LDLᵀ` (the diagonal, first in
    /// each column, holds `D` and is not used).
    #[inline(always)]
    fn solve_unit_lower(&mut self, l: SparseColMatRef<'_, usize, f64>) {
        for j in 0..l.ncols() {
            let (rows, vals) = (l.row_idx_of_col_raw(j), l.val_of_col(j));
            for (&i, &lij) in rows.iter().zip(vals).skip(1) {
                let (xj, xi) = self.pair_mut(j, i);
                for (yi, &yj) in xi.iter_mut().zip(xj) {
                    *yi -= lij * yj;
                }
            }
        }
    }

    /// `X ← L⁻ᵀ D⁻¹ X` for the `LDLᵀ` factor `l` (`D` on its diagonal, first in each
    /// column): `x_j ← x_j · (1/d_j) − Σ l_ij x_i`.
    #[inline(always)]
    fn solve_scaled_lower_transpose(&mut self, l: SparseColMatRef<'_, usize, f64>) {
        let q = self.q;
        let mut acc = vec![0.0; q];
        for j in (0..l.ncols()).rev() {
            let (rows, vals) = (l.row_idx_of_col_raw(j), l.val_of_col(j));
            acc.fill(0.0);
            for (&i, &lij) in rows[1..].iter().zip(&vals[1..]).rev() {
                for (a, &xi) in acc.iter_mut().zip(self.row(i)) {
                    *a += lij * xi;
                }
            }
            let d = vals[0].recip();
            for (x, &a) in self.data[j * q..(j + 1) * q].iter_mut().zip(&acc) {
                *x = *x * d - a;
            }
        }
    }

    /// Writes these rows into `a` (as many rows and columns).
    fn scatter_into(&self, mut a: MatMut<'_, f64>) {
        let q = self.q;
        for c in 0..self.width {
            let mut col = a.as_mut().col_mut(c);
            for i in 0..col.nrows() {
                col[i] = self.data[i * q + c];
            }
        }
    }

    /// `A X` for the sparse `a` (entries in any order within a column).
    #[inline(always)]
    pub(crate) fn product(&self, a: SparseColMatRef<'_, usize, f64>) -> Self {
        let q = self.q;
        let mut data = vec![0.0; a.nrows() * q];
        for j in 0..a.ncols() {
            let xj = self.row(j);
            for (&i, &aij) in a.row_idx_of_col_raw(j).iter().zip(a.val_of_col(j)) {
                for (y, &x) in data[i * q..(i + 1) * q].iter_mut().zip(xj) {
                    *y += aij * x;
                }
            }
        }
        Self {
            q,
            width: self.width,
            data,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use faer::Side;
    use faer::dyn_stack::{MemBuffer, MemStack};
    use faer::linalg::solvers::Solve;
    use faer::sparse::linalg::cholesky::SymbolicCholeskyRaw;
    use faer::sparse::linalg::solvers::{Llt, SymbolicLlt};

    /// A block of 27 vectors (q not a multiple of 4, as faer's column groups are) on the
    /// lab frame's `K` and `M`: the row-wise solve and product equal faer's bit for bit.
    #[test]
    fn row_wise_solves_and_products_are_faers_bit_for_bit() {
        let model = crate::core::model::lab_frame();
        let theta = model.nominal_theta();
        let pattern = model.union_pattern().pattern.symbolic();
        let mut k_values = vec![0.0; model.union_pattern().pattern.val().len()];
        model.shifted_stiffness_values(&theta, 0.0, &mut k_values);
        let k = SparseColMatRef::new(pattern, &k_values);
        let n = model.n_dof();
        let b = Mat::from_fn(n, 27, |i, c| {
            ((i * 31 + c * 17) % 13) as f64 - 6.0 + 0.1 * c as f64
        });

        let symbolic = SymbolicLlt::try_new(pattern, Side::Lower).unwrap();
        let llt = Llt::try_new_with_symbolic(symbolic, k, Side::Lower).unwrap();
        let mut expected = b.clone();
        llt.solve_in_place(expected.as_mut());

        let chol = super::super::union_symbolic_cholesky(&model).unwrap();
        let mut l_values = vec![0.0; chol.len_val()];
        let mut mem = MemBuffer::new(
            chol.factorize_numeric_llt_scratch::<f64>(faer::Par::Seq, Default::default()),
        );
        chol.factorize_numeric_llt(
            &mut l_values,
            k,
            Side::Lower,
            Default::default(),
            faer::Par::Seq,
            MemStack::new(&mut mem),
            Default::default(),
        )
        .unwrap();
        let SymbolicCholeskyRaw::Simplicial(simplicial) = chol.raw() else {
            panic!("the lab frame's factor is simplicial");
        };
        let l = SparseColMatRef::new(simplicial.factor(), &l_values);
        let (fwd, inv) = chol.perm().map(|p| p.arrays()).unwrap();
        let mut x = Rows::gather(b.as_ref(), Some(fwd));
        x.solve_lower(l);
        x.solve_lower_transpose(l);
        let x = x.permuted(inv);
        let got = x.to_mat();
        for c in 0..27 {
            for i in 0..n {
                assert_eq!(
                    got[(i, c)].to_bits(),
                    expected[(i, c)].to_bits(),
                    "({i}, {c})"
                );
            }
        }

        let mx_expected = model.mass() * &got;
        for mx in [
            x.product(model.mass().as_ref()).to_mat(),
            mass_product(&model, &got),
        ] {
            for c in 0..27 {
                for i in 0..n {
                    assert_eq!(
                        mx[(i, c)].to_bits(),
                        mx_expected[(i, c)].to_bits(),
                        "M ({i}, {c})"
                    );
                }
            }
        }
    }

    /// The row-wise `LDLᵀ` solve (Nelson's) on the reordered pattern equals faer's, bit
    /// for bit, on 17 right-hand sides and a diagonally heavy indefinite matrix.
    #[test]
    fn row_wise_ldlt_solve_is_faers_bit_for_bit() {
        use faer::sparse::linalg::cholesky::LdltRef;
        let model = crate::core::model::lab_frame();
        let order = model.reordered().unwrap();
        let (_, factor) = crate::core::modal::up_looking::tests::diag_heavy_nelson_ldlt(order);
        let n = model.n_dof();
        let b = Mat::from_fn(n, 17, |i, c| ((i * 13 + c * 5) % 11) as f64 - 5.0);
        let mut theirs = b.clone();
        let mut mem = MemBuffer::new(order.symbolic.solve_in_place_scratch::<f64>(17, Par::Seq));
        LdltRef::new(&order.symbolic, &factor).solve_in_place_with_conj(
            Conj::No,
            theirs.as_mut(),
            Par::Seq,
            MemStack::new(&mut mem),
        );
        let SymbolicCholeskyRaw::Simplicial(simplicial) = order.symbolic.raw() else {
            panic!("the reordered pattern's factor is simplicial")
        };
        let mut mine = b;
        solve_ldlt_in_place(
            SparseColMatRef::new(simplicial.factor(), &factor),
            mine.as_mut(),
        );
        for c in 0..17 {
            for i in 0..n {
                assert_eq!(
                    mine[(i, c)].to_bits(),
                    theirs[(i, c)].to_bits(),
                    "({i}, {c})"
                );
            }
        }
    }
}
