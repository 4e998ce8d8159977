//! Normalisation of the tracked parameters for the environment (Sohn, "Effects of
//! environmental and operational variability on structural health monitoring", Phil.
//! Trans. R. Soc. A 365, 2007): what a healthy structure's ln θ is expected to be under the
//! conditions of a set, so that a loss is judged against that and not against a fixed
//! baseline.
//!
//! Two models, both learned online from the sets while the structure is assumed healthy:
//! * [`covariates`]: a regression of ln θ on measured covariates (temperature, …) with a
//!   basis that bends at a knee;
//! * [`factors`]: without covariates, the variation all parameters share, as a factor model
//!   of the ln θ vectors, each parameter predicted from the others.
//!
//! Both give, per parameter, a [`Prediction`]: the expected ln θ, the variance of that
//! expectation (the model's own uncertainty, shared by every set under similar conditions)
//! and the variance of a single set about it (its measurement and the scatter the model
//! does not explain).

pub mod covariates;
pub mod factors;

/// The expected ln θ of one parameter under a set's conditions (module docs).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Prediction {
    /// Expected ln θ.
    pub mean: f64,
    /// Variance of `mean` (the model's uncertainty).
    pub model_var: f64,
    /// Variance of one set's ln θ about the true expectation (its own measurement
    /// variance included).
    pub noise_var: f64,
}

impl Prediction {
    /// The predictive variance of one set's ln θ.
    pub fn total_var(&self) -> f64 {
        self.model_var + self.noise_var
    }
}
