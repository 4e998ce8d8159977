//! The steps of [`diagnose`](super::diagnose) after the first fit (module docs of [`super`]):
//! one round (screen, refit the shortlist, test the best, name it and withdraw what it stood
//! in for), the joint refit of the effects named, and the evidence recomputed after a
//! withdrawal.

use super::fit::Fit;
use super::*;

/// What every step of the workflow reads: the model class, the data and the test.
pub(super) struct Workflow<'a> {
    pub(super) spec: &'a Description,
    pub(super) data: &'a MeasuredData,
    pub(super) opts: &'a DiagnosisOptions,
    /// The likelihood-ratio threshold of the test.
    pub(super) threshold: f64,
    /// The number of data, as the BIC's `N`.
    pub(super) n_data: f64,
    pub(super) effects: Vec<Box<dyn Effect>>,
}

/// The model as enriched so far: the effects named, the description with them added, and
/// its fit.
pub(super) struct Enriched {
    pub(super) named: Vec<Named>,
    pub(super) current: Description,
    pub(super) f: Fit,
}

/// An earlier named effect that no longer passes the test with the others in the model.
struct StandIn {
    /// Its index in the effects named.
    index: usize,
    /// The ε increase when it is taken out.
    likelihood_ratio: f64,
    /// The other effects named, refitted without it.
    others: Vec<Refit>,
}

impl Workflow<'_> {
    /// One round (module docs, steps 2–5): screens every candidate, refits the shortlist,
    /// tests the best and, when it is significant, names it and withdraws what it stood in
    /// for.
    pub(super) fn round(
        &self,
        s: &mut Enriched,
        progress: &mut impl FnMut(&str, usize, usize),
    ) -> Result<Round, DiagnosisError> {
        let base = s.f.result.last.clone();
        let screened = self.screen_all(s, &base, progress)?;
        let refits = self.refit_shortlist(&s.current, &screened, &base.theta, progress);
        let eps_before = s.f.result.epsilon();
        let winner = self.name_if_significant(&refits, eps_before);
        let mut round = Round {
            epsilon: eps_before,
            candidates: screened,
            refits,
            named: winner.clone(),
            withdrawn: Vec::new(),
        };
        if let Some(w) = winner {
            let theta = w.refit.theta.clone();
            s.named.push(w);
            round.withdrawn = self.withdraw_stand_ins(s, &theta)?;
        }
        Ok(round)
    }

    /// Step 2: every candidate not yet named, screened at the fitted θ (`base`) against the
    /// span of the model's own Jacobian; best score first.
    fn screen_all(
        &self,
        s: &Enriched,
        base: &Evaluation,
        progress: &mut impl FnMut(&str, usize, usize),
    ) -> Result<Vec<Candidate>, DiagnosisError> {
        let (current, data) = (&s.current, self.data);
        let mut ev = Evaluator::new(&s.f.model)?;
        let j = ev.jacobian(&s.f.model, data, base)?;
        let q = j.qr().compute_thin_Q();
        let cands = candidates_of(&self.effects, current, &s.named);
        let total = cands.len();
        let reduced = ReducedBasis::new(&s.f.model, data, &base.theta);
        let mut screened: Vec<Candidate> = map_with_progress(
            &cands,
            |(e, l)| screen(current, *e, l, data, base, &q, reduced.as_ref()),
            |done| progress("screening", done, total),
        )
        .into_iter()
        .flatten()
        .collect();
        screened.sort_by(|a, b| b.score.total_cmp(&a.score));
        Ok(screened)
    }

    /// Step 3: the shortlist ([`shortlist`]) refitted with the full nonlinear update from
    /// `theta0`; lowest ε first.
    fn refit_shortlist(
        &self,
        current: &Description,
        screened: &[Candidate],
        theta0: &[f64],
        progress: &mut impl FnMut(&str, usize, usize),
    ) -> Vec<Refit> {
        let (effects, data) = (&self.effects, self.data);
        let best = shortlist(effects, screened, self.opts.refits);
        let mut refits: Vec<Refit> = map_with_progress(
            &best,
            |c| refit(current, effect_of(effects, c.effect), c, data, theta0),
            |done| progress("refitting", done, best.len()),
        )
        .into_iter()
        .flatten()
        .collect();
        refits.sort_by(|a, b| a.epsilon.total_cmp(&b.epsilon));
        refits
    }

    /// Step 4: the best refit (`refits` sorted by ε) against the model without it, named
    /// when its likelihood ratio exceeds the threshold.
    fn name_if_significant(&self, refits: &[Refit], eps_before: f64) -> Option<Named> {
        refits.first().and_then(|r| {
            let lr = eps_before - r.epsilon;
            (lr > self.threshold).then(|| Named {
                refit: r.clone(),
                epsilon_before: eps_before,
                likelihood_ratio: lr,
                threshold: self.threshold,
                log_bayes_factor: lr / 2.0 - 0.5 * self.n_data.ln(),
                indistinguishable_from: refits[1..]
                    .iter()
                    .filter(|o| o.epsilon - r.epsilon < INDISTINGUISHABLE)
                    .cloned()
                    .collect(),
            })
        })
    }

    /// Backward elimination after an effect is named: an earlier effect that no longer
    /// passes the test with the new one in the model stood in for it; withdraw it. The test
    /// of each refits the values of the others without it (they were fitted with it
    /// present). Refits `s` from `theta` with what remains; returns what was withdrawn.
    fn withdraw_stand_ins(
        &self,
        s: &mut Enriched,
        theta: &[f64],
    ) -> Result<Vec<Withdrawn>, DiagnosisError> {
        let mut withdrawn = Vec::new();
        loop {
            let refs: Vec<&Refit> = s.named.iter().map(|n| &n.refit).collect();
            s.current = with_effects(self.spec, &self.effects, &refs)?;
            s.f = fit(&s.current, self.data, theta, false)?;
            let Some(weakest) = self.weakest(s, theta)? else {
                return Ok(withdrawn);
            };
            let gone = s.named.remove(weakest.index);
            for (n, r) in s.named.iter_mut().zip(weakest.others) {
                n.refit = r;
            }
            withdrawn.push(Withdrawn {
                effect: gone.refit.effect,
                location: gone.refit.location.clone(),
                likelihood_ratio: weakest.likelihood_ratio,
            });
        }
    }

    /// The earlier named effect (all but the last) whose withdrawal from the fitted `s`
    /// raises ε least, if that does not pass the test.
    fn weakest(&self, s: &Enriched, theta: &[f64]) -> Result<Option<StandIn>, DiagnosisError> {
        let mut weakest: Option<StandIn> = None;
        for i in 0..s.named.len().saturating_sub(1) {
            let mut others = others_than(&s.named, i);
            // An effect another one depends on (a splice whose node carries a named
            // mass) is not withdrawn alone.
            let eps_without =
                match reprofile(self.spec, &self.effects, &mut others, self.data, theta) {
                    Ok((e, _)) => e,
                    Err(DiagnosisError::Location(_)) => continue,
                    Err(e) => return Err(e),
                };
            let lr = eps_without - s.f.result.epsilon();
            if lr <= self.threshold && weakest.as_ref().is_none_or(|w| lr < w.likelihood_ratio) {
                weakest = Some(StandIn {
                    index: i,
                    likelihood_ratio: lr,
                    others,
                });
            }
        }
        Ok(weakest)
    }

    /// With several effects named, each value was fitted with the later ones still missing:
    /// refit each with the others at their values, kept when ε does not rise.
    pub(super) fn refit_jointly(&self, s: &mut Enriched) -> Result<(), DiagnosisError> {
        if s.named.len() > 1 {
            let mut set: Vec<Refit> = s.named.iter().map(|n| n.refit.clone()).collect();
            let (eps, theta) = reprofile(
                self.spec,
                &self.effects,
                &mut set,
                self.data,
                &s.f.result.theta,
            )?;
            if eps <= s.f.result.epsilon() {
                for (n, r) in s.named.iter_mut().zip(set) {
                    n.refit = r;
                }
                let refs: Vec<&Refit> = s.named.iter().map(|n| &n.refit).collect();
                s.current = with_effects(self.spec, &self.effects, &refs)?;
                s.f = fit(&s.current, self.data, &theta, false)?;
            }
        }
        Ok(())
    }

    /// After a withdrawal, the evidence of what remains is recomputed against the model
    /// without it (with the other remaining effects refitted); `after` is the misfit of `s`.
    pub(super) fn reassess(
        &self,
        s: &mut Enriched,
        before: &Localization,
        after: &Localization,
    ) -> Result<(), DiagnosisError> {
        for i in 0..s.named.len() {
            let eps_without = if s.named.len() == 1 {
                before.epsilon
            } else {
                let mut others = others_than(&s.named, i);
                match reprofile(
                    self.spec,
                    &self.effects,
                    &mut others,
                    self.data,
                    &s.f.result.theta,
                ) {
                    Ok((e, _)) => e,
                    // The others need it (as above): its evidence stays as named.
                    Err(DiagnosisError::Location(_)) => continue,
                    Err(e) => return Err(e),
                }
            };
            let lr = eps_without - after.epsilon;
            let n = &mut s.named[i];
            n.epsilon_before = eps_without;
            n.likelihood_ratio = lr;
            n.log_bayes_factor = lr / 2.0 - 0.5 * self.n_data.ln();
        }
        Ok(())
    }
}

/// The candidates refitted: the best few by score, and the best of each effect type (the
/// score is a first-order measure and underrates effects whose modal signature is strongly
/// nonlinear in their size: a member losing half its stiffness).
fn shortlist<'c>(
    effects: &[Box<dyn Effect>],
    screened: &'c [Candidate],
    refits: usize,
) -> Vec<&'c Candidate> {
    let mut best: Vec<&Candidate> = screened
        .iter()
        .filter(|c| c.score > 0.0)
        .take(refits)
        .collect();
    for e in effects {
        if let Some(c) = screened
            .iter()
            .find(|c| c.effect == e.kind() && c.score > 0.0)
            && !best.iter().any(|b| std::ptr::eq(*b, c))
        {
            best.push(c);
        }
    }
    best
}

/// The refits of the effects named other than the `i`-th.
fn others_than(named: &[Named], i: usize) -> Vec<Refit> {
    named
        .iter()
        .enumerate()
        .filter(|&(k, _)| k != i)
        .map(|(_, n)| n.refit.clone())
        .collect()
}
