//! One accepted modal set through the tracker: the update, the state it moves (drift
//! filters, baseline, normalisation), the estimate, the alerts and what is scheduled after
//! it (cross-check, checkpoint).

use chrono::{DateTime, Utc};

use super::alerts::Judged;
use super::normalise::{Judgement, Mode, SetEstimate};
use super::outputs::{inadequacy_message, loosening_message};
use super::{
    Action, CrosscheckRequest, DiagnoseRequest, SetFit, Tracker, alerts_off, measured_data,
};
use crate::contract::environment::Conditions;
use crate::contract::modal_set::{ModalSet, Rejection};
use crate::contract::stiffness::{
    FilteredLevel, Method, NormalisationDoc, NormalisedLevel, ParameterEstimate,
};
use crate::contract::{
    Alert, AlertDetail, AlertKind, AlertLevel, Estimate, ModeComparison, Output, Schema, finite,
    output_id,
};
use crate::core::stats::{Z95, chi2_bound, chi2_dof};

/// The normalisation's outcome for a set: `None` when it is off or the fit did not
/// converge; `Err` why no expectation was available.
type Normalisation = Option<Result<Judgement, String>>;

/// Numbers a set's alerts and wraps them as actions.
struct AlertSink {
    structure: String,
    time: DateTime<Utc>,
    count: usize,
    actions: Vec<Action>,
}

impl AlertSink {
    fn push(
        &mut self,
        connection: Option<String>,
        kind: AlertKind,
        level: AlertLevel,
        confidence: Option<f64>,
        message: String,
        detail: AlertDetail,
    ) {
        self.actions
            .push(Action::Publish(Output::Alert(Box::new(Alert {
                schema: Schema::new(),
                id: output_id(&self.structure, self.time, "alert", self.count),
                structure: self.structure.clone(),
                time: self.time,
                connection,
                kind,
                level,
                confidence,
                message,
                detail,
            }))));
        self.count += 1;
    }
}

impl Tracker {
    pub(super) fn handle_set(
        &mut self,
        set: ModalSet,
        received: DateTime<Utc>,
        payload: &[u8],
    ) -> Vec<Action> {
        let data = measured_data(&set, &self.model, self.cfg.shape_weight);
        if let Some(why) = self.implausible(&data) {
            return self.reject(received, &rejection(why), payload);
        }
        let fit = match self.fit(&data) {
            Ok(x) => x,
            // The model could not be evaluated for this set (e.g. more modes than the model
            // resolves): a rejection, state unchanged.
            Err(e) => {
                return self.reject(received, &rejection(format!("update failed: {e}")), payload);
            }
        };
        let std = fit.result.std();
        // Nothing non-finite enters the state, the filters or a checkpoint: a set whose
        // update gives a non-finite θ, σ or ε (extreme but finite inputs can) is rejected.
        if let Some(what) = not_finite(&fit.result.theta, &std, fit.epsilon) {
            let why = format!(
                "the update on this set is not finite ({what}); its frequencies, shapes or uncertainties are out of the model's range"
            );
            return self.reject(received, &rejection(why), payload);
        }
        let days = self.record(&set, &fit, &std);
        let conditions = self.state.normalisation.conditions(
            &set.conditions(),
            set.time,
            self.cfg.normalisation.max_age_s,
        );
        let judgement = self.normalise(&set, &fit, &std, days, &conditions);
        let n_data = data.n_data();
        let estimate = self.estimate(&set, &fit, &std, n_data, &conditions, &judgement);
        let mut sink = AlertSink {
            structure: self.model.name.clone(),
            time: set.time,
            count: 0,
            actions: vec![Action::Publish(Output::Estimate(Box::new(estimate)))],
        };
        self.inadequacy_alert(&mut sink, &set, fit.epsilon, n_data);
        if fit.result.converged() {
            self.loosening_alerts(&mut sink, &judgement, &conditions);
        }
        let mut actions = sink.actions;
        actions.extend(self.schedule(set, &fit, std));
        actions
    }

    /// The state after an accepted set: counts, θ and its covariance, the drift filters and
    /// the baseline (once the commissioning sets are in). Returns the set's time in days
    /// from the tracker's origin.
    fn record(&mut self, set: &ModalSet, fit: &SetFit, std: &[f64]) -> f64 {
        let res = &fit.result;
        let st = &mut self.state;
        st.scales = fit.scales.clone();
        st.accepted += 1;
        st.last_time = Some(set.time);
        let origin = *st.origin.get_or_insert(set.time);
        let days = (set.time - origin).num_milliseconds() as f64 / 86_400_000.0;
        if !fit.warm {
            st.cold_starts += 1;
        }
        if !res.converged() {
            st.unconverged += 1;
            return days;
        }
        st.theta = Some(res.theta.clone());
        st.linearized_at = Some(res.last.theta.clone());
        st.std = Some(std.to_vec());
        st.covariance = res.covariance.as_ref().map(|c| {
            (0..c.nrows())
                .map(|i| (0..c.ncols()).map(|j| c[(i, j)]).collect())
                .collect()
        });
        st.epsilon = Some(fit.epsilon);
        for (l, f) in st.filters.iter_mut().enumerate() {
            f.observe(days, res.theta[l], std[l] * std[l]);
        }
        if st.baseline.is_none() {
            // Σσ over the commissioning sets (restarted from this set when a checkpoint of
            // an older version left it empty).
            if st.commissioning_std_sum.len() != std.len() {
                st.commissioning_std_sum = vec![0.0; std.len()];
                st.commissioning_sets = 0;
            }
            for (sum, s) in st.commissioning_std_sum.iter_mut().zip(std) {
                *sum += s;
            }
            st.commissioning_sets += 1;
            st.commissioning_modes = st.commissioning_modes.max(set.modes.len());
            for c in &set.channels {
                if !st.commissioning_channels.contains(c) {
                    st.commissioning_channels.push(c.clone());
                }
            }
            if st.accepted - st.unconverged >= u64::from(self.cfg.baseline_sets) {
                st.baseline = Some(st.filters.iter().map(|f| f.estimate().level).collect());
                let n = st.commissioning_sets as f64;
                st.baseline_std = Some(st.commissioning_std_sum.iter().map(|s| s / n).collect());
            }
        }
        days
    }

    /// The set judged against the expectation under its conditions ([`super::normalise`]).
    fn normalise(
        &mut self,
        set: &ModalSet,
        fit: &SetFit,
        std: &[f64],
        days: f64,
        conditions: &Conditions,
    ) -> Normalisation {
        if self.cfg.normalisation.mode == Mode::Off || !fit.result.converged() {
            return None;
        }
        let covariance = self.state.covariance.clone();
        let estimate = SetEstimate {
            time: set.time,
            days,
            theta: &fit.result.theta,
            std,
            covariance: covariance.as_deref(),
        };
        Some(
            self.state
                .normalisation
                .judge(&self.cfg.normalisation, &estimate, conditions.clone()),
        )
    }

    /// The estimate published for the set.
    fn estimate(
        &self,
        set: &ModalSet,
        fit: &SetFit,
        std: &[f64],
        n_data: usize,
        conditions: &Conditions,
        judgement: &Normalisation,
    ) -> Estimate {
        let res = &fit.result;
        let parameters = self.parameter_estimates(fit, std, judgement);
        Estimate {
            schema: Schema::new(),
            id: output_id(&self.model.name, set.time, "stiffness", 0),
            structure: self.model.name.clone(),
            time: set.time,
            method: Method::ModeMatching,
            converged: res.converged(),
            termination: (&res.termination).into(),
            iterations: res.iterations,
            warm_start: fit.warm,
            cold_start_reason: fit.fallback.clone(),
            epsilon: fit.epsilon,
            epsilon_bound: chi2_bound(n_data, self.model.n_params()),
            temperature_c: conditions.temperature_c,
            covariates: conditions.covariates.clone(),
            normalisation: judgement.as_ref().map(normalisation_doc),
            parameters,
            modes: set
                .modes
                .iter()
                .enumerate()
                .map(|(m, mode)| ModeComparison::of(&res.last, m, mode.frequency_hz))
                .collect(),
            weights: fit.weights.clone(),
        }
    }

    /// Each parameter's entry in the estimate: the set's θ with its σ and 95 % band, the
    /// change from the baseline, the stiffness, the drift filter's level, why its alerts are
    /// off (if they are) and the level normalised for the set's conditions.
    fn parameter_estimates(
        &self,
        fit: &SetFit,
        std: &[f64],
        judgement: &Normalisation,
    ) -> Vec<ParameterEstimate> {
        let res = &fit.result;
        let st = &self.state;
        let alerts_off = alerts_off(&self.cfg.alerts, &self.is_connection, st);
        self.model
            .parameters()
            .iter()
            .enumerate()
            .map(|(l, p)| {
                let f = st.filters[l].estimate();
                let b = st.baseline.as_ref().map(|b| b[l]);
                ParameterEstimate {
                    name: p.name.clone(),
                    theta: res.theta[l],
                    std: finite(std[l]),
                    lower95: finite(res.theta[l] - Z95 * std[l]),
                    upper95: finite(res.theta[l] + Z95 * std[l]),
                    baseline: b,
                    change: b.map(|b| (res.theta[l] - b) / b),
                    stiffness: self.k_nominal[l].map(|k| k * res.theta[l]),
                    filtered: FilteredLevel {
                        level: f.level,
                        trend_per_day: f.trend,
                        std: f.std,
                        lower95: f.lower95,
                        upper95: f.upper95,
                        change: b.map(|b| (f.level - b) / b),
                    },
                    alerts_off: alerts_off[l].clone(),
                    normalised: normalised_level(judgement, l),
                }
            })
            .collect()
    }

    /// The model-inadequacy alert on ε (and the diagnosis of a warning).
    fn inadequacy_alert(
        &mut self,
        sink: &mut AlertSink,
        set: &ModalSet,
        epsilon: f64,
        n_data: usize,
    ) {
        let p = self.model.n_params();
        let bound = chi2_bound(n_data, p);
        let Some(level) = self.state.inadequacy.step(
            epsilon,
            chi2_dof(n_data, p),
            self.cfg.alerts.inadequacy_window,
            self.cfg.alerts.persistence,
        ) else {
            return;
        };
        sink.push(
            None,
            AlertKind::ModelInadequate,
            level,
            None,
            inadequacy_message(level, epsilon, bound, &self.cfg.alerts),
            AlertDetail::Inadequacy {
                epsilon,
                epsilon_bound: bound,
                diagnosis: None,
            },
        );
        if level == AlertLevel::Warning {
            sink.actions
                .push(Action::Diagnose(Box::new(DiagnoseRequest {
                    set: set.clone(),
                    epsilon,
                    epsilon_bound: bound,
                })));
        }
    }

    /// The loosening alerts of every connection with alerts on: with normalisation against
    /// the expectation under the set's conditions, else (off, or no expectation yet)
    /// against the baseline.
    fn loosening_alerts(
        &mut self,
        sink: &mut AlertSink,
        judgement: &Normalisation,
        conditions: &Conditions,
    ) {
        let t = self.cfg.alerts;
        let alerts_off = alerts_off(&t, &self.is_connection, &self.state);
        let Some(baseline) = self.state.baseline.clone() else {
            return;
        };
        // Without an expectation (normalisation off, or not yet learned enough), against
        // the baseline.
        let normalised = match judgement {
            Some(Ok(j)) => Some(j),
            _ => None,
        };
        for (l, &b_l) in baseline.iter().enumerate() {
            if !self.is_connection[l] || alerts_off[l].is_some() {
                continue;
            }
            let f = self.state.filters[l].estimate();
            let judged = match normalised {
                Some(j) => {
                    let n = j.parameters[l];
                    Judged::from_confidence(&t, n.loss(), |drop| n.confidence(drop))
                }
                None => Judged::against_baseline(&t, b_l, f.level, f.std),
            };
            let Some(tr) = self.state.loosening[l].step(&t, judged) else {
                continue;
            };
            let inadequate = self.state.inadequacy.raised;
            let label = self.connection_label(l);
            let against = normalised.map(|j| {
                let n = j.parameters[l];
                let at = if conditions.is_empty() {
                    "from the other connections".to_string()
                } else {
                    format!("at {}", conditions.describe())
                };
                (n.expected, at)
            });
            let message = loosening_message(
                &label,
                tr.level,
                judged.drop,
                tr.confidence,
                inadequate,
                against.as_ref(),
            );
            sink.push(
                Some(self.model.parameters()[l].name.clone()),
                AlertKind::Loosening,
                tr.level,
                Some(tr.confidence),
                message,
                AlertDetail::Loosening {
                    theta: f.level,
                    lower95: f.lower95,
                    upper95: f.upper95,
                    baseline: b_l,
                    drop: judged.drop,
                    model_inadequate: inadequate,
                    expected: against.as_ref().map(|a| a.0),
                    conditions: normalised
                        .map(|j| j.conditions.describe())
                        .filter(|c| !c.is_empty()),
                },
            );
        }
    }

    /// The name of parameter `l` with the connections it scales, when they are not just
    /// its name (a space frame's `<member>@<node>.<axis>`).
    fn connection_label(&self, l: usize) -> String {
        let name = &self.model.parameters()[l].name;
        let scaled: Vec<String> = self
            .model
            .parameter_elements(l)
            .into_iter()
            .map(|(_, n)| n)
            .collect();
        if scaled.len() == 1 && scaled[0] == *name {
            name.clone()
        } else {
            format!("{name} ({})", scaled.join(", "))
        }
    }

    /// The cross-check when due (recording time, so replays are deterministic) and the
    /// checkpoint when due.
    fn schedule(&mut self, set: ModalSet, fit: &SetFit, std: Vec<f64>) -> Vec<Action> {
        let mut actions = Vec::new();
        let st = &mut self.state;
        if fit.result.converged() {
            let due_sets = self.cfg.crosscheck_every_sets > 0
                && st
                    .last_crosscheck
                    .is_none_or(|(n, _)| st.accepted - n >= self.cfg.crosscheck_every_sets);
            let due_time = self.cfg.crosscheck_every_s > 0.0
                && st.last_crosscheck.is_some_and(|(_, t)| {
                    (set.time - t).num_milliseconds() as f64 / 1000.0 >= self.cfg.crosscheck_every_s
                });
            if due_sets || due_time {
                st.last_crosscheck = Some((st.accepted, set.time));
                actions.push(Action::Crosscheck(Box::new(CrosscheckRequest {
                    set,
                    theta: fit.result.theta.clone(),
                    std,
                    iterations: fit.result.iterations,
                })));
            }
        }
        if st.accepted.is_multiple_of(self.cfg.checkpoint_every_sets) {
            actions.push(Action::Checkpoint);
        }
        actions
    }
}

fn rejection(reason: String) -> Rejection {
    Rejection {
        field: "modes".into(),
        reason,
    }
}

/// The first non-finite value of θ, σ or ε, named.
fn not_finite(theta: &[f64], std: &[f64], epsilon: f64) -> Option<String> {
    let bad = |what: &str, v: &[f64]| {
        v.iter()
            .position(|x| !x.is_finite())
            .map(|l| format!("{what}[{l}] = {}", v[l]))
    };
    bad("θ", theta)
        .or_else(|| bad("σ", std))
        .or_else(|| bad("ε", &[epsilon]))
}

/// Parameter `l` judged against its expectation under the set's conditions: `None` when
/// the normalisation is off, the fit did not converge or no expectation was available.
fn normalised_level(judgement: &Normalisation, l: usize) -> Option<NormalisedLevel> {
    let j = judgement.as_ref()?.as_ref().ok()?;
    let n = j.parameters[l];
    let [lo, hi] = n.loss_band();
    Some(NormalisedLevel {
        expected: n.expected,
        expected_lower95: n.lower95,
        expected_upper95: n.upper95,
        z: n.z,
        loss: n.loss(),
        loss_lower95: lo,
        loss_upper95: hi,
    })
}

fn normalisation_doc(j: &Result<Judgement, String>) -> NormalisationDoc {
    match j {
        Ok(j) => NormalisationDoc {
            source: Some(j.source),
            learning: j.learning,
            extrapolated: j.extrapolated.clone(),
            note: j.note.clone(),
            unavailable: None,
        },
        Err(why) => NormalisationDoc {
            source: None,
            learning: true,
            extrapolated: None,
            note: None,
            unavailable: Some(why.clone()),
        },
    }
}
