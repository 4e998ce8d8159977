//! Seasons without false alarms: each parameter judged against the θ a healthy structure
//! is expected to have under the set's conditions ([`crate::core::normalisation`]), not
//! against a fixed baseline.
//!
//! Per converged set, with `y = ln θ` and its covariance `R` (15):
//! 1. **Conditions**: the set's own `temperature_c` and `covariates`, completed from the
//!    nearest environment reading at most `max_age_s` away.
//! 2. **Expectation**: by the covariate regression when the set has every configured
//!    covariate (`mode = "auto"` or `"covariates"`), else by the output-only factor model
//!    (`"auto"` or `"output-only"`). The prediction is made before the set is learned.
//! 3. **Learning**: while training (`training_days` from the first set), the set is learned
//!    by both models, each holding out what looks like a loss; then the models are frozen.
//! 4. **Normalised level**: the residual `e = y − ŷ` (a log ratio: −0.18 is a loss of 16 %)
//!    feeds a drift filter per parameter ([`super::drift`]) with the variance of one set
//!    about its expectation plus the expectation's own; the loosening alert judges the
//!    filtered level with the expectation's variance added again (it is shared by every
//!    set under similar conditions, so averaging does not reduce it):
//!    `P(loss ≥ f) = Φ((ln(1 − f) − ē) / √(P_ē + v))`.

use std::collections::VecDeque;

use chrono::{DateTime, Utc};
use nalgebra::DMatrix;
use serde::{Deserialize, Serialize};

use super::drift::{DriftFilter, DriftNoise};
use crate::contract::environment::{Conditions, TEMPERATURE};
use crate::contract::stiffness::NormalisationSource as Source;
use crate::core::normalisation::Prediction;
use crate::core::normalisation::covariates::{Basis, CovariateModel};
use crate::core::normalisation::factors::FactorModel;
use crate::core::stats::{Z95, normal_cdf};

/// Which expectation a tracker judges by (`tracker.normalisation.mode`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Mode {
    /// The covariates when a set has them all, else output-only.
    #[default]
    Auto,
    Covariates,
    OutputOnly,
    /// A fixed baseline, as without normalisation.
    Off,
}

/// `[tracker.normalisation]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct NormalisationConfig {
    pub mode: Mode,
    /// The covariates regressed on: `temperature_c` and names of a set's `covariates`.
    pub covariates: Vec<String>,
    /// Knees of the temperature law, °C: below each the law may bend (a joint stiffens
    /// faster once frozen).
    pub knees: Vec<f64>,
    /// Days from the first set during which the models learn; then they are frozen.
    pub training_days: f64,
    /// Prior standard deviation of every slope of the regression, ln θ per unit of its
    /// covariate (0.05: 5 % per °C, more than any bolted joint moves away from freezing).
    pub slope_prior: f64,
    /// A set this many standard deviations from its expectation is not learned from.
    pub gate: f64,
    /// Factors of the output-only model (0: chosen from the data).
    pub factors: usize,
    /// A set's conditions beyond the learned range by more than this fraction of it are
    /// flagged `extrapolated`.
    pub extrapolation_margin: f64,
    /// An environment reading completes a set at most this far from it in time, s.
    pub max_age_s: f64,
    /// A law file (`boltwatch normalisation learn`): when set, the tracker judges by the
    /// models in it, frozen, instead of what it learned itself ("": none).
    pub law: String,
    /// The drift filters of the normalised levels: quieter than `[tracker.drift]`, whose
    /// filters follow θ itself through the seasons (module docs, step 4).
    pub drift: DriftNoise,
}

/// `[tracker.normalisation.drift]` by default: a level wandering 0.2 %/√day and a trend
/// 0.5 %/day per √day. A healthy connection's normalised level is stationary (the season
/// is in the expectation), so the filter may average over days: on the lab frame (a set's
/// σ of ln θ about 4.5 %, four sets a day) its level settles to σ ≈ 1.8 % instead of 2.9 %
/// under the tracker's drift intensities, and a 15 % loss stands clear of a 10 % warning
/// threshold. A sudden loss restarts the filter (the step tests of [`super::drift`]); a
/// slow one is followed through the trend and the same window test.
pub fn normalised_drift() -> DriftNoise {
    DriftNoise {
        level_per_day: 0.002,
        trend_per_day: 0.005,
        ..DriftNoise::default()
    }
}

impl Default for NormalisationConfig {
    fn default() -> Self {
        Self {
            mode: Mode::Auto,
            covariates: vec![TEMPERATURE.to_string()],
            knees: vec![0.0],
            training_days: 365.0,
            slope_prior: 0.05,
            gate: 5.0,
            factors: 0,
            extrapolation_margin: 0.1,
            max_age_s: 3600.0,
            law: String::new(),
            drift: normalised_drift(),
        }
    }
}

impl NormalisationConfig {
    /// Checks every value; the error names the key (under `normalisation.`).
    pub fn validate(&self) -> Result<(), (&'static str, String)> {
        let positive = |v: f64| v.is_finite() && v > 0.0;
        if self.covariates.is_empty() && self.mode == Mode::Covariates {
            return Err((
                "covariates",
                "mode = \"covariates\" needs at least one".into(),
            ));
        }
        if let Some(c) = self
            .covariates
            .iter()
            .find(|c| c.is_empty() || c.len() > 64)
        {
            return Err(("covariates", format!("`{c}` is not a covariate name")));
        }
        if self.knees.iter().any(|k| !k.is_finite()) {
            return Err(("knees", "must be finite temperatures, °C".into()));
        }
        if !positive(self.training_days) {
            return Err(("training_days", "must be a number of days > 0".into()));
        }
        if !positive(self.slope_prior) {
            return Err(("slope_prior", "must be a number > 0".into()));
        }
        if !(self.gate.is_finite() && self.gate >= 2.0) {
            return Err(("gate", "must be a number ≥ 2 (standard deviations)".into()));
        }
        if !(self.extrapolation_margin.is_finite() && self.extrapolation_margin >= 0.0) {
            return Err(("extrapolation_margin", "must be a number ≥ 0".into()));
        }
        if !(self.max_age_s.is_finite() && self.max_age_s >= 0.0) {
            return Err(("max_age_s", "must be a number of seconds ≥ 0".into()));
        }
        self.drift.validate().map_err(|(key, why)| {
            let key = match key {
                "level_per_day" => "drift.level_per_day",
                "trend_per_day" => "drift.trend_per_day",
                _ => "drift.step_z",
            };
            (key, why)
        })
    }

    fn basis(&self) -> Basis {
        Basis {
            covariates: self.covariates.clone(),
            knees: self.knees.clone(),
        }
    }
}

/// The normalisation's view of one parameter after a set.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Normalised {
    /// θ expected under the set's conditions, and the 95 % band of a healthy θ there (the
    /// expectation's uncertainty and the scatter it does not explain; not this set's own
    /// measurement noise).
    pub expected: f64,
    pub lower95: f64,
    pub upper95: f64,
    /// This set's standardised residual `(y − ŷ)/√(predictive variance)`.
    pub z: f64,
    /// Filtered `ln(θ / expected)` and its standard deviation, the expectation's included.
    pub level: f64,
    pub std: f64,
}

impl Normalised {
    /// The normalised loss `1 − exp(level)`.
    pub fn loss(&self) -> f64 {
        1.0 - self.level.exp()
    }

    /// The loss at the upper and lower ends of the 95 % band of the level.
    pub fn loss_band(&self) -> [f64; 2] {
        [
            1.0 - (self.level + Z95 * self.std).exp(),
            1.0 - (self.level - Z95 * self.std).exp(),
        ]
    }

    /// Confidence that the loss is at least `f` (module docs).
    pub fn confidence(&self, f: f64) -> f64 {
        let limit = (1.0 - f).ln();
        if self.std > 0.0 && self.std.is_finite() {
            normal_cdf((limit - self.level) / self.std)
        } else if self.level < limit {
            1.0
        } else {
            0.0
        }
    }
}

/// A set's judgement.
#[derive(Debug, Clone, PartialEq)]
pub struct Judgement {
    pub source: Source,
    pub parameters: Vec<Normalised>,
    /// The conditions judged under (the set's, completed from an environment reading).
    pub conditions: Conditions,
    /// Why the conditions are outside what the model learned, if they are.
    pub extrapolated: Option<String>,
    /// The models were still learning at this set.
    pub learning: bool,
    /// Why the covariates could not be used, when the output-only model stood in.
    pub note: Option<String>,
}

/// The normalisation's persistent state (in the checkpoint).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct NormalisationState {
    /// Time of the first set learned (the training period starts there).
    pub start: Option<DateTime<Utc>>,
    /// When training ended; the models are frozen since.
    pub frozen_at: Option<DateTime<Utc>>,
    pub covariates: Option<CovariateModel>,
    pub factors: Option<FactorModel>,
    /// Drift filters of each parameter's `ln(θ / expected)`.
    pub filters: Vec<DriftFilter>,
    /// Environment readings kept for joining, oldest first.
    pub environment: VecDeque<(DateTime<Utc>, Conditions)>,
}

/// The most environment readings kept for joining.
pub const ENVIRONMENT_KEPT: usize = 256;

/// One set's estimate, as the normalisation takes it.
pub struct SetEstimate<'a> {
    pub time: DateTime<Utc>,
    /// Days since the tracker's time origin.
    pub days: f64,
    pub theta: &'a [f64],
    pub std: &'a [f64],
    /// Covariance (15), row by row, when the fit gave one.
    pub covariance: Option<&'a [Vec<f64>]>,
}

impl NormalisationState {
    /// Keeps an environment reading for the sets it may complete.
    /// A reading already kept (a re-delivery) is not kept twice.
    pub fn add_reading(&mut self, time: DateTime<Utc>, conditions: Conditions) {
        if self
            .environment
            .iter()
            .any(|(t, c)| *t == time && *c == conditions)
        {
            return;
        }
        let at = self.environment.partition_point(|(t, _)| *t <= time);
        self.environment.insert(at, (time, conditions));
        while self.environment.len() > ENVIRONMENT_KEPT {
            self.environment.pop_front();
        }
    }

    /// The set's conditions completed from the nearest reading within `max_age_s`.
    pub fn conditions(&self, own: &Conditions, time: DateTime<Utc>, max_age_s: f64) -> Conditions {
        let age = |t: &DateTime<Utc>| (time - *t).num_milliseconds().abs() as f64 / 1000.0;
        let nearest = self
            .environment
            .iter()
            .filter(|(t, _)| age(t) <= max_age_s)
            .min_by(|a, b| age(&a.0).total_cmp(&age(&b.0)));
        let mut out = own.clone();
        if let Some((_, c)) = nearest {
            if out.temperature_c.is_none() {
                out.temperature_c = c.temperature_c;
            }
            for (k, v) in &c.covariates {
                out.covariates.entry(k.clone()).or_insert(*v);
            }
        }
        out
    }

    /// Takes the models of a law (learned elsewhere, frozen) in place of its own; the
    /// normalised filters start again. Returns whether anything changed (a tracker restored
    /// with the law it already has keeps its filters).
    pub fn adopt(&mut self, law: &NormalisationState) -> bool {
        if self.covariates == law.covariates
            && self.factors == law.factors
            && self.frozen_at == law.frozen_at
        {
            return false;
        }
        self.start = law.start;
        self.frozen_at = law.frozen_at;
        self.covariates = law.covariates.clone();
        self.factors = law.factors.clone();
        self.filters.clear();
        true
    }

    /// Judges one converged set and learns from it while training (module docs). `Err`
    /// says why no expectation is available for it (the models have not seen enough).
    pub fn judge(
        &mut self,
        cfg: &NormalisationConfig,
        set: &SetEstimate,
        conditions: Conditions,
    ) -> Result<Judgement, String> {
        let p = set.theta.len();
        let y: Vec<f64> = set
            .theta
            .iter()
            .map(|t| t.abs().max(f64::MIN_POSITIVE).ln())
            .collect();
        let big_r = log_covariance(set);
        let r: Vec<f64> = (0..p).map(|i| big_r[(i, i)]).collect();
        let start = *self.start.get_or_insert(set.time);
        let learning = self.frozen_at.is_none();
        let x: Result<Vec<f64>, String> = cfg
            .covariates
            .iter()
            .map(|c| conditions.value(c).ok_or_else(|| format!("{c} missing")))
            .collect();
        let use_covariates = cfg.mode != Mode::OutputOnly && !cfg.covariates.is_empty();
        let use_factors = matches!(cfg.mode, Mode::Auto | Mode::OutputOnly);
        if use_covariates && self.covariates.is_none() {
            self.covariates = Some(CovariateModel::new(cfg.basis(), &y, 1.0, cfg.slope_prior));
        }
        if use_factors && self.factors.is_none() {
            self.factors = Some(FactorModel::new(p, cfg.factors));
        }
        // The expectation, before this set is learned.
        let expectation = match (&x, &self.covariates) {
            (Ok(x), Some(m)) if use_covariates => Ok((
                Source::Covariates,
                m.predict(x, &r),
                m.extrapolated(x, cfg.extrapolation_margin),
                None,
            )),
            _ => {
                let why = x.as_ref().err().cloned();
                match self.factors.as_ref().filter(|_| use_factors) {
                    Some(f) => match f.predict(&y, &big_r) {
                        Some(pred) => Ok((
                            Source::OutputOnly,
                            pred,
                            factor_extrapolation(f, &y, &big_r),
                            why.map(|w| format!("{w}: judged by the output-only model")),
                        )),
                        None => Err(format!(
                            "the output-only model has learned {} of the {} sets it needs",
                            f.sets,
                            f.min_sets()
                        )),
                    },
                    None => Err(why.unwrap_or_else(|| "no model".into())),
                }
            }
        };
        if learning {
            self.learn(cfg, &x, &y, &r, &big_r);
            let days = (set.time - start).num_milliseconds() as f64 / 86_400_000.0;
            if days >= cfg.training_days {
                self.frozen_at = Some(set.time);
            }
        }
        let (source, pred, extrapolated, note) = expectation?;
        let parameters = self.filter(cfg.drift, set.days, &y, &pred);
        Ok(Judgement {
            source,
            parameters,
            conditions,
            extrapolated,
            learning,
            note,
        })
    }

    /// Step 3 (module docs).
    fn learn(
        &mut self,
        cfg: &NormalisationConfig,
        x: &Result<Vec<f64>, String>,
        y: &[f64],
        r: &[f64],
        big_r: &DMatrix<f64>,
    ) {
        if let (Ok(x), Some(m)) = (x, self.covariates.as_mut()) {
            m.learn(x, y, r, cfg.gate);
        }
        if let Some(f) = self.factors.as_mut() {
            f.learn(y, big_r, cfg.gate);
        }
    }

    /// Step 4 (module docs).
    fn filter(
        &mut self,
        drift: DriftNoise,
        days: f64,
        y: &[f64],
        pred: &[Prediction],
    ) -> Vec<Normalised> {
        if self.filters.len() != y.len() {
            self.filters = vec![DriftFilter::new(1.0, drift); y.len()];
        }
        self.filters
            .iter_mut()
            .zip(y.iter().zip(pred))
            .map(|(f, (&y, q))| {
                let e = y - q.mean;
                let total = q.total_var();
                let est = f.observe(days, e, total);
                let band = (q.model_var + (q.noise_var).max(0.0)).sqrt();
                Normalised {
                    expected: q.mean.exp(),
                    lower95: (q.mean - Z95 * band).exp(),
                    upper95: (q.mean + Z95 * band).exp(),
                    z: e / total.sqrt(),
                    level: est.level,
                    std: (est.std.powi(2) + q.model_var).sqrt(),
                }
            })
            .collect()
    }
}

/// The covariance of ln θ: `R_ij = C_ij / (θ_i θ_j)`, from the fit's covariance (15), else
/// from σ alone.
fn log_covariance(set: &SetEstimate) -> DMatrix<f64> {
    let p = set.theta.len();
    let t = |i: usize| set.theta[i].abs().max(f64::MIN_POSITIVE);
    match set.covariance {
        Some(c) if c.len() == p => DMatrix::from_fn(p, p, |i, j| c[i][j] / (t(i) * t(j))),
        _ => DMatrix::from_fn(p, p, |i, j| {
            if i == j {
                (set.std[i] / t(i)).powi(2)
            } else {
                0.0
            }
        }),
    }
}

/// Scores this many standard deviations of the learned variation away are extrapolated.
pub const FACTOR_EXTRAPOLATION: f64 = 4.0;

fn factor_extrapolation(f: &FactorModel, y: &[f64], r: &DMatrix<f64>) -> Option<String> {
    let scores = f.scores(y, r)?;
    let (i, s) = scores
        .iter()
        .enumerate()
        .max_by(|a, b| a.1.abs().total_cmp(&b.1.abs()))?;
    (s.abs() > FACTOR_EXTRAPOLATION).then(|| {
        format!(
            "shared variation {} at {s:.1} standard deviations of the learned (> {FACTOR_EXTRAPOLATION})",
            i + 1
        )
    })
}
