//! The command-line commands (DESIGN §2): file I/O and tables around the pure core.

pub mod bayes;
pub mod diagnose;
pub mod export;
pub mod modes;
pub mod publish;
pub mod replay;
pub mod report;
pub mod run;
pub mod scenario;
pub mod simulate;
pub mod update;

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};

use crate::core::model::Model;

/// `--model M.toml [--theta a,b,…]`: a model evaluated at θ (default: its nominal θ).
#[derive(Debug, clap::Args)]
pub struct ModelAtTheta {
    /// Model file (TOML).
    #[arg(long)]
    pub model: PathBuf,
    /// Parameter values θ, comma separated (default: the model's nominal θ).
    #[arg(long, allow_hyphen_values = true)]
    pub theta: Option<String>,
}

impl ModelAtTheta {
    /// Loads the model and parses θ against it.
    pub fn load(&self) -> Result<(Model, Vec<f64>)> {
        let model = load_model(&self.model)?;
        let theta = parse_theta(&model, self.theta.as_deref(), "--theta")?;
        Ok((model, theta))
    }
}

/// Reads a model file without assembling it.
pub fn load_spec(path: &Path) -> Result<crate::core::model::spec::ModelSpec> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("cannot read model file {}", path.display()))?;
    toml::from_str(&text).with_context(|| format!("model file {}", path.display()))
}

/// The model file of a watched structure, read once: its text form (the diagnosis
/// enriches it) and its assembly, checked to describe that structure.
pub fn load_structure(
    s: &crate::settings::StructureSettings,
) -> Result<(crate::core::model::spec::ModelSpec, Model)> {
    let spec = load_spec(&s.model)?;
    let model =
        Model::from_spec(&spec).with_context(|| format!("model file {}", s.model.display()))?;
    if model.name != s.name {
        bail!(
            "configuration key structures: structure `{}` has model file {} describing `{}`",
            s.name,
            s.model.display(),
            model.name
        );
    }
    Ok((spec, model))
}

/// Reads and assembles a model file.
pub fn load_model(path: &Path) -> Result<Model> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("cannot read model file {}", path.display()))?;
    Model::from_toml(&text).with_context(|| format!("model file {}", path.display()))
}

/// Parses `--theta a,b,...` against the model's parameters (default: nominal θ).
pub fn parse_theta(model: &Model, arg: Option<&str>, flag: &str) -> Result<Vec<f64>> {
    let Some(s) = arg else {
        return Ok(model.nominal_theta());
    };
    let values = s
        .split(',')
        .enumerate()
        .map(|(i, v)| {
            let x: f64 = v
                .trim()
                .parse()
                .with_context(|| format!("{flag}: entry {} `{v}` is not a number", i + 1))?;
            if !(x.is_finite() && x > 0.0) {
                bail!("{flag}: entry {} = {x} must be a finite number > 0", i + 1);
            }
            Ok(x)
        })
        .collect::<Result<Vec<f64>>>()?;
    if values.len() != model.n_params() {
        bail!(
            "{flag}: {} values given but model `{}` has {} parameters ({})",
            values.len(),
            model.name,
            model.n_params(),
            model
                .parameters()
                .iter()
                .map(|p| p.name.as_str())
                .collect::<Vec<_>>()
                .join(", ")
        );
    }
    Ok(values)
}

/// Writes pretty JSON to `path`.
pub fn write_json(path: &Path, value: &serde_json::Value) -> Result<()> {
    let text = serde_json::to_string_pretty(value)?;
    std::fs::write(path, text + "\n").with_context(|| format!("cannot write {}", path.display()))
}

/// Starts the `tracing` subscriber: human-readable lines on stderr, or JSON lines.
pub fn init_logging(log: &crate::settings::LogSettings) -> Result<()> {
    let filter = tracing_subscriber::EnvFilter::try_new(&log.level)
        .with_context(|| format!("configuration key log.level: `{}`", log.level))?;
    let b = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr);
    let r = match log.format {
        crate::settings::LogFormat::Human => b.try_init(),
        crate::settings::LogFormat::Json => b.json().try_init(),
    };
    // Already initialised (a second command in one process, tests): keep the first.
    let _ = r;
    Ok(())
}
