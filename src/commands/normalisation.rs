//! `boltwatch normalisation`: what a tracker has learned of its structure's seasons, and
//! learning it again, explicitly.
//!
//! * `show STATE [--json]`: the normalisation models in a checkpoint (the daemon's
//!   `<structure>.checkpoint.json`, a replay's `OUT.checkpoint.json`) or a law file: per
//!   parameter the temperature law (θ at 20 °C, the slope and the slope below each knee, with
//!   their standard deviations, the scatter τ, the sets learned and held out), the conditions
//!   learned from, and the output-only factors. (A checkpoint does not name the parameters:
//!   they are numbered θ1, θ2, … in the model's order.)
//! * `learn RECORDING --from T1 --to T2 -o LAW.json [--config C]`: the models learned from
//!   the sets of a recording between two times (its modal sets and environment readings, as
//!   `replay` reads them), frozen at T2, for one structure. With
//!   `tracker.normalisation.law = "LAW.json"` in the configuration, that structure's tracker
//!   judges by them from its next start (replay or daemon), whatever it had learned.

use std::fmt::Write;
use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use chrono::{DateTime, Utc};
use serde::{Deserialize, Serialize};

use crate::core::normalisation::covariates::CovariateModel;
use crate::core::normalisation::factors::FactorModel;
use crate::io::mcap::from_ns;
use crate::pipeline::normalise::NormalisationState;
use crate::pipeline::{Tracker, TrackerState};
use crate::settings::Settings;

#[derive(Debug, clap::Subcommand)]
pub enum NormalisationCommand {
    /// Print the normalisation models of a checkpoint or a law file.
    Show(ShowArgs),
    /// Learn the models again from a recording between two times; write them frozen.
    Learn(LearnArgs),
}

#[derive(Debug, clap::Args)]
pub struct ShowArgs {
    /// A checkpoint (daemon or replay) or a law file written by `learn`.
    pub state: PathBuf,
    /// Print the models as JSON instead of tables.
    #[arg(long)]
    pub json: bool,
}

#[derive(Debug, clap::Args)]
pub struct LearnArgs {
    /// Recording with the structure's modal sets (and environment readings).
    pub recording: PathBuf,
    /// First time learned from (RFC 3339, e.g. 2026-03-01T00:00:00Z).
    #[arg(long)]
    pub from: String,
    /// Last time learned from (RFC 3339); the models are frozen there.
    #[arg(long)]
    pub to: String,
    /// Configuration file (structures, tracker settings); default: the bundled defaults.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// The structure, when the configuration watches several.
    #[arg(long)]
    pub structure: Option<String>,
    /// The law file written.
    #[arg(short, long)]
    pub out: PathBuf,
}

/// The schema name of a law file.
pub const LAW_SCHEMA: &str = "boltwatch.normalisation.v1";

/// A law file: one structure's normalisation models, learned over `[from, to]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Law {
    pub schema: String,
    pub structure: String,
    pub parameters: Vec<String>,
    pub from: DateTime<Utc>,
    pub to: DateTime<Utc>,
    pub sets: u64,
    pub state: NormalisationState,
}

pub fn run(cmd: &NormalisationCommand) -> Result<()> {
    match cmd {
        NormalisationCommand::Show(a) => show(a),
        NormalisationCommand::Learn(a) => learn(a),
    }
}

fn time_arg(v: &str, flag: &str) -> Result<DateTime<Utc>> {
    Ok(DateTime::parse_from_rfc3339(v)
        .with_context(|| format!("{flag} {v}: not an RFC 3339 time (e.g. 2026-03-01T00:00:00Z)"))?
        .with_timezone(&Utc))
}

fn learn(a: &LearnArgs) -> Result<()> {
    let (from, to) = (time_arg(&a.from, "--from")?, time_arg(&a.to, "--to")?);
    if to <= from {
        bail!("--to {} must be after --from {}", a.to, a.from);
    }
    let settings = Settings::load(a.config.as_deref())?;
    let s = match &a.structure {
        Some(name) => settings
            .structures
            .iter()
            .find(|s| &s.name == name)
            .with_context(|| format!("--structure {name}: not a configured structure"))?,
        None => match &settings.structures[..] {
            [one] => one,
            _ => bail!("the configuration watches several structures: name one with --structure"),
        },
    };
    let loaded = std::sync::Arc::new(crate::io::model::load_structure(s)?);
    let model = &loaded.1;
    let parameters = model.parameters().iter().map(|p| p.name.clone()).collect();
    let mut cfg = settings.tracker.clone();
    cfg.crosscheck_every_sets = 0;
    cfg.crosscheck_every_s = 0.0;
    cfg.normalisation.law.clear();
    cfg.normalisation.training_days = (to - from).num_milliseconds() as f64 / 86_400_000.0 + 1.0;
    let mut tracker = Tracker::new(model.clone(), cfg)?;
    let name = s.name.clone();
    let models = std::collections::HashMap::from([(name.clone(), loaded.clone())]);
    let (inputs, _) = crate::io::replay::read_inputs(&a.recording, &models, &settings.identify)?;
    let mut sets = 0u64;
    for (_, input) in inputs {
        use crate::io::replay::Input;
        match input {
            Input::Recorded(m) if (from..=to).contains(&from_ns(m.log_time)) => {
                tracker.handle(from_ns(m.log_time), &m.data);
                sets += 1;
            }
            Input::Environment(m) => {
                tracker.handle_environment(from_ns(m.log_time), &m.data);
            }
            _ => {}
        }
    }
    if sets == 0 {
        bail!(
            "{} has no modal sets of {name} logged between {} and {}",
            a.recording.display(),
            a.from,
            a.to
        );
    }
    let mut state = tracker.state().normalisation.clone();
    state.frozen_at = Some(to);
    state.filters.clear();
    state.environment.clear();
    let law = Law {
        schema: LAW_SCHEMA.into(),
        structure: name,
        parameters,
        from,
        to,
        sets,
        state,
    };
    std::fs::write(&a.out, serde_json::to_vec_pretty(&law)?)
        .with_context(|| format!("cannot write {}", a.out.display()))?;
    print!("{}", describe(&law.structure, &law.parameters, &law.state));
    println!("learned from {sets} sets -> {}", a.out.display());
    Ok(())
}

fn show(a: &ShowArgs) -> Result<()> {
    let text = std::fs::read_to_string(&a.state)
        .with_context(|| format!("cannot read {}", a.state.display()))?;
    let v: serde_json::Value = serde_json::from_str(&text)
        .with_context(|| format!("{} is not JSON", a.state.display()))?;
    // (structure, parameter names when the file has them, models)
    let mut found: Vec<(String, Vec<String>, NormalisationState)> = Vec::new();
    if v["schema"] == LAW_SCHEMA {
        let law: Law = serde_json::from_value(v).context("law file")?;
        found.push((law.structure, law.parameters, law.state));
    } else if let Some(trackers) = v["trackers"].as_object() {
        for (name, cp) in trackers {
            let st: TrackerState = serde_json::from_value(cp["state"].clone())
                .with_context(|| format!("checkpoint of {name}"))?;
            found.push((name.clone(), Vec::new(), st.normalisation));
        }
    } else if v.get("state").is_some() {
        let st: TrackerState = serde_json::from_value(v["state"].clone()).context("checkpoint")?;
        found.push((st.structure.clone(), Vec::new(), st.normalisation));
    } else {
        bail!(
            "{}: neither a checkpoint (daemon or replay) nor a law file ({LAW_SCHEMA})",
            a.state.display()
        );
    }
    for (name, names, st) in found {
        if a.json {
            println!("{}", serde_json::to_string_pretty(&st)?);
        } else {
            print!("{}", describe(&name, &names, &st));
        }
    }
    Ok(())
}

/// The models as tables (module docs).
pub fn describe(structure: &str, names: &[String], st: &NormalisationState) -> String {
    let mut out = String::new();
    let when = |t: Option<DateTime<Utc>>| t.map_or("-".to_string(), crate::contract::rfc3339);
    let _ = writeln!(
        out,
        "{structure}: learning from {}; frozen at {}",
        when(st.start),
        when(st.frozen_at)
    );
    if let Some(m) = &st.covariates {
        write_covariate_law(&mut out, names, m);
    }
    if let Some(f) = &st.factors {
        write_factors(&mut out, f);
    }
    out
}

/// The covariate law: its terms and the ranges learned over, then per parameter (named
/// from `names`, else θ1, θ2, …) each coefficient ± its std, the scatter τ and the sets
/// learned and held out.
fn write_covariate_law(out: &mut String, names: &[String], m: &CovariateModel) {
    let terms = m.basis.terms();
    let ranges: Vec<String> = m
        .basis
        .covariates
        .iter()
        .zip(&m.ranges)
        .map(|(c, r)| match r {
            Some([lo, hi]) => format!("{c} {lo} … {hi}"),
            None => format!("{c}: nothing learned"),
        })
        .collect();
    let _ = writeln!(
        out,
        "covariate law: ln θ on {} (learned over {})",
        terms.join(", "),
        ranges.join("; ")
    );
    let _ = writeln!(
        out,
        "  {:<14} {}  {:>7}  {:>6} {:>6}",
        "parameter",
        terms
            .iter()
            .map(|t| format!("{:>20}", t))
            .collect::<Vec<_>>()
            .join(" "),
        "τ",
        "sets",
        "held"
    );
    for (l, r) in m.parameters.iter().enumerate() {
        let name = names
            .get(l)
            .cloned()
            .unwrap_or_else(|| format!("θ{}", l + 1));
        let coef: Vec<String> = r
            .beta
            .iter()
            .enumerate()
            .map(|(i, b)| format!("{:>9.4} ± {:<8.4}", b, r.p[i][i].max(0.0).sqrt()))
            .collect();
        let _ = writeln!(
            out,
            "  {:<14} {}  {:>7.4}  {:>6} {:>6}",
            name,
            coef.join(" "),
            r.scatter().sqrt(),
            r.learned,
            r.held_out
        );
    }
}

/// The output-only factor model: its factors, sets and leading generalised eigenvalues, or
/// how many of the sets it needs it has learned.
fn write_factors(out: &mut String, f: &FactorModel) {
    match &f.fit {
        Some(fit) => {
            let k = fit.loadings.first().map_or(0, Vec::len);
            let eig: Vec<String> = fit
                .eigenvalues
                .iter()
                .take(6)
                .map(|e| format!("{e:.2}"))
                .collect();
            let _ = writeln!(
                out,
                "output-only: {k} factor(s) from {} sets ({} held out); generalised eigenvalues {} …",
                f.sets,
                f.held_out,
                eig.join(", ")
            );
        }
        None => {
            let _ = writeln!(
                out,
                "output-only: {} of the {} sets needed learned",
                f.sets,
                f.min_sets()
            );
        }
    }
}
