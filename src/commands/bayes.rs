//! `update --method bayesian` and `sweep-sigma`: the Bayesian MAP (paper §2.3) from the
//! command line, its uncertainty, the σ_c study (Figs. 5, 7, 15, 18) and the two-stage use
//! (§4.2).

use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use anyhow::{Result, bail};
use indicatif::ProgressBar;

use super::inputs::{Inputs, measured_data};
use super::progress::{fmt_theta, iteration_progress, progress_line, spinner};
use super::{load_model, parse_positive_list, write_json};
use crate::contract::stiffness::Method;
use crate::contract::update::{
    AutoSigmaDoc, BayesBlock, BayesDoc, BayesModeDoc, BayesParameter, BayesTermination, Bound,
    LCurveDoc, Mapping, NamedTheta, SigmaMisfit, Solver, StageDoc, StageOneDoc, TsvdDoc,
};
use crate::contract::{Schema, finite};
use crate::core::model::Model;
use crate::core::updating::bayesian::{
    AutoSigma, BayesOptions, BayesProgress, BayesResult, BayesSolver, BayesUpdate,
    ContinuationStage, Observers, SigmaChoice, SigmaTrial, bayesian_update,
    stage_one as core_stage_one,
};
use crate::core::updating::{AtBound, LogBounds};

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

fn auto_doc(auto: &Option<AutoSigma>) -> Option<AutoSigmaDoc> {
    auto.as_ref().map(|a| AutoSigmaDoc {
        rule:
            "smallest σ_c at which e_Mᵀ Σ_M⁻¹ e_M ≤ ν = N_data − N_θ − N_m (discrepancy principle)"
                .into(),
        nu: a.target,
        misfit: a.misfit,
        met: a.met,
        trials: a
            .trials
            .iter()
            .map(|&(sigma_c, misfit)| SigmaMisfit { sigma_c, misfit })
            .collect(),
    })
}

/// The σ_c continuation of a Newton solve (one stage when the cold start converged).
pub(super) fn stage_docs(stages: &[ContinuationStage]) -> Vec<StageDoc> {
    stages
        .iter()
        .map(|s| StageDoc {
            sigma_c: s.sigma_c,
            iterations: s.iterations,
            converged: s.converged,
        })
        .collect()
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
    fine_set: &crate::contract::modal_set::ModalSet,
    max_iter: usize,
    bounds: Option<(f64, f64)>,
) -> Result<StageOneOut> {
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
    let data = measured_data(&set, &coarse, shape_weight);
    let (prior_mean, prior_std) = prior(&coarse, &b.prior)?;
    let sigma = sigma_choice(
        &coarse,
        b.stage1_sigma_c.as_deref().or(b.sigma_c.as_deref()),
        &b.sigma_range,
    )?;
    let (pb, mut report) = sigma_reporter(sigma);
    let one = core_stage_one(
        fine,
        &coarse,
        &data,
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
    let res = &one.result;
    println!(
        "stage I: {} at σ_c = {:.4e}, {} modes, {} iterations: θ̃ = [{}]",
        coarse.name,
        one.sigma_c,
        set.modes.len(),
        res.iterations,
        res.state
            .theta
            .iter()
            .map(|t| format!("{t:.4}"))
            .collect::<Vec<_>>()
            .join(", ")
    );
    Ok(StageOneOut {
        doc: StageOneDoc {
            model: coarse.name.clone(),
            modes: set.modes.len(),
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
        },
        theta0: one.theta0(),
    })
}

fn solver(s: SolverArg) -> BayesSolver {
    match s {
        SolverArg::Newton => BayesSolver::Newton,
        SolverArg::Alternating => BayesSolver::Alternating,
    }
}

/// `update --method bayesian`.
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
    let sigma = sigma_choice(model, b.sigma_c.as_deref(), &b.sigma_range)?;
    let (sigma_pb, mut report) = sigma_reporter(sigma);
    // One bar per phase: the σ_c search, the MAP iterations, the TSVD.
    let bar: Arc<Mutex<Option<ProgressBar>>> = Arc::default();
    let shown = bar.clone();
    let iteration: BayesProgress = Box::new(move |s, k, value, theta| {
        if let Some(b) = shown.lock().unwrap_or_else(|p| p.into_inner()).as_ref() {
            progress_line(
                b,
                format!(
                    "stage σ_c = {s:.3e}, iteration {k}: objective {value:.6e}, θ = {}",
                    fmt_theta(theta)
                ),
            );
        }
    });
    let solver_name = b.solver;
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
    let u = bayesian_update(
        model,
        data,
        &theta0,
        &BayesOptions {
            solver: solver(b.solver),
            sigma,
            prior_mean,
            prior_std: std.clone(),
            max_iterations: max_iter,
            tsvd: !b.no_tsvd,
            bounds,
        },
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
    let BayesUpdate {
        sigma_c,
        auto,
        result: res,
        misfit_dof,
        macs,
        free,
        tsvd,
        evaluation: eval,
        mode_matching: mm,
    } = u;
    if let Err(e) = &free {
        eprintln!("warning: no threshold-free covariance: {e}");
    }
    let tsvd = match tsvd {
        Some(Err(e)) => {
            eprintln!("warning: no TSVD covariance: {e}");
            None
        }
        Some(Ok(t)) => Some(t),
        None => None,
    };
    let p = model.n_params();
    let nan = vec![f64::NAN; p];
    let (post, samp) = match &free {
        Ok(f) => (f.posterior_theta_std(), f.sampling_theta_std()),
        Err(_) => (nan.clone(), nan.clone()),
    };
    let lambda_std = match &free {
        Ok(f) => f.posterior_lambda_std(),
        Err(_) => vec![f64::NAN; res.state.lambda.len()],
    };
    let tsvd_std = tsvd.as_ref().map_or(nan.clone(), |t| t.theta_std());
    let at_bound = LogBounds::new(model, bounds).at_bound(&res.state.theta);
    let two_pi = 2.0 * std::f64::consts::PI;
    let out_doc = BayesDoc {
        schema: Schema::new(),
        method: Method::Bayesian,
        structure: set.structure.clone(),
        time: set.time.to_rfc3339_opts(chrono::SecondsFormat::AutoSi, true),
        converged: res.converged,
        termination: termination(&res),
        iterations: res.iterations,
        seconds,
        solver: match res.solver {
            BayesSolver::Newton => Solver::Newton,
            BayesSolver::Alternating => Solver::Alternating,
        },
        start: if stage1.is_some() { "stage I" } else { "theta0" }.into(),
        epsilon: eval.epsilon,
        n_data: data.n_data(),
        bayesian: BayesBlock {
            sigma_c,
            sigma_c_auto: auto_doc(&auto),
            prior_std: std,
            J_p: res.terms.total,
            measurement_misfit: res.terms.measurement,
            modelling_error: res.terms.modelling,
            prior_term: res.terms.prior,
            misfit_dof,
            continuation: stage_docs(&res.stages),
            tsvd: tsvd.as_ref().map(|t| TsvdDoc {
                s_tol: t.s_tol(),
                kept: t.curve[t.chosen].kept,
                of: t.singular_values.len(),
                condition: t.condition(),
                corner_rule: "least E (25): where E stops falling as singular values are added; points with a negative variance excluded".into(),
                l_curve: t
                    .curve
                    .iter()
                    .map(|c| LCurveDoc {
                        s_tol: c.s_tol,
                        E: c.error,
                        norm: c.norm,
                        negative_variance: c.negative_variance,
                    })
                    .collect(),
            }),
        },
        stage1: stage1.as_ref().map(|s| s.doc.clone()),
        parameters: model
            .parameters()
            .iter()
            .enumerate()
            .map(|(l, par)| BayesParameter {
                name: par.name.clone(),
                theta: res.state.theta[l],
                std: finite(post[l]),
                sampling_std: finite(samp[l]),
                tsvd_std: finite(tsvd_std[l]),
                mode_matching_theta: mm.as_ref().map(|r| r.theta[l]),
                at_bound: at_bound[l].map(|b| match b {
                    AtBound::Upper => Bound::Upper,
                    AtBound::Lower => Bound::Lower,
                }),
            })
            .collect(),
        modes: set
            .modes
            .iter()
            .enumerate()
            .map(|(m, mode)| BayesModeDoc {
                measured_hz: mode.frequency_hz,
                most_probable_lambda: res.state.lambda[m],
                most_probable_lambda_std: finite(lambda_std[m]),
                most_probable_hz: res.state.lambda[m].max(0.0).sqrt() / two_pi,
                mac_most_probable_to_measured: macs[m],
                model_hz: eval.model_hz(m),
                model_mac: finite(eval.mac[m]),
            })
            .collect(),
    };
    write_json(out, &out_doc)?;
    print_bayes_table(
        model,
        set,
        &res,
        &eval,
        &macs,
        (&post, &samp, &tsvd_std, &at_bound),
        mm.as_ref(),
    );
    println!(
        "σ_c = {sigma_c:.4e}{}; {:?} solver: {} after {} iterations in {seconds:.2} s",
        if auto.is_some() { " (automatic)" } else { "" },
        res.solver,
        match termination(&res) {
            BayesTermination::Converged => "converged",
            BayesTermination::Boundary =>
                "NOT converged (stopped against θ > 0 or λ > 0: no interior minimum)",
            BayesTermination::MaxIterations => "NOT converged",
        },
        res.iterations
    );
    println!(
        "J_p = {:.6e}: e_Mᵀ Σ_M⁻¹ e_M = {:.4e} (ν = {}), e_Cᵀe_C = {:.4e}, prior {:.3e}; ε(θ_MAP) = {:.4e}",
        res.terms.total,
        res.terms.measurement,
        misfit_dof,
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

/// Per parameter: posterior, sampling and TSVD std, and the bound it is on.
type ParameterColumns<'a> = (&'a [f64], &'a [f64], &'a [f64], &'a [Option<AtBound>]);

fn print_bayes_table(
    model: &Model,
    set: &crate::contract::modal_set::ModalSet,
    res: &BayesResult,
    eval: &crate::core::updating::Evaluation,
    macs: &[f64],
    (post, samp, tsvd, at_bound): ParameterColumns<'_>,
    mm: Option<&crate::core::updating::ModeMatchingResult>,
) {
    println!(
        "{:<12} {:>11} {:>11} {:>11} {:>11} {:>11}",
        "parameter", "θ MAP", "σ post.", "σ sampling", "σ TSVD", "θ mode m."
    );
    for (l, p) in model.parameters().iter().enumerate() {
        let note = match at_bound[l] {
            Some(AtBound::Upper) => "  at its upper bound",
            Some(AtBound::Lower) => "  at its lower bound",
            None => "",
        };
        println!(
            "{:<12} {:>11.5} {:>11.5} {:>11.5} {:>11.3e} {:>11}{note}",
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

/// The `termination` of `boltwatch.update.v1` for a MAP solve: `converged`, `boundary` (no
/// step lowers J_p and the Hessian is not positive definite there: the minimum lies outside
/// θ > 0, λ > 0, or at a saddle) or `max_iterations`.
fn termination(res: &BayesResult) -> BayesTermination {
    if res.converged {
        BayesTermination::Converged
    } else if res.stuck {
        BayesTermination::Boundary
    } else {
        BayesTermination::MaxIterations
    }
}
