//! Operational modal analysis (issue 26): from multichannel output-only vibration records
//! to modal sets.
//!
//! * [`ssi`]: covariance-driven stochastic subspace identification (SSI-COV; Peeters & De
//!   Roeck, "Reference-based stochastic subspace identification for output-only modal
//!   analysis", MSSP 13(6), 1999): output covariances, their block Hankel matrix, its SVD,
//!   and the poles of the identified state matrix at every model order.
//! * [`stabilize`]: the automatic choice of modes from the poles of many orders
//!   (stabilization across orders, clustering of stable poles, rejection of spurious and
//!   noise poles).
//! * [`synth`]: records simulated from a model (modal superposition under random forces,
//!   modal damping, sensor noise), the exact truth the tests and `scenario` need.

pub mod identify;
pub mod ssi;
pub mod stabilize;
pub mod synth;
pub mod uncertainty;

use faer::Mat;

/// A uniformly sampled multichannel record.
#[derive(Debug, Clone)]
pub struct Record {
    /// Channel names, one per column of `samples`.
    pub channels: Vec<String>,
    /// Sampling rate, Hz.
    pub rate_hz: f64,
    /// Samples as rows, channels as columns (N × r).
    pub samples: Mat<f64>,
}

impl Record {
    /// Number of samples.
    pub fn len(&self) -> usize {
        self.samples.nrows()
    }

    /// Whether the record holds no samples.
    pub fn is_empty(&self) -> bool {
        self.samples.nrows() == 0
    }

    /// Duration, s.
    pub fn duration_s(&self) -> f64 {
        self.len() as f64 / self.rate_hz
    }
}

/// Failures of an identification.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum OmaError {
    #[error("{0}")]
    Input(String),
    #[error(
        "the record is too short: {samples} samples for {lags} covariance lags (need at least {need})"
    )]
    TooShort {
        samples: usize,
        lags: usize,
        need: usize,
    },
    #[error("numerical failure: {0}")]
    Numerical(String),
}
