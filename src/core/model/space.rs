//! Space frames (issue 25): nodes with six DOF, members of [`super::frame3d`] elements,
//! rigid joints with mass, rotary inertia and member-end offsets, bolted connections with a
//! rotational spring about any of a member end's local axes, assembled primally (paper
//! (3)–(4)): every element DOF is a linear combination of the model's DOFs (an offset end's
//! translation is the joint's `u + ω × r`; a member end's rotation about a rigid axis is the
//! joint's rotation projected on that axis, about a sprung axis a DOF of its own).
//!
//! ```toml
//! [space_frame]
//! materials = [{ name = "steel", E = 2.1e11, nu = 0.3, rho = 7850.0 }]
//! sections = [{ name = "beam", A = 8e-4, Iy = 2.67e-8, Iz = 1.07e-7, J = 7.33e-8 }]
//! nodes = [{ name = "J1A1", x = 0.0, y = 0.6, z = 0.0 }]
//! members = [{ name = "BX11a", from = "J1A1", to = "J1B1", section = "beam",
//!              material = "steel", elements = 4 }]  # orientation = [0, 1, 0], axial_force
//! joints = [{ node = "J1A1", mass = 2.0 }]           # inertia = [Ix, Iy, Iz], size = 0.04
//! supports = [{ node = "A1" }]                       # fix = ["x", "ry"]; absent: all six
//! restrain = ["z", "rx", "ry"]                       # fixed at every node (optional)
//! connections = [{ member = "BX11a", node = "J1A1", strong = 5e4, weak = 2e4 }]
//! masses = [{ at = "BX11a.2", mass = 0.5 }]          # inertia = [Ix, Iy, Iz]
//! springs = [{ name = "pad", a = "A1", dof = "y", k = 1e7 }]  # b = "<location>"
//! parameters = [{ name = "BX11a@J1A1", connections = ["BX11a@J1A1.strong"] }]
//! channels = [{ name = "BX11a.2.y", at = "BX11a.2", dir = "y" }]
//! ```
//! Locations (`at`, `a`, `b`) are nodes or mesh nodes `<member>.<k>` counted from the
//! member's `from` end (`<member>.0` is the offset end itself). Parameters scale connection
//! axes (`<connection>.<torsion|weak|strong>`, the connection named `<member>@<node>`
//! unless it has a `name`), members (E) or springs.

use std::collections::HashMap;

use nalgebra::{Matrix3, Vector3};

use super::frame3d::{Section3, default_reference, global_geometric, global_matrices, local_axes};
pub use super::space_check::DOF_NAMES;
use super::space_check::{check, dof_index, fixed_dofs, invalid, node_index, restrained_dofs};
use super::sparse::{Csc, csc_from_triplets};
pub use super::spec::{
    AXES, Connection3, Joint3, Mass3, Material3, Member3, Node3, SectionSpec3, SpaceFrameSpec,
    Spring3,
};
use super::spec::{BayesSpec, ParameterSpec};
use super::{Channel, Connection, Model, ModelError, Parameter, ParameterKind};

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

/// Adds `v ℓ ℓᵀ` for the combination `ℓ` into `out` (a spring or a lumped mass).
fn scatter_rank_one(out: &mut Vec<(usize, usize, f64)>, ell: &[(usize, f64)], v: f64) {
    for &(i, ci) in ell {
        for &(j, cj) in ell {
            out.push((i, j, v * ci * cj));
        }
    }
}

/// `c += w · other`.
fn add_scaled(c: &mut Combo, other: &[(usize, f64)], w: f64) {
    if w != 0.0 {
        c.extend(other.iter().map(|&(d, x)| (d, w * x)));
    }
}

/// Checks and assembles a `[space_frame]` model, primally (paper (2)–(4)): the entries'
/// references, the fixed DOFs, the nodes' DOFs, each member (mesh, end kinematics, element
/// matrices), the bolted connections' springs, the joint and lumped masses, the discrete
/// springs, then the parameters and channels.
pub fn assemble(name: &str, s: &SpaceFrameSpec, bayesian: &BayesSpec) -> Result<Model, ModelError> {
    check(s)?;
    let restrained = restrained_dofs(s)?;
    let fixed = fixed_dofs(s, restrained)?;
    let mut frame = Assembly::new(s, restrained, &fixed);
    for m in &s.members {
        frame.add_member(m)?;
    }
    let connections = frame.add_connection_springs();
    frame.add_joint_masses()?;
    frame.add_lumped_masses()?;
    frame.add_springs()?;
    let parameters = parameters_of(s, &connections);
    let channels = frame.channels()?;
    let (labels, mats) = frame.into_matrices();
    super::finish::finish(
        name,
        labels,
        mats,
        parameters,
        connections,
        channels,
        bayesian.clone(),
    )
}

/// The matrix an item's stiffness goes to: `K_l` (slot `l`, from 1) for the parameter
/// listing it in `list`, K0 (slot 0) for none.
fn slot_of(s: &SpaceFrameSpec, item: &str, list: fn(&ParameterSpec) -> &Vec<String>) -> usize {
    s.parameters
        .iter()
        .position(|q| list(q).iter().any(|x| x == item))
        .map_or(0, |l| l + 1)
}

/// A node's DOFs as combinations (empty where fixed).
fn node_combo(dofs: &[Option<usize>; 6]) -> [Combo; 6] {
    std::array::from_fn(|c| dofs[c].map(|d| vec![(d, 1.0)]).unwrap_or_default())
}

/// The combinations at every location: the nodes, and each member's mesh nodes
/// `<member>.<k>`.
struct Locations(HashMap<String, [Combo; 6]>);

impl Locations {
    /// The combinations at location `at`, named in `field`.
    fn get(&self, field: String, at: &str) -> Result<&[Combo; 6], ModelError> {
        self.0.get(at).ok_or_else(|| ModelError::Unknown {
            field,
            what: "location (node or <member>.<k>)",
            name: at.to_string(),
        })
    }

    /// Names a location.
    fn insert(&mut self, at: String, combo: [Combo; 6]) {
        self.0.insert(at, combo);
    }
}

/// A sprung axis of a bolted connection: its spring `½ k (ℓ · q)²`, `ℓ` the end's own
/// rotation less the joint's about the axis.
struct AxisSpring {
    /// `<connection>.<torsion|weak|strong>`.
    name: String,
    member: String,
    node: String,
    ell: Combo,
    k: f64,
}

/// Where a member lies: its end nodes, section, local axes and joint offsets.
struct MemberGeometry {
    /// `members.<name>`, for errors.
    field: String,
    /// The indices of its `from` and `to` nodes.
    a: usize,
    b: usize,
    section: Section3,
    /// The positions of its `from` and `to` nodes.
    pa: Vector3<f64>,
    pb: Vector3<f64>,
    reference: Vector3<f64>,
    /// Global to local axes (rows: local x, y, z).
    r: Matrix3<f64>,
    /// The unit vector from `from` to `to`.
    e: Vector3<f64>,
    /// The joint offsets at `from` and `to`.
    sa: f64,
    sb: f64,
}

impl MemberGeometry {
    /// Checks member `m` (its nodes, at least one element, its section, its orientation,
    /// longer than its joint offsets) and places it.
    fn of(s: &SpaceFrameSpec, m: &Member3) -> Result<Self, ModelError> {
        let field = format!("members.{}", m.name);
        let (a, b) = (
            node_index(s, &m.from, &field)?,
            node_index(s, &m.to, &field)?,
        );
        if m.elements == 0 {
            return Err(invalid(format!("{field}.elements"), "must be at least 1"));
        }
        let section = s.section_of(m)?;
        let pos = |k: usize| Vector3::new(s.nodes[k].x, s.nodes[k].y, s.nodes[k].z);
        let (pa, pb) = (pos(a), pos(b));
        let reference = m.orientation.map_or_else(
            || default_reference(pa, pb),
            |o| Vector3::new(o[0], o[1], o[2]),
        );
        let r = local_axes(pa, pb, reference)
            .map_err(|e| invalid(format!("{field}.orientation"), e.to_string()))?;
        let len = (pb - pa).norm();
        let e = (pb - pa) / len;
        let (sa, sb) = (s.joint_size(&m.from), s.joint_size(&m.to));
        if len <= sa + sb {
            return Err(invalid(
                field,
                format!("length {len} m is not longer than the joint offsets {sa} + {sb} m"),
            ));
        }
        Ok(Self {
            field,
            a,
            b,
            section,
            pa,
            pb,
            reference,
            r,
            e,
            sa,
            sb,
        })
    }
}

/// A space frame under assembly: its numbered DOFs, the combinations at every location,
/// the triplets of `K0, K_1 … K_p, M`, and the connection springs met so far.
struct Assembly<'s> {
    s: &'s SpaceFrameSpec,
    /// The DOFs fixed at every node and mesh node.
    restrained: [bool; 6],
    dofs: Dofs,
    /// Each node's numbered DOFs (`None`: fixed).
    node_dofs: Vec<[Option<usize>; 6]>,
    locations: Locations,
    /// `K0, K_1 … K_p, M` as triplets.
    mats: Vec<Vec<(usize, usize, f64)>>,
    /// The sprung connection axes, in the order their DOFs were numbered.
    springs: Vec<AxisSpring>,
}

impl<'s> Assembly<'s> {
    /// Numbers the nodes' free DOFs (node by node, `x` … `rz`) and names the nodes as
    /// locations.
    fn new(s: &'s SpaceFrameSpec, restrained: [bool; 6], fixed: &[[bool; 6]]) -> Self {
        let mut dofs = Dofs { labels: Vec::new() };
        let node_dofs: Vec<[Option<usize>; 6]> = s
            .nodes
            .iter()
            .enumerate()
            .map(|(k, n)| {
                std::array::from_fn(|c| {
                    (!fixed[k][c]).then(|| dofs.add(format!("{}.{}", n.name, DOF_NAMES[c])))
                })
            })
            .collect();
        let locations = Locations(
            s.nodes
                .iter()
                .enumerate()
                .map(|(k, n)| (n.name.clone(), node_combo(&node_dofs[k])))
                .collect(),
        );
        Self {
            s,
            restrained,
            dofs,
            node_dofs,
            locations,
            mats: vec![Vec::new(); s.parameters.len() + 2],
            springs: Vec::new(),
        }
    }

    /// The index of `M` in `mats`.
    fn mass_slot(&self) -> usize {
        self.s.parameters.len() + 1
    }

    /// Checks, meshes and adds member `m`: its stiffness to K0 or the `K_l` of the
    /// parameter scaling its E.
    fn add_member(&mut self, m: &Member3) -> Result<(), ModelError> {
        let g = MemberGeometry::of(self.s, m)?;
        let slot = slot_of(self.s, &m.name, |q| &q.members);
        let mesh = self.mesh(m, &g);
        self.add_elements(m, &g, &mesh, slot)
    }

    /// The combinations at member `m`'s mesh nodes from its `from` end, numbering their
    /// DOFs: the ends follow their joints ([`Self::end_combo`]), interior nodes get six
    /// DOFs each (less the restrained), numbered before the far end's (the plane frames'
    /// DOF order).
    fn mesh(&mut self, m: &Member3, g: &MemberGeometry) -> Vec<[Combo; 6]> {
        let mut mesh: Vec<[Combo; 6]> = Vec::with_capacity(m.elements + 1);
        for (end, k, offset) in [(0usize, g.a, g.e * g.sa), (m.elements, g.b, -g.e * g.sb)] {
            if end > 0 {
                for i in 1..m.elements {
                    mesh.push(self.interior_node(m, i));
                }
            }
            let combo = self.end_combo(m, k, offset, &g.r);
            self.locations
                .insert(format!("{}.{end}", m.name), combo.clone());
            mesh.push(combo);
        }
        mesh
    }

    /// Numbers the DOFs of member `m`'s interior mesh node `i` and names it as a location.
    fn interior_node(&mut self, m: &Member3, i: usize) -> [Combo; 6] {
        let restrained = self.restrained;
        let dofs = &mut self.dofs;
        let interior: [Combo; 6] = std::array::from_fn(|c| {
            if restrained[c] {
                Vec::new()
            } else {
                vec![(dofs.add(format!("{}.{i}.{}", m.name, DOF_NAMES[c])), 1.0)]
            }
        });
        self.locations
            .insert(format!("{}.{i}", m.name), interior.clone());
        interior
    }

    /// The combinations at member `m`'s end that sits `offset` from the centre of joint
    /// `k`: translations `u + ω × offset`, rotations the joint's `ω` or, at a bolted
    /// connection, [`Self::connection_rotations`].
    fn end_combo(
        &mut self,
        m: &Member3,
        k: usize,
        offset: Vector3<f64>,
        r: &Matrix3<f64>,
    ) -> [Combo; 6] {
        let s = self.s;
        let mut combo = node_combo(&self.node_dofs[k]);
        let w = [combo[3].clone(), combo[4].clone(), combo[5].clone()];
        add_scaled(&mut combo[0], &w[1], offset.z);
        add_scaled(&mut combo[0], &w[2], -offset.y);
        add_scaled(&mut combo[1], &w[2], offset.x);
        add_scaled(&mut combo[1], &w[0], -offset.z);
        add_scaled(&mut combo[2], &w[0], offset.y);
        add_scaled(&mut combo[2], &w[1], -offset.x);
        if let Some(conn) = s
            .connections
            .iter()
            .find(|c| c.member == m.name && c.node == s.nodes[k].name)
        {
            let [rx, ry, rz] = self.connection_rotations(m, conn, r, &w);
            [combo[3], combo[4], combo[5]] = [rx, ry, rz];
        }
        combo
    }

    /// The rotations `Σ_a e_a ρ_a` of a member end at connection `conn`, `e_a` the member's
    /// local axes (rows of `r`) and `ρ_a` the joint rotation `w` about `e_a` (a rigid axis)
    /// or the end's own DOF (a sprung one, whose spring `½ k (ρ_own − e_a · ω)²` is kept for
    /// paper (2)).
    fn connection_rotations(
        &mut self,
        m: &Member3,
        conn: &Connection3,
        r: &Matrix3<f64>,
        w: &[Combo; 3],
    ) -> [Combo; 3] {
        let mut rot: [Combo; 3] = Default::default();
        for (ax, kval) in [conn.torsion, conn.weak, conn.strong].iter().enumerate() {
            let axis = r.row(ax);
            let mut along: Combo = Vec::new();
            for c in 0..3 {
                add_scaled(&mut along, &w[c], axis[c]);
            }
            let rho_a = match kval {
                None => along,
                Some(kv) => {
                    let cname = format!("{}.{}", conn.name(), AXES[ax]);
                    let own = self.dofs.add(cname.clone());
                    let mut diff: Combo = vec![(own, 1.0)];
                    add_scaled(&mut diff, &along, -1.0);
                    self.springs.push(AxisSpring {
                        name: cname,
                        member: m.name.clone(),
                        node: conn.node.clone(),
                        ell: diff,
                        k: *kv,
                    });
                    vec![(own, 1.0)]
                }
            };
            for c in 0..3 {
                add_scaled(&mut rot[c], &rho_a, axis[c]);
            }
        }
        rot
    }

    /// Adds member `m`'s elements over its `mesh`: stiffness to `K_slot`, consistent mass
    /// to M and, under an axial force, geometric stiffness to K0.
    fn add_elements(
        &mut self,
        m: &Member3,
        g: &MemberGeometry,
        mesh: &[[Combo; 6]],
        slot: usize,
    ) -> Result<(), ModelError> {
        let mass = self.mass_slot();
        let (p0, p1) = (g.pa + g.e * g.sa, g.pb - g.e * g.sb);
        let step = (p1 - p0) / m.elements as f64;
        for el in 0..m.elements {
            let q0 = p0 + step * el as f64;
            let (ke, me) = global_matrices(&g.section, q0, q0 + step, g.reference)
                .map_err(|err| invalid(g.field.clone(), err.to_string()))?;
            let combos: [Combo; 12] = std::array::from_fn(|i| mesh[el + i / 6][i % 6].clone());
            scatter(&mut self.mats[slot], &combos, &ke);
            scatter(&mut self.mats[mass], &combos, &me);
            if m.axial_force != 0.0 {
                let kg = global_geometric(m.axial_force, q0, q0 + step, g.reference)
                    .map_err(|err| invalid(g.field.clone(), err.to_string()))?;
                scatter(&mut self.mats[0], &combos, &kg);
            }
        }
        Ok(())
    }

    /// Adds each connection axis's spring `k ℓ ℓᵀ` to K0 or its parameter's `K_l`, paper
    /// (2), and lists the connections in that order.
    fn add_connection_springs(&mut self) -> Vec<Connection> {
        let springs = std::mem::take(&mut self.springs);
        let mut connections: Vec<Connection> = Vec::with_capacity(springs.len());
        for sp in springs {
            let slot = slot_of(self.s, &sp.name, |q| &q.connections);
            scatter_rank_one(&mut self.mats[slot], &sp.ell, sp.k);
            connections.push(Connection {
                name: sp.name,
                member: sp.member,
                node: sp.node,
                k: sp.k,
                parameter: (slot > 0).then(|| slot - 1),
            });
        }
        connections
    }

    /// Adds each joint's mass and rotary inertia, at the joint's centre, to M.
    fn add_joint_masses(&mut self) -> Result<(), ModelError> {
        let s = self.s;
        let mass = self.mass_slot();
        for j in &s.joints {
            let k = node_index(s, &j.node, "joints.node")?;
            super::finish::check_non_negative(format!("joints.{}.mass", j.node), j.mass)?;
            super::finish::check_non_negative(format!("joints.{}.size", j.node), j.size)?;
            for (c, dof) in self.node_dofs[k].iter().enumerate() {
                let v = if c < 3 { j.mass } else { j.inertia[c - 3] };
                super::finish::check_non_negative(format!("joints.{}.inertia", j.node), v)?;
                if let (Some(d), true) = (dof, v != 0.0) {
                    self.mats[mass].push((*d, *d, v));
                }
            }
        }
        Ok(())
    }

    /// Adds each lumped mass and rotary inertia `v ℓ ℓᵀ`, at its location, to M.
    fn add_lumped_masses(&mut self) -> Result<(), ModelError> {
        let s = self.s;
        let mass = self.mass_slot();
        for (i, ms) in s.masses.iter().enumerate() {
            let field = format!("masses[{i}]");
            let c = self.locations.get(format!("{field}.at"), &ms.at)?;
            for (d, ell) in c.iter().enumerate() {
                let v = if d < 3 { ms.mass } else { ms.inertia[d - 3] };
                super::finish::check_non_negative(format!("{field}.{}", DOF_NAMES[d]), v)?;
                scatter_rank_one(&mut self.mats[mass], ell, v);
            }
        }
        Ok(())
    }

    /// Adds each discrete spring `k ℓ ℓᵀ` (`ℓ` its DOF at `a` less that at `b`; an elastic
    /// support when `b` is absent) to K0 or its parameter's `K_l`.
    fn add_springs(&mut self) -> Result<(), ModelError> {
        let s = self.s;
        for (i, sp) in s.springs.iter().enumerate() {
            let field = format!("springs[{i}] `{}`", sp.name);
            super::finish::check_positive(format!("{field}.k"), sp.k)?;
            let d = dof_index(&format!("{field}.dof"), &sp.dof)?;
            let mut ell = self.locations.get(format!("{field}.a"), &sp.a)?[d].clone();
            if let Some(b) = &sp.b {
                add_scaled(
                    &mut ell,
                    &self.locations.get(format!("{field}.b"), b)?[d],
                    -1.0,
                );
            }
            if ell.is_empty() {
                return Err(invalid(field, "both ends are fixed"));
            }
            scatter_rank_one(
                &mut self.mats[slot_of(s, &sp.name, |q| &q.springs)],
                &ell,
                sp.k,
            );
        }
        Ok(())
    }

    /// The channels, each reading the combination of its location's DOF `dir`.
    fn channels(&self) -> Result<Vec<Channel>, ModelError> {
        self.s
            .channels
            .iter()
            .map(|ch| {
                let field = format!("channels.{}", ch.name);
                let c = dof_index(&format!("{field}.dir"), &ch.dir)?;
                let dofs = self.locations.get(format!("{field}.at"), &ch.at)?[c].clone();
                if dofs.is_empty() {
                    return Err(invalid(format!("{field}.at"), "reads only fixed DOFs"));
                }
                Ok(Channel {
                    name: ch.name.clone(),
                    dofs,
                })
            })
            .collect()
    }

    /// The DOF labels, and `K0, K_1 … K_p, M` as sparse matrices.
    fn into_matrices(self) -> (Vec<String>, Vec<Csc>) {
        let n = self.dofs.labels.len();
        let mats: Vec<Csc> = self
            .mats
            .into_iter()
            .map(|t| csc_from_triplets(n, t.into_iter()))
            .collect();
        (self.dofs.labels, mats)
    }
}

/// The updating parameters: each scales members' E, springs, or connection axes (by their
/// index in `connections`).
fn parameters_of(s: &SpaceFrameSpec, connections: &[Connection]) -> Vec<Parameter> {
    s.parameters
        .iter()
        .map(|q| Parameter {
            name: q.name.clone(),
            nominal: q.nominal.unwrap_or(1.0),
            lower: None,
            upper: None,
            kind: if !q.members.is_empty() {
                ParameterKind::Modulus(q.members.clone())
            } else if !q.springs.is_empty() {
                ParameterKind::Springs(q.springs.clone())
            } else {
                ParameterKind::Connections(
                    connections
                        .iter()
                        .enumerate()
                        .filter(|(_, c)| q.connections.contains(&c.name))
                        .map(|(i, _)| i)
                        .collect(),
                )
            },
        })
        .collect()
}
