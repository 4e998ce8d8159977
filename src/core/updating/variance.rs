//! Weights the data can support: one variance scale per data group, estimated from the
//! data when the stated uncertainties cannot explain the misfit.
//!
//! The groups are the measured eigenvalues (one group) and the shape of each measured mode
//! (one group per mode). Under the stated `Σ_M` (28), ε far above its χ² bound says the
//! stated σ are too small or the model lacks an effect; with several hundred shape entries
//! against a handful of frequencies, a fit under those weights trades a frequency error of
//! many σ for a little MAC (the SMU footbridge: +14 % on the first mode for MAC 0.98
//! instead of 0.93).
//!
//! Each mode's shape group gets the maximum-likelihood variance factor of its prediction
//! error at the fit (Yuen & Beck, "Updating properties of nonlinear dynamical systems with
//! uncertain input", J. Eng. Mech. 2003; Yuen, *Bayesian Methods for Structural Dynamics
//! and Civil Engineering*, 2010, §3.3): `s_g² = ε_g / n_g`, its misfit under the stated σ
//! over its entry count, never below 1 (the stated σ are a lower bound on the uncertainty:
//! a group that fits within them keeps them). The frequencies keep their stated σ: they are
//! identified an order more precisely than shapes, and a model's frequency error is what
//! its adequacy is judged on (Friswell & Mottershead, *Finite Element Model Updating in
//! Structural Dynamics*, 1995, §1.3), while a shape's stated σ (the identification's own)
//! leave out the errors of a model shape that the parameters cannot express. Let the
//! frequencies be rescaled too and the footbridge's 5 frequencies yield to its 290 shape
//! entries again: its misfit-14 % point has the higher likelihood.
//!
//! Fit and factors are iterated to a fixed point (iteratively reweighted variance
//! components). Fixed points are compared by `J_w = Σ_g ε_g/s_g² + n_g ln s_g²`, minus
//! twice the log-likelihood at the factors ([`weighted_objective`]). The verdict on the
//! model (ε against its χ² bound) stays with the stated σ.

use super::data::MeasuredData;

/// The factors have settled when none changes by more than this (relative) in an outer
/// iteration.
pub const SCALE_TOL: f64 = 0.01;

/// Outer iterations (fit, then factors) at most.
pub const MAX_OUTER: usize = 12;

/// One data group and its factor.
#[derive(Debug, Clone, PartialEq)]
pub struct GroupScale {
    /// Index of the group: 0 the eigenvalues, `1 + m` the shape of mode m.
    pub group: usize,
    /// `frequencies`, or `shape of mode m` (1-based).
    pub name: String,
    /// Entries of the residual in the group.
    pub n: usize,
    /// Its misfit under the stated σ at the fit.
    pub misfit: f64,
    /// The factor its stated σ are multiplied by (≥ 1).
    pub scale: f64,
}

/// The group of every residual entry, in the residual's order (eigenvalue of mode m, then
/// its shape entries): 0 for the eigenvalues, `1 + m` for the shape of mode m.
pub fn group_of_rows(data: &MeasuredData) -> Vec<usize> {
    let mut rows = Vec::with_capacity(data.n_data());
    for (m, mode) in data.modes.iter().enumerate() {
        rows.push(0);
        if let Some(s) = &mode.shape {
            rows.extend(std::iter::repeat_n(1 + m, s.values.len()));
        }
    }
    rows
}

/// The groups with their misfits under the stated σ, given the whitened residual `r` of
/// data scaled by `scales` (one per group: `r_i · s_g` is the stated residual), and the
/// new factors: `max(1, √(ε_g / n_g))` for a shape group, 1 for the frequencies (module
/// docs). Shape groups of modes without a shape are left out.
pub fn estimate(data: &MeasuredData, r: &[f64], scales: &[f64]) -> Vec<GroupScale> {
    let rows = group_of_rows(data);
    let mut n = vec![0usize; scales.len()];
    let mut misfit = vec![0.0; scales.len()];
    for (i, &g) in rows.iter().enumerate() {
        n[g] += 1;
        misfit[g] += (r[i] * scales[g]).powi(2);
    }
    (0..scales.len())
        .filter(|&g| n[g] > 0)
        .map(|g| GroupScale {
            group: g,
            name: if g == 0 {
                "frequencies".into()
            } else {
                format!("shape of mode {g}")
            },
            n: n[g],
            misfit: misfit[g],
            // The frequencies keep their stated σ (module docs).
            scale: if g == 0 {
                1.0
            } else {
                (misfit[g] / n[g] as f64).sqrt().max(1.0)
            },
        })
        .collect()
}

impl MeasuredData {
    /// Number of groups (module docs): 1 + the number of modes.
    pub fn n_groups(&self) -> usize {
        1 + self.modes.len()
    }

    /// The data with every σ of group g multiplied by `scales[g]`.
    pub fn rescaled(&self, scales: &[f64]) -> MeasuredData {
        let mut out = self.clone();
        for (m, mode) in out.modes.iter_mut().enumerate() {
            mode.sigma_lambda *= scales[0];
            if let Some(s) = &mut mode.shape {
                for sd in &mut s.sigma {
                    *sd *= scales[1 + m];
                }
            }
        }
        out
    }
}

/// The factors per group (indexed as [`group_of_rows`]) from [`estimate`]'s list, 1 where
/// a group is absent.
pub fn factors(data: &MeasuredData, groups: &[GroupScale]) -> Vec<f64> {
    let mut out = vec![1.0; data.n_groups()];
    for g in groups {
        out[g.group] = g.scale;
    }
    out
}

/// `J_w = Σ_g ε_g/s_g² + n_g ln s_g²` of the groups at their factors: minus twice the
/// log-likelihood of the data under the rescaled σ, up to a constant (module docs).
pub fn weighted_objective(groups: &[GroupScale]) -> f64 {
    groups
        .iter()
        .map(|g| {
            let s2 = g.scale * g.scale;
            g.misfit / s2 + g.n as f64 * s2.ln()
        })
        .sum()
}

/// A fit under data-supported weights.
#[derive(Debug, Clone)]
pub struct Rescaled {
    /// The fit under the rescaled σ (its ε, covariance (15) and first-order check are those
    /// of the rescaled problem).
    pub result: super::ModeMatchingResult,
    /// The groups, their misfits under the stated σ at the fit and their factors.
    pub groups: Vec<GroupScale>,
    /// The factor per group the fit used.
    pub scales: Vec<f64>,
    /// ε (5) under the stated σ at the fit.
    pub stated_epsilon: f64,
    /// Outer iterations (fits) it took.
    pub outer: usize,
    /// [`weighted_objective`] at the fit.
    pub objective: f64,
}

impl Rescaled {
    /// A fit under the stated σ, in the same form: every factor 1, `J_w = ε`.
    pub fn stated(data: &MeasuredData, result: super::ModeMatchingResult) -> Self {
        let ones = vec![1.0; data.n_groups()];
        let groups: Vec<GroupScale> = estimate(data, &result.last.r, &ones)
            .into_iter()
            .map(|mut g| {
                g.scale = 1.0;
                g
            })
            .collect();
        Self {
            stated_epsilon: result.epsilon(),
            objective: result.epsilon(),
            result,
            groups,
            scales: ones,
            outer: 1,
        }
    }
}

impl super::ModeMatching {
    /// The fit and the group factors iterated to their fixed point (module docs), from θ
    /// and the factors `scales` (1 for the stated σ), in at most `max_outer` fits.
    pub fn run_rescaled(
        &mut self,
        model: &crate::core::model::Model,
        data: &MeasuredData,
        theta: &[f64],
        scales: &[f64],
        opts: &super::ModeMatchingOptions,
        max_outer: usize,
    ) -> Result<Rescaled, super::UpdateError> {
        let mut scales = scales.to_vec();
        let mut theta = theta.to_vec();
        let max_outer = max_outer.max(1);
        for outer in 1..=max_outer {
            let result = self.run(model, &data.rescaled(&scales), &theta, opts)?;
            let groups = estimate(data, &result.last.r, &scales);
            let new = factors(data, &groups);
            let settled = (new.iter().zip(&scales)).all(|(a, b)| (a / b - 1.0).abs() <= SCALE_TOL);
            if settled || outer == max_outer {
                // J_w at the factors the fit used (a fixed point: the new ones, to SCALE_TOL).
                let at_fit: Vec<GroupScale> = (groups.iter().cloned())
                    .map(|mut g| {
                        g.scale = scales[g.group];
                        g
                    })
                    .collect();
                return Ok(Rescaled {
                    objective: weighted_objective(&at_fit),
                    stated_epsilon: groups.iter().map(|g| g.misfit).sum(),
                    result,
                    groups,
                    scales,
                    outer,
                });
            }
            scales = new;
            theta = result.theta;
        }
        unreachable!("the loop returns at its last iteration")
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::updating::data::{TargetMode, TargetShape, Weighting};

    fn two_modes() -> MeasuredData {
        let shape = |n: usize| TargetShape {
            channels: (0..n).collect(),
            values: vec![1.0; n],
            sigma: vec![0.1; n],
        };
        MeasuredData {
            modes: vec![
                TargetMode {
                    lambda: 100.0,
                    sigma_lambda: 2.0,
                    shape: Some(shape(3)),
                },
                TargetMode {
                    lambda: 400.0,
                    sigma_lambda: 8.0,
                    shape: None,
                },
            ],
            weighting: Weighting::Covariance,
        }
    }

    /// Residual rows: λ1, ψ1 (3), λ2. The shape's 3·0.5²/3 = 0.25 < 1 → kept at 1; a mode
    /// without a shape has no shape group.
    #[test]
    fn factors_are_the_rms_misfit_per_group_floored_at_one() {
        let data = two_modes();
        assert_eq!(group_of_rows(&data), vec![0, 1, 1, 1, 0]);
        let r = [2.0, 0.5, -0.5, 0.5, 4.0];
        let groups = estimate(&data, &r, &[1.0, 1.0, 1.0]);
        assert_eq!(groups.len(), 2);
        // The frequencies keep their σ, whatever their misfit.
        assert_eq!(
            (groups[0].n, groups[0].misfit, groups[0].scale),
            (2, 20.0, 1.0)
        );
        assert_eq!((groups[1].n, groups[1].scale), (3, 1.0));
        // A shape group misfitting by 4× its entry count: σ × 2.
        let r4 = [2.0, 2.0, -2.0, 2.0, 4.0];
        let g4 = estimate(&data, &r4, &[1.0, 1.0, 1.0]);
        assert_eq!((g4[1].misfit, g4[1].scale), (12.0, 2.0));
        // J_w = 20 + (12/4 + 3 ln 4).
        assert!((weighted_objective(&g4) - (23.0 + 3.0 * 4.0_f64.ln())).abs() < 1e-12);
        // Residuals of data already scaled by 2 are half the stated ones.
        let half: Vec<f64> = r.iter().map(|v| v / 2.0).collect();
        let again = estimate(&data, &half, &[2.0, 2.0, 2.0]);
        assert_eq!(again[0].misfit, 20.0);
        let f = factors(&data, &g4);
        assert_eq!(f, vec![1.0, 2.0, 1.0]);
        let scaled = data.rescaled(&f);
        assert_eq!(scaled.modes[1].sigma_lambda, 8.0);
        assert_eq!(scaled.modes[0].shape.as_ref().unwrap().sigma, vec![0.2; 3]);
    }
}
