//! `boltwatch plan`: before drilling, which connections the instrumentation will let the
//! tracker watch, how small a loosening it will catch, and which sensors to add
//! ([`crate::core::plan`]).

use std::path::PathBuf;

use anyhow::{Context, Result, bail};

mod assess;
mod draw;
mod places;
pub(crate) mod verify;

use super::write_json;
use crate::core::plan::places::WithCandidates;
use crate::core::plan::{Added, Criterion, Planner};
use crate::core::simulate::Noise;
use crate::pipeline::detectability::Detectability;
use assess::{Judge, document, summary};
use draw::drawing;

#[derive(Debug, clap::Args)]
pub struct PlanArgs {
    /// The model: a model file (plane, space or solid frame, or `bundled:<name>`) or an
    /// imported model's `model.json`.
    #[arg(long)]
    pub model: PathBuf,
    /// The channels installed now: a TOML file `channels = ["name", …]` (default: every
    /// channel of the model).
    #[arg(long)]
    pub channels: Option<PathBuf>,
    /// Where sensors may be added: `nodes` (translations at the named nodes; a solid's
    /// beams at every sixth; an imported model's named locations), `dofs` (translations at
    /// every node of the mesh; an imported model's every DOF) or `all` (rotations too).
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
    /// Sets the filter has seen when a loss must be caught (the smallest loss caught is
    /// that after this many sets).
    #[arg(long, default_value_t = 20)]
    pub sets: usize,
    /// Sets identified per day (the filter's time step).
    #[arg(long, default_value_t = 4.0)]
    pub per_day: f64,
    /// The configuration whose `[tracker.alerts]` thresholds apply (default: the defaults).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Check the plan by simulation: this many noisy sets with the planned channels and
    /// modes, as planned, tracked by the tracker a replay runs (0: no check).
    #[arg(long, default_value_t = 0)]
    pub verify: usize,
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
    let settings = crate::settings::Settings::load(args.config.as_deref())?;
    if !(args.per_day.is_finite() && args.per_day > 0.0) {
        bail!("--per-day {}: give a positive rate", args.per_day);
    }
    if args.sets == 0 {
        bail!("--sets 0: the filter needs at least one set");
    }
    let (
        WithCandidates {
            model,
            spec,
            candidates,
        },
        installed,
    ) = places::planned_model(&args.model, args.candidates)?;
    crate::core::numerics_for(&model);
    let current = places::current_channels(&model, args.channels.as_deref(), &installed)?;
    let mut planner = Planner::new(model, args.modes, noise)?.with_reference(&current);
    let modes: Vec<usize> = (0..args.modes).collect();
    let candidates: Vec<usize> = candidates
        .iter()
        .filter_map(|n| planner.model().channel_index(n))
        .filter(|&c| planner.moves(c, &modes))
        .collect();
    let judge = Judge {
        rules: Detectability::of(&settings.tracker, args.per_day),
        sets: args.sets,
        target: args.target_loss,
    };
    let added = choose(&mut planner, &current, &candidates, &modes, args, &judge)?;
    let mut planned = current.clone();
    planned.extend(added.iter().map(|a| a.channel));
    let mut doc = document(&mut planner, &judge, &current, &candidates, &added, args)?;
    if args.verify > 0 {
        let check = verify::Check {
            channels: &planned,
            modes: &modes,
            sets: args.verify,
            per_day: args.per_day,
        };
        doc["verification"] = check.run(&planner, &settings.tracker, &doc["planned"])?;
    }
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("cannot create {}", args.out.display()))?;
    write_json(&args.out.join("plan.json"), &doc)?;
    let svg = spec
        .as_ref()
        .and_then(|spec| drawing(spec, &planner, &doc, &planned, &current));
    if let Some(svg) = svg {
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

/// The channels to add: `--add N`, or with `--budget N` the fewest that make every
/// connection watchable, or none. Each added channel is the greedy choice on the
/// connections' shortfall from the σ the target needs ([`Judge::needed`]); with a budget,
/// the additions that turn out not to be needed once the target is met are taken out
/// again (a greedy choice can be overtaken by later ones).
fn choose(
    planner: &mut Planner,
    current: &[usize],
    candidates: &[usize],
    modes: &[usize],
    args: &PlanArgs,
    judge: &Judge,
) -> Result<Vec<Added>> {
    let criterion = Criterion {
        needed: judge.needed(),
    };
    if let Some(n) = args.add {
        return planner.greedy(current, candidates, modes, n, criterion);
    }
    let Some(budget) = args.budget else {
        return Ok(Vec::new());
    };
    let free = candidates.iter().filter(|c| !current.contains(c)).count();
    if budget > free {
        bail!("--budget {budget}: only {free} candidate places are not measured already");
    }
    let sigma = planner.sigma(current, modes)?;
    if judge.all_watchable(&planner.relative(&sigma)) {
        return Ok(Vec::new());
    }
    let mut chosen = current.to_vec();
    let mut added = Vec::new();
    for _ in 0..budget {
        let step = planner
            .greedy(&chosen, candidates, modes, 1, criterion)?
            .remove(0);
        chosen.push(step.channel);
        added.push(step.channel);
        if judge.all_watchable(&planner.relative(&step.sigma)) {
            let kept = prune(planner, judge, current, &added, modes)?;
            return steps(planner, current, &kept, modes);
        }
    }
    steps(planner, current, &added, modes)
}

/// `added` without each channel, first added first, that the target does not need.
fn prune(
    planner: &mut Planner,
    judge: &Judge,
    current: &[usize],
    added: &[usize],
    modes: &[usize],
) -> Result<Vec<usize>> {
    let mut kept = added.to_vec();
    for &c in added {
        let mut without: Vec<usize> = current.to_vec();
        without.extend(kept.iter().copied().filter(|&k| k != c));
        let sigma = planner.sigma(&without, modes)?;
        if judge.all_watchable(&planner.relative(&sigma)) {
            kept.retain(|&k| k != c);
        }
    }
    Ok(kept)
}

/// The additions in order, each with what the channels up to it give.
fn steps(
    planner: &mut Planner,
    current: &[usize],
    added: &[usize],
    modes: &[usize],
) -> Result<Vec<Added>> {
    let mut chosen = current.to_vec();
    added
        .iter()
        .map(|&channel| {
            chosen.push(channel);
            let sigma = planner.sigma(&chosen, modes)?;
            let (worst, _) = planner.worst(&sigma);
            Ok(Added {
                channel,
                worst,
                sigma,
            })
        })
        .collect()
}
