//! The model a plan is made on, read from its file with its candidate places, and the
//! channels installed now.

use std::path::Path;

use anyhow::{Context, Result};

use super::Candidates;
use crate::core::model::Model;
use crate::core::plan::places::{Places, WithCandidates, with_candidates};

impl From<Candidates> for Places {
    fn from(c: Candidates) -> Self {
        match c {
            Candidates::Nodes => Places::Nodes,
            Candidates::Dofs => Places::Dofs,
            Candidates::All => Places::All,
        }
    }
}

/// The model of `path` (a model file or an imported model's `model.json`) with its
/// candidate places, and the names of the channels it has of its own.
pub(super) fn planned_model(
    path: &Path,
    kind: Candidates,
) -> Result<(WithCandidates, Vec<String>)> {
    let (spec, base) = if crate::io::model::is_matrices(path) {
        (None, crate::io::model::load_model(path)?)
    } else {
        let spec = crate::io::model::load_spec(path)?;
        let model =
            Model::from_spec(&spec).with_context(|| format!("model file {}", path.display()))?;
        (Some(spec), model)
    };
    let installed = base.channels().iter().map(|c| c.name.clone()).collect();
    Ok((
        with_candidates(spec.as_ref(), &base, kind.into())?,
        installed,
    ))
}

/// The channels installed now: those of `--channels`, else the model's own (`installed`).
pub(super) fn current_channels(
    model: &Model,
    file: Option<&Path>,
    installed: &[String],
) -> Result<Vec<usize>> {
    let names: Vec<String> = match file {
        Some(path) => {
            #[derive(serde::Deserialize)]
            #[serde(deny_unknown_fields)]
            struct Installed {
                channels: Vec<String>,
            }
            let text = std::fs::read_to_string(path)
                .with_context(|| format!("--channels: cannot read {}", path.display()))?;
            let i: Installed =
                toml::from_str(&text).with_context(|| format!("--channels {}", path.display()))?;
            i.channels
        }
        None => installed.to_vec(),
    };
    names
        .iter()
        .map(|n| {
            model.channel_index(n).with_context(|| {
                format!("--channels: `{n}` is not a channel or a candidate place of the model")
            })
        })
        .collect()
}
