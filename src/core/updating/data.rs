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
    /// `RMS(ψ̂)·S^w` for every entry by (28), the entry's own std when the set gives
    /// `shape_std` ([`floored_shape_std`]), or `(N_o‖ψ̂‖²/w_ψ)^{1/2}` under weighting (9).
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
    /// Absolute standard deviation of each entry of `shape` (in its order); used instead
    /// of `shape_nsd` when given, floored by [`floored_shape_std`].
    pub shape_std: Option<Vec<f64>>,
}

/// An entry's std below this fraction of the mode's median std is taken as "about 0"
/// ([`floored_shape_std`]).
pub const SHAPE_STD_FLOOR: f64 = 1e-3;

/// The median of the positive values, `None` if there is none.
pub fn positive_median<'a>(values: impl Iterator<Item = &'a f64>) -> Option<f64> {
    let mut v: Vec<f64> = values.copied().filter(|x| *x > 0.0).collect();
    if v.is_empty() {
        return None;
    }
    v.sort_by(f64::total_cmp);
    let h = v.len() / 2;
    Some(if v.len() % 2 == 1 {
        v[h]
    } else {
        0.5 * (v[h - 1] + v[h])
    })
}

/// Per-entry shape stds as `Σ_M` (28) uses them: every entry below [`SHAPE_STD_FLOOR`]
/// times the median of the mode's positive stds is raised to that median. The rule is for
/// a shape normalized to one reference entry: that entry's std is 0 by construction (the
/// normalization moved its measurement error into the others), but the model's shape is
/// fitted to all entries by one scale factor (7), so its residual at the reference entry
/// is as uncertain as at a typical one; a std of ~0 would make that one residual dominate ε.
/// Entries with an honest small std (≥ 1/1000 of the median) are kept.
pub fn floored_shape_std(std: &[f64]) -> Vec<f64> {
    let median = positive_median(std.iter()).unwrap_or(0.0);
    std.iter()
        .map(|&s| {
            if s < SHAPE_STD_FLOOR * median {
                median
            } else {
                s
            }
        })
        .collect()
}

impl MeasuredData {
    /// Builds `Σ_M` by (28) when every mode carries its uncertainties, otherwise the
    /// weights (9) with `w_psi`. (Modal-set validation rejects sets that mix the two.)
    pub fn new(raw: &[RawMode], w_psi: f64) -> Self {
        let with_cov = raw.iter().all(|m| {
            m.frequency_cov.is_some()
                && (m.shape.is_none() || m.shape_nsd.is_some() || m.shape_std.is_some())
        });
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
                    let sigma = match (weighting, &m.shape_std, m.shape_nsd) {
                        (Weighting::Covariance, Some(std), _) => floored_shape_std(std),
                        (Weighting::Covariance, None, Some(nsd)) => {
                            vec![(sq / n_o).sqrt() * nsd; channels.len()]
                        }
                        _ => vec![(n_o * sq / w_psi).sqrt(); channels.len()],
                    };
                    TargetShape {
                        sigma,
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

#[cfg(test)]
mod tests {
    use super::*;

    /// The floor: a zero (the reference entry) and a 1e-4-of-median entry take the median
    /// of the positive stds; the others are kept, however they compare with the median.
    #[test]
    fn shape_std_floor_raises_only_the_near_zero_entries() {
        let std = [0.0, 0.02, 0.01, 1e-6, 0.04, 3e-5];
        // Positive: 1e-6, 3e-5, 0.01, 0.02, 0.04 → median 0.01; floor 1e-5.
        assert_eq!(
            floored_shape_std(&std),
            vec![0.01, 0.02, 0.01, 0.01, 0.04, 3e-5]
        );
        assert_eq!(positive_median([1.0, 3.0].iter()), Some(2.0));
        assert_eq!(positive_median([0.0].iter()), None);
    }

    /// `shape_std` of `RMS(ψ̂)·S` on every entry weighs exactly as `shape_nsd = S`.
    #[test]
    fn uniform_shape_std_is_the_scalar_nsd() {
        let shape = vec![(0, 0.3), (1, -1.0), (2, 0.7)];
        let rms = ((0.09_f64 + 1.0 + 0.49) / 3.0).sqrt();
        let mode = |nsd: Option<f64>, std: Option<Vec<f64>>| RawMode {
            frequency_hz: 5.0,
            frequency_cov: Some(0.01),
            shape: Some(shape.clone()),
            shape_nsd: nsd,
            shape_std: std,
        };
        let a = MeasuredData::new(&[mode(Some(0.05), None)], 1.0);
        let b = MeasuredData::new(&[mode(None, Some(vec![rms * 0.05; 3]))], 1.0);
        assert_eq!(a.weighting, Weighting::Covariance);
        assert_eq!(b.weighting, Weighting::Covariance);
        let (sa, sb) = (
            &a.modes[0].shape.as_ref().unwrap().sigma,
            &b.modes[0].shape.as_ref().unwrap().sigma,
        );
        for (x, y) in sa.iter().zip(sb) {
            assert!((x - y).abs() <= 1e-15 * x, "{x} vs {y}");
        }
    }
}
