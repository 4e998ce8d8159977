//! Measured modal data prepared for updating: eigenvalues, mode shapes at model channels,
//! and their standard deviations, i.e. the diagonal of `Σ_M` (28) or the weights (9).

use std::f64::consts::PI;

/// A measured mode shape restricted to its measured entries.
#[derive(Debug, Clone, PartialEq)]
pub struct TargetShape {
    /// Model channel index of each measured entry.
    pub channels: Vec<usize>,
    /// ψ̂ at those channels.
    pub values: Vec<f64>,
    /// Standard deviation of each entry (the shape block of the diagonal of `Σ_M`):
    /// `RMS(ψ̂)·S^w` for every entry by (28), or `(N_o‖ψ̂‖²/w_ψ)^{1/2}` under weighting (9).
    pub sigma: Vec<f64>,
}

/// One measured mode.
#[derive(Debug, Clone, PartialEq)]
pub struct TargetMode {
    /// λ̂ = (2π f̂)², rad²/s².
    pub lambda: f64,
    /// Standard deviation of λ̂: `2 V^f λ̂` under (8) (a frequency CoV V^f is an eigenvalue
    /// CoV 2V^f to first order, as λ ∝ f²), or `λ̂` under (9).
    pub sigma_lambda: f64,
    pub shape: Option<TargetShape>,
}

/// How the residual is weighted.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Weighting {
    /// `W = Σ_M⁻¹`, paper (8), with `Σ_M` from (28): the covariance (15) is absolute.
    Covariance,
    /// `W` of paper (9) with shape weight `w_ψ`: no uncertainties were given, so the
    /// covariance (15) is scaled by the residual variance `ε / (N − N_θ)`.
    Heuristic { w_psi: f64 },
}

/// The measured data of one modal set, in the form the updating methods use.
#[derive(Debug, Clone, PartialEq)]
pub struct MeasuredData {
    pub modes: Vec<TargetMode>,
    pub weighting: Weighting,
}

/// One mode as read from a modal set: frequency (Hz), its CoV, and the measured shape
/// entries `(model channel, value)` with their NSD.
#[derive(Debug, Clone)]
pub struct RawMode {
    pub frequency_hz: f64,
    pub frequency_cov: Option<f64>,
    pub shape: Option<Vec<(usize, f64)>>,
    pub shape_nsd: Option<f64>,
}

impl MeasuredData {
    /// Builds `Σ_M` by (28) when every mode carries its uncertainties, otherwise the
    /// weights (9) with `w_psi`. (Modal-set validation rejects sets that mix the two.)
    pub fn new(raw: &[RawMode], w_psi: f64) -> Self {
        let with_cov = raw
            .iter()
            .all(|m| m.frequency_cov.is_some() && (m.shape.is_none() || m.shape_nsd.is_some()));
        let weighting = if with_cov {
            Weighting::Covariance
        } else {
            Weighting::Heuristic { w_psi }
        };
        let modes = raw
            .iter()
            .map(|m| {
                let lambda = (2.0 * PI * m.frequency_hz).powi(2);
                let sigma_lambda = match (weighting, m.frequency_cov) {
                    (Weighting::Covariance, Some(v)) => 2.0 * v * lambda,
                    _ => lambda,
                };
                let shape = m.shape.as_ref().map(|entries| {
                    let channels: Vec<usize> = entries.iter().map(|e| e.0).collect();
                    let values: Vec<f64> = entries.iter().map(|e| e.1).collect();
                    let n_o = values.len() as f64;
                    let sq: f64 = values.iter().map(|v| v * v).sum();
                    let sigma = match (weighting, m.shape_nsd) {
                        (Weighting::Covariance, Some(nsd)) => (sq / n_o).sqrt() * nsd,
                        _ => (n_o * sq / w_psi).sqrt(),
                    };
                    TargetShape {
                        sigma: vec![sigma; channels.len()],
                        channels,
                        values,
                    }
                });
                TargetMode {
                    lambda,
                    sigma_lambda,
                    shape,
                }
            })
            .collect();
        Self { modes, weighting }
    }

    /// Number of residual entries N (eigenvalues plus measured shape entries).
    pub fn n_data(&self) -> usize {
        self.modes
            .iter()
            .map(|m| 1 + m.shape.as_ref().map_or(0, |s| s.values.len()))
            .sum()
    }
}
