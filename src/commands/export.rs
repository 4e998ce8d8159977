//! `boltwatch export-matrices`: `K0`, every `K_l` and `M` as Matrix Market files in the
//! model's DOF order (DESIGN §2), so other tools can work on the same matrices.
//!
//! Each file is `coordinate real symmetric` (the lower triangle, 1-based indices, values
//! with 17 significant digits so that they read back bit for bit). Beside them,
//! `dofs.txt` names each DOF (one per line, in order) and `model.json` lists the files,
//! the parameters (name and nominal θ) and the channels as rows of `D`.

use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use serde_json::json;

use super::{load_model, write_json};
use crate::core::model::{Csc, Model, Parameter, ParameterKind};

#[derive(Debug, clap::Args)]
pub struct ExportArgs {
    /// Model file (TOML), a bundled model (`bundled:lab-frame`, `bundled:space-frame`, ...),
    /// or the `model.json` of a model imported from matrices.
    #[arg(long)]
    pub model: PathBuf,
    /// Output directory (created if missing).
    #[arg(short, long)]
    pub out: PathBuf,
}

/// Writes the lower triangle of the symmetric `a` as a Matrix Market file.
pub fn write_matrix_market(path: &Path, a: &Csc, comment: &str) -> Result<()> {
    let file =
        std::fs::File::create(path).with_context(|| format!("cannot create {}", path.display()))?;
    let mut w = BufWriter::new(file);
    let s = a.symbolic();
    let lower = |j: usize| {
        s.row_idx_of_col_raw(j)
            .iter()
            .zip(a.val_of_col(j))
            .filter(move |&(&i, _)| i >= j)
    };
    let nnz: usize = (0..a.ncols()).map(|j| lower(j).count()).sum();
    writeln!(w, "%%MatrixMarket matrix coordinate real symmetric")?;
    writeln!(w, "% {comment}")?;
    writeln!(w, "{} {} {nnz}", a.nrows(), a.ncols())?;
    for j in 0..a.ncols() {
        for (&i, v) in lower(j) {
            writeln!(w, "{} {} {v:.16e}", i + 1, j + 1)?;
        }
    }
    w.flush()
        .with_context(|| format!("cannot write {}", path.display()))
}

/// The `kind` of a parameter in `model.json`.
fn kind_name(kind: &ParameterKind) -> &'static str {
    match kind {
        ParameterKind::Connections(_) => "connection",
        ParameterKind::Modulus(_) => "modulus",
        ParameterKind::Springs(_) => "spring",
        ParameterKind::Matrix(_) => "matrix",
    }
}

/// Exports `K0`, every `K_l` and `M` of the model, its DOF names (`dofs.txt`) and
/// `model.json` into the output directory.
pub fn run(args: &ExportArgs) -> Result<()> {
    let model = load_model(&args.model)?;
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("cannot create directory {}", args.out.display()))?;
    let files = exported_matrices(&model);
    write_matrices(&args.out, &model, &files)?;
    let dofs = args.out.join("dofs.txt");
    std::fs::write(&dofs, model.dof_labels().join("\n") + "\n")
        .with_context(|| format!("cannot write {}", dofs.display()))?;
    write_json(&args.out.join("model.json"), &model_json(&model, &files))?;
    Ok(())
}

/// The matrices exported, by file stem: `K0`, `K_<parameter>` for each parameter, `M`.
fn exported_matrices(model: &Model) -> Vec<(String, &Csc)> {
    let mut files = vec![("K0".to_string(), model.k0())];
    for (l, p) in model.parameters().iter().enumerate() {
        files.push((format!("K_{}", p.name), model.k_param(l)));
    }
    files.push(("M".to_string(), model.mass()));
    files
}

/// Writes each matrix as `<stem>.mtx` in `out`, printing a table of their sizes and
/// lower-triangle nonzeros.
fn write_matrices(out: &Path, model: &Model, files: &[(String, &Csc)]) -> Result<()> {
    println!("{:<24} {:>10} {:>12}", "file", "n", "nnz (lower)");
    for (name, a) in files {
        let path = out.join(format!("{name}.mtx"));
        write_matrix_market(
            &path,
            a,
            &format!(
                "{} of model {} (boltwatch export-matrices)",
                name, model.name
            ),
        )?;
        let s = a.symbolic();
        let nnz: usize = (0..a.ncols())
            .map(|j| s.row_idx_of_col_raw(j).iter().filter(|&&i| i >= j).count())
            .sum();
        println!(
            "{:<24} {:>10} {:>12}",
            format!("{name}.mtx"),
            a.nrows(),
            nnz
        );
    }
    Ok(())
}

/// `model.json`: the schema, the files, the parameters, the Bayesian defaults, the
/// channels as rows of `D` and the named locations.
fn model_json(model: &Model, files: &[(String, &Csc)]) -> serde_json::Value {
    json!({
        "schema": "boltwatch.matrices.v1",
        "structure": model.name,
        "n_dof": model.n_dof(),
        "stiffness": "K(θ) = K0 + Σ θ_l K_l",
        "files": files.iter().map(|(n, _)| format!("{n}.mtx")).collect::<Vec<_>>(),
        "parameters": model
            .parameters()
            .iter()
            .enumerate()
            .map(|(l, p)| parameter_json(model, l, p))
            .collect::<Vec<_>>(),
        "bayesian": model.bayesian,
        "channels": model.channels().iter().map(|c| json!({
            "name": c.name,
            "dofs": c.dofs.iter().map(|&(i, w)| json!([i, w])).collect::<Vec<_>>(),
        })).collect::<Vec<_>>(),
        "locations": model.locations().iter().map(|l| json!({
            "name": l.name,
            "dofs": l.dofs,
        })).collect::<Vec<_>>(),
    })
}

/// Parameter `l`'s entry in `model.json`: name, nominal θ, file and kind, then (where it
/// has them) its connection stiffness, the elements it scales and its bounds.
fn parameter_json(model: &Model, l: usize, p: &Parameter) -> serde_json::Value {
    let mut e = json!({
        "name": p.name,
        "nominal": p.nominal,
        "file": format!("K_{}.mtx", p.name),
        "kind": kind_name(&p.kind),
    });
    if let Some(k) = model.connection_stiffness(l) {
        e["stiffness"] = json!(k);
    }
    let elements: Vec<String> = model
        .parameter_elements(l)
        .into_iter()
        .filter(|(kind, _)| *kind != "matrix")
        .map(|(_, name)| name)
        .collect();
    if !elements.is_empty() {
        e["elements"] = json!(elements);
    }
    if let Some(v) = p.lower {
        e["lower"] = json!(v);
    }
    if let Some(v) = p.upper {
        e["upper"] = json!(v);
    }
    e
}
