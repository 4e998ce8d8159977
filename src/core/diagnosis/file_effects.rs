//! The effects that need a model file's geometry ([`FileEffect`]): support flexibility,
//! member stiffness, modulus, joint inertia, axial force and splice. Each edits the file (or
//! its `[space_frame]`, through [`super::space`]); none has a location in an imported model.

use super::DiagnosisError;
use super::effect_traits::{FileEffect, Sign, interior_nodes, unknown};
use super::space;
use crate::core::model::spec::{
    ConnectionSpec, MaterialSpec, MemberSpec, ModelSpec, NodeSpec, SpringSpec,
};

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

    /// The node splitting member `m` at its mesh node `k` (`<member>.splice<k>`).
    fn split_node(spec: &ModelSpec, m: &MemberSpec, k: usize) -> Result<NodeSpec, DiagnosisError> {
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
        Ok(NodeSpec {
            name: space::split_names(&m.name, k).1,
            x: x0 + t * (x1 - x0),
            y: y0 + t * (y1 - y0),
        })
    }

    /// Hands what refers to member `m` over to its parts `(a, node, b)` (split at `node`,
    /// its mesh node `k`): connections, parameters, interior locations.
    fn hand_over(spec: &mut ModelSpec, m: &MemberSpec, k: usize, parts: (&str, &str, &str)) {
        let (a, _, b) = parts;
        // Connections keep their names; the part that now ends at their node takes over.
        for c in spec.connections.iter_mut().filter(|c| c.member == m.name) {
            c.name
                .get_or_insert_with(|| format!("{}@{}", m.name, c.node));
            c.member = if c.node == m.from {
                a.to_string()
            } else {
                b.to_string()
            };
        }
        for p in spec.parameters.iter_mut() {
            if let Some(i) = p.members.iter().position(|x| *x == m.name) {
                p.members[i] = a.to_string();
                p.members.push(b.to_string());
            }
        }
        // Interior locations of the member move to the part that holds them.
        let relocate = |at: &mut String| space::relocate_split(at, &m.name, k, parts);
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
        let split_node = Self::split_node(spec, &m, k)?;
        let node = split_node.name.clone();
        spec.nodes.push(split_node);
        let (a, _, b) = space::split_names(&m.name, k);
        Self::hand_over(spec, &m, k, (&a, &node, &b));
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
        spec.connections.push(ConnectionSpec {
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
    /// The member's mesh nodes move to its parts: `<member>.<j>` becomes `<member>~a.<j>`,
    /// `<member>.splice<k>` or `<member>~b.<j − k>`; a DOF keeps its component.
    fn dof_label_after(&self, spec: &ModelSpec, location: &str, label: &str) -> String {
        let split = match &spec.space_frame {
            Some(sf) => space::splice_member(sf, location),
            None => Self::split(spec, location).map(|(mi, k)| (spec.members[mi].name.as_str(), k)),
        };
        let (Some((member, k)), Some((at, component))) = (split, label.rsplit_once('.')) else {
            return label.to_string();
        };
        if !at.starts_with(member) {
            return label.to_string();
        }
        let mut at = at.to_string();
        let (a, node, b) = space::split_names(member, k);
        space::relocate_split(&mut at, member, k, (&a, &node, &b));
        format!("{at}.{component}")
    }
}
