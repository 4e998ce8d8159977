//! `boltwatch.sigma_sweep.v1`: the σ_c study of `sweep-sigma` (paper Figs. 5, 7, 15, 18).

use serde::{Deserialize, Serialize};

use super::update::StageDoc;
use super::wire::{Message, Schema};

/// The study (module docs).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SweepDoc {
    pub schema: Schema<SweepDoc>,
    pub model: String,
    /// Parameter names, in the order of every `theta`.
    pub parameters: Vec<String>,
    /// The true θ, when given (`--truth`).
    pub truth: Option<Vec<f64>>,
    pub seconds: f64,
    pub auto: SweepAuto,
    pub points: Vec<SweepPointDoc>,
}

impl Message for SweepDoc {
    const SCHEMA: &'static str = "boltwatch.sigma_sweep.v1";
}

/// The automatic σ_c on the grid.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SweepAuto {
    pub rule: String,
    pub sigma_c: f64,
    pub nu: f64,
    pub met: bool,
}

/// The MAP at one σ_c.
#[allow(non_snake_case)]
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SweepPointDoc {
    pub sigma_c: f64,
    pub theta: Vec<f64>,
    pub most_probable_lambda: Vec<f64>,
    pub J_p: f64,
    pub measurement_misfit: f64,
    pub modelling_error: f64,
    pub prior_term: f64,
    pub epsilon: f64,
    pub mac_most_probable_to_measured: Vec<f64>,
    pub newton: NewtonRun,
    pub alternating: Option<AlternatingDoc>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct NewtonRun {
    pub iterations: usize,
    pub converged: bool,
    pub continuation: Vec<StageDoc>,
}

/// The paper's alternating solver at the same σ_c (`--alternating-max-iter`).
#[allow(non_snake_case)]
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AlternatingDoc {
    pub iterations: usize,
    pub converged: bool,
    pub theta: Vec<f64>,
    pub J_p: f64,
}
