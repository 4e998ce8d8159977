//! `sweep-sigma`: the σ_c study of the Bayesian MAP (paper Figs. 5, 7, 15, 18): θ, the
//! objective's terms, ε and iterations against σ_c, as JSON and a plot, with the automatic
//! σ_c marked.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result};
use indicatif::{ProgressBar, ProgressStyle};

use super::bayes::{PriorArgs, prior, stage_docs};
use super::inputs::{Inputs, load_inputs};
use super::{parse_theta, write_json};
use crate::contract::Schema;
use crate::contract::sweep::{AlternatingDoc, NewtonRun, SweepAuto, SweepDoc, SweepPointDoc};
use crate::core::model::Model;
use crate::core::updating::bayesian::{
    AutoSigma, BayesProblem, BayesSettings, SweepPoint, SweepSettings, discrepancy_choice,
    log_grid, sweep_sigma,
};
use crate::plot::{Panel, Scale, Series, figure_svg};

/// `boltwatch sweep-sigma`.
#[derive(Debug, clap::Args)]
pub struct SweepArgs {
    /// Model file (TOML), a bundled model (`bundled:lab-frame`, `bundled:space-frame`, ...),
    /// or the `model.json` of a model imported from matrices.
    #[arg(long)]
    pub model: PathBuf,
    /// Modal set (boltwatch.modal_set.v1).
    #[arg(long)]
    pub data: PathBuf,
    /// Smallest σ_c.
    #[arg(long)]
    pub from: f64,
    /// Largest σ_c.
    #[arg(long)]
    pub to: f64,
    /// Number of σ_c values, log-spaced.
    #[arg(long, default_value_t = 25)]
    pub points: usize,
    /// Starting θ of every solve, comma separated (default: nominal θ).
    #[arg(long, allow_hyphen_values = true)]
    pub theta0: Option<String>,
    /// The exact θ, if known (simulated data): plotted, with the error of θ (Fig. 5a).
    #[arg(long)]
    pub truth: Option<String>,
    /// Also run the paper's alternating solver at every σ_c, up to this many iterations.
    #[arg(long)]
    pub alternating_max_iter: Option<usize>,
    /// Shape weight w_ψ of weighting (9), used when the set carries no uncertainties.
    #[arg(long, default_value_t = 1.0)]
    pub shape_weight: f64,
    #[command(flatten)]
    pub prior: PriorArgs,
    /// Output directory (sweep.json, sweep.svg).
    #[arg(short, long)]
    pub out: PathBuf,
}

/// `boltwatch sweep-sigma`: the MAP at every σ_c of the grid, the automatic σ_c, and the
/// study written (sweep.json, sweep.svg) and printed as a table.
pub fn run_sweep(args: &SweepArgs) -> Result<()> {
    let Inputs {
        model,
        data,
        theta0,
        ..
    } = load_inputs(
        &args.model,
        &args.data,
        args.theta0.as_deref(),
        args.shape_weight,
    )?;
    let truth = args
        .truth
        .as_deref()
        .map(|t| parse_theta(&model, Some(t), "--truth"))
        .transpose()?;
    let sigmas = log_grid(args.from, args.to, args.points)
        .map_err(|e| anyhow::anyhow!("--from/--to/--points: {e}"))?;
    let (mean, std) = prior(&model, &args.prior)?;
    let settings = SweepSettings {
        prior_mean: mean.clone(),
        prior_std: std.clone(),
        theta0,
        newton_max_iterations: 200,
        alternating_max_iterations: args.alternating_max_iter,
        bounds: None,
    };
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("cannot create {}", args.out.display()))?;
    let pb = progress_bar(sigmas.len());
    let started = Instant::now();
    let points = sweep_sigma(&model, &data, &sigmas, &settings, &mut |_, p| {
        pb.set_message(format!("{:.3e}", p.sigma_c));
        pb.inc(1);
    })?;
    pb.finish_and_clear();
    let nu = BayesProblem::new(
        &model,
        &data,
        &BayesSettings {
            sigma_c: 1.0,
            prior_mean: mean,
            prior_std: std,
        },
    )?
    .misfit_dof();
    let auto = discrepancy_choice(&points, nu).expect("a sweep has at least two points");
    let out = sweep_doc(&model, truth.clone(), started, &auto, nu, &points);
    write_json(&args.out.join("sweep.json"), &out)?;
    let svg = figure_svg(&sweep_panels(&model, &points, truth.as_deref(), &auto), 2);
    let svg_path = args.out.join("sweep.svg");
    std::fs::write(&svg_path, svg)
        .with_context(|| format!("cannot write {}", svg_path.display()))?;
    print_sweep_table(&model, &points);
    print_auto(&auto, nu);
    println!(
        "wrote {} and {}",
        args.out.join("sweep.json").display(),
        svg_path.display()
    );
    Ok(())
}

/// The progress bar of a sweep over `n` values of σ_c.
fn progress_bar(n: usize) -> ProgressBar {
    let pb = ProgressBar::new(n as u64);
    pb.set_style(
        ProgressStyle::with_template("{bar:40} {pos}/{len} σ_c  {msg}  [{elapsed_precise}]")
            .expect("static template"),
    );
    pb
}

/// The sweep as its JSON document: the model, the automatic σ_c (held to ν = `nu`), and
/// every point; the time taken counted from `started`.
fn sweep_doc(
    model: &Model,
    truth: Option<Vec<f64>>,
    started: Instant,
    auto: &AutoSigma,
    nu: f64,
    points: &[SweepPoint],
) -> SweepDoc {
    SweepDoc {
        schema: Schema::new(),
        model: model.name.clone(),
        parameters: model.parameters().iter().map(|p| p.name.clone()).collect(),
        truth,
        seconds: started.elapsed().as_secs_f64(),
        auto: SweepAuto {
            rule: "smallest σ_c at which e_Mᵀ Σ_M⁻¹ e_M ≤ ν = N_data − N_θ − N_m (discrepancy principle), interpolated on the grid".into(),
            sigma_c: auto.sigma_c,
            nu,
            met: auto.met,
        },
        points: points.iter().map(point_doc).collect(),
    }
}

/// One point of the sweep as its JSON document.
fn point_doc(p: &SweepPoint) -> SweepPointDoc {
    SweepPointDoc {
        sigma_c: p.sigma_c,
        theta: p.theta.clone(),
        most_probable_lambda: p.lambda.clone(),
        J_p: p.terms.total,
        measurement_misfit: p.terms.measurement,
        modelling_error: p.terms.modelling,
        prior_term: p.terms.prior,
        epsilon: p.epsilon,
        mac_most_probable_to_measured: p.mac.clone(),
        newton: NewtonRun {
            iterations: p.iterations,
            converged: p.converged,
            continuation: stage_docs(&p.stages),
        },
        alternating: p.alternating.as_ref().map(|a| AlternatingDoc {
            iterations: a.iterations,
            converged: a.converged,
            theta: a.theta.clone(),
            J_p: a.total,
        }),
    }
}

/// The automatic σ_c, and whether the misfit came down to ν = `nu` within the range.
fn print_auto(auto: &AutoSigma, nu: f64) {
    println!(
        "automatic σ_c (discrepancy rule, ν = {nu}): {:.4e}{}",
        auto.sigma_c,
        if auto.met {
            ""
        } else {
            " — misfit still above ν at the top of the range"
        }
    );
}

/// The sweep as a table: the error terms, ε, least MAC, the first θ and the iterations
/// per σ_c.
fn print_sweep_table(model: &Model, points: &[SweepPoint]) {
    let p = model.n_params().min(4);
    print!(
        "{:>11} {:>11} {:>11} {:>11} {:>8}",
        "σ_c", "e_MΣ⁻¹e_M", "e_Cᵀe_C", "ε", "min MAC"
    );
    for par in &model.parameters()[..p] {
        print!(" {:>10}", par.name.chars().take(10).collect::<String>());
    }
    println!(" {:>7} {:>10}", "Newton", "altern.");
    for pt in points {
        print!(
            "{:>11.4e} {:>11.4e} {:>11.4e} {:>11.4e} {:>8.4}",
            pt.sigma_c,
            pt.terms.measurement,
            pt.terms.modelling,
            pt.epsilon,
            pt.mac.iter().copied().fold(1.0, f64::min)
        );
        for t in &pt.theta[..p] {
            print!(" {t:>10.5}");
        }
        let alt = pt.alternating.as_ref().map_or("-".into(), |a| {
            format!("{}{}", a.iterations, if a.converged { "" } else { "+" })
        });
        println!(" {:>7} {alt:>10}", pt.iterations);
    }
}

/// The panels of the study against σ_c (paper Figs. 5, 7, 15, 18), the automatic σ_c
/// marked on each: θ, the two error terms, ε, iterations, MAC, and with `truth` the error
/// of θ.
fn sweep_panels(
    model: &Model,
    points: &[SweepPoint],
    truth: Option<&[f64]>,
    auto: &AutoSigma,
) -> Vec<Panel> {
    let x: Vec<f64> = points.iter().map(|p| p.sigma_c).collect();
    let mark = vec![(auto.sigma_c, "auto σ_c".to_string())];
    let mut panels = vec![
        theta_panel(model, points, truth, &x, &mark),
        errors_panel(points, auto, &x, &mark),
        epsilon_panel(points, &x, &mark),
        iterations_panel(points, &x),
        mac_panel(points, &x),
    ];
    if let Some(t) = truth {
        panels.push(theta_error_panel(points, t, &x, mark));
    }
    panels
}

/// (a) The MAP θ, a line per parameter, with the exact θ when known.
fn theta_panel(
    model: &Model,
    points: &[SweepPoint],
    truth: Option<&[f64]>,
    x: &[f64],
    mark: &[(f64, String)],
) -> Panel {
    let mut theta = Panel::new("(a) MAP θ", "σ_c", "θ", Scale::Log, Scale::Linear);
    for (l, par) in model.parameters().iter().enumerate() {
        theta.series.push(Series::line(
            par.name.clone(),
            x.to_vec(),
            points.iter().map(|p| p.theta[l]).collect(),
        ));
        if let Some(t) = truth {
            theta.hlines.push((t[l], format!("exact {}", par.name)));
        }
    }
    theta.vlines = mark.to_vec();
    theta
}

/// (b) The modelling error e_Cᵀe_C and the measurement misfit e_Mᵀ Σ_M⁻¹ e_M, with the
/// target ν of the automatic σ_c.
fn errors_panel(
    points: &[SweepPoint],
    auto: &AutoSigma,
    x: &[f64],
    mark: &[(f64, String)],
) -> Panel {
    let mut errors = Panel::new(
        "(b) modelling and measurement error",
        "σ_c",
        "",
        Scale::Log,
        Scale::Log,
    );
    errors.series.push(Series::line(
        "e_Cᵀe_C",
        x.to_vec(),
        points.iter().map(|p| p.terms.modelling).collect(),
    ));
    errors.series.push(Series::line(
        "e_Mᵀ Σ_M⁻¹ e_M",
        x.to_vec(),
        points.iter().map(|p| p.terms.measurement).collect(),
    ));
    errors
        .hlines
        .push((auto.target, format!("ν = {}", auto.target)));
    errors.vlines = mark.to_vec();
    errors
}

/// (c) ε (5) of the model at the MAP θ.
fn epsilon_panel(points: &[SweepPoint], x: &[f64], mark: &[(f64, String)]) -> Panel {
    let mut eps = Panel::new(
        "(c) ε (5) of the model at the MAP θ",
        "σ_c",
        "ε",
        Scale::Log,
        Scale::Log,
    );
    eps.series.push(Series::line(
        "ε",
        x.to_vec(),
        points.iter().map(|p| p.epsilon).collect(),
    ));
    eps.vlines = mark.to_vec();
    eps
}

/// (d) Iterations to the MAP: Newton's, and the alternating solver's when it ran.
fn iterations_panel(points: &[SweepPoint], x: &[f64]) -> Panel {
    let mut iters = Panel::new(
        "(d) iterations to the MAP",
        "σ_c",
        "iterations",
        Scale::Log,
        Scale::Log,
    );
    iters.series.push(Series::line(
        "Newton (reduced)",
        x.to_vec(),
        points.iter().map(|p| p.iterations as f64).collect(),
    ));
    if points.iter().any(|p| p.alternating.is_some()) {
        iters.series.push(Series::line(
            "alternating (21)–(23)",
            x.to_vec(),
            points
                .iter()
                .map(|p| {
                    p.alternating
                        .as_ref()
                        .map_or(f64::NAN, |a| a.iterations as f64)
                })
                .collect(),
        ));
    }
    iters
}

/// (e) MAC of each most probable shape to the measured one, a line per mode.
fn mac_panel(points: &[SweepPoint], x: &[f64]) -> Panel {
    let mut mac = Panel::new(
        "(e) MAC of most probable to measured shapes",
        "σ_c",
        "MAC",
        Scale::Log,
        Scale::Linear,
    );
    let nm = points.first().map_or(0, |p| p.mac.len());
    for m in 0..nm {
        mac.series.push(Series::line(
            format!("mode {}", m + 1),
            x.to_vec(),
            points.iter().map(|p| p.mac[m]).collect(),
        ));
    }
    mac
}

/// (f) The largest relative error of θ against the exact θ `t`.
fn theta_error_panel(
    points: &[SweepPoint],
    t: &[f64],
    x: &[f64],
    mark: Vec<(f64, String)>,
) -> Panel {
    let mut err = Panel::new(
        "(f) max relative error of θ",
        "σ_c",
        "max |θ − θ_exact| / θ_exact",
        Scale::Log,
        Scale::Log,
    );
    err.series.push(Series::line(
        "max rel. error",
        x.to_vec(),
        points
            .iter()
            .map(|p| {
                p.theta
                    .iter()
                    .zip(t)
                    .map(|(a, b)| ((a - b) / b).abs())
                    .fold(0.0, f64::max)
            })
            .collect(),
    ));
    err.vlines = mark;
    err
}
