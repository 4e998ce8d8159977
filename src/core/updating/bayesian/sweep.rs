//! The σ_c study of paper Figs. 5, 7, 15 and 18, and an automatic choice of σ_c.
//!
//! **Rule (discrepancy principle).** σ_c is the standard deviation allowed to the model
//! equation's residual `e_C = (K(θ) − λM)φ`. Small σ_c trusts the model: the most probable
//! modes are the model's, and the measurement misfit `e_Mᵀ Σ_M⁻¹ e_M` is what the model
//! class leaves unexplained. Raising σ_c lets φ and λ absorb modelling error, and the misfit
//! falls. The automatic σ_c is the **smallest** σ_c at which the misfit has fallen to its
//! χ² expectation under measurement noise alone, `ν = N_data − N_θ − N_m`
//! ([`BayesProblem::misfit_dof`]): just enough modelling-error allowance to explain the
//! data to the noise level, and no more (a larger σ_c starts fitting the noise). If the
//! misfit is already at or below ν at the bottom of the range, the model needs no allowance
//! and the bottom is taken; if it is still above ν at the top, the top is taken and the
//! rule is reported as not met.

use super::newton::NewtonStop;
use super::{
    BayesError, BayesProblem, BayesResult, BayesSettings, BayesSolver, ContinuationStage,
    ObjectiveTerms,
};
use crate::core::modal::ModalError;
use crate::core::model::Model;
use crate::core::updating::{Evaluator, LogBounds, MeasuredData};

/// Failures of a sweep.
#[derive(Debug, thiserror::Error)]
pub enum SweepError {
    #[error(transparent)]
    Bayes(#[from] BayesError),
    #[error("ε at the MAP θ: {0}")]
    Modal(#[from] ModalError),
    #[error("σ_c range: need 0 < from < to and at least 2 points (got {from} … {to}, {points})")]
    Range { from: f64, to: f64, points: usize },
}

/// What a sweep solves at each σ_c.
#[derive(Debug, Clone)]
pub struct SweepSettings {
    pub prior_mean: Vec<f64>,
    pub prior_std: Vec<f64>,
    /// Every solve starts here (cold start, so iteration counts compare across σ_c; the
    /// Newton solver continues in σ_c from above when its cold start stalls).
    pub theta0: Vec<f64>,
    pub newton_max_iterations: usize,
    /// Also run the paper's alternating solver, to this many iterations.
    pub alternating_max_iterations: Option<usize>,
    /// θ is kept within these factors of its nominal value as well as within the model's
    /// own bounds (`None`: the model's only).
    pub bounds: Option<(f64, f64)>,
}

/// The alternating solver's outcome at one σ_c.
#[derive(Debug, Clone, PartialEq)]
pub struct AlternatingRun {
    pub iterations: usize,
    pub converged: bool,
    pub theta: Vec<f64>,
    pub total: f64,
}

/// One σ_c of the sweep (Newton solver), with ε (5) of the model at the MAP θ.
#[derive(Debug, Clone)]
pub struct SweepPoint {
    pub sigma_c: f64,
    pub theta: Vec<f64>,
    pub lambda: Vec<f64>,
    pub terms: ObjectiveTerms,
    pub epsilon: f64,
    /// MAC of each most probable shape to the measured one.
    pub mac: Vec<f64>,
    /// Newton iterations, all continuation stages together.
    pub iterations: usize,
    pub converged: bool,
    /// The σ_c continuation of the Newton solve (one stage when the cold start converged).
    pub stages: Vec<ContinuationStage>,
    pub alternating: Option<AlternatingRun>,
}

/// `points` values from `from` to `to`, equally spaced in log σ_c.
pub fn log_grid(from: f64, to: f64, points: usize) -> Result<Vec<f64>, SweepError> {
    if !(from > 0.0 && to > from && to.is_finite() && points >= 2) {
        return Err(SweepError::Range { from, to, points });
    }
    let (a, b) = (from.ln(), to.ln());
    Ok((0..points)
        .map(|i| (a + (b - a) * i as f64 / (points - 1) as f64).exp())
        .collect())
}

/// The MAP (Newton) at one σ_c, with ε of the model at its θ.
fn point(
    model: &Model,
    data: &MeasuredData,
    sigma_c: f64,
    settings: &SweepSettings,
    evaluator: &mut Evaluator,
) -> Result<SweepPoint, SweepError> {
    let mut prob = BayesProblem::new(
        model,
        data,
        &BayesSettings {
            sigma_c,
            prior_mean: settings.prior_mean.clone(),
            prior_std: settings.prior_std.clone(),
        },
    )?;
    prob.set_bounds(LogBounds::new(model, settings.bounds));
    let res = prob.solve(
        BayesSolver::Newton,
        &settings.theta0,
        settings.newton_max_iterations,
    )?;
    let alternating = match settings.alternating_max_iterations {
        Some(max) => {
            let alt = prob.solve(BayesSolver::Alternating, &settings.theta0, max)?;
            Some(AlternatingRun {
                iterations: alt.iterations,
                converged: alt.converged,
                theta: alt.state.theta,
                total: alt.terms.total,
            })
        }
        None => None,
    };
    // ε of mode matching at the MAP's θ, for comparison; where θ is so far out that the
    // eigen solver fails there (a large σ_c leaves θ hardly constrained), not a number.
    let epsilon = evaluator
        .evaluate(model, data, &res.state.theta)
        .map_or(f64::NAN, |e| e.epsilon);
    Ok(SweepPoint {
        sigma_c,
        mac: prob.mac_to_measured(&res.state.phi),
        theta: res.state.theta,
        lambda: res.state.lambda,
        terms: res.terms,
        epsilon,
        iterations: res.iterations,
        converged: res.converged,
        stages: res.stages,
        alternating,
    })
}

/// The MAP at every σ_c of `sigmas`; `progress(i, point)` after each.
pub fn sweep_sigma(
    model: &Model,
    data: &MeasuredData,
    sigmas: &[f64],
    settings: &SweepSettings,
    progress: &mut dyn FnMut(usize, &SweepPoint),
) -> Result<Vec<SweepPoint>, SweepError> {
    let mut evaluator = Evaluator::new(model)?;
    let mut out = Vec::with_capacity(sigmas.len());
    for (i, &s) in sigmas.iter().enumerate() {
        let p = point(model, data, s, settings, &mut evaluator)?;
        progress(i, &p);
        out.push(p);
    }
    Ok(out)
}

/// One trial of [`AutoSigma::search`], as it starts (`misfit` `None`) or ends.
#[derive(Debug, Clone, Copy)]
pub struct SigmaTrial {
    /// 1-based.
    pub index: usize,
    pub sigma_c: f64,
    /// `e_Mᵀ Σ_M⁻¹ e_M` at the trial's MAP.
    pub misfit: Option<f64>,
    /// The χ² expectation ν it is held to.
    pub target: f64,
}

/// The automatic σ_c (module docs) and how it was found.
#[derive(Debug, Clone)]
pub struct AutoSigma {
    pub sigma_c: f64,
    /// The χ² expectation ν the misfit is held to.
    pub target: f64,
    /// The misfit `e_Mᵀ Σ_M⁻¹ e_M` at the chosen σ_c.
    pub misfit: f64,
    /// `false` when the misfit is still above ν at the top of the range.
    pub met: bool,
    /// Every σ_c tried, with its misfit.
    pub trials: Vec<(f64, f64)>,
    /// θ of the MAP at the chosen σ_c, when a trial solved it there (the search's choice;
    /// not the sweep's, which is interpolated): the final solve starts from it.
    pub theta: Option<Vec<f64>>,
    /// λ of that MAP, with `theta`.
    pub lambda: Option<Vec<f64>>,
}

/// The discrepancy rule applied to a finished sweep (ascending σ_c): the first crossing of
/// the misfit below `target`, interpolated linearly in `(log σ_c, log misfit)`.
pub fn discrepancy_choice(points: &[SweepPoint], target: f64) -> Option<AutoSigma> {
    let trials: Vec<(f64, f64)> = points
        .iter()
        .map(|p| (p.sigma_c, p.terms.measurement))
        .collect();
    let first = *trials.first()?;
    let last = *trials.last()?;
    let done = |sigma_c: f64, misfit: f64, met: bool| AutoSigma {
        sigma_c,
        target,
        misfit,
        met,
        trials: trials.clone(),
        theta: None,
        lambda: None,
    };
    if first.1 <= target {
        return Some(done(first.0, first.1, true));
    }
    for w in trials.windows(2) {
        let ((s0, m0), (s1, m1)) = (w[0], w[1]);
        if m1 <= target {
            let t = (m0.ln() - target.ln()) / (m0.ln() - m1.ln());
            let s = (s0.ln() + t * (s1.ln() - s0.ln())).exp();
            return Some(done(s, target, true));
        }
    }
    Some(done(last.0, last.1, false))
}

/// The automatic σ_c search's first trial, as a factor of the bottom of its range. The
/// bottom is the costliest MAP of the range (a small σ_c holds λ and φ to the model's
/// eigenpairs: on the four-bay frame it stalled for 50–126 Newton iterations, 100–174 s,
/// and ended far above ν) and, when the model is wrong, only says that the root lies
/// higher. Two decades up, a model that needs no allowance costs two more trials on the
/// way down (the lab frame: 100, 10, 1), and the four-bay frame's root (47) is bracketed
/// by the first step down.
pub const AUTO_FIRST_TRIAL: f64 = 100.0;

/// The first factor by which the automatic σ_c search steps up from its first trial until
/// the misfit falls below ν (each further step squares it, up to
/// [`AUTO_BRACKET_STEP_MAX`]), and the factor by which it steps down while the misfit is
/// below ν.
pub const AUTO_BRACKET_STEP: f64 = 10.0;

/// The largest step up of the automatic σ_c search. Squaring without a cap overshot: on
/// the cantilever (root at 1.84e4) the steps from 1 reached 1e3 and then the top of the
/// range, 1e6, where the misfit was 5 orders of magnitude below ν, and the lopsided
/// bracket took 9 more trials to refine (13 in all); with steps of at most ×100 it ends at
/// 1e5, within a decade of the root.
pub const AUTO_BRACKET_STEP_MAX: f64 = 100.0;

/// The refinement of the automatic σ_c bisects instead of taking the secant when one end
/// of the bracket has `|ln(misfit/ν)|` over this many times the other's. Four-bay seed 3
/// jumps from 56 ν to 0.96 ν (a ratio of 98) and is flat above, where the secant crept by
/// tenths of the bracket; the cantilever's smooth curve has a ratio of 12 at a bracket
/// whose secant lands within 0.2 % of the root, and a guard at 10 bisected there instead
/// (three more trials).
pub const AUTO_LOPSIDED: f64 = 30.0;

/// The misfit is taken as on target when within this fraction of ν: the χ² target itself
/// spreads by `√(2/ν)` (7 % for the four-bay frame's ν = 392, 5 % for ν ≈ 800), so a closer
/// match only costs solves.
pub const AUTO_MISFIT_TOL: f64 = 0.01;

impl AutoSigma {
    /// The discrepancy rule on `[from, to]`: the root of `ln(misfit(σ_c)/ν)` in `ln σ_c`.
    /// The first trial is [`AUTO_FIRST_TRIAL`] times the bottom (never past `to`): the
    /// bottom is the costliest MAP of the range and the least informative when the model
    /// is wrong. If the misfit there is still above ν, the root is bracketed from it
    /// upwards — steps of [`AUTO_BRACKET_STEP`], then its square up to
    /// [`AUTO_BRACKET_STEP_MAX`] (never past `to`) — so the large σ_c where θ is hardly
    /// constrained are solved only when the root lies near them; if it is at or below ν,
    /// downwards by [`AUTO_BRACKET_STEP`] until the misfit is above ν or the bottom is
    /// reached (then the bottom is taken).
    /// The bracket is then refined by regula falsi with the Illinois modification (Dowell &
    /// Jarratt, BIT 11 (1971) 168–174; superlinear on this smooth, monotone curve, where
    /// bisection of the whole range needs ~11 solves), a step kept a tenth of the bracket
    /// away from either end; it bisects instead after any step that did not halve the
    /// bracket and when one end's `ln(misfit/ν)` is over [`AUTO_LOPSIDED`] times the
    /// other's (the curve can jump: four-bay seed 3 falls from 56 ν at σ_c = 1.59 to
    /// 0.96 ν at 2.4 and stays flat above, where unguarded regula falsi crept down by
    /// tenths of the bracket, six trials without reaching ν). It stops when the misfit is within
    /// [`AUTO_MISFIT_TOL`] of ν or the bracket is `rel_tol` wide in σ_c; the σ_c returned
    /// has its misfit at or below ν (the smallest such σ_c found), or within
    /// [`AUTO_MISFIT_TOL`] above it. Each trial is one MAP solve to the precision the
    /// rule needs, warm-started from the `(λ, θ)` of the trial nearest in `ln σ_c`
    /// ([`SigmaTrials::solve_trial`]). `progress` hears of each trial as it starts
    /// (`None`) and when it ends (its misfit), with the target ν: on a large model a trial
    /// takes seconds to a minute.
    pub fn search(
        model: &Model,
        data: &MeasuredData,
        from: f64,
        to: f64,
        settings: &SweepSettings,
        rel_tol: f64,
        progress: &mut dyn FnMut(SigmaTrial),
    ) -> Result<Self, SweepError> {
        log_grid(from, to, 2)?;
        let mut trials = SigmaTrials::new(model, data, from, settings, progress)?;
        let first = (from * AUTO_FIRST_TRIAL).min(to);
        let m_first = trials.misfit_at(first)?;
        let bracket = if trials.on_target(m_first) {
            return Ok(trials.choice(first, m_first, true));
        } else if m_first <= trials.target {
            match trials.bracket_down(first, m_first, from)? {
                Down::Bracket(bracket) => bracket,
                Down::Choice(sigma, m) => return Ok(trials.choice(sigma, m, true)),
            }
        } else if first >= to {
            return Ok(trials.choice(to, m_first, false));
        } else {
            let bracket = trials.bracket_up(first.ln(), m_first, to.ln())?;
            if !trials.explained(bracket.m_hi) {
                return Ok(trials.choice(to, bracket.m_hi, false));
            }
            bracket
        };
        let (hi, m_at_hi) = trials.refine(bracket, rel_tol)?;
        Ok(trials.choice(hi.exp(), m_at_hi, true))
    }
}

/// A bracket of the discrepancy rule's root in `ln σ_c`: the misfit above ν at `lo`, at or
/// below ν (or on target) at `hi`.
struct Bracket {
    lo: f64,
    m_lo: f64,
    hi: f64,
    m_hi: f64,
}

/// Where the downward bracket of [`SigmaTrials::bracket_down`] ended.
enum Down {
    /// The root lies inside.
    Bracket(Bracket),
    /// This σ_c and its misfit are the choice: on target, or the bottom of the range.
    Choice(f64, f64),
}

/// The trials of [`AutoSigma::search`]: each one MAP solve at a σ_c, warm-started from the
/// solved trial nearest in `ln σ_c` (its `(λ, θ)`), reported to `progress` as it starts
/// and ends.
struct SigmaTrials<'a> {
    model: &'a Model,
    data: &'a MeasuredData,
    /// The sweep's settings without the alternating solver; `theta0` is the warm start.
    settings: SweepSettings,
    /// The χ² expectation ν the misfit is held to.
    target: f64,
    progress: &'a mut dyn FnMut(SigmaTrial),
    /// Every σ_c tried, with its misfit.
    trials: Vec<(f64, f64)>,
    /// Solved trials: ln σ_c, λ and θ, for the warm starts.
    solved: Vec<(f64, Vec<f64>, Vec<f64>)>,
}

impl<'a> SigmaTrials<'a> {
    /// No trial yet; ν from the problem at σ_c = `from` ([`BayesProblem::misfit_dof`]).
    fn new(
        model: &'a Model,
        data: &'a MeasuredData,
        from: f64,
        settings: &SweepSettings,
        progress: &'a mut dyn FnMut(SigmaTrial),
    ) -> Result<Self, SweepError> {
        let trials = Vec::new();
        let mut s = settings.clone();
        s.alternating_max_iterations = None;
        let target = {
            let prob = BayesProblem::new(
                model,
                data,
                &BayesSettings {
                    sigma_c: from,
                    prior_mean: s.prior_mean.clone(),
                    prior_std: s.prior_std.clone(),
                },
            )?;
            prob.misfit_dof()
        };
        Ok(Self {
            model,
            data,
            settings: s,
            target,
            progress,
            trials,
            solved: Vec::new(),
        })
    }

    /// Whether misfit `m` is within [`AUTO_MISFIT_TOL`] of ν.
    fn on_target(&self, m: f64) -> bool {
        (m / self.target - 1.0).abs() <= AUTO_MISFIT_TOL
    }

    /// `ln(m/ν)`, whose root the search finds.
    fn f(&self, m: f64) -> f64 {
        (m / self.target).ln()
    }

    /// Whether misfit `m` is explained: at or below ν, or on target.
    fn explained(&self, m: f64) -> bool {
        m <= self.target || self.on_target(m)
    }

    /// The misfit of the MAP at σ_c = `sigma`: one trial.
    fn misfit_at(&mut self, sigma: f64) -> Result<f64, SweepError> {
        let x = sigma.ln();
        let (index, target) = (self.trials.len() + 1, self.target);
        let trial = |misfit| SigmaTrial {
            index,
            sigma_c: sigma,
            misfit,
            target,
        };
        (self.progress)(trial(None));
        let start = self
            .solved
            .iter()
            .min_by(|a, b| (a.0 - x).abs().total_cmp(&(b.0 - x).abs()))
            .map(|(_, lambda, theta)| (Some(lambda.clone()), theta.clone()))
            .unwrap_or_else(|| (None, self.settings.theta0.clone()));
        let r = self.solve_trial(sigma, start.0.as_deref(), &start.1)?;
        let misfit = r.terms.measurement;
        (self.progress)(trial(Some(misfit)));
        self.solved.push((x, r.state.lambda, r.state.theta));
        self.trials.push((sigma, misfit));
        Ok(misfit)
    }

    /// The MAP at `sigma` to the precision the rule needs ([`NewtonStop::TRIAL`]): from
    /// `(lambda0, theta0)` (a trial's MAP at a neighbouring σ_c) by plain Newton when
    /// `lambda0` is given, and by the σ_c continuation from `theta0` (and `λ̂`) when there
    /// is none or that did not converge (the lower `J_p` of the two then). Not from the
    /// model's eigenvalues: there `K − λM` is singular to rounding and the φ substep of a
    /// small σ_c cannot be solved (four-bay frame, σ_c = 1: its misfit ended at 31 ν).
    fn solve_trial(
        &self,
        sigma: f64,
        lambda0: Option<&[f64]>,
        theta0: &[f64],
    ) -> Result<BayesResult, SweepError> {
        let s = &self.settings;
        let mut prob = BayesProblem::new(
            self.model,
            self.data,
            &BayesSettings {
                sigma_c: sigma,
                prior_mean: s.prior_mean.clone(),
                prior_std: s.prior_std.clone(),
            },
        )?;
        prob.set_bounds(LogBounds::new(self.model, s.bounds));
        let max = s.newton_max_iterations;
        let warm = match lambda0 {
            Some(l0) => match prob.newton(l0, theta0, max, NewtonStop::TRIAL) {
                Ok(r) if r.converged => return Ok(r),
                Ok(r) => Some(r),
                // A warm start on an eigenvalue of the model (a φ substep that cannot be
                // solved): the continuation, as from no start.
                Err(_) => None,
            },
            None => None,
        };
        let continued = prob.solve_newton_continued_to(theta0, max, NewtonStop::TRIAL)?;
        Ok(match warm {
            Some(w) if w.terms.total < continued.terms.total => w,
            _ => continued,
        })
    }

    /// Steps up from `lo0` (misfit `m_lo` above ν) by [`AUTO_BRACKET_STEP`], its square,
    /// then [`AUTO_BRACKET_STEP_MAX`] each… until the misfit is explained
    /// ([`Self::explained`]) or `top` is reached.
    fn bracket_up(&mut self, mut lo0: f64, mut m_lo: f64, top: f64) -> Result<Bracket, SweepError> {
        let mut step = AUTO_BRACKET_STEP.ln();
        let (hi0, m_hi) = loop {
            let x = (lo0 + step).min(top);
            step = (2.0 * step).min(AUTO_BRACKET_STEP_MAX.ln());
            let m = self.misfit_at(x.exp())?;
            if self.explained(m) || x >= top {
                break (x, m);
            }
            (lo0, m_lo) = (x, m);
        };
        Ok(Bracket {
            lo: lo0,
            m_lo,
            hi: hi0,
            m_hi,
        })
    }

    /// Steps down from σ_c = `hi` (misfit `m_hi` explained) by [`AUTO_BRACKET_STEP`] until
    /// the misfit is above ν, or the bottom `from` is explained too. A misfit above ν but
    /// on target, or at the bottom, ends the search there.
    fn bracket_down(&mut self, mut hi: f64, mut m_hi: f64, from: f64) -> Result<Down, SweepError> {
        loop {
            let sigma = (hi / AUTO_BRACKET_STEP).max(from);
            let m = self.misfit_at(sigma)?;
            if self.on_target(m) || (m <= self.target && sigma <= from) {
                return Ok(Down::Choice(sigma, m));
            }
            if m > self.target {
                return Ok(Down::Bracket(Bracket {
                    lo: sigma.ln(),
                    m_lo: m,
                    hi: hi.ln(),
                    m_hi,
                }));
            }
            (hi, m_hi) = (sigma, m);
        }
    }

    /// Regula falsi (Illinois) on `bracket`, bisecting after a step that did not halve
    /// it or when its ends are lopsided, until the misfit at `hi` is on target or the
    /// bracket is `rel_tol` wide in σ_c: `ln σ_c` at `hi` and its misfit.
    fn refine(&mut self, bracket: Bracket, rel_tol: f64) -> Result<(f64, f64), SweepError> {
        // f(lo) > 0 ≥ f(hi).
        let (mut lo, mut hi) = (bracket.lo, bracket.hi);
        let (mut f_lo, mut f_hi) = (self.f(bracket.m_lo), self.f(bracket.m_hi));
        let mut m_at_hi = bracket.m_hi;
        // Which end the last two steps kept (Illinois: halve a kept end's f).
        let mut kept: Option<bool> = None;
        // Bisect next when the last step did not halve the bracket.
        let mut bisect = false;
        while hi - lo > rel_tol.ln_1p() && !self.on_target(m_at_hi) {
            let width = hi - lo;
            // A secant between ends whose f differ by more than a factor of AUTO_LOPSIDED
            // lands next to the smaller one, which moves the bracket by little.
            let lopsided = f_lo > AUTO_LOPSIDED * -f_hi || -f_hi > AUTO_LOPSIDED * f_lo;
            let x = if bisect || lopsided {
                lo + 0.5 * width
            } else {
                (hi - f_hi * width / (f_hi - f_lo)).clamp(lo + 0.1 * width, hi - 0.1 * width)
            };
            let m = self.misfit_at(x.exp())?;
            if m <= self.target {
                (hi, f_hi, m_at_hi) = (x, self.f(m), m);
                if kept == Some(false) {
                    f_lo *= 0.5;
                }
                kept = Some(false);
            } else {
                (lo, f_lo) = (x, self.f(m));
                if kept == Some(true) {
                    f_hi *= 0.5;
                }
                kept = Some(true);
                if self.on_target(m) {
                    // Within the tolerance above ν: as good a σ_c as one below.
                    (hi, m_at_hi) = (x, m);
                }
            }
            bisect = hi - lo > 0.5 * width;
        }
        Ok((hi, m_at_hi))
    }

    /// The search's outcome at `sigma` (`misfit`, `met`), with every trial and the θ of
    /// the trial solved at `sigma`, if any.
    fn choice(self, sigma: f64, misfit: f64, met: bool) -> AutoSigma {
        let at = self
            .solved
            .into_iter()
            .find(|(x, _, _)| (x - sigma.ln()).abs() <= 1e-12);
        let (lambda, theta) = match at {
            Some((_, l, t)) => (Some(l), Some(t)),
            None => (None, None),
        };
        AutoSigma {
            sigma_c: sigma,
            target: self.target,
            misfit,
            met,
            trials: self.trials,
            theta,
            lambda,
        }
    }
}
