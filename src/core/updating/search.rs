//! Global search for the mode-matching minimum inside the bounds (DESIGN §5: local minima
//! are real).
//!
//! A space-filling design of starts in `u = ln θ` over the search box (a scrambled Sobol
//! sequence: Burley, "Practical Hash-based Owen Scrambling", JCGT 2020, through the
//! `sobol_burley` crate), each start screened by a few Levenberg–Marquardt iterations, the
//! best few polished to convergence; every start runs on its own evaluator, on every core.
//! With rescaled σ ([`super::variance`]) each fit is iterated with its group factors and
//! fits are ranked by `J_w`; otherwise by ε. The polished fits are grouped into distinct
//! minima (the same objective to 1e-4 and every θ_i within its standard deviation), each
//! listed with how many starts reached it. A start's
//! fit depends on the start alone (cold eigen solves, no shared state), so the search is
//! deterministic for a seed whatever the thread count.

use rayon::prelude::*;

use super::UpdateError;
use super::bounds::LogBounds;
use super::data::MeasuredData;
use super::mode_matching::{FinalStep, ModeMatching, ModeMatchingOptions};
use super::residual::{Evaluator, Pairing};
use super::variance::{MAX_OUTER, Rescaled};
use crate::core::model::Model;

/// Where the box has no bound of its own (an unbounded side, or `lower: 0`), it spans this
/// factor either side of the nominal θ: the range over which a connection's stiffness
/// moves its frequencies measurably (paper Fig. 9b), beyond which starts only waste solves.
pub const DESIGN_SPAN: f64 = 10.0;

/// Levenberg–Marquardt iterations that screen a start: enough to leave the start's
/// transient (the first steps cut most of ε) and rank the basins, few enough that a start
/// costs a handful of eigen solves.
pub const SCREEN_ITERATIONS: usize = 4;

/// Options of [`global_search`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SearchOptions {
    /// Number of design points (starts).
    pub starts: usize,
    /// Seed of the scrambling: the same seed gives the same starts.
    pub seed: u32,
    /// How many screened starts are polished to convergence.
    pub polish: usize,
    /// Fit with the σ rescaled per data group ([`super::variance`]).
    pub rescale: bool,
    /// The pairing rule of every fit.
    pub pairing: Pairing,
}

impl SearchOptions {
    /// `starts` starts of which an eighth (at least 4) are polished, under the stated σ
    /// and pairing by misfit.
    pub fn new(starts: usize, seed: u32) -> Self {
        Self {
            starts,
            seed,
            polish: (starts / 8).max(4).min(starts),
            rescale: false,
            pairing: Pairing::Misfit,
        }
    }
}

/// One distinct minimum found.
#[derive(Debug, Clone)]
pub struct Minimum {
    /// The best fit that ended here, with its weighting.
    pub fit: Rescaled,
    /// Indices of the starts whose fit ended here (`None`: the run from θ0).
    pub reached_from: Vec<Option<usize>>,
}

/// The outcome of [`global_search`]: the minima, best first (converged before not, then
/// by ε).
#[derive(Debug, Clone)]
pub struct SearchResult {
    pub minima: Vec<Minimum>,
    /// The design points, in `θ`.
    pub starts: Vec<Vec<f64>>,
    pub options: SearchOptions,
}

impl SearchResult {
    /// The best minimum.
    pub fn best(&self) -> &Minimum {
        &self.minima[0]
    }
}

/// The design points: Sobol points of `bounds` ∩ `nominal ×/÷` [`DESIGN_SPAN`] in ln θ.
pub fn design(nominal: &[f64], bounds: &LogBounds, starts: usize, seed: u32) -> Vec<Vec<f64>> {
    let span = DESIGN_SPAN.ln();
    let boxes: Vec<(f64, f64)> = (nominal.iter().enumerate())
        .map(|(i, p)| {
            let u = p.ln();
            (bounds.lo[i].max(u - span), bounds.hi[i].min(u + span))
        })
        .collect();
    (0..starts)
        .map(|k| {
            boxes
                .iter()
                .enumerate()
                .map(|(i, &(lo, hi))| (lo + (hi - lo) * sobol(k, i, seed)).exp())
                .collect()
        })
        .collect()
}

/// Most starts a design can have: the Sobol sequence's own limit, 2¹⁶ points.
pub const MAX_STARTS: usize = 1 << 16;

/// Coordinate `i` of Sobol point `k`: the crate's 256 dimensions, padded beyond by a new
/// seed per set of 256 (Burley's padding: each set stratified, the sets decorrelated).
fn sobol(k: usize, i: usize, seed: u32) -> f64 {
    let set = (i / sobol_burley::NUM_DIMENSIONS as usize) as u32;
    let seed = seed.wrapping_add(set.wrapping_mul(0x9E37_79B9));
    sobol_burley::sample(
        k as u32,
        (i % sobol_burley::NUM_DIMENSIONS as usize) as u32,
        seed,
    ) as f64
}

/// Searches for the global minimum of ε (or `J_w`) inside the bounds of `opts` (module
/// docs). `first` is the fit from θ0, if there is one; it takes part as a minimum like any
/// other.
pub fn global_search(
    model: &Model,
    data: &MeasuredData,
    opts: &ModeMatchingOptions,
    search: &SearchOptions,
    first: Option<Rescaled>,
) -> Result<SearchResult, UpdateError> {
    let bounds = LogBounds::new(model, opts.bounds);
    let starts = design(&model.nominal_theta(), &bounds, search.starts, search.seed);
    let screen_opts = ModeMatchingOptions {
        max_iterations: SCREEN_ITERATIONS,
        final_step: FinalStep::Stop,
        ..*opts
    };
    let ones = vec![1.0; data.n_groups()];
    let cold: Vec<(Vec<f64>, Vec<f64>)> =
        starts.iter().map(|s| (s.clone(), ones.clone())).collect();
    let screened = fit_all(model, data, &screen_opts, search, 2, &cold)?;
    let mut order: Vec<usize> = (0..starts.len())
        .filter(|&k| screened[k].is_some())
        .collect();
    let screen_rank = |k: usize| screened[k].as_ref().map_or(f64::INFINITY, rank);
    order.sort_by(|&a, &b| screen_rank(a).total_cmp(&screen_rank(b)));
    order.truncate(search.polish);
    order.sort_unstable();
    let from: Vec<(Vec<f64>, Vec<f64>)> = (order.iter())
        .filter_map(|&k| screened[k].as_ref())
        .map(|f| (f.result.theta.clone(), f.scales.clone()))
        .collect();
    let polished = fit_all(model, data, opts, search, MAX_OUTER, &from)?;
    let fits = first.map(|f| (None, f)).into_iter().chain(
        (order.iter().map(|&k| Some(k)).zip(polished)).filter_map(|(k, f)| f.map(|f| (k, f))),
    );
    let minima = distinct_minima(fits);
    if minima.is_empty() {
        return Err(UpdateError::Option {
            name: "starts",
            value: search.starts as f64,
            reason: "no start could be fitted (every eigen solve failed)",
        });
    }
    Ok(SearchResult {
        minima,
        starts,
        options: *search,
    })
}

/// The objective of a fit for ranking (a failed fit ranks last).
fn rank(f: &Rescaled) -> f64 {
    if f.objective.is_finite() {
        f.objective
    } else {
        f64::INFINITY
    }
}

/// Mode matching from every start `(θ, factors)`, in parallel, one evaluator per worker
/// (cold solves: the fit of a start does not depend on what its worker ran before); with
/// rescaled σ, at most `max_outer` fits per start. A start whose fit fails (an eigen solve
/// the solver cannot do at its θ) is a bad start: `None`, not a failed search.
fn fit_all(
    model: &Model,
    data: &MeasuredData,
    opts: &ModeMatchingOptions,
    search: &SearchOptions,
    max_outer: usize,
    starts: &[(Vec<f64>, Vec<f64>)],
) -> Result<Vec<Option<Rescaled>>, UpdateError> {
    // The evaluator is built once up front, so a model it cannot take is an error.
    Evaluator::new(model)?;
    Ok(starts
        .par_iter()
        .map_init(
            || None::<ModeMatching>,
            |mm, (theta, scales)| {
                let mm = match mm {
                    Some(mm) => mm,
                    None => {
                        let mut ev = Evaluator::new(model).ok()?;
                        ev.set_pairing(search.pairing);
                        mm.insert(ModeMatching::new(ev))
                    }
                };
                if search.rescale {
                    mm.run_rescaled(model, data, theta, scales, opts, max_outer)
                        .ok()
                } else {
                    let r = mm.run(model, data, theta, opts).ok()?;
                    Some(Rescaled::stated(data, r))
                }
            },
        )
        .collect())
}

/// Groups fits into distinct minima (module docs), best first.
fn distinct_minima(fits: impl Iterator<Item = (Option<usize>, Rescaled)>) -> Vec<Minimum> {
    let mut minima: Vec<Minimum> = Vec::new();
    for (from, f) in fits {
        match minima.iter_mut().find(|m| same_minimum(&m.fit, &f)) {
            Some(m) => {
                m.reached_from.push(from);
                if rank(&f) < rank(&m.fit) {
                    m.fit = f;
                }
            }
            None => minima.push(Minimum {
                fit: f,
                reached_from: vec![from],
            }),
        }
    }
    minima.sort_by(|a, b| {
        (b.fit.result.converged())
            .cmp(&a.fit.result.converged())
            .then(rank(&a.fit).total_cmp(&rank(&b.fit)))
    });
    minima
}

/// Whether two fits ended at the same minimum: the objective equal to 1e-4 of its value
/// (or 1e-4 absolute) and every `ln θ_i` within the larger of its standard deviation and
/// 1e-3 (a parameter the data do not determine, std NaN, does not separate minima).
fn same_minimum(fa: &Rescaled, fb: &Rescaled) -> bool {
    let (ea, eb) = (fa.objective, fb.objective);
    if (ea - eb).abs() > 1e-4 * ea.abs().max(eb.abs()).max(1.0) {
        return false;
    }
    let (a, b) = (&fa.result, &fb.result);
    let std = a.std();
    (0..a.theta.len()).all(|i| {
        let d = (a.theta[i].ln() - b.theta[i].ln()).abs();
        let s = std[i] / a.theta[i];
        s.is_nan() || d <= s.max(1e-3)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every point inside its box (a bound where given, a factor 10 of nominal where not),
    /// the same points for the same seed, others for another; 300 dimensions (beyond the
    /// crate's 256) padded, and each coordinate's 64 points spread over its range (no
    /// empty eighth: a stratified design, where 64 uniform draws leave one empty with
    /// probability ~0.01).
    #[test]
    fn the_design_fills_its_box_and_depends_on_the_seed_alone() {
        let p = 300;
        let nominal = vec![2.0; p];
        let mut bounds = LogBounds::none(p);
        bounds.lo[0] = 1.5_f64.ln();
        bounds.hi[0] = 3.0_f64.ln();
        let a = design(&nominal, &bounds, 64, 3);
        assert_eq!(a, design(&nominal, &bounds, 64, 3));
        assert_ne!(a, design(&nominal, &bounds, 64, 4));
        for i in 0..p {
            let (lo, hi) = if i == 0 { (1.5, 3.0) } else { (0.2, 20.0) };
            let mut eighths = [0usize; 8];
            for x in a.iter().map(|pt| pt[i]) {
                assert!(
                    x >= lo * (1.0 - 1e-12) && x <= hi * (1.0 + 1e-12),
                    "{i}: {x}"
                );
                let f = (x / lo).ln() / (hi / lo).ln();
                eighths[((f * 8.0) as usize).min(7)] += 1;
            }
            assert!(eighths.iter().all(|&c| c > 0), "dimension {i}: {eighths:?}");
        }
    }
}
