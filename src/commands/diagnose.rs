//! `boltwatch diagnose --model M.toml --data D.json -o DIR`: the discrepancy workflow
//! ([`crate::core::diagnosis`]) with a progress bar; `DIR/diagnosis.json`
//! (`boltwatch.diagnosis.v1`), `DIR/modes.svg` (per-mode errors and MAC before and after)
//! and `DIR/structure.svg` (the frame, the shape residual per channel, the named effects).

use std::fmt::Write;
use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use indicatif::{ProgressBar, ProgressStyle};

use super::{load_description, write_json};
use crate::contract::diagnosis::DiagnosisDoc;
use crate::core::diagnosis::{Diagnosis, DiagnosisOptions, diagnose};
use crate::core::model::Model;
use crate::core::model::spec::ModelSpec;
use crate::draw::{Canvas, Geometry, change_color};
use crate::plot::{Panel, Scale, Series, figure_svg};

#[derive(Debug, clap::Args)]
pub struct DiagnoseArgs {
    /// Model file (TOML), a bundled model (`bundled:lab-frame`, `bundled:space-frame`, ...),
    /// or the `model.json` of a model imported from matrices.
    #[arg(long)]
    pub model: PathBuf,
    /// Modal set (boltwatch.modal_set.v1).
    #[arg(long)]
    pub data: PathBuf,
    /// Family-wise significance level of the test over all candidates.
    #[arg(long, default_value_t = 1e-4)]
    pub alpha: f64,
    /// Candidates refitted with the full update per round.
    #[arg(long, default_value_t = 4)]
    pub refits: usize,
    /// Effects named at most.
    #[arg(long, default_value_t = 4)]
    pub max_effects: usize,
    /// Shape weight of weighting (9), for sets without uncertainties.
    #[arg(long, default_value_t = 1.0)]
    pub shape_weight: f64,
    /// Output directory.
    #[arg(short, long)]
    pub out: PathBuf,
}

pub fn run(args: &DiagnoseArgs) -> Result<()> {
    if !(args.alpha > 0.0 && args.alpha < 1.0) {
        bail!("--alpha = {} must be in (0, 1)", args.alpha);
    }
    if args.refits == 0 {
        bail!("--refits must be at least 1");
    }
    let (description, model) = load_description(&args.model)?;
    let set = super::inputs::load_set(&model, &args.data)?;
    let data = super::inputs::measured_data(&set, &model, args.shape_weight);
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("cannot create {}", args.out.display()))?;
    let pb = ProgressBar::new(0);
    pb.set_style(
        ProgressStyle::with_template("{msg:>22} {bar:40} {pos}/{len} ({elapsed})")
            .expect("template"),
    );
    let started = std::time::Instant::now();
    let mut round = 1;
    let mut last_stage = String::new();
    let d = diagnose(
        &description,
        &data,
        &DiagnosisOptions {
            alpha: args.alpha,
            refits: args.refits,
            max_effects: args.max_effects,
        },
        |stage, done, total| {
            if stage != last_stage {
                if stage == "screening" && !last_stage.is_empty() {
                    round += 1;
                }
                last_stage = stage.to_string();
                pb.set_length(total as u64);
                pb.set_message(format!("round {round}: {stage}"));
            }
            pb.set_position(done as u64);
        },
    )?;
    pb.finish_and_clear();
    let seconds = started.elapsed().as_secs_f64();
    let out = DiagnosisDoc::new(&d, &model.name, seconds);
    write_json(&args.out.join("diagnosis.json"), &out)?;
    std::fs::write(args.out.join("modes.svg"), modes_svg(&d))?;
    print!("{}", table(&d, seconds));
    match description
        .spec()
        .and_then(|spec| structure_svg(spec, &model, &d))
    {
        Some(svg) => {
            std::fs::write(args.out.join("structure.svg"), svg)?;
            println!(
                "written: {}/{{diagnosis.json, modes.svg, structure.svg}}",
                args.out.display()
            );
        }
        // An imported model has no geometry to draw, nor has the generated solid.
        None => println!(
            "written: {}/{{diagnosis.json, modes.svg}} (no structure.svg: the model has no \
             frame geometry)",
            args.out.display()
        ),
    }
    Ok(())
}

fn table(d: &Diagnosis, seconds: f64) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "ε before {:.1}, after {:.1} ({:.0} % of before); {} candidates, threshold Λ > {:.1} (α = {}); {:.1} s",
        d.before.epsilon,
        d.after.epsilon,
        100.0 * d.after.epsilon / d.before.epsilon,
        d.n_candidates,
        d.threshold,
        d.alpha,
        seconds
    );
    if d.named.is_empty() {
        let _ = writeln!(s, "named: nothing (no candidate is significant)");
    }
    for n in &d.named {
        let _ = writeln!(
            s,
            "named: {}@{} = {:.4e} ± {:.2e} {} (ε {:.1} -> {:.1}, Λ = {:.1}){}",
            n.refit.effect,
            n.refit.location,
            n.refit.value,
            n.refit.std,
            n.refit.unit,
            n.epsilon_before,
            n.refit.epsilon,
            n.likelihood_ratio,
            if n.indistinguishable_from.is_empty() {
                String::new()
            } else {
                format!(
                    "; the data cannot tell it from {}",
                    n.indistinguishable_from
                        .iter()
                        .map(|o| format!("{}@{} (ε {:.1})", o.effect, o.location, o.epsilon))
                        .collect::<Vec<_>>()
                        .join(", ")
                )
            }
        );
    }
    for w in d.rounds.iter().flat_map(|r| &r.withdrawn) {
        let _ = writeln!(
            s,
            "withdrawn: {}@{} (with the later effects in, taking it out raises ε by only {:.1})",
            w.effect, w.location, w.likelihood_ratio
        );
    }
    let _ = writeln!(
        s,
        "{:>4} {:>10} {:>10} {:>10} {:>8} {:>10} {:>8}",
        "mode", "meas Hz", "before σ", "after σ", "MAC bef", "MAC after", "paired"
    );
    for (m, (b, a)) in d.before.modes.iter().zip(&d.after.modes).enumerate() {
        // The model mode paired after, with the one before when the pairing changed.
        let paired = if b.paired_with == a.paired_with {
            a.paired_with.to_string()
        } else {
            format!("{}→{}", b.paired_with, a.paired_with)
        };
        let _ = writeln!(
            s,
            "{:>4} {:>10.3} {:>10.2} {:>10.2} {:>8.4} {:>10.4} {:>8}",
            m + 1,
            b.measured_hz,
            b.error_sigma,
            a.error_sigma,
            b.mac,
            a.mac,
            paired
        );
    }
    s
}

fn modes_svg(d: &Diagnosis) -> String {
    let idx: Vec<f64> = (1..=d.before.modes.len()).map(|k| k as f64).collect();
    let mut err = Panel::new(
        "frequency error per mode",
        "measured mode",
        "(measured − model) / σ",
        Scale::Linear,
        Scale::Linear,
    );
    err.series.push(
        Series::line(
            "before",
            idx.clone(),
            d.before.modes.iter().map(|m| m.error_sigma).collect(),
        )
        .with_color("#c0392b"),
    );
    err.series.push(
        Series::line(
            "after",
            idx.clone(),
            d.after.modes.iter().map(|m| m.error_sigma).collect(),
        )
        .with_color("#2471a3"),
    );
    let mut mac = Panel::new(
        "MAC per mode",
        "measured mode",
        "MAC",
        Scale::Linear,
        Scale::Linear,
    );
    mac.series.push(
        Series::line(
            "before",
            idx.clone(),
            d.before.modes.iter().map(|m| m.mac).collect(),
        )
        .with_color("#c0392b"),
    );
    mac.series.push(
        Series::line("after", idx, d.after.modes.iter().map(|m| m.mac).collect())
            .with_color("#2471a3"),
    );
    figure_svg(&[err, mac], 2)
}

/// The frame (in isometric projection when it is a space frame), each channel as a disc
/// whose area is its shape residual before (red) and after (blue) the named effects, each
/// connection coloured by how its parameter moves once the effects are added (the part
/// of the discrepancy it had absorbed), and the named effects marked.
fn structure_svg(spec: &ModelSpec, model: &Model, d: &Diagnosis) -> Option<String> {
    let g = Geometry::of(spec)?;
    let named = if d.named.is_empty() {
        "no missing effect named".to_string()
    } else {
        d.named
            .iter()
            .map(|n| format!("{}@{}", n.refit.effect, n.refit.location))
            .collect::<Vec<_>>()
            .join(", ")
    };
    let (w, h) = (720.0, 640.0);
    let mut c = Canvas::new(
        &g,
        w,
        h,
        &format!("shape residual per channel (area): before red, after blue; named: {named}"),
    );
    c.text(
        10.0,
        38.0,
        "connections: change of θ once the effects are added",
    );
    c.change_legend(w, 0.5);
    c.connections(|mark| {
        let changes: Vec<(String, f64, String)> = parameters_of(model, &mark.model_names)
            .into_iter()
            .filter_map(|l| {
                let (b, a) = (*d.before.theta.get(l)?, *d.after.theta.get(l)?);
                Some((
                    model.parameters()[l].name.clone(),
                    a / b - 1.0,
                    format!(" (θ {b:.3} → {a:.3})"),
                ))
            })
            .collect();
        largest_change(&changes)
    });
    let max_r = d.before.channels.iter().map(|c| c.1).fold(1e-12, f64::max);
    for (loc, color, dx) in [(&d.before, "#c0392b", -4.0), (&d.after, "#2471a3", 4.0)] {
        for (name, r, _) in &loc.channels {
            if let Some((_, p)) = g.channels.iter().find(|(n, _)| n == name) {
                c.disc(
                    *p,
                    18.0 * (r / max_r).sqrt(),
                    color,
                    dx,
                    &format!("{name}: {r:.2}"),
                );
            }
        }
    }
    for n in &d.named {
        if let Some(p) = g.position(&n.refit.location) {
            c.cross(
                p,
                "#117a65",
                &format!(
                    "{}@{} = {:.3e} {}",
                    n.refit.effect, n.refit.location, n.refit.value, n.refit.unit
                ),
            );
        }
    }
    Some(c.finish())
}

/// The parameters that scale these model connections, each once, in model order.
pub fn parameters_of(model: &Model, connections: &[String]) -> Vec<usize> {
    let mut out: Vec<usize> = model
        .connections()
        .iter()
        .filter(|c| connections.contains(&c.name))
        .filter_map(|c| c.parameter)
        .collect();
    out.sort_unstable();
    out.dedup();
    out
}

/// Of a connection's parameters and their changes, the largest change (its colour) and a
/// line per parameter (its tooltip).
pub fn largest_change(changes: &[(String, f64, String)]) -> Option<(String, String)> {
    let worst = changes
        .iter()
        .map(|c| c.1)
        .fold(None, |a: Option<f64>, c| match a {
            Some(x) if x.abs() >= c.abs() => Some(x),
            _ => Some(c),
        })?;
    let lines: Vec<String> = changes
        .iter()
        .map(|(name, change, note)| format!("\n{name}: {:+.1} %{note}", 100.0 * change))
        .collect();
    Some((change_color(worst, 0.5), lines.concat()))
}
