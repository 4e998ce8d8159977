//! Planning the instrumentation before it is installed: the standard deviation of each
//! parameter per modal set that a choice of channels and modes will give, and a greedy
//! choice of channels to add.
//!
//! The prediction is the covariance (15) of the mode-matching estimate, `(JᵀJ)⁻¹` with the
//! Jacobian whitened by the stated σ of the data (frequency CoV, shape NSD of each mode's
//! RMS over the channels measured), evaluated at the nominal parameters on the model's own
//! noise-free modes: the inverse Fisher information of the estimate the tracker makes,
//! with the same weighting and pairing it uses.
//!
//! Channels are chosen greedily, one at a time: the candidate that most lowers the worst
//! relative σ of the connections (σ_l / θ0_l), ties broken by the sum of their relative
//! variances (an A-optimal criterion on the connections). Unlike effective independence
//! (Kammer 1991), which keeps the channels that most span the target modes, this aims
//! directly at what the tracker needs: every connection resolved.

use anyhow::{Context, Result, bail};
use faer::Mat;

use crate::core::modal::solver_for;
use crate::core::model::{Model, ParameterKind};
use crate::core::simulate::{Noise, SimulatedMode, simulate_modes};
use crate::core::updating::mode_matching::covariance_from_jacobian;
use crate::core::updating::{Evaluator, MeasuredData, Pairing, RawMode};

/// The model, its nominal parameters and noise-free modes, and the evaluator whose
/// sensitivities at the nominal parameters are reused by every prediction.
pub struct Planner {
    model: Model,
    theta0: Vec<f64>,
    modes: Vec<SimulatedMode>,
    noise: Noise,
    /// Per mode, the RMS of its shape over the installed channels, when set: every
    /// channel's shape σ is then the NSD times it (a sensor added is as noisy as those
    /// installed), not the NSD times the RMS over whichever channels are measured.
    reference_rms: Option<Vec<f64>>,
    evaluator: Evaluator,
}

/// One channel added by [`Planner::greedy`], and what the channels then give.
#[derive(Debug, Clone)]
pub struct Added {
    pub channel: usize,
    /// The worst relative σ of a connection with this channel added.
    pub worst: f64,
    /// σ of every parameter per set.
    pub sigma: Vec<f64>,
}

impl Planner {
    /// The planner of `model` with its lowest `n_modes` modes, identified with the stated
    /// `noise` (frequency CoV, shape NSD).
    pub fn new(model: Model, n_modes: usize, noise: Noise) -> Result<Self> {
        if n_modes == 0 {
            bail!("--modes: at least one mode is needed");
        }
        if n_modes > model.n_dof() {
            bail!(
                "--modes {n_modes}: the model has only {} DOFs",
                model.n_dof()
            );
        }
        let theta0 = model.nominal_theta();
        let mut solver = solver_for(&model)?;
        // Noise-free: the generator is never drawn from.
        let mut rng = <rand_chacha::ChaCha8Rng as rand::SeedableRng>::seed_from_u64(0);
        let clean = Noise {
            frequency_cov: 0.0,
            shape_nsd: 0.0,
        };
        let modes = simulate_modes(&model, &mut *solver, &theta0, n_modes, clean, &mut rng)?;
        let mut evaluator = Evaluator::new(&model)?;
        evaluator.set_pairing(Pairing::Misfit);
        Ok(Self {
            model,
            theta0,
            modes,
            noise,
            reference_rms: None,
            evaluator,
        })
    }

    /// States every channel's shape σ against the RMS of each mode over `installed`:
    /// adding a channel then adds information and takes none from the others.
    pub fn with_reference(mut self, installed: &[usize]) -> Self {
        let rms = self
            .modes
            .iter()
            .map(|m| {
                let sum: f64 = installed.iter().map(|&c| m.shape[c] * m.shape[c]).sum();
                (sum / installed.len().max(1) as f64).sqrt()
            })
            .collect();
        self.reference_rms = Some(rms);
        self
    }

    pub fn model(&self) -> &Model {
        &self.model
    }

    pub fn noise(&self) -> Noise {
        self.noise
    }

    /// The frequency of mode `k` (0-based) at the nominal parameters, Hz.
    pub fn frequency_hz(&self, k: usize) -> f64 {
        self.modes[k].frequency_hz
    }

    /// Whether channel `c` reads anything of `modes` (a channel at a support reads
    /// nothing, and would only shrink the RMS the shape σ are stated against).
    pub fn moves(&self, c: usize, modes: &[usize]) -> bool {
        modes.iter().any(|&k| self.modes[k].shape[c].abs() > 1e-9)
    }

    /// The data a set identified at `channels` with the modes `modes` (indices into the
    /// lowest modes) states: noise-free values, the planned σ.
    pub fn data(&self, channels: &[usize], modes: &[usize]) -> MeasuredData {
        let raw: Vec<RawMode> = modes
            .iter()
            .map(|&k| {
                let m = &self.modes[k];
                let shape = channels
                    .iter()
                    .map(|&c| (c, m.shape[c]))
                    .collect::<Vec<_>>();
                RawMode {
                    frequency_hz: m.frequency_hz,
                    frequency_cov: Some(self.noise.frequency_cov),
                    shape: (!shape.is_empty()).then_some(shape),
                    shape_nsd: Some(self.noise.shape_nsd),
                    shape_std: self
                        .reference_rms
                        .as_ref()
                        .map(|rms| vec![self.noise.shape_nsd * rms[k]; channels.len()]),
                }
            })
            .collect();
        MeasuredData::new(&raw, 1.0)
    }

    /// σ of every parameter per set with `channels` and `modes` (NaN for all when the
    /// data do not determine every parameter: the Fisher information is singular).
    pub fn sigma(&mut self, channels: &[usize], modes: &[usize]) -> Result<Vec<f64>> {
        Ok(self.sigma_and_correlation(channels, modes)?.0)
    }

    /// [`Planner::sigma`] and the parameters' correlation matrix (`None` when singular).
    pub fn sigma_and_correlation(
        &mut self,
        channels: &[usize],
        modes: &[usize],
    ) -> Result<(Vec<f64>, Option<Mat<f64>>)> {
        let data = self.data(channels, modes);
        let ev = self
            .evaluator
            .evaluate(&self.model, &data, &self.theta0)
            .context("the model's modes at its nominal parameters")?;
        let jac = self.evaluator.jacobian(&self.model, &data, &ev)?;
        let p = self.model.n_params();
        let Some(cov) = covariance_from_jacobian(&jac, &data, &ev) else {
            return Ok((vec![f64::NAN; p], None));
        };
        let sigma: Vec<f64> = (0..p).map(|l| cov[(l, l)].max(0.0).sqrt()).collect();
        let corr = Mat::from_fn(p, p, |a, b| cov[(a, b)] / (sigma[a] * sigma[b]));
        Ok((sigma, Some(corr)))
    }

    /// The worst relative σ (σ_l / θ0_l) over the connections' parameters (infinite when
    /// one is not determined), and the sum of their relative variances.
    pub fn worst(&self, sigma: &[f64]) -> (f64, f64) {
        let mut worst = 0.0_f64;
        let mut sum = 0.0;
        for (l, p) in self.model.parameters().iter().enumerate() {
            if !matches!(p.kind, ParameterKind::Connections(_)) {
                continue;
            }
            let rel = sigma[l] / self.theta0[l].abs();
            let rel = if rel.is_finite() { rel } else { f64::INFINITY };
            worst = worst.max(rel);
            sum += rel * rel;
        }
        (worst, sum)
    }

    /// Adds `n` of `candidates` to `current`, one at a time, each the one that gives the
    /// lowest worst relative σ (then the lowest sum of relative variances), with every
    /// mode in `modes`.
    pub fn greedy(
        &mut self,
        current: &[usize],
        candidates: &[usize],
        modes: &[usize],
        n: usize,
    ) -> Result<Vec<Added>> {
        let mut chosen = current.to_vec();
        let mut left: Vec<usize> = candidates
            .iter()
            .copied()
            .filter(|c| !current.contains(c))
            .collect();
        if n > left.len() {
            bail!(
                "--add {n}: only {} candidate channels are not measured already",
                left.len()
            );
        }
        let mut steps = Vec::with_capacity(n);
        for _ in 0..n {
            let mut best: Option<(usize, (f64, f64), Vec<f64>)> = None;
            for (i, &c) in left.iter().enumerate() {
                chosen.push(c);
                let sigma = self.sigma(&chosen, modes)?;
                chosen.pop();
                let score = self.worst(&sigma);
                if best.as_ref().is_none_or(|(_, b, _)| score < *b) {
                    best = Some((i, score, sigma));
                }
            }
            let (i, (worst, _), sigma) = best.expect("a candidate is left");
            let channel = left.remove(i);
            chosen.push(channel);
            steps.push(Added {
                channel,
                worst,
                sigma,
            });
        }
        Ok(steps)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::simulate::simulated_measured_data;
    use crate::core::updating::{ModeMatching, ModeMatchingOptions};

    fn lab_frame() -> Model {
        let spec = crate::io::model::load_spec(std::path::Path::new("bundled:lab-frame")).unwrap();
        Model::from_spec(&spec).unwrap()
    }

    const NOISE: Noise = Noise {
        frequency_cov: 0.01,
        shape_nsd: 0.05,
    };

    /// With every channel and 9 modes the prediction is the σ the tracker's fit reports on
    /// noise-free data stated with the same σ (it converges at the nominal parameters).
    #[test]
    fn the_prediction_is_the_fits_covariance_at_the_nominal_parameters() {
        let model = lab_frame();
        let all: Vec<usize> = (0..model.channels().len()).collect();
        let mut planner = Planner::new(model.clone(), 9, NOISE).unwrap();
        let predicted = planner.sigma(&all, &(0..9).collect::<Vec<_>>()).unwrap();
        let theta0 = model.nominal_theta();
        let data = simulated_measured_data(&model, &theta0, 9, NOISE, false, 1).unwrap();
        let mut evaluator = Evaluator::new(&model).unwrap();
        evaluator.set_pairing(Pairing::Misfit);
        let mut mm = ModeMatching::new(evaluator);
        let fit = mm
            .run(&model, &data, &theta0, &ModeMatchingOptions::default())
            .unwrap();
        for (l, (p, f)) in predicted.iter().zip(fit.std()).enumerate() {
            // Same formula at the same θ: equal to rounding.
            assert!(
                (p - f).abs() <= 1e-9 * f.abs().max(1e-12),
                "{l}: {p} against {f}"
            );
        }
    }

    /// Taking channels away raises σ, and the greedy choice puts back what matters: from
    /// a third of the channels, each added channel lowers the worst relative σ.
    #[test]
    fn greedy_additions_lower_the_worst_sigma_step_by_step() {
        let model = lab_frame();
        let n = model.channels().len();
        let modes: Vec<usize> = (0..9).collect();
        let mut planner = Planner::new(model, 9, NOISE).unwrap();
        let few: Vec<usize> = (0..n).step_by(3).collect();
        let all: Vec<usize> = (0..n).collect();
        let sigma_few = planner.sigma(&few, &modes).unwrap();
        let (worst_few, _) = planner.worst(&sigma_few);
        let sigma_all = planner.sigma(&all, &modes).unwrap();
        let (worst_all, _) = planner.worst(&sigma_all);
        assert!(worst_all < worst_few, "{worst_all} against {worst_few}");
        let steps = planner.greedy(&few, &all, &modes, 4).unwrap();
        let mut last = worst_few;
        for s in &steps {
            assert!(s.worst < last, "{} after {last}", s.worst);
            assert!(!few.contains(&s.channel));
            last = s.worst;
        }
        let e = planner
            .greedy(&few, &all, &modes, n)
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains("only"), "{e}");
    }

    /// Monte Carlo: 200 noisy sets (every channel, 9 modes, the stated noise drawn), each
    /// fitted from the nominal parameters; the sample σ of every parameter is within 20 %
    /// of the prediction. With 200 sets a sample σ's own relative standard error is
    /// 1/√400 = 5 %: 20 % is four of them, leaving room for the estimate's nonlinearity.
    #[test]
    fn the_prediction_matches_the_scatter_of_fits_to_noisy_sets() {
        let model = lab_frame();
        let all: Vec<usize> = (0..model.channels().len()).collect();
        let mut planner = Planner::new(model.clone(), 9, NOISE).unwrap();
        let predicted = planner.sigma(&all, &(0..9).collect::<Vec<_>>()).unwrap();
        let theta0 = model.nominal_theta();
        let mut mm = ModeMatching::new(Evaluator::new(&model).unwrap());
        let fits: Vec<Vec<f64>> = (0..200)
            .map(|seed| {
                let data = simulated_measured_data(&model, &theta0, 9, NOISE, true, seed).unwrap();
                let opts = ModeMatchingOptions::default();
                mm.run(&model, &data, &theta0, &opts).unwrap().theta
            })
            .collect();
        for (l, p) in predicted.iter().enumerate() {
            let x: Vec<f64> = fits.iter().map(|t| t[l]).collect();
            let mean = x.iter().sum::<f64>() / x.len() as f64;
            let var = x.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (x.len() - 1) as f64;
            let sample = var.sqrt();
            assert!(
                (sample / p - 1.0).abs() < 0.2,
                "{l}: sample {sample} against {p}"
            );
        }
    }

    /// Against the installed channels' noise, a channel added only adds information: no σ
    /// rises (to rounding), whichever channel it is. (Stated against the RMS of whatever is
    /// measured, a loud channel would make every other one noisier.)
    #[test]
    fn with_a_reference_an_added_channel_never_raises_a_sigma() {
        let model = lab_frame();
        let n = model.channels().len();
        let modes: Vec<usize> = (0..9).collect();
        let installed: Vec<usize> = (0..n).step_by(2).collect();
        let mut planner = Planner::new(model, 9, NOISE)
            .unwrap()
            .with_reference(&installed);
        let before = planner.sigma(&installed, &modes).unwrap();
        for extra in (1..n).step_by(2) {
            let mut more = installed.clone();
            more.push(extra);
            let after = planner.sigma(&more, &modes).unwrap();
            for (l, (a, b)) in after.iter().zip(&before).enumerate() {
                assert!(
                    *a <= b * (1.0 + 1e-9),
                    "channel {extra}, parameter {l}: {b} → {a}"
                );
            }
        }
    }

    #[test]
    fn zero_modes_are_refused() {
        let e = Planner::new(lab_frame(), 0, NOISE)
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains("--modes"), "{e}");
    }
}
