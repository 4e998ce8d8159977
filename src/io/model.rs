//! Model files (DESIGN §3.1): read, assembled, and checked against the structure a
//! configuration watches.

use std::path::Path;

use anyhow::{Context, Result, bail};

use crate::core::diagnosis::Description;
use crate::core::model::Model;
use crate::core::model::spec::ModelSpec;
use crate::settings::StructureSettings;

/// Reads a TOML model file without assembling it.
pub fn load_spec(path: &Path) -> Result<ModelSpec> {
    if is_matrices(path) {
        bail!(
            "model {}: a model imported from matrices has no model file to read",
            path.display()
        );
    }
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("cannot read model file {}", path.display()))?;
    toml::from_str(&text).with_context(|| format!("model file {}", path.display()))
}

/// Reads and assembles a model file, or imports a model from matrices when `path` is a
/// `boltwatch.matrices.v1` `model.json` ([`crate::core::model::import`]).
pub fn load_model(path: &Path) -> Result<Model> {
    if is_matrices(path) {
        return Ok(crate::core::model::import::read_matrices(path)?);
    }
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("cannot read model file {}", path.display()))?;
    Model::from_toml(&text).with_context(|| format!("model file {}", path.display()))
}

/// A model as the diagnosis and `simulate --inject` enrich it: a TOML model file, or a
/// model imported from matrices; with its assembly.
pub fn load_description(path: &Path) -> Result<(Description, Model)> {
    if is_matrices(path) {
        let model = load_model(path)?;
        Ok((
            Description::matrices(std::sync::Arc::new(model.clone())),
            model,
        ))
    } else {
        let spec = load_spec(path)?;
        let model =
            Model::from_spec(&spec).with_context(|| format!("model file {}", path.display()))?;
        Ok((Description::File(spec), model))
    }
}

/// Whether `path` names an imported model's `model.json` (rather than a TOML model file).
pub fn is_matrices(path: &Path) -> bool {
    path.extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("json"))
}

/// The model file of a watched structure, read once: its text form (the diagnosis
/// enriches it; none for a model imported from matrices) and its assembly, checked to
/// describe that structure.
pub fn load_structure(s: &StructureSettings) -> Result<(Option<ModelSpec>, Model)> {
    let (spec, model) = if is_matrices(&s.model) {
        (None, load_model(&s.model)?)
    } else {
        let spec = load_spec(&s.model)?;
        let model =
            Model::from_spec(&spec).with_context(|| format!("model file {}", s.model.display()))?;
        (Some(spec), model)
    };
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

/// Makes `tracker` judge by the law file of `tracker.normalisation.law`, when one is
/// configured: it must be for the tracker's structure and parameters.
pub fn adopt_law(tracker: &mut crate::pipeline::Tracker) -> Result<()> {
    let path = tracker.config().normalisation.law.clone();
    if path.is_empty() {
        return Ok(());
    }
    let text = std::fs::read_to_string(&path).with_context(|| {
        format!("configuration key tracker.normalisation.law: cannot read {path}")
    })?;
    let law: crate::commands::normalisation::Law = serde_json::from_str(&text)
        .with_context(|| format!("tracker.normalisation.law: {path} is not a law file"))?;
    let model = tracker.model();
    let name = model.name.clone();
    let names: Vec<&str> = model.parameters().iter().map(|p| p.name.as_str()).collect();
    if law.structure != name || law.parameters != names {
        bail!(
            "tracker.normalisation.law: {path} was learned for {} ({} parameters), not {} ({} parameters)",
            law.structure,
            law.parameters.len(),
            name,
            names.len()
        );
    }
    if tracker.adopt_normalisation(&law.state) {
        tracing::info!(
            structure = name,
            "judging by the normalisation law {path}, learned from {} sets between {} and {}",
            law.sets,
            crate::contract::rfc3339(law.from),
            crate::contract::rfc3339(law.to)
        );
    }
    Ok(())
}
