//! Pairing (29): each measured mode with a model mode among the lowest candidates, by the
//! highest MAC or the least misfit ([`Pairing`]), from the candidates' readings at the
//! model channels.

use super::{Pairing, TargetMode, TargetShape};
use crate::core::modal::{EigenPairs, mac};
use crate::core::model::Channel;

/// Every candidate's reading `D φ_k` at every model channel, once (rows: the first `n_cand`
/// candidates).
pub(super) fn candidate_readings(
    channels: &[Channel],
    eig: &EigenPairs,
    n_cand: usize,
) -> Vec<Vec<f64>> {
    (0..n_cand)
        .map(|k| {
            channels
                .iter()
                .map(|ch| ch.dofs.iter().map(|&(i, w)| w * eig.phi[(i, k)]).sum())
                .collect()
        })
        .collect()
}

/// Candidate `k`'s readings at the channels `idx` into `out`.
pub(super) fn gather(readings: &[Vec<f64>], k: usize, idx: &[usize], out: &mut Vec<f64>) {
    out.clear();
    out.extend(idx.iter().map(|&c| readings[k][c]));
}

/// Pairing (29) by `rule` of measured mode `mode` among the first `n_cand` candidates: the
/// model mode (0-based) and the MAC of the shape with it (NaN without a shape). `dphi_k` is
/// scratch for the candidates' readings.
pub(super) fn pair_mode(
    mode: &TargetMode,
    rule: Pairing,
    eig: &EigenPairs,
    readings: &[Vec<f64>],
    n_cand: usize,
    dphi_k: &mut Vec<f64>,
) -> (usize, f64) {
    match &mode.shape {
        Some(s) => {
            // The best candidate by the rule: the highest MAC, or the least misfit (the
            // MAC then only of the one chosen).
            let misfit = (rule == Pairing::Misfit).then(|| ShapeMisfit::new(mode, s));
            let mut best = (0, f64::INFINITY);
            for k in 0..n_cand {
                let score = match &misfit {
                    None => {
                        gather(readings, k, &s.channels, dphi_k);
                        -mac(&s.values, dphi_k)
                    }
                    Some(m) => m.at(eig.lambda[k], &readings[k]),
                };
                if score < best.1 {
                    best = (k, score);
                }
            }
            if best.1 == f64::INFINITY {
                return (0, f64::NAN);
            }
            gather(readings, best.0, &s.channels, dphi_k);
            (best.0, mac(&s.values, dphi_k))
        }
        // Frequency only: the nearest model eigenvalue.
        None => {
            let k = (0..n_cand)
                .min_by(|&a, &b| {
                    (eig.lambda[a] - mode.lambda)
                        .abs()
                        .total_cmp(&(eig.lambda[b] - mode.lambda).abs())
                })
                .unwrap_or(0);
            (k, f64::NAN)
        }
    }
}

/// The contribution to ε (5) of a measured mode paired with a model mode: its eigenvalue
/// term and its shape term with the optimal scale factor (7), for ranking the candidates.
/// The shape term `Σ((ψ̂ − c Dφ)/σ)²` is expanded as `A − 2cB + c²C` so one pass over the
/// channels gives it with `c`; the cancellation costs ~1e-16·A, far below any difference
/// between two candidates that matters.
struct ShapeMisfit<'a> {
    mode: &'a TargetMode,
    s: &'a TargetShape,
    /// `1/σ²` per entry.
    w: Vec<f64>,
    /// `A = Σ ψ̂²/σ²`.
    a: f64,
}

impl<'a> ShapeMisfit<'a> {
    fn new(mode: &'a TargetMode, s: &'a TargetShape) -> Self {
        let w: Vec<f64> = s.sigma.iter().map(|sd| 1.0 / (sd * sd)).collect();
        let a = s.values.iter().zip(&w).map(|(p, w)| p * p * w).sum();
        Self { mode, s, w, a }
    }

    /// The misfit of a candidate of eigenvalue `lambda` and readings `reading` at every
    /// model channel.
    fn at(&self, lambda: f64, reading: &[f64]) -> f64 {
        let (mut pd, mut dd, mut b, mut c2) = (0.0, 0.0, 0.0, 0.0);
        for ((&ch, &psi), &w) in self.s.channels.iter().zip(&self.s.values).zip(&self.w) {
            let d = reading[ch];
            pd += psi * d;
            dd += d * d;
            b += psi * d * w;
            c2 += d * d * w;
        }
        let c = if dd == 0.0 { 0.0 } else { pd / dd };
        let shape = (self.a - 2.0 * c * b + c * c * c2).max(0.0);
        ((self.mode.lambda - lambda) / self.mode.sigma_lambda).powi(2) + shape
    }
}

#[cfg(test)]
mod tests {
    use super::super::scale_factor;
    use super::*;

    /// The one-pass misfit equals `((λ̂ − λ)/σ_λ)² + Σ((ψ̂ − c Dφ)/σ)²` with `c` of (7)
    /// computed directly, to 1e-12 relative (the expansion's cancellation is ~1e-16·A with
    /// A ≈ 1e3 here), for a close candidate, a far one and one that reads zero.
    #[test]
    fn one_pass_misfit_is_the_direct_sum() {
        let s = TargetShape {
            channels: vec![0, 2, 3, 5],
            values: vec![0.9, -0.4, 0.31, 1.0],
            sigma: vec![0.02, 0.03, 0.025, 0.05],
        };
        let mode = TargetMode {
            lambda: 4.0e4,
            sigma_lambda: 80.0,
            shape: Some(s.clone()),
        };
        let direct = |lambda: f64, reading: &[f64]| {
            let dphi: Vec<f64> = s.channels.iter().map(|&c| reading[c]).collect();
            let c = scale_factor(&s.values, &dphi);
            let shape: f64 = (s.values.iter().zip(&dphi).zip(&s.sigma))
                .map(|((p, d), sd)| ((p - c * d) / sd).powi(2))
                .sum();
            ((mode.lambda - lambda) / mode.sigma_lambda).powi(2) + shape
        };
        let m = ShapeMisfit::new(&mode, &s);
        for (lambda, reading) in [
            (4.01e4, vec![0.45, 7.0, -0.21, 0.16, 9.0, 0.5]),
            (5.0e4, vec![-0.1, 7.0, 0.8, 0.6, 9.0, -0.2]),
            (3.0e4, vec![0.0; 6]),
        ] {
            let (got, want) = (m.at(lambda, &reading), direct(lambda, &reading));
            assert!(
                (got - want).abs() <= 1e-12 * want.abs().max(1.0),
                "{got} vs {want}"
            );
        }
    }
}
