//! What would turn a connection's alerts on: the planner's computation
//! ([`crate::core::plan`]) for a tracker whose commissioning left some connections with
//! alerts off.
//!
//! Each such connection's measured mean per-set σ is set beside the σ the planner predicts
//! for the model's channels and the modes the sets carried; their ratio carries the noise
//! the sets actually had over to every other choice. Then, with the same ratio:
//!
//! - **sensors**: candidate places ([`crate::core::plan::places`]) added greedily, each the
//!   one that most lowers the connections' shortfall ([`Criterion`]), until every
//!   connection's alerts would come on (or `max_add` are added); each connection is given
//!   the first sensors after which its own alerts would be on;
//! - **modes**: the fewest of the model's lowest modes, at most `max_modes`, with which its
//!   alerts would be on with the channels installed.

use anyhow::Result;

use super::detectability::Detectability;
use super::{Tracker, alerts_off};
use crate::core::plan::places::WithCandidates;
use crate::core::plan::{Criterion, Planner};
use crate::core::simulate::Noise;

impl Tracker {
    /// The connections whose alerts are off after commissioning (indices into θ), each
    /// with its mean per-set σ over the commissioning sets, relative to its baseline.
    pub fn alerts_off_sigma(&self) -> Vec<(usize, f64)> {
        let st = &self.state;
        let (Some(b), Some(s)) = (&st.baseline, &st.baseline_std) else {
            return Vec::new();
        };
        alerts_off(&self.cfg.alerts, &self.is_connection, st)
            .iter()
            .enumerate()
            .filter(|(_, why)| why.is_some())
            .map(|(l, _)| (l, s[l] / b[l].abs()))
            .collect()
    }
}

/// Candidate channels to add (names), first first, and a connection's σ then (measured
/// scale); `None` when the sensors tried do not turn its alerts on.
pub type Sensors = Option<(Vec<String>, f64)>;

/// A connection with alerts off, and what would turn them on.
#[derive(Debug, Clone, PartialEq)]
pub struct Remedy {
    /// Index into θ.
    pub parameter: usize,
    /// Its mean per-set relative σ over the commissioning sets.
    pub measured: f64,
    /// The relative σ the planner predicts with the channels and modes of the sets.
    pub predicted: f64,
    /// The candidate channels to add, and the σ then; `None` when `max_add` do not do it.
    pub sensors: Sensors,
    /// The number of lowest modes to identify instead, and the σ then; `None` when
    /// `max_modes` do not do it.
    pub modes: Option<(usize, f64)>,
}

impl Remedy {
    /// One line: the σ measured and predicted, and what would turn the alerts on.
    pub fn describe(&self, n_channels: usize, n_modes: usize) -> String {
        let mut out = format!(
            "mean per-set σ {:.2} measured, {:.2} predicted with the {n_channels} channels \
             and {n_modes} modes",
            self.measured, self.predicted
        );
        let mut ways = Vec::new();
        if let Some((names, after)) = &self.sensors {
            ways.push(format!("sensors at {} (σ {after:.2})", names.join(", ")));
        }
        if let Some((k, after)) = self.modes {
            ways.push(format!("the lowest {k} modes identified (σ {after:.2})"));
        }
        if ways.is_empty() {
            out += "; neither the sensors nor the modes tried turn its alerts on";
        } else {
            out += &format!("; alerts come on with {}", ways.join(", or "));
        }
        out
    }
}

/// What the advice may propose.
#[derive(Debug, Clone, Copy)]
pub struct Limits {
    pub max_add: usize,
    pub max_modes: usize,
}

/// The remedies of the connections `off` (index into θ, measured mean per-set relative σ),
/// for sets that carried `n_modes` modes at the model's own channels `installed` (indices
/// into `with.model`'s channels), stated with `noise`.
pub fn remedies(
    with: &WithCandidates,
    installed: &[usize],
    n_modes: usize,
    noise: Noise,
    rules: &Detectability,
    off: &[(usize, f64)],
    limits: Limits,
) -> Result<Vec<Remedy>> {
    let max_modes = limits
        .max_modes
        .max(n_modes)
        .min(with.model.n_finite_modes());
    let mut planner = Planner::new(with.model.clone(), max_modes, noise)?.with_reference(installed);
    let modes: Vec<usize> = (0..n_modes).collect();
    let sigma = planner.sigma(installed, &modes)?;
    let scaled = Scaled::new(&planner, &sigma, off);
    let sensors = by_sensors(
        &mut planner,
        with,
        installed,
        &modes,
        rules,
        &scaled,
        limits,
    )?;
    let mut out = Vec::with_capacity(off.len());
    for (i, &(parameter, measured)) in off.iter().enumerate() {
        let modes = by_modes(
            &mut planner,
            installed,
            n_modes,
            max_modes,
            rules,
            &scaled,
            i,
        )?;
        out.push(Remedy {
            parameter,
            measured,
            predicted: scaled.predicted[i],
            sensors: sensors[i].clone(),
            modes,
        });
    }
    Ok(out)
}

/// The connections' predicted relative σ with the installed data and the ratio that takes
/// a prediction to the noise the sets had (1 where the prediction is not finite).
struct Scaled {
    theta0: Vec<f64>,
    parameters: Vec<usize>,
    predicted: Vec<f64>,
    ratio: Vec<f64>,
}

impl Scaled {
    fn new(planner: &Planner, sigma: &[f64], off: &[(usize, f64)]) -> Self {
        let theta0 = planner.model().nominal_theta();
        let predicted: Vec<f64> = off
            .iter()
            .map(|&(l, _)| sigma[l] / theta0[l].abs())
            .collect();
        let ratio = off
            .iter()
            .zip(&predicted)
            .map(|(&(_, m), &p)| {
                let r = m / p;
                if r.is_finite() && r > 0.0 { r } else { 1.0 }
            })
            .collect();
        Self {
            theta0,
            parameters: off.iter().map(|&(l, _)| l).collect(),
            predicted,
            ratio,
        }
    }

    /// The connections' relative σ at the sets' noise from a prediction `sigma`.
    fn of(&self, sigma: &[f64]) -> Vec<f64> {
        self.parameters
            .iter()
            .zip(&self.ratio)
            .map(|(&l, r)| {
                let rel = r * sigma[l] / self.theta0[l].abs();
                if rel.is_finite() { rel } else { f64::INFINITY }
            })
            .collect()
    }
}

/// The greedy additions from the candidate places, and per connection the first of them
/// after which its alerts would be on, with its σ then.
fn by_sensors(
    planner: &mut Planner,
    with: &WithCandidates,
    installed: &[usize],
    modes: &[usize],
    rules: &Detectability,
    scaled: &Scaled,
    limits: Limits,
) -> Result<Vec<Sensors>> {
    let model = planner.model().clone();
    let mut left: Vec<usize> = with
        .candidates
        .iter()
        .filter_map(|n| model.channel_index(n))
        .filter(|c| !installed.contains(c) && planner.moves(*c, modes))
        .collect();
    let criterion = Criterion {
        needed: bound(rules),
    };
    let mut chosen = installed.to_vec();
    let mut out: Vec<Sensors> = vec![None; scaled.parameters.len()];
    for _ in 0..limits.max_add.min(left.len()) {
        let mut best: Option<(usize, [f64; 4], Vec<f64>)> = None;
        for (i, &c) in left.iter().enumerate() {
            chosen.push(c);
            let rel = scaled.of(&planner.sigma(&chosen, modes)?);
            chosen.pop();
            let score = criterion.score(&rel);
            if best.as_ref().is_none_or(|(_, b, _)| score < *b) {
                best = Some((i, score, rel));
            }
        }
        let Some((i, _, rel)) = best else { break };
        chosen.push(left.remove(i));
        for (slot, &r) in out.iter_mut().zip(&rel) {
            if slot.is_none() && rules.alerts_on(r) {
                let names = chosen[installed.len()..]
                    .iter()
                    .map(|&c| model.channels()[c].name.clone())
                    .collect();
                *slot = Some((names, r));
            }
        }
        if out.iter().all(Option::is_some) {
            break;
        }
    }
    Ok(out)
}

/// The fewest lowest modes, more than `n_modes` and at most `max_modes`, with which
/// connection `i` of `scaled` would have its alerts on, with its σ then.
fn by_modes(
    planner: &mut Planner,
    installed: &[usize],
    n_modes: usize,
    max_modes: usize,
    rules: &Detectability,
    scaled: &Scaled,
    i: usize,
) -> Result<Option<(usize, f64)>> {
    for k in n_modes + 1..=max_modes {
        let modes: Vec<usize> = (0..k).collect();
        let rel = scaled.of(&planner.sigma(installed, &modes)?)[i];
        if rules.alerts_on(rel) {
            return Ok(Some((k, rel)));
        }
    }
    Ok(None)
}

/// The largest per-set relative σ at which alerts stay on ([`Detectability::alerts_on`]),
/// by bisection.
fn bound(rules: &Detectability) -> f64 {
    let (mut lo, mut hi) = (0.0, rules.thresholds.max_std);
    for _ in 0..60 {
        let mid = 0.5 * (lo + hi);
        if rules.alerts_on(mid) {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    lo
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::model::Model;
    use crate::core::plan::places::{Places, with_candidates};

    const NOISE: Noise = Noise {
        frequency_cov: 0.01,
        shape_nsd: 0.05,
    };

    fn rules() -> Detectability {
        let s = crate::settings::Settings::load(None).unwrap();
        Detectability::of(&s.tracker, 4.0)
    }

    /// The lab frame with every fourth of its channels and 5 modes, its connections with
    /// alerts off measured exactly as predicted: every one is given sensors, and with
    /// them its alerts are on; one measured twice as noisy as predicted needs at least as
    /// many sensors.
    #[test]
    fn connections_with_alerts_off_are_given_sensors() {
        let path = std::path::Path::new("bundled:lab-frame");
        let spec = crate::io::model::load_spec(path).unwrap();
        let base = Model::from_spec(&spec).unwrap();
        let with = with_candidates(Some(&spec), &base, Places::All).unwrap();
        let installed: Vec<usize> = (0..base.channels().len()).step_by(4).collect();
        let rules = rules();
        let modes: Vec<usize> = (0..5).collect();
        let mut planner = Planner::new(with.model.clone(), 5, NOISE)
            .unwrap()
            .with_reference(&installed);
        let sigma = planner.sigma(&installed, &modes).unwrap();
        let rel = planner.relative(&sigma);
        let off: Vec<(usize, f64)> = planner
            .watched()
            .iter()
            .zip(&rel)
            .filter(|(_, r)| r.is_finite() && !rules.alerts_on(**r))
            .map(|(&l, &r)| (l, r))
            .take(3)
            .collect();
        assert!(!off.is_empty(), "{rel:?}");
        let limits = Limits {
            max_add: 20,
            max_modes: 10,
        };
        let as_predicted = remedies(&with, &installed, 5, NOISE, &rules, &off, limits).unwrap();
        for r in &as_predicted {
            assert!((r.predicted - r.measured).abs() <= 1e-9 * r.measured);
            let (names, after) = r.sensors.clone().expect("sensors within 20");
            assert!(!names.is_empty() && rules.alerts_on(after), "{r:?}");
        }
        let noisier: Vec<(usize, f64)> = off.iter().map(|&(l, m)| (l, 2.0 * m)).collect();
        let twice = remedies(&with, &installed, 5, NOISE, &rules, &noisier, limits).unwrap();
        for (a, b) in as_predicted.iter().zip(&twice) {
            let n = |r: &Remedy| r.sensors.as_ref().map_or(usize::MAX, |s| s.0.len());
            assert!(n(b) >= n(a), "{a:?} then {b:?}");
        }
    }
}
