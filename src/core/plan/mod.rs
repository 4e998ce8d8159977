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
//! Channels are chosen greedily, one at a time ([`Planner::greedy`]): the candidate that
//! most lowers the connections' shortfall from a required relative σ (σ_l / θ0_l), the sum
//! over connections of how far each is above it ([`Criterion`]); once none falls short,
//! the worst relative σ, then the sum of relative variances (an A-optimal criterion on the
//! connections). Unlike effective independence (Kammer 1991, [`baselines`]), which keeps
//! the channels that most span the target modes, this aims directly at what the tracker
//! needs: every connection resolved well enough to be watched.

pub mod baselines;
pub mod places;

use anyhow::{Context, Result, bail};
use faer::Mat;

use crate::core::modal::{EigenPairs, solver_for};
use crate::core::model::{Model, ParameterKind};
use crate::core::simulate::{Noise, SimulatedMode, simulate_modes};
use crate::core::updating::mode_matching::covariance_from_jacobian;
use crate::core::updating::{Evaluation, Evaluator, MeasuredData, Pairing, RawMode};

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
    /// The model's candidate modes at θ0 for every prediction: one solve, and the same
    /// candidates (so the same cached sensitivities) whatever the channels and modes.
    eig: EigenPairs,
    evaluator: Evaluator,
    /// [`Planner::watched`].
    watched: Vec<usize>,
}

/// What a greedy step minimises, from the connections' relative σ per set: first the
/// number the data do not determine, then the shortfall `Σ max(0, rel_l / needed − 1)`,
/// then the worst relative σ, then the sum of relative variances. With `needed` zero the
/// shortfall is the same for all, and the worst σ decides.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Criterion {
    pub needed: f64,
}

impl Criterion {
    /// The score of relative σ `rel`, compared lexicographically (lower is better).
    pub fn score(&self, rel: &[f64]) -> [f64; 4] {
        let mut out = [0.0; 4];
        for &r in rel {
            if !r.is_finite() {
                out[0] += 1.0;
                continue;
            }
            if self.needed > 0.0 {
                out[1] += (r / self.needed - 1.0).max(0.0);
            }
            out[2] = out[2].max(r);
            out[3] += r * r;
        }
        out
    }
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
        let connections: Vec<usize> = (0..model.n_params())
            .filter(|&l| matches!(model.parameters()[l].kind, ParameterKind::Connections(_)))
            .collect();
        let watched = if connections.is_empty() {
            (0..model.n_params()).collect()
        } else {
            connections
        };
        let mut planner = Self {
            watched,
            model,
            theta0,
            modes,
            noise,
            reference_rms: None,
            eig: EigenPairs {
                lambda: Vec::new(),
                phi: Mat::zeros(0, 0),
            },
            evaluator,
        };
        // The candidates of the largest data: every channel, every mode.
        let every: Vec<usize> = (0..planner.model.channels().len()).collect();
        let data = planner.data(&every, &(0..n_modes).collect::<Vec<_>>());
        planner.eig = planner
            .evaluator
            .evaluate(&planner.model, &data, &planner.theta0)
            .context("the model's modes at its nominal parameters")?
            .eig;
        Ok(planner)
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
                        .is_some()
                        .then(|| vec![self.shape_sigma(k, channels); channels.len()]),
                }
            })
            .collect();
        MeasuredData::new(&raw, 1.0)
    }

    /// The σ of mode `k`'s shape entries at `channels`: the NSD times the mode's RMS over
    /// the installed channels ([`Planner::with_reference`]), else over `channels`.
    pub fn shape_sigma(&self, k: usize, channels: &[usize]) -> f64 {
        let rms = match &self.reference_rms {
            Some(rms) => rms[k],
            None => {
                let m = &self.modes[k];
                let sum: f64 = channels.iter().map(|&c| m.shape[c] * m.shape[c]).sum();
                (sum / channels.len().max(1) as f64).sqrt()
            }
        };
        self.noise.shape_nsd * rms
    }

    /// One set as planned, with its noise drawn: each mode's frequency with the stated CoV,
    /// its shape at `channels` with [`Planner::shape_sigma`] per entry (returned with it),
    /// the modes by frequency as an identification lists them.
    pub fn draw(
        &self,
        channels: &[usize],
        modes: &[usize],
        rng: &mut impl rand::Rng,
    ) -> Vec<(SimulatedMode, f64)> {
        use rand_distr::StandardNormal;
        let mut out: Vec<(SimulatedMode, f64)> = modes
            .iter()
            .map(|&k| {
                let m = &self.modes[k];
                let xi: f64 = rng.sample(StandardNormal);
                let frequency_hz = m.frequency_hz * (1.0 + self.noise.frequency_cov * xi);
                let sigma = self.shape_sigma(k, channels);
                let shape = channels
                    .iter()
                    .map(|&c| m.shape[c] + sigma * rng.sample::<f64, _>(StandardNormal))
                    .collect();
                let mode = SimulatedMode {
                    frequency_hz,
                    shape,
                };
                (mode, sigma)
            })
            .collect();
        out.sort_by(|a, b| a.0.frequency_hz.total_cmp(&b.0.frequency_hz));
        out
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
        let ev = Evaluation::of_pairs(
            &self.model,
            &data,
            &self.theta0,
            self.eig.clone(),
            Pairing::Misfit,
        );
        let jac = self.evaluator.jacobian(&self.model, &data, &ev)?;
        let p = self.model.n_params();
        let Some(cov) = covariance_from_jacobian(&jac, &data, &ev) else {
            return Ok((vec![f64::NAN; p], None));
        };
        let sigma: Vec<f64> = (0..p).map(|l| cov[(l, l)].max(0.0).sqrt()).collect();
        let corr = Mat::from_fn(p, p, |a, b| cov[(a, b)] / (sigma[a] * sigma[b]));
        Ok((sigma, Some(corr)))
    }

    /// The parameters a plan must make watchable (indices into θ): the connections', or
    /// every parameter of a model that has none (an imported model's matrices).
    pub fn watched(&self) -> &[usize] {
        &self.watched
    }

    /// What the watched parameters are: `connections`, or `parameters` for a model with
    /// no connection parameters.
    pub fn watched_noun(&self) -> &'static str {
        let is_connection = |&l: &usize| {
            matches!(
                self.model.parameters()[l].kind,
                ParameterKind::Connections(_)
            )
        };
        if self.watched.iter().all(is_connection) {
            "connections"
        } else {
            "parameters"
        }
    }

    /// The watched parameters' relative σ (σ_l / θ0_l; infinite where not determined).
    pub fn relative(&self, sigma: &[f64]) -> Vec<f64> {
        self.watched
            .iter()
            .map(|&l| {
                let rel = sigma[l] / self.theta0[l].abs();
                if rel.is_finite() { rel } else { f64::INFINITY }
            })
            .collect()
    }

    /// The worst relative σ of a watched parameter (infinite when one is not determined),
    /// and the sum of their relative variances.
    pub fn worst(&self, sigma: &[f64]) -> (f64, f64) {
        let rel = self.relative(sigma);
        let worst = rel.iter().fold(0.0_f64, |w, &r| w.max(r));
        (worst, rel.iter().map(|r| r * r).sum())
    }

    /// Adds `n` of `candidates` to `current`, one at a time, each the one of lowest
    /// [`Criterion::score`], with every mode in `modes`.
    pub fn greedy(
        &mut self,
        current: &[usize],
        candidates: &[usize],
        modes: &[usize],
        n: usize,
        criterion: Criterion,
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
            let mut best: Option<(usize, [f64; 4], Vec<f64>)> = None;
            for (i, &c) in left.iter().enumerate() {
                chosen.push(c);
                let sigma = self.sigma(&chosen, modes)?;
                chosen.pop();
                let score = criterion.score(&self.relative(&sigma));
                if best.as_ref().is_none_or(|(_, b, _)| score < *b) {
                    best = Some((i, score, sigma));
                }
            }
            let (i, _, sigma) = best.expect("a candidate is left");
            let (worst, _) = self.worst(&sigma);
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
mod tests;
