//! `boltwatch.crosscheck.v1` (DESIGN §3.3, §7): the Bayesian MAP against the tracked
//! mode-matching estimate on one modal set.

use chrono::{DateTime, Utc};
use serde::{Deserialize, Serialize};

use super::wire::{Message, Schema, time};

/// One cross-check (module docs). A failed MAP solve is reported (`ok: false`, `error`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Crosscheck {
    pub schema: Schema<Crosscheck>,
    /// Stable id ([`super::output_id`]); absent (empty) in messages written before ids.
    #[serde(default)]
    pub id: String,
    pub structure: String,
    #[serde(with = "time")]
    pub time: DateTime<Utc>,
    /// σ_c of (14).
    pub sigma_c: f64,
    pub mode_matching: FitIterations,
    pub ok: bool,
    pub error: Option<String>,
    /// The MAP solve (absent when it failed).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub bayesian: Option<MapSolve>,
    pub parameters: Vec<ParameterComparison>,
    /// The largest z over the parameters.
    pub max_z: Option<f64>,
    /// Parameters with z above the configured threshold.
    pub disagree: Vec<String>,
}

impl Message for Crosscheck {
    const SCHEMA: &'static str = "boltwatch.crosscheck.v1";
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FitIterations {
    pub iterations: usize,
}

/// The MAP solve's outcome.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MapSolve {
    pub iterations: usize,
    pub converged: bool,
    /// J_p (14) at the MAP.
    pub j_p: f64,
}

/// One parameter under both methods.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ParameterComparison {
    pub name: String,
    pub mode_matching: ThetaStd,
    pub bayesian: BayesTheta,
    /// |θ_mm − θ_b| / √(σ_mm² + σ_b²).
    pub z: Option<f64>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ThetaStd {
    pub theta: f64,
    pub std: Option<f64>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BayesTheta {
    pub theta: f64,
    /// Sampling standard deviation of the MAP.
    pub std: Option<f64>,
    pub posterior_std: Option<f64>,
}
