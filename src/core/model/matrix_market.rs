//! The Matrix Market reader of an imported model (`K0`, every `K_l` and `M`), and the
//! error every file of an import reports ([`ImportError`]).
//!
//! Matrix Market as programs write it: `coordinate real` (or `integer`), `symmetric` with
//! either triangle stored, or `general` (then checked for symmetry); `pattern`, `complex`,
//! `hermitian`, `skew-symmetric` and dense `array` files are refused. Every error names the
//! file and the entry (line).

use std::path::Path;

use super::sparse::{Csc, column_pairs, csc_from_lower, csc_from_one_triangle, csc_from_triplets};

/// Relative tolerance of the symmetry check of a `general` file: `|a_ij − a_ji|` against
/// the largest `|a|` of the matrix (a few roundings of a program that assembles both
/// triangles separately).
pub const SYMMETRY_TOL: f64 = 1e-12;

/// An import error: the file, and what is wrong where (of every file an import reads:
/// `model.json`, `dofs.txt` and the Matrix Market files).
#[derive(Debug, thiserror::Error, PartialEq)]
#[error("{file}: {reason}")]
pub struct ImportError {
    pub file: String,
    pub reason: String,
}

/// An [`ImportError`] naming `file`.
pub(super) fn err(file: &Path, reason: impl Into<String>) -> ImportError {
    ImportError {
        file: file.display().to_string(),
        reason: reason.into(),
    }
}

/// The lines of a Matrix Market file, numbered from 0.
type Lines<'a> = std::iter::Enumerate<std::str::Lines<'a>>;

/// How a Matrix Market file stores its matrix.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Symmetry {
    Symmetric,
    General,
}

/// Reads an `n × n` symmetric matrix from a Matrix Market file (module docs), as a CSC
/// matrix with both triangles stored: the header, the size line, the entries (their count
/// checked against the size line's), then the matrix from the stored triangle(s).
pub fn read_matrix_market(path: &Path, n: usize) -> Result<Csc, ImportError> {
    let text = std::fs::read_to_string(path).map_err(|e| err(path, format!("cannot read: {e}")))?;
    let mut lines = text.lines().enumerate();
    let symmetry = read_header(path, &mut lines)?;
    let (size_line, nnz) = read_size(path, &mut lines, n)?;
    // The entries: the body after the size line, parsed in chunks on the worker threads.
    let body_start = match lines.next() {
        Some((_, first)) => first.as_ptr() as usize - text.as_ptr() as usize,
        None => text.len(),
    };
    let chunks = parse_entries(path, &text, body_start, size_line + 1, n)?;
    drop(text);
    let count: usize = chunks.iter().map(Vec::len).sum();
    if count != nnz {
        return Err(err(
            path,
            format!("line {size_line} announces {nnz} entries, the file has {count}"),
        ));
    }
    symmetric_matrix(path, n, symmetry, &chunks)
}

/// Line 1, the `%%MatrixMarket matrix coordinate real|integer symmetric|general` header:
/// how the file stores its matrix.
fn read_header(path: &Path, lines: &mut Lines<'_>) -> Result<Symmetry, ImportError> {
    let (_, header) = lines
        .next()
        .ok_or_else(|| err(path, "empty file (no %%MatrixMarket header)"))?;
    let h: Vec<String> = header
        .split_whitespace()
        .map(|t| t.to_ascii_lowercase())
        .collect();
    if h.len() != 5 || h[0] != "%%matrixmarket" || h[1] != "matrix" {
        return Err(err(
            path,
            format!("line 1: not a Matrix Market matrix header: {header:?}"),
        ));
    }
    if h[2] != "coordinate" {
        return Err(err(
            path,
            format!(
                "line 1: `{}` format is not read (write the matrix as `coordinate`)",
                h[2]
            ),
        ));
    }
    if h[3] != "real" && h[3] != "integer" {
        return Err(err(
            path,
            format!(
                "line 1: `{}` entries are not read (a stiffness or mass matrix is `real`)",
                h[3]
            ),
        ));
    }
    let symmetry = match h[4].as_str() {
        "symmetric" => Symmetry::Symmetric,
        "general" => Symmetry::General,
        other => {
            return Err(err(
                path,
                format!(
                    "line 1: `{other}` matrices are not read (a stiffness or mass matrix is `symmetric`, or `general` with symmetric values)"
                ),
            ));
        }
    };
    Ok(symmetry)
}

/// The size line `rows cols entries` after the header's comments, checked to be `n × n`:
/// its line number (1-based) and the number of entries it announces.
fn read_size(path: &Path, lines: &mut Lines<'_>, n: usize) -> Result<(usize, usize), ImportError> {
    let (size_line, size) = loop {
        let (k, line) = lines
            .next()
            .ok_or_else(|| err(path, "no size line after the header"))?;
        let t = line.trim();
        if t.is_empty() || t.starts_with('%') {
            continue;
        }
        break (k + 1, t);
    };
    let dims: Vec<usize> = size
        .split_whitespace()
        .map(|t| t.parse::<usize>())
        .collect::<Result<_, _>>()
        .map_err(|_| {
            err(
                path,
                format!("line {size_line}: expected `rows cols entries`, got {size:?}"),
            )
        })?;
    let [rows, cols, nnz] = dims[..] else {
        return Err(err(
            path,
            format!("line {size_line}: expected `rows cols entries`, got {size:?}"),
        ));
    };
    if rows != n || cols != n {
        return Err(err(
            path,
            format!("line {size_line}: the matrix is {rows} × {cols}, the model has {n} DOFs"),
        ));
    }
    Ok((size_line, nnz))
}

/// The symmetric matrix, both triangles stored, of a file's entries (in the chunks they
/// were parsed in): one triangle of a `symmetric` file, a `general` file's checked to be
/// symmetric ([`symmetric_lower`]).
fn symmetric_matrix(
    path: &Path,
    n: usize,
    symmetry: Symmetry,
    chunks: &[Entries],
) -> Result<Csc, ImportError> {
    match symmetry {
        // One triangle, whichever; an off-diagonal pair given twice would count twice.
        Symmetry::Symmetric => csc_from_one_triangle(n, chunks).map_err(|(r, c)| {
            err(
                path,
                format!(
                    "entry ({}, {}) is given twice (a `symmetric` file stores one triangle)",
                    r + 1,
                    c + 1
                ),
            )
        }),
        Symmetry::General => Ok(csc_from_lower(
            n,
            &symmetric_lower(path, n, &chunks.concat())?,
        )),
    }
}

/// Entries `(row, column, value)` of a matrix file, 0-based.
type Entries = Vec<(usize, usize, f64)>;

/// A chunk's first bad line: its line within the chunk (0-based), why, and its text.
type ChunkError<'a> = (usize, BadLine, &'a str);

/// A line of a coordinate body that is not an entry of the matrix.
enum BadLine {
    Malformed,
    Outside(usize, usize),
    NotFinite(usize, usize, f64),
}

/// The `(row, column, value)` entries (0-based) of a coordinate body starting at byte
/// `body_start` of `text`, which is line `first_line` (1-based), in file order, in the
/// chunks they were parsed in. Parsed in
/// chunks split at line ends, one per worker thread and a few more (a 190 MB `K0` of a
/// 100,000-DOF solid: 7.6 million entries); an error names the first bad line of the file.
fn parse_entries(
    path: &Path,
    text: &str,
    body_start: usize,
    first_line: usize,
    n: usize,
) -> Result<Vec<Entries>, ImportError> {
    use rayon::prelude::*;
    let body = &text[body_start..];
    let pieces = if body.len() < 1 << 20 {
        1
    } else {
        4 * rayon::current_num_threads()
    };
    let mut bounds = vec![0];
    for k in 1..pieces {
        let from = (body.len() * k / pieces).max(*bounds.last().expect("starts at 0"));
        let end = body.as_bytes()[from..]
            .iter()
            .position(|&b| b == b'\n')
            .map_or(body.len(), |p| from + p + 1);
        bounds.push(end);
    }
    bounds.push(body.len());
    bounds.dedup();
    let parsed: Vec<Result<Entries, ChunkError>> = bounds
        .par_windows(2)
        .map(|w| parse_chunk(&body[w[0]..w[1]], n))
        .collect();
    let mut entries = Vec::with_capacity(parsed.len());
    for (c, chunk) in parsed.into_iter().enumerate() {
        match chunk {
            Ok(e) => entries.push(e),
            Err((local, bad, t)) => {
                let before = body.as_bytes()[..bounds[c]]
                    .iter()
                    .filter(|&&b| b == b'\n')
                    .count();
                let line = first_line + before + local;
                return Err(err(
                    path,
                    match bad {
                        BadLine::Malformed => {
                            format!("line {line}: expected `row col value`, got {t:?}")
                        }
                        BadLine::Outside(i, j) => format!(
                            "line {line}: entry ({i}, {j}) is outside the {n} × {n} matrix \
                             (indices are 1-based)"
                        ),
                        BadLine::NotFinite(i, j, v) => {
                            format!("line {line}: entry ({i}, {j}) is {v}")
                        }
                    },
                ));
            }
        }
    }
    Ok(entries)
}

/// The entries of one chunk of lines, or the first bad one: its line within the chunk
/// (0-based), why, and its text.
fn parse_chunk(chunk: &str, n: usize) -> Result<Entries, ChunkError<'_>> {
    let mut out = Vec::with_capacity(chunk.len() / 24);
    for (k, line) in chunk.lines().enumerate() {
        let t = line.trim();
        if t.is_empty() || t.starts_with('%') {
            continue;
        }
        let mut it = t.split_ascii_whitespace();
        let (Some(i), Some(j), Some(v), None) = (it.next(), it.next(), it.next(), it.next()) else {
            return Err((k, BadLine::Malformed, t));
        };
        let (Ok(i), Ok(j), Ok(v)) = (i.parse::<usize>(), j.parse::<usize>(), v.parse::<f64>())
        else {
            return Err((k, BadLine::Malformed, t));
        };
        if i == 0 || j == 0 || i > n || j > n {
            return Err((k, BadLine::Outside(i, j), t));
        }
        if !v.is_finite() {
            return Err((k, BadLine::NotFinite(i, j, v), t));
        }
        out.push((i - 1, j - 1, v));
    }
    Ok(out)
}

/// The lower triangle of a `general` file's matrix, checked to be symmetric within
/// [`SYMMETRY_TOL`] (duplicates summed, as Matrix Market readers do).
fn symmetric_lower(
    path: &Path,
    n: usize,
    entries: &[(usize, usize, f64)],
) -> Result<Vec<(usize, usize, f64)>, ImportError> {
    let a = csc_from_triplets(n, entries.iter().copied());
    let at = csc_from_triplets(n, entries.iter().map(|&(i, j, v)| (j, i, v)));
    let scale = a.val().iter().fold(0.0_f64, |m, v| m.max(v.abs()));
    let mut lower = Vec::with_capacity(entries.len() / 2 + n);
    for j in 0..n {
        for (i, x, y) in column_pairs(&a, &at, j) {
            if (x - y).abs() > SYMMETRY_TOL * scale {
                return Err(err(
                    path,
                    format!(
                        "not symmetric: entry ({}, {}) is {x:e}, entry ({}, {}) is {y:e}",
                        i + 1,
                        j + 1,
                        j + 1,
                        i + 1
                    ),
                ));
            }
            if i >= j {
                lower.push((i, j, x));
            }
        }
    }
    Ok(lower)
}

#[cfg(test)]
mod tests {
    use std::path::PathBuf;

    use super::*;

    fn write(dir: &Path, name: &str, text: &str) -> PathBuf {
        let p = dir.join(name);
        std::fs::write(&p, text).unwrap();
        p
    }

    fn tmp(name: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("bw-import-{name}-{}", std::process::id()));
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    fn dense(a: &Csc, n: usize) -> Vec<Vec<f64>> {
        let s = a.symbolic();
        let mut m = vec![vec![0.0; n]; n];
        for (j, c) in (0..n).map(|j| (j, s.row_idx_of_col_raw(j))) {
            for (&i, &v) in c.iter().zip(a.val_of_col(j)) {
                m[i][j] += v;
            }
        }
        m
    }

    /// The same matrix stored as the lower triangle, as the upper triangle and as a
    /// `general` file reads back identically, with both triangles.
    #[test]
    fn either_triangle_or_general_reads_the_same_matrix() {
        let d = tmp("triangles");
        let want = vec![
            vec![4.0, -1.0, 0.0],
            vec![-1.0, 4.0, -2.5],
            vec![0.0, -2.5, 3.0],
        ];
        let lower = write(
            &d,
            "l.mtx",
            "%%MatrixMarket matrix coordinate real symmetric\n% c\n3 3 5\n1 1 4\n2 1 -1\n2 2 4\n3 2 -2.5\n3 3 3\n",
        );
        let upper = write(
            &d,
            "u.mtx",
            "%%MatrixMarket matrix coordinate real symmetric\n3 3 5\n1 1 4\n1 2 -1\n2 2 4\n2 3 -2.5\n3 3 3\n",
        );
        let general = write(
            &d,
            "g.mtx",
            "%%MatrixMarket matrix coordinate real general\n3 3 7\n1 1 4\n1 2 -1\n2 1 -1\n2 2 4\n2 3 -2.5\n3 2 -2.5\n3 3 3\n",
        );
        for p in [lower, upper, general] {
            let a = read_matrix_market(&p, 3).unwrap();
            assert_eq!(dense(&a, 3), want, "{}", p.display());
        }
    }

    #[test]
    fn malformed_matrix_files_are_refused_naming_the_entry() {
        let d = tmp("malformed");
        let cases = [
            (
                "pattern",
                "%%MatrixMarket matrix coordinate pattern symmetric\n2 2 1\n1 1\n",
                "`pattern` entries",
            ),
            (
                "complex",
                "%%MatrixMarket matrix coordinate complex symmetric\n2 2 1\n1 1 1 0\n",
                "`complex` entries",
            ),
            (
                "array",
                "%%MatrixMarket matrix array real general\n2 2\n1\n0\n0\n1\n",
                "`array` format",
            ),
            (
                "size",
                "%%MatrixMarket matrix coordinate real symmetric\n3 3 1\n1 1 1\n",
                "3 × 3, the model has 2",
            ),
            (
                "range",
                "%%MatrixMarket matrix coordinate real symmetric\n2 2 1\n3 1 1\n",
                "entry (3, 1) is outside",
            ),
            (
                "nan",
                "%%MatrixMarket matrix coordinate real symmetric\n2 2 1\n1 1 nan\n",
                "line 3: entry (1, 1) is NaN",
            ),
            (
                "count",
                "%%MatrixMarket matrix coordinate real symmetric\n2 2 2\n1 1 1\n",
                "announces 2 entries, the file has 1",
            ),
            (
                "twice",
                "%%MatrixMarket matrix coordinate real symmetric\n2 2 2\n2 1 1\n1 2 1\n",
                "entry (2, 1) is given twice",
            ),
            (
                "asym",
                "%%MatrixMarket matrix coordinate real general\n2 2 2\n2 1 1\n1 2 2\n",
                "not symmetric: entry (2, 1)",
            ),
            ("header", "hello\n", "not a Matrix Market matrix header"),
        ];
        for (name, text, want) in cases {
            let p = write(&d, &format!("{name}.mtx"), text);
            let e = read_matrix_market(&p, 2).unwrap_err();
            assert!(e.file.ends_with(&format!("{name}.mtx")), "{e}");
            assert!(e.reason.contains(want), "{name}: {e}");
        }
    }
}
