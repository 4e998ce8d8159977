//! Where sensors could go: the candidate places of each kind of model, added to it as
//! channels. A frame's are its named nodes, the nodes of its members' meshes and (with
//! [`Places::All`]) their rotations; a solid frame's are points on its beams' axes
//! ([`crate::core::model::solid::candidate_channels`]); an imported model's are its DOFs,
//! by label, those of its named locations or all.

use anyhow::{Context, Result, bail};

use crate::core::model::spec::{ChannelSpec, ModelSpec};
use crate::core::model::{Channel, Model};

/// Which places are candidates.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Places {
    /// Translations at the named nodes (a solid's beams at every sixth of their length; an
    /// imported model's named locations).
    Nodes,
    /// Translations at every node of the mesh (an imported model's every DOF).
    Dofs,
    /// [`Places::Dofs`] and a frame's rotations.
    All,
}

/// A model with a channel at every candidate place, and the candidates' names (the
/// places the model measures already among them).
pub struct WithCandidates {
    pub model: Model,
    /// The model file with the candidate channels, for a frame (what a drawing needs).
    pub spec: Option<ModelSpec>,
    pub candidates: Vec<String>,
}

/// `base` (assembled from `spec`, when it has a model file) with the candidate places of
/// `kind` added as channels.
pub fn with_candidates(
    spec: Option<&ModelSpec>,
    base: &Model,
    kind: Places,
) -> Result<WithCandidates> {
    let extra = match spec {
        None => matrix_candidates(base, kind)?,
        Some(s) => match &s.solid_frame {
            Some(sf) => crate::core::model::solid::candidate_channels(sf, kind != Places::Nodes)
                .with_context(|| format!("candidate places of {}", base.name))?,
            None => {
                let (spec, candidates) = frame_candidates(s, kind)?;
                let model = Model::from_spec(&spec)
                    .with_context(|| format!("candidate places of {}", base.name))?;
                return Ok(WithCandidates {
                    model,
                    spec: Some(spec),
                    candidates,
                });
            }
        },
    };
    let mut candidates: Vec<String> = extra.iter().map(|c| c.name.clone()).collect();
    candidates.extend(base.channels().iter().map(|c| c.name.clone()));
    let model = base
        .with_channels(extra)
        .with_context(|| format!("candidate places of {}", base.name))?;
    Ok(WithCandidates {
        model,
        spec: spec.cloned(),
        candidates,
    })
}

/// Where a sensor could go on a model imported from matrices, one DOF each and named by
/// its label: every DOF of the model's named locations (`nodes`) or every DOF (`dofs`,
/// `all`). A DOF one of the model's channels reads on its own is left out.
fn matrix_candidates(model: &Model, kind: Places) -> Result<Vec<Channel>> {
    let dofs: Vec<usize> = match kind {
        Places::Nodes => {
            if model.locations().is_empty() {
                bail!(
                    "--candidates nodes: the model {} names no locations; give \
                     --candidates dofs to consider every DOF",
                    model.name
                );
            }
            let mut d: Vec<usize> = model
                .locations()
                .iter()
                .flat_map(|l| l.dofs.clone())
                .collect();
            d.sort_unstable();
            d.dedup();
            d
        }
        Places::Dofs | Places::All => (0..model.n_dof()).collect(),
    };
    let read = |i: usize| {
        model
            .channels()
            .iter()
            .any(|c| matches!(c.dofs[..], [(j, _)] if j == i))
    };
    let labels = model.dof_labels();
    Ok(dofs
        .into_iter()
        .filter(|&i| !read(i) && model.channel_index(&labels[i]).is_none())
        .map(|i| Channel {
            name: labels[i].clone(),
            dofs: vec![(i, 1.0)],
        })
        .collect())
}

/// A frame's model file with a channel added at every candidate place not measured
/// already, and the candidates' names.
fn frame_candidates(spec: &ModelSpec, kind: Places) -> Result<(ModelSpec, Vec<String>)> {
    let mut spec = spec.clone();
    let (places, dirs): (Vec<String>, &[&str]) = if let Some(s) = &spec.space_frame {
        let meshes = s.members.iter().map(|m| (m.name.as_str(), m.elements));
        let dirs: &[&str] = match kind {
            Places::All => &["x", "y", "z", "rx", "ry", "rz"],
            _ => &["x", "y", "z"],
        };
        (
            frame_places(s.nodes.iter().map(|n| n.name.as_str()), meshes, kind),
            dirs,
        )
    } else if !spec.members.is_empty() {
        let meshes = spec.members.iter().map(|m| (m.name.as_str(), m.elements));
        let dirs: &[&str] = match kind {
            Places::All => &["x", "y", "rz"],
            _ => &["x", "y"],
        };
        (
            frame_places(spec.nodes.iter().map(|n| n.name.as_str()), meshes, kind),
            dirs,
        )
    } else {
        bail!("{}: not a frame model", spec.name);
    };
    let (supports, restrain) = match &spec.space_frame {
        Some(s) => (s.supports.clone(), s.restrain.clone()),
        None => (spec.supports.clone(), Vec::new()),
    };
    // A DOF a support or the frame's restraint fixes reads nothing: no sensor there.
    let fixed = |at: &str, dir: &str| {
        restrain.iter().any(|r| r == dir)
            || supports
                .iter()
                .any(|s| s.node == at && s.fix.as_ref().is_none_or(|f| f.iter().any(|d| d == dir)))
    };
    let channels = match &mut spec.space_frame {
        Some(s) => &mut s.channels,
        None => &mut spec.channels,
    };
    let mut names = Vec::new();
    for at in &places {
        for dir in dirs.iter().filter(|d| !fixed(at, d)) {
            let name = format!("{at}.{dir}");
            if !channels.iter().any(|c| c.name == name) {
                channels.push(ChannelSpec {
                    name: name.clone(),
                    at: at.clone(),
                    dir: dir.to_string(),
                });
            }
            names.push(name);
        }
    }
    Ok((spec, names))
}

/// The named nodes, and with `dofs` or `all` every interior node of each member's mesh
/// (`<member>.<k>`).
fn frame_places<'a>(
    nodes: impl Iterator<Item = &'a str>,
    meshes: impl Iterator<Item = (&'a str, usize)>,
    kind: Places,
) -> Vec<String> {
    let mut out: Vec<String> = nodes.map(str::to_string).collect();
    if kind != Places::Nodes {
        for (member, elements) in meshes {
            out.extend((1..elements).map(|k| format!("{member}.{k}")));
        }
    }
    out
}
