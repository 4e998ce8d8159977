//! What the plan says of a choice of channels: per connection, σ, whether alerts are on,
//! the smallest loss caught; the modes' value; the baselines a placement is judged
//! against; plan.json and the lines printed.

use std::collections::BTreeMap;

use anyhow::Result;
use serde_json::{Value, json};

use super::PlanArgs;
use crate::core::model::Model;
use crate::core::plan::{Added, Planner};
use crate::pipeline::detectability::Detectability;

/// What the tracker's rules make of a σ, with the filter's sets and the target loss.
pub(super) struct Judge {
    pub rules: Detectability,
    pub sets: usize,
    pub target: f64,
}

impl Judge {
    /// Whether a connection of per-set relative σ `rel` keeps its alerts and its warning
    /// catches the target loss.
    pub fn watchable(&self, rel: f64) -> bool {
        self.rules.watchable(rel, self.sets, self.target)
    }

    /// The largest per-set relative σ that is watchable.
    pub fn needed(&self) -> f64 {
        self.rules.needed(self.sets, self.target)
    }

    /// Whether every connection of relative σ `rel` is watchable.
    pub fn all_watchable(&self, rel: &[f64]) -> bool {
        rel.iter().all(|&r| self.watchable(r))
    }
}

/// Per connection of `channels`: σ per set and after the filter's sets, relative; alerts
/// on or off; the smallest loss the warning and the alarm report; and the connections
/// resolved only together (correlation over 0.9).
fn assess(
    planner: &mut Planner,
    judge: &Judge,
    channels: &[usize],
    modes: &[usize],
) -> Result<Value> {
    let (sigma, corr) = planner.sigma_and_correlation(channels, modes)?;
    let params = planner.watched().to_vec();
    let model = planner.model();
    let (d, t) = (&judge.rules, &judge.rules.thresholds);
    let mut rows = Vec::new();
    let mut worst = 0.0_f64;
    for l in params {
        let p = &model.parameters()[l];
        let rel = sigma[l] / p.nominal.abs();
        let s = d.filtered(rel, judge.sets);
        worst = worst.max(if rel.is_finite() { rel } else { f64::INFINITY });
        rows.push(json!({
            "name": p.name,
            "sigma_per_set": finite(rel),
            "sigma_after_sets": finite(s),
            "alerts_off": !d.alerts_on(rel),
            "detectable_warning": finite(d.detectable(t.warning_drop, rel, judge.sets)),
            "detectable_alarm": finite(d.detectable(t.alarm_drop, rel, judge.sets)),
            "watchable": judge.watchable(rel),
        }));
    }
    Ok(json!({
        "channels": channels.iter().map(|&c| model.channels()[c].name.clone()).collect::<Vec<_>>(),
        "worst_sigma_per_set": finite(worst),
        "connections": rows,
        "resolved_together": clusters(model, planner.watched(), &corr, 0.9),
    }))
}

/// A JSON number, or null when not finite.
pub(super) fn finite(v: f64) -> Value {
    if v.is_finite() { json!(v) } else { Value::Null }
}

/// Groups of connections linked by a correlation of magnitude at least `limit`.
fn clusters(
    model: &Model,
    params: &[usize],
    corr: &Option<faer::Mat<f64>>,
    limit: f64,
) -> Vec<Vec<String>> {
    let Some(c) = corr else {
        return Vec::new();
    };
    let mut group: Vec<usize> = (0..params.len()).collect();
    let find = |g: &Vec<usize>, mut i: usize| {
        while g[i] != i {
            i = g[i];
        }
        i
    };
    for a in 0..params.len() {
        for b in a + 1..params.len() {
            if c[(params[a], params[b])].abs() >= limit {
                let (ra, rb) = (find(&group, a), find(&group, b));
                group[ra.max(rb)] = ra.min(rb);
            }
        }
    }
    let mut out: BTreeMap<usize, Vec<String>> = BTreeMap::new();
    for (i, &l) in params.iter().enumerate() {
        out.entry(find(&group, i))
            .or_default()
            .push(model.parameters()[l].name.clone());
    }
    out.into_values().filter(|g| g.len() > 1).collect()
}

/// Which modes carry the information: the worst relative σ with each one left out.
fn mode_value(planner: &mut Planner, channels: &[usize], modes: &[usize]) -> Result<Value> {
    let sigma = planner.sigma(channels, modes)?;
    let (all, _) = planner.worst(&sigma);
    let mut rows = Vec::new();
    for &k in modes {
        let without: Vec<usize> = modes.iter().copied().filter(|&m| m != k).collect();
        let sigma = planner.sigma(channels, &without)?;
        let (w, _) = planner.worst(&sigma);
        rows.push(json!({
            "mode": k + 1,
            "frequency_hz": planner.frequency_hz(k),
            "worst_sigma_without": finite(w),
            "could_be_dropped": w.is_finite() && w <= 1.05 * all,
        }));
    }
    Ok(Value::Array(rows))
}

/// plan.json.
pub(super) fn document(
    planner: &mut Planner,
    judge: &Judge,
    current: &[usize],
    candidates: &[usize],
    added: &[Added],
    args: &PlanArgs,
) -> Result<Value> {
    let modes: Vec<usize> = (0..args.modes).collect();
    let mut planned = current.to_vec();
    planned.extend(added.iter().map(|a| a.channel));
    let (d, t) = (&judge.rules, &judge.rules.thresholds);
    let steps: Vec<Value> = added
        .iter()
        .map(|a| {
            json!({
                "channel": planner.model().channels()[a.channel].name,
                "worst_sigma_per_set": finite(a.worst),
            })
        })
        .collect();
    let planned_sigma = planner.sigma(&planned, &modes)?;
    Ok(json!({
        "schema": "boltwatch.plan.v1",
        "structure": planner.model().name,
        "watched": planner.watched_noun(),
        "modes": modes.len(),
        "noise": {"frequency_cov": planner.noise().frequency_cov, "shape_nsd": planner.noise().shape_nsd},
        "sets": judge.sets,
        "per_day": d.per_day,
        "sigma_needed": judge.needed(),
        "target_loss": judge.target,
        "target_met": judge.all_watchable(&planner.relative(&planned_sigma)),
        "thresholds": {"warning_drop": t.warning_drop, "alarm_drop": t.alarm_drop,
            "confidence": t.confidence, "max_std": t.max_std},
        "candidates": format!("{:?}", args.candidates).to_lowercase(),
        "current": assess(planner, judge, current, &modes)?,
        "added": steps,
        "planned": assess(planner, judge, &planned, &modes)?,
        "mode_value": mode_value(planner, &planned, &modes)?,
        "baselines": baselines(planner, current, candidates, added, &modes)?,
    }))
}

/// Random placements drawn for the baseline.
const RANDOM_PLACEMENTS: usize = 100;

/// The added channels' worst σ against the same number placed by effective independence
/// and at random ([`RANDOM_PLACEMENTS`] draws, seed 1): null when nothing is added.
fn baselines(
    planner: &mut Planner,
    current: &[usize],
    candidates: &[usize],
    added: &[Added],
    modes: &[usize],
) -> Result<Value> {
    let Some(last) = added.last() else {
        return Ok(Value::Null);
    };
    let n = added.len();
    let efi = planner.effective_independence(current, candidates, modes, n)?;
    let mut with_efi = current.to_vec();
    with_efi.extend(&efi);
    let efi_sigma = planner.sigma(&with_efi, modes)?;
    let (efi_worst, _) = planner.worst(&efi_sigma);
    let mut random =
        planner.random_placements(current, candidates, modes, n, RANDOM_PLACEMENTS, 1)?;
    random.sort_by(f64::total_cmp);
    let beaten = random.iter().filter(|&&w| w > last.worst).count();
    let q = |p: f64| finite(random[((random.len() - 1) as f64 * p).round() as usize]);
    let names = |cs: &[usize]| -> Vec<String> {
        cs.iter()
            .map(|&c| planner.model().channels()[c].name.clone())
            .collect()
    };
    Ok(json!({
        "plan_worst_sigma_per_set": finite(last.worst),
        "effective_independence": {"channels": names(&efi), "worst_sigma_per_set": finite(efi_worst)},
        "random": {
            "placements": RANDOM_PLACEMENTS,
            "worst_sigma_per_set": {"p05": q(0.05), "median": q(0.5), "p95": q(0.95)},
            "plan_better_than": beaten as f64 / random.len() as f64,
        },
    }))
}

/// The lines printed: the worst σ and the connections not watchable, before and after.
pub(super) fn summary(doc: &Value) -> String {
    let line = |key: &str| {
        let a = &doc[key];
        let off: Vec<&str> = a["connections"]
            .as_array()
            .into_iter()
            .flatten()
            .filter(|c| c["watchable"] == false)
            .filter_map(|c| c["name"].as_str())
            .collect();
        format!(
            "{key}: {} channels, worst σ per set {:.3}, {} {} not watchable at {:.0} % {:?}",
            a["channels"].as_array().map_or(0, Vec::len),
            a["worst_sigma_per_set"].as_f64().unwrap_or(f64::INFINITY),
            off.len(),
            doc["watched"].as_str().unwrap_or("connections"),
            100.0 * doc["target_loss"].as_f64().unwrap_or(0.0),
            off
        )
    };
    let added: Vec<&str> = doc["added"]
        .as_array()
        .into_iter()
        .flatten()
        .filter_map(|a| a["channel"].as_str())
        .collect();
    let mut out = format!("{}\nadded {added:?}\n{}", line("current"), line("planned"));
    let b = &doc["baselines"];
    if !b.is_null() {
        out += &format!(
            "\nsame number placed by effective independence: worst σ per set {:.3}; \
             at random: median {:.3}, the plan better than {:.0} % of {}",
            b["effective_independence"]["worst_sigma_per_set"]
                .as_f64()
                .unwrap_or(f64::INFINITY),
            b["random"]["worst_sigma_per_set"]["median"]
                .as_f64()
                .unwrap_or(f64::INFINITY),
            100.0 * b["random"]["plan_better_than"].as_f64().unwrap_or(0.0),
            b["random"]["placements"],
        );
    }
    out
}
