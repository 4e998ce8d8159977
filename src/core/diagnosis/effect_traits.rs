//! The interface of a candidate effect ([`Effect`], and [`FileEffect`] for the effects that
//! edit a model file's geometry), the sign of its internal coordinate ([`Sign`]), and the
//! helpers the effect types share (module docs of [`super::effects`]).

use super::DiagnosisError;
use super::description::Description;
use crate::core::model::spec::ModelSpec;

/// Which values of the internal coordinate are physical.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Sign {
    /// `u > 0` only (an added mass, a compliance).
    Positive,
    /// Either sign (a stiffness or inertia error).
    Any,
}

/// A kind of missing physical effect (module docs of [`super::effects`]), on a model file or
/// an imported model ([`Description`]).
pub trait Effect: Send + Sync {
    /// Contract name (`added-mass`, …).
    fn kind(&self) -> &'static str;
    /// Unit of [`Effect::value`] at `location`.
    fn unit(&self, location: &str) -> &'static str;
    /// Every location of the model where the effect can be added (the candidates).
    fn locations(&self, d: &Description) -> Vec<String>;
    /// Whether the effect can be added at `location` (`--inject`): one of
    /// [`Effect::locations`] unless the effect says otherwise.
    fn accepts(&self, d: &Description, location: &str) -> bool {
        self.locations(d).iter().any(|l| l == location)
    }
    /// Adds the effect at `location` with internal coordinate `u`.
    fn apply(&self, d: &mut Description, location: &str, u: f64) -> Result<(), DiagnosisError>;
    /// A step of `u` that changes the modal data measurably but stays in the linear range
    /// (finite-difference screening, the scale of the search).
    fn step(&self, d: &Description, location: &str) -> f64;
    fn sign(&self) -> Sign;
    /// The reported value for internal coordinate `u`.
    fn value(&self, u: f64) -> f64 {
        u
    }
    /// The reported standard deviation for `u ± std_u` (first order).
    fn value_std(&self, u: f64, std_u: f64) -> f64 {
        let _ = u;
        std_u
    }
    /// The internal coordinate of a reported value (`--inject`).
    fn coordinate(&self, value: f64) -> f64 {
        value
    }
    /// The label, in the model with the effect added at `location`, of the DOF labelled
    /// `label` without it: the same label unless the effect renames the node it is at (a
    /// splice splits a member, and its mesh nodes move to the parts). Lets a reduced solve
    /// match the two models' DOFs.
    fn dof_label_after(&self, d: &Description, location: &str, label: &str) -> String {
        let _ = (d, location);
        label.to_string()
    }
}

impl<T: FileEffect> Effect for T {
    fn kind(&self) -> &'static str {
        FileEffect::kind(self)
    }
    fn unit(&self, location: &str) -> &'static str {
        FileEffect::unit(self, location)
    }
    fn locations(&self, d: &Description) -> Vec<String> {
        d.spec()
            .map_or_else(Vec::new, |spec| FileEffect::locations(self, spec))
    }
    fn apply(&self, d: &mut Description, location: &str, u: f64) -> Result<(), DiagnosisError> {
        match d {
            Description::File(spec) => FileEffect::apply(self, spec, location, u),
            Description::Matrices(_) => Err(needs_geometry(FileEffect::kind(self))),
        }
    }
    fn step(&self, d: &Description, location: &str) -> f64 {
        d.spec()
            .map_or(1.0, |spec| FileEffect::step(self, spec, location))
    }
    fn sign(&self) -> Sign {
        FileEffect::sign(self)
    }
    fn value(&self, u: f64) -> f64 {
        FileEffect::value(self, u)
    }
    fn value_std(&self, u: f64, std_u: f64) -> f64 {
        FileEffect::value_std(self, u, std_u)
    }
    fn coordinate(&self, value: f64) -> f64 {
        FileEffect::coordinate(self, value)
    }
    fn dof_label_after(&self, d: &Description, location: &str, label: &str) -> String {
        match d.spec() {
            Some(spec) => FileEffect::dof_label_after(self, spec, location, label),
            None => label.to_string(),
        }
    }
}

/// The error of an effect that needs geometry, applied to a model imported from matrices.
fn needs_geometry(kind: &str) -> DiagnosisError {
    DiagnosisError::Location(format!(
        "{kind} needs a model file's geometry; on a model imported from matrices the effects \
         are added-mass, grounded-spring and stiffness-scale"
    ))
}

/// An effect that needs a model file's geometry (members, joints, supports): it edits the
/// file. Every such effect is an [`Effect`] that has no locations in an imported model.
pub trait FileEffect: Send + Sync {
    /// Contract name (`added-mass`, …).
    fn kind(&self) -> &'static str;
    /// Unit of [`Effect::value`] at `location`.
    fn unit(&self, location: &str) -> &'static str;
    /// Every location of the model where the effect can be added.
    fn locations(&self, spec: &ModelSpec) -> Vec<String>;
    /// Adds the effect at `location` with internal coordinate `u`.
    fn apply(&self, spec: &mut ModelSpec, location: &str, u: f64) -> Result<(), DiagnosisError>;
    /// A step of `u` that changes the modal data measurably but stays in the linear range
    /// (finite-difference screening, the scale of the search).
    fn step(&self, spec: &ModelSpec, location: &str) -> f64;
    fn sign(&self) -> Sign;
    /// The reported value for internal coordinate `u`.
    fn value(&self, u: f64) -> f64 {
        u
    }
    /// The reported standard deviation for `u ± std_u` (first order).
    fn value_std(&self, u: f64, std_u: f64) -> f64 {
        let _ = u;
        std_u
    }
    /// The internal coordinate of a reported value (`--inject`).
    fn coordinate(&self, value: f64) -> f64 {
        value
    }
    /// [`Effect::dof_label_after`].
    fn dof_label_after(&self, spec: &ModelSpec, location: &str, label: &str) -> String {
        let _ = (spec, location);
        label.to_string()
    }
}

/// The error of a location that is not `what` of the model.
pub(super) fn unknown(location: &str, what: &str) -> DiagnosisError {
    DiagnosisError::Location(format!("`{location}` is not {what} of the model"))
}

/// Interior mesh nodes `<member>.<k>`, k = 1 … elements − 1.
pub(super) fn interior_nodes(spec: &ModelSpec) -> Vec<String> {
    spec.members
        .iter()
        .flat_map(|m| (1..m.elements).map(move |k| format!("{}.{k}", m.name)))
        .collect()
}
