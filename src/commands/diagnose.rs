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
use crate::core::model::spec::ModelSpec;
use crate::plot::{Panel, Scale, Series, figure_svg};

#[derive(Debug, clap::Args)]
pub struct DiagnoseArgs {
    /// Model file (TOML), or the `model.json` of a model imported from matrices.
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
    match description.spec() {
        Some(spec) => {
            std::fs::write(args.out.join("structure.svg"), structure_svg(spec, &d))?;
            println!(
                "written: {}/{{diagnosis.json, modes.svg, structure.svg}}",
                args.out.display()
            );
        }
        // An imported model has no geometry to draw.
        None => println!(
            "written: {}/{{diagnosis.json, modes.svg}} (no structure.svg: a model imported \
             from matrices has no geometry)",
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
    for (b, a) in d.before.modes.iter().zip(&d.after.modes) {
        let _ = writeln!(
            s,
            "{:>4} {:>10.3} {:>10.2} {:>10.2} {:>8.4} {:>10.4} {:>8}",
            a.paired_with, b.measured_hz, b.error_sigma, a.error_sigma, b.mac, a.mac, a.paired_with
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

/// Plane coordinates of a location: a node, or an interior mesh node `<member>.<k>`.
fn position(spec: &ModelSpec, at: &str) -> Option<(f64, f64)> {
    let node = |n: &str| spec.nodes.iter().find(|p| p.name == n).map(|p| (p.x, p.y));
    if let Some(p) = node(at) {
        return Some(p);
    }
    let (member, k) = at.rsplit_once('.')?;
    let k: f64 = k.parse().ok()?;
    let m = spec.members.iter().find(|m| m.name == member)?;
    let ((x0, y0), (x1, y1)) = (node(&m.from)?, node(&m.to)?);
    let t = k / m.elements as f64;
    Some((x0 + t * (x1 - x0), y0 + t * (y1 - y0)))
}

/// The frame, each channel as a disc whose area is its shape residual before (red) and
/// after (blue) the named effects, and the named effects marked.
fn structure_svg(spec: &ModelSpec, d: &Diagnosis) -> String {
    let pts: Vec<(f64, f64)> = spec.nodes.iter().map(|n| (n.x, n.y)).collect();
    let (xmin, xmax) = pts.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |a, p| {
        (a.0.min(p.0), a.1.max(p.0))
    });
    let (ymin, ymax) = pts.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |a, p| {
        (a.0.min(p.1), a.1.max(p.1))
    });
    let (w, h, pad) = (640.0, 640.0, 70.0);
    let span = (xmax - xmin).max(ymax - ymin).max(1e-9);
    let sx = |x: f64| pad + (x - xmin) / span * (w - 2.0 * pad);
    let sy = |y: f64| h - pad - (y - ymin) / span * (h - 2.0 * pad);
    let mut s = String::new();
    let _ = writeln!(
        s,
        r#"<svg xmlns="http://www.w3.org/2000/svg" width="{w}" height="{h}" font-family="sans-serif" font-size="12">"#
    );
    let _ = writeln!(s, r#"<rect width="100%" height="100%" fill="white"/>"#);
    let title = if d.named.is_empty() {
        "no missing effect named".to_string()
    } else {
        d.named
            .iter()
            .map(|n| format!("{}@{}", n.refit.effect, n.refit.location))
            .collect::<Vec<_>>()
            .join(", ")
    };
    let _ = writeln!(
        s,
        r#"<text x="10" y="20" font-size="14">shape residual per channel (area): before red, after blue; named: {title}</text>"#
    );
    for m in &spec.members {
        if let (Some(a), Some(b)) = (position(spec, &m.from), position(spec, &m.to)) {
            let _ = writeln!(
                s,
                r##"<line x1="{:.1}" y1="{:.1}" x2="{:.1}" y2="{:.1}" stroke="#444" stroke-width="3"/>"##,
                sx(a.0),
                sy(a.1),
                sx(b.0),
                sy(b.1)
            );
        }
    }
    let max_r = d.before.channels.iter().map(|c| c.1).fold(1e-12, f64::max);
    let channel_pos = |name: &str| {
        spec.channels
            .iter()
            .find(|c| c.name == name)
            .and_then(|c| position(spec, &c.at))
    };
    for (loc, color, dx) in [(&d.before, "#c0392b", -4.0), (&d.after, "#2471a3", 4.0)] {
        for (name, r, _) in &loc.channels {
            if let Some((x, y)) = channel_pos(name) {
                let radius = 18.0 * (r / max_r).sqrt();
                let _ = writeln!(
                    s,
                    r#"<circle cx="{:.1}" cy="{:.1}" r="{radius:.1}" fill="{color}" fill-opacity="0.35"><title>{name}: {r:.2}</title></circle>"#,
                    sx(x) + dx,
                    sy(y)
                );
            }
        }
    }
    for n in &d.named {
        let at = n.refit.location.split('.').next().unwrap_or_default();
        let p = position(spec, &n.refit.location)
            .or_else(|| position(spec, at))
            .or_else(|| {
                spec.members
                    .iter()
                    .find(|m| m.name == n.refit.location)
                    .and_then(|m| {
                        let (a, b) = (position(spec, &m.from)?, position(spec, &m.to)?);
                        Some(((a.0 + b.0) / 2.0, (a.1 + b.1) / 2.0))
                    })
            });
        if let Some((x, y)) = p {
            let _ = writeln!(
                s,
                r##"<path d="M {x0:.1} {y0:.1} l 10 -10 m -10 10 l -10 -10 m 10 10 l -10 10 m 10 -10 l 10 10" stroke="#117a65" stroke-width="3"/><text x="{tx:.1}" y="{y0:.1}" fill="#117a65">{}@{} = {:.3e} {}</text>"##,
                n.refit.effect,
                n.refit.location,
                n.refit.value,
                n.refit.unit,
                x0 = sx(x),
                y0 = sy(y),
                tx = sx(x) + 14.0
            );
        }
    }
    s.push_str("</svg>\n");
    s
}
