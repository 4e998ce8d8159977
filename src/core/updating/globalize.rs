//! Globalized mode matching (DESIGN §5): local minima are real (MAC pairing can lock onto
//! wrong modes early), so a fit that ends far above its χ² bound is restarted from spread
//! starts.

use super::UpdateError;
use super::data::MeasuredData;
use super::mode_matching::{ModeMatching, ModeMatchingOptions, ModeMatchingResult};
use super::residual::Evaluator;
use crate::core::model::Model;
use crate::core::stats::chi2_bound;

/// Where a globalized update found its answer.
#[derive(Debug, Clone, PartialEq)]
pub enum StartPath {
    /// The run from the given θ0 was accepted.
    Given,
    /// A restart from the uniform start `θ = value · 1` (tried in order of [`RESTART_STARTS`]).
    Restart { value: f64 },
}

/// Uniform restart values, tried in this order: moderately soft and stiff first, then the
/// ends of the range where bolted connections are identifiable (paper Fig. 9b).
pub const RESTART_STARTS: [f64; 6] = [0.5, 2.0, 0.3, 3.5, 0.7, 1.4];

impl ModeMatching {
    /// [`ModeMatching::run`] with globalization (DESIGN §5): a run that does not converge, or
    /// ends with ε above [`chi2_bound`], is taken for a local minimum (typically MAC pairing
    /// locked onto wrong modes early), and the update is restarted from the spread starts
    /// [`RESTART_STARTS`] (the E-type and other parameters at their nominal value). The first
    /// restart that converges within the bound is accepted; otherwise the lowest-ε converged
    /// run (or the lowest-ε run) is returned. Also returns the path that found it.
    pub fn run_global(
        &mut self,
        model: &Model,
        data: &MeasuredData,
        theta0: &[f64],
        opts: &ModeMatchingOptions,
    ) -> Result<(ModeMatchingResult, StartPath), UpdateError> {
        self.globalize(model, data, theta0, opts, false)
    }

    /// [`ModeMatching::run_global`] with the run from `theta0` and every restart started at
    /// once on rayon's pool, each on an evaluator of its own and without progress reports;
    /// a run is not started once an earlier one is accepted. A cold evaluation depends on θ
    /// alone, so the result is the sequential one; an evaluator with warm starts (whose
    /// solves depend on the last one) runs them in turn. Runs beside one that is accepted
    /// are wasted, so this is for one-off fits (`diagnose`'s first), not for a tracker's.
    pub fn run_global_parallel(
        &mut self,
        model: &Model,
        data: &MeasuredData,
        theta0: &[f64],
        opts: &ModeMatchingOptions,
    ) -> Result<(ModeMatchingResult, StartPath), UpdateError> {
        let at_once = !self.evaluator.warm() && rayon::current_num_threads() > 1;
        self.globalize(model, data, theta0, opts, at_once)
    }

    /// The globalization: the run from `theta0`, then the restarts in order until one is
    /// accepted, on this evaluator; with `at_once` all at once ([`Self::all_runs`]), chosen
    /// among in the same order.
    fn globalize(
        &mut self,
        model: &Model,
        data: &MeasuredData,
        theta0: &[f64],
        opts: &ModeMatchingOptions,
        at_once: bool,
    ) -> Result<(ModeMatchingResult, StartPath), UpdateError> {
        let bound = chi2_bound(data.n_data(), model.n_params());
        // Converged within its bound. (A fit paired across a crossing is accepted here: the
        // tracker's cold starts and the diagnosis's fits keep their behaviour; `update`
        // searches on it, see [`super::strategy::search_reason`].)
        let good = |r: &ModeMatchingResult| r.converged() && r.epsilon() <= bound;
        let mut runs = if at_once {
            self.all_runs(model, data, theta0, opts, &good)
        } else {
            Vec::new()
        }
        .into_iter();
        let mut next = |me: &mut Self, start: &[f64]| {
            runs.next()
                .flatten()
                .unwrap_or_else(|| me.run(model, data, start, opts))
        };
        let first = next(self, theta0)?;
        if good(&first) {
            return Ok((first, StartPath::Given));
        }
        let mut best = (first, StartPath::Given);
        for value in RESTART_STARTS {
            // A start the solver cannot handle (an eigen solve that fails at its θ) is a bad
            // start, not a failed update.
            let Ok(r) = next(self, &uniform_start(model, value)) else {
                continue;
            };
            let path = StartPath::Restart { value };
            if good(&r) {
                return Ok((r, path));
            }
            let better = match (r.converged(), best.0.converged()) {
                (true, false) => true,
                (false, true) => false,
                _ => r.epsilon() < best.0.epsilon(),
            };
            if better {
                best = (r, path);
            }
        }
        Ok(best)
    }

    /// The run from `theta0` and every restart at once on rayon's pool, each on an
    /// evaluator of its own (in order; `None` for a run not started because an earlier one
    /// was already accepted). Work-stealing keeps both cores busy to the end, where runs
    /// run in pairs waited for the longer of each pair.
    fn all_runs(
        &self,
        model: &Model,
        data: &MeasuredData,
        theta0: &[f64],
        opts: &ModeMatchingOptions,
        good: &(dyn Fn(&ModeMatchingResult) -> bool + Sync),
    ) -> Vec<Option<Result<ModeMatchingResult, UpdateError>>> {
        use rayon::prelude::*;
        use std::sync::atomic::{AtomicUsize, Ordering};
        let starts: Vec<Vec<f64>> = std::iter::once(theta0.to_vec())
            .chain(RESTART_STARTS.iter().map(|&v| uniform_start(model, v)))
            .collect();
        let accepted = AtomicUsize::new(usize::MAX);
        let pairing = self.evaluator.pairing();
        starts
            .par_iter()
            .enumerate()
            .map(|(i, start)| {
                if accepted.load(Ordering::Relaxed) < i {
                    return None;
                }
                let run = Evaluator::new(model)
                    .map_err(UpdateError::from)
                    .and_then(|mut ev| {
                        ev.set_pairing(pairing);
                        ModeMatching::new(ev).run(model, data, start, opts)
                    });
                if run.as_ref().is_ok_and(good) {
                    accepted.fetch_min(i, Ordering::Relaxed);
                }
                Some(run)
            })
            .collect()
    }
}

/// The restart `θ = value × nominal` (the E-type parameters at their nominal value).
fn uniform_start(model: &Model, value: f64) -> Vec<f64> {
    model
        .parameters()
        .iter()
        .map(|p| match p.kind {
            crate::core::model::ParameterKind::Modulus(_) => p.nominal,
            _ => value * p.nominal,
        })
        .collect()
}
