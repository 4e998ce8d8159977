//! `update --method bayesian` and `sweep-sigma`: the Bayesian MAP (paper §2.3) from the
//! command line, its uncertainty, the σ_c study (Figs. 5, 7, 15, 18) and the two-stage use
//! (§4.2). What the update writes and prints once solved is in `bayes_output`.

use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use anyhow::{Result, bail};
use indicatif::ProgressBar;

use super::bayes_output::{
    Solved, Uncertainties, auto_doc, bayes_doc, print_bayes_table, print_summary,
};
use super::inputs::{Inputs, measured_data};
use super::progress::{fmt_theta, iteration_progress, progress_line, spinner};
use super::{load_model, parse_positive_list, write_json};
use crate::contract::modal_set::ModalSet;
use crate::contract::update::{Mapping, NamedTheta, StageOneDoc};
use crate::core::model::Model;
use crate::core::updating::bayesian::{
    BayesOptions, BayesProgress, BayesSolver, BayesUpdate, Observers, SigmaChoice, SigmaTrial,
    StageOne, bayesian_update, stage_one as core_stage_one,
};
use crate::core::updating::{LogBounds, MeasuredData};

// The σ_c continuation as documented, which `sweep-sigma` writes too.
pub(super) use super::bayes_output::stage_docs;

/// Default prior standard deviation of θ: non-informative, as in the paper (§4.2).
pub const DEFAULT_PRIOR_STD: f64 = 1000.0;
/// Default range searched by `--sigma-c auto`.
pub const DEFAULT_SIGMA_RANGE: (f64, f64) = (1.0, 1e8);

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

/// The prior of (12) for `model`: mean = nominal θ, std from the flag or the model file.
pub(super) fn prior(model: &Model, args: &PriorArgs) -> Result<(Vec<f64>, Vec<f64>)> {
    let p = model.n_params();
    let std = match &args.prior_std {
        Some(s) => {
            let v = parse_positive_list(s, "--prior-std")?;
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
    let v = parse_positive_list(s, "--sigma-range")?;
    match v[..] {
        [a, b] if a < b => Ok((a, b)),
        _ => bail!("--sigma-range `{s}`: need two numbers `from,to` with 0 < from < to"),
    }
}

/// σ_c from `--sigma-c` (number or `auto`), else the model file's, else `auto`.
fn sigma_choice(model: &Model, arg: Option<&str>, range: &str) -> Result<SigmaChoice> {
    let arg = arg
        .map(str::to_string)
        .or_else(|| model.bayesian.sigma_c.map(|v| v.to_string()))
        .unwrap_or_else(|| "auto".into());
    if arg.trim() == "auto" {
        let (from, to) = parse_range(range)?;
        Ok(SigmaChoice::Auto { from, to })
    } else {
        Ok(SigmaChoice::Value(
            parse_positive_list(&arg, "--sigma-c")?[0],
        ))
    }
}

/// A spinner on stderr for the automatic σ_c, if `choice` is automatic, and the reporter
/// of its trials.
fn sigma_reporter(choice: SigmaChoice) -> (Option<ProgressBar>, impl FnMut(SigmaTrial)) {
    let pb = match choice {
        SigmaChoice::Auto { from, to } => Some(spinner(format!(
            "σ_c by the discrepancy rule in [{from:e}, {to:e}]"
        ))),
        SigmaChoice::Value(_) => None,
    };
    let bar = pb.clone();
    let report = move |t: SigmaTrial| {
        let line = match t.misfit {
            None => format!("σ_c trial {}: the MAP at σ_c = {:.4e}", t.index, t.sigma_c),
            Some(m) => format!(
                "σ_c trial {}: σ_c = {:.4e}, misfit {m:.1} (target ν = {:.1})",
                t.index, t.sigma_c, t.target
            ),
        };
        if let Some(pb) = &bar {
            progress_line(pb, line);
        }
    };
    (pb, report)
}

/// Stage I of the two-stage update: its result and the fine θ0 it gives.
struct StageOneOut {
    doc: StageOneDoc,
    theta0: Vec<f64>,
}

/// Stage I reads the same modal set as stage II: it was validated against the fine model
/// (structure name, channels), and every channel must exist in the coarse model too.
fn stage_one(
    b: &BayesUpdateArgs,
    shape_weight: f64,
    fine: &Model,
    fine_set: &ModalSet,
    max_iter: usize,
    bounds: Option<(f64, f64)>,
) -> Result<StageOneOut> {
    let path = b
        .stage1_model
        .as_ref()
        .expect("called with a stage-I model");
    let coarse = load_model(path)?;
    check_coarse_channels(path, &coarse, fine_set)?;
    let set = stage_one_set(fine_set, b.stage1_modes)?;
    let data = measured_data(&set, &coarse, shape_weight);
    let one = solve_stage_one(b, fine, &coarse, &data, max_iter, bounds)?;
    let modes = set.modes.len();
    print_stage_one(&coarse, &one, modes);
    Ok(StageOneOut {
        doc: stage_one_doc(fine, &coarse, &one, modes),
        theta0: one.theta0(),
    })
}

/// Refuses a coarse model (read from `path`) that lacks a channel of the modal set.
fn check_coarse_channels(path: &Path, coarse: &Model, fine_set: &ModalSet) -> Result<()> {
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
    Ok(())
}

/// The modal set of stage I: the fine set, cut to its first `stage1_modes` modes if given.
fn stage_one_set(fine_set: &ModalSet, stage1_modes: Option<usize>) -> Result<ModalSet> {
    let mut set = fine_set.clone();
    if let Some(n) = stage1_modes {
        if n == 0 || n > set.modes.len() {
            bail!(
                "--stage1-modes = {n}: the modal set has {} modes",
                set.modes.len()
            );
        }
        set.modes.truncate(n);
    }
    Ok(set)
}

/// The MAP of the coarse model (the prior and σ_c of stage I, a spinner while σ_c is
/// searched), mapped onto the fine model's parameters.
fn solve_stage_one(
    b: &BayesUpdateArgs,
    fine: &Model,
    coarse: &Model,
    data: &MeasuredData,
    max_iter: usize,
    bounds: Option<(f64, f64)>,
) -> Result<StageOne> {
    let (prior_mean, prior_std) = prior(coarse, &b.prior)?;
    let sigma = sigma_choice(
        coarse,
        b.stage1_sigma_c.as_deref().or(b.sigma_c.as_deref()),
        &b.sigma_range,
    )?;
    let (pb, mut report) = sigma_reporter(sigma);
    let one = core_stage_one(
        fine,
        coarse,
        data,
        &BayesOptions {
            solver: solver(b.solver),
            sigma,
            prior_mean,
            prior_std,
            max_iterations: max_iter,
            tsvd: false,
            bounds,
        },
        &mut report,
    )?;
    if let Some(pb) = pb {
        pb.finish_and_clear();
    }
    Ok(one)
}

/// The line on stdout that reports stage I: model, σ_c, modes, iterations and θ̃.
fn print_stage_one(coarse: &Model, one: &StageOne, modes: usize) {
    let res = &one.result;
    println!(
        "stage I: {} at σ_c = {:.4e}, {} modes, {} iterations: θ̃ = [{}]",
        coarse.name,
        one.sigma_c,
        modes,
        res.iterations,
        res.state
            .theta
            .iter()
            .map(|t| format!("{t:.4}"))
            .collect::<Vec<_>>()
            .join(", ")
    );
}

/// The document of stage I: its σ_c, the coarse θ by name and how each fine parameter's
/// start was mapped from it.
fn stage_one_doc(fine: &Model, coarse: &Model, one: &StageOne, modes: usize) -> StageOneDoc {
    let res = &one.result;
    StageOneDoc {
        model: coarse.name.clone(),
        modes,
        sigma_c: one.sigma_c,
        sigma_c_auto: auto_doc(&one.auto),
        iterations: res.iterations,
        J_p: res.terms.total,
        parameters: coarse
            .parameters()
            .iter()
            .zip(&res.state.theta)
            .map(|(p, &theta)| NamedTheta {
                name: p.name.clone(),
                theta,
            })
            .collect(),
        mapping: fine
            .parameters()
            .iter()
            .zip(&one.mapped)
            .map(|(p, &(theta0, c))| Mapping {
                name: p.name.clone(),
                theta0,
                from: c.map(|c| coarse.parameters()[c].name.clone()),
            })
            .collect(),
    }
}

fn solver(s: SolverArg) -> BayesSolver {
    match s {
        SolverArg::Newton => BayesSolver::Newton,
        SolverArg::Alternating => BayesSolver::Alternating,
    }
}

/// `update --method bayesian`: stage I when asked for, the prior and the choice of σ_c, the
/// MAP of (14) with its uncertainties, then the document at `out` and the table.
pub fn run_update(
    b: &BayesUpdateArgs,
    max_iter: Option<usize>,
    shape_weight: f64,
    bounds: Option<(f64, f64)>,
    out: &Path,
    inputs: &Inputs,
) -> Result<()> {
    let Inputs {
        model, set, data, ..
    } = inputs;
    let max_iter = max_iter.unwrap_or(match b.solver {
        SolverArg::Newton => 200,
        SolverArg::Alternating => 1_000_000,
    });
    let stage1 = match &b.stage1_model {
        Some(_) => Some(stage_one(b, shape_weight, model, set, max_iter, bounds)?),
        None => None,
    };
    let theta0 = stage1
        .as_ref()
        .map_or_else(|| inputs.theta0.clone(), |s| s.theta0.clone());
    let (prior_mean, std) = prior(model, &b.prior)?;
    let opts = BayesOptions {
        solver: solver(b.solver),
        sigma: sigma_choice(model, b.sigma_c.as_deref(), &b.sigma_range)?,
        prior_mean,
        prior_std: std.clone(),
        max_iterations: max_iter,
        tsvd: !b.no_tsvd,
        bounds,
    };
    let (update, seconds) = solve_map(model, data, &theta0, &opts, b.solver)?;
    let uncertainty = uncertainties(model, &update);
    let at_bound = LogBounds::new(model, bounds).at_bound(&update.result.state.theta);
    let solved = Solved {
        update: &update,
        seconds,
        uncertainty,
        at_bound,
    };
    let stage1_doc = stage1.as_ref().map(|s| &s.doc);
    write_json(out, &bayes_doc(inputs, stage1_doc, std, &solved))?;
    print_bayes_table(model, set, &solved);
    print_summary(&solved);
    Ok(())
}

/// The MAP of (14) by [`bayesian_update`], with a progress bar on stderr for each phase (the
/// σ_c search, the MAP iterations, the TSVD); the update and its wall-clock seconds.
fn solve_map(
    model: &Model,
    data: &MeasuredData,
    theta0: &[f64],
    opts: &BayesOptions,
    solver_name: SolverArg,
) -> Result<(BayesUpdate, f64)> {
    let (sigma_pb, mut report) = sigma_reporter(opts.sigma);
    // One bar per phase: the σ_c search, the MAP iterations, the TSVD.
    let bar: Arc<Mutex<Option<ProgressBar>>> = Arc::default();
    let iteration = iteration_reporter(bar.clone());
    let mut phase = |p: &'static str| {
        let mut current = bar.lock().unwrap_or_else(|p| p.into_inner());
        if let Some(old) = current.take() {
            old.finish_and_clear();
        }
        if let Some(s) = &sigma_pb {
            s.finish_and_clear();
        }
        *current = Some(match p {
            "solve" => iteration_progress(&format!("MAP by the {solver_name:?} solver")),
            _ => spinner("TSVD of the Hessian (16) and the L-curve (24)–(25)".into()),
        });
    };
    let started = Instant::now();
    let update = bayesian_update(
        model,
        data,
        theta0,
        opts,
        Observers {
            sigma_trial: &mut report,
            iteration: Some(iteration),
            phase: &mut phase,
        },
    )?;
    let seconds = started.elapsed().as_secs_f64();
    for p in [
        sigma_pb,
        bar.lock().unwrap_or_else(|p| p.into_inner()).take(),
    ]
    .into_iter()
    .flatten()
    {
        p.finish_and_clear();
    }
    Ok((update, seconds))
}

/// The reporter of the MAP iterations: a line on the phase's bar in `shown`, if any.
fn iteration_reporter(shown: Arc<Mutex<Option<ProgressBar>>>) -> BayesProgress {
    Box::new(move |s, k, value, theta| {
        if let Some(b) = shown.lock().unwrap_or_else(|p| p.into_inner()).as_ref() {
            progress_line(
                b,
                format!(
                    "stage σ_c = {s:.3e}, iteration {k}: objective {value:.6e}, θ = {}",
                    fmt_theta(theta)
                ),
            );
        }
    })
}

/// The uncertainties of the MAP: the threshold-free posterior and sampling std of θ and the
/// posterior std of λ, and the TSVD std of θ (24)–(25); NaN, with a warning on stderr,
/// where a covariance failed.
fn uncertainties<'a>(model: &Model, update: &'a BayesUpdate) -> Uncertainties<'a> {
    let free = &update.free;
    if let Err(e) = free {
        eprintln!("warning: no threshold-free covariance: {e}");
    }
    let tsvd = match &update.tsvd {
        Some(Err(e)) => {
            eprintln!("warning: no TSVD covariance: {e}");
            None
        }
        Some(Ok(t)) => Some(t),
        None => None,
    };
    let p = model.n_params();
    let nan = vec![f64::NAN; p];
    let (post, samp) = match free {
        Ok(f) => (f.posterior_theta_std(), f.sampling_theta_std()),
        Err(_) => (nan.clone(), nan.clone()),
    };
    let lambda_std = match free {
        Ok(f) => f.posterior_lambda_std(),
        Err(_) => vec![f64::NAN; update.result.state.lambda.len()],
    };
    let tsvd_std = tsvd.map_or(nan.clone(), |t| t.theta_std());
    Uncertainties {
        theta_std: post,
        theta_sampling_std: samp,
        lambda_std,
        theta_tsvd_std: tsvd_std,
        tsvd,
    }
}
