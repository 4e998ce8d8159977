//! `update --method bayesian` and `sweep-sigma`: the Bayesian MAP (paper §2.3) from the
//! command line, its uncertainty, the σ_c study (Figs. 5, 7, 15, 18) and the two-stage use
//! (§4.2).

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use indicatif::{ProgressBar, ProgressStyle};
use serde_json::{Value, json};

use super::update::{Inputs, UpdateArgs, load_inputs, measured_data};
use super::{load_model, parse_theta, write_json};
use crate::core::model::Model;
use crate::core::updating::bayesian::{
    AutoSigma, BayesProblem, BayesResult, BayesSettings, BayesSolver, ContinuationStage,
    SigmaTrial, SweepPoint, SweepSettings, discrepancy_choice, log_grid, sweep_sigma,
};
use crate::core::updating::{Evaluator, MeasuredData, ModeMatching, ModeMatchingOptions};
use crate::plot::{Panel, Scale, Series, figure_svg};

/// Default prior standard deviation of θ: non-informative, as in the paper (§4.2).
pub const DEFAULT_PRIOR_STD: f64 = 1000.0;
/// Default range searched by `--sigma-c auto`.
pub const DEFAULT_SIGMA_RANGE: (f64, f64) = (1.0, 1e8);
/// Relative precision of the automatic σ_c.
pub const AUTO_SIGMA_TOL: f64 = 0.05;

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum SolverArg {
    /// Damped Newton on the reduced objective (φ eliminated); default.
    Newton,
    /// The paper's alternating substeps (21)–(23).
    Alternating,
}

/// Prior of (12): shared by `update --method bayesian` and `sweep-sigma`.
#[derive(Debug, Clone, clap::Args)]
pub struct PriorArgs {
    /// Prior standard deviation of θ about the model's nominal θ (Σ_θ = diag(std²), (12)):
    /// one value, or one per parameter, comma separated. Default: the model file's
    /// `[bayesian] prior_std`, else 1000 (non-informative, as in the paper).
    #[arg(long)]
    pub prior_std: Option<String>,
}

/// The Bayesian options of `update`.
#[derive(Debug, Clone, clap::Args)]
pub struct BayesUpdateArgs {
    /// Minimizer of (14) (with `--method bayesian`).
    #[arg(long, value_enum, default_value_t = SolverArg::Newton)]
    pub solver: SolverArg,
    /// σ_c of (14): a number, or `auto` for the discrepancy rule (see `sweep-sigma`).
    /// Default: the model file's `[bayesian] sigma_c`, else `auto`.
    #[arg(long, allow_hyphen_values = true)]
    pub sigma_c: Option<String>,
    /// Range searched by `--sigma-c auto`, `from,to`.
    #[arg(long, default_value = "1,1e8")]
    pub sigma_range: String,
    #[command(flatten)]
    pub prior: PriorArgs,
    /// Skip the TSVD / L-curve covariance (24)–(25) (a dense eigendecomposition of (16)).
    #[arg(long)]
    pub no_tsvd: bool,
    /// Two-stage update (paper §4.2): first update this coarser model of the same
    /// structure, then start the fine update from its θ mapped onto the fine parameters.
    #[arg(long)]
    pub stage1_model: Option<PathBuf>,
    /// Modes used in stage I (default: all; the paper uses 5).
    #[arg(long)]
    pub stage1_modes: Option<usize>,
    /// σ_c of stage I: a number or `auto` (default: as `--sigma-c`).
    #[arg(long)]
    pub stage1_sigma_c: Option<String>,
}

fn parse_list(s: &str, flag: &str) -> Result<Vec<f64>> {
    s.split(',')
        .enumerate()
        .map(|(i, v)| {
            let x: f64 = v
                .trim()
                .parse()
                .with_context(|| format!("{flag}: entry {} `{v}` is not a number", i + 1))?;
            if !(x.is_finite() && x > 0.0) {
                bail!("{flag}: entry {} = {x} must be a finite number > 0", i + 1);
            }
            Ok(x)
        })
        .collect()
}

/// The prior of (12) for `model`: mean = nominal θ, std from the flag or the model file.
fn prior(model: &Model, args: &PriorArgs) -> Result<(Vec<f64>, Vec<f64>)> {
    let p = model.n_params();
    let std = match &args.prior_std {
        Some(s) => {
            let v = parse_list(s, "--prior-std")?;
            match v.len() {
                1 => vec![v[0]; p],
                n if n == p => v,
                n => bail!(
                    "--prior-std: {n} values given but model `{}` has {p} parameters",
                    model.name
                ),
            }
        }
        None => vec![model.bayesian.prior_std.unwrap_or(DEFAULT_PRIOR_STD); p],
    };
    Ok((model.nominal_theta(), std))
}

fn parse_range(s: &str) -> Result<(f64, f64)> {
    let v = parse_list(s, "--sigma-range")?;
    match v[..] {
        [a, b] if a < b => Ok((a, b)),
        _ => bail!("--sigma-range `{s}`: need two numbers `from,to` with 0 < from < to"),
    }
}

fn spinner(msg: String) -> ProgressBar {
    let pb = ProgressBar::new_spinner();
    pb.set_message(msg);
    pb.enable_steady_tick(std::time::Duration::from_millis(120));
    pb
}

/// σ_c from `--sigma-c` (number or `auto`), the model file, or the automatic rule.
fn choose_sigma(
    model: &Model,
    data: &MeasuredData,
    arg: Option<&str>,
    range: (f64, f64),
    settings: &SweepSettings,
) -> Result<(f64, Option<AutoSigma>)> {
    let arg = arg
        .map(str::to_string)
        .or_else(|| model.bayesian.sigma_c.map(|v| v.to_string()))
        .unwrap_or_else(|| "auto".into());
    if arg.trim() == "auto" {
        let pb = spinner(format!(
            "σ_c by the discrepancy rule in [{:e}, {:e}]",
            range.0, range.1
        ));
        let mut report = |t: SigmaTrial| {
            let line = match t.misfit {
                None => format!("σ_c trial {}: the MAP at σ_c = {:.4e}", t.index, t.sigma_c),
                Some(m) => format!(
                    "σ_c trial {}: σ_c = {:.4e}, misfit {m:.1} (target ν = {:.1})",
                    t.index, t.sigma_c, t.target
                ),
            };
            super::update::progress_line(&pb, line);
        };
        let auto = AutoSigma::search(
            model,
            data,
            range.0,
            range.1,
            settings,
            AUTO_SIGMA_TOL,
            &mut report,
        )?;
        pb.finish_and_clear();
        Ok((auto.sigma_c, Some(auto)))
    } else {
        Ok((parse_list(&arg, "--sigma-c")?[0], None))
    }
}

fn auto_json(auto: &Option<AutoSigma>) -> Value {
    match auto {
        None => Value::Null,
        Some(a) => json!({
            "rule": "smallest σ_c at which e_Mᵀ Σ_M⁻¹ e_M ≤ ν = N_data − N_θ − N_m (discrepancy principle)",
            "nu": a.target,
            "misfit": a.misfit,
            "met": a.met,
            "trials": a.trials.iter().map(|(s, m)| json!({"sigma_c": s, "misfit": m})).collect::<Vec<_>>(),
        }),
    }
}

/// The σ_c continuation of a Newton solve (one stage when the cold start converged).
fn stages_json(stages: &[ContinuationStage]) -> Value {
    stages
        .iter()
        .map(
            |s| json!({"sigma_c": s.sigma_c, "iterations": s.iterations, "converged": s.converged}),
        )
        .collect()
}

fn num_or_null(v: f64) -> Value {
    if v.is_finite() { json!(v) } else { Value::Null }
}

/// Stage I of the two-stage update: its result and the fine θ0 it gives.
struct StageOne {
    json: Value,
    theta0: Vec<f64>,
}

/// Stage I reads the same modal set as stage II: it was validated against the fine model
/// (structure name, channels), and every channel must exist in the coarse model too.
fn stage_one(
    args: &UpdateArgs,
    fine: &Model,
    fine_set: &crate::contract::modal_set::ModalSet,
    max_iter: usize,
) -> Result<StageOne> {
    let b = &args.bayes;
    let path = b
        .stage1_model
        .as_ref()
        .expect("called with a stage-I model");
    let coarse = load_model(path)?;
    if let Some(c) = fine_set
        .channels
        .iter()
        .find(|c| coarse.channel_index(c).is_none())
    {
        bail!(
            "--stage1-model {}: channel `{c}` of the modal set is not in model `{}`",
            path.display(),
            coarse.name
        );
    }
    let mut set = fine_set.clone();
    if let Some(n) = b.stage1_modes {
        if n == 0 || n > set.modes.len() {
            bail!(
                "--stage1-modes = {n}: the modal set has {} modes",
                set.modes.len()
            );
        }
        set.modes.truncate(n);
    }
    let data = measured_data(&set, &coarse, args.shape_weight);
    let (mean, std) = prior(&coarse, &b.prior)?;
    let theta0 = coarse.nominal_theta();
    let settings = SweepSettings {
        prior_mean: mean.clone(),
        prior_std: std.clone(),
        theta0: theta0.clone(),
        newton_max_iterations: max_iter,
        alternating_max_iterations: None,
    };
    let sigma_arg = b.stage1_sigma_c.as_deref().or(b.sigma_c.as_deref());
    let (sigma_c, auto) = choose_sigma(
        &coarse,
        &data,
        sigma_arg,
        parse_range(&b.sigma_range)?,
        &settings,
    )?;
    let mut prob = BayesProblem::new(
        &coarse,
        &data,
        &BayesSettings {
            sigma_c,
            prior_mean: mean,
            prior_std: std,
        },
    )?;
    let res = prob.solve(solver(b.solver), &theta0, max_iter)?;
    if !res.converged {
        bail!(
            "stage I ({}) did not converge in {} iterations",
            coarse.name,
            res.iterations
        );
    }
    let mapped = fine.refine_theta(&coarse, &res.state.theta)?;
    println!(
        "stage I: {} at σ_c = {sigma_c:.4e}, {} modes, {} iterations: θ̃ = [{}]",
        coarse.name,
        set.modes.len(),
        res.iterations,
        res.state
            .theta
            .iter()
            .map(|t| format!("{t:.4}"))
            .collect::<Vec<_>>()
            .join(", ")
    );
    Ok(StageOne {
        json: json!({
            "model": coarse.name,
            "modes": set.modes.len(),
            "sigma_c": sigma_c,
            "sigma_c_auto": auto_json(&auto),
            "iterations": res.iterations,
            "J_p": res.terms.total,
            "parameters": coarse.parameters().iter().zip(&res.state.theta)
                .map(|(p, t)| json!({"name": p.name, "theta": t})).collect::<Vec<_>>(),
            "mapping": fine.parameters().iter().zip(&mapped).map(|(p, (v, c))| json!({
                "name": p.name, "theta0": v,
                "from": c.map(|c| coarse.parameters()[c].name.clone()),
            })).collect::<Vec<_>>(),
        }),
        theta0: mapped.iter().map(|(v, _)| *v).collect(),
    })
}

fn solver(s: SolverArg) -> BayesSolver {
    match s {
        SolverArg::Newton => BayesSolver::Newton,
        SolverArg::Alternating => BayesSolver::Alternating,
    }
}

/// `update --method bayesian`.
pub fn run_update(args: &UpdateArgs, inputs: &Inputs) -> Result<()> {
    let Inputs {
        model, set, data, ..
    } = inputs;
    let b = &args.bayes;
    let max_iter = args.max_iter.unwrap_or(match b.solver {
        SolverArg::Newton => 200,
        SolverArg::Alternating => 1_000_000,
    });
    let stage1 = match &b.stage1_model {
        Some(_) => Some(stage_one(args, model, set, max_iter)?),
        None => None,
    };
    let theta0 = stage1
        .as_ref()
        .map_or_else(|| inputs.theta0.clone(), |s| s.theta0.clone());
    let (mean, std) = prior(model, &b.prior)?;
    let settings = SweepSettings {
        prior_mean: mean.clone(),
        prior_std: std.clone(),
        theta0: theta0.clone(),
        newton_max_iterations: 200,
        alternating_max_iterations: None,
    };
    let (sigma_c, auto) = choose_sigma(
        model,
        data,
        b.sigma_c.as_deref(),
        parse_range(&b.sigma_range)?,
        &settings,
    )?;
    let mut prob = BayesProblem::new(
        model,
        data,
        &BayesSettings {
            sigma_c,
            prior_mean: mean,
            prior_std: std.clone(),
        },
    )?;
    let pb = super::update::iteration_progress(&format!(
        "MAP by the {:?} solver at σ_c = {sigma_c:.4e}",
        b.solver
    ));
    let bar = pb.clone();
    prob.set_progress(Box::new(move |s, k, value, theta| {
        super::update::progress_line(
            &bar,
            format!(
                "stage σ_c = {s:.3e}, iteration {k}: objective {value:.6e}, θ = {}",
                super::update::fmt_theta(theta)
            ),
        );
    }));
    let started = Instant::now();
    let res = prob.solve(solver(b.solver), &theta0, max_iter)?;
    let seconds = started.elapsed().as_secs_f64();
    pb.finish_and_clear();
    let free = prob.threshold_free_covariance(&res.state);
    if let Err(e) = &free {
        eprintln!("warning: no threshold-free covariance: {e}");
    }
    let tsvd = if b.no_tsvd {
        None
    } else {
        let pb = spinner("TSVD of the Hessian (16) and the L-curve (24)–(25)".into());
        let t = prob.tsvd_covariance(&res.state);
        pb.finish_and_clear();
        match t {
            Ok(t) => Some(t),
            Err(e) => {
                eprintln!("warning: no TSVD covariance: {e}");
                None
            }
        }
    };
    let eval = Evaluator::new(model)?.evaluate(model, data, &res.state.theta)?;
    // Mode matching from the same θ0, for comparison.
    let mm = ModeMatching::new(Evaluator::new(model)?)
        .run_global(model, data, &theta0, &ModeMatchingOptions::default())
        .ok()
        .filter(|(r, _)| r.converged())
        .map(|(r, _)| r);
    let macs = prob.mac_to_measured(&res.state.phi);
    let p = model.n_params();
    let nan = vec![f64::NAN; p];
    let (post, samp) = match &free {
        Ok(f) => (f.posterior_theta_std(), f.sampling_theta_std()),
        Err(_) => (nan.clone(), nan.clone()),
    };
    let lambda_std = match &free {
        Ok(f) => f.posterior_lambda_std(),
        Err(_) => vec![f64::NAN; prob.n_modes()],
    };
    let tsvd_std = tsvd.as_ref().map_or(nan.clone(), |t| t.theta_std());
    let two_pi = 2.0 * std::f64::consts::PI;
    let out = json!({
        "schema": "boltwatch.update.v1",
        "method": "bayesian",
        "structure": set.structure,
        "time": set.time.to_rfc3339_opts(chrono::SecondsFormat::AutoSi, true),
        "converged": res.converged,
        "termination": termination(&res),
        "iterations": res.iterations,
        "seconds": seconds,
        "solver": format!("{:?}", res.solver).to_lowercase(),
        "start": if stage1.is_some() { "stage I" } else { "theta0" },
        "epsilon": eval.epsilon,
        "n_data": data.n_data(),
        "bayesian": {
            "sigma_c": sigma_c,
            "sigma_c_auto": auto_json(&auto),
            "prior_std": std,
            "J_p": res.terms.total,
            "measurement_misfit": res.terms.measurement,
            "modelling_error": res.terms.modelling,
            "prior_term": res.terms.prior,
            "misfit_dof": prob.misfit_dof(),
            "continuation": stages_json(&res.stages),
            "tsvd": tsvd.as_ref().map(|t| json!({
                "s_tol": t.s_tol(),
                "kept": t.curve[t.chosen].kept,
                "of": t.singular_values.len(),
                "condition": t.condition(),
                "corner_rule": "least E (25): where E stops falling as singular values are added; points with a negative variance excluded",
                "l_curve": t.curve.iter().map(|c| json!({
                    "s_tol": c.s_tol, "E": c.error, "norm": c.norm, "negative_variance": c.negative_variance,
                })).collect::<Vec<_>>(),
            })),
        },
        "stage1": stage1.as_ref().map(|s| s.json.clone()),
        "parameters": model.parameters().iter().enumerate().map(|(l, par)| json!({
            "name": par.name,
            "theta": res.state.theta[l],
            "std": num_or_null(post[l]),
            "sampling_std": num_or_null(samp[l]),
            "tsvd_std": num_or_null(tsvd_std[l]),
            "mode_matching_theta": mm.as_ref().map(|r| r.theta[l]),
        })).collect::<Vec<_>>(),
        "modes": set.modes.iter().enumerate().map(|(m, mode)| json!({
            "measured_hz": mode.frequency_hz,
            "most_probable_lambda": res.state.lambda[m],
            "most_probable_lambda_std": num_or_null(lambda_std[m]),
            "most_probable_hz": res.state.lambda[m].max(0.0).sqrt() / two_pi,
            "mac_most_probable_to_measured": macs[m],
            "model_hz": eval.model_hz(m),
            "model_mac": num_or_null(eval.mac[m]),
        })).collect::<Vec<_>>(),
    });
    write_json(&args.out, &out)?;
    print_bayes_table(
        model,
        set,
        &res,
        &eval,
        &macs,
        (&post, &samp, &tsvd_std),
        mm.as_ref(),
    );
    println!(
        "σ_c = {sigma_c:.4e}{}; {:?} solver: {} after {} iterations in {seconds:.2} s",
        if auto.is_some() { " (automatic)" } else { "" },
        res.solver,
        match termination(&res) {
            "converged" => "converged",
            "boundary" => "NOT converged (stopped against θ > 0 or λ > 0: no interior minimum)",
            _ => "NOT converged",
        },
        res.iterations
    );
    println!(
        "J_p = {:.6e}: e_Mᵀ Σ_M⁻¹ e_M = {:.4e} (ν = {}), e_Cᵀe_C = {:.4e}, prior {:.3e}; ε(θ_MAP) = {:.4e}",
        res.terms.total,
        res.terms.measurement,
        prob.misfit_dof(),
        res.terms.modelling,
        res.terms.prior,
        eval.epsilon
    );
    if let Some(t) = &tsvd {
        println!(
            "TSVD: cond(H) = {:.2e}, s_tol = {:.4e} (L-curve corner, {} of {} kept)",
            t.condition(),
            t.s_tol(),
            t.curve[t.chosen].kept,
            t.singular_values.len()
        );
    }
    Ok(())
}

fn print_bayes_table(
    model: &Model,
    set: &crate::contract::modal_set::ModalSet,
    res: &BayesResult,
    eval: &crate::core::updating::Evaluation,
    macs: &[f64],
    (post, samp, tsvd): (&[f64], &[f64], &[f64]),
    mm: Option<&crate::core::updating::ModeMatchingResult>,
) {
    println!(
        "{:<12} {:>11} {:>11} {:>11} {:>11} {:>11}",
        "parameter", "θ MAP", "σ post.", "σ sampling", "σ TSVD", "θ mode m."
    );
    for (l, p) in model.parameters().iter().enumerate() {
        println!(
            "{:<12} {:>11.5} {:>11.5} {:>11.5} {:>11.3e} {:>11}",
            p.name,
            res.state.theta[l],
            post[l],
            samp[l],
            tsvd[l],
            mm.map_or("-".into(), |r| format!("{:.5}", r.theta[l]))
        );
    }
    println!();
    println!(
        "{:>4} {:>12} {:>14} {:>12} {:>9} {:>9}",
        "mode", "measured Hz", "most prob. Hz", "model Hz", "MAC m.p.", "MAC model"
    );
    let two_pi = 2.0 * std::f64::consts::PI;
    for (m, mode) in set.modes.iter().enumerate() {
        println!(
            "{:>4} {:>12.3} {:>14.3} {:>12.3} {:>9.4} {:>9.4}",
            m + 1,
            mode.frequency_hz,
            res.state.lambda[m].max(0.0).sqrt() / two_pi,
            eval.model_hz(m),
            macs[m],
            eval.mac[m]
        );
    }
    println!();
}

/// `boltwatch sweep-sigma`.
#[derive(Debug, clap::Args)]
pub struct SweepArgs {
    /// Model file (TOML).
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
    };
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("cannot create {}", args.out.display()))?;
    let pb = ProgressBar::new(sigmas.len() as u64);
    pb.set_style(
        ProgressStyle::with_template("{bar:40} {pos}/{len} σ_c  {msg}  [{elapsed_precise}]")
            .expect("static template"),
    );
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
    let out = json!({
        "schema": "boltwatch.sigma_sweep.v1",
        "model": model.name,
        "parameters": model.parameters().iter().map(|p| p.name.clone()).collect::<Vec<_>>(),
        "truth": truth,
        "seconds": started.elapsed().as_secs_f64(),
        "auto": {
            "rule": "smallest σ_c at which e_Mᵀ Σ_M⁻¹ e_M ≤ ν = N_data − N_θ − N_m (discrepancy principle), interpolated on the grid",
            "sigma_c": auto.sigma_c, "nu": nu, "met": auto.met,
        },
        "points": points.iter().map(|p| json!({
            "sigma_c": p.sigma_c,
            "theta": p.theta,
            "most_probable_lambda": p.lambda,
            "J_p": p.terms.total,
            "measurement_misfit": p.terms.measurement,
            "modelling_error": p.terms.modelling,
            "prior_term": p.terms.prior,
            "epsilon": p.epsilon,
            "mac_most_probable_to_measured": p.mac,
            "newton": {"iterations": p.iterations, "converged": p.converged, "continuation": stages_json(&p.stages)},
            "alternating": p.alternating.as_ref().map(|a| json!({
                "iterations": a.iterations, "converged": a.converged, "theta": a.theta, "J_p": a.total,
            })),
        })).collect::<Vec<_>>(),
    });
    write_json(&args.out.join("sweep.json"), &out)?;
    let svg = figure_svg(&sweep_panels(&model, &points, truth.as_deref(), &auto), 2);
    let svg_path = args.out.join("sweep.svg");
    std::fs::write(&svg_path, svg)
        .with_context(|| format!("cannot write {}", svg_path.display()))?;
    print_sweep_table(&model, &points);
    println!(
        "automatic σ_c (discrepancy rule, ν = {nu}): {:.4e}{}",
        auto.sigma_c,
        if auto.met {
            ""
        } else {
            " — misfit still above ν at the top of the range"
        }
    );
    println!(
        "wrote {} and {}",
        args.out.join("sweep.json").display(),
        svg_path.display()
    );
    Ok(())
}

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

fn sweep_panels(
    model: &Model,
    points: &[SweepPoint],
    truth: Option<&[f64]>,
    auto: &AutoSigma,
) -> Vec<Panel> {
    let x: Vec<f64> = points.iter().map(|p| p.sigma_c).collect();
    let mark = vec![(auto.sigma_c, "auto σ_c".to_string())];
    let mut theta = Panel::new("(a) MAP θ", "σ_c", "θ", Scale::Log, Scale::Linear);
    for (l, par) in model.parameters().iter().enumerate() {
        theta.series.push(Series::line(
            par.name.clone(),
            x.clone(),
            points.iter().map(|p| p.theta[l]).collect(),
        ));
        if let Some(t) = truth {
            theta.hlines.push((t[l], format!("exact {}", par.name)));
        }
    }
    theta.vlines = mark.clone();
    let mut errors = Panel::new(
        "(b) modelling and measurement error",
        "σ_c",
        "",
        Scale::Log,
        Scale::Log,
    );
    errors.series.push(Series::line(
        "e_Cᵀe_C",
        x.clone(),
        points.iter().map(|p| p.terms.modelling).collect(),
    ));
    errors.series.push(Series::line(
        "e_Mᵀ Σ_M⁻¹ e_M",
        x.clone(),
        points.iter().map(|p| p.terms.measurement).collect(),
    ));
    errors
        .hlines
        .push((auto.target, format!("ν = {}", auto.target)));
    errors.vlines = mark.clone();
    let mut eps = Panel::new(
        "(c) ε (5) of the model at the MAP θ",
        "σ_c",
        "ε",
        Scale::Log,
        Scale::Log,
    );
    eps.series.push(Series::line(
        "ε",
        x.clone(),
        points.iter().map(|p| p.epsilon).collect(),
    ));
    eps.vlines = mark.clone();
    let mut iters = Panel::new(
        "(d) iterations to the MAP",
        "σ_c",
        "iterations",
        Scale::Log,
        Scale::Log,
    );
    iters.series.push(Series::line(
        "Newton (reduced)",
        x.clone(),
        points.iter().map(|p| p.iterations as f64).collect(),
    ));
    if points.iter().any(|p| p.alternating.is_some()) {
        iters.series.push(Series::line(
            "alternating (21)–(23)",
            x.clone(),
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
            x.clone(),
            points.iter().map(|p| p.mac[m]).collect(),
        ));
    }
    let mut panels = vec![theta, errors, eps, iters, mac];
    if let Some(t) = truth {
        let mut err = Panel::new(
            "(f) max relative error of θ",
            "σ_c",
            "max |θ − θ_exact| / θ_exact",
            Scale::Log,
            Scale::Log,
        );
        err.series.push(Series::line(
            "max rel. error",
            x.clone(),
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
        panels.push(err);
    }
    panels
}

/// The `termination` of `boltwatch.update.v1` for a MAP solve: `converged`, `boundary` (no
/// step lowers J_p and the Hessian is not positive definite there: the minimum lies outside
/// θ > 0, λ > 0, or at a saddle) or `max_iterations`.
fn termination(res: &BayesResult) -> &'static str {
    if res.converged {
        "converged"
    } else if res.stuck {
        "boundary"
    } else {
        "max_iterations"
    }
}
