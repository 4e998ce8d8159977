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
//! 3. **Refit** the best few with the full nonlinear update: the minimum over the effect's
//!    value of the profile `ε(u) = min_θ ε(θ, u)`, found by fitting the value jointly with θ
//!    (`joint.rs`) and checked on the profile (θ refitted there from every start), or by a
//!    downhill bracket and Brent's search of the profile where the joint fit cannot be
//!    used; its standard deviation is the Laplace one, `σ_u² = 2/ε''` (ε is −2 log L up to a
//!    constant).
//! 4. **Decide** by a likelihood-ratio test: `Λ = ε_before − ε_after` is χ²₁ under "no missing
//!    effect"; the best refit is named when Λ exceeds the χ²₁ quantile at family-wise level α
//!    over all candidates screened (Bonferroni). The BIC approximation of the log Bayes factor,
//!    `Λ/2 − ½ ln N`, is reported beside it.
//! 5. A named effect is added to the model (at its fitted value) and the next round starts;
//!    the workflow stops when nothing is significant.

pub mod description;
mod effect_traits;
pub mod effects;
mod file_effects;
mod fit;
pub mod injection;
mod joint;
mod matrix_effects;
mod reduced;
mod refit;
mod screen;
mod search;
mod space;
mod workflow;

use faer::Mat;

use crate::core::modal::ModalError;
use crate::core::model::{Model, ModelError};
use crate::core::stats::chi2_1_upper_quantile;
use crate::core::updating::{
    BoundStep, Evaluation, Evaluator, FinalStep, MeasuredData, ModeMatching, ModeMatchingOptions,
    ModeMatchingResult, StepControl, UpdateError,
};
pub use description::Description;
use effects::{Effect, Sign};
use fit::{THETA_RANGE, build, fit, localize, model_with, profile_point, with_effect};
use reduced::ReducedBasis;
use refit::{effect_of, map_with_progress, refit, reprofile, with_effects};
use screen::{candidates_of, screen};
use search::minimize_1d;
use workflow::{Enriched, Workflow};

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
    // Step 1: fit the model class as it is (globalized) and localize the disagreement.
    let effects = effects::catalogue();
    let nominal = build(spec, || "no effect added".into())?;
    let f = fit(spec, data, &nominal.nominal_theta(), true)?;
    let before = localize(&f.model, data, &f.result.last);
    let n_candidates = candidates_of(&effects, spec, &[]).len();
    let w = Workflow {
        spec,
        data,
        opts,
        threshold: chi2_1_upper_quantile(opts.alpha / n_candidates.max(1) as f64),
        n_data: data.n_data() as f64,
        effects,
    };
    let mut model = Enriched {
        named: Vec::new(),
        current: spec.clone(),
        f,
    };
    // Steps 2–5, round by round, until nothing more is significant or enough is named.
    let mut rounds = Vec::new();
    loop {
        let round = w.round(&mut model, &mut progress)?;
        let done = round.named.is_none() || model.named.len() >= opts.max_effects;
        rounds.push(round);
        if done {
            break;
        }
    }
    w.refit_jointly(&mut model)?;
    let after = localize(&model.f.model, data, &model.f.result.last);
    if rounds.iter().any(|r| !r.withdrawn.is_empty()) {
        w.reassess(&mut model, &before, &after)?;
    }
    Ok(Diagnosis {
        before,
        after,
        named: model.named,
        rounds,
        n_candidates,
        threshold: w.threshold,
        alpha: opts.alpha,
        enriched: model.current,
    })
}

/// Fixtures the diagnosis module's tests share.
#[cfg(test)]
mod fixtures {
    use super::Description;
    use crate::core::model::Model;
    use crate::core::simulate::Noise;

    /// A bundled model file.
    fn bundled(name: &str) -> Description {
        let path = format!("{}/config/models/{name}", env!("CARGO_MANIFEST_DIR"));
        let text = std::fs::read_to_string(path).unwrap();
        Description::File(toml::from_str(&text).unwrap())
    }

    /// The bundled lab frame's model file.
    pub(super) fn lab() -> Description {
        bundled("lab-frame.toml")
    }

    /// The bundled space frame's model file.
    pub(super) fn space_frame() -> Description {
        bundled("space-frame.toml")
    }

    /// The stated uncertainty of simulated data: 1 % frequency CoV, 5 % shape NSD.
    pub(super) const NOISE: Noise = Noise {
        frequency_cov: 0.01,
        shape_nsd: 0.05,
    };

    /// The model's bolts spread from 0.8 to 1.0 of nominal.
    pub(super) fn spread_theta(model: &Model) -> Vec<f64> {
        model
            .nominal_theta()
            .iter()
            .enumerate()
            .map(|(i, t)| t * (0.8 + 0.05 * (i % 5) as f64))
            .collect()
    }
}
