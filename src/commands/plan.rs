//! `boltwatch plan`: before drilling, which connections the instrumentation will let the
//! tracker watch, how small a loosening it will catch, and which sensors to add
//! ([`crate::core::plan`]).

use std::collections::BTreeMap;
use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use serde_json::{Value, json};

use super::write_json;
use crate::core::model::spec::{ChannelSpec, ModelSpec};
use crate::core::model::{Model, ParameterKind};
use crate::core::plan::Planner;
use crate::core::simulate::Noise;
use crate::pipeline::alerts::AlertThresholds;

#[derive(Debug, clap::Args)]
pub struct PlanArgs {
    /// The model file (TOML frame or space frame, or `bundled:<name>`).
    #[arg(long)]
    pub model: PathBuf,
    /// The channels installed now: a TOML file `channels = ["name", …]` (default: every
    /// channel of the model).
    #[arg(long)]
    pub channels: Option<PathBuf>,
    /// Where sensors may be added: `nodes` (translations at the named nodes), `dofs`
    /// (translations at every node of the mesh) or `all` (rotations too).
    #[arg(long, default_value = "dofs")]
    pub candidates: Candidates,
    /// Add exactly this many sensors.
    #[arg(long, conflicts_with = "budget")]
    pub add: Option<usize>,
    /// Add the fewest sensors, at most this many, that make every connection detectable
    /// at `--target-loss`.
    #[arg(long)]
    pub budget: Option<usize>,
    /// The loss every connection must be detectable at (a fraction), with `--budget`.
    #[arg(long, default_value_t = 0.2)]
    pub target_loss: f64,
    /// The modes identified per set (the lowest K).
    #[arg(long, default_value_t = 9)]
    pub modes: usize,
    /// The stated noise of a set: frequency CoV and mode-shape NSD.
    #[arg(long, default_value = "0.01,0.05")]
    pub noise: String,
    /// Sets the tracker's filter averages over (σ after S sets is σ/√S).
    #[arg(long, default_value_t = 20)]
    pub sets: usize,
    /// The configuration whose `[tracker.alerts]` thresholds apply (default: the defaults).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Output directory: plan.json and plan.svg.
    #[arg(short, long)]
    pub out: PathBuf,
}

/// Where sensors may be added.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Candidates {
    Nodes,
    Dofs,
    All,
}

pub fn run(args: &PlanArgs) -> Result<()> {
    let noise = parse_noise(&args.noise)?;
    let thresholds = crate::settings::Settings::load(args.config.as_deref())?
        .tracker
        .alerts;
    let installed = crate::io::model::load_spec(&args.model)?;
    let (spec, candidates) = with_candidates(&installed, args.candidates)?;
    let model =
        Model::from_spec(&spec).with_context(|| format!("model file {}", args.model.display()))?;
    crate::core::numerics_for(&model);
    let current = current_channels(&model, args.channels.as_deref(), &installed)?;
    let mut planner = Planner::new(model, args.modes, noise)?.with_reference(&current);
    let modes: Vec<usize> = (0..args.modes).collect();
    let candidates: Vec<usize> = candidates
        .iter()
        .filter_map(|n| planner.model().channel_index(n))
        .filter(|&c| planner.moves(c, &modes))
        .collect();
    let judge = Judge {
        thresholds,
        sets: args.sets,
        target: args.target_loss,
    };
    let added = choose(&mut planner, &current, &candidates, &modes, args, &judge)?;
    let mut planned = current.clone();
    planned.extend(added.iter().map(|a| a.channel));
    let doc = document(
        &mut planner,
        &judge,
        &current,
        &planned,
        &added,
        &modes,
        args,
    )?;
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("cannot create {}", args.out.display()))?;
    write_json(&args.out.join("plan.json"), &doc)?;
    if let Some(svg) = drawing(&spec, &planner, &doc, &planned, &current) {
        let file = args.out.join("plan.svg");
        std::fs::write(&file, svg).with_context(|| format!("cannot write {}", file.display()))?;
    }
    println!("{}", summary(&doc));
    Ok(())
}

/// `freq_cov,shape_nsd`, both positive.
fn parse_noise(s: &str) -> Result<Noise> {
    let v = super::parse_positive_list(s, "--noise")?;
    let [frequency_cov, shape_nsd] = v[..] else {
        bail!("--noise {s}: give the frequency CoV and the shape NSD, e.g. 0.01,0.05");
    };
    Ok(Noise {
        frequency_cov,
        shape_nsd,
    })
}

/// The model file with a channel added at every candidate place not measured already, and
/// the candidates' names. Only frame models (plane and space) can take new channels.
fn with_candidates(spec: &ModelSpec, kind: Candidates) -> Result<(ModelSpec, Vec<String>)> {
    let mut spec = spec.clone();
    let (places, dirs): (Vec<String>, &[&str]) = if let Some(s) = &spec.space_frame {
        let meshes = s.members.iter().map(|m| (m.name.as_str(), m.elements));
        let dirs: &[&str] = match kind {
            Candidates::All => &["x", "y", "z", "rx", "ry", "rz"],
            _ => &["x", "y", "z"],
        };
        (
            places(s.nodes.iter().map(|n| n.name.as_str()), meshes, kind),
            dirs,
        )
    } else if !spec.members.is_empty() {
        let meshes = spec.members.iter().map(|m| (m.name.as_str(), m.elements));
        let dirs: &[&str] = match kind {
            Candidates::All => &["x", "y", "rz"],
            _ => &["x", "y"],
        };
        (
            places(spec.nodes.iter().map(|n| n.name.as_str()), meshes, kind),
            dirs,
        )
    } else {
        bail!(
            "{}: sensors can be added to frame models (plane or space) only; \
             solids and imported matrices are planned over their own channels",
            spec.name
        );
    };
    let (supports, restrain) = match &spec.space_frame {
        Some(s) => (s.supports.clone(), s.restrain.clone()),
        None => (spec.supports.clone(), Vec::new()),
    };
    // A DOF a support or the frame's restraint fixes reads nothing: no sensor there.
    let fixed = |at: &str, dir: &str| {
        restrain.iter().any(|r| r == dir)
            || supports
                .iter()
                .any(|s| s.node == at && s.fix.as_ref().is_none_or(|f| f.iter().any(|d| d == dir)))
    };
    let channels = match &mut spec.space_frame {
        Some(s) => &mut s.channels,
        None => &mut spec.channels,
    };
    let mut names = Vec::new();
    for at in &places {
        for dir in dirs.iter().filter(|d| !fixed(at, d)) {
            let name = format!("{at}.{dir}");
            if !channels.iter().any(|c| c.name == name) {
                channels.push(ChannelSpec {
                    name: name.clone(),
                    at: at.clone(),
                    dir: dir.to_string(),
                });
            }
            names.push(name);
        }
    }
    Ok((spec, names))
}

/// The named nodes, and with `dofs` or `all` every interior node of each member's mesh
/// (`<member>.<k>`).
fn places<'a>(
    nodes: impl Iterator<Item = &'a str>,
    meshes: impl Iterator<Item = (&'a str, usize)>,
    kind: Candidates,
) -> Vec<String> {
    let mut out: Vec<String> = nodes.map(str::to_string).collect();
    if kind != Candidates::Nodes {
        for (member, elements) in meshes {
            out.extend((1..elements).map(|k| format!("{member}.{k}")));
        }
    }
    out
}

/// The channels installed now: those of `--channels`, else the model file's own.
fn current_channels(
    model: &Model,
    file: Option<&std::path::Path>,
    spec: &ModelSpec,
) -> Result<Vec<usize>> {
    let names: Vec<String> = match file {
        Some(path) => {
            #[derive(serde::Deserialize)]
            #[serde(deny_unknown_fields)]
            struct Installed {
                channels: Vec<String>,
            }
            let text = std::fs::read_to_string(path)
                .with_context(|| format!("--channels: cannot read {}", path.display()))?;
            let i: Installed =
                toml::from_str(&text).with_context(|| format!("--channels {}", path.display()))?;
            i.channels
        }
        None => match &spec.space_frame {
            Some(s) => s.channels.iter().map(|c| c.name.clone()).collect(),
            None => spec.channels.iter().map(|c| c.name.clone()).collect(),
        },
    };
    names
        .iter()
        .map(|n| {
            model.channel_index(n).with_context(|| {
                format!("--channels: `{n}` is not a channel or a candidate place of the model")
            })
        })
        .collect()
}

/// What the alert thresholds make of a σ.
struct Judge {
    thresholds: AlertThresholds,
    sets: usize,
    target: f64,
}

impl Judge {
    /// The z of the thresholds' confidence.
    fn z(&self) -> f64 {
        crate::core::stats::inverse_normal_cdf(self.thresholds.confidence)
    }

    /// The smallest loss a `drop` threshold reports at the thresholds' confidence, with a
    /// filtered level of relative σ `s`: the loss `f` where `Φ((f − drop)/s)` reaches it.
    fn detectable(&self, drop: f64, s: f64) -> f64 {
        drop + self.z() * s
    }

    /// Relative σ after the filter's sets.
    fn after_sets(&self, rel: f64) -> f64 {
        rel / (self.sets.max(1) as f64).sqrt()
    }

    /// Whether a connection of per-set relative σ `rel` is watched (alerts on) and its
    /// warning catches the target loss.
    fn watchable(&self, rel: f64) -> bool {
        rel.is_finite()
            && rel <= self.thresholds.max_std
            && self.detectable(self.thresholds.warning_drop, self.after_sets(rel)) <= self.target
    }
}

/// The channels to add: `--add N`, or with `--budget N` the fewest (greedy) that make
/// every connection watchable, or none.
fn choose(
    planner: &mut Planner,
    current: &[usize],
    candidates: &[usize],
    modes: &[usize],
    args: &PlanArgs,
    judge: &Judge,
) -> Result<Vec<crate::core::plan::Added>> {
    if let Some(n) = args.add {
        return planner.greedy(current, candidates, modes, n);
    }
    let Some(budget) = args.budget else {
        return Ok(Vec::new());
    };
    let free = candidates.iter().filter(|c| !current.contains(c)).count();
    if budget > free {
        bail!("--budget {budget}: only {free} candidate places are not measured already");
    }
    let all_watchable = |p: &Planner, sigma: &[f64]| {
        connection_params(p.model())
            .into_iter()
            .all(|l| judge.watchable(sigma[l] / p.model().parameters()[l].nominal.abs()))
    };
    let sigma = planner.sigma(current, modes)?;
    let mut added = Vec::new();
    if all_watchable(planner, &sigma) {
        return Ok(added);
    }
    let mut chosen = current.to_vec();
    for _ in 0..budget {
        let step = planner.greedy(&chosen, candidates, modes, 1)?.remove(0);
        chosen.push(step.channel);
        let done = all_watchable(planner, &step.sigma);
        added.push(step);
        if done {
            break;
        }
    }
    Ok(added)
}

/// The parameters that are connections.
fn connection_params(model: &Model) -> Vec<usize> {
    (0..model.n_params())
        .filter(|&l| matches!(model.parameters()[l].kind, ParameterKind::Connections(_)))
        .collect()
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
    let model = planner.model();
    let t = &judge.thresholds;
    let mut rows = Vec::new();
    let mut worst = 0.0_f64;
    for l in connection_params(model) {
        let p = &model.parameters()[l];
        let rel = sigma[l] / p.nominal.abs();
        let s = judge.after_sets(rel);
        worst = worst.max(if rel.is_finite() { rel } else { f64::INFINITY });
        rows.push(json!({
            "name": p.name,
            "sigma_per_set": finite(rel),
            "sigma_after_sets": finite(s),
            "alerts_off": !(rel.is_finite() && rel <= t.max_std),
            "detectable_warning": finite(judge.detectable(t.warning_drop, s)),
            "detectable_alarm": finite(judge.detectable(t.alarm_drop, s)),
            "watchable": judge.watchable(rel),
        }));
    }
    Ok(json!({
        "channels": channels.iter().map(|&c| model.channels()[c].name.clone()).collect::<Vec<_>>(),
        "worst_sigma_per_set": finite(worst),
        "connections": rows,
        "resolved_together": clusters(model, &corr, 0.9),
    }))
}

/// A JSON number, or null when not finite.
fn finite(v: f64) -> Value {
    if v.is_finite() { json!(v) } else { Value::Null }
}

/// Groups of connections linked by a correlation of magnitude at least `limit`.
fn clusters(model: &Model, corr: &Option<faer::Mat<f64>>, limit: f64) -> Vec<Vec<String>> {
    let Some(c) = corr else {
        return Vec::new();
    };
    let params = connection_params(model);
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
fn document(
    planner: &mut Planner,
    judge: &Judge,
    current: &[usize],
    planned: &[usize],
    added: &[crate::core::plan::Added],
    modes: &[usize],
    args: &PlanArgs,
) -> Result<Value> {
    let t = &judge.thresholds;
    let steps: Vec<Value> = added
        .iter()
        .map(|a| {
            json!({
                "channel": planner.model().channels()[a.channel].name,
                "worst_sigma_per_set": finite(a.worst),
            })
        })
        .collect();
    Ok(json!({
        "schema": "boltwatch.plan.v1",
        "structure": planner.model().name,
        "modes": modes.len(),
        "noise": {"frequency_cov": planner.noise().frequency_cov, "shape_nsd": planner.noise().shape_nsd},
        "sets": judge.sets,
        "target_loss": judge.target,
        "thresholds": {"warning_drop": t.warning_drop, "alarm_drop": t.alarm_drop,
            "confidence": t.confidence, "max_std": t.max_std},
        "candidates": format!("{:?}", args.candidates).to_lowercase(),
        "current": assess(planner, judge, current, modes)?,
        "added": steps,
        "planned": assess(planner, judge, planned, modes)?,
        "mode_value": mode_value(planner, planned, modes)?,
    }))
}

/// The lines printed: the worst σ and the connections not watchable, before and after.
fn summary(doc: &Value) -> String {
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
            "{key}: {} channels, worst σ per set {:.3}, {} connections not watchable at {:.0} % {:?}",
            a["channels"].as_array().map_or(0, Vec::len),
            a["worst_sigma_per_set"].as_f64().unwrap_or(f64::INFINITY),
            off.len(),
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
    format!("{}\nadded {added:?}\n{}", line("current"), line("planned"))
}

/// The structure with the planned channels (added ones crossed) and each connection
/// coloured by the loss its warning catches: green when watchable, orange when alerts stay
/// on but the target is missed, red when alerts are off.
fn drawing(
    spec: &ModelSpec,
    planner: &Planner,
    doc: &Value,
    planned: &[usize],
    current: &[usize],
) -> Option<String> {
    use crate::draw::{Canvas, Geometry};
    let mut g = Geometry::of(spec)?;
    let names = |cs: &[usize]| -> Vec<String> {
        cs.iter()
            .map(|&c| planner.model().channels()[c].name.clone())
            .collect()
    };
    let (planned, current) = (names(planned), names(current));
    g.channels.retain(|(n, _)| planned.contains(n));
    let rows: BTreeMap<String, Value> = doc["planned"]["connections"]
        .as_array()?
        .iter()
        .filter_map(|r| Some((r["name"].as_str()?.to_string(), r.clone())))
        .collect();
    let title = format!(
        "{}: planned channels (+ added) and what each connection's warning catches",
        planner.model().name
    );
    let mut c = Canvas::new(&g, 760.0, 640.0, &title);
    for (n, p) in &g.channels {
        if !current.contains(n) {
            c.cross(*p, "#d62728", n);
        }
    }
    c.connections(|mark| {
        let params = super::diagnose::parameters_of(planner.model(), &mark.model_names);
        let worst = params
            .iter()
            .filter_map(|&l| rows.get(&planner.model().parameters()[l].name))
            .max_by(|a, b| detect(a).total_cmp(&detect(b)))?;
        let color = match (worst["alerts_off"] == true, worst["watchable"] == true) {
            (true, _) => "#d62728",
            (false, true) => "#2ca02c",
            (false, false) => "#ff7f0e",
        };
        Some((
            color.to_string(),
            format!(": warning at {:.0} % loss", 100.0 * detect(worst)),
        ))
    });
    c.text(
        10.0,
        38.0,
        "green: watchable at the target loss; orange: alerts on, target missed; red: alerts off",
    );
    Some(c.finish())
}

/// The loss a row's warning catches (infinite when unknown).
fn detect(row: &Value) -> f64 {
    row["detectable_warning"].as_f64().unwrap_or(f64::INFINITY)
}
