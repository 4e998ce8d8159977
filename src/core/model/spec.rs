//! The model file: a TOML description of a plane frame (DESIGN §3.1), deserialized as written.
//! [`super::Model::from_spec`] checks it and assembles the matrices.
//!
//! ```toml
//! name = "lab-frame"
//! [[materials]] name = "steel", E = 2.1e11, rho = 7840.0
//! [[sections]]  name = "flat-50x11", A = 5.5e-4, I = 5.5458e-9
//! [[nodes]]     name = "J1L", x = 0.0, y = 0.5
//! [[joints]]    node = "J1L", mass = 1.86, inertia = 1.55e-3, size = 0.04
//! [[members]]   name = "C1L", from = "BL", to = "J1L", section = "flat-50x11",
//!               material = "steel", elements = 5
//! [[supports]]  node = "BL"                       # clamped; or fix = ["x", "y"]
//! [[connections]] member = "C1L", node = "J1L", k = 1e4   # name defaults to "C1L@J1L"
//! [[parameters]] name = "C1L@J1L", connections = ["C1L@J1L"]
//! [[parameters]] name = "E", members = ["C1L", "C2L"]     # scales E of those members
//! [[channels]]  name = "C1L.1", at = "C1L.1", dir = "x"
//! [bayesian]    sigma_c = 1e4, prior_std = 1000.0       # optional defaults for (14)
//! ```
//! Locations (`at`) are model nodes (`J1L`) or interior mesh nodes of a member, numbered
//! from the member's `from` end (`C2L.3`). Directions are global: `x`, `y`, `rz`.

use nalgebra::Vector3;
use serde::Deserialize;

use super::ModelError;
use super::frame3d::Section3;

/// A whole model file.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ModelSpec {
    /// The structure's name; modal sets name it in `structure`.
    pub name: String,
    #[serde(default)]
    pub description: String,
    #[serde(default)]
    pub materials: Vec<MaterialSpec>,
    #[serde(default)]
    pub sections: Vec<SectionSpec>,
    #[serde(default)]
    pub nodes: Vec<NodeSpec>,
    #[serde(default)]
    pub joints: Vec<JointSpec>,
    #[serde(default)]
    pub members: Vec<MemberSpec>,
    #[serde(default)]
    pub supports: Vec<SupportSpec>,
    #[serde(default)]
    pub connections: Vec<ConnectionSpec>,
    #[serde(default)]
    pub masses: Vec<MassSpec>,
    #[serde(default)]
    pub springs: Vec<SpringSpec>,
    #[serde(default)]
    pub parameters: Vec<ParameterSpec>,
    #[serde(default)]
    pub channels: Vec<ChannelSpec>,
    /// A solid (20-node hexahedra) multi-bay frame generated from a few dimensions, instead
    /// of the frame entries above (DESIGN §4.3).
    #[serde(default)]
    pub solid_frame: Option<SolidFrameSpec>,
    /// A space frame (six DOF per node), instead of the plane-frame entries above
    /// (issue 25, [`super::space`]).
    #[serde(default)]
    pub space_frame: Option<SpaceFrameSpec>,
    /// Defaults of the Bayesian MAP (14) for this model; command-line flags override them.
    #[serde(default)]
    pub bayesian: BayesSpec,
}

/// `[bayesian] sigma_c = 1e4, prior_std = 1000.0`: σ_c and the prior standard deviation of
/// every θ_l (`Σ_θ = diag(prior_std²)`), both optional.
#[derive(Debug, Clone, Default, PartialEq, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct BayesSpec {
    pub sigma_c: Option<f64>,
    pub prior_std: Option<f64>,
}

#[allow(non_snake_case)]
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MaterialSpec {
    pub name: String,
    /// Young's modulus, Pa.
    pub E: f64,
    /// Density, kg/m³.
    pub rho: f64,
}

#[allow(non_snake_case)]
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SectionSpec {
    pub name: String,
    /// Area, m².
    pub A: f64,
    /// Second moment of area about the bending axis, m⁴.
    pub I: f64,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NodeSpec {
    pub name: String,
    pub x: f64,
    pub y: f64,
}

/// A rigid body centred on a node (3 DOF at the centre). Member ends at its node stop
/// `size` short of the centre along the member axis; their translations follow the body
/// (primal assembly with a non-Boolean L, paper (3)–(4)).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct JointSpec {
    pub node: String,
    /// kg
    #[serde(default)]
    pub mass: f64,
    /// Rotary inertia about z, kg·m².
    #[serde(default)]
    pub inertia: f64,
    /// Distance from the centre at which member ends stop, m.
    #[serde(default)]
    pub size: f64,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MemberSpec {
    pub name: String,
    pub from: String,
    pub to: String,
    pub section: String,
    pub material: String,
    /// Number of frame elements along the member.
    pub elements: usize,
    /// Axial force (N, tension positive): its geometric stiffness enters K0 (not scaled by
    /// any parameter).
    #[serde(default)]
    pub axial_force: f64,
}

/// Fixed DOFs of a node; all three (clamped) when `fix` is absent.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SupportSpec {
    pub node: String,
    pub fix: Option<Vec<String>>,
}

/// A bolted connection: the rotation of `member`'s end at `node` becomes its own DOF, tied
/// to the node's rotation by a rotational spring `k` (N·m/rad), paper (2).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ConnectionSpec {
    pub name: Option<String>,
    pub member: String,
    pub node: String,
    pub k: f64,
}

/// A lumped mass (kg, on x and y) and rotary inertia (kg·m², on rz) at a location.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MassSpec {
    pub at: String,
    #[serde(default)]
    pub mass: f64,
    #[serde(default)]
    pub inertia: f64,
}

/// A discrete spring along one global DOF direction between locations `a` and `b`, or from
/// `a` to the ground when `b` is absent. Stiffness in N/m (translations) or N·m/rad
/// (rotations).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SpringSpec {
    pub name: String,
    pub a: String,
    pub b: Option<String>,
    pub dof: String,
    pub k: f64,
}

/// An updating parameter θ_l: a group of connections, springs, or a scale of E of a set of
/// members. Exactly one of the lists is non-empty.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ParameterSpec {
    pub name: String,
    #[serde(default)]
    pub connections: Vec<String>,
    #[serde(default)]
    pub members: Vec<String>,
    #[serde(default)]
    pub springs: Vec<String>,
    /// Nominal (starting) value; 1 when absent.
    pub nominal: Option<f64>,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ChannelSpec {
    pub name: String,
    pub at: String,
    pub dir: String,
}

/// `[solid_frame]` in a model file.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SolidFrameSpec {
    /// Bays per chord (≥ 2).
    pub bays: usize,
    pub beam: BeamSpec,
    pub coupler: CouplerSpec,
    pub material: SolidMaterialSpec,
    /// `k = factor · 4EI/L` of the connection springs (50 in the paper).
    pub spring_factor: f64,
}

/// A beam: `length` (m) along its axis, `in_plane` (m) across it in the frame plane (the
/// depth of in-plane bending), `out_of_plane` (m) through the plane; `divisions` = elements
/// along the length, `in_plane` and `out_of_plane`.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BeamSpec {
    pub length: f64,
    pub in_plane: f64,
    pub out_of_plane: f64,
    pub divisions: [usize; 3],
}

/// A coupler: a square block of side `size` (m) in the frame plane and the beams'
/// `out_of_plane` size through it, with `divisions` elements along each in-plane side (and
/// the beams' through the plane).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CouplerSpec {
    pub size: f64,
    pub divisions: usize,
}

#[allow(non_snake_case)]
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SolidMaterialSpec {
    pub E: f64,
    pub nu: f64,
    pub rho: f64,
}

/// The parameter names, in order.
pub const PARAMETERS: [&str; 4] = ["ip-left", "ip-right", "ip-vertical", "op"];

impl ModelSpec {
    /// A `[solid_frame]` model generates its own structure: no frame entries beside it.
    pub(super) fn check_no_frame_entries(&self) -> Result<(), ModelError> {
        let frame_entries = [
            ("materials", self.materials.len()),
            ("sections", self.sections.len()),
            ("nodes", self.nodes.len()),
            ("joints", self.joints.len()),
            ("members", self.members.len()),
            ("supports", self.supports.len()),
            ("connections", self.connections.len()),
            ("masses", self.masses.len()),
            ("springs", self.springs.len()),
            ("parameters", self.parameters.len()),
            ("channels", self.channels.len()),
        ];
        if let Some((key, _)) = frame_entries.iter().find(|(_, n)| *n > 0) {
            return Err(ModelError::Invalid {
                field: key.to_string(),
                reason:
                    "a [solid_frame] model generates its own structure; remove the frame entries"
                        .into(),
            });
        }
        Ok(())
    }
}

// Space frames (`[space_frame]`, assembled by [`super::space`]).

/// The local axes a connection spring can act about: x, y, z of the member.
pub const AXES: [&str; 3] = ["torsion", "weak", "strong"];

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
pub struct Joint3 {
    pub node: String,
    /// kg, on each translation.
    #[serde(default)]
    pub mass: f64,
    /// Rotary inertia about global x, y, z (kg·m²).
    #[serde(default)]
    pub inertia: [f64; 3],
    /// Member-end offset (m): member ends at this joint stop `size` short of its centre
    /// along their axes and move with it as a rigid body (u_end = u + ω × r).
    #[serde(default)]
    pub size: f64,
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
    /// Axial force (N, tension positive): its geometric stiffness enters K0.
    #[serde(default)]
    pub axial_force: f64,
}

/// A bolted member end: a rotational spring (N·m/rad) about each named local axis of the
/// member (`torsion` = x, `weak` = y, `strong` = z); the other axes are rigid. The axes are
/// named `<name>.<axis>`, `name` defaulting to `<member>@<node>`.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Connection3 {
    pub name: Option<String>,
    pub member: String,
    pub node: String,
    pub torsion: Option<f64>,
    pub weak: Option<f64>,
    pub strong: Option<f64>,
}

impl Connection3 {
    /// The connection's name, `<member>@<node>` unless given.
    pub fn name(&self) -> String {
        self.name
            .clone()
            .unwrap_or_else(|| format!("{}@{}", self.member, self.node))
    }

    /// The names of its sprung axes with their stiffness.
    pub fn axes(&self) -> impl Iterator<Item = (String, f64)> + '_ {
        let name = self.name();
        [self.torsion, self.weak, self.strong]
            .into_iter()
            .zip(AXES)
            .filter_map(move |(k, ax)| k.map(|k| (format!("{name}.{ax}"), k)))
    }
}

/// A lumped mass (kg, on the three translations) and rotary inertia (kg·m² about global x,
/// y, z) at a location: a node, or `<member>.<k>` (a mesh node, from the `from` end).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Mass3 {
    pub at: String,
    #[serde(default)]
    pub mass: f64,
    #[serde(default)]
    pub inertia: [f64; 3],
}

/// A spring of a space frame: the plane frame's [`SpringSpec`], whose `dof` may also be
/// `z`, `rx` or `ry` (an elastic support when `b` is absent).
pub type Spring3 = SpringSpec;

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
    /// DOFs fixed at every node and mesh node (`["z", "rx", "ry"]`: a frame braced out of
    /// its x–y plane, analysed in-plane).
    #[serde(default)]
    pub restrain: Vec<String>,
    #[serde(default)]
    pub connections: Vec<Connection3>,
    #[serde(default)]
    pub masses: Vec<Mass3>,
    #[serde(default)]
    pub springs: Vec<Spring3>,
    #[serde(default)]
    pub parameters: Vec<ParameterSpec>,
    #[serde(default)]
    pub channels: Vec<ChannelSpec>,
}

impl SpaceFrameSpec {
    /// The position of a node.
    pub fn position(&self, node: &str) -> Option<Vector3<f64>> {
        self.nodes
            .iter()
            .find(|n| n.name == node)
            .map(|n| Vector3::new(n.x, n.y, n.z))
    }

    /// The section properties of a member, from its material and section entries.
    pub fn section_of(&self, m: &Member3) -> Result<Section3, ModelError> {
        fn find<'a, T>(
            list: &'a [T],
            name: &str,
            field: &str,
            what: &'static str,
            key: impl Fn(&T) -> &str,
        ) -> Result<&'a T, ModelError> {
            list.iter()
                .find(|x| key(x) == name)
                .ok_or_else(|| ModelError::Unknown {
                    field: field.to_string(),
                    what,
                    name: name.to_string(),
                })
        }
        let field = format!("members.{}", m.name);
        let mat = find(&self.materials, &m.material, &field, "material", |x| {
            &x.name
        })?;
        let sec = find(&self.sections, &m.section, &field, "section", |x| &x.name)?;
        Ok(Section3 {
            E: mat.E,
            G: mat.E / (2.0 * (1.0 + mat.nu)),
            rho: mat.rho,
            A: sec.A,
            Iy: sec.Iy,
            Iz: sec.Iz,
            J: sec.J,
            Jp: sec.Jp.unwrap_or(sec.Iy + sec.Iz),
        })
    }

    /// The joint-centre offset of member ends at `node` (m).
    pub fn joint_size(&self, node: &str) -> f64 {
        self.joints
            .iter()
            .find(|j| j.node == node)
            .map_or(0.0, |j| j.size)
    }

    /// Every connection axis name with its stiffness, in file order.
    pub fn connection_axes(&self) -> Vec<(String, f64)> {
        self.connections
            .iter()
            .flat_map(Connection3::axes)
            .collect()
    }
}
