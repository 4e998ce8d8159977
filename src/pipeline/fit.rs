//! The fit of one modal set (the paper's (5)–(9), (15), (18)–(20)): mode matching
//! warm-started from the last estimate, a globalized cold start from the baseline where
//! the warm start fails, and the refit under rescaled σ when the stated σ do not explain
//! the data (`tracker.weights = "auto"`).

use super::{Tracker, Weights};
use crate::contract::update::WeightsDoc;
use crate::core::stats::chi2_bound;
use crate::core::updating::strategy::rescale_reason;
use crate::core::updating::variance::MAX_OUTER;
use crate::core::updating::{MeasuredData, ModeMatchingResult, UpdateError};

impl Tracker {
    /// The fit under the stated σ ([`Self::fit_stated`]), refitted with each mode's shape
    /// σ rescaled to its misfit when its ε ends above the χ² bound (`tracker.weights =
    /// "auto"`: the rule of `update`, [`crate::core::updating::variance`]). The rescaled fit
    /// starts from the last such fit's factors; one that fails or does not converge leaves
    /// the stated fit in place.
    pub(super) fn fit(&mut self, data: &MeasuredData) -> Result<SetFit, UpdateError> {
        let (stated, warm, fallback) = self.fit_stated(data)?;
        let bound = chi2_bound(data.n_data(), self.model.n_params());
        let epsilon = stated.epsilon();
        let plain = |result| SetFit {
            result,
            epsilon,
            warm,
            fallback: fallback.clone(),
            weights: None,
            scales: None,
        };
        if self.cfg.weights == Weights::Stated || epsilon <= bound || !stated.converged() {
            return Ok(plain(stated));
        }
        let start = match &self.state.scales {
            Some(s) if s.len() == data.n_groups() => s.clone(),
            _ => vec![1.0; data.n_groups()],
        };
        let rescaled = self.mm.run_rescaled(
            &self.model,
            data,
            &stated.theta,
            &start,
            &self.opts,
            MAX_OUTER,
        );
        let Some(fit) = rescaled.ok().filter(|f| f.result.converged()) else {
            return Ok(plain(stated));
        };
        Ok(SetFit {
            epsilon: fit.stated_epsilon,
            warm,
            weights: Some(WeightsDoc::of(&fit, Some(rescale_reason(epsilon, bound)))),
            scales: Some(fit.scales),
            fallback,
            result: fit.result,
        })
    }

    /// Warm start from the last θ; a cold, globalized start from the baseline (or the
    /// nominal θ) on the first set or when the warm fit fails. Returns the fit, whether it
    /// was warm, and why a cold start was needed.
    fn fit_stated(
        &mut self,
        data: &MeasuredData,
    ) -> Result<(ModeMatchingResult, bool, Option<String>), UpdateError> {
        let cold_theta = self
            .state
            .baseline
            .clone()
            .unwrap_or_else(|| self.model.nominal_theta());
        let Some(theta) = self
            .state
            .linearized_at
            .clone()
            .or_else(|| self.state.theta.clone())
        else {
            let (r, _) = self
                .mm
                .run_global(&self.model, data, &cold_theta, &self.opts)?;
            return Ok((r, false, Some("first set".into())));
        };
        let warm = self.mm.run(&self.model, data, &theta, &self.opts)?;
        let bound = chi2_bound(data.n_data(), self.model.n_params());
        let mut pairs = warm.last.pairing.clone();
        pairs.sort_unstable();
        pairs.dedup();
        let reason = if !warm.converged() {
            Some(format!(
                "warm start did not converge ({:?})",
                warm.termination
            ))
        } else if pairs.len() < warm.last.pairing.len() {
            Some("pairing collapsed (two measured modes on one model mode)".into())
        } else if warm.epsilon() > bound
            && self
                .state
                .epsilon
                .is_some_and(|e| warm.epsilon() > self.cfg.epsilon_jump * e.max(1e-300))
        {
            Some(format!(
                "ε jumped from {:.1} to {:.1}",
                self.state.epsilon.unwrap_or(f64::NAN),
                warm.epsilon()
            ))
        } else {
            None
        };
        let Some(reason) = reason else {
            return Ok((warm, true, None));
        };
        let (cold, _) = self
            .mm
            .run_global(&self.model, data, &cold_theta, &self.opts)?;
        // Keep the better of the two (a converged fit with the lower ε).
        let better = match (cold.converged(), warm.converged()) {
            (true, false) => true,
            (false, true) => false,
            _ => cold.epsilon() <= warm.epsilon(),
        };
        Ok(if better {
            (cold, false, Some(reason))
        } else {
            (
                warm,
                true,
                Some(format!("{reason}; the cold start did no better")),
            )
        })
    }
}

/// A set's fit as the tracker reports it.
pub(super) struct SetFit {
    /// Under the rescaled σ when `weights` is set, else under the stated σ.
    pub(super) result: ModeMatchingResult,
    /// ε (5) under the set's stated σ at the fit.
    pub(super) epsilon: f64,
    /// Warm-started from the last θ.
    pub(super) warm: bool,
    /// Why a cold start was needed.
    pub(super) fallback: Option<String>,
    /// The rescaled weighting, when the fit used one.
    pub(super) weights: Option<WeightsDoc>,
    /// Its factors, the next rescaled fit's start; stored only once the set is accepted.
    pub(super) scales: Option<Vec<f64>>,
}
