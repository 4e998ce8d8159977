//! The catalogue of candidate effects (DESIGN §6, issue 6): physically named enrichments of
//! a model file, each with one parameter and its unit, scanned over every location where it
//! can occur.
//!
//! An effect works on the model *file* ([`ModelSpec`]): [`Effect::apply`] adds it at a
//! location with a value, and the enriched file is assembled as any other. So an effect
//! needs no support in the assembly, the eigen solvers or the sensitivities, and a new
//! effect type is one more implementation of [`Effect`] in [`catalogue`]: the search does
//! not change.
//!
//! Each effect is applied through an internal coordinate `u` that is 0 for the model as it
//! is ([`Effect::apply`] with `u = 0` changes nothing) and in which the residual is close to
//! linear near 0; [`Effect::value`] turns it into the reported value and unit (support
//! flexibility: `u` is the compliance, the value its stiffness).

use super::DiagnosisError;
use super::description::Description;
use super::space;
use crate::core::model::Model;
use crate::core::model::sparse::diagonal;
use crate::core::model::spec::{MassSpec, MaterialSpec, ModelSpec, SpringSpec};

/// Which values of the internal coordinate are physical.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Sign {
    /// `u > 0` only (an added mass, a compliance).
    Positive,
    /// Either sign (a stiffness or inertia error).
    Any,
}

/// A kind of missing physical effect (module docs), on a model file or an imported model
/// ([`Description`]).
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
}

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
}

/// Every effect type, in the order candidates are listed.
pub fn catalogue() -> Vec<Box<dyn Effect>> {
    vec![
        Box::new(AddedMass),
        Box::new(SupportFlexibility),
        Box::new(MemberStiffness),
        Box::new(Modulus),
        Box::new(JointInertia),
        Box::new(Splice),
        Box::new(AxialForce),
        Box::new(GroundedSpring),
        Box::new(StiffnessScale),
    ]
}

/// The effect of a contract name.
pub fn by_kind(kind: &str) -> Option<Box<dyn Effect>> {
    catalogue().into_iter().find(|e| e.kind() == kind)
}

fn unknown(location: &str, what: &str) -> DiagnosisError {
    DiagnosisError::Location(format!("`{location}` is not {what} of the model"))
}

/// Interior mesh nodes `<member>.<k>`, k = 1 … elements − 1.
fn interior_nodes(spec: &ModelSpec) -> Vec<String> {
    spec.members
        .iter()
        .flat_map(|m| (1..m.elements).map(move |k| format!("{}.{k}", m.name)))
        .collect()
}

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

/// A fixed DOF of a support (`<node>.<dof>`) that is in fact a spring: internal coordinate
/// the compliance (1/k), value the stiffness (N·m/rad for `rz`, N/m for `x`, `y`).
pub struct SupportFlexibility;

impl SupportFlexibility {
    fn split(location: &str) -> Option<(&str, &str)> {
        let (node, dof) = location.rsplit_once('.')?;
        ["x", "y", "rz"].contains(&dof).then_some((node, dof))
    }

    /// Bending (or axial) stiffness scale of the members at a support node: 4EI/L for
    /// rotation, 12EI/L³ for translation, the stiffest member.
    fn member_stiffness(spec: &ModelSpec, node: &str, dof: &str) -> f64 {
        let pos = |n: &str| {
            spec.nodes
                .iter()
                .find(|p| p.name == n)
                .map(|p| (p.x, p.y))
                .unwrap_or((0.0, 0.0))
        };
        spec.members
            .iter()
            .filter(|m| m.from == node || m.to == node)
            .filter_map(|m| {
                let e = spec.materials.iter().find(|x| x.name == m.material)?.E;
                let i = spec.sections.iter().find(|x| x.name == m.section)?.I;
                let ((x0, y0), (x1, y1)) = (pos(&m.from), pos(&m.to));
                let l = ((x1 - x0).powi(2) + (y1 - y0).powi(2)).sqrt().max(1e-9);
                Some(if dof == "rz" {
                    4.0 * e * i / l
                } else {
                    12.0 * e * i / l.powi(3)
                })
            })
            .fold(0.0, f64::max)
            .max(1.0)
    }
}

impl FileEffect for SupportFlexibility {
    fn kind(&self) -> &'static str {
        "support-flexibility"
    }
    fn unit(&self, location: &str) -> &'static str {
        if location
            .rsplit_once('.')
            .is_some_and(|(_, d)| d.starts_with('r'))
        {
            "N·m/rad"
        } else {
            "N/m"
        }
    }
    fn locations(&self, spec: &ModelSpec) -> Vec<String> {
        if let Some(sf) = &spec.space_frame {
            return space::support_locations(sf);
        }
        spec.supports
            .iter()
            .flat_map(|s| {
                let fixed: Vec<String> = s
                    .fix
                    .clone()
                    .unwrap_or_else(|| vec!["x".into(), "y".into(), "rz".into()]);
                fixed.into_iter().map(move |d| format!("{}.{d}", s.node))
            })
            .collect()
    }
    fn apply(&self, spec: &mut ModelSpec, location: &str, u: f64) -> Result<(), DiagnosisError> {
        if let Some(sf) = &mut spec.space_frame {
            return space::free_support(sf, location, u);
        }
        let (node, dof) =
            Self::split(location).ok_or_else(|| unknown(location, "a support DOF (`BL.rz`)"))?;
        let s = spec
            .supports
            .iter_mut()
            .find(|s| s.node == node)
            .ok_or_else(|| unknown(location, "a support DOF"))?;
        let mut fixed = s
            .fix
            .clone()
            .unwrap_or_else(|| vec!["x".into(), "y".into(), "rz".into()]);
        if !fixed.iter().any(|d| d == dof) {
            return Err(unknown(location, "a fixed support DOF"));
        }
        if u <= 0.0 {
            return Ok(());
        }
        fixed.retain(|d| d != dof);
        s.fix = Some(fixed);
        spec.springs.push(SpringSpec {
            name: format!("support-flexibility@{location}"),
            a: node.to_string(),
            b: None,
            dof: dof.to_string(),
            k: 1.0 / u,
        });
        Ok(())
    }
    fn step(&self, spec: &ModelSpec, location: &str) -> f64 {
        if let Some(sf) = &spec.space_frame {
            return space::support_step(sf, location);
        }
        let (node, dof) = Self::split(location).unwrap_or(("", "rz"));
        // A spring 100 times stiffer than the members at the support.
        1.0 / (100.0 * Self::member_stiffness(spec, node, dof))
    }
    fn sign(&self) -> Sign {
        Sign::Positive
    }
    fn value(&self, u: f64) -> f64 {
        1.0 / u
    }
    fn value_std(&self, u: f64, std_u: f64) -> f64 {
        std_u / (u * u)
    }
    fn coordinate(&self, value: f64) -> f64 {
        1.0 / value
    }
}

/// Adds `material` scaled by `factor` (E only) as a new material and returns its name.
fn scaled_material(spec: &mut ModelSpec, material: &str, factor: f64, tag: &str) -> Option<String> {
    let base = spec.materials.iter().find(|m| m.name == material)?.clone();
    let name = format!("{}*{tag}", base.name);
    spec.materials.push(MaterialSpec {
        name: name.clone(),
        E: base.E * factor,
        rho: base.rho,
    });
    Some(name)
}

/// A change of one member's bending stiffness EI, relative (0.1: 10 % stiffer).
pub struct MemberStiffness;

impl FileEffect for MemberStiffness {
    fn kind(&self) -> &'static str {
        "member-stiffness"
    }
    fn unit(&self, _: &str) -> &'static str {
        "relative"
    }
    fn locations(&self, spec: &ModelSpec) -> Vec<String> {
        if let Some(sf) = &spec.space_frame {
            return space::member_axis_locations(sf);
        }
        spec.members.iter().map(|m| m.name.clone()).collect()
    }
    fn apply(&self, spec: &mut ModelSpec, location: &str, u: f64) -> Result<(), DiagnosisError> {
        if let Some(sf) = &mut spec.space_frame {
            return space::scale_member_axis(sf, location, u);
        }
        let k = spec
            .members
            .iter()
            .position(|m| m.name == location)
            .ok_or_else(|| unknown(location, "a member"))?;
        if u <= -1.0 {
            return Err(DiagnosisError::Location(format!(
                "member-stiffness@{location} = {u}: EI would not be positive"
            )));
        }
        if u != 0.0 {
            let material = spec.members[k].material.clone();
            let name = scaled_material(spec, &material, 1.0 + u, location)
                .ok_or_else(|| unknown(&material, "a material"))?;
            spec.members[k].material = name;
        }
        Ok(())
    }
    fn step(&self, _: &ModelSpec, _: &str) -> f64 {
        0.02
    }
    fn sign(&self) -> Sign {
        Sign::Any
    }
}

/// A change of Young's modulus of every member (temperature), relative. Not a candidate
/// when a parameter of the model already scales the modulus of every member.
pub struct Modulus;

impl FileEffect for Modulus {
    fn kind(&self) -> &'static str {
        "modulus"
    }
    fn unit(&self, _: &str) -> &'static str {
        "relative"
    }
    fn locations(&self, spec: &ModelSpec) -> Vec<String> {
        let covered = match &spec.space_frame {
            Some(sf) => space::modulus_covered(sf),
            None => spec.parameters.iter().any(|p| {
                !p.members.is_empty() && spec.members.iter().all(|m| p.members.contains(&m.name))
            }),
        };
        if covered {
            Vec::new()
        } else {
            vec!["global".to_string()]
        }
    }
    fn apply(&self, spec: &mut ModelSpec, location: &str, u: f64) -> Result<(), DiagnosisError> {
        if location != "global" {
            return Err(unknown(
                location,
                "`global` (the modulus effect's location)",
            ));
        }
        if u <= -1.0 {
            return Err(DiagnosisError::Location(format!(
                "modulus = {u}: E would not be positive"
            )));
        }
        if u != 0.0 {
            for m in spec.materials.iter_mut() {
                m.E *= 1.0 + u;
            }
            if let Some(sf) = &mut spec.space_frame {
                space::scale_modulus(sf, u);
            }
        }
        Ok(())
    }
    fn step(&self, _: &ModelSpec, _: &str) -> f64 {
        0.01
    }
    fn sign(&self) -> Sign {
        Sign::Any
    }
}

/// An error of a rigid joint's rotary inertia (kg·m²), either sign.
pub struct JointInertia;

impl FileEffect for JointInertia {
    fn kind(&self) -> &'static str {
        "joint-inertia"
    }
    fn unit(&self, _: &str) -> &'static str {
        "kg·m²"
    }
    fn locations(&self, spec: &ModelSpec) -> Vec<String> {
        if let Some(sf) = &spec.space_frame {
            return space::joint_inertia_locations(sf);
        }
        spec.joints.iter().map(|j| j.node.clone()).collect()
    }
    fn apply(&self, spec: &mut ModelSpec, location: &str, u: f64) -> Result<(), DiagnosisError> {
        if let Some(sf) = &mut spec.space_frame {
            return space::add_joint_inertia(sf, location, u);
        }
        let j = spec
            .joints
            .iter_mut()
            .find(|j| j.node == location)
            .ok_or_else(|| unknown(location, "a joint"))?;
        if j.inertia + u <= 0.0 {
            return Err(DiagnosisError::Location(format!(
                "joint-inertia@{location} = {u}: the joint's inertia would not be positive"
            )));
        }
        j.inertia += u;
        Ok(())
    }
    fn step(&self, spec: &ModelSpec, location: &str) -> f64 {
        if let Some(sf) = &spec.space_frame {
            return space::joint_inertia_step(sf, location);
        }
        spec.joints
            .iter()
            .find(|j| j.node == location)
            .map_or(1e-4, |j| (0.1 * j.inertia).max(1e-6))
    }
    fn sign(&self) -> Sign {
        Sign::Any
    }
}

/// Length, EI of a member (from the file).
fn member_length_ei(spec: &ModelSpec, member: &str) -> Option<(f64, f64)> {
    let m = spec.members.iter().find(|m| m.name == member)?;
    let pos = |n: &str| spec.nodes.iter().find(|p| p.name == n).map(|p| (p.x, p.y));
    let ((x0, y0), (x1, y1)) = (pos(&m.from)?, pos(&m.to)?);
    let e = spec.materials.iter().find(|x| x.name == m.material)?.E;
    let i = spec.sections.iter().find(|x| x.name == m.section)?.I;
    Some(((x1 - x0).hypot(y1 - y0), e * i))
}

/// An axial force in a member (N, tension positive) through its geometric stiffness: a
/// preload, a thermal restraint force, a load carried by the frame.
pub struct AxialForce;

impl FileEffect for AxialForce {
    fn kind(&self) -> &'static str {
        "axial-force"
    }
    fn unit(&self, _: &str) -> &'static str {
        "N"
    }
    fn locations(&self, spec: &ModelSpec) -> Vec<String> {
        if let Some(sf) = &spec.space_frame {
            return sf.members.iter().map(|m| m.name.clone()).collect();
        }
        spec.members.iter().map(|m| m.name.clone()).collect()
    }
    fn apply(&self, spec: &mut ModelSpec, location: &str, u: f64) -> Result<(), DiagnosisError> {
        if let Some(sf) = &mut spec.space_frame {
            return space::add_axial_force(sf, location, u);
        }
        let m = spec
            .members
            .iter_mut()
            .find(|m| m.name == location)
            .ok_or_else(|| unknown(location, "a member"))?;
        m.axial_force += u;
        Ok(())
    }
    fn step(&self, spec: &ModelSpec, location: &str) -> f64 {
        if let Some(sf) = &spec.space_frame {
            return space::axial_force_step(sf, location);
        }
        // 2 % of the member's Euler load π²EI/L².
        member_length_ei(spec, location).map_or(1.0, |(l, ei)| {
            0.02 * std::f64::consts::PI.powi(2) * ei / (l * l)
        })
    }
    fn sign(&self) -> Sign {
        Sign::Any
    }
}

/// An unmodelled splice: at an interior mesh node `<member>.<k>` the member is in two parts
/// joined by a rotational spring. Internal coordinate the compliance (1/k), value the
/// stiffness (N·m/rad).
pub struct Splice;

impl Splice {
    fn split(spec: &ModelSpec, location: &str) -> Option<(usize, usize)> {
        let (member, k) = location.rsplit_once('.')?;
        let k: usize = k.parse().ok()?;
        let mi = spec.members.iter().position(|m| m.name == member)?;
        (k >= 1 && k < spec.members[mi].elements).then_some((mi, k))
    }
}

impl FileEffect for Splice {
    fn kind(&self) -> &'static str {
        "splice"
    }
    fn unit(&self, _: &str) -> &'static str {
        "N·m/rad"
    }
    fn locations(&self, spec: &ModelSpec) -> Vec<String> {
        if let Some(sf) = &spec.space_frame {
            return space::splice_locations(sf);
        }
        interior_nodes(spec)
    }
    fn apply(&self, spec: &mut ModelSpec, location: &str, u: f64) -> Result<(), DiagnosisError> {
        if let Some(sf) = &mut spec.space_frame {
            return space::splice(sf, location, u);
        }
        let (mi, k) = Self::split(spec, location)
            .ok_or_else(|| unknown(location, "an interior mesh node (`C2L.3`)"))?;
        if u <= 0.0 {
            return Ok(());
        }
        let m = spec.members[mi].clone();
        let pos = |n: &str| spec.nodes.iter().find(|p| p.name == n).map(|p| (p.x, p.y));
        let ((x0, y0), (x1, y1)) = (
            pos(&m.from).ok_or_else(|| unknown(&m.from, "a node"))?,
            pos(&m.to).ok_or_else(|| unknown(&m.to, "a node"))?,
        );
        // The parts span the same mesh (joint offsets are part of the end elements: the
        // split node sits where mesh node k was only if the ends carry no offset; the
        // lab frame's joint offsets make the first and last elements shorter, so the node
        // is placed at the mesh node's position along the offset span).
        let size = |n: &str| {
            spec.joints
                .iter()
                .find(|j| j.node == n)
                .map_or(0.0, |j| j.size)
        };
        let len = (x1 - x0).hypot(y1 - y0);
        let (sa, sb) = (size(&m.from), size(&m.to));
        let t = (sa + (len - sa - sb) * k as f64 / m.elements as f64) / len;
        let node = format!("{}.splice{k}", m.name);
        spec.nodes.push(crate::core::model::spec::NodeSpec {
            name: node.clone(),
            x: x0 + t * (x1 - x0),
            y: y0 + t * (y1 - y0),
        });
        let (a, b) = (format!("{}~a", m.name), format!("{}~b", m.name));
        // Connections keep their names; the part that now ends at their node takes over.
        for c in spec.connections.iter_mut().filter(|c| c.member == m.name) {
            c.name
                .get_or_insert_with(|| format!("{}@{}", m.name, c.node));
            c.member = if c.node == m.from {
                a.clone()
            } else {
                b.clone()
            };
        }
        for p in spec.parameters.iter_mut() {
            if let Some(i) = p.members.iter().position(|x| *x == m.name) {
                p.members[i] = a.clone();
                p.members.push(b.clone());
            }
        }
        // Interior locations of the member move to the part that holds them.
        let relocate = |at: &mut String| space::relocate_split(at, &m.name, k, (&a, &node, &b));
        for c in spec.channels.iter_mut() {
            relocate(&mut c.at);
        }
        for x in spec.masses.iter_mut() {
            relocate(&mut x.at);
        }
        for x in spec.springs.iter_mut() {
            relocate(&mut x.a);
            if let Some(bn) = x.b.as_mut() {
                relocate(bn);
            }
        }
        let mut part_a = m.clone();
        part_a.name = a.clone();
        part_a.to = node.clone();
        part_a.elements = k;
        let mut part_b = m.clone();
        part_b.name = b.clone();
        part_b.from = node.clone();
        part_b.elements = m.elements - k;
        spec.members[mi] = part_a;
        spec.members.insert(mi + 1, part_b);
        spec.connections
            .push(crate::core::model::spec::ConnectionSpec {
                name: Some(format!("splice@{location}")),
                member: b,
                node,
                k: 1.0 / u,
            });
        Ok(())
    }
    fn step(&self, spec: &ModelSpec, location: &str) -> f64 {
        if let Some(sf) = &spec.space_frame {
            return space::splice_step(sf, location);
        }
        let member = location.rsplit_once('.').map_or(location, |x| x.0);
        // A spring 100 times the member's EI/L.
        member_length_ei(spec, member).map_or(1e-6, |(l, ei)| l / (100.0 * ei))
    }
    fn sign(&self) -> Sign {
        Sign::Positive
    }
    fn value(&self, u: f64) -> f64 {
        1.0 / u
    }
    fn value_std(&self, u: f64, std_u: f64) -> f64 {
        std_u / (u * u)
    }
    fn coordinate(&self, value: f64) -> f64 {
        1.0 / value
    }
}
