//! Sparse symmetric matrices as the model holds them, and the union pattern on which
//! `K(θ) − λM` is formed without re-deriving structure.

use faer::Side;
use faer::sparse::linalg::cholesky::{
    SymbolicCholesky, SymmetricOrdering, factorize_symbolic_cholesky,
};
use faer::sparse::{SparseColMat, SymbolicSparseColMat, SymbolicSparseColMatRef, Triplet};
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

/// `Y = A X` for a symmetric sparse `A` and a block `X`, the rows of `Y` shared among
/// `parts` tasks on rayon's pool. By symmetry column `j` of the CSC storage is row `j`, so
/// each task gathers `Y[j, :] = Σ_i A_ij X[i, :]` for its rows from a row-interleaved copy
/// of `X`, reads only its share of `A` (the rows are split where the stored entries split
/// evenly), and keeps a row's sums in registers: columns go in groups of at most eight,
/// each group's width a compile-time constant. On the four-bay solid frame's mass matrix
/// (1.1M entries), six columns on two cores: 1.5 ms, against 3.6 ms for a scatter over
/// columns split between the cores (each reading all of `A`).
pub fn spmm_symmetric(a: &Csc, x: MatRef<'_, f64>, mut y: MatMut<'_, f64>, parts: usize) {
    let r = x.ncols();
    debug_assert_eq!(
        (a.nrows(), a.ncols(), y.nrows(), y.ncols()),
        (x.nrows(), x.nrows(), x.nrows(), r)
    );
    let mut first = 0;
    while first < r {
        let width = (r - first).min(8);
        let (xs, ys) = (
            x.subcols(first, width),
            y.as_mut().subcols_mut(first, width),
        );
        match width {
            1 => gather_rows::<1>(a, xs, ys, parts),
            2 => gather_rows::<2>(a, xs, ys, parts),
            3 => gather_rows::<3>(a, xs, ys, parts),
            4 => gather_rows::<4>(a, xs, ys, parts),
            5 => gather_rows::<5>(a, xs, ys, parts),
            6 => gather_rows::<6>(a, xs, ys, parts),
            7 => gather_rows::<7>(a, xs, ys, parts),
            _ => gather_rows::<8>(a, xs, ys, parts),
        }
        first += width;
    }
}

/// [`spmm_symmetric`] for `R` columns.
fn gather_rows<const R: usize>(a: &Csc, x: MatRef<'_, f64>, y: MatMut<'_, f64>, parts: usize) {
    let n = x.nrows();
    let s = a.symbolic();
    let col_ptr = s.col_ptr();
    let mut xi = vec![[0.0; R]; n];
    for (j, row) in xi.iter_mut().enumerate() {
        for (c, v) in row.iter_mut().enumerate() {
            *v = x[(j, c)];
        }
    }
    let xi = xi.as_slice();
    let parts = parts.clamp(1, n.max(1));
    let nnz = col_ptr[n];
    rayon::scope(|scope| {
        let mut rest = y;
        let mut first = 0;
        for p in 1..=parts {
            // First row of the next part: where the stored entries pass p/parts of all.
            let end = if p == parts {
                n
            } else {
                col_ptr
                    .partition_point(|&c| c < nnz * p / parts)
                    .clamp(first, n)
            };
            let (mut mine, tail) = rest.split_at_row_mut(end - first);
            rest = tail;
            let rows = first..end;
            first = end;
            scope.spawn(move |_| {
                for (local, j) in rows.enumerate() {
                    let mut acc = [0.0; R];
                    for (&i, &v) in s.row_idx_of_col_raw(j).iter().zip(a.val_of_col(j)) {
                        for (ac, xc) in acc.iter_mut().zip(&xi[i]) {
                            *ac += v * xc;
                        }
                    }
                    for (c, &v) in acc.iter().enumerate() {
                        mine[(local, c)] = v;
                    }
                }
            });
        }
    });
}

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

/// From this many DOFs the AMD ordering is computed on the quotient graph
/// (`amd_by_supervariables`). Below, AMD on the whole graph costs little (52 ms at the
/// four-bay frame's 31,458 DOF, so ~15 ms at this size) and gives the least fill; the quotient ordering's different rounding also
/// moved the sparse solver's eigenvectors on the 2,232-DOF two-bay solid from 0.9e-8 to
/// 1.2e-8 of the dense solver's, past that test's 1e-8.
pub const QUOTIENT_ORDERING_FROM_DOF: usize = 10_000;

/// The AMD ordering of a symmetric pattern (both triangles stored), as `(fwd, inv)`: the
/// ordering alone (faer's symbolic factorization with `Amd` would also analyse the
/// unpermuted pattern's factor, and throw it away).
fn amd_on_the_whole_graph(
    pattern: SymbolicSparseColMatRef<'_, usize>,
) -> Result<(Vec<usize>, Vec<usize>), faer::sparse::FaerError> {
    use faer::dyn_stack::{MemBuffer, MemStack};
    use faer::sparse::linalg::amd;
    let n = pattern.nrows();
    let (mut fwd, mut inv) = (vec![0usize; n], vec![0usize; n]);
    let nnz = pattern.row_idx().len();
    let mut mem = MemBuffer::try_new(amd::order_maybe_unsorted_scratch::<usize>(n, nnz))
        .map_err(|_| faer::sparse::FaerError::OutOfMemory)?;
    amd::order_maybe_unsorted(
        &mut fwd,
        &mut inv,
        pattern,
        amd::Control::default(),
        MemStack::new(&mut mem),
    )?;
    Ok((fwd, inv))
}

/// The AMD ordering of a symmetric pattern (both triangles stored, rows sorted), as
/// `(fwd, inv)`: computed on its quotient graph, where each run of consecutive columns with
/// the same rows is one node (a node's three translations in a solid mesh; such columns
/// are indistinguishable, each holding the others), then expanded, each run kept together
/// in its order. On the four-bay solid frame: 50 → 11 ms, for a factor 4.5 % larger (3.95
/// against 3.78 million entries; the whole `modes` run is faster by 40 ms).
fn amd_by_supervariables(
    pattern: SymbolicSparseColMatRef<'_, usize>,
) -> Result<(Vec<usize>, Vec<usize>), faer::sparse::FaerError> {
    let n = pattern.nrows();
    let mut run_start = Vec::with_capacity(n + 1);
    let mut run_of = Vec::with_capacity(n);
    for j in 0..n {
        if j == 0 || pattern.row_idx_of_col_raw(j) != pattern.row_idx_of_col_raw(j - 1) {
            run_start.push(j);
        }
        run_of.push(run_start.len() - 1);
    }
    let runs = run_start.len();
    run_start.push(n);
    // The quotient pattern: each run's rows, by run.
    let mut q_ptr = Vec::with_capacity(runs + 1);
    let mut q_rows: Vec<usize> = Vec::new();
    q_ptr.push(0);
    for &j in &run_start[..runs] {
        for &i in pattern.row_idx_of_col_raw(j) {
            let r = run_of[i];
            if q_rows.len() == *q_ptr.last().expect("starts at 0") || q_rows.last() != Some(&r) {
                q_rows.push(r);
            }
        }
        q_ptr.push(q_rows.len());
    }
    let quotient = SymbolicSparseColMat::new_checked(runs, runs, q_ptr, None, q_rows);
    let (q_fwd, _) = amd_on_the_whole_graph(quotient.as_ref())?;
    let fwd: Vec<usize> = q_fwd
        .iter()
        .flat_map(|&r| run_start[r]..run_start[r + 1])
        .collect();
    let mut inv = vec![0usize; n];
    for (new, &old) in fwd.iter().enumerate() {
        inv[old] = new;
    }
    Ok((fwd, inv))
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
pub(super) fn column_blocks(n: usize) -> Vec<usize> {
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

impl ValueLayout for Reordered {
    fn maps(&self) -> &[Vec<u32>] {
        &self.maps
    }
}

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

/// Marks a source entry a [`ValueLayout`] does not hold: in [`Reordered`], one above the
/// diagonal.
pub const MIRROR: u32 = u32::MAX;

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
    /// AMD ordering and symbolic factorization of a union pattern (symmetric, both
    /// triangles stored).
    pub fn new(union: &UnionPattern) -> Result<Self, faer::sparse::FaerError> {
        let pattern = union.pattern.symbolic();
        let n = pattern.nrows();
        let (fwd, inv) = if n < QUOTIENT_ORDERING_FROM_DOF {
            amd_on_the_whole_graph(pattern)?
        } else {
            amd_by_supervariables(pattern)?
        };
        // The lower triangle of P A Pᵀ, by columns, each entry with its union position. Its
        // entries are first placed by rows (the upper triangle's columns, in any order),
        // then read back row by row into their columns, which so come out sorted (two
        // counting passes, no sort per column: 50 → 36 ms on the four-bay solid frame,
        // most of it now the scattered writes).
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
        let nnz_lower = col_ptr[n];
        // (new column, union position) of every lower entry, grouped by new row.
        let mut by_row = vec![(0u32, 0u32); nnz_lower];
        let mut next = row_ptr.clone();
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
        let mut fill = col_ptr.clone();
        for r in 0..n {
            for &(c, pos) in &by_row[row_ptr[r]..row_ptr[r + 1]] {
                let c = c as usize;
                row_idx[fill[c]] = r;
                below[pos as usize] = fill[c] as u32;
                fill[c] += 1;
            }
        }
        drop(by_row);
        // faer reads an identity-ordered pattern as its upper triangle: the transpose
        // (columns read in order, so each of its columns comes out sorted).
        let upper_ptr = row_ptr;
        let mut fill = upper_ptr.clone();
        let mut upper_idx = vec![0usize; nnz_lower];
        for c in 0..n {
            for &r in &row_idx[col_ptr[c]..col_ptr[c + 1]] {
                upper_idx[fill[r]] = c;
                fill[r] += 1;
            }
        }
        let upper = SymbolicSparseColMat::new_checked(n, n, upper_ptr, None, upper_idx);
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

#[cfg(test)]
mod tests {
    use super::*;
    use faer::Mat;

    /// The row-split block product against column-by-column products on a symmetric
    /// pattern with an empty row and column and duplicates summed, 1 to 19 columns (groups
    /// of eight and a remainder), split into 1 to 9 parts (more than the rows, and parts
    /// with no entries): equal up to the order of additions (1e-14 of the entries' scale,
    /// which is 1).
    #[test]
    fn block_product_matches_column_products() {
        let n = 7;
        let entries: Vec<(usize, usize, f64)> = (0..40)
            .map(|k| ((k * 5 + 1) % n, (k * 3) % n, 0.1 * k as f64 - 1.7))
            .filter(|&(i, j, _)| i != 4 && j != 4)
            .flat_map(|(i, j, v)| [(i, j, v), (j, i, v)])
            .collect();
        let a = csc_from_triplets(n, entries.iter().copied());
        for r in 1..=19 {
            let x = Mat::from_fn(n, r, |i, j| (i as f64 + 1.0) * 0.3 - j as f64 * 0.7);
            for parts in 1..=9 {
                let mut y = Mat::from_fn(n, r, |_, _| f64::NAN);
                spmm_symmetric(&a, x.as_ref(), y.as_mut(), parts);
                for j in 0..r {
                    let xj: Vec<f64> = (0..n).map(|i| x[(i, j)]).collect();
                    let mut yj = vec![0.0; n];
                    spmv_add(&a, &xj, 1.0, &mut yj);
                    for i in 0..n {
                        assert!(
                            (y[(i, j)] - yj[i]).abs() < 1e-14,
                            "{r} columns, {parts} parts: ({i}, {j})"
                        );
                    }
                }
            }
        }
    }

    /// Triplets of a symmetric `n × n` matrix: `k` off-diagonal pairs placed by `off`, and
    /// a dominant diagonal.
    fn symmetric_triplets(n: usize, k: usize, off: usize) -> Vec<(usize, usize, f64)> {
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

    /// A 3-D grid of nodes with three DOFs each, every node coupled to its 26 neighbours
    /// (a solid mesh's pattern): the quotient-graph ordering is a permutation that keeps
    /// each node's DOFs together, and its Cholesky factor is within 10 % of the one from
    /// AMD on the whole graph (the four-bay frame: 4.5 %).
    #[test]
    fn the_quotient_ordering_keeps_nodes_together_at_little_extra_fill() {
        let (nx, ny, nz) = (12, 10, 6);
        let node = |x: usize, y: usize, z: usize| (z * ny + y) * nx + x;
        let n = 3 * nx * ny * nz;
        let mut col_ptr = vec![0];
        let mut row_idx = Vec::new();
        for z in 0..nz {
            for y in 0..ny {
                for x in 0..nx {
                    let mut rows = Vec::new();
                    for (zz, yy, xx) in (z.saturating_sub(1)..(z + 2).min(nz)).flat_map(|zz| {
                        (y.saturating_sub(1)..(y + 2).min(ny)).flat_map(move |yy| {
                            (x.saturating_sub(1)..(x + 2).min(nx)).map(move |xx| (zz, yy, xx))
                        })
                    }) {
                        rows.extend((0..3).map(|d| 3 * node(xx, yy, zz) + d));
                    }
                    rows.sort_unstable();
                    for _ in 0..3 {
                        row_idx.extend_from_slice(&rows);
                        col_ptr.push(row_idx.len());
                    }
                }
            }
        }
        let pattern = SymbolicSparseColMat::new_checked(n, n, col_ptr, None, row_idx);
        let (fwd, inv) = amd_by_supervariables(pattern.as_ref()).unwrap();
        for (new, &old) in fwd.iter().enumerate() {
            assert_eq!(inv[old], new);
        }
        for k in (0..n).step_by(3) {
            assert_eq!(fwd[k] % 3, 0, "a node's first DOF opens each triple");
            assert_eq!((fwd[k + 1], fwd[k + 2]), (fwd[k] + 1, fwd[k] + 2));
        }
        let fill = |perm: Option<(Vec<usize>, Vec<usize>)>| {
            let ordering = match &perm {
                Some((f, i)) => {
                    SymmetricOrdering::Custom(faer::perm::PermRef::new_checked(f, i, n))
                }
                None => SymmetricOrdering::Amd,
            };
            factorize_symbolic_cholesky(pattern.as_ref(), Side::Lower, ordering, Default::default())
                .unwrap()
                .len_val()
        };
        let (quotient, whole) = (fill(Some((fwd, inv))), fill(None));
        assert!(
            (quotient as f64) < 1.1 * whole as f64,
            "factor entries: quotient ordering {quotient}, whole graph {whole}"
        );
    }
}
