//! The whole mode-matching update as `boltwatch update` runs it: the fit from θ0; when it
//! ends above its χ² bound, the shape σ rescaled to what the data support
//! ([`super::variance`]); when it is not a credible answer (not converged, above its bound,
//! a parameter on a bound, or two measured modes paired across a crossing), the global
//! search inside the bounds ([`super::search`]).

use super::UpdateError;
use super::data::MeasuredData;
use super::mode_matching::{ModeMatching, ModeMatchingOptions, ModeMatchingResult, StepControl};
use super::search::{MAX_STARTS, SearchOptions, SearchResult, global_search};
use super::variance::{MAX_OUTER, Rescaled};
use crate::core::model::Model;
use crate::core::stats::chi2_bound;

/// Starts of the automatic global search: enough that the footbridge's 17 bounded
/// parameters find the basin of its published best fit (4 of 4 polished starts reach it
/// with seed 1), within a minute on two cores.
pub const AUTO_STARTS: usize = 32;

/// Which σ the fit weighs the data by.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum WeightsPolicy {
    /// Rescaled when the fit under the stated σ ends above its χ² bound.
    Auto,
    Stated,
    Rescaled,
}

/// When the global search runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SearchPolicy {
    /// With [`AUTO_STARTS`] starts when the fit from θ0 is not credible.
    Auto,
    Never,
    /// Always, with this many starts.
    Starts(usize),
}

/// How [`update`] proceeds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct UpdatePolicy {
    pub weights: WeightsPolicy,
    pub search: SearchPolicy,
    pub seed: u32,
}

impl Default for UpdatePolicy {
    fn default() -> Self {
        Self {
            weights: WeightsPolicy::Auto,
            search: SearchPolicy::Auto,
            seed: 1,
        }
    }
}

/// The outcome of [`update`].
#[derive(Debug, Clone)]
pub struct Update {
    /// The answer, with its weighting.
    pub fit: Rescaled,
    /// Why the σ were rescaled, if they were.
    pub rescaled: Option<String>,
    /// The search and why it ran, if it did.
    pub search: Option<(SearchResult, String)>,
    /// The start the answer came from: `None` for θ0, else the search's start index.
    pub start: Option<usize>,
}

/// The update of `model` to `data` from `theta0` (module docs). The paper's fixed-κ
/// Gauss–Newton runs as published: one fit, the stated σ, no search.
pub fn update(
    mm: &mut ModeMatching,
    model: &Model,
    data: &MeasuredData,
    theta0: &[f64],
    opts: &ModeMatchingOptions,
    policy: &UpdatePolicy,
) -> Result<Update, UpdateError> {
    if let SearchPolicy::Starts(n) = policy.search
        && !(1..=MAX_STARTS).contains(&n)
    {
        return Err(UpdateError::Option {
            name: "starts",
            value: n as f64,
            reason: "need 1 to 65,536 starts",
        });
    }
    let first = mm.run(model, data, theta0, opts)?;
    let bound = chi2_bound(data.n_data(), model.n_params());
    let kappa = matches!(opts.step, StepControl::FixedKappa(_));
    let rescaled = match policy.weights {
        _ if kappa => None,
        WeightsPolicy::Stated => None,
        WeightsPolicy::Rescaled => Some("requested".to_string()),
        WeightsPolicy::Auto => {
            (first.epsilon() > bound).then(|| rescale_reason(first.epsilon(), bound))
        }
    };
    let search = match policy.search {
        _ if kappa => None,
        SearchPolicy::Never => None,
        SearchPolicy::Starts(n) => Some((n, format!("{n} starts requested"))),
        SearchPolicy::Auto => search_reason(&first, bound).map(|r| (AUTO_STARTS, r)),
    };
    let local = match &rescaled {
        Some(_) => {
            let ones = vec![1.0; data.n_groups()];
            mm.run_rescaled(model, data, &first.theta, &ones, opts, MAX_OUTER)?
        }
        None => Rescaled::stated(data, first),
    };
    let Some((n, why)) = search else {
        return Ok(Update {
            fit: local,
            rescaled,
            search: None,
            start: None,
        });
    };
    let options = SearchOptions {
        rescale: rescaled.is_some(),
        pairing: mm.evaluator.pairing(),
        ..SearchOptions::new(n, policy.seed)
    };
    let found = global_search(model, data, opts, &options, Some(local))?;
    let best = found.best();
    // The start it came from: θ0 if the fit from θ0 ended there too.
    let start = match best.reached_from.contains(&None) {
        true => None,
        false => best.reached_from.iter().find_map(|s| *s),
    };
    Ok(Update {
        fit: best.fit.clone(),
        rescaled,
        start,
        search: Some((found, why)),
    })
}

/// Why a fit that ended at `epsilon` under the stated σ, above its χ² `bound`, is redone
/// with the σ rescaled ([`super::variance`]).
pub fn rescale_reason(epsilon: f64, bound: f64) -> String {
    format!(
        "under the stated σ the fit ends at ε = {epsilon:.1}, above its χ² bound {bound:.1}: \
         the σ of each mode's shape that misfits beyond them are scaled to its misfit \
         (the frequencies keep theirs)"
    )
}

/// Why the fit from θ0 calls for a global search, if it does.
pub fn search_reason(first: &ModeMatchingResult, bound: f64) -> Option<String> {
    if !first.converged() {
        Some(format!("the fit from θ0 stopped ({:?})", first.termination))
    } else if first.epsilon() > bound {
        Some(format!(
            "the fit from θ0 ended at ε = {:.1}, above its χ² bound {bound:.1}",
            first.epsilon()
        ))
    } else if first.at_bound.iter().any(Option::is_some) {
        Some("the fit from θ0 ended with a parameter at a bound".into())
    } else if let Some((a, b)) = crossed(&first.last.pairing) {
        Some(format!(
            "the fit from θ0 pairs measured modes {} and {} with model modes in the opposite \
             order: the answer may lie beyond a crossing",
            a + 1,
            b + 1
        ))
    } else {
        None
    }
}

/// Two measured modes (in ascending frequency) paired with model modes in the opposite
/// order, if any: a fit on one side of a crossing, with a minimum on the other side too
/// (noise-free lab-frame truths that swap two modes end there 15 times in 50, at ε below
/// its χ² bound).
pub fn crossed(pairing: &[usize]) -> Option<(usize, usize)> {
    (0..pairing.len())
        .flat_map(|a| (a + 1..pairing.len()).map(move |b| (a, b)))
        .find(|&(a, b)| pairing[a] > pairing[b])
}
