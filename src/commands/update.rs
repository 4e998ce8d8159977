//! `boltwatch update`: one full update from θ0, result as `boltwatch.update.v1`.

use std::path::PathBuf;

use anyhow::{Context, Result};
use serde_json::json;

use super::{load_model, parse_theta, write_json};
use crate::contract::modal_set::{ModalSet, ValidationContext, parse_modal_set};
use crate::core::model::Model;
use crate::core::updating::{
    AtBound, Evaluator, FinalStep, MeasuredData, ModeMatching, ModeMatchingOptions, StartPath,
    StepControl, Weighting, chi2_bound,
};

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Method {
    /// Sensitivity-based mode matching, paper §2.2.
    ModeMatching,
    /// Bayesian MAP without mode matching, paper §2.3 (objective (14)).
    Bayesian,
}

#[derive(Debug, clap::Args)]
pub struct UpdateArgs {
    /// Model file (TOML).
    #[arg(long)]
    pub model: PathBuf,
    /// Modal set (boltwatch.modal_set.v1).
    #[arg(long)]
    pub data: PathBuf,
    #[arg(long, value_enum, default_value_t = Method::ModeMatching)]
    pub method: Method,
    /// Starting θ, comma separated (default: the model's nominal θ).
    #[arg(long, allow_hyphen_values = true)]
    pub theta0: Option<String>,
    /// Reproduce the paper's Gauss–Newton (20) with this fixed step factor κ instead of
    /// the default Levenberg–Marquardt step control.
    #[arg(long)]
    pub kappa: Option<f64>,
    /// Stop when every |Δθ_i|/θ_i is below this.
    #[arg(long, default_value_t = 1e-5)]
    pub tol: f64,
    /// Mode matching: also stop when the Gauss–Newton step's predicted decrease of ε is
    /// below this (ε is a χ² quantity: a decrease of 1e-3 changes the likelihood by a
    /// factor 1.0005), so a parameter the data cannot pin down (a flat valley of ε) does
    /// not creep on for dozens of iterations.
    #[arg(long)]
    pub eps_tol: Option<f64>,
    /// Mode matching: keep every θ_i within `lo,hi` times its nominal value, or `none`. A
    /// parameter the data cannot pin down then stops at a bound (reported as such: the
    /// data only say it is beyond it) instead of running off while the fit stalls. The
    /// bounds hold the Levenberg–Marquardt steps; with `--kappa` (the paper's fixed-step
    /// Gauss–Newton, reproduced as published) they only clamp θ0.
    #[arg(long, default_value = "1e-3,1e3")]
    pub bounds: String,
    /// Maximum iterations (default: 200; 10⁶ for `--solver alternating`).
    #[arg(long)]
    pub max_iter: Option<usize>,
    /// Shape weight w_ψ of weighting (9), used when the set carries no uncertainties.
    #[arg(long, default_value_t = 1.0)]
    pub shape_weight: f64,
    /// Output file (boltwatch.update.v1).
    #[arg(short, long)]
    pub out: PathBuf,
    #[command(flatten)]
    pub bayes: super::bayes::BayesUpdateArgs,
}

/// A model, a validated modal set on it, its numbers as [`MeasuredData`], and θ0.
pub struct Inputs {
    pub model: Model,
    pub set: ModalSet,
    pub data: MeasuredData,
    pub theta0: Vec<f64>,
}

/// Loads and validates `--model`, `--data` and `--theta0` (shape weight for weighting (9)).
pub fn load_inputs(
    model: &std::path::Path,
    data: &std::path::Path,
    theta0: Option<&str>,
    shape_weight: f64,
) -> Result<Inputs> {
    let model = load_model(model)?;
    crate::core::numerics_for(&model);
    let theta0 = parse_theta(&model, theta0, "--theta0")?;
    let set = load_set(&model, data)?;
    if !(shape_weight.is_finite() && shape_weight > 0.0) {
        anyhow::bail!("--shape-weight = {shape_weight} must be a finite number > 0");
    }
    let data = measured_data(&set, &model, shape_weight);
    Ok(Inputs {
        model,
        set,
        data,
        theta0,
    })
}

/// Reads and validates a modal set against `model`.
pub fn load_set(model: &Model, path: &std::path::Path) -> Result<ModalSet> {
    let bytes =
        std::fs::read(path).with_context(|| format!("cannot read modal set {}", path.display()))?;
    let channels: Vec<String> = model.channels().iter().map(|c| c.name.clone()).collect();
    let ctx = ValidationContext {
        structures: &[model.name.as_str()],
        model_channels: &channels,
        last_time: None,
        allow_equal_time: true,
    };
    parse_modal_set(&bytes, &ctx).with_context(|| format!("modal set {} rejected", path.display()))
}

pub use crate::pipeline::measured_data;

pub fn run(args: &UpdateArgs) -> Result<()> {
    let inputs = load_inputs(
        &args.model,
        &args.data,
        args.theta0.as_deref(),
        args.shape_weight,
    )?;
    match args.method {
        Method::ModeMatching => run_mode_matching(args, &inputs),
        Method::Bayesian => super::bayes::run_update(args, &inputs),
    }
}

fn run_mode_matching(args: &UpdateArgs, inputs: &Inputs) -> Result<()> {
    let Inputs {
        model,
        set,
        data,
        theta0,
    } = inputs;
    let opts = ModeMatchingOptions {
        step: args
            .kappa
            .map_or(StepControl::LevenbergMarquardt, StepControl::FixedKappa),
        tol: args.tol,
        max_iterations: args.max_iter.unwrap_or(200),
        final_step: FinalStep::Evaluate,
        sigma_tol: None,
        eps_tol: args.eps_tol,
        bounds: parse_bounds(&args.bounds)?,
    };
    let mut mm = ModeMatching::new(Evaluator::new(model)?);
    let pb = iteration_progress("mode matching");
    let bar = pb.clone();
    mm.set_progress(Box::new(move |k, rec| {
        progress_line(
            &bar,
            format!(
                "iteration {k}: ε = {:.4}, θ = {}",
                rec.epsilon,
                fmt_theta(&rec.theta)
            ),
        );
    }));
    // The paper's fixed-κ Gauss–Newton runs as published; the default is globalized.
    let (res, path) = match opts.step {
        StepControl::FixedKappa(_) => (mm.run(model, data, theta0, &opts)?, StartPath::Given),
        StepControl::LevenbergMarquardt => mm.run_global(model, data, theta0, &opts)?,
    };
    pb.finish_and_clear();
    let start = match path {
        StartPath::Given => "theta0".to_string(),
        StartPath::Restart { value } => {
            format!("restart from uniform θ = {value} (the run from θ0 ended in a local minimum)")
        }
    };
    let std = res.std();
    let last = &res.last;
    let modes: Vec<_> = set
        .modes
        .iter()
        .enumerate()
        .map(|(m, mode)| {
            json!({
                "measured_hz": mode.frequency_hz,
                "model_hz": last.model_hz(m),
                "error": (last.model_hz(m) - mode.frequency_hz) / mode.frequency_hz,
                "mac": if last.mac[m].is_nan() { serde_json::Value::Null } else { json!(last.mac[m]) },
                "paired_with": last.pairing[m] + 1,
            })
        })
        .collect();
    let out = json!({
        "schema": "boltwatch.update.v1",
        "method": "mode-matching",
        "structure": set.structure,
        "time": set.time.to_rfc3339_opts(chrono::SecondsFormat::AutoSi, true),
        "converged": res.converged(),
        "termination": format!("{:?}", res.termination),
        "iterations": res.iterations,
        "evaluations": res.evaluations,
        "start": start,
        "chi2_bound": chi2_bound(data.n_data(), model.n_params()),
        "epsilon": res.epsilon(),
        "n_data": data.n_data(),
        "weighting": match data.weighting { Weighting::Covariance => "covariance (8)", Weighting::Heuristic { .. } => "heuristic (9)" },
        "parameters": model.parameters().iter().enumerate().map(|(l, p)| json!({
            "name": p.name, "theta": res.theta[l],
            "std": if std[l].is_nan() { serde_json::Value::Null } else { json!(std[l]) },
            "at_bound": match res.at_bound[l] {
                Some(AtBound::Upper) => json!("upper"),
                Some(AtBound::Lower) => json!("lower"),
                None => serde_json::Value::Null,
            },
        })).collect::<Vec<_>>(),
        "modes": modes,
    });
    write_json(&args.out, &out)?;
    print_table(model, set, &res, &std);
    println!("found from: {start}");
    Ok(())
}

/// A spinner on stderr for an iterative update, its message replaced at every iterate
/// (hidden when stderr is not a terminal).
pub fn iteration_progress(what: &str) -> indicatif::ProgressBar {
    let pb = indicatif::ProgressBar::new_spinner();
    pb.set_style(
        indicatif::ProgressStyle::with_template("{spinner} {prefix} [{elapsed}] {msg}")
            .expect("valid template"),
    );
    pb.set_prefix(what.to_string());
    pb.enable_steady_tick(std::time::Duration::from_millis(120));
    pb
}

/// Shows an iteration's line on `bar`; without a terminal (a log file, a service) the bar
/// is hidden, so the line goes to stderr instead and a long run can still be followed.
pub fn progress_line(bar: &indicatif::ProgressBar, line: String) {
    if bar.is_hidden() {
        eprintln!("{line}");
    }
    bar.set_message(line);
}

/// `--bounds`: `lo,hi` or `none`.
fn parse_bounds(s: &str) -> Result<Option<(f64, f64)>> {
    if s.trim() == "none" {
        return Ok(None);
    }
    let v: Vec<f64> = s
        .split(',')
        .map(|x| x.trim().parse::<f64>())
        .collect::<std::result::Result<_, _>>()
        .with_context(|| {
            format!("--bounds `{s}`: need `lo,hi` (factors of the nominal θ) or `none`")
        })?;
    match v[..] {
        [lo, hi] if lo > 0.0 && lo < 1.0 && hi > 1.0 && hi.is_finite() => Ok(Some((lo, hi))),
        _ => anyhow::bail!("--bounds `{s}`: need two factors 0 < lo < 1 < hi, or `none`"),
    }
}

/// θ as `(0.3600, 1.0000, …)`.
pub fn fmt_theta(theta: &[f64]) -> String {
    let v: Vec<String> = theta.iter().map(|t| format!("{t:.4}")).collect();
    format!("({})", v.join(", "))
}

fn print_table(
    model: &Model,
    set: &ModalSet,
    res: &crate::core::updating::ModeMatchingResult,
    std: &[f64],
) {
    println!("{:<12} {:>12} {:>12}", "parameter", "θ", "σ");
    for (l, p) in model.parameters().iter().enumerate() {
        let note = match res.at_bound[l] {
            Some(AtBound::Upper) => "  at its upper bound: the data say only that it is stiffer",
            Some(AtBound::Lower) => "  at its lower bound: the data say only that it is softer",
            None => "",
        };
        println!(
            "{:<12} {:>12.5} {:>12.5}{note}",
            p.name, res.theta[l], std[l]
        );
    }
    println!();
    println!(
        "{:>4} {:>12} {:>12} {:>9} {:>7} {:>6}",
        "mode", "measured Hz", "model Hz", "error %", "MAC", "pair"
    );
    for (m, mode) in set.modes.iter().enumerate() {
        let f = res.last.model_hz(m);
        println!(
            "{:>4} {:>12.3} {:>12.3} {:>9.3} {:>7.4} {:>6}",
            m + 1,
            mode.frequency_hz,
            f,
            100.0 * (f - mode.frequency_hz) / mode.frequency_hz,
            res.last.mac[m],
            res.last.pairing[m] + 1
        );
    }
    println!();
    println!(
        "{:?} after {} iterations ({} evaluations); ε = {:.4}",
        res.termination,
        res.iterations,
        res.evaluations,
        res.epsilon()
    );
}
