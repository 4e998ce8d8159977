//! Assembles a checked plane-frame [`ModelSpec`] (the checks in `assemble_check`): `K0`,
//! `K_l`, `M` and the channel rows.

use std::collections::HashMap;

use super::assemble_check::{
    Names, Scaling, connections_by_end, dir_index, invalid, joints, parameters, supports, unknown,
    validate,
};
use super::element::{Section, frame_element, geometric_element};
use super::finish::{check_non_negative, check_positive, finish};
use super::sparse::Accumulator;
use super::spec::{MemberSpec, ModelSpec};
use super::{Channel, Connection, Model, ModelError};

/// A mesh node's DOF as a linear combination of unique DOFs (one row of `L`).
type Combo = Vec<(usize, f64)>;

/// Where a stiffness contribution goes: K0 or a parameter's K_l.
fn target(param: Option<usize>) -> usize {
    param.map_or(0, |l| l + 1)
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
    let names = validate(spec)?;
    let fixed = supports(spec, &names.nodes)?;
    let joint_of_node = joints(spec, &names.nodes)?;
    let scaling = parameters(spec, &names)?;
    let conn_at = connections_by_end(spec, &names, &scaling.conn_names)?;
    let mut layout = Layout::new(spec, names, scaling, joint_of_node, conn_at);
    layout.add_node_dofs(&fixed);
    for mi in 0..spec.members.len() {
        layout.member(mi)?;
    }
    let connections = layout.bolted_connections();
    layout.joint_masses();
    layout.lumped_masses()?;
    layout.springs()?;
    let channels = layout.channels()?;
    layout.into_model(connections, channels)
}

/// A DOF as a combination: itself, or nothing when it is fixed.
fn combo(d: Option<usize>) -> Combo {
    d.map(|i| vec![(i, 1.0)]).unwrap_or_default()
}

/// A member's axis between the joint offsets at its ends, and its section.
struct Geometry {
    /// The model nodes it starts and ends at.
    a: usize,
    b: usize,
    section: Section,
    /// Unit vector from `a` to `b`.
    e: [f64; 2],
    /// The joint offsets at `a` and `b`, m.
    sa: f64,
    sb: f64,
    /// The ends of the meshed length.
    p0: [f64; 2],
    p1: [f64; 2],
    /// Number of elements.
    n_el: f64,
}

impl Geometry {
    /// Position of mesh node `k` (`0..=elements`, evenly spaced from `p0` to `p1`).
    fn at(&self, k: usize) -> [f64; 2] {
        let t = k as f64 / self.n_el;
        [
            self.p0[0] + t * (self.p1[0] - self.p0[0]),
            self.p0[1] + t * (self.p1[1] - self.p0[1]),
        ]
    }
}

/// The DOF layout and the matrices under assembly, after the checks of names, supports,
/// joints, parameters and connections.
struct Layout<'a> {
    spec: &'a ModelSpec,
    names: Names<'a>,
    scaling: Scaling,
    joint_of_node: Vec<Option<usize>>,
    conn_at: HashMap<(usize, usize), usize>,
    dofs: Dofs,
    /// The unique DOFs (x, y, rz) of each model node; `None` where fixed.
    node_dofs: Vec<[Option<usize>; 3]>,
    /// The DOFs of the interior mesh nodes, by location name `<member>.<k>`.
    interior: HashMap<String, [Combo; 3]>,
    /// The rotation DOF of each connection's member end.
    connection_dof: Vec<usize>,
    /// `K0`, `K_1..K_p`, `M`.
    acc: Vec<Accumulator>,
    mass_target: usize,
}

impl<'a> Layout<'a> {
    /// A layout without DOFs, and zero matrices.
    fn new(
        spec: &'a ModelSpec,
        names: Names<'a>,
        scaling: Scaling,
        joint_of_node: Vec<Option<usize>>,
        conn_at: HashMap<(usize, usize), usize>,
    ) -> Self {
        let p = scaling.parameters.len();
        Layout {
            spec,
            names,
            scaling,
            joint_of_node,
            conn_at,
            dofs: Dofs { labels: Vec::new() },
            node_dofs: Vec::with_capacity(spec.nodes.len()),
            interior: HashMap::new(),
            connection_dof: vec![usize::MAX; spec.connections.len()],
            acc: vec![Accumulator::default(); p + 2], // K0, K_1..K_p, M
            mass_target: p + 1,
        }
    }

    /// Numbers the free DOFs of the model nodes, node by node (`<node>.x`, `.y`, `.rz`).
    fn add_node_dofs(&mut self, fixed: &[[bool; 3]]) {
        let spec = self.spec;
        for (n, node) in spec.nodes.iter().enumerate() {
            let mut d = [None; 3];
            for (k, suffix) in ["x", "y", "rz"].iter().enumerate() {
                if !fixed[n][k] {
                    d[k] = Some(self.dofs.new_dof(format!("{}.{suffix}", node.name)));
                }
            }
            self.node_dofs.push(d);
        }
    }

    /// Meshes member `mi` and adds its element matrices: stiffness to `K0` or its
    /// parameter's `K_l`, consistent mass to `M`, and the geometric stiffness of its axial
    /// force to `K0`.
    fn member(&mut self, mi: usize) -> Result<(), ModelError> {
        let spec = self.spec;
        let m = &spec.members[mi];
        let g = self.geometry(mi)?;
        let mesh = self.mesh(mi, &g);
        let kt = target(self.scaling.claims.member[mi]);
        for k in 0..m.elements {
            let (ke, me) = frame_element(&g.section, g.at(k), g.at(k + 1));
            let (c1, c2) = (&mesh[k], &mesh[k + 1]);
            let maps: [&[(usize, f64)]; 6] = [&c1[0], &c1[1], &c1[2], &c2[0], &c2[1], &c2[2]];
            self.acc[kt].add_mapped(&ke, &maps);
            self.acc[self.mass_target].add_mapped(&me, &maps);
            if m.axial_force != 0.0 {
                let kg = geometric_element(m.axial_force, g.at(k), g.at(k + 1));
                self.acc[target(None)].add_mapped(&kg, &maps);
            }
        }
        Ok(())
    }

    /// Checks member `mi` (its end nodes, element count, material and section, and that it
    /// is longer than the joint offsets at its ends) and returns its geometry.
    fn geometry(&self, mi: usize) -> Result<Geometry, ModelError> {
        let spec = self.spec;
        let m = &spec.members[mi];
        let field = format!("members[{mi}] `{}`", m.name);
        let a = *self
            .names
            .nodes
            .get(m.from.as_str())
            .ok_or_else(|| unknown(format!("{field}.from"), "node", &m.from))?;
        let b = *self
            .names
            .nodes
            .get(m.to.as_str())
            .ok_or_else(|| unknown(format!("{field}.to"), "node", &m.to))?;
        if a == b {
            return Err(invalid(field, "starts and ends at the same node"));
        }
        if m.elements == 0 {
            return Err(invalid(format!("{field}.elements"), "must be ≥ 1"));
        }
        let section = section_of(spec, m, &self.names.materials, &self.names.sections, &field)?;
        let pa = [spec.nodes[a].x, spec.nodes[a].y];
        let pb = [spec.nodes[b].x, spec.nodes[b].y];
        let len = (pb[0] - pa[0]).hypot(pb[1] - pa[1]);
        let e = [(pb[0] - pa[0]) / len, (pb[1] - pa[1]) / len];
        let size_at = |n: usize| self.joint_of_node[n].map_or(0.0, |j| spec.joints[j].size);
        let (sa, sb) = (size_at(a), size_at(b));
        if len <= sa + sb {
            return Err(invalid(
                field,
                format!("length {len} m is not longer than the joint offsets {sa} + {sb} m"),
            ));
        }
        Ok(Geometry {
            a,
            b,
            section,
            e,
            sa,
            sb,
            p0: [pa[0] + sa * e[0], pa[1] + sa * e[1]],
            p1: [pb[0] - sb * e[0], pb[1] - sb * e[1]],
            n_el: m.elements as f64,
        })
    }

    /// The DOF combinations of member `mi`'s mesh nodes, from `a` to `b`: its start, new
    /// DOFs for each interior node (`<member>.<k>.x`, `.y`, `.rz`), its end.
    fn mesh(&mut self, mi: usize, g: &Geometry) -> Vec<[Combo; 3]> {
        let spec = self.spec;
        let m = &spec.members[mi];
        let start = self.end(mi, g.a, [g.sa * g.e[0], g.sa * g.e[1]]);
        let mut mesh: Vec<[Combo; 3]> = vec![start];
        for k in 1..m.elements {
            let mut c: [Combo; 3] = Default::default();
            for (d, suffix) in ["x", "y", "rz"].iter().enumerate() {
                c[d] = vec![(self.dofs.new_dof(format!("{}.{k}.{suffix}", m.name)), 1.0)];
            }
            self.interior.insert(format!("{}.{k}", m.name), c.clone());
            mesh.push(c);
        }
        mesh.push(self.end(mi, g.b, [-g.sb * g.e[0], -g.sb * g.e[1]]));
        mesh
    }

    /// The DOF combinations of member `mi`'s end at node `n`, offset `r` from it.
    /// Translations follow the node (rigid offset r from a joint's centre:
    /// u = u_c − r_y θ_c, v = v_c + r_x θ_c); the rotation is the node's, or its own new DOF
    /// when a bolted connection is defined at this end.
    fn end(&mut self, mi: usize, n: usize, r: [f64; 2]) -> [Combo; 3] {
        let [ux, uy, rz] = self.node_dofs[n];
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
        let crot = match self.conn_at.get(&(mi, n)) {
            Some(&ci) => {
                let d = self
                    .dofs
                    .new_dof(format!("{}.rz", self.scaling.conn_names[ci]));
                self.connection_dof[ci] = d;
                vec![(d, 1.0)]
            }
            None => combo(rz),
        };
        [cx, cy, crot]
    }

    /// Adds the bolted connections, paper (2): `K_l = k ℓ ℓᵀ` with `ℓ = e_end − e_node`, to
    /// `K0` or the parameter's `K_l`; returns them.
    fn bolted_connections(&mut self) -> Vec<Connection> {
        let spec = self.spec;
        let mut connections = Vec::with_capacity(spec.connections.len());
        for (ci, c) in spec.connections.iter().enumerate() {
            let n = self.names.nodes[c.node.as_str()];
            let d = self.connection_dof[ci];
            let mut ell: Combo = vec![(d, 1.0)];
            if let Some(r) = self.node_dofs[n][2] {
                ell.push((r, -1.0));
            }
            let t = target(self.scaling.claims.conn[ci]);
            self.acc[t].add_mapped(&[[c.k]], &[&ell]);
            connections.push(Connection {
                name: self.scaling.conn_names[ci].clone(),
                member: c.member.clone(),
                node: c.node.clone(),
                k: c.k,
                parameter: self.scaling.claims.conn[ci],
            });
        }
        connections
    }

    /// Adds each joint's mass (on x and y) and rotary inertia (on rz) to `M`.
    fn joint_masses(&mut self) {
        let spec = self.spec;
        for j in &spec.joints {
            let [x, y, r] = self.node_dofs[self.names.nodes[j.node.as_str()]];
            for (d, v) in [(x, j.mass), (y, j.mass), (r, j.inertia)] {
                if let Some(i) = d {
                    self.acc[self.mass_target].add(i, i, v);
                }
            }
        }
    }

    /// Checks the lumped masses and adds each (mass on x and y, rotary inertia on rz) to `M`.
    fn lumped_masses(&mut self) -> Result<(), ModelError> {
        let spec = self.spec;
        for (i, ms) in spec.masses.iter().enumerate() {
            let field = format!("masses[{i}]");
            check_non_negative(format!("{field}.mass"), ms.mass)?;
            check_non_negative(format!("{field}.inertia"), ms.inertia)?;
            let c = self.location(format!("{field}.at"), &ms.at)?;
            for (d, v) in [(0, ms.mass), (1, ms.mass), (2, ms.inertia)] {
                self.acc[self.mass_target].add_mapped(&[[v]], &[&c[d]]);
            }
        }
        Ok(())
    }

    /// Checks the discrete springs and adds each, `k ℓ ℓᵀ` with `ℓ = e_a − e_b` along its
    /// DOF, to `K0` or its parameter's `K_l`.
    fn springs(&mut self) -> Result<(), ModelError> {
        let spec = self.spec;
        for (i, s) in spec.springs.iter().enumerate() {
            let field = format!("springs[{i}] `{}`", s.name);
            check_positive(format!("{field}.k"), s.k)?;
            let d = dir_index(&s.dof).ok_or_else(|| {
                invalid(format!("{field}.dof"), format!("unknown DOF `{}`", s.dof))
            })?;
            let mut ell = self.location(format!("{field}.a"), &s.a)?[d].clone();
            if let Some(b) = &s.b {
                let cb = self.location(format!("{field}.b"), b)?;
                ell.extend(cb[d].iter().map(|&(j, c)| (j, -c)));
            }
            if ell.is_empty() {
                return Err(invalid(field, "both ends are fixed"));
            }
            self.acc[target(self.scaling.claims.spring[i])].add_mapped(&[[s.k]], &[&ell]);
        }
        Ok(())
    }

    /// Checks the channels and returns each as its combination of DOFs.
    fn channels(&self) -> Result<Vec<Channel>, ModelError> {
        let spec = self.spec;
        let mut channels = Vec::with_capacity(spec.channels.len());
        for (i, c) in spec.channels.iter().enumerate() {
            let field = format!("channels[{i}] `{}`", c.name);
            let d = dir_index(&c.dir).ok_or_else(|| {
                invalid(
                    format!("{field}.dir"),
                    format!("unknown direction `{}`", c.dir),
                )
            })?;
            let dofs = self.location(format!("{field}.at"), &c.at)?[d].clone();
            if dofs.is_empty() {
                return Err(invalid(field, "reads only fixed DOFs"));
            }
            channels.push(Channel {
                name: c.name.clone(),
                dofs,
            });
        }
        Ok(channels)
    }

    /// Resolves a location name (a model node, or an interior mesh node `<member>.<k>`) to
    /// the combinations of its three DOFs.
    fn location(&self, field: String, at: &str) -> Result<[Combo; 3], ModelError> {
        if let Some(&n) = self.names.nodes.get(at) {
            let [x, y, r] = self.node_dofs[n];
            return Ok([combo(x), combo(y), combo(r)]);
        }
        self.interior
            .get(at)
            .cloned()
            .ok_or_else(|| unknown(field, "location (node or <member>.<k>)", at))
    }

    /// Builds the matrices over all DOFs and completes the model ([`finish`]).
    fn into_model(
        self,
        connections: Vec<Connection>,
        channels: Vec<Channel>,
    ) -> Result<Model, ModelError> {
        let n = self.dofs.labels.len();
        finish(
            &self.spec.name,
            self.dofs.labels,
            self.acc.iter().map(|a| a.build(n)).collect(),
            self.scaling.parameters,
            connections,
            channels,
            self.spec.bayesian.clone(),
        )
    }
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
