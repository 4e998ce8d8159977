//! The effects implemented on a [`Description`] directly rather than through
//! [`FileEffect`](super::effects::FileEffect): they also act on a model imported from
//! matrices. Added mass (on a model file too), grounded spring and stiffness scale.

use super::DiagnosisError;
use super::description::Description;
use super::effect_traits::{Effect, Sign, interior_nodes, unknown};
use super::space;
use crate::core::model::Model;
use crate::core::model::sparse::diagonal;
use crate::core::model::spec::{MassSpec, ModelSpec};

/// A point mass (kg): in a model file on both translations of a node, joint or interior
/// mesh node; in an imported model on each DOF of a named location (or of one DOF named by
/// its label), added to the diagonal of `M` (so on a rotation it is a rotary inertia,
/// kg·m²).
pub struct AddedMass;

impl AddedMass {
    fn file_locations(spec: &ModelSpec) -> Vec<String> {
        if let Some(sf) = &spec.space_frame {
            return space::added_mass_locations(sf);
        }
        let supported: Vec<&str> = spec.supports.iter().map(|s| s.node.as_str()).collect();
        spec.nodes
            .iter()
            .map(|n| n.name.clone())
            .filter(|n| !supported.contains(&n.as_str()))
            .chain(interior_nodes(spec))
            .collect()
    }
}

impl Effect for AddedMass {
    fn kind(&self) -> &'static str {
        "added-mass"
    }
    fn unit(&self, _: &str) -> &'static str {
        "kg"
    }
    fn locations(&self, d: &Description) -> Vec<String> {
        match d {
            Description::File(spec) => Self::file_locations(spec),
            Description::Matrices(e) => matrix_locations(&e.base),
        }
    }
    fn accepts(&self, d: &Description, location: &str) -> bool {
        match d {
            Description::File(spec) => Self::file_locations(spec).iter().any(|l| l == location),
            Description::Matrices(e) => e.base.location_dofs(location).is_some(),
        }
    }
    fn apply(&self, d: &mut Description, location: &str, u: f64) -> Result<(), DiagnosisError> {
        match d {
            Description::File(ModelSpec {
                space_frame: Some(sf),
                ..
            }) => space::add_mass(sf, location, u)?,
            Description::File(spec) => {
                if !Self::file_locations(spec).iter().any(|l| l == location) {
                    return Err(unknown(location, "a free node or interior mesh node"));
                }
                if u != 0.0 {
                    spec.masses.push(MassSpec {
                        at: location.to_string(),
                        mass: u,
                        inertia: 0.0,
                    });
                }
            }
            Description::Matrices(e) => {
                let dofs = e.base.location_dofs(location).ok_or_else(|| {
                    unknown(location, "a location (model.json `locations`) or DOF label")
                })?;
                if u != 0.0 {
                    e.masses.extend(dofs.into_iter().map(|i| (i, u)));
                }
            }
        }
        Ok(())
    }
    fn step(&self, d: &Description, location: &str) -> f64 {
        match d {
            Description::File(ModelSpec {
                space_frame: Some(sf),
                ..
            }) => space::added_mass_step(sf),
            Description::File(spec) => {
                // 1 % of the lightest joint; 50 g without joints.
                let lightest = spec
                    .joints
                    .iter()
                    .map(|j| j.mass)
                    .filter(|&m| m > 0.0)
                    .fold(f64::INFINITY, f64::min);
                if lightest.is_finite() {
                    0.01 * lightest
                } else {
                    0.05
                }
            }
            // 1 % of the mean diagonal mass of the location's DOFs that carry mass (of
            // all DOFs with mass if none of them does).
            Description::Matrices(e) => {
                let diag = diagonal(e.base.mass());
                let mean = |dofs: &mut dyn Iterator<Item = usize>| {
                    let (sum, count) = dofs
                        .map(|i| diag[i])
                        .filter(|&m| m > 0.0)
                        .fold((0.0, 0usize), |(s, c), m| (s + m, c + 1));
                    (count > 0).then(|| sum / count as f64)
                };
                let dofs = e.base.location_dofs(location).unwrap_or_default();
                0.01 * mean(&mut dofs.into_iter())
                    .or_else(|| mean(&mut (0..diag.len())))
                    .unwrap_or(1.0)
            }
        }
    }
    fn sign(&self) -> Sign {
        Sign::Positive
    }
}

/// The candidate places of an imported model: its named locations, or every DOF (by label)
/// when it names none.
fn matrix_locations(model: &Model) -> Vec<String> {
    if model.locations().is_empty() {
        model.dof_labels().to_vec()
    } else {
        model.locations().iter().map(|l| l.name.clone()).collect()
    }
}

/// A grounded spring on each DOF of a named location (or of one DOF named by its label) of
/// an imported model, added to the diagonal of `K0`: a support or a connection to the
/// ground the model lacks. The value is the stiffness in the units of `K` at those DOFs
/// (N/m on a translation, N·m/rad on a rotation).
pub struct GroundedSpring;

impl Effect for GroundedSpring {
    fn kind(&self) -> &'static str {
        "grounded-spring"
    }
    fn unit(&self, _: &str) -> &'static str {
        "N/m"
    }
    fn locations(&self, d: &Description) -> Vec<String> {
        match d {
            Description::File(_) => Vec::new(),
            Description::Matrices(e) => matrix_locations(&e.base),
        }
    }
    fn accepts(&self, d: &Description, location: &str) -> bool {
        match d {
            Description::File(_) => false,
            Description::Matrices(e) => e.base.location_dofs(location).is_some(),
        }
    }
    fn apply(&self, d: &mut Description, location: &str, u: f64) -> Result<(), DiagnosisError> {
        let Description::Matrices(e) = d else {
            return Err(DiagnosisError::Location(
                "grounded-spring is an effect of models imported from matrices; a model file \
                 has support-flexibility"
                    .into(),
            ));
        };
        let dofs = e
            .base
            .location_dofs(location)
            .ok_or_else(|| unknown(location, "a location (model.json `locations`) or DOF label"))?;
        if u != 0.0 {
            e.springs.extend(dofs.into_iter().map(|i| (i, u)));
        }
        Ok(())
    }
    /// `0.01 λ₁ tr(M)`: a spring that, on a DOF moving with the whole structure in its
    /// first mode, raises λ₁ by about 1 % per unit of `tr(M)` over the moving mass (a few
    /// per cent at most): measurable, and far from the saturation of a rigid support.
    fn step(&self, d: &Description, _: &str) -> f64 {
        match d {
            Description::File(_) => 1.0,
            Description::Matrices(e) => {
                let trace: f64 = diagonal(e.base.mass()).iter().sum();
                0.01 * e.lambda_1() * trace
            }
        }
    }
    fn sign(&self) -> Sign {
        Sign::Positive
    }
}

/// A relative error of `K0`, the stiffness no parameter scales, of an imported model
/// (location `K0`): `K0 ← (1 + u) K0`. Not a candidate when `K0` is empty.
pub struct StiffnessScale;

impl Effect for StiffnessScale {
    fn kind(&self) -> &'static str {
        "stiffness-scale"
    }
    fn unit(&self, _: &str) -> &'static str {
        "relative"
    }
    fn locations(&self, d: &Description) -> Vec<String> {
        match d {
            Description::Matrices(e) if e.base.k0().val().iter().any(|&v| v != 0.0) => {
                vec!["K0".to_string()]
            }
            _ => Vec::new(),
        }
    }
    fn apply(&self, d: &mut Description, location: &str, u: f64) -> Result<(), DiagnosisError> {
        if !self.accepts(d, location) {
            return Err(unknown(
                location,
                "`K0` (the stiffness-scale effect's location, in a model imported from \
                 matrices with a non-empty K0)",
            ));
        }
        if u <= -1.0 {
            return Err(DiagnosisError::Location(format!(
                "stiffness-scale = {u}: K0 would not be positive"
            )));
        }
        if let Description::Matrices(e) = d {
            e.k0_scale = (1.0 + e.k0_scale) * (1.0 + u) - 1.0;
        }
        Ok(())
    }
    fn step(&self, _: &Description, _: &str) -> f64 {
        0.01
    }
    fn sign(&self) -> Sign {
        Sign::Any
    }
}
