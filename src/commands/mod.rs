//! The command-line commands (DESIGN §2): file I/O and tables around the pure core.

pub mod bayes;
mod bayes_output;
pub mod diagnose;
pub mod export;
pub mod fleet;
pub mod identify;
pub mod identify_plot;
pub mod inputs;
pub mod modes;
pub mod normalisation;
pub mod plan;
pub mod progress;
pub mod publish;
pub mod replay;
pub mod report;
pub mod router;
pub mod run;
pub mod scenario;
pub mod simulate;
pub mod sweep;
pub mod update;

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};

use crate::core::model::Model;
pub use crate::io::model::{load_description, load_model, load_spec};

/// `--model M.toml [--theta a,b,…]`: a model evaluated at θ (default: its nominal θ).
#[derive(Debug, clap::Args)]
pub struct ModelAtTheta {
    /// Model file (TOML), a bundled model (`bundled:lab-frame`, `bundled:space-frame`, ...),
    /// or the `model.json` of a model imported from matrices.
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

/// Parses a comma-separated list of finite positive numbers given to `flag`.
pub fn parse_positive_list(s: &str, flag: &str) -> Result<Vec<f64>> {
    s.split(',')
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
        .collect()
}

/// Parses `--theta a,b,...` against the model's parameters (default: nominal θ).
pub fn parse_theta(model: &Model, arg: Option<&str>, flag: &str) -> Result<Vec<f64>> {
    let Some(s) = arg else {
        return Ok(model.nominal_theta());
    };
    let values = parse_positive_list(s, flag)?;
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

/// Writes pretty JSON to `path`, keys sorted as on the wire ([`crate::contract::wire`]).
pub fn write_json<T: serde::Serialize>(path: &Path, value: &T) -> Result<()> {
    let text = serde_json::to_string_pretty(&serde_json::to_value(value)?)?;
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
