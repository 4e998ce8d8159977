//! What `update --method bayesian` writes and prints once the MAP is solved: the
//! `boltwatch.update.v1` document ([`BayesDoc`]) and the table on stdout, both made from a
//! [`Solved`] MAP and its uncertainties.

use super::inputs::Inputs;
use crate::contract::modal_set::ModalSet;
use crate::contract::stiffness::Method;
use crate::contract::update::{
    AutoSigmaDoc, BayesBlock, BayesDoc, BayesModeDoc, BayesParameter, BayesTermination, Bound,
    LCurveDoc, SigmaMisfit, Solver, StageDoc, StageOneDoc, TsvdDoc,
};
use crate::contract::{Schema, finite};
use crate::core::model::Model;
use crate::core::updating::AtBound;
use crate::core::updating::bayesian::{
    AutoSigma, BayesResult, BayesSolver, BayesUpdate, ContinuationStage, Tsvd,
};

/// The uncertainties of a MAP, NaN where their covariance failed.
pub(super) struct Uncertainties<'a> {
    /// Threshold-free posterior std of θ.
    pub(super) theta_std: Vec<f64>,
    /// Threshold-free sampling std of θ.
    pub(super) theta_sampling_std: Vec<f64>,
    /// Threshold-free posterior std of each most probable λ.
    pub(super) lambda_std: Vec<f64>,
    /// TSVD std of θ (24)–(25).
    pub(super) theta_tsvd_std: Vec<f64>,
    /// The TSVD covariance, when asked for and computed.
    pub(super) tsvd: Option<&'a Tsvd>,
}

/// A solved MAP and what the document and the table read beside it.
pub(super) struct Solved<'a> {
    pub(super) update: &'a BayesUpdate,
    /// Wall-clock time of the solve.
    pub(super) seconds: f64,
    pub(super) uncertainty: Uncertainties<'a>,
    /// The bound each MAP θ is on, if any.
    pub(super) at_bound: Vec<Option<AtBound>>,
}

/// The automatic σ_c (discrepancy rule) as documented, when σ_c was chosen by it.
pub(super) fn auto_doc(auto: &Option<AutoSigma>) -> Option<AutoSigmaDoc> {
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

/// The `boltwatch.update.v1` document of a MAP started from stage I's θ when there is a
/// stage I, else from θ0.
pub(super) fn bayes_doc(
    inputs: &Inputs,
    stage1: Option<&StageOneDoc>,
    prior_std: Vec<f64>,
    s: &Solved,
) -> BayesDoc {
    let Inputs {
        model, set, data, ..
    } = inputs;
    let (res, eval) = (&s.update.result, &s.update.evaluation);
    BayesDoc {
        schema: Schema::new(),
        method: Method::Bayesian,
        structure: set.structure.clone(),
        time: set
            .time
            .to_rfc3339_opts(chrono::SecondsFormat::AutoSi, true),
        converged: res.converged,
        termination: termination(res),
        iterations: res.iterations,
        seconds: s.seconds,
        solver: match res.solver {
            BayesSolver::Newton => Solver::Newton,
            BayesSolver::Alternating => Solver::Alternating,
        },
        start: if stage1.is_some() {
            "stage I"
        } else {
            "theta0"
        }
        .into(),
        epsilon: eval.epsilon,
        n_data: data.n_data(),
        bayesian: bayes_block(s, prior_std),
        stage1: stage1.cloned(),
        parameters: parameter_docs(model, s),
        modes: mode_docs(set, s),
    }
}

/// The `bayesian` block: σ_c, the prior, the terms of J_p (14), the continuation, the TSVD.
fn bayes_block(s: &Solved, prior_std: Vec<f64>) -> BayesBlock {
    let u = s.update;
    let res = &u.result;
    BayesBlock {
        sigma_c: u.sigma_c,
        sigma_c_auto: auto_doc(&u.auto),
        prior_std,
        J_p: res.terms.total,
        measurement_misfit: res.terms.measurement,
        modelling_error: res.terms.modelling,
        prior_term: res.terms.prior,
        misfit_dof: u.misfit_dof,
        continuation: stage_docs(&res.stages),
        tsvd: s.uncertainty.tsvd.map(tsvd_doc),
    }
}

/// The TSVD covariance (24)–(25): its threshold at the L-curve's corner, and the L-curve.
fn tsvd_doc(t: &Tsvd) -> TsvdDoc {
    TsvdDoc {
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
    }
}

/// Per parameter: the MAP θ, its uncertainties, mode matching's θ and the bound it is on.
fn parameter_docs(model: &Model, s: &Solved) -> Vec<BayesParameter> {
    let (res, unc) = (&s.update.result, &s.uncertainty);
    model
        .parameters()
        .iter()
        .enumerate()
        .map(|(l, par)| BayesParameter {
            name: par.name.clone(),
            theta: res.state.theta[l],
            std: finite(unc.theta_std[l]),
            sampling_std: finite(unc.theta_sampling_std[l]),
            tsvd_std: finite(unc.theta_tsvd_std[l]),
            mode_matching_theta: s.update.mode_matching.as_ref().map(|r| r.theta[l]),
            at_bound: s.at_bound[l].map(|b| match b {
                AtBound::Upper => Bound::Upper,
                AtBound::Lower => Bound::Lower,
            }),
        })
        .collect()
}

/// Per measured mode: the most probable λ, its std, frequency and MAC, and the model's
/// frequency and MAC at the MAP θ.
fn mode_docs(set: &ModalSet, s: &Solved) -> Vec<BayesModeDoc> {
    let u = s.update;
    let two_pi = 2.0 * std::f64::consts::PI;
    set.modes
        .iter()
        .enumerate()
        .map(|(m, mode)| BayesModeDoc {
            measured_hz: mode.frequency_hz,
            most_probable_lambda: u.result.state.lambda[m],
            most_probable_lambda_std: finite(s.uncertainty.lambda_std[m]),
            most_probable_hz: u.result.state.lambda[m].max(0.0).sqrt() / two_pi,
            mac_most_probable_to_measured: u.macs[m],
            model_hz: u.evaluation.model_hz(m),
            model_mac: finite(u.evaluation.mac[m]),
        })
        .collect()
}

/// The table on stdout: per parameter the MAP θ, its uncertainties and mode matching's θ;
/// per measured mode its frequency against the most probable and the model's, with MACs.
pub(super) fn print_bayes_table(model: &Model, set: &ModalSet, s: &Solved) {
    let (res, eval, unc) = (&s.update.result, &s.update.evaluation, &s.uncertainty);
    println!(
        "{:<12} {:>11} {:>11} {:>11} {:>11} {:>11}",
        "parameter", "θ MAP", "σ post.", "σ sampling", "σ TSVD", "θ mode m."
    );
    for (l, p) in model.parameters().iter().enumerate() {
        let note = match s.at_bound[l] {
            Some(AtBound::Upper) => "  at its upper bound",
            Some(AtBound::Lower) => "  at its lower bound",
            None => "",
        };
        println!(
            "{:<12} {:>11.5} {:>11.5} {:>11.5} {:>11.3e} {:>11}{note}",
            p.name,
            res.state.theta[l],
            unc.theta_std[l],
            unc.theta_sampling_std[l],
            unc.theta_tsvd_std[l],
            s.update
                .mode_matching
                .as_ref()
                .map_or("-".into(), |r| format!("{:.5}", r.theta[l]))
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
            s.update.macs[m],
            eval.mac[m]
        );
    }
    println!();
}

/// The lines under the table: σ_c and how the solve ended, the terms of J_p (14) and
/// ε (5) at the MAP θ, and the TSVD's threshold.
pub(super) fn print_summary(s: &Solved) {
    let u = s.update;
    let res = &u.result;
    let (sigma_c, seconds) = (u.sigma_c, s.seconds);
    println!(
        "σ_c = {sigma_c:.4e}{}; {:?} solver: {} after {} iterations in {seconds:.2} s",
        if u.auto.is_some() { " (automatic)" } else { "" },
        res.solver,
        match termination(res) {
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
        u.misfit_dof,
        res.terms.modelling,
        res.terms.prior,
        u.evaluation.epsilon
    );
    if let Some(t) = s.uncertainty.tsvd {
        println!(
            "TSVD: cond(H) = {:.2e}, s_tol = {:.4e} (L-curve corner, {} of {} kept)",
            t.condition(),
            t.s_tol(),
            t.curve[t.chosen].kept,
            t.singular_values.len()
        );
    }
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
