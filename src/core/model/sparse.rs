//! Sparse symmetric matrices as the model holds them, and the union pattern on which
//! `K(θ) − λM` is formed without re-deriving structure.

use faer::sparse::{SparseColMat, SymbolicSparseColMat, Triplet};
use faer::{MatMut, MatRef};

/// Sparse matrix in CSC form with `usize` indices.
pub type Csc = SparseColMat<usize, f64>;

/// Triplet accumulator for one assembled matrix (duplicates are summed on build).
#[derive(Debug, Default, Clone)]
pub(crate) struct Accumulator {
    pub trips: Vec<Triplet<usize, usize, f64>>,
}

impl Accumulator {
    pub fn add(&mut self, i: usize, j: usize, v: f64) {
        if v != 0.0 {
            self.trips.push(Triplet::new(i, j, v));
        }
    }

    /// Adds `coef · (Σ_a c_a e_{i_a})(Σ_b c_b e_{j_b})ᵀ`-type contributions for a dense block:
    /// `a[p][q]` scattered through DOF combinations `maps[p]` (each a linear combination of
    /// global DOFs): `G += Lᵀ a L` with the rows of `L` given by `maps`.
    pub fn add_mapped<const N: usize>(&mut self, a: &[[f64; N]; N], maps: &[&[(usize, f64)]; N]) {
        for p in 0..N {
            for q in 0..N {
                let v = a[p][q];
                if v == 0.0 {
                    continue;
                }
                for &(gi, ci) in maps[p] {
                    for &(gj, cj) in maps[q] {
                        self.add(gi, gj, ci * cj * v);
                    }
                }
            }
        }
    }

    pub fn build(&self, n: usize) -> Csc {
        csc_from_triplets(n, self.trips.iter().map(|t| (t.row, t.col, t.val)))
    }
}

/// An `n × n` CSC matrix from `(row, col, value)` entries, duplicates summed: a counting
/// sort by column, then each column's rows sorted and merged (O(N + Σ c log c) for N
/// entries and c per column; the generic triplet constructor sorts all N).
pub fn csc_from_triplets(
    n: usize,
    entries: impl Iterator<Item = (usize, usize, f64)> + Clone,
) -> Csc {
    let mut count = vec![0usize; n + 1];
    for (i, j, _) in entries.clone() {
        assert!(
            i < n && j < n,
            "assembly produced an out-of-range entry ({i}, {j})"
        );
        count[j + 1] += 1;
    }
    for j in 0..n {
        count[j + 1] += count[j];
    }
    let mut next = count.clone();
    let mut bucket = vec![(0usize, 0.0f64); count[n]];
    for (i, j, v) in entries {
        bucket[next[j]] = (i, v);
        next[j] += 1;
    }
    let mut col_ptr = Vec::with_capacity(n + 1);
    let mut row_idx = Vec::with_capacity(bucket.len());
    let mut val = Vec::with_capacity(bucket.len());
    col_ptr.push(0);
    for j in 0..n {
        let col = &mut bucket[count[j]..count[j + 1]];
        col.sort_by_key(|e| e.0);
        for &(i, v) in col.iter() {
            if row_idx.len() > col_ptr[j] && row_idx.last() == Some(&i) {
                *val.last_mut().expect("a value per row index") += v;
            } else {
                row_idx.push(i);
                val.push(v);
            }
        }
        col_ptr.push(row_idx.len());
    }
    let symbolic = SymbolicSparseColMat::new_checked(n, n, col_ptr, None, row_idx);
    SparseColMat::new(symbolic, val)
}

/// `y += a · A x` for a sparse `A`.
pub fn spmv_add(a: &Csc, x: &[f64], alpha: f64, y: &mut [f64]) {
    let s = a.symbolic();
    for (j, &x_j) in x.iter().enumerate().take(a.ncols()) {
        let xj = alpha * x_j;
        if xj == 0.0 {
            continue;
        }
        for (&i, &v) in s.row_idx_of_col_raw(j).iter().zip(a.val_of_col(j)) {
            y[i] += v * xj;
        }
    }
}

/// `Y = A X` for a sparse `A` and a block `X`, `A` read once per block of columns: rows of
/// the block are interleaved so each stored entry of `A` updates a contiguous row of the
/// product (at six columns 5× faster than six products [`spmv_add`] on the four-bay
/// solid frame's mass matrix, which is memory-bound).
pub fn spmm(a: &Csc, x: MatRef<'_, f64>, mut y: MatMut<'_, f64>) {
    let (n, r) = (x.nrows(), x.ncols());
    debug_assert_eq!((a.ncols(), y.nrows(), y.ncols()), (n, a.nrows(), r));
    let s = a.symbolic();
    let xi: Vec<f64> = (0..n)
        .flat_map(|j| (0..r).map(move |c| x[(j, c)]))
        .collect();
    let mut yi = vec![0.0; a.nrows() * r];
    for j in 0..n {
        let xj = &xi[j * r..(j + 1) * r];
        for (&i, &v) in s.row_idx_of_col_raw(j).iter().zip(a.val_of_col(j)) {
            let yrow = &mut yi[i * r..(i + 1) * r];
            for (yc, xc) in yrow.iter_mut().zip(xj) {
                *yc += v * xc;
            }
        }
    }
    for (i, row) in yi.chunks_exact(r.max(1)).enumerate() {
        for (c, &v) in row.iter().enumerate() {
            y[(i, c)] = v;
        }
    }
}

/// The union of the patterns of several matrices, with each matrix's entries mapped to
/// positions in the union's value array.
#[derive(Debug, Clone)]
pub struct UnionPattern {
    /// The union pattern, all values zero.
    pub pattern: Csc,
    /// For each source matrix, the union position of each of its stored entries.
    pub maps: Vec<Vec<usize>>,
}

impl UnionPattern {
    pub fn new(n: usize, mats: &[&Csc]) -> Self {
        // Column by column: the rows of every matrix and the diagonal (kept so a row and
        // column can always be pinned to the identity), sorted and deduplicated.
        let entries: usize = mats.iter().map(|m| m.val().len()).sum();
        let mut col_ptr = Vec::with_capacity(n + 1);
        let mut row_idx = Vec::with_capacity(entries + n);
        col_ptr.push(0);
        for j in 0..n {
            let first = row_idx.len();
            row_idx.push(j);
            for m in mats {
                row_idx.extend_from_slice(m.symbolic().row_idx_of_col_raw(j));
            }
            row_idx[first..].sort_unstable();
            let mut kept = first;
            for r in first..row_idx.len() {
                if r == first || row_idx[r] != row_idx[kept - 1] {
                    row_idx[kept] = row_idx[r];
                    kept += 1;
                }
            }
            row_idx.truncate(kept);
            col_ptr.push(kept);
        }
        let nnz = row_idx.len();
        let pattern = Csc::new(
            SymbolicSparseColMat::new_checked(n, n, col_ptr, None, row_idx),
            vec![0.0; nnz],
        );
        let ps = pattern.symbolic();
        let maps = mats
            .iter()
            .map(|m| {
                let s = m.symbolic();
                let mut map = Vec::with_capacity(s.row_idx().len());
                for j in 0..n {
                    let rows = ps.row_idx_of_col_raw(j);
                    let base = ps.col_ptr()[j];
                    for &i in s.row_idx_of_col_raw(j) {
                        let pos = rows.binary_search(&i).expect("entry is in the union");
                        map.push(base + pos);
                    }
                }
                map
            })
            .collect();
        Self { pattern, maps }
    }

    /// `out += alpha · (matrix k)` on the union's value array.
    pub fn add_into(&self, k: usize, mat: &Csc, alpha: f64, out: &mut [f64]) {
        let vals = mat.val();
        for (&pos, &v) in self.maps[k].iter().zip(vals) {
            out[pos] += alpha * v;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use faer::Mat;

    /// The block product against column-by-column products on an unsymmetric pattern with
    /// an empty column and duplicates summed: equal up to the order of additions (1e-14 of
    /// the entries' scale, which is 1).
    #[test]
    fn block_product_matches_column_products() {
        let n = 7;
        let entries: Vec<(usize, usize, f64)> = (0..40)
            .map(|k| ((k * 5 + 1) % n, (k * 3) % n, 0.1 * k as f64 - 1.7))
            .filter(|&(_, j, _)| j != 4)
            .collect();
        let a = csc_from_triplets(n, entries.iter().copied());
        let x = Mat::from_fn(n, 5, |i, j| (i as f64 + 1.0) * 0.3 - j as f64 * 0.7);
        let mut y = Mat::from_fn(n, 5, |_, _| f64::NAN);
        spmm(&a, x.as_ref(), y.as_mut());
        for j in 0..5 {
            let xj: Vec<f64> = (0..n).map(|i| x[(i, j)]).collect();
            let mut yj = vec![0.0; n];
            spmv_add(&a, &xj, 1.0, &mut yj);
            for i in 0..n {
                assert!((y[(i, j)] - yj[i]).abs() < 1e-14, "({i}, {j})");
            }
        }
    }
}
