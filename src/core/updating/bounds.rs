//! Bounds of the updating parameters, in the coordinates the solvers step in: `u = ln θ`.
//!
//! A parameter's own `lower`/`upper` (an imported model's published bounds) and the
//! factors of `--bounds` (`lo·nominal … hi·nominal`) both hold, whichever is tighter. A
//! lower bound of 0 is "positive, no other limit": `ln 0 = −∞`, and θ > 0 is kept by the
//! log parameterization itself. Mode matching, the global search and the Bayesian MAP all
//! read their bounds from here, so a parameter "at a bound" means the same in each.

use crate::core::model::Model;

/// Which bound a parameter ended at (`ModeMatchingOptions::bounds`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum AtBound {
    Lower,
    Upper,
}

/// How close (in ln θ) to a bound counts as on it when a result is reported.
pub const AT_BOUND_TOL: f64 = 1e-9;

/// Per parameter, the interval `[lo, hi]` of `u = ln θ` (either end may be infinite).
#[derive(Debug, Clone, PartialEq)]
pub struct LogBounds {
    pub lo: Vec<f64>,
    pub hi: Vec<f64>,
}

impl LogBounds {
    /// The model's bounds intersected with `factors × nominal` (`None`: the model's only).
    pub fn new(model: &Model, factors: Option<(f64, f64)>) -> Self {
        let (lo, hi) = model
            .parameters()
            .iter()
            .map(|par| {
                let (lo, hi) = match factors {
                    Some((lo, hi)) => (lo * par.nominal, hi * par.nominal),
                    None => (0.0, f64::INFINITY),
                };
                (
                    par.lower.map_or(lo, |v| v.max(lo)).ln(),
                    par.upper.map_or(hi, |v| v.min(hi)).ln(),
                )
            })
            .unzip();
        Self { lo, hi }
    }

    /// Unbounded (θ > 0 only), for `p` parameters.
    pub fn none(p: usize) -> Self {
        Self {
            lo: vec![f64::NEG_INFINITY; p],
            hi: vec![f64::INFINITY; p],
        }
    }

    pub fn len(&self) -> usize {
        self.lo.len()
    }

    pub fn is_empty(&self) -> bool {
        self.lo.is_empty()
    }

    /// θ moved into the bounds.
    pub fn clamp(&self, theta: &[f64]) -> Vec<f64> {
        theta
            .iter()
            .enumerate()
            .map(|(i, t)| t.clamp(self.lo[i].exp(), self.hi[i].exp()))
            .collect()
    }

    /// The change `d` of `u_i` cut so that `u_i + d` stays within the bounds.
    pub fn clip(&self, i: usize, u: f64, d: f64) -> f64 {
        (u + d).clamp(self.lo[i], self.hi[i]) - u
    }

    /// Which bound `u_i` is on, within `tol`.
    pub fn side(&self, i: usize, u: f64, tol: f64) -> Option<AtBound> {
        if u >= self.hi[i] - tol {
            Some(AtBound::Upper)
        } else if u <= self.lo[i] + tol {
            Some(AtBound::Lower)
        } else {
            None
        }
    }

    /// Per parameter, the bound θ_i ends at (within [`AT_BOUND_TOL`] in ln θ), if any.
    pub fn at_bound(&self, theta: &[f64]) -> Vec<Option<AtBound>> {
        (0..theta.len())
            .map(|i| self.side(i, theta[i].ln(), AT_BOUND_TOL))
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A lower bound of 0 is −∞ in ln θ: nothing is clamped from below and no parameter is
    /// ever reported at it.
    #[test]
    fn a_zero_lower_bound_is_positivity_only() {
        let b = LogBounds {
            lo: vec![0.0_f64.ln(), 0.5_f64.ln()],
            hi: vec![2.0_f64.ln(), f64::INFINITY],
        };
        assert_eq!(b.clamp(&[1e-30, 0.1]), vec![1e-30, 0.5]);
        assert_eq!(b.at_bound(&[1e-30, 0.5]), vec![None, Some(AtBound::Lower)]);
        assert_eq!(b.at_bound(&[2.0, 1e9]), vec![Some(AtBound::Upper), None]);
        // A step is cut at the bound it would cross, exactly.
        let u = 1.0_f64.ln();
        assert_eq!(b.clip(0, u, 5.0), 2.0_f64.ln());
        assert_eq!(b.clip(0, u, -50.0), -50.0);
    }
}
