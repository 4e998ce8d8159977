//! The checks of a plane-frame [`ModelSpec`] before assembly, in the order they run: unique
//! names and valid values, supports, joints, parameters (what each scales) and the bolted
//! connections at member ends; and the name lookups the assembly shares with them.

use std::collections::HashMap;

use super::finish::{check_non_negative, check_positive};
use super::spec::ModelSpec;
use super::{ModelError, Parameter, ParameterKind};

/// An invalid value of `field`, for `reason`.
pub(super) fn invalid(field: impl Into<String>, reason: impl Into<String>) -> ModelError {
    ModelError::Invalid {
        field: field.into(),
        reason: reason.into(),
    }
}

/// An unknown `what` named `name`, referenced in `field`.
pub(super) fn unknown(field: impl Into<String>, what: &'static str, name: &str) -> ModelError {
    ModelError::Unknown {
        field: field.into(),
        what,
        name: name.to_string(),
    }
}

/// The index of each name, in order; fails on a name given twice.
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

/// The index of a plane-frame DOF (`x`, `y`, `rz`).
pub(super) fn dir_index(d: &str) -> Option<usize> {
    match d {
        "x" => Some(0),
        "y" => Some(1),
        "rz" => Some(2),
        _ => None,
    }
}

/// The name → index maps the later steps look entries up in.
pub(super) struct Names<'a> {
    pub(super) nodes: HashMap<&'a str, usize>,
    members: HashMap<&'a str, usize>,
    pub(super) materials: HashMap<&'a str, usize>,
    pub(super) sections: HashMap<&'a str, usize>,
    springs: HashMap<&'a str, usize>,
}

/// Checks that the names of each kind of entry are unique, then the values
/// ([`check_values`]); returns the name maps.
pub(super) fn validate(spec: &ModelSpec) -> Result<Names<'_>, ModelError> {
    let nodes = index_names("node", spec.nodes.iter().map(|n| n.name.as_str()))?;
    let members = index_names("member", spec.members.iter().map(|m| m.name.as_str()))?;
    let materials = index_names("material", spec.materials.iter().map(|m| m.name.as_str()))?;
    let sections = index_names("section", spec.sections.iter().map(|s| s.name.as_str()))?;
    let springs = index_names("spring", spec.springs.iter().map(|s| s.name.as_str()))?;
    index_names("parameter", spec.parameters.iter().map(|p| p.name.as_str()))?;
    index_names("channel", spec.channels.iter().map(|c| c.name.as_str()))?;
    check_values(spec)?;
    Ok(Names {
        nodes,
        members,
        materials,
        sections,
        springs,
    })
}

/// Checks, in this order, `[bayesian]` (finite and > 0), the node coordinates (finite), the
/// materials (`E > 0`, `rho ≥ 0`) and the sections (`A > 0`, `I > 0`).
fn check_values(spec: &ModelSpec) -> Result<(), ModelError> {
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
    Ok(())
}

/// The fixed DOFs (x, y, rz) of each node, from the supports.
pub(super) fn supports(
    spec: &ModelSpec,
    nodes: &HashMap<&str, usize>,
) -> Result<Vec<[bool; 3]>, ModelError> {
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
    Ok(fixed)
}

/// The joint (a rigid body) at each node, if any; at most one per node, with its mass,
/// inertia and size checked.
pub(super) fn joints(
    spec: &ModelSpec,
    nodes: &HashMap<&str, usize>,
) -> Result<Vec<Option<usize>>, ModelError> {
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
    Ok(joint_of_node)
}

/// The parameter, if any, that scales each connection, member and spring.
pub(super) struct Claims {
    pub(super) conn: Vec<Option<usize>>,
    pub(super) member: Vec<Option<usize>>,
    pub(super) spring: Vec<Option<usize>>,
}

/// The updating parameters, and what each scales.
pub(super) struct Scaling {
    /// The connections' names (`<member>@<node>` when unnamed), in file order.
    pub(super) conn_names: Vec<String>,
    pub(super) claims: Claims,
    pub(super) parameters: Vec<Parameter>,
}

/// Names the connections and checks the parameters: each has exactly one non-empty list of
/// connections, members or springs, a nominal value > 0, and scales only items that no
/// earlier parameter scales.
pub(super) fn parameters(spec: &ModelSpec, names: &Names<'_>) -> Result<Scaling, ModelError> {
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
    let mut claims = Claims {
        conn: vec![None; spec.connections.len()],
        member: vec![None; spec.members.len()],
        spring: vec![None; spec.springs.len()],
    };
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
        let kind = parameter_kind(spec, l, &field, &conn_index, names, &mut claims)?;
        parameters.push(Parameter {
            name: p.name.clone(),
            nominal,
            lower: None,
            upper: None,
            kind,
        });
    }
    Ok(Scaling {
        conn_names,
        claims,
        parameters,
    })
}

/// What parameter `l` (reported as `field`) scales; claims each of its items for it, and
/// fails on an unknown item or one that another parameter claimed already.
fn parameter_kind(
    spec: &ModelSpec,
    l: usize,
    field: &str,
    conn_index: &HashMap<&str, usize>,
    names: &Names<'_>,
    claims: &mut Claims,
) -> Result<ParameterKind, ModelError> {
    let p = &spec.parameters[l];
    let claim = |slot: &mut Option<usize>, item: &str| -> Result<(), ModelError> {
        match slot.replace(l) {
            Some(other) => Err(invalid(
                field,
                format!(
                    "`{item}` is already scaled by parameter `{}`",
                    spec.parameters[other].name
                ),
            )),
            None => Ok(()),
        }
    };
    if !p.connections.is_empty() {
        let mut idx = Vec::new();
        for c in &p.connections {
            let ci = *conn_index
                .get(c.as_str())
                .ok_or_else(|| unknown(format!("{field}.connections"), "connection", c))?;
            claim(&mut claims.conn[ci], c)?;
            idx.push(ci);
        }
        Ok(ParameterKind::Connections(idx))
    } else if !p.members.is_empty() {
        for m in &p.members {
            let mi = *names
                .members
                .get(m.as_str())
                .ok_or_else(|| unknown(format!("{field}.members"), "member", m))?;
            claim(&mut claims.member[mi], m)?;
        }
        Ok(ParameterKind::Modulus(p.members.clone()))
    } else {
        for s in &p.springs {
            let si = *names
                .springs
                .get(s.as_str())
                .ok_or_else(|| unknown(format!("{field}.springs"), "spring", s))?;
            claim(&mut claims.spring[si], s)?;
        }
        Ok(ParameterKind::Springs(p.springs.clone()))
    }
}

/// The connection at each member end `(member, node)`. Checks each connection: its member
/// and node exist, the member ends at the node, `k > 0`, and no other is at that end.
pub(super) fn connections_by_end(
    spec: &ModelSpec,
    names: &Names<'_>,
    conn_names: &[String],
) -> Result<HashMap<(usize, usize), usize>, ModelError> {
    let mut conn_at: HashMap<(usize, usize), usize> = HashMap::new();
    for (i, c) in spec.connections.iter().enumerate() {
        let field = format!("connections[{i}] `{}`", conn_names[i]);
        let mi = *names
            .members
            .get(c.member.as_str())
            .ok_or_else(|| unknown(format!("{field}.member"), "member", &c.member))?;
        let n = *names
            .nodes
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
    Ok(conn_at)
}
