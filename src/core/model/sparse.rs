//! Sparse symmetric matrices as the model holds them, and the union pattern on which
//! `K(θ) − λM` is formed without re-deriving structure.

use faer::sparse::{SparseColMat, SymbolicSparseColMat, Triplet};

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
        let mut trips = Vec::new();
        for m in mats {
            let s = m.symbolic();
            for j in 0..n {
                for &i in s.row_idx_of_col_raw(j) {
                    trips.push((i, j, 0.0));
                }
            }
        }
        // Also keep the full diagonal so a row/column can always be pinned to identity.
        trips.extend((0..n).map(|i| (i, i, 0.0)));
        let pattern = csc_from_triplets(n, trips.iter().copied());
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
