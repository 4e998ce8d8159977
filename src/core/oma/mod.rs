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
//! * [`track`]: mode identity across windows (pairing with the modes seen before or with a
//!   model's, missing modes reported).
//! * [`synth`]: records simulated from a model (modal superposition under random forces,
//!   modal damping, sensor noise), the exact truth the tests and `scenario` need.

pub mod decimate;
pub mod identify;
pub mod settings;
pub mod spectrum;
pub mod ssi;
pub mod stabilize;
pub mod synth;
pub mod track;
pub mod uncertainty;

use faer::Mat;

/// A uniformly sampled multichannel record.
#[derive(Debug, Clone)]
pub struct Record {
    /// Channel names, one per column of `samples`.
    pub channels: Vec<String>,
    /// Sampling rate, Hz.
    pub rate_hz: f64,
    /// Samples as rows, channels as columns (N × r), in SI units (m/s², m/s, m).
    pub samples: Mat<f64>,
    /// What each channel measures (one per column).
    pub quantities: Vec<Quantity>,
}

impl Record {
    /// A record of accelerations on every channel.
    pub fn accelerations(channels: Vec<String>, rate_hz: f64, samples: Mat<f64>) -> Self {
        let quantities = vec![Quantity::Acceleration; channels.len()];
        Self {
            channels,
            rate_hz,
            samples,
            quantities,
        }
    }

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

/// What a channel measures. Channels of mixed quantities identify together: they share the
/// poles, and each mode-shape entry is brought to acceleration (`φ_a = λ^p φ`, λ the
/// continuous pole, p = [`Quantity::to_acceleration`]) before the shape is made real, so
/// the shape compares with the model's whatever each sensor measures.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Quantity {
    Displacement,
    Velocity,
    Acceleration,
}

impl Quantity {
    /// Time derivatives that take this quantity to an acceleration.
    pub fn to_acceleration(self) -> i32 {
        match self {
            Self::Displacement => 2,
            Self::Velocity => 1,
            Self::Acceleration => 0,
        }
    }
}

/// Units a channel may be in, with their quantity and factor to SI.
pub const UNITS: [(&str, Quantity, f64); 9] = [
    ("m/s^2", Quantity::Acceleration, 1.0),
    ("mm/s^2", Quantity::Acceleration, 1e-3),
    ("g", Quantity::Acceleration, 9.80665),
    ("m/s", Quantity::Velocity, 1.0),
    ("mm/s", Quantity::Velocity, 1e-3),
    ("in/s", Quantity::Velocity, 0.0254),
    ("m", Quantity::Displacement, 1.0),
    ("mm", Quantity::Displacement, 1e-3),
    ("um", Quantity::Displacement, 1e-6),
];

/// The quantity and the factor to SI of `unit` (one of [`UNITS`]).
pub fn parse_unit(unit: &str) -> Result<(Quantity, f64), String> {
    UNITS
        .iter()
        .find(|(u, _, _)| *u == unit)
        .map(|&(_, q, f)| (q, f))
        .ok_or_else(|| {
            format!(
                "unit `{unit}` is not known (known: {})",
                UNITS.map(|(u, _, _)| u).join(", ")
            )
        })
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
