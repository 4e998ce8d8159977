//! What a diagnosis enriches ([`Description`]): a model file, or a model imported from
//! matrices together with the effects added to it so far.
//!
//! A model file is enriched by editing the file and assembling it again (the effects of
//! [`super::effects`] that need geometry: members, joints, supports). An imported model has
//! no geometry, only its matrices and the places its `model.json` names
//! ([`crate::core::model::Location`]); the effects that make sense there act on the
//! matrices directly ([`Model::edited`]): a mass on the diagonal of `M`, a grounded spring
//! on the diagonal of `K0`, a scale of `K0`.

use std::sync::{Arc, OnceLock};

use crate::core::model::spec::ModelSpec;
use crate::core::model::{Model, ModelError};

/// A model the diagnosis can enrich (module docs).
#[derive(Debug, Clone)]
#[allow(clippy::large_enum_variant)] // a few live at a time, each cloned whole per trial
pub enum Description {
    /// A TOML model file.
    File(ModelSpec),
    /// An imported model and the additions made to it.
    Matrices(Edited),
}

/// An imported model with additions (module docs).
#[derive(Debug, Clone)]
pub struct Edited {
    pub base: Arc<Model>,
    /// Added to `M`'s diagonal: (DOF, value).
    pub masses: Vec<(usize, f64)>,
    /// Grounded springs on `K0`'s diagonal: (DOF, stiffness).
    pub springs: Vec<(usize, f64)>,
    /// `K0 ← (1 + k0_scale) K0`.
    pub k0_scale: f64,
    /// λ₁ of the base model at nominal θ (the scale of a grounded spring's step), computed
    /// on first use.
    lambda_1: Arc<OnceLock<f64>>,
}

impl Edited {
    pub fn new(base: Arc<Model>) -> Self {
        Self {
            base,
            masses: Vec::new(),
            springs: Vec::new(),
            k0_scale: 0.0,
            lambda_1: Arc::new(OnceLock::new()),
        }
    }

    /// λ₁ of the base model at nominal θ (1 if it cannot be computed: the step is then a
    /// guess, and screening still measures what it does).
    pub fn lambda_1(&self) -> f64 {
        *self.lambda_1.get_or_init(|| {
            crate::core::modal::solver_for(&self.base)
                .and_then(|mut s| s.solve(&self.base, &self.base.nominal_theta(), 1))
                .map_or(1.0, |p| p.lambda[0])
        })
    }
}

impl Description {
    /// An imported model, nothing added.
    pub fn matrices(model: Arc<Model>) -> Self {
        Self::Matrices(Edited::new(model))
    }

    /// The model as described.
    pub fn build(&self) -> Result<Model, ModelError> {
        match self {
            Self::File(spec) => Model::from_spec(spec),
            Self::Matrices(e) => {
                if e.masses.is_empty() && e.springs.is_empty() && e.k0_scale == 0.0 {
                    Ok((*e.base).clone())
                } else {
                    e.base.edited(&e.masses, &e.springs, e.k0_scale)
                }
            }
        }
    }

    /// The model file, if this is one.
    pub fn spec(&self) -> Option<&ModelSpec> {
        match self {
            Self::File(spec) => Some(spec),
            Self::Matrices(_) => None,
        }
    }
}
