//! `boltwatch.diagnosis.v1` (DESIGN §6): the document `diagnose` writes, from a
//! [`crate::core::diagnosis::Diagnosis`].

use serde::{Deserialize, Serialize};

use super::wire::{Message, Schema, finite};
use crate::core::diagnosis::{Diagnosis, Localization, Refit};

/// Candidates listed from the first round's screening.
pub const CANDIDATES_LISTED: usize = 30;

/// The document (module docs).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DiagnosisDoc {
    pub schema: Schema<DiagnosisDoc>,
    pub structure: String,
    pub epsilon_before: f64,
    pub epsilon_after: f64,
    pub named: Vec<NamedDoc>,
    /// The first round's screening, best first ([`CANDIDATES_LISTED`] at most).
    pub candidates: Vec<CandidateDoc>,
    pub test: TestDoc,
    pub rounds: Vec<RoundDoc>,
    pub before: LocalizationDoc,
    pub after: LocalizationDoc,
    /// Wall-clock time of the workflow.
    pub seconds: f64,
}

impl Message for DiagnosisDoc {
    const SCHEMA: &'static str = "boltwatch.diagnosis.v1";
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct NamedDoc {
    pub effect: String,
    pub location: String,
    pub value: f64,
    pub std: Option<f64>,
    pub unit: String,
    pub epsilon_before: f64,
    pub epsilon_after: f64,
    pub evidence: Evidence,
    pub indistinguishable_from: Vec<RefitDoc>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Evidence {
    pub likelihood_ratio: f64,
    pub threshold: f64,
    pub log_bayes_factor: f64,
}

/// A candidate effect refitted: its value, uncertainty and ε.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RefitDoc {
    pub effect: String,
    pub location: String,
    pub value: f64,
    pub std: Option<f64>,
    pub unit: String,
    pub epsilon: f64,
}

impl From<&Refit> for RefitDoc {
    fn from(r: &Refit) -> Self {
        Self {
            effect: r.effect.into(),
            location: r.location.clone(),
            value: r.value,
            std: finite(r.std),
            unit: r.unit.into(),
            epsilon: r.epsilon,
        }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CandidateDoc {
    pub effect: String,
    pub location: String,
    pub score: f64,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TestDoc {
    pub method: String,
    pub alpha: f64,
    pub candidates: usize,
    pub threshold: f64,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RoundDoc {
    pub epsilon: f64,
    pub refits: Vec<RefitDoc>,
    /// `effect@location` named in this round.
    pub named: Option<String>,
    pub withdrawn: Vec<WithdrawnDoc>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct WithdrawnDoc {
    pub effect: String,
    pub location: String,
    pub likelihood_ratio: f64,
}

/// Where the model and the data disagree.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LocalizationDoc {
    pub epsilon: f64,
    pub theta: Vec<f64>,
    pub modes: Vec<ModeMisfitDoc>,
    pub channels: Vec<ChannelMisfitDoc>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ModeMisfitDoc {
    pub measured_hz: f64,
    pub model_hz: f64,
    pub error_sigma: f64,
    pub mac: Option<f64>,
    pub paired_with: usize,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ChannelMisfitDoc {
    pub channel: String,
    pub shape_residual: f64,
    pub entries: usize,
}

impl From<&Localization> for LocalizationDoc {
    fn from(l: &Localization) -> Self {
        Self {
            epsilon: l.epsilon,
            theta: l.theta.clone(),
            modes: l
                .modes
                .iter()
                .map(|m| ModeMisfitDoc {
                    measured_hz: m.measured_hz,
                    model_hz: m.model_hz,
                    error_sigma: m.error_sigma,
                    mac: finite(m.mac),
                    paired_with: m.paired_with,
                })
                .collect(),
            channels: l
                .channels
                .iter()
                .map(|(channel, r, k)| ChannelMisfitDoc {
                    channel: channel.clone(),
                    shape_residual: *r,
                    entries: *k,
                })
                .collect(),
        }
    }
}

impl DiagnosisDoc {
    /// The document of `d` on `structure`, which took `seconds`.
    pub fn new(d: &Diagnosis, structure: &str, seconds: f64) -> Self {
        Self {
            schema: Schema::new(),
            structure: structure.to_string(),
            epsilon_before: d.before.epsilon,
            epsilon_after: d.after.epsilon,
            named: d
                .named
                .iter()
                .map(|n| NamedDoc {
                    effect: n.refit.effect.into(),
                    location: n.refit.location.clone(),
                    value: n.refit.value,
                    std: finite(n.refit.std),
                    unit: n.refit.unit.into(),
                    epsilon_before: n.epsilon_before,
                    epsilon_after: n.refit.epsilon,
                    evidence: Evidence {
                        likelihood_ratio: n.likelihood_ratio,
                        threshold: n.threshold,
                        log_bayes_factor: n.log_bayes_factor,
                    },
                    indistinguishable_from: n
                        .indistinguishable_from
                        .iter()
                        .map(RefitDoc::from)
                        .collect(),
                })
                .collect(),
            candidates: d.rounds.first().map_or_else(Vec::new, |r| {
                r.candidates
                    .iter()
                    .take(CANDIDATES_LISTED)
                    .map(|c| CandidateDoc {
                        effect: c.effect.into(),
                        location: c.location.clone(),
                        score: c.score,
                    })
                    .collect()
            }),
            test: TestDoc {
                method: "likelihood ratio, chi-square 1 dof, Bonferroni over candidates".into(),
                alpha: d.alpha,
                candidates: d.n_candidates,
                threshold: d.threshold,
            },
            rounds: d
                .rounds
                .iter()
                .map(|r| RoundDoc {
                    epsilon: r.epsilon,
                    refits: r.refits.iter().map(RefitDoc::from).collect(),
                    named: r
                        .named
                        .as_ref()
                        .map(|n| format!("{}@{}", n.refit.effect, n.refit.location)),
                    withdrawn: r
                        .withdrawn
                        .iter()
                        .map(|w| WithdrawnDoc {
                            effect: w.effect.into(),
                            location: w.location.clone(),
                            likelihood_ratio: w.likelihood_ratio,
                        })
                        .collect(),
                })
                .collect(),
            before: (&d.before).into(),
            after: (&d.after).into(),
            seconds,
        }
    }
}
