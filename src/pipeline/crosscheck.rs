//! The Bayesian cross-check (DESIGN §7, issue 4 item 5): the MAP of paper (14) on one
//! modal set, by the damped Newton solver with σ_c continuation, started from the tracked
//! mode-matching θ, compared parameter by parameter with that estimate.
//!
//! Both estimates answer "what θ explains this set"; under measurement noise alone they
//! differ by their sampling spreads, so a parameter disagrees when
//! `z = |θ_mm − θ_b| / √(σ_mm² + σ_b²)` exceeds `disagree_z`, with σ_b the MAP's sampling
//! standard deviation (threshold-free, [`crate::core::updating::bayesian`]). Disagreement
//! flags parameters the data hardly identify (the paper's stiff connections θ2, θ11),
//! where the two methods' different regularizations pull apart.
//!
//! Pure: runs on the caller's thread; the drivers run it off the tracking path.

use serde::{Deserialize, Serialize};

use super::{CrosscheckRequest, measured_data};
use crate::contract::crosscheck::{
    BayesTheta, FitIterations, MapSolve, ParameterComparison, ThetaStd,
};
use crate::contract::{Crosscheck, Schema, finite};
use crate::core::model::Model;
use crate::core::updating::bayesian::{BayesProblem, BayesSettings};

/// σ_c when neither the configuration nor the model file names one.
pub const DEFAULT_SIGMA_C: f64 = 1e4;
/// Prior standard deviation of θ (a vague prior) when the model file names none.
pub const DEFAULT_PRIOR_STD: f64 = 1000.0;

/// `[crosscheck]` of the configuration.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CrosscheckConfig {
    /// σ_c of (14); `None`: the model file's, else [`DEFAULT_SIGMA_C`].
    pub sigma_c: Option<f64>,
    /// A parameter disagrees above this many combined standard deviations.
    pub disagree_z: f64,
    /// Newton iterations allowed.
    pub max_iterations: usize,
}

impl Default for CrosscheckConfig {
    fn default() -> Self {
        Self {
            sigma_c: None,
            disagree_z: 3.0,
            max_iterations: 200,
        }
    }
}

impl CrosscheckConfig {
    /// Checks the values; the error names the key.
    pub fn validate(&self) -> Result<(), super::TrackerError> {
        let bad = |key: &str, reason: &str| super::TrackerError::Config {
            key: format!("crosscheck.{key}"),
            reason: reason.into(),
        };
        if let Some(s) = self.sigma_c
            && !(s.is_finite() && s > 0.0)
        {
            return Err(bad("sigma_c", "must be a finite number > 0"));
        }
        if !(self.disagree_z.is_finite() && self.disagree_z > 0.0) {
            return Err(bad("disagree_z", "must be a finite number > 0"));
        }
        if self.max_iterations == 0 {
            return Err(bad("max_iterations", "must be at least 1"));
        }
        Ok(())
    }
}

/// σ_c of the cross-check on `model`: the configuration's, else the model file's, else
/// [`DEFAULT_SIGMA_C`].
fn sigma_c_of(model: &Model, cfg: &CrosscheckConfig) -> f64 {
    cfg.sigma_c
        .or(model.bayesian.sigma_c)
        .unwrap_or(DEFAULT_SIGMA_C)
}

/// A cross-check message for `req` with no MAP in it yet (`ok: false`).
fn unanswered(model: &Model, sigma_c: f64, req: &CrosscheckRequest) -> Crosscheck {
    Crosscheck {
        schema: Schema::new(),
        id: crate::contract::output_id(&model.name, req.set.time, "crosscheck", 0),
        structure: model.name.clone(),
        time: req.set.time,
        sigma_c,
        mode_matching: FitIterations {
            iterations: req.iterations,
        },
        ok: false,
        error: None,
        bayesian: None,
        parameters: Vec::new(),
        max_z: None,
        disagree: Vec::new(),
    }
}

/// The cross-check of `req` not run, with the reason (e.g. the memory budget), published
/// so that a subscriber sees why none came.
pub fn skipped(
    model: &Model,
    cfg: &CrosscheckConfig,
    req: &CrosscheckRequest,
    reason: String,
) -> Crosscheck {
    let mut c = unanswered(model, sigma_c_of(model, cfg), req);
    c.error = Some(reason);
    c
}

/// Runs the cross-check. A failed MAP solve is reported in the message (`ok: false`,
/// `error`), never dropped.
pub fn crosscheck(
    model: &Model,
    cfg: &CrosscheckConfig,
    shape_weight: f64,
    req: &CrosscheckRequest,
) -> Crosscheck {
    let sigma_c = sigma_c_of(model, cfg);
    let p = model.n_params();
    let prior_std = model.bayesian.prior_std.unwrap_or(DEFAULT_PRIOR_STD);
    let data = measured_data(&req.set, model, shape_weight);
    let outcome = BayesProblem::new(
        model,
        &data,
        &BayesSettings {
            sigma_c,
            prior_mean: model.nominal_theta(),
            prior_std: vec![prior_std; p],
        },
    )
    .and_then(|mut prob| {
        let res = prob.solve_newton_continued(&req.theta, cfg.max_iterations)?;
        let free = prob.threshold_free_covariance(&res.state)?;
        Ok((res, free.sampling_theta_std(), free.posterior_theta_std()))
    });
    let mut c = unanswered(model, sigma_c, req);
    match outcome {
        Ok((res, std_b, post_b)) => {
            for (l, par) in model.parameters().iter().enumerate() {
                let (a, b) = (req.theta[l], res.state.theta[l]);
                let s = (req.std[l].powi(2) + std_b[l].powi(2)).sqrt();
                let z = finite((a - b).abs() / s);
                if let Some(z) = z {
                    c.max_z = Some(c.max_z.map_or(z, |m| m.max(z)));
                    if z > cfg.disagree_z {
                        c.disagree.push(par.name.clone());
                    }
                }
                c.parameters.push(ParameterComparison {
                    name: par.name.clone(),
                    mode_matching: ThetaStd {
                        theta: a,
                        std: finite(req.std[l]),
                    },
                    bayesian: BayesTheta {
                        theta: b,
                        std: finite(std_b[l]),
                        posterior_std: finite(post_b[l]),
                    },
                    z,
                });
            }
            c.ok = res.converged;
            c.error = (!res.converged).then(|| "the MAP solve did not converge".to_string());
            c.bayesian = Some(MapSolve {
                iterations: res.iterations,
                converged: res.converged,
                j_p: res.terms.total,
            });
        }
        Err(e) => c.error = Some(e.to_string()),
    }
    c
}
