//! Models from matrices (`boltwatch.matrices.v1`, what `boltwatch export-matrices` writes
//! and any FE program can): `model.json` (the structure's name, the DOF count, the
//! parameters with their `K_l` files, the channels as rows of `D`), `dofs.txt` (one DOF
//! label per line) and Matrix Market files for `K0`, every `K_l` and `M`.
//!
//! Matrix Market as programs write it: `coordinate real` (or `integer`), `symmetric` with
//! either triangle stored, or `general` (then checked for symmetry); `pattern`, `complex`,
//! `hermitian`, `skew-symmetric` and dense `array` files are refused. Every error names the
//! file and the entry (line), and nothing is half-loaded: the model exists only once every
//! file has been read and checked.

use std::collections::HashSet;
use std::path::{Path, PathBuf};

use serde::Deserialize;

use super::finish::finish;
use super::sparse::{Csc, column_pairs, csc_from_lower, csc_from_one_triangle, csc_from_triplets};
use super::spec::BayesSpec;
use super::{Channel, Connection, Location, Model, ModelError, Parameter, ParameterKind};

/// The schema name in `model.json`.
pub const MATRICES_SCHEMA: &str = "boltwatch.matrices.v1";

/// Relative tolerance of the symmetry check of a `general` file: `|a_ij − a_ji|` against
/// the largest `|a|` of the matrix (a few roundings of a program that assembles both
/// triangles separately).
pub const SYMMETRY_TOL: f64 = 1e-12;

/// An import error: the file, and what is wrong where.
#[derive(Debug, thiserror::Error, PartialEq)]
#[error("{file}: {reason}")]
pub struct ImportError {
    pub file: String,
    pub reason: String,
}

fn err(file: &Path, reason: impl Into<String>) -> ImportError {
    ImportError {
        file: file.display().to_string(),
        reason: reason.into(),
    }
}

/// `model.json`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct MatricesFile {
    schema: String,
    structure: String,
    n_dof: usize,
    /// Informative (`K(θ) = K0 + Σ θ_l K_l`).
    #[serde(default)]
    #[allow(dead_code)]
    stiffness: Option<String>,
    /// Informative: every file (the ones read are named below).
    #[serde(default)]
    #[allow(dead_code)]
    files: Vec<String>,
    /// `K0`; `null`: none (all of `K` is in the `K_l`).
    #[serde(default = "default_k0")]
    k0: Option<String>,
    #[serde(default = "default_m")]
    mass: String,
    #[serde(default = "default_dofs")]
    dofs: String,
    parameters: Vec<ParameterEntry>,
    #[serde(default)]
    channels: Vec<ChannelEntry>,
    /// Named places (a floor node's translations, a bearing): what `diagnose` and
    /// `simulate --inject` can name.
    #[serde(default)]
    locations: Vec<LocationEntry>,
    /// Defaults of the Bayesian MAP, as a model file's `[bayesian]`.
    #[serde(default)]
    bayesian: BayesSpec,
}

fn default_k0() -> Option<String> {
    Some("K0.mtx".into())
}
fn one() -> f64 {
    1.0
}
fn default_m() -> String {
    "M.mtx".into()
}
fn default_dofs() -> String {
    "dofs.txt".into()
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct ParameterEntry {
    name: String,
    /// θ_l of the model as given (default 1).
    #[serde(default = "one")]
    nominal: f64,
    /// Bounds of θ_l that `update` (both methods) and the tracker keep it within. A lower
    /// bound of 0 means no limit but positivity (θ > 0 is kept by the log parameterization).
    #[serde(default)]
    lower: Option<f64>,
    #[serde(default)]
    upper: Option<f64>,
    file: String,
    /// What `K_l` is: `connection` (bolted connections: loosening alerts watch it),
    /// `modulus`, `spring` or `matrix` (the default: anything else).
    #[serde(default)]
    kind: Kind,
    /// For a `connection`: the nominal rotational stiffness θ_l multiplies (N·m/rad),
    /// reported in the estimates as `k·θ`.
    #[serde(default)]
    stiffness: Option<f64>,
    /// Names of what θ_l scales (connections, members or springs; default: the parameter
    /// itself): a coarser model's parameter that scales all of them passes its value on
    /// in a two-stage update (`--stage1-model`).
    #[serde(default)]
    elements: Vec<String>,
}

#[derive(Debug, Default, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
enum Kind {
    Connection,
    Modulus,
    Spring,
    #[default]
    Matrix,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct LocationEntry {
    name: String,
    /// DOF indices (0-based).
    dofs: Vec<usize>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct ChannelEntry {
    name: String,
    /// `[dof index (0-based), weight]` pairs.
    dofs: Vec<(usize, f64)>,
}

/// Reads a `boltwatch.matrices.v1` model from its `model.json`.
pub fn read_matrices(json: &Path) -> Result<Model, ImportError> {
    let text = std::fs::read_to_string(json).map_err(|e| err(json, format!("cannot read: {e}")))?;
    let file: MatricesFile =
        serde_json::from_str(&text).map_err(|e| err(json, format!("not a matrices file: {e}")))?;
    if file.schema != MATRICES_SCHEMA {
        return Err(err(
            json,
            format!(
                "schema: expected {MATRICES_SCHEMA:?}, got {:?}",
                file.schema
            ),
        ));
    }
    if file.structure.trim().is_empty() {
        return Err(err(json, "structure: empty name"));
    }
    let n = file.n_dof;
    if n == 0 {
        return Err(err(json, "n_dof: must be at least 1"));
    }
    let dir = json.parent().unwrap_or(Path::new("."));
    let at = |name: &str| -> PathBuf { dir.join(name) };

    // Parameters and channels first: cheap checks before the large files.
    let mut names = HashSet::new();
    for (l, p) in file.parameters.iter().enumerate() {
        if p.name.trim().is_empty() {
            return Err(err(json, format!("parameters[{l}].name: empty")));
        }
        if !names.insert(p.name.as_str()) {
            return Err(err(
                json,
                format!("parameters[{l}].name: `{}` is defined twice", p.name),
            ));
        }
        if let Some(k) = p.stiffness
            && (p.kind != Kind::Connection || !(k.is_finite() && k > 0.0))
        {
            return Err(err(
                json,
                format!(
                    "parameters.{}.stiffness: {k} (a finite number > 0, for a `connection` only)",
                    p.name
                ),
            ));
        }
        if !(p.nominal.is_finite() && p.nominal > 0.0) {
            return Err(err(
                json,
                format!(
                    "parameters.{}.nominal: must be a finite number > 0, got {}",
                    p.name, p.nominal
                ),
            ));
        }
        let lower_ok = p
            .lower
            .is_none_or(|v| v.is_finite() && v >= 0.0 && v <= p.nominal);
        let upper_ok = p.upper.is_none_or(|v| v.is_finite() && v >= p.nominal);
        let apart = !matches!((p.lower, p.upper), (Some(a), Some(b)) if a >= b);
        if !(lower_ok && upper_ok && apart) {
            return Err(err(
                json,
                format!(
                    "parameters.{}: need 0 ≤ lower ≤ nominal ≤ upper < ∞ and lower < upper, got lower \
                     {}, nominal {}, upper {}",
                    p.name,
                    p.lower.map_or("none".into(), |v| v.to_string()),
                    p.nominal,
                    p.upper.map_or("none".into(), |v| v.to_string()),
                ),
            ));
        }
    }
    if file.parameters.is_empty() {
        return Err(err(json, "parameters: none (at least one K_l is needed)"));
    }
    let mut channel_names = HashSet::new();
    for (c, ch) in file.channels.iter().enumerate() {
        if !channel_names.insert(ch.name.as_str()) {
            return Err(err(
                json,
                format!("channels[{c}].name: `{}` is defined twice", ch.name),
            ));
        }
        if ch.dofs.is_empty() {
            return Err(err(json, format!("channels.{}.dofs: empty", ch.name)));
        }
        for &(i, w) in &ch.dofs {
            if i >= n {
                return Err(err(
                    json,
                    format!(
                        "channels.{}.dofs: DOF {i} is out of range (n_dof = {n}, 0-based)",
                        ch.name
                    ),
                ));
            }
            if !w.is_finite() {
                return Err(err(
                    json,
                    format!("channels.{}.dofs: weight of DOF {i} is {w}", ch.name),
                ));
            }
        }
    }

    let mut location_names = HashSet::new();
    for (k, loc) in file.locations.iter().enumerate() {
        if loc.name.trim().is_empty() {
            return Err(err(json, format!("locations[{k}].name: empty")));
        }
        if !location_names.insert(loc.name.as_str()) {
            return Err(err(
                json,
                format!("locations[{k}].name: `{}` is defined twice", loc.name),
            ));
        }
        if loc.dofs.is_empty() {
            return Err(err(json, format!("locations.{}.dofs: empty", loc.name)));
        }
        let mut seen = HashSet::new();
        for &i in &loc.dofs {
            if i >= n {
                return Err(err(
                    json,
                    format!(
                        "locations.{}.dofs: DOF {i} is out of range (n_dof = {n}, 0-based)",
                        loc.name
                    ),
                ));
            }
            if !seen.insert(i) {
                return Err(err(
                    json,
                    format!("locations.{}.dofs: DOF {i} is given twice", loc.name),
                ));
            }
        }
    }

    let dofs_path = at(&file.dofs);
    let labels = read_labels(&dofs_path, n)?;
    // K0, every K_l and M, read side by side (each parsed in chunks as well); a failure is
    // reported for the first bad file in this order.
    let files: Vec<Option<PathBuf>> = std::iter::once(file.k0.as_deref().map(at))
        .chain(file.parameters.iter().map(|p| Some(at(&p.file))))
        .chain(std::iter::once(Some(at(&file.mass))))
        .collect();
    let read: Vec<Result<Csc, ImportError>> = {
        use rayon::prelude::*;
        files
            .par_iter()
            .map(|f| match f {
                Some(path) => read_matrix_market(path, n),
                None => Ok(csc_from_lower(n, &[])),
            })
            .collect()
    };
    let mats = read.into_iter().collect::<Result<Vec<Csc>, _>>()?;

    // A connection parameter with a stiffness stands for one connection of that stiffness
    // (named after it); the file's name stands for the members and springs.
    let mut connections = Vec::new();
    let parameters = file
        .parameters
        .iter()
        .enumerate()
        .map(|(l, p)| Parameter {
            name: p.name.clone(),
            nominal: p.nominal,
            lower: p.lower,
            upper: p.upper,
            kind: match p.kind {
                Kind::Connection => {
                    // One connection per element (the parameter's name by default), of
                    // the stated stiffness (NaN when none is stated: not reported).
                    let names = if p.elements.is_empty() {
                        std::slice::from_ref(&p.name)
                    } else {
                        p.elements.as_slice()
                    };
                    ParameterKind::Connections(
                        names
                            .iter()
                            .map(|name| {
                                connections.push(Connection {
                                    name: name.clone(),
                                    member: p.file.clone(),
                                    node: String::new(),
                                    k: p.stiffness.unwrap_or(f64::NAN),
                                    parameter: Some(l),
                                });
                                connections.len() - 1
                            })
                            .collect(),
                    )
                }
                Kind::Modulus if !p.elements.is_empty() => {
                    ParameterKind::Modulus(p.elements.clone())
                }
                Kind::Modulus => ParameterKind::Modulus(vec![p.file.clone()]),
                Kind::Spring if !p.elements.is_empty() => {
                    ParameterKind::Springs(p.elements.clone())
                }
                Kind::Spring => ParameterKind::Springs(vec![p.file.clone()]),
                Kind::Matrix => ParameterKind::Matrix(p.file.clone()),
            },
        })
        .collect();
    let channels = file
        .channels
        .into_iter()
        .map(|c| Channel {
            name: c.name,
            dofs: c.dofs,
        })
        .collect();
    let mass_path = at(&file.mass);
    finish(
        &file.structure,
        labels,
        mats,
        parameters,
        connections,
        channels,
        file.bayesian,
    )
    .map_err(|e| match e {
        ModelError::Mass { .. } => err(&mass_path, e.to_string()),
        _ => err(json, e.to_string()),
    })
    .and_then(|mut model| {
        check_definite(&model, json, &mass_path)?;
        model.locations = file
            .locations
            .into_iter()
            .map(|l| Location {
                name: l.name,
                dofs: l.dofs,
            })
            .collect();
        Ok(model)
    })
}

/// What the solvers need of an imported model and only a factorization shows: `M`
/// positive definite on the DOFs that carry mass, and `K(θ0)` (nominal θ) positive
/// definite. A failure names the DOF at which the Cholesky factorization broke down and
/// says why: `K(θ0)` singular on the massless DOFs (a part that neither mass nor stiffness
/// holds), singular (a rigid-body motion or mechanism: the structure must be supported), or
/// not positive semi-definite. Both factorizations reuse the model's reordered pattern,
/// which the solvers need anyway.
fn check_definite(model: &Model, json: &Path, mass_path: &Path) -> Result<(), ImportError> {
    let order = model
        .reordered()
        .map_err(|e| err(json, format!("cannot analyse the matrices' pattern: {e:?}")))?;
    let labels = model.dof_labels();
    let massless = model.massless_dofs();
    let diagonal_of = |j: usize| {
        order
            .diagonal_position(j)
            .expect("a massless DOF has stiffness on its diagonal (checked by finish)")
    };
    // M plus the identity on the massless DOFs, whose rows and columns of M are zero
    // (checked by finish): positive definite exactly when M is on the others. Factorized
    // beside K(θ0), on the other worker thread.
    let mut m_values = vec![0.0; order.len()];
    model.subtract_mass_reordered(order, -1.0, &mut m_values);
    for &j in massless {
        m_values[diagonal_of(j)] = 1.0;
    }
    let mut values = vec![0.0; order.len()];
    model.shifted_stiffness_reordered(order, &model.nominal_theta(), 0.0, &mut values);
    let (m_breakdown, k_breakdown) = rayon::join(
        || order.cholesky_breakdown(&m_values),
        || order.cholesky_breakdown(&values),
    );
    drop(m_values);
    if let Some(j) = m_breakdown {
        return Err(err(
            mass_path,
            format!(
                "M is not positive definite on the DOFs that carry mass (a negative or zero \
                 eigenvalue): its factorization broke down at DOF `{}`",
                labels[j]
            ),
        ));
    }
    let Some(at) = k_breakdown else {
        return Ok(());
    };
    if !massless.is_empty() {
        // K(θ0) on the massless DOFs alone: the entries that touch a DOF with mass zeroed,
        // a unit diagonal there.
        let mut has_mass = vec![true; model.n_dof()];
        massless.iter().for_each(|&j| has_mass[j] = false);
        let mut block = values.clone();
        let (ptr, rows) = (order.lower.col_ptr(), order.lower.row_idx());
        for c in 0..model.n_dof() {
            for k in ptr[c]..ptr[c + 1] {
                let (i, j) = (order.fwd[rows[k]], order.fwd[c]);
                if has_mass[i] || has_mass[j] {
                    block[k] = if i == j { 1.0 } else { 0.0 };
                }
            }
        }
        if let Some(j) = order.cholesky_breakdown(&block) {
            return Err(err(
                json,
                format!(
                    "K(θ0) at nominal θ is singular on the DOFs without mass: its factorization \
                     on them broke down at DOF `{}` (a part that neither mass nor stiffness \
                     holds: fix it, or give it stiffness or mass)",
                    labels[j]
                ),
            ));
        }
    }
    // Singular (to 1e-9 of the largest diagonal entry) or indefinite?
    let largest = (0..model.n_dof())
        .filter_map(|j| order.diagonal_position(j).map(|k| values[k]))
        .fold(0.0_f64, f64::max);
    for j in 0..model.n_dof() {
        if let Some(k) = order.diagonal_position(j) {
            values[k] += 1e-9 * largest;
        }
    }
    let (what, why) = if order.cholesky_breakdown(&values).is_none() {
        (
            "is singular (to 1e-9 of its largest diagonal entry)",
            "a rigid-body motion or a mechanism: boltwatch needs a supported structure",
        )
    } else {
        (
            "is not positive semi-definite",
            "it has a negative eigenvalue",
        )
    };
    Err(err(
        json,
        format!(
            "K(θ0) at nominal θ {what}: its factorization broke down at DOF `{}` ({why})",
            labels[at]
        ),
    ))
}

/// `dofs.txt`: exactly `n` non-empty, distinct labels.
fn read_labels(path: &Path, n: usize) -> Result<Vec<String>, ImportError> {
    let text = std::fs::read_to_string(path).map_err(|e| err(path, format!("cannot read: {e}")))?;
    let labels: Vec<String> = text.lines().map(|l| l.trim().to_string()).collect();
    let labels: Vec<String> = match labels.last() {
        Some(l) if l.is_empty() => labels[..labels.len() - 1].to_vec(),
        _ => labels,
    };
    if labels.len() != n {
        return Err(err(
            path,
            format!("{} labels for n_dof = {n}", labels.len()),
        ));
    }
    let mut seen = HashSet::new();
    for (k, l) in labels.iter().enumerate() {
        if l.is_empty() {
            return Err(err(path, format!("line {}: empty label", k + 1)));
        }
        if !seen.insert(l.as_str()) {
            return Err(err(
                path,
                format!("line {}: label `{l}` is given twice", k + 1),
            ));
        }
    }
    Ok(labels)
}

/// How a Matrix Market file stores its matrix.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Symmetry {
    Symmetric,
    General,
}

/// Reads an `n × n` symmetric matrix from a Matrix Market file (module docs), as a CSC
/// matrix with both triangles stored.
pub fn read_matrix_market(path: &Path, n: usize) -> Result<Csc, ImportError> {
    let text = std::fs::read_to_string(path).map_err(|e| err(path, format!("cannot read: {e}")))?;
    let mut lines = text.lines().enumerate();
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
    // The size line, after the comments.
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
    match symmetry {
        // One triangle, whichever; an off-diagonal pair given twice would count twice.
        Symmetry::Symmetric => csc_from_one_triangle(n, &chunks).map_err(|(r, c)| {
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
