//! What the tracker makes of a connection whose estimate has a given relative σ per set:
//! whether it keeps the connection's alerts on, and how small a loss its warning and alarm
//! catch. Used to plan the instrumentation before installation (`boltwatch plan`) and to
//! say at start-up why a connection's alerts are off and what would turn them on.
//!
//! Both follow the tracker's own rules, with the thresholds of `[tracker.alerts]` and the
//! drift filter of `[tracker.drift]` ([`super::drift`]):
//!
//! - **Alerts on.** After its commissioning sets the tracker turns a connection's alerts
//!   off when the mean per-set σ over those sets is above `max_std` of the baseline
//!   (`alerts_off`). The baseline is itself the filter's level after those sets, with the
//!   filter's σ `s_b`, so a σ just under `max_std` is turned off whenever the baseline
//!   comes out low. Alerts count as on when they stay on at the thresholds' confidence:
//!   `rel ≤ max_std · (1 − z·s_b)`.
//! - **Loss caught.** A `drop` threshold reports a loss `f` when the filtered level is
//!   below `1 − drop` at the thresholds' confidence: once `f ≥ drop + z·s_S`, with `s_S`
//!   the filter's σ after `S` sets at the identification rate. The filter's σ comes from
//!   the filter itself, fed `S` estimates of that σ at that rate (its trend makes it
//!   larger than `rel/√S`).

use super::alerts::AlertThresholds;
use super::drift::{DriftFilter, DriftNoise};
use crate::core::stats::inverse_normal_cdf;

/// The tracker's rules of alerts, with the rate sets arrive at.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Detectability {
    pub thresholds: AlertThresholds,
    pub drift: DriftNoise,
    /// Commissioning sets (`baseline_sets`).
    pub baseline_sets: u32,
    /// Sets identified per day.
    pub per_day: f64,
}

impl Detectability {
    /// The rules of a tracker configured by `cfg`, with sets arriving `per_day` a day.
    pub fn of(cfg: &super::TrackerConfig, per_day: f64) -> Self {
        Self {
            thresholds: cfg.alerts,
            drift: cfg.drift,
            baseline_sets: cfg.baseline_sets,
            per_day,
        }
    }

    /// The z of the thresholds' confidence.
    pub fn z(&self) -> f64 {
        inverse_normal_cdf(self.thresholds.confidence)
    }

    /// The filter's relative σ of the level after `n` estimates of relative σ `rel`, one
    /// every `1/per_day` days (module docs).
    pub fn filtered(&self, rel: f64, n: usize) -> f64 {
        if !rel.is_finite() {
            return f64::INFINITY;
        }
        let mut filter = DriftFilter::new(1.0, self.drift);
        let mut std = rel;
        for k in 0..n.max(1) {
            std = filter.observe(k as f64 / self.per_day, 1.0, rel * rel).std;
        }
        std
    }

    /// Whether the tracker keeps alerts on for a connection of per-set relative σ `rel`,
    /// at the thresholds' confidence (module docs).
    pub fn alerts_on(&self, rel: f64) -> bool {
        let s_b = self.filtered(rel, self.baseline_sets as usize);
        rel.is_finite() && rel <= self.thresholds.max_std * (1.0 - self.z() * s_b)
    }

    /// The smallest loss a `drop` threshold reports at the thresholds' confidence after
    /// `sets` estimates of per-set relative σ `rel`.
    pub fn detectable(&self, drop: f64, rel: f64, sets: usize) -> f64 {
        drop + self.z() * self.filtered(rel, sets)
    }

    /// Whether alerts stay on and the warning catches a loss of `target` within `sets`.
    pub fn watchable(&self, rel: f64, sets: usize, target: f64) -> bool {
        self.alerts_on(rel) && self.detectable(self.thresholds.warning_drop, rel, sets) <= target
    }

    /// The largest per-set relative σ that is [`Detectability::watchable`] (zero when
    /// none is): both conditions only tighten as σ grows, so it is found by bisection.
    pub fn needed(&self, sets: usize, target: f64) -> f64 {
        let (mut lo, mut hi) = (0.0, self.thresholds.max_std);
        if self.watchable(hi, sets, target) {
            return hi;
        }
        for _ in 0..60 {
            let mid = 0.5 * (lo + hi);
            if self.watchable(mid, sets, target) {
                lo = mid;
            } else {
                hi = mid;
            }
        }
        lo
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rules() -> Detectability {
        Detectability {
            thresholds: AlertThresholds::default(),
            drift: DriftNoise::default(),
            baseline_sets: 20,
            per_day: 4.0,
        }
    }

    /// Without process noise and with the trend known (a long run), the level of n equal
    /// estimates is their mean: σ/√n. The trend the filter learns makes its σ larger.
    #[test]
    fn the_filtered_sigma_is_at_least_that_of_the_mean() {
        let d = rules();
        for n in [1, 5, 20, 100] {
            let s = d.filtered(0.2, n);
            let mean = 0.2 / (n as f64).sqrt();
            assert!(s >= mean * (1.0 - 1e-9), "{n}: {s} against {mean}");
        }
        assert!((d.filtered(0.2, 1) - 0.2).abs() < 1e-12);
        assert!(d.filtered(f64::INFINITY, 5).is_infinite());
    }

    /// `needed` is the edge: just under it watchable, just over not.
    #[test]
    fn needed_is_the_edge_of_watchable() {
        let d = rules();
        let n = d.needed(20, 0.2);
        assert!(n > 0.0 && n < d.thresholds.max_std, "{n}");
        assert!(d.watchable(n * 0.999, 20, 0.2));
        assert!(!d.watchable(n * 1.001, 20, 0.2));
        // A target below the warning threshold cannot be met.
        assert_eq!(d.needed(20, 0.05), 0.0);
    }
}
