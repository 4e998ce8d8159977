//! Checks a [`ModelSpec`] and assembles `K0`, `K_l`, `M` and the channel rows.

use std::collections::HashMap;

use super::element::{Section, frame_element, geometric_element};
use super::finish::{check_non_negative, check_positive, finish};
use super::sparse::Accumulator;
use super::spec::{MemberSpec, ModelSpec};
use super::{Channel, Connection, Model, ModelError, Parameter, ParameterKind};

/// A mesh node's DOF as a linear combination of unique DOFs (one row of `L`).
type Combo = Vec<(usize, f64)>;

/// Where a stiffness contribution goes: K0 or a parameter's K_l.
fn target(param: Option<usize>) -> usize {
    param.map_or(0, |l| l + 1)
}

fn invalid(field: impl Into<String>, reason: impl Into<String>) -> ModelError {
    ModelError::Invalid {
        field: field.into(),
        reason: reason.into(),
    }
}

fn unknown(field: impl Into<String>, what: &'static str, name: &str) -> ModelError {
    ModelError::Unknown {
        field: field.into(),
        what,
        name: name.to_string(),
    }
}

fn index_names<'a>(
    what: &'static str,
    names: impl Iterator<Item = &'a str>,
) -> Result<HashMap<&'a str, usize>, ModelError> {
    let mut map = HashMap::new();
    for (i, n) in names.enumerate() {
        if map.insert(n, i).is_some() {
            return Err(ModelError::Duplicate {
                what,
                name: n.to_string(),
            });
        }
    }
    Ok(map)
}

fn dir_index(d: &str) -> Option<usize> {
    match d {
        "x" => Some(0),
        "y" => Some(1),
        "rz" => Some(2),
        _ => None,
    }
}

/// DOF bookkeeping during assembly.
struct Dofs {
    labels: Vec<String>,
}

impl Dofs {
    fn new_dof(&mut self, label: String) -> usize {
        self.labels.push(label);
        self.labels.len() - 1
    }
}

/// Assembles a frame model; every failure names the offending entry.
pub(super) fn assemble(spec: &ModelSpec) -> Result<Model, ModelError> {
    let nodes = index_names("node", spec.nodes.iter().map(|n| n.name.as_str()))?;
    let members = index_names("member", spec.members.iter().map(|m| m.name.as_str()))?;
    let materials = index_names("material", spec.materials.iter().map(|m| m.name.as_str()))?;
    let sections = index_names("section", spec.sections.iter().map(|s| s.name.as_str()))?;
    let springs = index_names("spring", spec.springs.iter().map(|s| s.name.as_str()))?;
    index_names("parameter", spec.parameters.iter().map(|p| p.name.as_str()))?;
    index_names("channel", spec.channels.iter().map(|c| c.name.as_str()))?;
    for (key, v) in [
        ("bayesian.sigma_c", spec.bayesian.sigma_c),
        ("bayesian.prior_std", spec.bayesian.prior_std),
    ] {
        if let Some(v) = v.filter(|v| !(v.is_finite() && *v > 0.0)) {
            return Err(invalid(
                key,
                format!("must be a finite number > 0 (got {v})"),
            ));
        }
    }

    for (i, n) in spec.nodes.iter().enumerate() {
        if !(n.x.is_finite() && n.y.is_finite()) {
            return Err(invalid(
                format!("nodes[{i}] `{}`", n.name),
                "coordinates must be finite",
            ));
        }
    }
    for m in &spec.materials {
        check_positive(format!("materials `{}`.E", m.name), m.E)?;
        check_non_negative(format!("materials `{}`.rho", m.name), m.rho)?;
    }
    for s in &spec.sections {
        check_positive(format!("sections `{}`.A", s.name), s.A)?;
        check_positive(format!("sections `{}`.I", s.name), s.I)?;
    }

    // Fixed DOFs per node.
    let mut fixed = vec![[false; 3]; spec.nodes.len()];
    for (i, s) in spec.supports.iter().enumerate() {
        let field = format!("supports[{i}]");
        let n = *nodes
            .get(s.node.as_str())
            .ok_or_else(|| unknown(format!("{field}.node"), "node", &s.node))?;
        match &s.fix {
            None => fixed[n] = [true; 3],
            Some(list) => {
                for d in list {
                    let k = dir_index(d).ok_or_else(|| {
                        invalid(
                            format!("{field}.fix"),
                            format!("unknown DOF `{d}` (x, y or rz)"),
                        )
                    })?;
                    fixed[n][k] = true;
                }
            }
        }
    }

    // Joints: rigid bodies at nodes.
    let mut joint_of_node: Vec<Option<usize>> = vec![None; spec.nodes.len()];
    for (i, j) in spec.joints.iter().enumerate() {
        let field = format!("joints[{i}]");
        let n = *nodes
            .get(j.node.as_str())
            .ok_or_else(|| unknown(format!("{field}.node"), "node", &j.node))?;
        if joint_of_node[n].replace(i).is_some() {
            return Err(ModelError::Duplicate {
                what: "joint at node",
                name: j.node.clone(),
            });
        }
        check_non_negative(format!("{field}.mass"), j.mass)?;
        check_non_negative(format!("{field}.inertia"), j.inertia)?;
        check_non_negative(format!("{field}.size"), j.size)?;
    }

    // Parameters: which parameter scales each connection, member and spring.
    let conn_names: Vec<String> = spec
        .connections
        .iter()
        .map(|c| {
            c.name
                .clone()
                .unwrap_or_else(|| format!("{}@{}", c.member, c.node))
        })
        .collect();
    let conn_index = index_names("connection", conn_names.iter().map(|s| s.as_str()))?;
    let mut conn_param: Vec<Option<usize>> = vec![None; spec.connections.len()];
    let mut member_param: Vec<Option<usize>> = vec![None; spec.members.len()];
    let mut spring_param: Vec<Option<usize>> = vec![None; spec.springs.len()];
    let mut parameters = Vec::with_capacity(spec.parameters.len());
    for (l, p) in spec.parameters.iter().enumerate() {
        let field = format!("parameters[{l}] `{}`", p.name);
        let lists = [
            !p.connections.is_empty(),
            !p.members.is_empty(),
            !p.springs.is_empty(),
        ];
        if lists.iter().filter(|&&b| b).count() != 1 {
            return Err(invalid(
                field,
                "needs exactly one non-empty list of `connections`, `members` or `springs`",
            ));
        }
        let nominal = p.nominal.unwrap_or(1.0);
        check_positive(format!("{field}.nominal"), nominal)?;
        let claim = |slot: &mut Option<usize>, item: &str| -> Result<(), ModelError> {
            match slot.replace(l) {
                Some(other) => Err(invalid(
                    field.clone(),
                    format!(
                        "`{item}` is already scaled by parameter `{}`",
                        spec.parameters[other].name
                    ),
                )),
                None => Ok(()),
            }
        };
        let kind = if !p.connections.is_empty() {
            let mut idx = Vec::new();
            for c in &p.connections {
                let ci = *conn_index
                    .get(c.as_str())
                    .ok_or_else(|| unknown(format!("{field}.connections"), "connection", c))?;
                claim(&mut conn_param[ci], c)?;
                idx.push(ci);
            }
            ParameterKind::Connections(idx)
        } else if !p.members.is_empty() {
            for m in &p.members {
                let mi = *members
                    .get(m.as_str())
                    .ok_or_else(|| unknown(format!("{field}.members"), "member", m))?;
                claim(&mut member_param[mi], m)?;
            }
            ParameterKind::Modulus(p.members.clone())
        } else {
            for s in &p.springs {
                let si = *springs
                    .get(s.as_str())
                    .ok_or_else(|| unknown(format!("{field}.springs"), "spring", s))?;
                claim(&mut spring_param[si], s)?;
            }
            ParameterKind::Springs(p.springs.clone())
        };
        parameters.push(Parameter {
            name: p.name.clone(),
            nominal,
            lower: None,
            upper: None,
            kind,
        });
    }

    // Connections by member end.
    let mut conn_at: HashMap<(usize, usize), usize> = HashMap::new();
    for (i, c) in spec.connections.iter().enumerate() {
        let field = format!("connections[{i}] `{}`", conn_names[i]);
        let mi = *members
            .get(c.member.as_str())
            .ok_or_else(|| unknown(format!("{field}.member"), "member", &c.member))?;
        let n = *nodes
            .get(c.node.as_str())
            .ok_or_else(|| unknown(format!("{field}.node"), "node", &c.node))?;
        let m = &spec.members[mi];
        if m.from != c.node && m.to != c.node {
            return Err(invalid(
                field,
                format!("member `{}` has no end at node `{}`", c.member, c.node),
            ));
        }
        check_positive(format!("{field}.k"), c.k)?;
        if conn_at.insert((mi, n), i).is_some() {
            return Err(ModelError::Duplicate {
                what: "connection at member end",
                name: conn_names[i].clone(),
            });
        }
    }

    // Unique DOFs of the model nodes.
    let mut dofs = Dofs { labels: Vec::new() };
    let mut node_dofs: Vec<[Option<usize>; 3]> = Vec::with_capacity(spec.nodes.len());
    for (n, node) in spec.nodes.iter().enumerate() {
        let mut d = [None; 3];
        for (k, suffix) in ["x", "y", "rz"].iter().enumerate() {
            if !fixed[n][k] {
                d[k] = Some(dofs.new_dof(format!("{}.{suffix}", node.name)));
            }
        }
        node_dofs.push(d);
    }
    let combo = |d: Option<usize>| -> Combo { d.map(|i| vec![(i, 1.0)]).unwrap_or_default() };

    let p = parameters.len();
    let mut acc = vec![Accumulator::default(); p + 2]; // K0, K_1..K_p, M
    let mass_target = p + 1;

    // Members: mesh, element matrices, member-end kinematics.
    let mut interior: HashMap<String, [Combo; 3]> = HashMap::new();
    let mut connection_dof = vec![usize::MAX; spec.connections.len()];
    for (mi, m) in spec.members.iter().enumerate() {
        let field = format!("members[{mi}] `{}`", m.name);
        let a = *nodes
            .get(m.from.as_str())
            .ok_or_else(|| unknown(format!("{field}.from"), "node", &m.from))?;
        let b = *nodes
            .get(m.to.as_str())
            .ok_or_else(|| unknown(format!("{field}.to"), "node", &m.to))?;
        if a == b {
            return Err(invalid(field, "starts and ends at the same node"));
        }
        if m.elements == 0 {
            return Err(invalid(format!("{field}.elements"), "must be ≥ 1"));
        }
        let section = section_of(spec, m, &materials, &sections, &field)?;
        let pa = [spec.nodes[a].x, spec.nodes[a].y];
        let pb = [spec.nodes[b].x, spec.nodes[b].y];
        let len = (pb[0] - pa[0]).hypot(pb[1] - pa[1]);
        let e = [(pb[0] - pa[0]) / len, (pb[1] - pa[1]) / len];
        let size_at = |n: usize| joint_of_node[n].map_or(0.0, |j| spec.joints[j].size);
        let (sa, sb) = (size_at(a), size_at(b));
        if len <= sa + sb {
            return Err(invalid(
                field,
                format!("length {len} m is not longer than the joint offsets {sa} + {sb} m"),
            ));
        }
        // End positions and kinematics: translations follow the node (rigid offset r from a
        // joint's centre: u = u_c − r_y θ_c, v = v_c + r_x θ_c); the rotation is the node's,
        // or its own DOF when a bolted connection is defined at this end.
        let mut end = |n: usize, r: [f64; 2], dofs: &mut Dofs| -> [Combo; 3] {
            let [ux, uy, rz] = node_dofs[n];
            let mut cx = combo(ux);
            let mut cy = combo(uy);
            if let Some(t) = rz {
                if r[1] != 0.0 {
                    cx.push((t, -r[1]));
                }
                if r[0] != 0.0 {
                    cy.push((t, r[0]));
                }
            }
            let crot = match conn_at.get(&(mi, n)) {
                Some(&ci) => {
                    let d = dofs.new_dof(format!("{}.rz", conn_names[ci]));
                    connection_dof[ci] = d;
                    vec![(d, 1.0)]
                }
                None => combo(rz),
            };
            [cx, cy, crot]
        };
        let start = end(a, [sa * e[0], sa * e[1]], &mut dofs);
        let mut mesh: Vec<[Combo; 3]> = vec![start];
        let p0 = [pa[0] + sa * e[0], pa[1] + sa * e[1]];
        let p1 = [pb[0] - sb * e[0], pb[1] - sb * e[1]];
        for k in 1..m.elements {
            let mut c: [Combo; 3] = Default::default();
            for (d, suffix) in ["x", "y", "rz"].iter().enumerate() {
                c[d] = vec![(dofs.new_dof(format!("{}.{k}.{suffix}", m.name)), 1.0)];
            }
            interior.insert(format!("{}.{k}", m.name), c.clone());
            mesh.push(c);
        }
        mesh.push(end(b, [-sb * e[0], -sb * e[1]], &mut dofs));
        let n_el = m.elements as f64;
        let at = |k: usize| {
            let t = k as f64 / n_el;
            [p0[0] + t * (p1[0] - p0[0]), p0[1] + t * (p1[1] - p0[1])]
        };
        let kt = target(member_param[mi]);
        for k in 0..m.elements {
            let (ke, me) = frame_element(&section, at(k), at(k + 1));
            let (c1, c2) = (&mesh[k], &mesh[k + 1]);
            let maps: [&[(usize, f64)]; 6] = [&c1[0], &c1[1], &c1[2], &c2[0], &c2[1], &c2[2]];
            acc[kt].add_mapped(&ke, &maps);
            acc[mass_target].add_mapped(&me, &maps);
            if m.axial_force != 0.0 {
                let kg = geometric_element(m.axial_force, at(k), at(k + 1));
                acc[target(None)].add_mapped(&kg, &maps);
            }
        }
    }

    // Resolves a location name to the combinations of its three DOFs.
    let location = |field: String, at: &str| -> Result<[Combo; 3], ModelError> {
        if let Some(&n) = nodes.get(at) {
            let [x, y, r] = node_dofs[n];
            return Ok([combo(x), combo(y), combo(r)]);
        }
        interior
            .get(at)
            .cloned()
            .ok_or_else(|| unknown(field, "location (node or <member>.<k>)", at))
    };

    // Bolted connections, paper (2): K_l = k ℓ ℓᵀ with ℓ = e_end − e_node.
    let mut connections = Vec::with_capacity(spec.connections.len());
    for (ci, c) in spec.connections.iter().enumerate() {
        let n = nodes[c.node.as_str()];
        let d = connection_dof[ci];
        let mut ell: Combo = vec![(d, 1.0)];
        if let Some(r) = node_dofs[n][2] {
            ell.push((r, -1.0));
        }
        let t = target(conn_param[ci]);
        acc[t].add_mapped(&[[c.k]], &[&ell]);
        connections.push(Connection {
            name: conn_names[ci].clone(),
            member: c.member.clone(),
            node: c.node.clone(),
            k: c.k,
            parameter: conn_param[ci],
        });
    }

    // Joint masses.
    for j in &spec.joints {
        let [x, y, r] = node_dofs[nodes[j.node.as_str()]];
        for (d, v) in [(x, j.mass), (y, j.mass), (r, j.inertia)] {
            if let Some(i) = d {
                acc[mass_target].add(i, i, v);
            }
        }
    }
    // Lumped masses.
    for (i, ms) in spec.masses.iter().enumerate() {
        let field = format!("masses[{i}]");
        check_non_negative(format!("{field}.mass"), ms.mass)?;
        check_non_negative(format!("{field}.inertia"), ms.inertia)?;
        let c = location(format!("{field}.at"), &ms.at)?;
        for (d, v) in [(0, ms.mass), (1, ms.mass), (2, ms.inertia)] {
            acc[mass_target].add_mapped(&[[v]], &[&c[d]]);
        }
    }
    // Discrete springs.
    for (i, s) in spec.springs.iter().enumerate() {
        let field = format!("springs[{i}] `{}`", s.name);
        check_positive(format!("{field}.k"), s.k)?;
        let d = dir_index(&s.dof)
            .ok_or_else(|| invalid(format!("{field}.dof"), format!("unknown DOF `{}`", s.dof)))?;
        let mut ell = location(format!("{field}.a"), &s.a)?[d].clone();
        if let Some(b) = &s.b {
            let cb = location(format!("{field}.b"), b)?;
            ell.extend(cb[d].iter().map(|&(j, c)| (j, -c)));
        }
        if ell.is_empty() {
            return Err(invalid(field, "both ends are fixed"));
        }
        acc[target(spring_param[i])].add_mapped(&[[s.k]], &[&ell]);
    }

    // Channels.
    let mut channels = Vec::with_capacity(spec.channels.len());
    for (i, c) in spec.channels.iter().enumerate() {
        let field = format!("channels[{i}] `{}`", c.name);
        let d = dir_index(&c.dir).ok_or_else(|| {
            invalid(
                format!("{field}.dir"),
                format!("unknown direction `{}`", c.dir),
            )
        })?;
        let dofs = location(format!("{field}.at"), &c.at)?[d].clone();
        if dofs.is_empty() {
            return Err(invalid(field, "reads only fixed DOFs"));
        }
        channels.push(Channel {
            name: c.name.clone(),
            dofs,
        });
    }

    let n = dofs.labels.len();
    finish(
        &spec.name,
        dofs.labels,
        acc.iter().map(|a| a.build(n)).collect(),
        parameters,
        connections,
        channels,
        spec.bayesian.clone(),
    )
}

fn section_of(
    spec: &ModelSpec,
    m: &MemberSpec,
    materials: &HashMap<&str, usize>,
    sections: &HashMap<&str, usize>,
    field: &str,
) -> Result<Section, ModelError> {
    let mat = &spec.materials[*materials
        .get(m.material.as_str())
        .ok_or_else(|| unknown(format!("{field}.material"), "material", &m.material))?];
    let sec = &spec.sections[*sections
        .get(m.section.as_str())
        .ok_or_else(|| unknown(format!("{field}.section"), "section", &m.section))?];
    Ok(Section {
        E: mat.E,
        rho: mat.rho,
        A: sec.A,
        I: sec.I,
    })
}
