//! The effects of [`super::effects`] on a space frame (`[space_frame]`, issue 25): the same
//! physical enrichments with the locations a three-dimensional frame has.
//!
//! | effect | locations | edit |
//! |---|---|---|
//! | `added-mass` | free nodes and mesh nodes `<member>.<k>` | a lumped mass on x, y, z |
//! | `support-flexibility` | `<node>.<dof>`, each fixed DOF of a support | the DOF freed, a grounded spring of stiffness 1/u |
//! | `member-stiffness` | `<member>.weak`, `<member>.strong` | `I_y` (weak) or `I_z` (strong) of the member scaled by 1 + u |
//! | `modulus` | `global` | E of every material scaled by 1 + u |
//! | `joint-inertia` | `<joint>.rx`, `.ry`, `.rz` | the joint's rotary inertia about that global axis + u |
//! | `splice` | `<member>.<k>.weak`, `.strong` | the member split at mesh node k, the parts joined by a spring 1/u about that axis (rigid about the others) |
//! | `axial-force` | members | the member's axial force + u (N) |

use nalgebra::Vector3;

use super::DiagnosisError;
use crate::core::model::space::{
    AXES, Connection3, DOF_NAMES, Mass3, Member3, Node3, SpaceFrameSpec, Spring3,
};

fn unknown(location: &str, what: &str) -> DiagnosisError {
    DiagnosisError::Location(format!("`{location}` is not {what} of the model"))
}

/// Mesh nodes `<member>.<k>`, k = 1 … elements − 1.
fn interior_nodes(sf: &SpaceFrameSpec) -> Vec<String> {
    sf.members
        .iter()
        .flat_map(|m| (1..m.elements).map(move |k| format!("{}.{k}", m.name)))
        .collect()
}

/// Length and the largest and smallest bending stiffness `E·I` of a member.
fn member_length_ei(sf: &SpaceFrameSpec, member: &str) -> Option<(f64, f64, f64)> {
    let m = sf.members.iter().find(|m| m.name == member)?;
    let l = (sf.position(&m.to)? - sf.position(&m.from)?).norm();
    let s = sf.section_of(m).ok()?;
    Some((l, s.E * s.Iy.max(s.Iz), s.E * s.Iy.min(s.Iz)))
}

/// The fixed DOFs of a support, by name.
fn fixed_dofs(fix: &Option<Vec<String>>) -> Vec<String> {
    fix.clone()
        .unwrap_or_else(|| DOF_NAMES.iter().map(|d| d.to_string()).collect())
}

pub fn added_mass_locations(sf: &SpaceFrameSpec) -> Vec<String> {
    let clamped: Vec<&str> = sf
        .supports
        .iter()
        .filter(|s| fixed_dofs(&s.fix).len() == 6)
        .map(|s| s.node.as_str())
        .collect();
    sf.nodes
        .iter()
        .map(|n| n.name.clone())
        .filter(|n| !clamped.contains(&n.as_str()))
        .chain(interior_nodes(sf))
        .collect()
}

pub fn add_mass(sf: &mut SpaceFrameSpec, location: &str, u: f64) -> Result<(), DiagnosisError> {
    if !added_mass_locations(sf).iter().any(|l| l == location) {
        return Err(unknown(location, "a free node or interior mesh node"));
    }
    if u != 0.0 {
        sf.masses.push(Mass3 {
            at: location.to_string(),
            mass: u,
            inertia: [0.0; 3],
        });
    }
    Ok(())
}

/// 1 % of the lightest joint; 50 g without joints.
pub fn added_mass_step(sf: &SpaceFrameSpec) -> f64 {
    let lightest = sf
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

pub fn support_locations(sf: &SpaceFrameSpec) -> Vec<String> {
    sf.supports
        .iter()
        .flat_map(|s| {
            fixed_dofs(&s.fix)
                .into_iter()
                .map(move |d| format!("{}.{d}", s.node))
        })
        .collect()
}

pub fn free_support(sf: &mut SpaceFrameSpec, location: &str, u: f64) -> Result<(), DiagnosisError> {
    let (node, dof) = location
        .rsplit_once('.')
        .filter(|(_, d)| DOF_NAMES.contains(d))
        .ok_or_else(|| unknown(location, "a support DOF (`A1.ry`)"))?;
    let s = sf
        .supports
        .iter_mut()
        .find(|s| s.node == node)
        .ok_or_else(|| unknown(location, "a support DOF"))?;
    let mut fixed = fixed_dofs(&s.fix);
    if !fixed.iter().any(|d| d == dof) {
        return Err(unknown(location, "a fixed support DOF"));
    }
    if u <= 0.0 {
        return Ok(());
    }
    fixed.retain(|d| d != dof);
    s.fix = Some(fixed);
    sf.springs.push(Spring3 {
        name: format!("support-flexibility@{location}"),
        a: node.to_string(),
        b: None,
        dof: dof.to_string(),
        k: 1.0 / u,
    });
    Ok(())
}

/// A compliance 1/100 of the stiffest member at the support: 4EI/L for a rotation,
/// 12EI/L³ for a translation.
pub fn support_step(sf: &SpaceFrameSpec, location: &str) -> f64 {
    let (node, dof) = location.rsplit_once('.').unwrap_or((location, "rz"));
    let k = sf
        .members
        .iter()
        .filter(|m| m.from == node || m.to == node)
        .filter_map(|m| member_length_ei(sf, &m.name))
        .map(|(l, ei, _)| {
            if dof.starts_with('r') {
                4.0 * ei / l
            } else {
                12.0 * ei / l.powi(3)
            }
        })
        .fold(0.0, f64::max)
        .max(1.0);
    1.0 / (100.0 * k)
}

/// The bending axes a member's stiffness and a splice act about.
const BENDING: [&str; 2] = ["weak", "strong"];

pub fn member_axis_locations(sf: &SpaceFrameSpec) -> Vec<String> {
    sf.members
        .iter()
        .flat_map(|m| BENDING.iter().map(move |a| format!("{}.{a}", m.name)))
        .collect()
}

/// Gives member `k` its own copy of its section with `I_y` (weak) or `I_z` (strong) scaled
/// by `factor`.
pub fn scale_member_axis(
    sf: &mut SpaceFrameSpec,
    location: &str,
    u: f64,
) -> Result<(), DiagnosisError> {
    let (member, axis) = location
        .rsplit_once('.')
        .filter(|(_, a)| BENDING.contains(a))
        .ok_or_else(|| unknown(location, "a member axis (`BX11a.strong`)"))?;
    let k = sf
        .members
        .iter()
        .position(|m| m.name == member)
        .ok_or_else(|| unknown(location, "a member axis"))?;
    if u <= -1.0 {
        return Err(DiagnosisError::Location(format!(
            "member-stiffness@{location} = {u}: EI would not be positive"
        )));
    }
    if u == 0.0 {
        return Ok(());
    }
    let mut section = sf
        .sections
        .iter()
        .find(|s| s.name == sf.members[k].section)
        .cloned()
        .ok_or_else(|| unknown(&sf.members[k].section, "a section"))?;
    section.name = format!("{}*{location}", section.name);
    if axis == "weak" {
        section.Iy *= 1.0 + u;
    } else {
        section.Iz *= 1.0 + u;
    }
    sf.members[k].section = section.name.clone();
    sf.sections.push(section);
    Ok(())
}

/// Every member scaled by a parameter of the model's modulus: no `modulus` candidate then.
pub fn modulus_covered(sf: &SpaceFrameSpec) -> bool {
    sf.parameters
        .iter()
        .any(|p| !p.members.is_empty() && sf.members.iter().all(|m| p.members.contains(&m.name)))
}

pub fn scale_modulus(sf: &mut SpaceFrameSpec, u: f64) {
    for m in sf.materials.iter_mut() {
        m.E *= 1.0 + u;
    }
}

pub fn joint_inertia_locations(sf: &SpaceFrameSpec) -> Vec<String> {
    sf.joints
        .iter()
        .flat_map(|j| {
            DOF_NAMES[3..]
                .iter()
                .map(move |r| format!("{}.{r}", j.node))
        })
        .collect()
}

fn joint_axis(location: &str) -> Option<(&str, usize)> {
    let (node, r) = location.rsplit_once('.')?;
    Some((node, DOF_NAMES[3..].iter().position(|x| *x == r)?))
}

pub fn add_joint_inertia(
    sf: &mut SpaceFrameSpec,
    location: &str,
    u: f64,
) -> Result<(), DiagnosisError> {
    let (node, c) =
        joint_axis(location).ok_or_else(|| unknown(location, "a joint axis (`J1A1.rz`)"))?;
    let j = sf
        .joints
        .iter_mut()
        .find(|j| j.node == node)
        .ok_or_else(|| unknown(location, "a joint axis"))?;
    if j.inertia[c] + u < 0.0 {
        return Err(DiagnosisError::Location(format!(
            "joint-inertia@{location} = {u}: the joint's inertia would be negative"
        )));
    }
    j.inertia[c] += u;
    Ok(())
}

/// 10 % of the joint's inertia about the axis, or, when it has none, the inertia of its
/// mass at 1 cm.
pub fn joint_inertia_step(sf: &SpaceFrameSpec, location: &str) -> f64 {
    joint_axis(location)
        .and_then(|(node, c)| {
            let j = sf.joints.iter().find(|j| j.node == node)?;
            Some((0.1 * j.inertia[c]).max(1e-4 * j.mass).max(1e-6))
        })
        .unwrap_or(1e-4)
}

pub fn splice_locations(sf: &SpaceFrameSpec) -> Vec<String> {
    interior_nodes(sf)
        .into_iter()
        .flat_map(|n| BENDING.iter().map(move |a| format!("{n}.{a}")))
        .collect()
}

/// `<member>.<k>.<axis>` → (member index, k, axis).
fn splice_split<'a>(sf: &SpaceFrameSpec, location: &'a str) -> Option<(usize, usize, &'a str)> {
    let (at, axis) = location.rsplit_once('.')?;
    let (member, k) = at.rsplit_once('.')?;
    let k: usize = k.parse().ok()?;
    let mi = sf.members.iter().position(|m| m.name == member)?;
    (k >= 1 && k < sf.members[mi].elements && BENDING.contains(&axis)).then_some((mi, k, axis))
}

/// The member a splice at `location` splits and the mesh node `k` it splits it at.
pub(super) fn splice_member<'s>(
    sf: &'s SpaceFrameSpec,
    location: &str,
) -> Option<(&'s str, usize)> {
    splice_split(sf, location).map(|(mi, k, _)| (sf.members[mi].name.as_str(), k))
}

/// Splits the member at mesh node k into two members joined there by a spring `1/u` about
/// `axis` (rigid about the other axes): the new node sits where the mesh node was (joint
/// offsets included), both parts keep the member's local axes, and everything that named
/// the member (connections at its ends, parameters, locations `<member>.<j>`) follows the
/// part that now holds it.
pub fn splice(sf: &mut SpaceFrameSpec, location: &str, u: f64) -> Result<(), DiagnosisError> {
    let (mi, k, axis) = splice_split(sf, location)
        .ok_or_else(|| unknown(location, "a splice place (`BX11a.2.strong`)"))?;
    if u <= 0.0 {
        return Ok(());
    }
    let m: Member3 = sf.members[mi].clone();
    let (node, reference) = add_splice_node(sf, &m, k)?;
    let (a, _, b) = split_names(&m.name, k);
    follow_split(sf, &m, k, (&a, &node, &b));
    let part = |name: &str, from: &str, to: &str, elements: usize| Member3 {
        name: name.to_string(),
        from: from.to_string(),
        to: to.to_string(),
        elements,
        orientation: Some(reference),
        ..m.clone()
    };
    sf.members[mi] = part(&a, &m.from, &node, k);
    sf.members
        .insert(mi + 1, part(&b, &node, &m.to, m.elements - k));
    sf.connections.push(Connection3 {
        name: Some(format!("splice@{}.{k}", m.name)),
        member: b,
        node,
        torsion: None,
        weak: (axis == AXES[1]).then_some(1.0 / u),
        strong: (axis == AXES[2]).then_some(1.0 / u),
    });
    Ok(())
}

/// Adds the node `<member>.splice<k>` where member `m`'s mesh node `k` was (joint offsets
/// included); returns its name and the member's reference vector, which both parts keep
/// so that they keep the member's local axes.
fn add_splice_node(
    sf: &mut SpaceFrameSpec,
    m: &Member3,
    k: usize,
) -> Result<(String, [f64; 3]), DiagnosisError> {
    let (pa, pb) = (
        sf.position(&m.from)
            .ok_or_else(|| unknown(&m.from, "a node"))?,
        sf.position(&m.to).ok_or_else(|| unknown(&m.to, "a node"))?,
    );
    let e = (pb - pa).normalize();
    let (p0, p1) = (
        pa + e * sf.joint_size(&m.from),
        pb - e * sf.joint_size(&m.to),
    );
    let at: Vector3<f64> = p0 + (p1 - p0) * (k as f64 / m.elements as f64);
    let (_, node, _) = split_names(&m.name, k);
    sf.nodes.push(Node3 {
        name: node.clone(),
        x: at.x,
        y: at.y,
        z: at.z,
    });
    // The parts keep the member's local axes: the same reference vector.
    let reference = m.orientation.unwrap_or_else(|| {
        let r = crate::core::model::frame3d::default_reference(pa, pb);
        [r.x, r.y, r.z]
    });
    Ok((node, reference))
}

/// Moves everything that named member `m`, split at mesh node `k` into `parts` (`a`, the
/// new node, `b`), to the part that now holds it: the connections at its ends, the
/// parameters that scale it (both parts), and the locations `<member>.<j>` of channels,
/// masses and springs.
fn follow_split(sf: &mut SpaceFrameSpec, m: &Member3, k: usize, parts: (&str, &str, &str)) {
    let (a, _, b) = parts;
    for c in sf.connections.iter_mut().filter(|c| c.member == m.name) {
        c.name = Some(c.name());
        c.member = if c.node == m.from {
            a.to_string()
        } else {
            b.to_string()
        };
    }
    for p in sf.parameters.iter_mut() {
        if let Some(i) = p.members.iter().position(|x| *x == m.name) {
            p.members[i] = a.to_string();
            p.members.push(b.to_string());
        }
    }
    let relocate = |at: &mut String| {
        relocate_split(at, &m.name, k, parts);
    };
    for c in sf.channels.iter_mut() {
        relocate(&mut c.at);
    }
    for x in sf.masses.iter_mut() {
        relocate(&mut x.at);
    }
    for x in sf.springs.iter_mut() {
        relocate(&mut x.a);
        if let Some(bn) = x.b.as_mut() {
            relocate(bn);
        }
    }
}

/// A spring 100 times the member's EI/L about that axis.
pub fn splice_step(sf: &SpaceFrameSpec, location: &str) -> f64 {
    splice_split(sf, location)
        .and_then(|(mi, _, axis)| {
            let m = &sf.members[mi];
            let l = (sf.position(&m.to)? - sf.position(&m.from)?).norm();
            let s = sf.section_of(m).ok()?;
            let i = if axis == "weak" { s.Iy } else { s.Iz };
            Some(l / (100.0 * s.E * i))
        })
        .unwrap_or(1e-6)
}

pub fn add_axial_force(
    sf: &mut SpaceFrameSpec,
    location: &str,
    u: f64,
) -> Result<(), DiagnosisError> {
    let m = sf
        .members
        .iter_mut()
        .find(|m| m.name == location)
        .ok_or_else(|| unknown(location, "a member"))?;
    m.axial_force += u;
    Ok(())
}

/// 2 % of the member's Euler load π²EI/L² about its weak axis.
pub fn axial_force_step(sf: &SpaceFrameSpec, location: &str) -> f64 {
    member_length_ei(sf, location).map_or(1.0, |(l, _, ei)| {
        0.02 * std::f64::consts::PI.powi(2) * ei / (l * l)
    })
}

/// The names a member split at its mesh node `k` gives: its first part, the node between
/// the parts and its second part (`<member>~a`, `<member>.splice<k>`, `<member>~b`). Shared
/// by the plane and space frames' splices.
pub(super) fn split_names(member: &str, k: usize) -> (String, String, String) {
    (
        format!("{member}~a"),
        format!("{member}.splice{k}"),
        format!("{member}~b"),
    )
}

/// A location `<member>.<j>` of a member split at mesh node `k` into parts `a` and `b`
/// joined at `node`, renamed to where it now is (`a.j`, `node` or `b.(j − k)`); any other
/// location is left as it is. Shared by the plane and space frames' splices.
pub(super) fn relocate_split(at: &mut String, member: &str, k: usize, parts: (&str, &str, &str)) {
    let (a, node, b) = parts;
    let Some(j) = at
        .strip_prefix(member)
        .and_then(|rest| rest.strip_prefix('.'))
        .and_then(|j| j.parse::<usize>().ok())
    else {
        return;
    };
    *at = match j.cmp(&k) {
        std::cmp::Ordering::Less => format!("{a}.{j}"),
        std::cmp::Ordering::Equal => node.to_string(),
        std::cmp::Ordering::Greater => format!("{b}.{}", j - k),
    };
}
