//! The discrepancy workflow (DESIGN §6, issue 6): find where the model and a modal set
//! disagree, name the missing physical effect, add it, and show the gap shrink.
//!
//! One round:
//! 1. **Fit** the model class as it is (mode matching, globalized the first time) and
//!    **localize** the disagreement ([`Localization`]): per-mode frequency error in units of
//!    its σ, MAC per mode, per-channel shape residual.
//! 2. **Screen** every candidate of the [`effects::catalogue`] at every location. A
//!    candidate's residual column `g = ∂r/∂u` (finite difference at `u = 0`, at the fitted θ)
//!    is projected off the span of the model's own Jacobian `J`; the reduction of ε that the
//!    one extra parameter explains to first order is `(g⊥ᵀr)² / g⊥ᵀg⊥` (the score). A bolt
//!    stiffness change is inside the model class and so explains nothing here. A candidate
//!    whose step changes the mode pairing (it moves a measured mode across a close
//!    neighbour) has no first-order column; it is scored by the same reduction at a few
//!    finite values of `u`, θ corrected to first order (`screen::probe`).
//! 3. **Refit** the best few with the full nonlinear update: ε is minimized over the effect's
//!    value with θ refitted at every value (the profile `ε(u) = min_θ ε(θ, u)`, by a bracketed
//!    golden-section search), and its standard deviation is the Laplace one, `σ_u² = 2/ε''`
//!    (ε is −2 log L up to a constant).
//! 4. **Decide** by a likelihood-ratio test: `Λ = ε_before − ε_after` is χ²₁ under "no missing
//!    effect"; the best refit is named when Λ exceeds the χ²₁ quantile at family-wise level α
//!    over all candidates screened (Bonferroni). The BIC approximation of the log Bayes factor,
//!    `Λ/2 − ½ ln N`, is reported beside it.
//! 5. A named effect is added to the model (at its fitted value) and the next round starts;
//!    the workflow stops when nothing is significant.

pub mod description;
pub mod effects;
mod fit;
pub mod injection;
mod refit;
mod screen;
mod search;
mod space;

use faer::Mat;

use crate::core::modal::ModalError;
use crate::core::model::{Model, ModelError};
use crate::core::stats::chi2_1_upper_quantile;
use crate::core::updating::{
    Evaluation, Evaluator, FinalStep, MeasuredData, ModeMatching, ModeMatchingOptions,
    ModeMatchingResult, StepControl, UpdateError,
};
pub use description::Description;
use effects::{Effect, Sign};
use fit::{build, fit, localize, profile_point};
use refit::{effect_of, map_with_progress, refit, reprofile, with_effects};
use screen::{candidates_of, screen};
use search::minimize_1d;

/// Failures of a diagnosis.
#[derive(Debug, thiserror::Error)]
pub enum DiagnosisError {
    #[error("{0}")]
    Location(String),
    #[error("the model with {what} does not assemble: {source}")]
    Model {
        what: String,
        #[source]
        source: ModelError,
    },
    #[error("updating failed: {0}")]
    Update(#[from] UpdateError),
    #[error("updating failed: {0}")]
    Modal(#[from] ModalError),
}

/// Options of [`diagnose`].
#[derive(Debug, Clone)]
pub struct DiagnosisOptions {
    /// Family-wise significance level of the likelihood-ratio test over all candidates.
    pub alpha: f64,
    /// Candidates refitted per round.
    pub refits: usize,
    /// Rounds (effects named) at most.
    pub max_effects: usize,
}

impl Default for DiagnosisOptions {
    fn default() -> Self {
        Self {
            alpha: 1e-4,
            refits: 4,
            max_effects: 4,
        }
    }
}

/// Where the fitted model and the data disagree.
#[derive(Debug, Clone)]
pub struct Localization {
    pub epsilon: f64,
    pub theta: Vec<f64>,
    pub modes: Vec<ModeMisfit>,
    /// Per model channel: name, Σ over modes of the squared whitened shape residual, and
    /// the number of mode-shape entries measured there.
    pub channels: Vec<(String, f64, usize)>,
}

/// One measured mode against its paired model mode.
#[derive(Debug, Clone)]
pub struct ModeMisfit {
    pub measured_hz: f64,
    pub model_hz: f64,
    /// (measured − model eigenvalue) / σ_λ: the frequency error in units of its σ.
    pub error_sigma: f64,
    pub mac: f64,
    /// 1-based.
    pub paired_with: usize,
}

/// A screened candidate.
#[derive(Debug, Clone)]
pub struct Candidate {
    pub effect: &'static str,
    pub location: String,
    /// ε reduction explained to first order beyond the model's own parameters.
    pub score: f64,
    /// The first-order value of the internal coordinate (for a probed candidate, the probe
    /// value that scored best): where the refit starts.
    pub u_linear: f64,
}

/// A refitted candidate.
#[derive(Debug, Clone)]
pub struct Refit {
    pub effect: &'static str,
    pub unit: &'static str,
    pub location: String,
    pub u: f64,
    pub std_u: f64,
    pub value: f64,
    pub std: f64,
    pub epsilon: f64,
    pub theta: Vec<f64>,
}

/// An effect the workflow named.
#[derive(Debug, Clone)]
pub struct Named {
    pub refit: Refit,
    pub epsilon_before: f64,
    pub likelihood_ratio: f64,
    pub threshold: f64,
    pub log_bayes_factor: f64,
    /// Other refitted candidates whose ε is within [`INDISTINGUISHABLE`] of this one's: the
    /// data cannot tell them apart (e.g. a mass at either end of an axially rigid beam).
    pub indistinguishable_from: Vec<Refit>,
}

/// Two refits whose ε differ by less than this (2 ln 20: a likelihood ratio below 20, under
/// "strong" evidence) are reported as indistinguishable.
pub const INDISTINGUISHABLE: f64 = 6.0;

/// An effect named in an earlier round and withdrawn: with the later effects in the model it
/// no longer passed the test (it stood in for them).
#[derive(Debug, Clone)]
pub struct Withdrawn {
    pub effect: &'static str,
    pub location: String,
    /// ε increase when it is taken out again.
    pub likelihood_ratio: f64,
}

/// One round of the workflow.
#[derive(Debug, Clone)]
pub struct Round {
    pub epsilon: f64,
    pub candidates: Vec<Candidate>,
    pub refits: Vec<Refit>,
    pub named: Option<Named>,
    pub withdrawn: Vec<Withdrawn>,
}

/// The outcome of [`diagnose`].
#[derive(Debug, Clone)]
pub struct Diagnosis {
    pub before: Localization,
    pub after: Localization,
    pub named: Vec<Named>,
    pub rounds: Vec<Round>,
    pub n_candidates: usize,
    /// The likelihood-ratio threshold of the test.
    pub threshold: f64,
    pub alpha: f64,
    /// The model with every named effect added.
    pub enriched: Description,
}

/// Runs the workflow (module docs) on `spec` and `data`. `progress(stage, done, total)` is
/// called as candidates are screened and refitted.
pub fn diagnose(
    spec: &Description,
    data: &MeasuredData,
    opts: &DiagnosisOptions,
    mut progress: impl FnMut(&str, usize, usize),
) -> Result<Diagnosis, DiagnosisError> {
    let effects = effects::catalogue();
    let nominal = build(spec, || "no effect added".into())?;
    let mut f = fit(spec, data, &nominal.nominal_theta(), true)?;
    let before = localize(&f.model, data, &f.result.last);
    let n_candidates = candidates_of(&effects, spec, &[]).len();
    let threshold = chi2_1_upper_quantile(opts.alpha / n_candidates.max(1) as f64);
    let n_data = data.n_data() as f64;
    let mut named: Vec<Named> = Vec::new();
    let mut rounds = Vec::new();
    let mut current = spec.clone();
    loop {
        let base = f.result.last.clone();
        let mut ev = Evaluator::new(&f.model)?;
        let j = ev.jacobian(&f.model, data, &base)?;
        let q = j.qr().compute_thin_Q();
        let cands = candidates_of(&effects, &current, &named);
        let total = cands.len();
        let mut screened: Vec<Candidate> = map_with_progress(
            &cands,
            |(e, l)| screen(&current, *e, l, data, &base, &q),
            |done| progress("screening", done, total),
        )
        .into_iter()
        .flatten()
        .collect();
        screened.sort_by(|a, b| b.score.total_cmp(&a.score));
        // The best few by score, and the best of each effect type: the score is a first-order
        // measure and underrates effects whose modal signature is strongly nonlinear in
        // their size (a member losing half its stiffness).
        let mut best: Vec<&Candidate> = screened
            .iter()
            .filter(|c| c.score > 0.0)
            .take(opts.refits)
            .collect();
        for e in &effects {
            if let Some(c) = screened
                .iter()
                .find(|c| c.effect == e.kind() && c.score > 0.0)
                && !best.iter().any(|b| std::ptr::eq(*b, c))
            {
                best.push(c);
            }
        }
        let mut refits: Vec<Refit> = map_with_progress(
            &best,
            |c| {
                refit(
                    &current,
                    effect_of(&effects, c.effect),
                    c,
                    data,
                    &base.theta,
                )
            },
            |done| progress("refitting", done, best.len()),
        )
        .into_iter()
        .flatten()
        .collect();
        refits.sort_by(|a, b| a.epsilon.total_cmp(&b.epsilon));
        let eps_before = f.result.epsilon();
        let winner = refits.first().and_then(|r| {
            let lr = eps_before - r.epsilon;
            (lr > threshold).then(|| Named {
                refit: r.clone(),
                epsilon_before: eps_before,
                likelihood_ratio: lr,
                threshold,
                log_bayes_factor: lr / 2.0 - 0.5 * n_data.ln(),
                indistinguishable_from: refits[1..]
                    .iter()
                    .filter(|o| o.epsilon - r.epsilon < INDISTINGUISHABLE)
                    .cloned()
                    .collect(),
            })
        });
        let mut round = Round {
            epsilon: eps_before,
            candidates: screened,
            refits,
            named: winner.clone(),
            withdrawn: Vec::new(),
        };
        let Some(w) = winner else {
            rounds.push(round);
            break;
        };
        let theta = w.refit.theta.clone();
        named.push(w);
        // Backward elimination: an earlier effect that no longer passes the test with the
        // new one in the model stood in for it; withdraw it. The test of each refits the
        // values of the others without it (they were fitted with it present).
        loop {
            let refs: Vec<&Refit> = named.iter().map(|n| &n.refit).collect();
            current = with_effects(spec, &effects, &refs)?;
            f = fit(&current, data, &theta, false)?;
            let mut weakest: Option<(usize, f64, Vec<Refit>)> = None;
            for i in 0..named.len().saturating_sub(1) {
                let mut others: Vec<Refit> = named
                    .iter()
                    .enumerate()
                    .filter(|&(k, _)| k != i)
                    .map(|(_, n)| n.refit.clone())
                    .collect();
                // An effect another one depends on (a splice whose node carries a named
                // mass) is not withdrawn alone.
                let eps_without = match reprofile(spec, &effects, &mut others, data, &theta) {
                    Ok((e, _)) => e,
                    Err(DiagnosisError::Location(_)) => continue,
                    Err(e) => return Err(e),
                };
                let lr = eps_without - f.result.epsilon();
                if lr <= threshold && weakest.as_ref().is_none_or(|w| lr < w.1) {
                    weakest = Some((i, lr, others));
                }
            }
            let Some((i, lr, others)) = weakest else {
                break;
            };
            let gone = named.remove(i);
            for (n, r) in named.iter_mut().zip(others) {
                n.refit = r;
            }
            round.withdrawn.push(Withdrawn {
                effect: gone.refit.effect,
                location: gone.refit.location.clone(),
                likelihood_ratio: lr,
            });
        }
        rounds.push(round);
        if named.len() >= opts.max_effects {
            break;
        }
    }
    // With several effects named, each value was fitted with the later ones still missing:
    // refit each with the others at their values.
    if named.len() > 1 {
        let mut set: Vec<Refit> = named.iter().map(|n| n.refit.clone()).collect();
        let (eps, theta) = reprofile(spec, &effects, &mut set, data, &f.result.theta)?;
        if eps <= f.result.epsilon() {
            for (n, r) in named.iter_mut().zip(set) {
                n.refit = r;
            }
            let refs: Vec<&Refit> = named.iter().map(|n| &n.refit).collect();
            current = with_effects(spec, &effects, &refs)?;
            f = fit(&current, data, &theta, false)?;
        }
    }
    let after = localize(&f.model, data, &f.result.last);
    // After a withdrawal, the evidence of what remains is recomputed against the model
    // without it (with the other remaining effects refitted).
    if rounds.iter().any(|r| !r.withdrawn.is_empty()) {
        for i in 0..named.len() {
            let eps_without = if named.len() == 1 {
                before.epsilon
            } else {
                let mut others: Vec<Refit> = named
                    .iter()
                    .enumerate()
                    .filter(|&(k, _)| k != i)
                    .map(|(_, n)| n.refit.clone())
                    .collect();
                match reprofile(spec, &effects, &mut others, data, &f.result.theta) {
                    Ok((e, _)) => e,
                    // The others need it (as above): its evidence stays as named.
                    Err(DiagnosisError::Location(_)) => continue,
                    Err(e) => return Err(e),
                }
            };
            let lr = eps_without - after.epsilon;
            let n = &mut named[i];
            n.epsilon_before = eps_without;
            n.likelihood_ratio = lr;
            n.log_bayes_factor = lr / 2.0 - 0.5 * n_data.ln();
        }
    }
    Ok(Diagnosis {
        before,
        after,
        named,
        rounds,
        n_candidates,
        threshold,
        alpha: opts.alpha,
        enriched: current,
    })
}
