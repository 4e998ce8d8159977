//! Model files (DESIGN §3.1): read, assembled, and checked against the structure a
//! configuration watches.

use std::path::Path;

use anyhow::{Context, Result, bail};

use crate::core::diagnosis::Description;
use crate::core::model::Model;
use crate::core::model::spec::ModelSpec;
use crate::settings::StructureSettings;

/// The models compiled into the binary, named `bundled:<name>` wherever a model file is
/// expected: the files of `config/models/`, so that an installed binary has them anywhere.
pub const BUNDLED_MODELS: &[(&str, &str)] = &[
    (
        "lab-frame",
        include_str!("../../config/models/lab-frame.toml"),
    ),
    (
        "lab-frame-simplified",
        include_str!("../../config/models/lab-frame-simplified.toml"),
    ),
    (
        "space-frame",
        include_str!("../../config/models/space-frame.toml"),
    ),
    (
        "four-bay-solid",
        include_str!("../../config/models/four-bay-solid.toml"),
    ),
    (
        "cantilever-case1",
        include_str!("../../config/models/cantilever-case1.toml"),
    ),
    (
        "cantilever-case2",
        include_str!("../../config/models/cantilever-case2.toml"),
    ),
    (
        "cantilever-truth",
        include_str!("../../config/models/cantilever-truth.toml"),
    ),
];

/// The prefix naming a bundled model ([`BUNDLED_MODELS`]).
pub const BUNDLED: &str = "bundled:";

/// The text of a TOML model file, or of a bundled model (`bundled:<name>`).
pub fn read_model_text(path: &Path) -> Result<String> {
    let Some(name) = path.to_str().and_then(|p| p.strip_prefix(BUNDLED)) else {
        return std::fs::read_to_string(path)
            .with_context(|| format!("cannot read model file {}", path.display()));
    };
    match BUNDLED_MODELS.iter().find(|(n, _)| *n == name) {
        Some((_, text)) => Ok(text.to_string()),
        None => bail!(
            "no bundled model `{name}`; the bundled models are {}",
            BUNDLED_MODELS
                .iter()
                .map(|(n, _)| format!("{BUNDLED}{n}"))
                .collect::<Vec<_>>()
                .join(", ")
        ),
    }
}

/// Reads a TOML model file (or a bundled model) without assembling it.
pub fn load_spec(path: &Path) -> Result<ModelSpec> {
    if is_matrices(path) {
        bail!(
            "model {}: a model imported from matrices has no model file to read",
            path.display()
        );
    }
    let text = read_model_text(path)?;
    toml::from_str(&text).with_context(|| format!("model file {}", path.display()))
}

/// Reads and assembles a model file, or imports a model from matrices when `path` is a
/// `boltwatch.matrices.v1` `model.json` ([`crate::core::model::import`]).
pub fn load_model(path: &Path) -> Result<Model> {
    if is_matrices(path) {
        return Ok(crate::core::model::import::read_matrices(path)?);
    }
    let text = read_model_text(path)?;
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
