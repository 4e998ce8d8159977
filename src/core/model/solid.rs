//! The multi-bay solid frame (paper §5, DESIGN §4.3): flat steel beams and couplers in the
//! x–z plane meshed with 20-node hexahedra ([`super::hex20`]), joined at rigid interfaces.
//!
//! Layout (x along the chords, z up, y out of the plane): a bottom chord at `z = 0` and
//! a top chord at `z = H`, each `bays` beams long (support → coupler → … → support); the
//! `bays − 1` bottom couplers are joined to the top ones by vertical beams, so
//! `H = beam length + coupler size`. The four chord ends are clamped (their end faces' nodes
//! are fixed).
//!
//! **Rigid interfaces.** Every beam end at a coupler, and the part of the coupler face it
//! meets (the beam's cross-section), is a rigid interface: its nodes follow a 6-DOF master at the
//! face centre `c` by the linearized rigid-body motion `u = u_m + ω × (x − c)`, entered in
//! the primal assembly as non-Boolean rows of `L` (paper (3)–(4)), as the lab frame's member
//! ends follow its joints. The two masters of a connection share the three translations and
//! the rotation about the beam axis; the two bending rotations of each side are their own
//! DOFs, tied by rotational springs `θ_j k_IP` (in-plane: about y) and `θ4 k_OP`
//! (out-of-plane), `k = factor · 4EI/L` of the beam about that axis (the moment that turns
//! a beam end clamped at the other end by a unit angle), `factor` = 50 in the paper.
//!
//! **Parameters**, in this order: `ip-left`, `ip-right`, `ip-vertical` (the in-plane
//! springs of every coupler's left, right and vertical connection) and `op` (every
//! out-of-plane spring).
//!
//! **Orientation.** DESIGN §4.3 puts the beams' 80 mm in the frame plane; here the 8 mm is
//! (`in_plane = 0.008`, `out_of_plane = 0.08` in `four-bay-solid.toml`). The frame is
//! symmetric about its mid-plane, so in-plane and out-of-plane modes decouple exactly and
//! the in-plane springs θ1–θ3 act on in-plane modes only. With 80 mm in the plane, the 11
//! lowest modes are all out-of-plane: the six modes would carry no information on
//! θ1–θ3 (measured: mode matching drifts them to 1e9 with a singular Hessian). The paper
//! identifies θ1–θ3 from six modes and shares θ4 because the out-of-plane connections
//! "would require high-frequency modes": its in-plane direction is the flexible one, as in
//! the lab frame (flat bars 50 × 11 mm, 11 mm in the plane).
//!
//! **Channels.** At the mesh node nearest to 1/3 and 2/3 of each beam's length on the beam's
//! axis (the middle of its width, paper §5), three translations: `<beam>.<1|2>.<x|y|z>`.
//! Beams are `B1…` (bottom chord, left to right), `T1…` (top chord) and `V1…` (verticals);
//! couplers `KB1…` and `KT1…`.

use super::hex20::Material;
use super::mesh::BoxMesh;
pub use super::solid_element::solid_cantilever;
use super::solid_element::{Combos, Part, element_matrices};
use super::sparse::Accumulator;
use super::spec::{PARAMETERS, SolidFrameSpec};
use super::{Channel, Connection, Model, ModelError, Parameter, ParameterKind};

/// A [`ModelError::Invalid`] naming `field`.
fn invalid(field: &str, reason: impl Into<String>) -> ModelError {
    ModelError::Invalid {
        field: field.to_string(),
        reason: reason.into(),
    }
}

/// The axis (0 = x, 2 = z) along which a beam runs.
fn beam_axis(name: &str) -> usize {
    if name.starts_with('V') { 2 } else { 0 }
}

/// Checks a `[solid_frame]` and assembles it: the parts, the rigid interfaces (clamped
/// ends; elsewhere the masters' DOFs, the slaved nodes and the connections' springs, paper
/// (2)), every other node's own translations, `K0` and `M` of the elements through `L`
/// (paper (3)–(4)), the springs' `K_l`, the channels and the parameters.
pub(super) fn assemble(
    name: &str,
    sf: &SolidFrameSpec,
    bayesian: &super::spec::BayesSpec,
) -> Result<Model, ModelError> {
    let Layout {
        parts,
        labels,
        combos,
        joints,
        mat,
    } = lay_out(sf)?;
    let n_dof = labels.len();

    let couplings: Vec<(usize, usize)> =
        joints.springs.iter().map(|&(a, b, _, _)| (a, b)).collect();
    let (k0, mass) = element_matrices(&parts, &combos, &mat, n_dof, &couplings)?;
    let k_params = spring_matrices(&joints.springs);
    let channels = sensor_channels(&parts, &combos)?;
    let parameters = connection_parameters(&joints.conn_of_param);
    // K0 and M are mirrored by `element_matrices`; the springs' few entries here.
    let mut mats = vec![k0];
    mats.extend(
        k_params
            .iter()
            .map(|a| super::finish::symmetric_from_lower(a.build(n_dof))),
    );
    mats.push(mass);
    super::finish::finish_symmetric(
        name,
        labels,
        mats,
        parameters,
        joints.connections,
        channels,
        bayesian.clone(),
    )
    .inspect(|m| debug_assert_eq!(m.n_dof(), n_dof))
}

/// A checked `[solid_frame]` laid out: its parts, its DOFs (labels, and where every mesh
/// node's translations go), the joints' springs and connections, and the material.
struct Layout {
    parts: Vec<Part>,
    labels: Vec<String>,
    combos: Vec<Combos>,
    joints: Joints,
    mat: Material,
}

/// Checks a `[solid_frame]`, lays out its parts and joins them at the interfaces.
fn lay_out(sf: &SolidFrameSpec) -> Result<Layout, ModelError> {
    validate(sf)?;
    let parts = lay_out_parts(sf);
    let interfaces = interfaces_of(&parts, sf.bays);
    let mat = Material {
        e: sf.material.E,
        nu: sf.material.nu,
        rho: sf.material.rho,
    };
    let fm = FaceMatch {
        w: sf.beam.in_plane,
        tol: 1e-9 * (sf.beam.length + sf.coupler.size),
    };
    let mut dofs = Dofs::new(&parts);
    let mut joints = Joints::new(sf, &mat);
    for at in &interfaces {
        join(&parts, at, fm, &mut dofs, &mut joints)?;
    }
    dofs.own_translations(&parts);
    let (labels, combos) = dofs.finish();
    Ok(Layout {
        parts,
        labels,
        combos,
        joints,
        mat,
    })
}

/// Checks the sizes, the material and the meshes' divisions of a `[solid_frame]`.
fn validate(sf: &SolidFrameSpec) -> Result<(), ModelError> {
    if sf.bays < 2 {
        return Err(invalid(
            "solid_frame.bays",
            format!("must be at least 2, got {}", sf.bays),
        ));
    }
    let b = &sf.beam;
    for (f, v) in [
        ("solid_frame.beam.length", b.length),
        ("solid_frame.beam.in_plane", b.in_plane),
        ("solid_frame.beam.out_of_plane", b.out_of_plane),
        ("solid_frame.coupler.size", sf.coupler.size),
        ("solid_frame.material.E", sf.material.E),
        ("solid_frame.material.rho", sf.material.rho),
        ("solid_frame.spring_factor", sf.spring_factor),
    ] {
        super::finish::check_positive(f.to_string(), v)?;
    }
    if !(sf.material.nu > -1.0 && sf.material.nu < 0.5) {
        return Err(invalid(
            "solid_frame.material.nu",
            format!("must lie in (−1, 0.5), got {}", sf.material.nu),
        ));
    }
    if b.divisions.contains(&0) || sf.coupler.divisions == 0 {
        return Err(invalid(
            "solid_frame",
            "every `divisions` entry must be ≥ 1",
        ));
    }
    if sf.coupler.size < b.in_plane {
        return Err(invalid(
            "solid_frame.coupler.size",
            format!("must be at least the beam width {} m", b.in_plane),
        ));
    }
    // The interface on a coupler face is the beam's width about the face centre; it must
    // be made of whole mesh lines so that it matches nodes.
    let step = sf.coupler.size / (2 * sf.coupler.divisions) as f64;
    let margin = 0.5 * (sf.coupler.size - b.in_plane) / step;
    if (margin - margin.round()).abs() > 1e-9 {
        return Err(invalid(
            "solid_frame.coupler.divisions",
            "the beam width must start and end on the coupler's mesh lines (its half-element \
             grid)",
        ));
    }
    Ok(())
}

/// The parts, meshed, in a fixed order: bottom chord, top chord, verticals, then couplers;
/// each part's nodes numbered after the previous part's.
fn lay_out_parts(sf: &SolidFrameSpec) -> Vec<Part> {
    let b = &sf.beam;
    let (l, w, t, c) = (b.length, b.in_plane, b.out_of_plane, sf.coupler.size);
    let height = l + c;
    let pitch = l + c;
    let n_couplers = sf.bays - 1;

    let mut parts: Vec<Part> = Vec::new();
    let mut push = |name: String, origin: [f64; 3], size: [f64; 3], div: [usize; 3]| {
        let first = parts
            .last()
            .map_or(0, |p: &Part| p.first + p.mesh.nodes.len());
        parts.push(Part {
            name,
            mesh: BoxMesh::new(origin, size, div),
            first,
        });
    };
    let chord_div = [b.divisions[0], b.divisions[2], b.divisions[1]];
    let vert_div = [b.divisions[1], b.divisions[2], b.divisions[0]];
    for (prefix, z0) in [("B", 0.0), ("T", height)] {
        for i in 0..sf.bays {
            push(
                format!("{prefix}{}", i + 1),
                [i as f64 * pitch, -0.5 * t, z0 - 0.5 * w],
                [l, t, w],
                chord_div,
            );
        }
    }
    for i in 0..n_couplers {
        let xc = (i + 1) as f64 * pitch - 0.5 * c;
        push(
            format!("V{}", i + 1),
            [xc - 0.5 * w, -0.5 * t, 0.5 * c],
            [w, t, l],
            vert_div,
        );
    }
    let cd = sf.coupler.divisions;
    for (prefix, z0) in [("KB", 0.0), ("KT", height)] {
        for i in 0..n_couplers {
            let xc = (i + 1) as f64 * pitch - 0.5 * c;
            push(
                format!("{prefix}{}", i + 1),
                [xc - 0.5 * c, -0.5 * t, z0 - 0.5 * c],
                [c, t, c],
                [cd, b.divisions[2], cd],
            );
        }
    }
    parts
}

/// A beam end: the beam's part, its end (0 at the start of its axis, 1 at the end) and the
/// coupler it meets (`None`: a clamped end).
struct Interface {
    beam: usize,
    end: usize,
    coupler: Option<usize>,
}

/// The interfaces, in order: both ends of every chord beam (bottom chord, then top, left
/// to right), then of every vertical (bottom, then top).
fn interfaces_of(parts: &[Part], bays: usize) -> Vec<Interface> {
    let n_couplers = bays - 1;
    let part_index = |name: &str| {
        parts
            .iter()
            .position(|p| p.name == name)
            .expect("part exists")
    };
    let mut interfaces: Vec<Interface> = Vec::new();
    let mut push = |beam: usize, end: usize, coupler: Option<usize>| {
        interfaces.push(Interface { beam, end, coupler });
    };
    for prefix in ["B", "T"] {
        let kp = if prefix == "B" { "KB" } else { "KT" };
        for i in 0..bays {
            let beam = part_index(&format!("{prefix}{}", i + 1));
            let left = (i > 0).then(|| part_index(&format!("{kp}{i}")));
            let right = (i + 1 < bays).then(|| part_index(&format!("{kp}{}", i + 1)));
            push(beam, 0, left);
            push(beam, 1, right);
        }
    }
    for i in 0..n_couplers {
        let beam = part_index(&format!("V{}", i + 1));
        push(beam, 0, Some(part_index(&format!("KB{}", i + 1))));
        push(beam, 1, Some(part_index(&format!("KT{}", i + 1))));
    }
    interfaces
}

/// How an interface finds its coupler's nodes: the beam width `w` it spans across the
/// coupler face, and the tolerance `tol` of a coordinate match.
#[derive(Clone, Copy)]
struct FaceMatch {
    w: f64,
    tol: f64,
}

/// The unique DOFs as they are created (their labels, in order), and where every mesh
/// node's translations go: `None` until the node is placed (fixed, slaved to a master, or
/// given its own translations).
struct Dofs {
    labels: Vec<String>,
    combos: Vec<Option<Combos>>,
}

impl Dofs {
    /// No DOF yet, and every node of `parts` unplaced.
    fn new(parts: &[Part]) -> Self {
        let n_nodes = parts.last().map_or(0, |p| p.first + p.mesh.nodes.len());
        Self {
            labels: Vec::new(),
            combos: vec![None; n_nodes],
        }
    }

    /// A new unique DOF: its index.
    fn new_dof(&mut self, label: String) -> usize {
        self.labels.push(label);
        self.labels.len() - 1
    }

    /// The two masters of connection `cname` between the parts `sides` (beam, coupler),
    /// their beam running along `axis`: the shared DOFs (the translations and the rotation
    /// about the beam axis), then each side's own bending rotations, about y (in plane) and
    /// about the other in-plane axis (out of plane).
    fn masters(&mut self, cname: &str, sides: [&str; 2], axis: usize) -> ([usize; 4], [Master; 2]) {
        let shared: [usize; 4] = [
            self.new_dof(format!("{cname}.ux")),
            self.new_dof(format!("{cname}.uy")),
            self.new_dof(format!("{cname}.uz")),
            self.new_dof(format!("{cname}.r{}", ["x", "y", "z"][axis])),
        ];
        let op_axis = 2 - axis; // the other in-plane axis (x ↔ z)
        let masters = sides.map(|side| {
            let ry = self.new_dof(format!("{cname}.{side}.ry"));
            let rop = self.new_dof(format!("{cname}.{side}.r{}", ["x", "y", "z"][op_axis]));
            let mut rot = [0; 3];
            rot[axis] = shared[3];
            rot[1] = ry;
            rot[op_axis] = rop;
            Master { rot, ry, rop }
        });
        (shared, masters)
    }

    /// Gives every node not yet placed its own three translations.
    fn own_translations(&mut self, parts: &[Part]) {
        let Self { labels, combos } = self;
        for p in parts {
            for n in 0..p.mesh.nodes.len() {
                let slot = &mut combos[p.first + n];
                if slot.is_none() {
                    *slot = Some(std::array::from_fn(|r| {
                        labels.push(format!("{}.n{n}.{}", p.name, ["x", "y", "z"][r]));
                        vec![(labels.len() - 1, 1.0)]
                    }));
                }
            }
        }
    }

    /// The DOF labels and every node's combinations, once every node is placed.
    fn finish(self) -> (Vec<String>, Vec<Combos>) {
        let combos = self
            .combos
            .into_iter()
            .map(|c| c.expect("every node placed"))
            .collect();
        (self.labels, combos)
    }
}

/// One side's master at a connection: its rotation DOFs by axis, and among them its own
/// bending rotations about y (`ry`, in plane) and out of the plane (`rop`).
#[derive(Clone, Copy)]
struct Master {
    rot: [usize; 3],
    ry: usize,
    rop: usize,
}

/// Joins a beam end: clamps its end face, or slaves that face and the part of the coupler
/// face it meets to the connection's two masters at the face centre (paper (3)–(4)) and
/// ties the masters' bending rotations by the connection's springs (paper (2)).
fn join(
    parts: &[Part],
    at: &Interface,
    fm: FaceMatch,
    dofs: &mut Dofs,
    joints: &mut Joints,
) -> Result<(), ModelError> {
    let bp = &parts[at.beam];
    let axis = beam_axis(&bp.name);
    let (beam_face, centre) = beam_end(&bp.mesh, axis, at.end);
    let Some(coupler) = at.coupler else {
        for &n in &beam_face {
            dofs.combos[bp.first + n] = Some(Default::default());
        }
        return Ok(());
    };
    let cp = &parts[coupler];
    let cname = format!("{}@{}", bp.name, cp.name);
    let coupler_face = coupler_face_at(&cp.mesh, axis, centre, fm);
    let (shared, masters) = dofs.masters(&cname, [bp.name.as_str(), cp.name.as_str()], axis);
    for (side, (part, face)) in [(bp, &beam_face), (cp, &coupler_face)]
        .into_iter()
        .enumerate()
    {
        let slave = Slave {
            centre,
            shared,
            rot: masters[side].rot,
        };
        slave.face(part, face, &mut dofs.combos)?;
    }
    // θ1 the coupler's left connection (a chord beam ending at it), θ2 its right one
    // (a chord beam starting at it), θ3 its vertical one.
    let ip_param = match (axis, at.end) {
        (2, _) => 2,
        (_, 1) => 0,
        _ => 1,
    };
    joints.connect(&cname, bp, cp, ip_param, masters);
    Ok(())
}

/// A beam's end face `end` (its nodes) and the face's centre.
fn beam_end(bm: &BoxMesh, axis: usize, end: usize) -> (Vec<usize>, [f64; 3]) {
    let along = if end == 0 { 0 } else { 2 * bm.div[axis] };
    let beam_face: Vec<usize> = (0..bm.nodes.len())
        .filter(|&n| bm.nodes[n][axis] == along)
        .collect();
    let centre: [f64; 3] = std::array::from_fn(|r| {
        let at = match (r == axis, end) {
            (true, 0) => 0.0,
            (true, _) => 1.0,
            (false, _) => 0.5,
        };
        bm.origin[r] + at * bm.size[r]
    });
    (beam_face, centre)
}

/// The coupler face a beam end (along `axis`, centred at `centre`) meets, restricted to the
/// beam's width.
fn coupler_face_at(cm: &BoxMesh, axis: usize, centre: [f64; 3], fm: FaceMatch) -> Vec<usize> {
    let (w, tol) = (fm.w, fm.tol);
    let across = 2 - axis; // the other in-plane axis (x ↔ z)
    (0..cm.nodes.len())
        .filter(|&n| {
            let x = cm.coord(n);
            (x[axis] - centre[axis]).abs() < tol
                && (x[across] - centre[across]).abs() <= 0.5 * w + tol
        })
        .collect()
}

/// A master a face is slaved to: at `centre`, translations `shared[0..3]`, rotations `rot`.
struct Slave {
    centre: [f64; 3],
    shared: [usize; 4],
    rot: [usize; 3],
}

impl Slave {
    /// Slaves the nodes `face` of `part` by the linearized rigid-body motion
    /// `u = u_m + ω × (x − c)`: non-Boolean rows of `L` (paper (3)–(4)). A node already
    /// placed belongs to two interfaces: an error.
    fn face(
        &self,
        part: &Part,
        face: &[usize],
        combos: &mut [Option<Combos>],
    ) -> Result<(), ModelError> {
        let (centre, shared, rot) = (self.centre, self.shared, self.rot);
        for &n in face {
            let x = part.mesh.coord(n);
            let r = [x[0] - centre[0], x[1] - centre[1], x[2] - centre[2]];
            // u = u_m + ω × r: (ω_y r_z − ω_z r_y, ω_z r_x − ω_x r_z, ω_x r_y − ω_y r_x).
            let comb: Combos = [
                vec![(shared[0], 1.0), (rot[1], r[2]), (rot[2], -r[1])],
                vec![(shared[1], 1.0), (rot[2], r[0]), (rot[0], -r[2])],
                vec![(shared[2], 1.0), (rot[0], r[1]), (rot[1], -r[0])],
            ];
            let slot = &mut combos[part.first + n];
            if slot.is_some() {
                return Err(invalid(
                    "solid_frame",
                    format!("a node of {} belongs to two interfaces", part.name),
                ));
            }
            *slot = Some(comb.map(|v| v.into_iter().filter(|&(_, c)| c != 0.0).collect()));
        }
        Ok(())
    }
}

/// A connection spring: `(dof a, dof b, parameter, k)`.
type Spring = (usize, usize, usize, f64);

/// The bolted connections as the interfaces create them: their rotational springs (paper
/// (2)), the connections, and the connections each parameter scales.
struct Joints {
    /// `factor · 4EI/L` about the in-plane bending axis (y: I = t w³/12).
    k_ip: f64,
    /// `factor · 4EI/L` about the out-of-plane one (I = w t³/12).
    k_op: f64,
    springs: Vec<Spring>,
    connections: Vec<Connection>,
    conn_of_param: [Vec<usize>; 4],
}

impl Joints {
    /// No connection yet, and the spring constants of `sf`'s beams.
    fn new(sf: &SolidFrameSpec, mat: &Material) -> Self {
        let (l, w, t) = (sf.beam.length, sf.beam.in_plane, sf.beam.out_of_plane);
        Self {
            k_ip: sf.spring_factor * 4.0 * mat.e * t * w.powi(3) / 12.0 / l,
            k_op: sf.spring_factor * 4.0 * mat.e * w * t.powi(3) / 12.0 / l,
            springs: Vec::new(),
            connections: Vec::new(),
            conn_of_param: Default::default(),
        }
    }

    /// Connection `cname` of `beam` to `coupler`: a spring `θ_{ip_param} k_IP` between the
    /// masters' in-plane bending rotations and one `θ4 k_OP` between their out-of-plane
    /// ones, paper (2).
    fn connect(
        &mut self,
        cname: &str,
        beam: &Part,
        coupler: &Part,
        ip_param: usize,
        masters: [Master; 2],
    ) {
        for (dofs, param, k) in [
            ((masters[0].ry, masters[1].ry), ip_param, self.k_ip),
            ((masters[0].rop, masters[1].rop), 3, self.k_op),
        ] {
            self.springs.push((dofs.0, dofs.1, param, k));
            let suffix = if param == 3 { "op" } else { "ip" };
            self.conn_of_param[param].push(self.connections.len());
            self.connections.push(Connection {
                name: format!("{cname}.{suffix}"),
                member: beam.name.clone(),
                node: coupler.name.clone(),
                k,
                parameter: Some(param),
            });
        }
    }
}

/// `K_l`, paper (2): each spring `k` between DOFs `a` and `b` adds `k [[1, −1], [−1, 1]]`
/// on them to its parameter's matrix.
fn spring_matrices(springs: &[Spring]) -> Vec<Accumulator> {
    let mut k_params: Vec<Accumulator> = vec![Accumulator::default(); PARAMETERS.len()];
    for &(a, b2, param, k) in springs {
        k_params[param].add_mapped(&[[k, -k], [-k, k]], &[&[(a, 1.0)], &[(b2, 1.0)]]);
    }
    k_params
}

/// The channels (rows of `D`, paper (7)): at the mesh node nearest to 1/3 and 2/3 of each
/// beam's length on its axis (the middle of its width and of its thickness; ties go to the
/// lower node number), the three translations. A fixed sensor node is an error.
fn sensor_channels(parts: &[Part], combos: &[Combos]) -> Result<Vec<Channel>, ModelError> {
    let stations = |_: &Part| vec![1.0 / 3.0, 2.0 / 3.0];
    let mut channels = Vec::new();
    for (p, k, frac) in beam_stations(parts, stations) {
        let name = |d: &str| format!("{}.{}.{d}", p.name, k + 1);
        let Some(at) = translations_at(p, combos, frac, name) else {
            return Err(invalid(
                "solid_frame",
                format!("sensor {}.{} is fixed", p.name, k + 1),
            ));
        };
        channels.extend(at);
    }
    Ok(channels)
}

/// Where a sensor could go on a `[solid_frame]`: the three translations on each beam's
/// axis at every sixth of its length (`every_node` false) or at every element corner
/// between its ends, named `<beam>@<fraction of its length>.<x|y|z>`; a place the model's
/// own channels read already is left out.
pub fn candidate_channels(
    sf: &SolidFrameSpec,
    every_node: bool,
) -> Result<Vec<Channel>, ModelError> {
    let Layout { parts, combos, .. } = lay_out(sf)?;
    let own = sensor_channels(&parts, &combos)?;
    let stations = |p: &Part| {
        let n = if every_node {
            p.mesh.div[beam_axis(&p.name)]
        } else {
            6
        };
        (1..n).map(|i| i as f64 / n as f64).collect()
    };
    let mut channels: Vec<Channel> = Vec::new();
    for (p, _, frac) in beam_stations(&parts, stations) {
        let name = |d: &str| format!("{}@{frac:.3}.{d}", p.name);
        for c in translations_at(p, &combos, frac, name).unwrap_or_default() {
            let read = |o: &Channel| o.dofs == c.dofs;
            if !own.iter().any(read) && !channels.iter().any(read) {
                channels.push(c);
            }
        }
    }
    Ok(channels)
}

/// Every beam's stations: the beam, the station's number and its fraction of the length.
fn beam_stations<'a>(
    parts: &'a [Part],
    stations: impl Fn(&Part) -> Vec<f64> + 'a,
) -> impl Iterator<Item = (&'a Part, usize, f64)> + 'a {
    parts
        .iter()
        .filter(|p| !p.name.starts_with('K'))
        .flat_map(move |p| {
            stations(p)
                .into_iter()
                .enumerate()
                .map(move |(k, f)| (p, k, f))
        })
}

/// The three translations of beam `p` at the mesh node nearest to `frac` of its length on
/// its axis, named by `name(direction)`; `None` when that node is fixed.
fn translations_at(
    p: &Part,
    combos: &[Combos],
    frac: f64,
    name: impl Fn(&str) -> String,
) -> Option<Vec<Channel>> {
    let axis = beam_axis(&p.name);
    let m = &p.mesh;
    let target: [f64; 3] =
        std::array::from_fn(|r| m.origin[r] + if r == axis { frac } else { 0.5 } * m.size[r]);
    let dist = |n: usize| {
        let x = m.coord(n);
        (0..3).map(|r| (x[r] - target[r]).powi(2)).sum::<f64>()
    };
    let n = (0..m.nodes.len())
        .min_by(|&a, &b| dist(a).total_cmp(&dist(b)))
        .expect("a mesh has nodes");
    ["x", "y", "z"]
        .iter()
        .enumerate()
        .map(|(r, d)| {
            let dofs = combos[p.first + n][r].clone();
            (!dofs.is_empty()).then(|| Channel {
                name: name(d),
                dofs,
            })
        })
        .collect()
}

/// The parameters [`PARAMETERS`], nominal 1, each scaling its connections.
fn connection_parameters(conn_of_param: &[Vec<usize>; 4]) -> Vec<Parameter> {
    PARAMETERS
        .iter()
        .enumerate()
        .map(|(l, name)| Parameter {
            name: (*name).to_string(),
            nominal: 1.0,
            lower: None,
            upper: None,
            kind: ParameterKind::Connections(conn_of_param[l].clone()),
        })
        .collect()
}
