//! Simulated modal data: the lowest modes of a model at θ, read at its channels, with
//! Gaussian measurement noise matching the uncertainty model of the updating methods:
//! `f̃ = f (1 + V^f ξ)` (frequency CoV `V^f`) and `ψ̃_i = ψ_i + S^w RMS(ψ) ξ_i` (shape NSD
//! `S^w`, (27)–(28)), with independent standard normal ξ. Shapes are scaled so that their
//! largest-magnitude entry is +1 before noise is added.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

use crate::core::modal::{EigenSolver, ModalError, solver_for};
use crate::core::model::Model;
use crate::core::updating::{MeasuredData, RawMode};

/// One simulated mode: frequency (Hz) and shape at every model channel, in model order.
#[derive(Debug, Clone, PartialEq)]
pub struct SimulatedMode {
    pub frequency_hz: f64,
    pub shape: Vec<f64>,
}

/// Noise levels; zero means noise-free.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Noise {
    pub frequency_cov: f64,
    pub shape_nsd: f64,
}

/// The lowest `n_modes` modes of `model` at `theta`, with noise drawn from `rng`.
pub fn simulate_modes(
    model: &Model,
    solver: &mut dyn EigenSolver,
    theta: &[f64],
    n_modes: usize,
    noise: Noise,
    rng: &mut impl Rng,
) -> Result<Vec<SimulatedMode>, ModalError> {
    let eig = solver.solve(model, theta, n_modes)?;
    let channels = model.channels();
    let mut phi = vec![0.0; model.n_dof()];
    let mut out = Vec::with_capacity(n_modes);
    for k in 0..n_modes {
        for (i, v) in phi.iter_mut().enumerate() {
            *v = eig.phi[(i, k)];
        }
        let mut shape: Vec<f64> = channels.iter().map(|c| c.read(&phi)).collect();
        let peak = shape
            .iter()
            .fold(0.0_f64, |a, &b| if b.abs() > a.abs() { b } else { a });
        if peak != 0.0 {
            shape.iter_mut().for_each(|v| *v /= peak);
        }
        let f = eig.frequency_hz(k);
        let frequency_hz = if noise.frequency_cov > 0.0 {
            let xi: f64 = rng.sample(StandardNormal);
            f * (1.0 + noise.frequency_cov * xi)
        } else {
            f
        };
        if noise.shape_nsd > 0.0 && !shape.is_empty() {
            let rms = (shape.iter().map(|v| v * v).sum::<f64>() / shape.len() as f64).sqrt();
            for v in shape.iter_mut() {
                let xi: f64 = rng.sample(StandardNormal);
                *v += noise.shape_nsd * rms * xi;
            }
        }
        out.push(SimulatedMode {
            frequency_hz,
            shape,
        });
    }
    // By frequency, as an identification lists its modes (and as a modal set must be):
    // close modes (the space frame's 12–14 lie within 0.7 %) can swap under 1 % noise.
    // The sort is stable, so a set without a swap is unchanged.
    out.sort_by(|a, b| a.frequency_hz.total_cmp(&b.frequency_hz));
    Ok(out)
}

/// Measured data for updating, simulated from `model` at `theta` at every channel with
/// the uncertainties `stated` (frequency CoV, shape NSD) and, if `noisy`, noise of the same
/// size drawn from ChaCha8 seeded with `seed`. For tests, benchmarks and studies.
pub fn simulated_measured_data(
    model: &Model,
    theta: &[f64],
    n_modes: usize,
    stated: Noise,
    noisy: bool,
    seed: u64,
) -> Result<MeasuredData, ModalError> {
    let mut solver = solver_for(model)?;
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let noise = if noisy {
        stated
    } else {
        Noise {
            frequency_cov: 0.0,
            shape_nsd: 0.0,
        }
    };
    let modes = simulate_modes(model, &mut *solver, theta, n_modes, noise, &mut rng)?;
    let raw: Vec<RawMode> = modes
        .iter()
        .map(|m| RawMode {
            frequency_hz: m.frequency_hz,
            frequency_cov: Some(stated.frequency_cov),
            shape: Some(m.shape.iter().copied().enumerate().collect()),
            shape_nsd: Some(stated.shape_nsd),
            shape_std: None,
        })
        .collect();
    Ok(MeasuredData::new(&raw, 1.0))
}
