//! Space frames (issue 25, work in progress): nodes with six DOF, members of
//! [`super::frame3d`] elements, bolted connections with a rotational spring about any of a
//! member end's local axes, assembled primally (paper (3)–(4)): every element DOF is a
//! linear combination of the model's DOFs (a member end's rotation about a rigid axis is
//! the joint's rotation projected on that axis; about a sprung axis, a DOF of its own).
//!
//! ```toml
//! [space_frame]
//! materials = [{ name = "steel", E = 2.1e11, nu = 0.3, rho = 7850.0 }]
//! sections = [{ name = "beam", A = 8e-4, Iy = 2.67e-8, Iz = 1.07e-7, J = 7.33e-8 }]
//! nodes = [{ name = "J1A1", x = 0.0, y = 0.6, z = 0.0 }]
//! members = [{ name = "BX11a", from = "J1A1", to = "J1B1", section = "beam",
//!              material = "steel", elements = 4 }]            # orientation = [0, 1, 0]
//! joints = [{ node = "J1A1", mass = 2.0 }]                     # inertia = [Ix, Iy, Iz]
//! supports = [{ node = "A1" }]                                 # fix = ["x", "ry"]
//! connections = [{ member = "BX11a", node = "J1A1", strong = 5e4, weak = 2e4 }]
//! parameters = [{ name = "BX11a@J1A1", connections = ["BX11a@J1A1.strong"] }]
//! channels = [{ name = "BX11a.2.y", at = "BX11a.2", dir = "y" }]
//! ```

use nalgebra::Vector3;
use serde::Deserialize;

use super::frame3d::{Section3, default_reference, global_matrices, local_axes};
use super::sparse::{Csc, csc_from_triplets};
use super::spec::{BayesSpec, ChannelSpec, ParameterSpec, SupportSpec};
use super::{Channel, Connection, Model, ModelError, Parameter, ParameterKind};

#[allow(non_snake_case)]
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Material3 {
    pub name: String,
    pub E: f64,
    pub nu: f64,
    pub rho: f64,
}

#[allow(non_snake_case)]
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SectionSpec3 {
    pub name: String,
    pub A: f64,
    /// Bending in the local x–z plane (about local y), m⁴.
    pub Iy: f64,
    /// Bending in the local x–y plane (about local z, the strong axis of a beam whose
    /// local y is up), m⁴.
    pub Iz: f64,
    pub J: f64,
    /// Polar moment for the torsional inertia; `Iy + Iz` when absent.
    pub Jp: Option<f64>,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Node3 {
    pub name: String,
    pub x: f64,
    pub y: f64,
    #[serde(default)]
    pub z: f64,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Member3 {
    pub name: String,
    pub from: String,
    pub to: String,
    pub section: String,
    pub material: String,
    pub elements: usize,
    /// Reference vector fixing local y ([`default_reference`] when absent).
    pub orientation: Option<[f64; 3]>,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Joint3 {
    pub node: String,
    /// kg, on each translation.
    #[serde(default)]
    pub mass: f64,
    /// Rotary inertia about global x, y, z (kg·m²).
    #[serde(default)]
    pub inertia: [f64; 3],
}

/// A bolted member end: a rotational spring (N·m/rad) about each named local axis of the
/// member (`torsion` = x, `weak` = y, `strong` = z); the other axes are rigid.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Connection3 {
    pub member: String,
    pub node: String,
    pub torsion: Option<f64>,
    pub weak: Option<f64>,
    pub strong: Option<f64>,
}

/// `[space_frame]` in a model file.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SpaceFrameSpec {
    pub materials: Vec<Material3>,
    pub sections: Vec<SectionSpec3>,
    pub nodes: Vec<Node3>,
    pub members: Vec<Member3>,
    #[serde(default)]
    pub joints: Vec<Joint3>,
    #[serde(default)]
    pub supports: Vec<SupportSpec>,
    #[serde(default)]
    pub connections: Vec<Connection3>,
    #[serde(default)]
    pub parameters: Vec<ParameterSpec>,
    #[serde(default)]
    pub channels: Vec<ChannelSpec>,
}

const DOF_NAMES: [&str; 6] = ["x", "y", "z", "rx", "ry", "rz"];
const AXES: [&str; 3] = ["torsion", "weak", "strong"];

fn invalid(field: impl Into<String>, reason: impl Into<String>) -> ModelError {
    ModelError::Invalid {
        field: field.into(),
        reason: reason.into(),
    }
}

/// A DOF of the model as a combination of numbered DOFs (empty: fixed).
type Combo = Vec<(usize, f64)>;

/// Numbers DOFs by label.
struct Dofs {
    labels: Vec<String>,
}

impl Dofs {
    fn add(&mut self, label: String) -> usize {
        self.labels.push(label);
        self.labels.len() - 1
    }
}

/// Adds `Σ cᵢ cⱼ a[i][j]` over the combinations of each local DOF into `out`.
fn scatter(out: &mut Vec<(usize, usize, f64)>, combos: &[Combo; 12], a: &super::frame3d::Mat12) {
    for i in 0..12 {
        for j in 0..12 {
            let v = a[(i, j)];
            if v == 0.0 {
                continue;
            }
            for &(gi, ci) in &combos[i] {
                for &(gj, cj) in &combos[j] {
                    out.push((gi, gj, ci * cj * v));
                }
            }
        }
    }
}

/// Checks and assembles a `[space_frame]` model.
pub fn assemble(name: &str, s: &SpaceFrameSpec, bayesian: &BayesSpec) -> Result<Model, ModelError> {
    let node_index = |n: &str, field: &str| {
        s.nodes
            .iter()
            .position(|x| x.name == n)
            .ok_or_else(|| ModelError::Unknown {
                field: field.to_string(),
                what: "node",
                name: n.to_string(),
            })
    };
    check(s)?;
    // Node DOFs (fixed ones excluded).
    let mut fixed = vec![[false; 6]; s.nodes.len()];
    for sup in &s.supports {
        let k = node_index(&sup.node, "supports.node")?;
        match &sup.fix {
            None => fixed[k] = [true; 6],
            Some(list) => {
                for d in list {
                    let c = DOF_NAMES.iter().position(|x| x == d).ok_or_else(|| {
                        invalid(
                            format!("supports.{}.fix", sup.node),
                            format!("unknown DOF `{d}` (x, y, z, rx, ry, rz)"),
                        )
                    })?;
                    fixed[k][c] = true;
                }
            }
        }
    }
    let mut dofs = Dofs { labels: Vec::new() };
    let node_dofs: Vec<[Option<usize>; 6]> = s
        .nodes
        .iter()
        .enumerate()
        .map(|(k, n)| {
            let mut d = [None; 6];
            for c in 0..6 {
                if !fixed[k][c] {
                    d[c] = Some(dofs.add(format!("{}.{}", n.name, DOF_NAMES[c])));
                }
            }
            d
        })
        .collect();
    let p = s.parameters.len();
    // K0, K_1..K_p, M as triplets.
    let mut mats: Vec<Vec<(usize, usize, f64)>> = vec![Vec::new(); p + 2];
    let mut connections: Vec<Connection> = Vec::new();
    // Connection-axis name → (matrix slot for its spring, triplet list built later).
    let mut springs: Vec<(String, Combo, f64)> = Vec::new();
    let mut member_nodes: Vec<(String, Vec<[Option<usize>; 6]>)> = Vec::new();
    for m in &s.members {
        let field = format!("members.{}", m.name);
        let (a, b) = (node_index(&m.from, &field)?, node_index(&m.to, &field)?);
        let mat = s
            .materials
            .iter()
            .find(|x| x.name == m.material)
            .ok_or_else(|| ModelError::Unknown {
                field: field.clone(),
                what: "material",
                name: m.material.clone(),
            })?;
        let sec = s
            .sections
            .iter()
            .find(|x| x.name == m.section)
            .ok_or_else(|| ModelError::Unknown {
                field: field.clone(),
                what: "section",
                name: m.section.clone(),
            })?;
        if m.elements == 0 {
            return Err(invalid(format!("{field}.elements"), "must be at least 1"));
        }
        let section = Section3 {
            E: mat.E,
            G: mat.E / (2.0 * (1.0 + mat.nu)),
            rho: mat.rho,
            A: sec.A,
            Iy: sec.Iy,
            Iz: sec.Iz,
            J: sec.J,
            Jp: sec.Jp.unwrap_or(sec.Iy + sec.Iz),
        };
        let pos = |k: usize| Vector3::new(s.nodes[k].x, s.nodes[k].y, s.nodes[k].z);
        let (pa, pb) = (pos(a), pos(b));
        let reference = m.orientation.map_or_else(
            || default_reference(pa, pb),
            |o| Vector3::new(o[0], o[1], o[2]),
        );
        let r = local_axes(pa, pb, reference)
            .map_err(|e| invalid(format!("{field}.orientation"), e.to_string()))?;
        // The slot of this member's stiffness: the parameter scaling its E, or K0.
        let slot = s
            .parameters
            .iter()
            .position(|q| q.members.contains(&m.name))
            .map_or(0, |l| l + 1);
        // Mesh nodes: the ends are the model nodes; interior ones get six DOFs.
        let mut mesh: Vec<[Combo; 6]> = Vec::with_capacity(m.elements + 1);
        let node_combo = |k: usize| -> [Combo; 6] {
            std::array::from_fn(|c| node_dofs[k][c].map(|d| vec![(d, 1.0)]).unwrap_or_default())
        };
        for (end, k) in [(0usize, a), (m.elements, b)] {
            let mut combo = node_combo(k);
            if let Some(conn) = s
                .connections
                .iter()
                .find(|c| c.member == m.name && c.node == s.nodes[k].name)
            {
                // Rotations: Σ_a e_a ρ_a, ρ_a the joint's rotation about e_a (rigid) or
                // the end's own DOF (sprung).
                let joint_rot: [Combo; 3] = [combo[3].clone(), combo[4].clone(), combo[5].clone()];
                let mut rot: [Combo; 3] = Default::default();
                for (ax, kval) in [conn.torsion, conn.weak, conn.strong].iter().enumerate() {
                    let e = r.row(ax);
                    let rho_a: Combo = match kval {
                        None => (0..3)
                            .flat_map(|c| joint_rot[c].iter().map(move |&(d, w)| (d, w * e[c])))
                            .collect(),
                        Some(kv) => {
                            let cname = format!("{}@{}.{}", m.name, s.nodes[k].name, AXES[ax]);
                            let own = dofs.add(cname.clone());
                            // Spring: ½ k (ρ_own − e·θ_joint)².
                            let mut diff: Combo = vec![(own, 1.0)];
                            for c in 0..3 {
                                diff.extend(joint_rot[c].iter().map(|&(d, w)| (d, -w * e[c])));
                            }
                            springs.push((cname, diff, *kv));
                            vec![(own, 1.0)]
                        }
                    };
                    for c in 0..3 {
                        rot[c].extend(rho_a.iter().map(|&(d, w)| (d, w * e[c])));
                    }
                }
                combo[3] = rot[0].clone();
                combo[4] = rot[1].clone();
                combo[5] = rot[2].clone();
            }
            if end == 0 {
                mesh.push(combo);
            } else {
                for i in 1..m.elements {
                    mesh.push(std::array::from_fn(|c| {
                        vec![(dofs.add(format!("{}.{i}.{}", m.name, DOF_NAMES[c])), 1.0)]
                    }));
                }
                mesh.push(combo);
            }
        }
        let step = (pb - pa) / m.elements as f64;
        for e in 0..m.elements {
            let p0 = pa + step * e as f64;
            let (ke, me) = global_matrices(&section, p0, p0 + step, reference)
                .map_err(|err| invalid(field.clone(), err.to_string()))?;
            let combos: [Combo; 12] = std::array::from_fn(|i| mesh[e + i / 6][i % 6].clone());
            scatter(&mut mats[slot], &combos, &ke);
            scatter(&mut mats[p + 1], &combos, &me);
        }
        member_nodes.push((
            m.name.clone(),
            mesh.iter()
                .map(|n| {
                    std::array::from_fn(|c| {
                        (n[c].len() == 1 && n[c][0].1 == 1.0).then(|| n[c][0].0)
                    })
                })
                .collect(),
        ));
    }
    // Springs into K0 or their parameter's K_l.
    for (cname, diff, kv) in &springs {
        let slot = s
            .parameters
            .iter()
            .position(|q| q.connections.contains(cname))
            .map_or(0, |l| l + 1);
        for &(i, ci) in diff {
            for &(j, cj) in diff {
                mats[slot].push((i, j, kv * ci * cj));
            }
        }
        connections.push(Connection {
            name: cname.clone(),
            member: cname.split('@').next().unwrap_or_default().to_string(),
            node: String::new(),
            k: *kv,
            parameter: (slot > 0).then(|| slot - 1),
        });
    }
    // Joint masses and inertias.
    for j in &s.joints {
        let k = node_index(&j.node, "joints.node")?;
        for (c, dof) in node_dofs[k].iter().enumerate() {
            let v = if c < 3 { j.mass } else { j.inertia[c - 3] };
            if let (Some(d), true) = (dof, v != 0.0) {
                mats[p + 1].push((*d, *d, v));
            }
        }
    }
    let parameters = s
        .parameters
        .iter()
        .map(|q| Parameter {
            name: q.name.clone(),
            nominal: q.nominal.unwrap_or(1.0),
            lower: None,
            upper: None,
            kind: if q.members.is_empty() {
                ParameterKind::Connections(
                    connections
                        .iter()
                        .enumerate()
                        .filter(|(_, c)| q.connections.contains(&c.name))
                        .map(|(i, _)| i)
                        .collect(),
                )
            } else {
                ParameterKind::Modulus(q.members.clone())
            },
        })
        .collect();
    let channels = s
        .channels
        .iter()
        .map(|ch| {
            let c = DOF_NAMES.iter().position(|x| *x == ch.dir).ok_or_else(|| {
                invalid(
                    format!("channels.{}.dir", ch.name),
                    format!("unknown `{}`", ch.dir),
                )
            })?;
            let dof = match ch.at.rsplit_once('.') {
                Some((member, k)) if k.parse::<usize>().is_ok() => member_nodes
                    .iter()
                    .find(|(n, _)| n == member)
                    .and_then(|(_, nodes)| nodes.get(k.parse::<usize>().ok()?))
                    .and_then(|n| n[c]),
                _ => node_index(&ch.at, "channels.at")
                    .ok()
                    .and_then(|k| node_dofs[k][c]),
            }
            .ok_or_else(|| {
                invalid(
                    format!("channels.{}.at", ch.name),
                    "not a free DOF of the model",
                )
            })?;
            Ok(Channel {
                name: ch.name.clone(),
                dofs: vec![(dof, 1.0)],
            })
        })
        .collect::<Result<Vec<_>, ModelError>>()?;
    let n = dofs.labels.len();
    let mats: Vec<Csc> = mats
        .into_iter()
        .map(|t| csc_from_triplets(n, t.into_iter()))
        .collect();
    super::finish::finish(
        name,
        dofs.labels,
        mats,
        parameters,
        connections,
        channels,
        bayesian.clone(),
    )
}

/// The references between the entries: names unique, every connection on an existing
/// member end with at least one spring, every parameter naming existing connection axes or
/// members, each in one parameter at most.
fn check(s: &SpaceFrameSpec) -> Result<(), ModelError> {
    fn unique<'a>(
        what: &'static str,
        names: impl Iterator<Item = &'a str>,
    ) -> Result<(), ModelError> {
        let mut seen = std::collections::HashSet::new();
        for n in names {
            if !seen.insert(n) {
                return Err(ModelError::Duplicate {
                    what,
                    name: n.to_string(),
                });
            }
        }
        Ok(())
    }
    unique("node", s.nodes.iter().map(|n| n.name.as_str()))?;
    unique("member", s.members.iter().map(|m| m.name.as_str()))?;
    unique("material", s.materials.iter().map(|m| m.name.as_str()))?;
    unique("section", s.sections.iter().map(|m| m.name.as_str()))?;
    unique("parameter", s.parameters.iter().map(|m| m.name.as_str()))?;
    unique("channel", s.channels.iter().map(|m| m.name.as_str()))?;
    let mut axes = Vec::new();
    for c in &s.connections {
        let field = format!("connections.{}@{}", c.member, c.node);
        let m = s
            .members
            .iter()
            .find(|m| m.name == c.member)
            .ok_or_else(|| ModelError::Unknown {
                field: field.clone(),
                what: "member",
                name: c.member.clone(),
            })?;
        if m.from != c.node && m.to != c.node {
            return Err(invalid(
                field,
                format!("member {} has no end at {}", m.name, c.node),
            ));
        }
        let ks = [c.torsion, c.weak, c.strong];
        if ks.iter().all(Option::is_none) {
            return Err(invalid(
                field,
                "no spring (give torsion, weak and/or strong)",
            ));
        }
        for (ax, k) in ks.iter().enumerate() {
            if let Some(k) = k {
                super::finish::check_positive(format!("{field}.{}", AXES[ax]), *k)?;
                axes.push(format!("{}@{}.{}", c.member, c.node, AXES[ax]));
            }
        }
    }
    unique("connection", axes.iter().map(String::as_str))?;
    let mut used = std::collections::HashSet::new();
    for q in &s.parameters {
        let field = format!("parameters.{}", q.name);
        if q.connections.is_empty() == q.members.is_empty() || !q.springs.is_empty() {
            return Err(invalid(
                field,
                "give either connections (`<member>@<node>.<axis>`) or members",
            ));
        }
        for c in &q.connections {
            if !axes.contains(c) {
                return Err(ModelError::Unknown {
                    field: field.clone(),
                    what: "connection axis",
                    name: c.clone(),
                });
            }
        }
        for m in &q.members {
            if !s.members.iter().any(|x| &x.name == m) {
                return Err(ModelError::Unknown {
                    field: field.clone(),
                    what: "member",
                    name: m.clone(),
                });
            }
        }
        for e in q.connections.iter().chain(&q.members) {
            if !used.insert(e.as_str()) {
                return Err(invalid(
                    field,
                    format!("`{e}` is scaled by another parameter too"),
                ));
            }
        }
    }
    Ok(())
}
