//! `plan --verify N`: the plan checked by simulation. N noisy sets as planned (the planned
//! channels and modes, each value with the noise the plan states, drawn) go through the
//! tracker a replay runs, at the planned rate; per connection, the scatter of the sets'
//! estimates is set beside the σ predicted, and the tracker's own verdict (alerts on or
//! off after its commissioning sets) beside the plan's.

use anyhow::{Result, bail};
use chrono::{DateTime, Duration, Utc};
use rand::SeedableRng;
use serde_json::{Value, json};

use super::assess::finite;
use crate::contract::Output;
use crate::contract::modal_set::{MeasuredMode, ModalSet};
use crate::core::plan::Planner;
use crate::core::stats::sample_std;
use crate::pipeline::{Action, Tracker, TrackerConfig};

/// Every set's θ and σ as the tracker estimated them, and its last estimate.
type Tracked = (Vec<Vec<f64>>, Vec<Vec<f64>>, Box<crate::contract::Estimate>);

/// The seed of the drawn noise: the same check gives the same figures.
const SEED: u64 = 7;

/// What is simulated.
pub(crate) struct Check<'a> {
    pub channels: &'a [usize],
    pub modes: &'a [usize],
    pub sets: usize,
    pub per_day: f64,
}

impl Check<'_> {
    /// Simulates and tracks the sets; `planned` is plan.json's assessment of the planned
    /// channels, whose per-set σ the scatter is compared with.
    pub fn run(&self, planner: &Planner, cfg: &TrackerConfig, planned: &Value) -> Result<Value> {
        if (self.sets as u64) <= u64::from(cfg.baseline_sets) {
            bail!(
                "--verify {}: more sets than the tracker's {} commissioning sets are needed \
                 to see whether it turns alerts off",
                self.sets,
                cfg.baseline_sets
            );
        }
        let (thetas, stds, last) = self.track(planner, cfg)?;
        let mut rows = Vec::new();
        for (i, l) in planner.watched().iter().copied().enumerate() {
            let p = &planner.model().parameters()[l];
            let x: Vec<f64> = thetas.iter().map(|t| t[l]).collect();
            let empirical = sample_std(&x) / p.nominal.abs();
            let reported = stds.iter().map(|s| s[l]).sum::<f64>() / stds.len() as f64;
            let n_b = (cfg.baseline_sets as usize).min(stds.len());
            let commissioning = stds[..n_b].iter().map(|s| s[l]).sum::<f64>() / n_b as f64;
            let baseline = last.parameters[l].baseline.unwrap_or(f64::NAN);
            let predicted = planned["connections"][i]["sigma_per_set"]
                .as_f64()
                .unwrap_or(f64::NAN);
            let off = last.parameters[l].alerts_off.clone();
            rows.push(json!({
                "name": p.name,
                "sigma_per_set_predicted": finite(predicted),
                "sigma_per_set_empirical": finite(empirical),
                "ratio": finite(empirical / predicted),
                "sigma_per_set_tracker": finite(reported / p.nominal.abs()),
                "sigma_per_set_commissioning": finite(commissioning / baseline),
                "baseline": finite(baseline / p.nominal),
                "tracker_alerts_off": off,
            }));
        }
        Ok(json!({
            "sets": self.sets,
            "tracked": thetas.len(),
            "seed": SEED,
            "connections": rows,
        }))
    }

    /// The sets simulated and tracked.
    fn track(&self, planner: &Planner, cfg: &TrackerConfig) -> Result<Tracked> {
        let mut thetas = Vec::with_capacity(self.sets);
        let mut stds = Vec::with_capacity(self.sets);
        let mut last = None;
        self.feed(planner, cfg, |e| {
            thetas.push(e.parameters.iter().map(|p| p.theta).collect());
            let std = e.parameters.iter().map(|p| p.std.unwrap_or(f64::NAN));
            stds.push(std.collect());
            last = Some(e);
        })?;
        let Some(last) = last else {
            bail!("--verify: the tracker gave no estimate");
        };
        Ok((thetas, stds, last))
    }

    /// A tracker of `planner`'s model that has tracked the simulated sets, each estimate
    /// handed to `estimate`.
    pub(crate) fn feed(
        &self,
        planner: &Planner,
        cfg: &TrackerConfig,
        mut estimate: impl FnMut(Box<crate::contract::Estimate>),
    ) -> Result<Tracker> {
        let mut tracker = Tracker::new(planner.model().clone(), cfg.clone())?;
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(SEED);
        let start: DateTime<Utc> = "2026-01-01T00:00:00Z".parse()?;
        for k in 0..self.sets {
            let ms = (k as f64 * 86_400_000.0 / self.per_day).round() as i64;
            let time = start + Duration::milliseconds(ms);
            let set = self.set(planner, time, &mut rng);
            let payload = serde_json::to_vec(&set.to_json())?;
            for action in tracker.handle(time, &payload) {
                match action {
                    Action::Publish(Output::Estimate(e)) => estimate(e),
                    Action::Publish(Output::Rejected(r)) => {
                        bail!("--verify: the tracker rejected simulated set {k}: {r:?}")
                    }
                    _ => {}
                }
            }
        }
        Ok(tracker)
    }

    /// One simulated set at `time`.
    fn set(&self, planner: &Planner, time: DateTime<Utc>, rng: &mut impl rand::Rng) -> ModalSet {
        let model = planner.model();
        let noise = planner.noise();
        ModalSet {
            structure: model.name.clone(),
            time,
            channels: self
                .channels
                .iter()
                .map(|&c| model.channels()[c].name.clone())
                .collect(),
            modes: planner
                .draw(self.channels, self.modes, rng)
                .into_iter()
                .map(|(m, sigma)| MeasuredMode {
                    frequency_hz: m.frequency_hz,
                    frequency_cov: Some(noise.frequency_cov),
                    shape_std: Some(vec![Some(sigma); m.shape.len()]),
                    shape: Some(m.shape.into_iter().map(Some).collect()),
                    shape_nsd: Some(noise.shape_nsd),
                    damping_ratio: None,
                    damping_std: None,
                    label: None,
                })
                .collect(),
            temperature_c: None,
            covariates: Default::default(),
            source: Some(format!("boltwatch plan --verify (seed {SEED})")),
            missing: Vec::new(),
            unexplained_peaks: Vec::new(),
        }
    }
}
