//! Is a modal set within what the model can produce at all? A check in two eigen solves,
//! before any fit, so that a set in the wrong unit, of another structure or from a broken
//! channel map is refused at once instead of after a long globalized fit that cannot
//! succeed.
//!
//! With `K(θ) = K₀ + Σ θ_l K_l`, every `K_l ⪰ 0` and `M` fixed, each eigenvalue `λ_j(θ)` is
//! non-decreasing in every `θ_l` (Courant–Fischer: `K(θ') − K(θ) ⪰ 0` when `θ' ≥ θ`
//! componentwise; Parlett, *The Symmetric Eigenvalue Problem*, §10.1). Over the box of the
//! bounds `lo ≤ θ ≤ hi` therefore `λ_j(lo) ≤ λ_j(θ) ≤ λ_j(hi)`. The `j`-th lowest measured
//! eigenvalue is paired with a model mode of index `j` or above, so it cannot be below
//! `λ_j(lo)`; every measured mode is paired among the lowest `N` candidates, so none can be
//! above `λ_N(hi)`.
//!
//! The `K_l` of connections (2), member moduli and springs are positive semidefinite by
//! construction; those of an imported model are whatever the files hold, so no range is
//! claimed for a model with imported stiffness parameters.

use super::bounds::LogBounds;
use super::data::MeasuredData;
use crate::core::modal::{ModalError, solver_for};
use crate::core::model::{Model, ParameterKind};

/// How far outside the model's range a frequency may be before the set is refused: a
/// factor of two in frequency. The range is that of θ at its bounds (by default 10⁻³ to
/// 10³ times nominal, so frequencies over a factor of ~30 either way), so a set beyond it
/// by a further factor of two is not a loosening or a season but a wrong unit, structure or
/// channel map; the factor also covers the model's own error in mass.
pub const RANGE_FACTOR: f64 = 2.0;

/// The lowest `n` eigenvalues (rad²/s²) of the model with every parameter at its lower
/// bound and at its upper bound.
#[derive(Debug, Clone)]
pub struct EigenRange {
    pub lo: Vec<f64>,
    pub hi: Vec<f64>,
}

impl EigenRange {
    /// The range of the lowest `n` eigenvalues over the box of `bounds`, by two cold
    /// solves on a solver of its own. `None` when it is not bounded on both sides or a
    /// parameter's `K_l` is not known to be semidefinite (imported matrices).
    pub fn new(model: &Model, bounds: &LogBounds, n: usize) -> Result<Option<Self>, ModalError> {
        let imported = model
            .parameters()
            .iter()
            .any(|p| matches!(p.kind, ParameterKind::Matrix(_)));
        let finite = |v: &[f64]| v.iter().all(|x| x.is_finite());
        if imported || !finite(&bounds.lo) || !finite(&bounds.hi) {
            return Ok(None);
        }
        let at = |ln: &[f64]| ln.iter().map(|x| x.exp()).collect::<Vec<_>>();
        let mut solver = solver_for(model)?;
        let lo = solver.solve(model, &at(&bounds.lo), n)?.lambda;
        let hi = solver.solve(model, &at(&bounds.hi), n)?.lambda;
        Ok(Some(Self { lo, hi }))
    }

    /// Modes of the range.
    pub fn len(&self) -> usize {
        self.lo.len()
    }

    /// Whether the range holds no mode.
    pub fn is_empty(&self) -> bool {
        self.lo.is_empty()
    }

    /// Why `data` cannot come from the model within its bounds (module docs), its modes
    /// paired among the lowest `n` candidates (at most `self.len()`); `None` when it can.
    /// Frequencies are compared with [`RANGE_FACTOR`] of slack.
    pub fn implausible(&self, data: &MeasuredData, n: usize) -> Option<String> {
        let n = n.min(self.len());
        if n == 0 {
            return None;
        }
        let mut hz: Vec<f64> = data.modes.iter().map(|m| hz_of(m.lambda)).collect();
        hz.sort_by(f64::total_cmp);
        for (j, &f) in hz.iter().enumerate().take(n) {
            let floor = hz_of(self.lo[j]);
            if f * RANGE_FACTOR < floor {
                return Some(format!(
                    "the set's {} lowest frequency, {f:.6} Hz, is far below anything the model \
                     can have there: its mode {} is at {floor:.4} Hz with every parameter at \
                     its lower bound (a wrong unit, structure or channel map?)",
                    ordinal(j + 1),
                    j + 1
                ));
            }
        }
        let ceiling = hz_of(self.hi[n - 1]);
        match hz.last() {
            Some(&f) if f > RANGE_FACTOR * ceiling => Some(format!(
                "the set's highest frequency, {f:.4} Hz, is far above anything the model can \
                 pair it with: its mode {n} is at {ceiling:.4} Hz with every parameter at its \
                 upper bound (a wrong unit, structure or channel map?)"
            )),
            _ => None,
        }
    }
}

fn hz_of(lambda: f64) -> f64 {
    lambda.max(0.0).sqrt() / (2.0 * std::f64::consts::PI)
}

fn ordinal(k: usize) -> String {
    let suffix = match (k % 10, k % 100) {
        (1, r) if r != 11 => "st",
        (2, r) if r != 12 => "nd",
        (3, r) if r != 13 => "rd",
        _ => "th",
    };
    format!("{k}{suffix}")
}

#[cfg(test)]
mod tests {
    use super::*;

    impl EigenRange {
        fn implausible_all(&self, data: &MeasuredData) -> Option<String> {
            self.implausible(data, self.len())
        }
    }

    fn range() -> EigenRange {
        EigenRange {
            lo: vec![100.0, 400.0, 900.0],
            hi: vec![1e4, 4e4, 9e4],
        }
    }

    fn data(hz: &[f64]) -> MeasuredData {
        use super::super::data::RawMode;
        let raw: Vec<RawMode> = hz
            .iter()
            .map(|&f| RawMode {
                frequency_hz: f,
                frequency_cov: Some(0.01),
                shape: None,
                shape_nsd: None,
                shape_std: None,
            })
            .collect();
        MeasuredData::new(&raw, 1.0)
    }

    #[test]
    fn a_set_inside_the_range_or_within_its_slack_passes() {
        let r = range();
        let f1 = hz_of(100.0);
        assert!(r.implausible_all(&data(&[f1, 2.0 * f1])).is_none());
        // Half the floor is the limit (RANGE_FACTOR), just inside.
        assert!(r.implausible_all(&data(&[0.51 * f1])).is_none());
        assert!(r.implausible_all(&data(&[1.9 * hz_of(9e4)])).is_none());
    }

    #[test]
    fn a_set_far_below_or_above_is_refused_with_the_mode_named() {
        let r = range();
        let why = r.implausible_all(&data(&[1e-3, 5.0])).unwrap();
        assert!(why.contains("1st lowest frequency, 0.001000 Hz"), "{why}");
        // The lowest (0.9 Hz) within a factor of two of mode 1's floor (1.59 Hz), the
        // second (1.2 Hz) not of mode 2's (3.18 Hz at λ = 400).
        let why = r.implausible_all(&data(&[0.9, 1.2])).unwrap();
        assert!(
            why.contains("2nd lowest") && why.contains("3.1831 Hz"),
            "{why}"
        );
        let why = r
            .implausible_all(&data(&[hz_of(100.0), 2.1 * hz_of(9e4)]))
            .unwrap();
        assert!(
            why.contains("highest frequency") && why.contains("mode 3"),
            "{why}"
        );
    }
}
