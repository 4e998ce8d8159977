//! Model files (DESIGN §3.1): read, assembled, and checked against the structure a
//! configuration watches.

use std::path::Path;

use anyhow::{Context, Result, bail};

use crate::core::model::Model;
use crate::core::model::spec::ModelSpec;
use crate::settings::StructureSettings;

/// Reads a model file without assembling it.
pub fn load_spec(path: &Path) -> Result<ModelSpec> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("cannot read model file {}", path.display()))?;
    toml::from_str(&text).with_context(|| format!("model file {}", path.display()))
}

/// Reads and assembles a model file.
pub fn load_model(path: &Path) -> Result<Model> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("cannot read model file {}", path.display()))?;
    Model::from_toml(&text).with_context(|| format!("model file {}", path.display()))
}

/// The model file of a watched structure, read once: its text form (the diagnosis
/// enriches it) and its assembly, checked to describe that structure.
pub fn load_structure(s: &StructureSettings) -> Result<(ModelSpec, Model)> {
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
