//! What `update`, `sweep-sigma` and `diagnose` read: a model, a modal set validated against
//! it, and θ0.

use anyhow::{Context, Result};

use super::{load_model, parse_theta};
use crate::contract::modal_set::{ModalSet, ValidationContext, parse_modal_set};
use crate::core::model::Model;
use crate::core::updating::MeasuredData;
pub use crate::pipeline::measured_data;

/// A model, a validated modal set on it, its numbers as [`MeasuredData`], and θ0.
pub struct Inputs {
    pub model: Model,
    pub set: ModalSet,
    pub data: MeasuredData,
    pub theta0: Vec<f64>,
}

/// Loads and validates `--model`, `--data` and `--theta0` (shape weight for weighting (9)).
pub fn load_inputs(
    model: &std::path::Path,
    data: &std::path::Path,
    theta0: Option<&str>,
    shape_weight: f64,
) -> Result<Inputs> {
    let model = load_model(model)?;
    crate::core::numerics_for(&model);
    let theta0 = parse_theta(&model, theta0, "--theta0")?;
    let set = load_set(&model, data)?;
    if !(shape_weight.is_finite() && shape_weight > 0.0) {
        anyhow::bail!("--shape-weight = {shape_weight} must be a finite number > 0");
    }
    let data = measured_data(&set, &model, shape_weight);
    Ok(Inputs {
        model,
        set,
        data,
        theta0,
    })
}

/// Reads and validates a modal set against `model`.
pub fn load_set(model: &Model, path: &std::path::Path) -> Result<ModalSet> {
    let bytes =
        std::fs::read(path).with_context(|| format!("cannot read modal set {}", path.display()))?;
    let channels: Vec<String> = model.channels().iter().map(|c| c.name.clone()).collect();
    let ctx = ValidationContext {
        structures: &[model.name.as_str()],
        model_channels: &channels,
        last_time: None,
        allow_equal_time: true,
        max_future: None,
    };
    parse_modal_set(&bytes, &ctx).with_context(|| format!("modal set {} rejected", path.display()))
}
