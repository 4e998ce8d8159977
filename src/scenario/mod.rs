//! Synthetic monitoring histories (`boltwatch scenario`): a sequence of modal sets simulated
//! from a model whose parameters change in time as a named scenario prescribes, with the
//! noise model of [`crate::core::simulate`] and the truth of every set beside it.
//!
//! Every scenario shares the healthy background: the structure at `theta` (by default the
//! model's nominal θ), one set every `days / sets` days, temperature
//! `T(t) = mean + daily_amp · sin(2π t) + seasonal_amp · sin(2π t / 365.25)` (t in days),
//! acting on the modulus parameters as steel does, `E(T) = E(20 °C) (1 + α (T − 20))` with
//! `α = −2.6e-4 /°C` (a ±30 °C swing moves the frequencies by about ±0.4 %). Events:
//! * `healthy`: nothing else.
//! * `loosening`: a connection parameter loses `loss` (default 50 %) linearly over
//!   `duration_days` (10) from `start_day` (40).
//! * `sudden`: a connection parameter drops by `loss` (60 %) at `day` (30).
//! * `mass`: a point mass (0.8 kg) fixed to a node at `day` (30), absent from the model
//!   the tracker uses.
//! * `seasonal`: two years of four sets a day under the climate and thermal law of
//!   [`seasons`] instead of the background's temperature; with `--loosen`, a sudden loss.

pub mod seasons;

use chrono::{DateTime, Duration, Utc};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use crate::contract::modal_set::{MeasuredMode, ModalSet};
use crate::core::modal::{ModalError, solver_for};
use crate::core::model::spec::{MassSpec, ModelSpec};
use crate::core::model::{Model, ModelError, ParameterKind};
use crate::core::simulate::{Noise, simulate_modes};

/// Temperature coefficient of Young's modulus of structural steel, 1/°C.
pub const STEEL_ALPHA_E: f64 = -2.6e-4;
/// Temperature at which the model's moduli hold, °C.
pub const REFERENCE_TEMPERATURE_C: f64 = 20.0;

/// What happens to the structure.
#[derive(Debug, Clone, PartialEq)]
pub enum Event {
    None,
    Loosening {
        parameter: usize,
        start_day: f64,
        duration_days: f64,
        loss: f64,
    },
    Sudden {
        parameter: usize,
        day: f64,
        loss: f64,
    },
    Mass {
        at: String,
        mass: f64,
        day: f64,
    },
}

/// A whole scenario.
#[derive(Debug, Clone, PartialEq)]
pub struct Scenario {
    pub name: String,
    pub sets: usize,
    pub days: f64,
    pub start: DateTime<Utc>,
    pub seed: u64,
    pub modes: usize,
    pub noise: Noise,
    /// Healthy θ of the structure.
    pub theta: Vec<f64>,
    pub temperature_mean: f64,
    pub daily_amp: f64,
    pub seasonal_amp: f64,
    pub alpha_e: f64,
    pub event: Event,
    /// The seasonal climate and thermal law, instead of the background's temperature.
    pub seasons: Option<seasons::Seasons>,
}

/// Failures of scenario set-up or generation.
#[derive(Debug, thiserror::Error)]
pub enum ScenarioError {
    #[error("unknown scenario `{0}` (known: healthy, loosening, sudden, mass, seasonal)")]
    Unknown(String),
    #[error("{0}")]
    Invalid(String),
    #[error(transparent)]
    Model(#[from] ModelError),
    #[error(transparent)]
    Modal(#[from] ModalError),
}

/// The names [`Scenario::named`] knows.
pub const NAMES: [&str; 5] = ["healthy", "loosening", "sudden", "mass", "seasonal"];

impl Scenario {
    /// The named scenario (module docs) for `model`: 10,000 sets over 60 days, 9 modes, 1 %
    /// frequency CoV, 5 % NSD, at the model's nominal θ. Loosening and sudden act on
    /// `connection` (a connection parameter's name; default: the first connection
    /// parameter); mass is fixed to `at` (default: the second joint-like node named in the
    /// model's connections).
    pub fn named(
        name: &str,
        model: &Model,
        connection: Option<&str>,
        at: Option<&str>,
    ) -> Result<Self, ScenarioError> {
        let event = named_event(name, model, connection, at)?;
        Ok(Self {
            name: name.to_string(),
            sets: 10_000,
            days: 60.0,
            start: DateTime::parse_from_rfc3339("2026-03-01T00:00:00Z")
                .expect("constant time parses")
                .with_timezone(&Utc),
            seed: 1,
            modes: 9,
            noise: Noise {
                frequency_cov: 0.01,
                shape_nsd: 0.05,
            },
            theta: model.nominal_theta(),
            temperature_mean: 10.0,
            daily_amp: 15.0,
            seasonal_amp: 15.0,
            alpha_e: STEEL_ALPHA_E,
            event,
            seasons: None,
        }
        .with_seasons(name == "seasonal", model))
    }

    /// The seasonal scenario's defaults when `seasonal`: 2,920 sets over 730 days (four a
    /// day) under [`seasons::Seasons`].
    fn with_seasons(mut self, seasonal: bool, model: &Model) -> Self {
        if seasonal {
            self.sets = 2920;
            self.days = 730.0;
            self.reseason(model);
        }
        self
    }

    /// Draws the seasonal law again for the current `days`, `start` and `seed` (after
    /// changing them).
    pub fn reseason(&mut self, model: &Model) {
        let is_connection: Vec<bool> = model
            .parameters()
            .iter()
            .map(|p| matches!(p.kind, ParameterKind::Connections(_)))
            .collect();
        self.seasons = Some(seasons::Seasons::new(
            &is_connection,
            self.days,
            self.start,
            self.seed,
        ));
    }

    /// Time of set `k`, days from the start.
    pub fn day(&self, k: usize) -> f64 {
        k as f64 * self.days / self.sets as f64
    }

    /// Air temperature at day `t`, °C.
    pub fn temperature(&self, t: f64) -> f64 {
        use std::f64::consts::TAU;
        if let Some(s) = &self.seasons {
            return s.temperature(t);
        }
        self.temperature_mean
            + self.daily_amp * (TAU * t).sin()
            + self.seasonal_amp * (TAU * t / 365.25).sin()
    }

    /// The true θ at day `t` (the model's parameterization).
    pub fn theta_at(&self, model: &Model, t: f64) -> Vec<f64> {
        let mut theta = self.theta.clone();
        let temperature = self.temperature(t);
        let e_scale = 1.0 + self.alpha_e * (temperature - REFERENCE_TEMPERATURE_C);
        for (l, p) in model.parameters().iter().enumerate() {
            if matches!(p.kind, ParameterKind::Modulus(_)) {
                theta[l] *= e_scale;
            }
            if let Some(s) = &self.seasons {
                theta[l] *= s.log_factor(l, temperature).exp();
            }
        }
        match self.event {
            Event::Loosening {
                parameter,
                start_day,
                duration_days,
                loss,
            } => {
                let s = ((t - start_day) / duration_days).clamp(0.0, 1.0);
                theta[parameter] *= 1.0 - loss * s;
            }
            Event::Sudden {
                parameter,
                day,
                loss,
            } if t >= day => theta[parameter] *= 1.0 - loss,
            _ => {}
        }
        theta
    }

    /// Generates every set in time order, calling `sink(set, truth θ, temperature)`.
    pub fn generate(
        &self,
        spec: &ModelSpec,
        mut sink: impl FnMut(usize, ModalSet, &[f64]) -> Result<(), ScenarioError>,
    ) -> Result<(), ScenarioError> {
        if self.sets == 0 || self.days.is_nan() || self.days <= 0.0 {
            return Err(ScenarioError::Invalid(
                "a scenario needs at least one set over a positive duration".into(),
            ));
        }
        let model = Model::from_spec(spec)?;
        // The solver for the model's size: a large model's dense eigenproblem would not fit
        // in memory (the four-bay solid frame's K and M alone are 16 GB dense).
        let mut solver = solver_for(&model)?;
        let (mut mass_model, mass_day) = match &self.event {
            Event::Mass { at, mass, day } => {
                let mut with = spec.clone();
                with.masses.push(MassSpec {
                    at: at.clone(),
                    mass: *mass,
                    inertia: 0.0,
                });
                let m = Model::from_spec(&with)?;
                let s = solver_for(&m)?;
                (Some((m, s)), *day)
            }
            _ => (None, f64::INFINITY),
        };
        let mut rng = ChaCha8Rng::seed_from_u64(self.seed);
        let channels: Vec<String> = model.channels().iter().map(|c| c.name.clone()).collect();
        let positive = |v: f64| (v > 0.0).then_some(v);
        for k in 0..self.sets {
            let t = self.day(k);
            let theta = self.theta_at(&model, t);
            let modes = match (&mut mass_model, t >= mass_day) {
                (Some((m, s)), true) => {
                    simulate_modes(m, s.as_mut(), &theta, self.modes, self.noise, &mut rng)?
                }
                _ => simulate_modes(
                    &model,
                    solver.as_mut(),
                    &theta,
                    self.modes,
                    self.noise,
                    &mut rng,
                )?,
            };
            let temperature = self.temperature(t);
            let set = ModalSet {
                structure: model.name.clone(),
                time: self.start + Duration::milliseconds((t * 86_400_000.0).round() as i64),
                channels: channels.clone(),
                modes: modes
                    .iter()
                    .map(|m| MeasuredMode {
                        frequency_hz: m.frequency_hz,
                        frequency_cov: positive(self.noise.frequency_cov),
                        shape: Some(m.shape.iter().map(|&v| Some(v)).collect()),
                        shape_nsd: positive(self.noise.shape_nsd),
                        shape_std: None,
                        damping_ratio: None,
                        damping_std: None,
                        label: None,
                    })
                    .collect(),
                temperature_c: Some((temperature * 100.0).round() / 100.0),
                source: Some(format!(
                    "boltwatch scenario {} (seed {}), set {k}",
                    self.name, self.seed
                )),
                missing: Vec::new(),
                unexplained_peaks: Vec::new(),
                covariates: Default::default(),
            };
            sink(k, set, &theta)?;
        }
        Ok(())
    }
}

/// The event of scenario `name` with its defaults (module docs), on `connection` or at
/// `at` where it needs one; an unknown name is an error.
fn named_event(
    name: &str,
    model: &Model,
    connection: Option<&str>,
    at: Option<&str>,
) -> Result<Event, ScenarioError> {
    Ok(match name {
        "healthy" | "seasonal" => Event::None,
        "loosening" => Event::Loosening {
            parameter: connection_parameter(model, connection)?,
            start_day: 40.0,
            duration_days: 10.0,
            loss: 0.5,
        },
        "sudden" => Event::Sudden {
            parameter: connection_parameter(model, connection)?,
            day: 30.0,
            loss: 0.6,
        },
        "mass" => Event::Mass {
            at: mass_node(model, at)?,
            mass: 0.8,
            day: 30.0,
        },
        other => return Err(ScenarioError::Unknown(other.to_string())),
    })
}

/// The index of connection parameter `connection` of `model`, else of its first connection
/// parameter.
fn connection_parameter(model: &Model, connection: Option<&str>) -> Result<usize, ScenarioError> {
    let params = model.parameters();
    match connection {
        Some(c) => params
            .iter()
            .position(|p| p.name == c && matches!(p.kind, ParameterKind::Connections(_)))
            .ok_or_else(|| {
                ScenarioError::Invalid(format!(
                    "--connection {c}: not a connection parameter of {}",
                    model.name
                ))
            }),
        None => params
            .iter()
            .position(|p| matches!(p.kind, ParameterKind::Connections(_)))
            .ok_or_else(|| {
                ScenarioError::Invalid(format!("{} has no connection parameter", model.name))
            }),
    }
}

/// The node the mass is fixed to: `at`, else the second node named in the model's
/// connections (the first when there is one only).
fn mass_node(model: &Model, at: Option<&str>) -> Result<String, ScenarioError> {
    if let Some(a) = at {
        return Ok(a.to_string());
    }
    let mut nodes: Vec<&str> = model
        .connections()
        .iter()
        .map(|c| c.node.as_str())
        .collect();
    nodes.dedup();
    Ok(nodes
        .get(1)
        .or(nodes.first())
        .ok_or_else(|| ScenarioError::Invalid(format!("{} has no connections", model.name)))?
        .to_string())
}
