//! Mode identity across windows (issue 26): each window's identified modes are paired with
//! the reference modes (the modes seen so far, or a model's), so a physical mode keeps its
//! label from window to window, and a mode seen before and not found in a window is
//! reported missing rather than the others renumbered.
//!
//! **Gating rule.** An identified mode may take a reference when its frequency is within
//! [`Gate::max_df`] of the reference's (relative) and the MAC of the shapes, over the
//! channels both have, is at least [`Gate::min_mac`]. Among the admissible pairs the
//! assignment is greedy by MAC (then by the frequency difference), one to one. A paired
//! reference moves to the identified mode (frequency and shape), so slow changes (the
//! temperature, a connection loosening over days) are followed; an identified mode no
//! reference admits gets a new label.
//!
//! **Labels.** Paired with a model's modes ([`ModeTrack::from_model`]): `mode k`, the
//! model's k-th mode (from 1, ascending frequency at the nominal θ), and `new k` for modes
//! the model does not have. Without a model: `mode k` in the order modes first appear
//! (ascending frequency within a window).

use super::OmaError;
use super::ssi::mac_real;
use super::synth::modes_past;
use crate::core::model::Model;

/// The gating rule (module docs).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Gate {
    /// Largest relative frequency difference to a reference.
    pub max_df: f64,
    /// Smallest MAC with a reference's shape.
    pub min_mac: f64,
}

impl Default for Gate {
    /// 15 % and MAC 0.8: wide enough for a model a few percent off and for a 50 % loss of
    /// one connection's stiffness between two windows (the lab frame's modes move by at
    /// most 6 %), narrow enough that neighbouring modes (MAC between them < 0.3 on the
    /// lab frame) are not confused.
    fn default() -> Self {
        Self {
            max_df: 0.15,
            min_mac: 0.8,
        }
    }
}

/// One reference mode.
#[derive(Debug, Clone, PartialEq)]
pub struct Reference {
    pub label: String,
    pub frequency_hz: f64,
    /// The channels `shape` is read on.
    pub channels: Vec<String>,
    pub shape: Vec<f64>,
    /// Identified in some window already (only such a mode can be missing).
    pub seen: bool,
}

/// Labels of one window's modes, and the labels missing from it.
#[derive(Debug, Clone, PartialEq)]
pub struct Assignment {
    /// One per identified mode, in their order.
    pub labels: Vec<String>,
    /// References seen before and not paired in this window, in reference order.
    pub missing: Vec<String>,
}

/// The references and the gating rule (module docs).
#[derive(Debug, Clone)]
pub struct ModeTrack {
    pub refs: Vec<Reference>,
    pub gate: Gate,
    /// Prefix of the labels of modes no reference admits (`mode ` without a model, `new `
    /// with one), and how many have been given.
    new_prefix: &'static str,
    new_count: usize,
}

impl ModeTrack {
    /// No references yet: modes are labelled as they first appear.
    pub fn new(gate: Gate) -> Self {
        Self {
            refs: Vec::new(),
            gate,
            new_prefix: "mode ",
            new_count: 0,
        }
    }

    /// The modes of `model` at its nominal θ up to `max_frequency_hz` (at least one) as the
    /// references, read on the model's channels and labelled `mode k`.
    pub fn from_model(model: &Model, max_frequency_hz: f64, gate: Gate) -> Result<Self, OmaError> {
        let theta = model.nominal_theta();
        let pairs = modes_past(model, &theta, max_frequency_hz)?;
        let n = pairs.lambda.len();
        let channels: Vec<String> = model.channels().iter().map(|c| c.name.clone()).collect();
        let refs = (0..n)
            .filter(|&k| k == 0 || pairs.frequency_hz(k) <= max_frequency_hz)
            .map(|k| {
                let col: Vec<f64> = pairs.phi.col(k).iter().copied().collect();
                Reference {
                    label: format!("mode {}", k + 1),
                    frequency_hz: pairs.frequency_hz(k),
                    channels: channels.clone(),
                    shape: model.channels().iter().map(|c| c.read(&col)).collect(),
                    seen: false,
                }
            })
            .collect();
        Ok(Self {
            refs,
            gate,
            new_prefix: "new ",
            new_count: 0,
        })
    }

    /// Labels the `modes` (frequency, shape on `channels`) of one window and moves the
    /// paired references to them (module docs).
    pub fn assign(&mut self, channels: &[String], modes: &[(f64, &[f64])]) -> Assignment {
        let mut pairs = Vec::new();
        for (i, (f, shape)) in modes.iter().enumerate() {
            for (j, r) in self.refs.iter().enumerate() {
                let df = (f / r.frequency_hz - 1.0).abs();
                if df > self.gate.max_df {
                    continue;
                }
                let (a, b): (Vec<f64>, Vec<f64>) = channels
                    .iter()
                    .zip(shape.iter())
                    .filter_map(|(c, v)| {
                        r.channels
                            .iter()
                            .position(|rc| rc == c)
                            .map(|k| (*v, r.shape[k]))
                    })
                    .unzip();
                let mac = if a.is_empty() { 0.0 } else { mac_real(&a, &b) };
                if mac >= self.gate.min_mac {
                    pairs.push((i, j, mac, df));
                }
            }
        }
        pairs.sort_by(|x, y| y.2.total_cmp(&x.2).then(x.3.total_cmp(&y.3)));
        let mut label_of: Vec<Option<usize>> = vec![None; modes.len()];
        let mut taken = vec![false; self.refs.len()];
        for (i, j, _, _) in pairs {
            if label_of[i].is_none() && !taken[j] {
                label_of[i] = Some(j);
                taken[j] = true;
            }
        }
        let missing = self
            .refs
            .iter()
            .zip(&taken)
            .filter(|(r, t)| r.seen && !**t)
            .map(|(r, _)| r.label.clone())
            .collect();
        let mut labels = Vec::with_capacity(modes.len());
        for (i, (f, shape)) in modes.iter().enumerate() {
            let j = match label_of[i] {
                Some(j) => j,
                None => {
                    self.new_count += 1;
                    self.refs.push(Reference {
                        label: format!("{}{}", self.new_prefix, self.new_count),
                        frequency_hz: *f,
                        channels: Vec::new(),
                        shape: Vec::new(),
                        seen: false,
                    });
                    self.refs.len() - 1
                }
            };
            let r = &mut self.refs[j];
            r.frequency_hz = *f;
            r.channels = channels.to_vec();
            r.shape = shape.to_vec();
            r.seen = true;
            labels.push(r.label.clone());
        }
        Assignment { labels, missing }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ch(n: usize) -> Vec<String> {
        (0..n).map(|i| format!("c{i}")).collect()
    }

    /// Labels in order of appearance; a mode that drops out is missing, the others keep
    /// their labels; it comes back under its label; a new mode gets a new label; a mode
    /// whose shape changes beyond the MAC gate is not taken for the old one.
    #[test]
    fn identities_survive_dropouts_and_drift() {
        let c = ch(3);
        let (s1, s2, s3) = ([1.0, 1.0, 1.0], [1.0, 0.0, -1.0], [1.0, -2.0, 1.0]);
        let mut t = ModeTrack::new(Gate::default());
        let a = t.assign(&c, &[(10.0, &s1), (25.0, &s2), (40.0, &s3)]);
        assert_eq!(a.labels, ["mode 1", "mode 2", "mode 3"]);
        assert!(a.missing.is_empty());
        // The middle mode drops out; the others drift by 5 %.
        let a = t.assign(&c, &[(10.5, &s1), (42.0, &s3)]);
        assert_eq!(a.labels, ["mode 1", "mode 3"]);
        assert_eq!(a.missing, ["mode 2"]);
        // It comes back; a new mode appears between.
        let a = t.assign(
            &c,
            &[
                (10.5, &s1),
                (25.5, &s2),
                (33.0, &[0.0, 1.0, 0.0]),
                (42.0, &s3),
            ],
        );
        assert_eq!(a.labels, ["mode 1", "mode 2", "mode 4", "mode 3"]);
        assert!(a.missing.is_empty());
        // Near mode 1's frequency but with mode 2's shape: not mode 1.
        let a = t.assign(&c, &[(10.6, &s2)]);
        assert_eq!(a.labels, ["mode 5"]);
    }

    /// Paired with a model: the lab frame's modes are labelled by the model's numbering,
    /// read on a subset of its channels, and a mode outside every gate is `new 1`.
    #[test]
    fn modes_are_named_after_the_model() {
        let model = crate::core::model::Model::from_spec(
            &toml::from_str(include_str!("../../../config/models/lab-frame.toml")).unwrap(),
        )
        .unwrap();
        let mut t = ModeTrack::from_model(&model, 200.0, Gate::default()).unwrap();
        let channels: Vec<String> = t.refs[0].channels[..30].to_vec();
        let take = |r: &Reference| r.shape[..30].to_vec();
        let (s3, s1) = (take(&t.refs[2]), take(&t.refs[0]));
        let (f3, f1) = (t.refs[2].frequency_hz, t.refs[0].frequency_hz);
        let a = t.assign(
            &channels,
            &[(f1 * 1.02, &s1), (f3 * 0.97, &s3), (f3 * 2.5, &s1)],
        );
        assert_eq!(a.labels, ["mode 1", "mode 3", "new 1"]);
        assert!(a.missing.is_empty());
    }
}
