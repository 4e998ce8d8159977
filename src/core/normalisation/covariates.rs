//! Normalisation on measured covariates (temperature, humidity, traffic, ...): per
//! parameter, a linear regression of ln θ on a basis of the covariates that can bend,
//! learned online by recursive weighted least squares from a Gaussian prior (Ljung &
//! Söderström, *Theory and Practice of Recursive Identification*, 1983, §2.2). This is the
//! regression-model approach of Peeters & De Roeck (2001) for the Z24 bridge, whose
//! frequencies followed temperature bilinearly, much steeper below freezing: here the bend
//! is a hinge at a knee.
//!
//! Basis φ(x): 1; every covariate x_j; for `temperature_c`, a hinge (k − T)₊ at every knee k.
//! Model: `ln θ_k = φ(x_k)ᵀβ + e_k`, `e_k ~ N(0, r_k + τ²)`, with `r_k = (σ_k/θ_k)²` the
//! set's own variance (15) and τ² the scatter the covariates do not explain, estimated from
//! the predictive residuals (each taken before its set is learned), `E[e² − r − v] = τ²`,
//! averaged with weights `ω = (r / (r + v))²` so that the first sets, predicted mostly by
//! the prior, do not swamp it: `τ² = max(0, Σ ω (e² − r − v) / Σ ω)`. Prediction at x: mean `φᵀβ`, model variance `v = φᵀPφ`
//! (large where the prior still speaks, i.e. outside the conditions seen: the band widens
//! there instead of alarming), scatter τ².

use serde::{Deserialize, Serialize};

use super::Prediction;

/// The covariate every temperature law bends on.
pub const TEMPERATURE: &str = "temperature_c";

/// The regression basis φ(x) (module docs).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Basis {
    /// Covariate names, in the order of `x`.
    pub covariates: Vec<String>,
    /// Knees of the hinges on [`TEMPERATURE`], °C.
    pub knees: Vec<f64>,
}

impl Basis {
    /// Number of terms.
    pub fn len(&self) -> usize {
        1 + self.covariates.len() + self.hinged().map_or(0, |_| self.knees.len())
    }

    /// Never empty (the intercept).
    pub fn is_empty(&self) -> bool {
        false
    }

    fn hinged(&self) -> Option<usize> {
        self.covariates.iter().position(|c| c == TEMPERATURE)
    }

    /// φ(x).
    pub fn eval(&self, x: &[f64]) -> Vec<f64> {
        let mut phi = Vec::with_capacity(self.len());
        phi.push(1.0);
        phi.extend_from_slice(x);
        if let Some(t) = self.hinged() {
            phi.extend(self.knees.iter().map(|k| (k - x[t]).max(0.0)));
        }
        phi
    }

    /// A name per term: `1`, each covariate, `(0 − temperature_c)₊`.
    pub fn terms(&self) -> Vec<String> {
        let mut names = vec!["1".to_string()];
        names.extend(self.covariates.iter().cloned());
        if let Some(t) = self.hinged() {
            let c = &self.covariates[t];
            names.extend(self.knees.iter().map(|k| format!("({k} − {c})₊")));
        }
        names
    }
}

/// One parameter's regression (module docs), learned online.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Regression {
    /// Coefficients β, in the order of [`Basis::terms`].
    pub beta: Vec<f64>,
    /// Their covariance P, row by row.
    pub p: Vec<Vec<f64>>,
    /// Σ ω (e² − r − v) and Σ ω over the sets learned (τ², module docs).
    excess: f64,
    excess_weight: f64,
    pub learned: u64,
    /// Sets not learned from: their residual was beyond the gate.
    pub held_out: u64,
}

impl Regression {
    /// The prior: `β = (intercept, 0, …)` with standard deviations `prior_std` per term.
    pub fn new(intercept: f64, prior_std: &[f64]) -> Self {
        let q = prior_std.len();
        let mut beta = vec![0.0; q];
        beta[0] = intercept;
        let p = (0..q)
            .map(|i| {
                (0..q)
                    .map(|j| if i == j { prior_std[i].powi(2) } else { 0.0 })
                    .collect()
            })
            .collect();
        Self {
            beta,
            p,
            excess: 0.0,
            excess_weight: 0.0,
            learned: 0,
            held_out: 0,
        }
    }

    /// τ² (module docs).
    pub fn scatter(&self) -> f64 {
        if self.excess_weight > 0.0 {
            (self.excess / self.excess_weight).max(0.0)
        } else {
            0.0
        }
    }

    /// The prediction at φ for a set of variance `r` (module docs).
    pub fn predict(&self, phi: &[f64], r: f64) -> Prediction {
        Prediction {
            mean: dot(&self.beta, phi),
            model_var: quad(&self.p, phi),
            noise_var: r + self.scatter(),
        }
    }

    /// Learns `y` (ln θ) at φ with variance `r`, unless its predictive residual is beyond
    /// `gate` standard deviations (held out, counted). Returns whether it was learned.
    pub fn learn(&mut self, phi: &[f64], y: f64, r: f64, gate: f64) -> bool {
        let pred = self.predict(phi, r);
        let e = y - pred.mean;
        if e.abs() > gate * pred.total_var().sqrt() {
            self.held_out += 1;
            return false;
        }
        let omega = (r / (r + pred.model_var)).powi(2);
        self.excess += omega * (e * e - r - pred.model_var);
        self.excess_weight += omega;
        self.learned += 1;
        self.update(phi, y, 1.0 / pred.noise_var);
        true
    }

    /// The recursive least-squares step with weight `w`: `k = Pφ / (1/w + φᵀPφ)`,
    /// `β ← β + k (y − φᵀβ)`, `P ← P − k (Pφ)ᵀ`.
    fn update(&mut self, phi: &[f64], y: f64, w: f64) {
        let q = phi.len();
        let p_phi: Vec<f64> = self.p.iter().map(|row| dot(row, phi)).collect();
        let s = 1.0 / w + dot(phi, &p_phi);
        let e = y - dot(&self.beta, phi);
        for (b, k) in self.beta.iter_mut().zip(&p_phi) {
            *b += k / s * e;
        }
        for (row, ki) in self.p.iter_mut().zip(&p_phi) {
            for (v, kj) in row.iter_mut().zip(&p_phi) {
                *v -= ki * kj / s;
            }
        }
        // Keep P symmetric against round-off.
        for i in 0..q {
            for j in 0..i {
                let m = 0.5 * (self.p[i][j] + self.p[j][i]);
                self.p[i][j] = m;
                self.p[j][i] = m;
            }
        }
    }
}

/// Every parameter's regression on one basis, and the conditions learned from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CovariateModel {
    pub basis: Basis,
    pub parameters: Vec<Regression>,
    /// Per covariate, the least and greatest value of the sets learned from.
    pub ranges: Vec<Option<[f64; 2]>>,
}

impl CovariateModel {
    /// The prior model: intercepts at `ln_theta0` (±`intercept_std`), every other
    /// coefficient 0 ± `slope_std` per unit of its covariate.
    pub fn new(basis: Basis, ln_theta0: &[f64], intercept_std: f64, slope_std: f64) -> Self {
        let mut prior = vec![slope_std; basis.len()];
        prior[0] = intercept_std;
        let parameters = ln_theta0
            .iter()
            .map(|&y0| Regression::new(y0, &prior))
            .collect();
        let ranges = vec![None; basis.covariates.len()];
        Self {
            basis,
            parameters,
            ranges,
        }
    }

    /// The prediction of every parameter at covariates `x`, for a set of variances `r`.
    pub fn predict(&self, x: &[f64], r: &[f64]) -> Vec<Prediction> {
        let phi = self.basis.eval(x);
        self.parameters
            .iter()
            .zip(r)
            .map(|(m, &r)| m.predict(&phi, r))
            .collect()
    }

    /// Learns one set (ln θ `y`, variances `r`) at `x`, each parameter unless it is beyond
    /// `gate` (module docs). Returns how many parameters learned it.
    pub fn learn(&mut self, x: &[f64], y: &[f64], r: &[f64], gate: f64) -> usize {
        let phi = self.basis.eval(x);
        let used = self
            .parameters
            .iter_mut()
            .zip(y.iter().zip(r))
            .map(|(m, (&y, &r))| m.learn(&phi, y, r, gate))
            .filter(|&u| u)
            .count();
        if used > 0 {
            for (range, &v) in self.ranges.iter_mut().zip(x) {
                let [lo, hi] = range.get_or_insert([v, v]);
                *lo = lo.min(v);
                *hi = hi.max(v);
            }
        }
        used
    }

    /// Why `x` is outside the conditions learned from (by more than `margin` of each
    /// covariate's learned span), if it is.
    pub fn extrapolated(&self, x: &[f64], margin: f64) -> Option<String> {
        let out: Vec<String> = self
            .basis
            .covariates
            .iter()
            .zip(&self.ranges)
            .zip(x)
            .filter_map(|((name, range), &v)| match range {
                None => Some(format!("{name} = {v}: nothing learned yet")),
                Some([lo, hi]) => {
                    let pad = margin * (hi - lo);
                    (v < lo - pad || v > hi + pad)
                        .then(|| format!("{name} = {v} outside the learned {lo} … {hi}"))
                }
            })
            .collect();
        (!out.is_empty()).then(|| out.join("; "))
    }
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

/// `φᵀ P φ`.
fn quad(p: &[Vec<f64>], phi: &[f64]) -> f64 {
    p.iter().zip(phi).map(|(row, &f)| f * dot(row, phi)).sum()
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;
    use rand_distr::{Distribution, Normal};

    fn basis() -> Basis {
        Basis {
            covariates: vec![TEMPERATURE.into(), "humidity".into()],
            knees: vec![0.0],
        }
    }

    #[test]
    fn basis_terms_and_values() {
        let b = basis();
        assert_eq!(b.len(), 4);
        assert_eq!(b.eval(&[-3.0, 60.0]), vec![1.0, -3.0, 60.0, 3.0]);
        assert_eq!(b.eval(&[5.0, 60.0]), vec![1.0, 5.0, 60.0, 0.0]);
        assert_eq!(b.terms()[3], "(0 − temperature_c)₊");
    }

    /// Recursive least squares is the batch weighted least squares with the prior as
    /// pseudo-data: `β = (P₀⁻¹ + Σ w φφᵀ)⁻¹ (P₀⁻¹β₀ + Σ w φ y)`, with the weights the
    /// recursion used. Agreement to 1e-9 relative (a 4×4 system of condition ~1e6 in f64).
    #[test]
    fn recursion_equals_batch_weighted_least_squares() {
        let b = basis();
        let prior = [1.0, 0.05, 0.05, 0.05];
        let mut m = Regression::new(0.1, &prior);
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let noise = Normal::new(0.0, 0.05).unwrap();
        let mut a = nalgebra::DMatrix::<f64>::zeros(4, 4);
        let mut rhs = nalgebra::DVector::<f64>::zeros(4);
        for i in 0..4 {
            a[(i, i)] = 1.0 / prior[i].powi(2);
        }
        rhs[0] = 0.1 / prior[0].powi(2);
        for k in 0..200 {
            let t = -10.0 + 40.0 * ((k * 37) % 200) as f64 / 200.0;
            let h = 40.0 + (k % 7) as f64 * 5.0;
            let phi = b.eval(&[t, h]);
            let y = 0.02 - 0.004 * t + 0.001 * h + 0.02 * phi[3] + noise.sample(&mut rng);
            let r = 0.05f64.powi(2) * (1.0 + (k % 3) as f64);
            let w = 1.0 / m.predict(&phi, r).noise_var;
            assert!(m.learn(&phi, y, r, f64::INFINITY));
            for i in 0..4 {
                rhs[i] += w * phi[i] * y;
                for j in 0..4 {
                    a[(i, j)] += w * phi[i] * phi[j];
                }
            }
        }
        let batch = a.clone().lu().solve(&rhs).unwrap();
        let cov = a.try_inverse().unwrap();
        for i in 0..4 {
            assert!((m.beta[i] - batch[i]).abs() <= 1e-9 * batch[i].abs().max(1e-3));
            for j in 0..4 {
                assert!((m.p[i][j] - cov[(i, j)]).abs() <= 1e-9 * cov[(i, i)].abs());
            }
        }
    }

    /// Noise-free data of the model's own form are recovered (1e-6: the prior's pull,
    /// 1/P₀ against 300 sets of weight 1/r = 1e6, is 1e-8 relative).
    #[test]
    fn exact_law_is_recovered() {
        let b = basis();
        let mut m = CovariateModel::new(b.clone(), &[0.0], 1.0, 0.05);
        let truth = [0.05, -0.003, 0.0005, 0.025];
        for k in 0..300 {
            let t = -15.0 + 50.0 * (k as f64 * 0.618).fract();
            let h = 30.0 + 60.0 * (k as f64 * 0.414).fract();
            let y = dot(&truth, &b.eval(&[t, h]));
            m.learn(&[t, h], &[y], &[1e-6], 5.0);
        }
        for (got, want) in m.parameters[0].beta.iter().zip(truth) {
            assert!((got - want).abs() < 1e-6, "{got} vs {want}");
        }
        assert!(m.extrapolated(&[20.0, 50.0], 0.1).is_none());
        let why = m.extrapolated(&[-40.0, 50.0], 0.1).unwrap();
        assert!(why.contains("temperature_c = -40"), "{why}");
    }

    /// Scatter the covariates do not explain (σ 0.03 on top of r) is found by τ²
    /// (within 15 %: 2,000 sets give τ² to about ±5 %); the prediction interval then holds
    /// 95 % ± 1.5 % of new sets (Monte Carlo, 4,000 draws: ±0.7 % binomial, 2σ).
    #[test]
    fn scatter_and_prediction_interval_are_calibrated() {
        let b = Basis {
            covariates: vec![TEMPERATURE.into()],
            knees: vec![0.0],
        };
        let mut m = CovariateModel::new(b.clone(), &[0.0], 1.0, 0.05);
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        let meas = Normal::new(0.0, 0.04).unwrap();
        let extra = Normal::new(0.0, 0.03).unwrap();
        let law = |t: f64| 0.1 - 0.004 * t + 0.02 * (-t).max(0.0);
        let temp = |rng: &mut ChaCha8Rng| -10.0 + 40.0 * rand::Rng::random::<f64>(rng);
        for _ in 0..2000 {
            let t = temp(&mut rng);
            let y = law(t) + meas.sample(&mut rng) + extra.sample(&mut rng);
            m.learn(&[t], &[y], &[0.04f64.powi(2)], 5.0);
        }
        let tau = m.parameters[0].scatter().sqrt();
        assert!((tau / 0.03 - 1.0).abs() < 0.15, "τ = {tau}");
        let inside = (0..4000)
            .filter(|_| {
                let t = temp(&mut rng);
                let y = law(t) + meas.sample(&mut rng) + extra.sample(&mut rng);
                let p = &m.predict(&[t], &[0.04f64.powi(2)])[0];
                (y - p.mean).abs() < crate::core::stats::Z95 * p.total_var().sqrt()
            })
            .count();
        let frac = inside as f64 / 4000.0;
        assert!((frac - 0.95).abs() < 0.015, "{frac}");
    }

    /// Before any set below the knee, the hinge is the prior's: the model variance at
    /// −10 °C is at least (10 · 0.05)² less what the data above 0 °C pin of the other
    /// terms, i.e. the band is wide there and narrows once cold sets are learned.
    #[test]
    fn band_widens_outside_the_conditions_seen() {
        let b = Basis {
            covariates: vec![TEMPERATURE.into()],
            knees: vec![0.0],
        };
        let mut m = CovariateModel::new(b, &[0.0], 1.0, 0.05);
        for k in 0..200 {
            let t = 5.0 + 20.0 * (k as f64 * 0.618).fract();
            m.learn(&[t], &[0.1 - 0.004 * t], &[0.04f64.powi(2)], 5.0);
        }
        let cold = m.predict(&[-10.0], &[0.0])[0].model_var;
        let warm = m.predict(&[15.0], &[0.0])[0].model_var;
        assert!(cold > 0.2 && warm < 1e-4, "cold {cold}, warm {warm}");
        for k in 0..200 {
            let t = -12.0 + 12.0 * (k as f64 * 0.618).fract();
            m.learn(&[t], &[0.1 - 0.004 * t], &[0.04f64.powi(2)], 5.0);
        }
        assert!(m.predict(&[-10.0], &[0.0])[0].model_var < 1e-3);
    }

    /// A step of 30 % in one parameter, once the law is learned, is held out (|z| ≫ 5)
    /// and does not move the learned law.
    #[test]
    fn a_loss_is_not_learned() {
        let b = Basis {
            covariates: vec![TEMPERATURE.into()],
            knees: vec![],
        };
        let mut m = CovariateModel::new(b, &[0.0], 1.0, 0.05);
        let r = 0.03f64.powi(2);
        for k in 0..300 {
            let t = 30.0 * (k as f64 * 0.618).fract();
            m.learn(&[t], &[-0.003 * t], &[r], 5.0);
        }
        let before = m.parameters[0].beta.clone();
        for k in 0..50 {
            let t = 30.0 * (k as f64 * 0.377).fract();
            assert_eq!(m.learn(&[t], &[-0.003 * t + 0.7f64.ln()], &[r], 5.0), 0);
        }
        assert_eq!(m.parameters[0].beta, before);
        assert_eq!(m.parameters[0].held_out, 50);
    }
}
