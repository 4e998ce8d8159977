//! `boltwatch.update.v1` (DESIGN §2): the result of one full update from θ0. The
//! mode-matching document; the Bayesian one adds its `bayesian` block
//! (`commands::bayes`).

use serde::{Deserialize, Serialize};

use super::stiffness::{Method, ModeComparison, Termination};
use super::wire::{Message, Schema};

/// A mode-matching update (module docs).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ModeMatchingDoc {
    pub schema: Schema<ModeMatchingDoc>,
    pub method: Method,
    pub structure: String,
    /// The modal set's time as it was given (RFC 3339, seconds as precise as needed).
    pub time: String,
    pub converged: bool,
    /// `Diverged` (a fixed-κ run that left θ > 0) with its reason in the command's output.
    pub termination: Termination,
    pub iterations: usize,
    pub evaluations: usize,
    /// Where the answer was found from (`theta0`, or a restart).
    pub start: String,
    pub chi2_bound: f64,
    pub epsilon: f64,
    pub n_data: usize,
    /// `covariance (8)` or `heuristic (9)`.
    pub weighting: String,
    pub parameters: Vec<ParameterResult>,
    pub modes: Vec<ModeResult>,
}

impl Message for ModeMatchingDoc {
    const SCHEMA: &'static str = "boltwatch.update.v1";
}

/// One parameter of an update.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ParameterResult {
    pub name: String,
    pub theta: f64,
    pub std: Option<f64>,
    /// `upper` or `lower` when θ ends at a bound (the data only say it is stiffer, or
    /// softer).
    pub at_bound: Option<Bound>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Bound {
    Lower,
    Upper,
}

/// A measured mode against its paired model mode, with the relative frequency error.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ModeResult {
    #[serde(flatten)]
    pub pair: ModeComparison,
    /// (model − measured)/measured frequency.
    pub error: f64,
}

impl ModeResult {
    pub fn new(pair: ModeComparison) -> Self {
        let error = (pair.model_hz - pair.measured_hz) / pair.measured_hz;
        Self { pair, error }
    }
}
