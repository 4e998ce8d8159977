//! Numeric sparse Cholesky factorizations (`LLᵀ` and `LDLᵀ`) on a fixed pattern, with
//! the symbolic work done once.
//!
//! faer's simplicial numeric factorization is the up-looking algorithm: row `k` of `L` by
//! a sparse triangular solve over the reach of row `k` in the elimination tree (Davis,
//! *Direct Methods for Sparse Linear Systems*, 2006, §4.4). At every call it first permutes
//! (or transposes) the matrix into the upper triangle it works on and walks the tree anew
//! for every row's reach. The tracker factorizes matrices of one pattern thousands of times
//! (`K(θ)` and `K − σM` of the warm solves, `K − λM` of Nelson's method), and those two
//! steps were about half of each factorization. [`UpLooking`] maps the values to the upper
//! triangle through positions found once and keeps every row's reach, then runs faer's
//! arithmetic in faer's order: the factor is faer's bit for bit (tested below).

use faer::Side;
use faer::dyn_stack::{MemBuffer, MemStack, StackReq};
use faer::prelude::IntoConst;
use faer::sparse::linalg::cholesky::{SymbolicCholesky, SymbolicCholeskyRaw};
use faer::sparse::{SparseColMatRef, SymbolicSparseColMatRef, utils};

/// Which factor: `LLᵀ` (the diagonal holds `l_kk`) or `LDLᵀ` (it holds `d_k`).
#[derive(Clone, Copy, PartialEq, Eq)]
pub(crate) enum Kind {
    Llt,
    Ldlt,
}

/// A simplicial symbolic factorization's numeric step, its symbolic work done once.
pub(crate) struct UpLooking {
    /// Column `k` of the upper triangle of `P A Pᵀ`: its rows (`a_row`) and the positions
    /// of their values in the matrix's value array (`a_src`), from `a_ptr[k]`.
    a_ptr: Vec<usize>,
    a_row: Vec<usize>,
    a_src: Vec<usize>,
    /// The reach of row `k` in the elimination tree, in the order faer visits it.
    reach_ptr: Vec<usize>,
    reach: Vec<usize>,
    /// The factor's column pointers and row indices.
    l_ptr: Vec<usize>,
    l_row: Vec<usize>,
    /// Work: the sparse accumulator of a row, and the next free position of each column.
    x: Vec<f64>,
    next: Vec<usize>,
}

impl UpLooking {
    /// For `symbolic`, the symbolic factorization of matrices with the pattern `pattern`
    /// whose `side` triangle is stored; `None` when that factorization is supernodal.
    pub(crate) fn new(
        symbolic: &SymbolicCholesky<usize>,
        pattern: SymbolicSparseColMatRef<'_, usize>,
        side: Side,
    ) -> Option<Self> {
        let SymbolicCholeskyRaw::Simplicial(simplicial) = symbolic.raw() else {
            return None;
        };
        let n = pattern.ncols();
        let (a_ptr, a_row, a_src) = upper_positions(symbolic, pattern, side);
        let factor = simplicial.factor();
        let l_ptr = factor.col_ptr().to_vec();
        let l_row = factor.row_idx().to_vec();
        // The elimination tree: a column's parent is its first row below the diagonal.
        let parent: Vec<usize> = (0..n)
            .map(|j| {
                l_row
                    .get(l_ptr[j] + 1)
                    .filter(|_| l_ptr[j] + 1 < l_ptr[j + 1])
            })
            .map(|p| p.copied().unwrap_or(usize::MAX))
            .collect();
        let (reach_ptr, reach) = reaches(&a_ptr, &a_row, &parent);
        Some(Self {
            a_ptr,
            a_row,
            a_src,
            reach_ptr,
            reach,
            l_ptr,
            l_row,
            x: vec![0.0; n],
            next: vec![0; n],
        })
    }

    /// The factor of the matrix whose values (on the pattern given to [`UpLooking::new`])
    /// are `values`, into `l` (the symbolic factorization's layout). False when a pivot is
    /// not positive (`LLᵀ`) or is zero or not finite (`LDLᵀ`), as faer's.
    pub(crate) fn factorize(&mut self, values: &[f64], kind: Kind, l: &mut [f64]) -> bool {
        self.x.fill(0.0);
        self.next.copy_from_slice(&self.l_ptr[..self.x.len()]);
        for k in 0..self.x.len() {
            for p in self.a_ptr[k]..self.a_ptr[k + 1] {
                self.x[self.a_row[p]] += values[self.a_src[p]];
            }
            let mut d = self.x[k];
            self.x[k] = 0.0;
            for &j in &self.reach[self.reach_ptr[k]..self.reach_ptr[k + 1]] {
                let j_start = self.l_ptr[j];
                self.next[j] += 1;
                let row = self.next[j];
                let mut xj = self.x[j];
                self.x[j] = 0.0;
                let lkj = xj * l[j_start].recip();
                if kind == Kind::Llt {
                    xj = lkj;
                }
                let column = j_start + 1..row;
                for (&i, &lij) in self.l_row[column.clone()].iter().zip(&l[column]) {
                    self.x[i] -= lij * xj;
                }
                d -= lkj * xj;
                l[row] = lkj;
            }
            let k_start = self.l_ptr[k];
            match kind {
                Kind::Llt if d > 0.0 => l[k_start] = d.sqrt(),
                Kind::Ldlt if d != 0.0 && d.is_finite() => l[k_start] = d,
                _ => return false,
            }
        }
        true
    }
}

/// The upper triangle of `P A Pᵀ` as faer's numeric factorization builds it (permuted, or
/// transposed from the lower side), each entry with the position of its value in `A`'s
/// value array: found by passing the positions themselves through the same functions.
fn upper_positions(
    symbolic: &SymbolicCholesky<usize>,
    pattern: SymbolicSparseColMatRef<'_, usize>,
    side: Side,
) -> (Vec<usize>, Vec<usize>, Vec<usize>) {
    let n = pattern.ncols();
    let nnz = pattern.compute_nnz();
    let positions: Vec<f64> = (0..nnz).map(|p| p as f64).collect();
    let a = SparseColMatRef::new(pattern, &positions);
    let (mut val, mut col_ptr, mut row_idx) = (vec![0.0; nnz], vec![0usize; n + 1], vec![0; nnz]);
    let mut mem = MemBuffer::new(StackReq::any_of(&[
        utils::permute_self_adjoint_scratch::<usize>(n),
        utils::transpose_scratch::<usize>(n, n),
    ]));
    let stack = MemStack::new(&mut mem);
    let upper = match (symbolic.perm(), side) {
        (Some(perm), _) => utils::permute_self_adjoint_to_unsorted(
            &mut val,
            &mut col_ptr,
            &mut row_idx,
            a,
            perm,
            side,
            Side::Upper,
            stack,
        )
        .into_const(),
        (None, Side::Lower) => {
            utils::adjoint(&mut val, &mut col_ptr, &mut row_idx, a, stack).into_const()
        }
        (None, Side::Upper) => a,
    };
    let mut out = (vec![0], Vec::with_capacity(nnz), Vec::with_capacity(nnz));
    for k in 0..n {
        for (&i, &v) in upper.row_idx_of_col_raw(k).iter().zip(upper.val_of_col(k)) {
            out.1.push(i);
            out.2.push(v as usize);
        }
        out.0.push(out.1.len());
    }
    out
}

/// Every row's reach in the elimination tree `parent`, in the order of faer's `ereach`:
/// for each entry of the row left of the diagonal, the path up the tree to the first node
/// already seen, the paths stacked so that the last one found comes first.
fn reaches(a_ptr: &[usize], a_row: &[usize], parent: &[usize]) -> (Vec<usize>, Vec<usize>) {
    let n = parent.len();
    let mut visited = vec![usize::MAX; n];
    let mut stack = vec![0; n];
    let (mut reach_ptr, mut reach) = (vec![0], Vec::new());
    for k in 0..n {
        visited[k] = k;
        let mut top = n;
        for &first in &a_row[a_ptr[k]..a_ptr[k + 1]] {
            if first >= k {
                continue;
            }
            let (mut i, mut len) = (first, 0);
            while visited[i] != k {
                stack[len] = i;
                len += 1;
                visited[i] = k;
                i = parent[i];
            }
            stack.copy_within(..len, top - len);
            top -= len;
        }
        reach.extend_from_slice(&stack[top..]);
        reach_ptr.push(reach.len());
    }
    (reach_ptr, reach)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use faer::Par;
    use faer::linalg::cholesky::ldlt::factor::LdltRegularization;

    /// A diagonally heavy indefinite matrix on Nelson's reordered pattern (lower side, no
    /// permutation) and faer's `LDLᵀ` factor of it: `(values, factor)`.
    pub(crate) fn diag_heavy_nelson_ldlt(
        order: &crate::core::model::Reordered,
    ) -> (Vec<f64>, Vec<f64>) {
        let mut values: Vec<f64> = (0..order.len())
            .map(|p| ((p * 7919) % 101) as f64 - 50.0)
            .collect();
        for j in 0..order.lower.ncols() {
            values[order.lower.col_ptr()[j]] = 1.0e4;
        }
        let factor = order.factorize_ldlt(&values).unwrap();
        (values, factor)
    }

    /// On the lab frame's union pattern (AMD-permuted, lower side) and on Nelson's
    /// reordered pattern (no permutation): `K` by `LLᵀ`, `K − σM` (indefinite) by `LDLᵀ`;
    /// the factors equal faer's bit for bit, and a matrix that is not positive definite
    /// fails the `LLᵀ` as faer's does.
    #[test]
    fn factors_are_faers_bit_for_bit() {
        let model = crate::core::model::lab_frame();
        let theta = model.nominal_theta();
        let pattern = model.union_pattern().pattern.symbolic();
        let mut k = vec![0.0; model.union_pattern().pattern.val().len()];
        model.shifted_stiffness_values(&theta, 0.0, &mut k);
        let mut shifted = k.clone();
        model.subtract_mass_values(3.0e5, &mut shifted);
        let symbolic = super::super::union_symbolic_cholesky(&model).unwrap();
        let mut ours = UpLooking::new(&symbolic, pattern, Side::Lower).unwrap();
        for (values, kind) in [
            (&k, Kind::Llt),
            (&shifted, Kind::Ldlt),
            (&shifted, Kind::Llt),
        ] {
            let a = SparseColMatRef::new(pattern, values);
            let mut expected = vec![0.0; symbolic.len_val()];
            let mut mem = MemBuffer::new(StackReq::any_of(&[
                symbolic.factorize_numeric_llt_scratch::<f64>(Par::Seq, Default::default()),
                symbolic.factorize_numeric_ldlt_scratch::<f64>(Par::Seq, Default::default()),
            ]));
            let stack = MemStack::new(&mut mem);
            let theirs = match kind {
                Kind::Llt => symbolic
                    .factorize_numeric_llt(
                        &mut expected,
                        a,
                        Side::Lower,
                        Default::default(),
                        Par::Seq,
                        stack,
                        Default::default(),
                    )
                    .is_ok(),
                Kind::Ldlt => symbolic
                    .factorize_numeric_ldlt(
                        &mut expected,
                        a,
                        Side::Lower,
                        LdltRegularization::default(),
                        Par::Seq,
                        stack,
                        Default::default(),
                    )
                    .is_ok(),
            };
            let mut got = vec![0.0; symbolic.len_val()];
            assert_eq!(ours.factorize(values, kind, &mut got), theirs);
            if theirs {
                let same = got
                    .iter()
                    .zip(&expected)
                    .all(|(a, b)| a.to_bits() == b.to_bits());
                assert!(same, "the factor differs from faer's");
            }
        }
        // The indefinite matrix fails the LLᵀ.
        assert!(!ours.factorize(&shifted, Kind::Llt, &mut vec![0.0; symbolic.len_val()]));

        // Nelson's pattern: reordered already, no permutation, lower side.
        let order = model.reordered().unwrap();
        let mut ours = UpLooking::new(&order.symbolic, order.lower.as_ref(), Side::Lower).unwrap();
        let (diag_heavy, expected) = diag_heavy_nelson_ldlt(order);
        let mut got = vec![0.0; order.symbolic.len_val()];
        assert!(ours.factorize(&diag_heavy, Kind::Ldlt, &mut got));
        assert!(
            got.iter()
                .zip(&expected)
                .all(|(a, b)| a.to_bits() == b.to_bits())
        );
    }
}
