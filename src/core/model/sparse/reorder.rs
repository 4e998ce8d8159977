//! The union pattern reordered for factorization ([`Reordered`]): the fill-reducing
//! permutation, the permuted matrix's lower triangle with each source entry's position in
//! it, and the identity-ordered symbolic Cholesky factorization every numeric one reuses.

use faer::dyn_stack::{MemBuffer, MemStack};
use faer::linalg::cholesky::ldlt::factor::LdltRegularization;
use faer::sparse::linalg::cholesky::{
    SymbolicCholesky, SymmetricOrdering, factorize_symbolic_cholesky,
};
use faer::sparse::{SparseColMatRef, SymbolicSparseColMat, SymbolicSparseColMatRef};
use faer::{Par, Side};

use super::ordering::amd_ordering;
use super::union::{MIRROR, UnionPattern, ValueLayout};

/// The union pattern reordered once for factorization: `P A Pᵀ` by AMD, stored as its lower
/// triangle, with a symbolic Cholesky factorization of it in that order. Every sparse
/// factorization of a `K(θ) − σM` is done on it. Given the union pattern and an AMD
/// symbolic factorization, faer's numeric factorization permutes the full matrix to a
/// triangle on every call; given the permuted triangle and an identity-ordered symbolic
/// factorization it factorizes the values as they stand, and the values are half as many.
/// On the four-bay solid frame a numeric `LLᵀ` took 45 ms the first way and 27.5 ms this
/// way (the same factor: the identity-ordered symbolic analysis of the permuted matrix is
/// the one faer runs after its own permutation).
pub struct Reordered {
    /// `fwd[new] = old`, `inv[old] = new`.
    pub fwd: Vec<usize>,
    pub inv: Vec<usize>,
    /// Lower triangle of `P A Pᵀ`, rows sorted within each column.
    pub lower: SymbolicSparseColMat<usize>,
    /// Symbolic Cholesky factorization of `lower` (identity ordering, supernodal or
    /// simplicial as faer chooses).
    pub symbolic: SymbolicCholesky<usize>,
    /// For each source matrix of the union, the position in `lower`'s values of each of
    /// its stored entries, or `MIRROR` for an entry above the diagonal (whose value its
    /// symmetric twin below carries).
    maps: Vec<Vec<u32>>,
}

impl std::fmt::Debug for Reordered {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Reordered")
            .field("n", &self.fwd.len())
            .field("lower_nnz", &self.lower.row_idx().len())
            .field("factor_nnz", &self.symbolic.len_val())
            .finish()
    }
}

impl Reordered {
    /// faer's numeric `LDLᵀ` of `values` (on `lower`'s pattern), with scratch of its own:
    /// the factor's values, or `None` at a zero pivot. For a one-off factorization; a loop
    /// that factorizes again and again keeps its scratch instead.
    pub fn factorize_ldlt(&self, values: &[f64]) -> Option<Vec<f64>> {
        let mut factor = vec![0.0; self.symbolic.len_val()];
        let mut mem = MemBuffer::new(
            self.symbolic
                .factorize_numeric_ldlt_scratch::<f64>(Par::Seq, Default::default()),
        );
        self.symbolic
            .factorize_numeric_ldlt(
                &mut factor,
                SparseColMatRef::new(self.lower.as_ref(), values),
                Side::Lower,
                LdltRegularization::default(),
                Par::Seq,
                MemStack::new(&mut mem),
                Default::default(),
            )
            .ok()?;
        Some(factor)
    }

    /// AMD ordering and symbolic factorization of a union pattern (symmetric, both
    /// triangles stored).
    pub fn new(union: &UnionPattern) -> Result<Self, faer::sparse::FaerError> {
        let pattern = union.pattern.symbolic();
        let n = pattern.nrows();
        let (fwd, inv) = amd_ordering(pattern)?;
        let (row_ptr, col_ptr) = lower_counts(pattern, &inv);
        let (row_idx, below) = lower_entries(pattern, &inv, &row_ptr, &col_ptr);
        let upper = upper_of_lower(n, row_ptr, &col_ptr, &row_idx);
        let symbolic = factorize_symbolic_cholesky(
            upper.as_ref(),
            Side::Upper,
            SymmetricOrdering::Identity,
            Default::default(),
        )?;
        let lower = SymbolicSparseColMat::new_checked(n, n, col_ptr, None, row_idx);
        // The union's first source is stored on it: its positions are `below` itself.
        let mut maps: Vec<Vec<u32>> = union
            .maps
            .iter()
            .skip(1)
            .map(|m| m.iter().map(|&pos| below[pos as usize]).collect())
            .collect();
        maps.insert(0, below);
        Ok(Self {
            fwd,
            inv,
            lower,
            symbolic,
            maps,
        })
    }

    /// Position in the lower triangle's values of the diagonal entry of DOF `old`, if the
    /// pattern has one (rows are sorted, so it is its column's first).
    pub fn diagonal_position(&self, old: usize) -> Option<usize> {
        let j = self.inv[old];
        let start = self.lower.col_ptr()[j];
        (self.lower.col_ptr()[j + 1] > start && self.lower.row_idx()[start] == j).then_some(start)
    }

    /// Whether the matrix with these lower-triangle values is positive definite: `None`
    /// when its Cholesky factorization succeeds, else the DOF (original numbering) at whose
    /// pivot it broke down. Allocates its own scratch: for load-time checks.
    pub fn cholesky_breakdown(&self, values: &[f64]) -> Option<usize> {
        use faer::dyn_stack::{MemBuffer, MemStack};
        use faer::linalg::cholesky::llt::factor::LltRegularization;
        use faer::sparse::linalg::cholesky::SymbolicCholeskyRaw;
        let mut mem = MemBuffer::new(
            self.symbolic
                .factorize_numeric_llt_scratch::<f64>(faer::Par::Seq, Default::default()),
        );
        let mut l = vec![0.0; self.symbolic.len_val()];
        let a = faer::sparse::SparseColMatRef::new(self.lower.as_ref(), values);
        match self.symbolic.factorize_numeric_llt(
            &mut l,
            a,
            Side::Lower,
            LltRegularization::default(),
            faer::Par::Seq,
            MemStack::new(&mut mem),
            Default::default(),
        ) {
            Ok(_) => None,
            Err(faer::linalg::cholesky::llt::factor::LltError::NonPositivePivot { index }) => {
                // faer 0.24 reports the simplicial factorization's pivot one-based and the
                // supernodal one's zero-based.
                let new = match self.symbolic.raw() {
                    SymbolicCholeskyRaw::Simplicial(_) => index.saturating_sub(1),
                    SymbolicCholeskyRaw::Supernodal(_) => index,
                };
                Some(self.fwd[new.min(self.fwd.len() - 1)])
            }
        }
    }

    /// Number of stored values of the lower triangle.
    pub fn len(&self) -> usize {
        self.lower.row_idx().len()
    }

    /// Whether the pattern is empty (a model with no DOFs).
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// `x_new[i] = x[fwd[i]]`: a vector into the reordered numbering.
    pub fn permute(&self, x: &[f64], out: &mut [f64]) {
        for (o, &old) in out.iter_mut().zip(&self.fwd) {
            *o = x[old];
        }
    }

    /// `x[i] = x_new[inv[i]]`: a vector back from the reordered numbering.
    pub fn unpermute(&self, x_new: &[f64], out: &mut [f64]) {
        for (o, &new) in out.iter_mut().zip(&self.inv) {
            *o = x_new[new];
        }
    }
}

impl ValueLayout for Reordered {
    fn maps(&self) -> &[Vec<u32>] {
        &self.maps
    }
}

/// The first counting pass of [`Reordered::new`]: where each new row's and each new
/// column's entries start in the lower triangle of `P A Pᵀ` (`inv[old] = new`), as
/// `(row_ptr, col_ptr)`. The lower triangle's entries are first placed by rows (the upper
/// triangle's columns, in any order), then read back row by row into their columns, which
/// so come out sorted (two counting passes, no sort per column: 50 → 36 ms on the four-bay
/// solid frame, most of it now the scattered writes).
fn lower_counts(
    pattern: SymbolicSparseColMatRef<'_, usize>,
    inv: &[usize],
) -> (Vec<usize>, Vec<usize>) {
    let n = pattern.nrows();
    let in_lower = |i: usize, j: usize| inv[i] >= inv[j];
    let mut row_ptr = vec![0usize; n + 1];
    let mut col_ptr = vec![0usize; n + 1];
    for j in 0..n {
        for &i in pattern.row_idx_of_col_raw(j) {
            if in_lower(i, j) {
                row_ptr[inv[i] + 1] += 1;
                col_ptr[inv[j] + 1] += 1;
            }
        }
    }
    for j in 0..n {
        row_ptr[j + 1] += row_ptr[j];
        col_ptr[j + 1] += col_ptr[j];
    }
    (row_ptr, col_ptr)
}

/// The lower triangle of `P A Pᵀ` by columns, laid out by [`lower_counts`]: its row
/// indices (sorted within each column), and for each stored entry of `pattern` its
/// position among them, or [`MIRROR`] for one above the diagonal, as `(row_idx, below)`.
fn lower_entries(
    pattern: SymbolicSparseColMatRef<'_, usize>,
    inv: &[usize],
    row_ptr: &[usize],
    col_ptr: &[usize],
) -> (Vec<usize>, Vec<u32>) {
    let n = pattern.nrows();
    let in_lower = |i: usize, j: usize| inv[i] >= inv[j];
    let nnz_lower = col_ptr[n];
    // (new column, union position) of every lower entry, grouped by new row.
    let mut by_row = vec![(0u32, 0u32); nnz_lower];
    let mut next = row_ptr.to_vec();
    for j in 0..n {
        let base = pattern.col_ptr()[j];
        for (k, &i) in pattern.row_idx_of_col_raw(j).iter().enumerate() {
            if in_lower(i, j) {
                by_row[next[inv[i]]] = (inv[j] as u32, (base + k) as u32);
                next[inv[i]] += 1;
            }
        }
    }
    let mut below = vec![MIRROR; pattern.row_idx().len()];
    let mut row_idx = vec![0usize; nnz_lower];
    let mut fill = col_ptr.to_vec();
    for r in 0..n {
        for &(c, pos) in &by_row[row_ptr[r]..row_ptr[r + 1]] {
            let c = c as usize;
            row_idx[fill[c]] = r;
            below[pos as usize] = fill[c] as u32;
            fill[c] += 1;
        }
    }
    (row_idx, below)
}

/// The upper triangle of `P A Pᵀ`, as faer reads an identity-ordered pattern: the
/// transpose of the lower triangle `(col_ptr, row_idx)`, whose rows start at `row_ptr`
/// (columns read in order, so each of its columns comes out sorted).
fn upper_of_lower(
    n: usize,
    row_ptr: Vec<usize>,
    col_ptr: &[usize],
    row_idx: &[usize],
) -> SymbolicSparseColMat<usize> {
    let nnz_lower = col_ptr[n];
    let upper_ptr = row_ptr;
    let mut fill = upper_ptr.clone();
    let mut upper_idx = vec![0usize; nnz_lower];
    for c in 0..n {
        for &r in &row_idx[col_ptr[c]..col_ptr[c + 1]] {
            upper_idx[fill[r]] = c;
            fill[r] += 1;
        }
    }
    SymbolicSparseColMat::new_checked(n, n, upper_ptr, None, upper_idx)
}

#[cfg(test)]
mod tests {
    use super::super::csc::{csc_from_triplets, symmetric_triplets};
    use super::*;
    use faer::Mat;

    /// The reordered lower triangle holds `P A Pᵀ`: rebuilt to a full matrix through the
    /// permutation, a sum of two symmetric source matrices (one with a pattern the other
    /// lacks) equals the sum formed directly, entry by entry (exact: each entry is the same
    /// one or two products). The identity-ordered symbolic factorization has as many
    /// entries as the AMD one faer computes for the union itself.
    #[test]
    fn reordered_lower_triangle_is_the_permuted_matrix() {
        let n = 9;
        let sym = |k, off| symmetric_triplets(n, k, off);
        let a = csc_from_triplets(n, sym(12, 1).into_iter());
        let b = csc_from_triplets(n, sym(5, 3).into_iter());
        let union = UnionPattern::new(n, &[&a, &b]);
        let r = Reordered::new(&union).unwrap();
        let mut values = vec![0.0; r.len()];
        r.add_into(0, &union.pattern, 1.0, &mut values);
        r.add_into(1, &b, -2.0, &mut values);
        let mut full = Mat::<f64>::zeros(n, n);
        let lower = r.lower.as_ref();
        for j in 0..n {
            let range = lower.col_ptr()[j]..lower.col_ptr()[j + 1];
            for (&i, &v) in lower.row_idx_of_col_raw(j).iter().zip(&values[range]) {
                assert!(i >= j, "entry ({i}, {j}) above the diagonal");
                full[(r.fwd[i], r.fwd[j])] = v;
                full[(r.fwd[j], r.fwd[i])] = v;
            }
        }
        let mut direct = Mat::<f64>::zeros(n, n);
        for (m, alpha) in [(&a, 1.0), (&b, -2.0)] {
            for j in 0..n {
                for (&i, &v) in m
                    .symbolic()
                    .row_idx_of_col_raw(j)
                    .iter()
                    .zip(m.val_of_col(j))
                {
                    direct[(i, j)] += alpha * v;
                }
            }
        }
        assert_eq!(full, direct);
        let amd = factorize_symbolic_cholesky(
            union.pattern.symbolic(),
            Side::Lower,
            SymmetricOrdering::Amd,
            Default::default(),
        )
        .unwrap();
        assert_eq!(r.symbolic.len_val(), amd.len_val());
        let x: Vec<f64> = (0..n).map(|i| i as f64 * 1.5 - 2.0).collect();
        let (mut xp, mut back) = (vec![0.0; n], vec![0.0; n]);
        r.permute(&x, &mut xp);
        r.unpermute(&xp, &mut back);
        assert_eq!(back, x);
    }
}
