//! The union pattern of a model's matrices, on which `K(θ) − σM` is formed without
//! re-deriving structure, and the value layouts ([`ValueLayout`]) that its source matrices
//! scatter into through their maps.

use faer::sparse::{SymbolicSparseColMat, SymbolicSparseColMatRef};

use super::csc::Csc;

/// The union of the patterns of several matrices, carrying the first one's values, with
/// each other matrix's entries mapped to positions in the union's value array.
#[derive(Debug, Clone)]
pub struct UnionPattern {
    /// The union pattern with the values of the first source matrix (zero where it has no
    /// entry). A model's `K0` is this matrix: on a solid model `K0` holds nearly every
    /// entry of the union, and a separate copy with its own map to the union took 54 MB
    /// of the four-bay frame's 31,458 DOF.
    pub pattern: Csc,
    /// For each source matrix, the union position of each of its stored entries; the
    /// first one's is the identity, stored empty (see [`ValueLayout::add_into`]).
    pub maps: Vec<Vec<u32>>,
}

impl UnionPattern {
    pub fn new(n: usize, mats: &[&Csc]) -> Self {
        use rayon::prelude::*;
        // Column by column: the rows of every matrix and the diagonal (kept so a row and
        // column can always be pinned to the identity), merged (each column's rows are
        // sorted). Blocks of columns on the worker threads (a 100,000-DOF solid's matrices
        // hold 15 million entries), joined in order.
        let blocks = column_blocks(n);
        let parts: Vec<(Vec<usize>, Vec<usize>)> = blocks
            .par_windows(2)
            .map(|w| {
                let mut counts = Vec::with_capacity(w[1] - w[0]);
                let mut rows = Vec::new();
                let (mut merged, mut scratch) = (Vec::new(), Vec::new());
                for j in w[0]..w[1] {
                    merged.clear();
                    merged.push(j);
                    for m in mats {
                        merge_sorted(&merged, m.symbolic().row_idx_of_col_raw(j), &mut scratch);
                        std::mem::swap(&mut merged, &mut scratch);
                    }
                    rows.extend_from_slice(&merged);
                    counts.push(merged.len());
                }
                (counts, rows)
            })
            .collect();
        let mut col_ptr = Vec::with_capacity(n + 1);
        col_ptr.push(0);
        let mut row_idx = Vec::with_capacity(parts.iter().map(|p| p.1.len()).sum());
        for (counts, rows) in parts {
            for c in counts {
                col_ptr.push(col_ptr.last().expect("starts at 0") + c);
            }
            row_idx.extend(rows);
        }
        let nnz = row_idx.len();
        assert!(
            nnz < MIRROR as usize,
            "a union pattern of {nnz} entries does not fit the 32-bit positions"
        );
        let ps = SymbolicSparseColMat::new_checked(n, n, col_ptr, None, row_idx);
        // The union position of every stored entry of `m`.
        let map_of =
            |m: &Csc| positions_in(ps.as_ref(), m, &blocks).expect("every entry is in the union");
        let mut maps = Vec::with_capacity(mats.len());
        let values = match mats.first() {
            // The first source's pattern is the union (a solid's K0 holds every other
            // matrix's entries and the diagonal): its values as they are.
            Some(first) if first.val().len() == nnz => first.val().to_vec(),
            Some(first) => {
                let mut values = vec![0.0; nnz];
                for (&pos, &v) in map_of(first).iter().zip(first.val()) {
                    values[pos as usize] = v;
                }
                values
            }
            None => vec![0.0; nnz],
        };
        if !mats.is_empty() {
            maps.push(Vec::new());
        }
        maps.extend(mats.iter().skip(1).map(|m| map_of(m)));
        Self {
            pattern: Csc::new(ps, values),
            maps,
        }
    }
}

impl UnionPattern {
    /// The union of `first`'s pattern and the `others'`, taking `first` itself as the
    /// union when it already holds every other entry and its diagonal (a solid's `K0`
    /// holds `M`'s and the springs': no merge, and no copy of its 3.4 million entries on
    /// the four-bay frame); [`UnionPattern::new`] otherwise.
    pub fn with_first(n: usize, first: Csc, others: &[&Csc]) -> Self {
        let blocks = column_blocks(n);
        let s = first.symbolic();
        let has_diagonal = (0..n).all(|j| s.row_idx_of_col_raw(j).binary_search(&j).is_ok());
        if has_diagonal {
            let maps: Option<Vec<Vec<u32>>> =
                others.iter().map(|m| positions_in(s, m, &blocks)).collect();
            if let Some(rest) = maps {
                assert!(
                    first.val().len() < MIRROR as usize,
                    "a union pattern of {} entries does not fit the 32-bit positions",
                    first.val().len()
                );
                let mut maps = Vec::with_capacity(others.len() + 1);
                maps.push(Vec::new());
                maps.extend(rest);
                return Self {
                    pattern: first,
                    maps,
                };
            }
        }
        let mut all = Vec::with_capacity(others.len() + 1);
        all.push(&first);
        all.extend_from_slice(others);
        Self::new(n, &all)
    }
}

/// The position in `pattern` (rows sorted within each column) of every stored entry of
/// `m`, by columns, or `None` if one is not in it. Both sorted: one walk along each of
/// `pattern`'s columns, column blocks on the worker threads.
fn positions_in(
    pattern: SymbolicSparseColMatRef<'_, usize>,
    m: &Csc,
    blocks: &[usize],
) -> Option<Vec<u32>> {
    use rayon::prelude::*;
    let s = m.symbolic();
    let parts: Vec<Option<Vec<u32>>> = blocks
        .par_windows(2)
        .map(|w| {
            let mut map = Vec::new();
            for j in w[0]..w[1] {
                let rows = pattern.row_idx_of_col_raw(j);
                let base = pattern.col_ptr()[j];
                let mut r = 0;
                for &i in s.row_idx_of_col_raw(j) {
                    while r < rows.len() && rows[r] < i {
                        r += 1;
                    }
                    if r == rows.len() || rows[r] != i {
                        return None;
                    }
                    map.push((base + r) as u32);
                }
            }
            Some(map)
        })
        .collect();
    parts
        .into_iter()
        .collect::<Option<Vec<_>>>()
        .map(|p| p.concat())
}

/// `out` ← the sorted union of the sorted, duplicate-free `a` and `b`.
fn merge_sorted(a: &[usize], b: &[usize], out: &mut Vec<usize>) {
    out.clear();
    let (mut x, mut y) = (0, 0);
    while x < a.len() && y < b.len() {
        let (u, v) = (a[x], b[y]);
        out.push(u.min(v));
        x += usize::from(u <= v);
        y += usize::from(v <= u);
    }
    out.extend_from_slice(&a[x..]);
    out.extend_from_slice(&b[y..]);
}

/// Column blocks for the worker threads: boundaries from 0 to `n`, a few blocks per thread.
pub(in crate::core::model) fn column_blocks(n: usize) -> Vec<usize> {
    let blocks = if n < 4096 {
        1
    } else {
        4 * rayon::current_num_threads()
    };
    let mut b: Vec<usize> = (0..=blocks).map(|k| n * k / blocks).collect();
    b.dedup();
    b
}

/// A value array for `K(θ) − σM` that the source matrices of a union pattern scatter into:
/// the union's own, or its reordered lower triangle.
pub trait ValueLayout {
    /// Per source matrix, the position of each of its stored entries in the value array,
    /// or [`MIRROR`] for an entry the array does not hold (its symmetric twin does). Empty
    /// for a source stored on the layout's own pattern (the union's first) and for one
    /// without entries.
    fn maps(&self) -> &[Vec<u32>];

    /// `out += alpha · (source matrix k)` on the value array (for a source stored on the
    /// layout's own pattern, `mat` is that matrix).
    fn add_into(&self, k: usize, mat: &Csc, alpha: f64, out: &mut [f64]) {
        let map = &self.maps()[k];
        if map.is_empty() {
            debug_assert!(mat.val().is_empty() || mat.val().len() == out.len());
            for (o, &v) in out.iter_mut().zip(mat.val()) {
                *o += alpha * v;
            }
            return;
        }
        for (&pos, &v) in map.iter().zip(mat.val()) {
            if pos != MIRROR {
                out[pos as usize] += alpha * v;
            }
        }
    }
}

impl ValueLayout for UnionPattern {
    fn maps(&self) -> &[Vec<u32>] {
        &self.maps
    }
}

/// Marks a source entry a [`ValueLayout`] does not hold: in
/// [`Reordered`](super::Reordered), one above the diagonal.
pub const MIRROR: u32 = u32::MAX;

#[cfg(test)]
mod tests {
    use super::super::csc::{csc_from_triplets, symmetric_triplets};
    use super::*;

    /// `UnionPattern::with_first` takes the first matrix as the union when it holds the
    /// others' entries and its diagonal, and builds the union as `new` does otherwise: the
    /// same pattern, values and maps either way, each map pointing at its entry's row and
    /// column.
    #[test]
    fn a_union_taken_from_its_first_matrix_is_the_merged_union() {
        let n = 9;
        let sym = |k, off| symmetric_triplets(n, k, off);
        let a = csc_from_triplets(n, sym(12, 1).into_iter());
        // Inside a's pattern: a's entries of every other column, scaled.
        let inside = csc_from_triplets(
            n,
            (0..n).step_by(2).flat_map(|j| {
                let a = &a;
                a.symbolic()
                    .row_idx_of_col_raw(j)
                    .iter()
                    .map(move |&i| (i, j, 2.0 + i as f64))
                    .collect::<Vec<_>>()
            }),
        );
        let outside = csc_from_triplets(n, sym(5, 3).into_iter());
        for other in [&inside, &outside] {
            let merged = UnionPattern::new(n, &[&a, other]);
            let taken = UnionPattern::with_first(n, a.clone(), &[other]);
            assert_eq!(
                taken.pattern.symbolic().col_ptr(),
                merged.pattern.symbolic().col_ptr()
            );
            assert_eq!(
                taken.pattern.symbolic().row_idx(),
                merged.pattern.symbolic().row_idx()
            );
            assert_eq!(taken.pattern.val(), merged.pattern.val());
            assert_eq!(taken.maps, merged.maps);
            let u = taken.pattern.symbolic();
            for j in 0..n {
                let range = other.symbolic().col_ptr()[j]..other.symbolic().col_ptr()[j + 1];
                for (k, &i) in range.clone().zip(other.symbolic().row_idx_of_col_raw(j)) {
                    let pos = taken.maps[1][k] as usize;
                    assert!(u.col_ptr()[j] <= pos && pos < u.col_ptr()[j + 1]);
                    assert_eq!(u.row_idx()[pos], i);
                }
            }
        }
        // The first case took a's own pattern: nothing was added.
        let taken = UnionPattern::with_first(n, a.clone(), &[&inside]);
        assert_eq!(taken.pattern.symbolic().row_idx(), a.symbolic().row_idx());
        let merged = UnionPattern::new(n, &[&a, &outside]);
        assert!(merged.pattern.symbolic().row_idx().len() > a.symbolic().row_idx().len());
    }
}
