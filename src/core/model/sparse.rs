//! Sparse symmetric matrices as the model holds them, and the union pattern on which
//! `K(θ) − λM` is formed without re-deriving structure.

use faer::sparse::{SparseColMat, Triplet};

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
        // Triplets are in range by construction; an empty matrix is valid.
        SparseColMat::try_new_from_triplets(n, n, &self.trips)
            .expect("assembly produced an out-of-range triplet")
    }
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
                    trips.push(Triplet::new(i, j, 0.0));
                }
            }
        }
        // Also keep the full diagonal so a row/column can always be pinned to identity.
        for i in 0..n {
            trips.push(Triplet::new(i, i, 0.0));
        }
        let pattern = SparseColMat::try_new_from_triplets(n, n, &trips)
            .expect("union of valid patterns is valid");
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
