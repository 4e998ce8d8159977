//! The CSC type the model holds its matrices in, and building it: the triplet
//! [`Accumulator`] of assembly, counting sorts from `(row, col, value)` entries (one or both
//! triangles given), and reading columns and the diagonal back.

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

/// The symmetric `n × n` matrix, both triangles stored, whose lower triangle is `lower`
/// (entries with row ≥ column).
pub fn csc_from_lower(n: usize, lower: &[(usize, usize, f64)]) -> Csc {
    let mirror = lower
        .iter()
        .filter(|e| e.0 != e.1)
        .map(|&(i, j, v)| (j, i, v));
    csc_from_triplets(n, lower.iter().copied().chain(mirror))
}

/// The symmetric `n × n` matrix, both triangles stored, of entries (in chunks) that give one
/// triangle of it, each entry in whichever triangle (a `symmetric` Matrix Market file). `Err` with
/// the (row, column) of the lower triangle given twice. Counting sort by column, rows sorted
/// within each; the upper triangle is then read off in order, without another sort.
pub fn csc_from_one_triangle(
    n: usize,
    chunks: &[Vec<(usize, usize, f64)>],
) -> Result<Csc, (usize, usize)> {
    let lower = |&(i, j, v): &(usize, usize, f64)| if i >= j { (i, j, v) } else { (j, i, v) };
    let entries = || chunks.iter().flatten();
    let mut start = vec![0usize; n + 1];
    for e in entries() {
        start[lower(e).1 + 1] += 1;
    }
    for j in 0..n {
        start[j + 1] += start[j];
    }
    let mut next = start.clone();
    let mut low = vec![(0usize, 0.0f64); start[n]];
    for e in entries() {
        let (i, j, v) = lower(e);
        low[next[j]] = (i, v);
        next[j] += 1;
    }
    // Rows ascending in each column; a row twice is a duplicate.
    for j in 0..n {
        let col = &mut low[start[j]..start[j + 1]];
        col.sort_unstable_by_key(|e| e.0);
        if let Some(w) = col.windows(2).find(|w| w[0].0 == w[1].0) {
            return Err((w[0].0, j));
        }
    }
    // Column j of the full matrix: row c for each lower entry (j, c), c < j (met in
    // ascending c when the columns are read in order), then its own lower rows.
    let mut upper_count = vec![0usize; n];
    for (c, w) in start.windows(2).enumerate() {
        for &(i, _) in &low[w[0]..w[1]] {
            if i > c {
                upper_count[i] += 1;
            }
        }
    }
    let mut col_ptr = Vec::with_capacity(n + 1);
    col_ptr.push(0usize);
    for j in 0..n {
        col_ptr.push(col_ptr[j] + upper_count[j] + (start[j + 1] - start[j]));
    }
    let total = col_ptr[n];
    let mut row_idx = vec![0usize; total];
    let mut val = vec![0.0f64; total];
    let mut fill: Vec<usize> = col_ptr[..n].to_vec();
    for c in 0..n {
        for &(i, v) in &low[start[c]..start[c + 1]] {
            if i > c {
                row_idx[fill[i]] = c;
                val[fill[i]] = v;
                fill[i] += 1;
            }
        }
        // Every column of the upper part of c is done once c is reached.
        for &(i, v) in &low[start[c]..start[c + 1]] {
            row_idx[fill[c]] = i;
            val[fill[c]] = v;
            fill[c] += 1;
        }
    }
    let symbolic = SymbolicSparseColMat::new_checked(n, n, col_ptr, None, row_idx);
    Ok(SparseColMat::new(symbolic, val))
}

/// Column `j` of `a` and of `b` side by side: every row stored in either, ascending, with
/// its value in each (zero where it is not stored).
pub fn column_pairs<'a>(
    a: &'a Csc,
    b: &'a Csc,
    j: usize,
) -> impl Iterator<Item = (usize, f64, f64)> + 'a {
    let (ra, va) = (a.symbolic().row_idx_of_col_raw(j), a.val_of_col(j));
    let (rb, vb) = (b.symbolic().row_idx_of_col_raw(j), b.val_of_col(j));
    let (mut p, mut q) = (0, 0);
    std::iter::from_fn(move || {
        let next = match (ra.get(p), rb.get(q)) {
            (Some(&i), Some(&k)) if i == k => (i, va[p], vb[q]),
            (Some(&i), Some(&k)) if i < k => (i, va[p], 0.0),
            (Some(&i), None) => (i, va[p], 0.0),
            (_, Some(&k)) => (k, 0.0, vb[q]),
            (None, None) => return None,
        };
        if ra.get(p) == Some(&next.0) {
            p += 1;
        }
        if rb.get(q) == Some(&next.0) {
            q += 1;
        }
        Some(next)
    })
}

/// The diagonal of a matrix with sorted row indices (zero where nothing is stored).
pub fn diagonal(a: &Csc) -> Vec<f64> {
    let s = a.symbolic();
    (0..a.ncols())
        .map(|j| {
            s.row_idx_of_col_raw(j)
                .binary_search(&j)
                .map_or(0.0, |k| a.val_of_col(j)[k])
        })
        .collect()
}

/// Triplets of a symmetric `n × n` matrix: `k` off-diagonal pairs placed by `off`, and
/// a dominant diagonal (a fixture of the union and reordering tests).
#[cfg(test)]
pub(super) fn symmetric_triplets(n: usize, k: usize, off: usize) -> Vec<(usize, usize, f64)> {
    (0..k)
        .map(|t| {
            (
                (t * 4 + off) % n,
                (t * 7 + 2 * off) % n,
                0.3 * t as f64 - 1.1,
            )
        })
        .flat_map(|(i, j, v)| [(i, j, v), (j, i, v)])
        .chain((0..n).map(|i| (i, i, 10.0 + i as f64)))
        .collect()
}
