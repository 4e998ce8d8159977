//! The checks of a `[space_frame]` spec before assembly: unique names, the bolted
//! connections' member ends and springs, the parameters' references; the fixed DOFs
//! (`restrain`, supports); and the DOF and node name lookups the assembly shares with them.

use super::ModelError;
use super::spec::SpaceFrameSpec;

/// The DOF names of a node, in order.
pub const DOF_NAMES: [&str; 6] = ["x", "y", "z", "rx", "ry", "rz"];

/// An invalid value of `field`, for `reason`.
pub(super) fn invalid(field: impl Into<String>, reason: impl Into<String>) -> ModelError {
    ModelError::Invalid {
        field: field.into(),
        reason: reason.into(),
    }
}

/// The index of a DOF name (`x` … `rz`).
pub(super) fn dof_index(field: &str, d: &str) -> Result<usize, ModelError> {
    DOF_NAMES
        .iter()
        .position(|x| *x == d)
        .ok_or_else(|| invalid(field, format!("unknown DOF `{d}` (x, y, z, rx, ry, rz)")))
}

/// The index of node `n`.
pub(super) fn node_index(s: &SpaceFrameSpec, n: &str, field: &str) -> Result<usize, ModelError> {
    s.nodes
        .iter()
        .position(|x| x.name == n)
        .ok_or_else(|| ModelError::Unknown {
            field: field.to_string(),
            what: "node",
            name: n.to_string(),
        })
}

/// The references between the entries: names unique, every connection on an existing
/// member end with at least one spring, every parameter naming existing connection axes or
/// members, each in one parameter at most.
pub(super) fn check(s: &SpaceFrameSpec) -> Result<(), ModelError> {
    check_names(s)?;
    let axes = connection_axes(s)?;
    unique("connection", axes.iter().map(String::as_str))?;
    check_parameters(s, &axes)
}

/// Fails on the first name of `names` given twice, a duplicate `what`.
fn unique<'a>(what: &'static str, names: impl Iterator<Item = &'a str>) -> Result<(), ModelError> {
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

/// Checks that the names of each kind of entry are unique, and that no two connections are
/// at the same member end.
fn check_names(s: &SpaceFrameSpec) -> Result<(), ModelError> {
    unique("node", s.nodes.iter().map(|n| n.name.as_str()))?;
    unique("member", s.members.iter().map(|m| m.name.as_str()))?;
    unique("material", s.materials.iter().map(|m| m.name.as_str()))?;
    unique("section", s.sections.iter().map(|m| m.name.as_str()))?;
    unique("parameter", s.parameters.iter().map(|m| m.name.as_str()))?;
    unique("channel", s.channels.iter().map(|m| m.name.as_str()))?;
    unique("spring", s.springs.iter().map(|m| m.name.as_str()))?;
    unique(
        "connection at member end",
        s.connections
            .iter()
            .map(|c| format!("{}@{}", c.member, c.node))
            .collect::<Vec<_>>()
            .iter()
            .map(String::as_str),
    )?;
    Ok(())
}

/// Checks each connection (its member exists and ends at its node, it has at least one
/// spring, each `> 0`); returns the names of the sprung axes, in file order.
fn connection_axes(s: &SpaceFrameSpec) -> Result<Vec<String>, ModelError> {
    let mut axes = Vec::new();
    for c in &s.connections {
        let field = format!("connections.{}", c.name());
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
        if c.axes().next().is_none() {
            return Err(invalid(
                field,
                "no spring (give torsion, weak and/or strong)",
            ));
        }
        for (axis, k) in c.axes() {
            super::finish::check_positive(format!("connections.{axis}"), k)?;
            axes.push(axis);
        }
    }
    Ok(axes)
}

/// Checks each parameter: exactly one list, naming existing connection `axes`, members or
/// springs, none scaled by an earlier parameter.
fn check_parameters(s: &SpaceFrameSpec, axes: &[String]) -> Result<(), ModelError> {
    let mut used = std::collections::HashSet::new();
    for q in &s.parameters {
        let field = format!("parameters.{}", q.name);
        let lists = [&q.connections, &q.members, &q.springs];
        if lists.iter().filter(|l| !l.is_empty()).count() != 1 {
            return Err(invalid(
                field,
                "give one list: connections (`<member>@<node>.<axis>`), members or springs",
            ));
        }
        let known: [(&Vec<String>, &'static str, Vec<&str>); 3] = [
            (
                &q.connections,
                "connection axis",
                axes.iter().map(String::as_str).collect(),
            ),
            (
                &q.members,
                "member",
                s.members.iter().map(|x| x.name.as_str()).collect(),
            ),
            (
                &q.springs,
                "spring",
                s.springs.iter().map(|x| x.name.as_str()).collect(),
            ),
        ];
        for (list, what, names) in known {
            if let Some(e) = list.iter().find(|e| !names.contains(&e.as_str())) {
                return Err(ModelError::Unknown {
                    field: field.clone(),
                    what,
                    name: e.clone(),
                });
            }
        }
        for e in lists.into_iter().flatten() {
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

/// The DOFs fixed at every node and mesh node (`restrain`).
pub(super) fn restrained_dofs(s: &SpaceFrameSpec) -> Result<[bool; 6], ModelError> {
    let mut restrained = [false; 6];
    for d in &s.restrain {
        restrained[dof_index("restrain", d)?] = true;
    }
    Ok(restrained)
}

/// The fixed DOFs of each node: the restrained ones, and its support's (all six unless it
/// lists them in `fix`).
pub(super) fn fixed_dofs(
    s: &SpaceFrameSpec,
    restrained: [bool; 6],
) -> Result<Vec<[bool; 6]>, ModelError> {
    let mut fixed = vec![restrained; s.nodes.len()];
    for sup in &s.supports {
        let k = node_index(s, &sup.node, "supports.node")?;
        match &sup.fix {
            None => fixed[k] = [true; 6],
            Some(list) => {
                for d in list {
                    fixed[k][dof_index(&format!("supports.{}.fix", sup.node), d)?] = true;
                }
            }
        }
    }
    Ok(fixed)
}
