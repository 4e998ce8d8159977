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
use serde_json::{Value, json};

use super::{CROSSCHECK_SCHEMA, CrosscheckRequest, measured_data, rfc3339};
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

/// Runs the cross-check and returns the `boltwatch.crosscheck.v1` payload. A failed MAP
/// solve is reported in the payload (`ok: false`, `error`), never dropped.
pub fn crosscheck(
    model: &Model,
    cfg: &CrosscheckConfig,
    shape_weight: f64,
    req: &CrosscheckRequest,
) -> Value {
    let sigma_c = cfg
        .sigma_c
        .or(model.bayesian.sigma_c)
        .unwrap_or(DEFAULT_SIGMA_C);
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
    let mut body = json!({
        "schema": CROSSCHECK_SCHEMA,
        "structure": model.name,
        "time": rfc3339(req.set.time),
        "sigma_c": sigma_c,
        "mode_matching": {"iterations": req.iterations},
    });
    let finite = |v: f64| v.is_finite().then_some(v);
    match outcome {
        Ok((res, std_b, post_b)) => {
            let mut max_z: Option<f64> = None;
            let mut disagree = Vec::new();
            let params: Vec<Value> = model
                .parameters()
                .iter()
                .enumerate()
                .map(|(l, par)| {
                    let (a, b) = (req.theta[l], res.state.theta[l]);
                    let s = (req.std[l].powi(2) + std_b[l].powi(2)).sqrt();
                    let z = finite((a - b).abs() / s);
                    if let Some(z) = z {
                        max_z = Some(max_z.map_or(z, |m| m.max(z)));
                        if z > cfg.disagree_z {
                            disagree.push(par.name.clone());
                        }
                    }
                    json!({
                        "name": par.name,
                        "mode_matching": {"theta": a, "std": finite(req.std[l])},
                        "bayesian": {"theta": b, "std": finite(std_b[l]), "posterior_std": finite(post_b[l])},
                        "z": z,
                    })
                })
                .collect();
            let b = body.as_object_mut().expect("object");
            b.insert("ok".into(), res.converged.into());
            b.insert(
                "error".into(),
                (!res.converged)
                    .then(|| "the MAP solve did not converge".to_string())
                    .into(),
            );
            b.insert(
                "bayesian".into(),
                json!({"iterations": res.iterations, "converged": res.converged, "j_p": res.terms.total}),
            );
            b.insert("parameters".into(), params.into());
            b.insert("max_z".into(), max_z.into());
            b.insert("disagree".into(), disagree.into());
        }
        Err(e) => {
            let b = body.as_object_mut().expect("object");
            b.insert("ok".into(), false.into());
            b.insert("error".into(), e.to_string().into());
            b.insert("parameters".into(), Value::Array(vec![]));
            b.insert("max_z".into(), Value::Null);
            b.insert("disagree".into(), Value::Array(vec![]));
        }
    }
    body
}
