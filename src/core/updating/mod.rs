//! Model updating from modal data: mode matching (5)–(9), (15), (18)–(20), and the
//! Bayesian MAP (10)–(14), (16), (21)–(23).

pub mod bayesian;
pub mod bounds;
pub mod data;
pub mod globalize;
pub mod mode_matching;
pub mod plausibility;
pub mod residual;
pub mod search;
pub mod strategy;
pub mod variance;

pub use bounds::{AtBound, LogBounds};
pub use data::{MeasuredData, RawMode, TargetMode, TargetShape, Weighting};
pub use globalize::{RESTART_STARTS, StartPath};
pub use mode_matching::{
    BoundStep, FinalStep, FirstOrder, ModeMatching, ModeMatchingOptions, ModeMatchingResult,
    StepControl, Termination,
};
pub use residual::{Evaluation, Evaluator, Pairing};

use crate::core::modal::ModalError;

/// Failures of an update.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum UpdateError {
    #[error(transparent)]
    Modal(#[from] ModalError),
    #[error("θ0 has {got} entries but the model has {expected} parameters")]
    ThetaLength { expected: usize, got: usize },
    #[error("θ0[{index}] = {value} must be a finite number > 0")]
    ThetaNotPositive { index: usize, value: f64 },
    #[error("the modal set has {modes} modes but the model has only {dofs} DOFs")]
    TooManyModes { modes: usize, dofs: usize },
    #[error("option {name} = {value} is invalid: {reason}")]
    Option {
        name: &'static str,
        value: f64,
        reason: &'static str,
    },
}
