//! Models from matrices (`boltwatch.matrices.v1`, what `boltwatch export-matrices` writes
//! and any FE program can): `model.json` (the structure's name, the DOF count, the
//! parameters with their `K_l` files, the channels as rows of `D`), `dofs.txt` (one DOF
//! label per line) and Matrix Market files for `K0`, every `K_l` and `M` (read by
//! [`read_matrix_market`]). Every error names the file and the entry (line), and nothing is
//! half-loaded: the model exists only once every file has been read and checked.

use std::collections::HashSet;
use std::path::{Path, PathBuf};

use serde::Deserialize;

use super::finish::finish;
use super::matrix_market::err;
pub use super::matrix_market::{ImportError, SYMMETRY_TOL, read_matrix_market};
use super::sparse::{Csc, Reordered, csc_from_lower};
use super::spec::BayesSpec;
use super::{Channel, Connection, Location, Model, ModelError, Parameter, ParameterKind};

/// The schema name in `model.json`.
pub const MATRICES_SCHEMA: &str = "boltwatch.matrices.v1";

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

/// Reads a `boltwatch.matrices.v1` model from its `model.json`: the description, its
/// parameters, channels and locations checked (cheap checks before the large files), the
/// DOF labels, every matrix file, then the model built and checked.
pub fn read_matrices(json: &Path) -> Result<Model, ImportError> {
    let file = read_description(json)?;
    let n = file.n_dof;
    let dir = json.parent().unwrap_or(Path::new("."));
    check_parameters(json, &file.parameters)?;
    check_channels(json, &file.channels, n)?;
    check_locations(json, &file.locations, n)?;
    let labels = read_labels(&dir.join(&file.dofs), n)?;
    let mats = read_matrix_files(&file, dir)?;
    build_model(json, dir, file, labels, mats)
}

/// `model.json`, parsed, with its schema, structure name and DOF count checked.
fn read_description(json: &Path) -> Result<MatricesFile, ImportError> {
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
    Ok(file)
}

/// The parameters' names (non-empty, distinct), stiffnesses, nominal values and bounds; at
/// least one parameter.
fn check_parameters(json: &Path, parameters: &[ParameterEntry]) -> Result<(), ImportError> {
    let mut names = HashSet::new();
    for (l, p) in parameters.iter().enumerate() {
        if p.name.trim().is_empty() {
            return Err(err(json, format!("parameters[{l}].name: empty")));
        }
        if !names.insert(p.name.as_str()) {
            return Err(err(
                json,
                format!("parameters[{l}].name: `{}` is defined twice", p.name),
            ));
        }
        check_parameter_values(json, p)?;
    }
    if parameters.is_empty() {
        return Err(err(json, "parameters: none (at least one K_l is needed)"));
    }
    Ok(())
}

/// One parameter's stiffness (a `connection`'s only), nominal value and bounds.
fn check_parameter_values(json: &Path, p: &ParameterEntry) -> Result<(), ImportError> {
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
    Ok(())
}

/// The channels' names (distinct) and DOFs (some, in range, finite weights).
fn check_channels(json: &Path, channels: &[ChannelEntry], n: usize) -> Result<(), ImportError> {
    let mut channel_names = HashSet::new();
    for (c, ch) in channels.iter().enumerate() {
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
    Ok(())
}

/// The locations' names (non-empty, distinct) and DOFs (some, in range, distinct).
fn check_locations(json: &Path, locations: &[LocationEntry], n: usize) -> Result<(), ImportError> {
    let mut location_names = HashSet::new();
    for (k, loc) in locations.iter().enumerate() {
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
    Ok(())
}

/// `K0` (zero when the file names none), every `K_l` and `M`, read side by side (each
/// parsed in chunks as well); a failure is reported for the first bad file in this order.
fn read_matrix_files(file: &MatricesFile, dir: &Path) -> Result<Vec<Csc>, ImportError> {
    let n = file.n_dof;
    let at = |name: &str| -> PathBuf { dir.join(name) };
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
    read.into_iter().collect::<Result<Vec<Csc>, _>>()
}

/// The model of a checked description, its labels and its matrices: its parameters (and
/// the connections they stand for) and channels, the checks of every assembly
/// ([`finish`]; an error about `M` names its file) and of definiteness
/// ([`check_definite`]), then its locations.
fn build_model(
    json: &Path,
    dir: &Path,
    file: MatricesFile,
    labels: Vec<String>,
    mats: Vec<Csc>,
) -> Result<Model, ImportError> {
    let (parameters, connections) = model_parameters(&file.parameters);
    let channels = file
        .channels
        .into_iter()
        .map(|c| Channel {
            name: c.name,
            dofs: c.dofs,
        })
        .collect();
    let mass_path = dir.join(&file.mass);
    let mut model = finish(
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
    })?;
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
}

/// The model's parameters, and the connections they stand for: a connection parameter
/// with a stiffness stands for one connection of that stiffness (named after it); the
/// file's name stands for the members and springs.
fn model_parameters(entries: &[ParameterEntry]) -> (Vec<Parameter>, Vec<Connection>) {
    let mut connections = Vec::new();
    let parameters: Vec<Parameter> = entries
        .iter()
        .enumerate()
        .map(|(l, p)| Parameter {
            name: p.name.clone(),
            nominal: p.nominal,
            lower: p.lower,
            upper: p.upper,
            kind: parameter_kind(l, p, &mut connections),
        })
        .collect();
    (parameters, connections)
}

/// What parameter `l` (entry `p`) scales; the connections a `connection` parameter stands
/// for are appended to `connections`.
fn parameter_kind(
    l: usize,
    p: &ParameterEntry,
    connections: &mut Vec<Connection>,
) -> ParameterKind {
    match p.kind {
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
        Kind::Modulus if !p.elements.is_empty() => ParameterKind::Modulus(p.elements.clone()),
        Kind::Modulus => ParameterKind::Modulus(vec![p.file.clone()]),
        Kind::Spring if !p.elements.is_empty() => ParameterKind::Springs(p.elements.clone()),
        Kind::Spring => ParameterKind::Springs(vec![p.file.clone()]),
        Kind::Matrix => ParameterKind::Matrix(p.file.clone()),
    }
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
    // M (with a unit diagonal on the massless DOFs) factorized beside K(θ0), on the other
    // worker thread.
    let m_values = mass_with_unit_massless(model, order);
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
    Err(stiffness_breakdown(model, order, values, json, at))
}

/// `M` plus the identity on the massless DOFs, whose rows and columns of `M` are zero
/// (checked by finish), on the value array of `order`'s lower triangle: positive definite
/// exactly when `M` is on the others.
fn mass_with_unit_massless(model: &Model, order: &Reordered) -> Vec<f64> {
    let diagonal_of = |j: usize| {
        order
            .diagonal_position(j)
            .expect("a massless DOF has stiffness on its diagonal (checked by finish)")
    };
    let mut m_values = vec![0.0; order.len()];
    model.subtract_mass_reordered(order, -1.0, &mut m_values);
    for &j in model.massless_dofs() {
        m_values[diagonal_of(j)] = 1.0;
    }
    m_values
}

/// Why the factorization of `K(θ0)` (`values`, on `order`'s lower triangle) broke down at
/// DOF `at`: singular on the massless DOFs, singular, or not positive semi-definite.
fn stiffness_breakdown(
    model: &Model,
    order: &Reordered,
    mut values: Vec<f64>,
    json: &Path,
    at: usize,
) -> ImportError {
    let labels = model.dof_labels();
    if let Some(j) = massless_breakdown(model, order, &values) {
        return err(
            json,
            format!(
                "K(θ0) at nominal θ is singular on the DOFs without mass: its factorization \
                 on them broke down at DOF `{}` (a part that neither mass nor stiffness \
                 holds: fix it, or give it stiffness or mass)",
                labels[j]
            ),
        );
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
    err(
        json,
        format!(
            "K(θ0) at nominal θ {what}: its factorization broke down at DOF `{}` ({why})",
            labels[at]
        ),
    )
}

/// Where the factorization of `K(θ0)` (`values`, on `order`'s lower triangle) on the
/// massless DOFs alone breaks down, if the model has massless DOFs and it does.
fn massless_breakdown(model: &Model, order: &Reordered, values: &[f64]) -> Option<usize> {
    let massless = model.massless_dofs();
    if massless.is_empty() {
        return None;
    }
    // K(θ0) on the massless DOFs alone: the entries that touch a DOF with mass zeroed,
    // a unit diagonal there.
    let mut has_mass = vec![true; model.n_dof()];
    massless.iter().for_each(|&j| has_mass[j] = false);
    let mut block = values.to_vec();
    let (ptr, rows) = (order.lower.col_ptr(), order.lower.row_idx());
    for c in 0..model.n_dof() {
        for k in ptr[c]..ptr[c + 1] {
            let (i, j) = (order.fwd[rows[k]], order.fwd[c]);
            if has_mass[i] || has_mass[j] {
                block[k] = if i == j { 1.0 } else { 0.0 };
            }
        }
    }
    order.cholesky_breakdown(&block)
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
