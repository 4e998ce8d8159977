//! Acceleration records simulated from a model: the exact truth for identification tests
//! and for `scenario` recordings of raw data.
//!
//! Modal superposition: the model's modes below `max_frequency_hz` (mass-normalized, so the
//! modal equations are `q̈ + 2ζω q̇ + ω² q = p`), each driven by its own Gaussian white
//! force held constant over a sample interval (zero-order hold), which is what a spatially
//! white excitation distributed like the mass gives (`Cov p = Φᵀ M Φ = I`). Each modal
//! equation is stepped exactly (the matrix exponential of the 2 × 2 system, closed form), so
//! the discrete record has exactly the model's poles `exp((−ζω ± iω√(1−ζ²)) Δt)`.
//! Accelerations `q̈ = p − ω²q − 2ζωq̇` are read at the model's channels, and white sensor
//! noise of `noise_rel` times each channel's RMS is added. A burn-in of 10 time constants
//! of the slowest-decaying mode is simulated and dropped, so the record is stationary.

use faer::Mat;
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};

use super::{OmaError, Quantity, Record};
use crate::core::modal::{EigenPairs, solver_for};
use crate::core::model::Model;

/// Options of [`accelerations`].
#[derive(Debug, Clone)]
pub struct SynthOptions {
    pub rate_hz: f64,
    pub duration_s: f64,
    /// Modal damping ratio of every mode.
    pub damping: f64,
    /// Modes up to this frequency (default: 0.4 of the sampling rate).
    pub max_frequency_hz: Option<f64>,
    /// Sensor noise standard deviation relative to each channel's RMS.
    pub noise_rel: f64,
    pub seed: u64,
    /// What each channel measures (empty: accelerations everywhere); a velocity or
    /// displacement channel reads the modal velocities or displacements instead.
    pub quantities: Vec<Quantity>,
}

/// One mode of the truth, as the channels see it.
#[derive(Debug, Clone)]
pub struct TrueMode {
    pub frequency_hz: f64,
    pub damping: f64,
    /// Channel readings of the mass-normalized mode shape.
    pub shape: Vec<f64>,
}

/// A simulated record and the modes it was made of.
#[derive(Debug, Clone)]
pub struct Synthesized {
    pub record: Record,
    pub modes: Vec<TrueMode>,
}

/// Simulates an acceleration record of `model` at θ (module docs).
pub fn accelerations(
    model: &Model,
    theta: &[f64],
    opts: &SynthOptions,
) -> Result<Synthesized, OmaError> {
    let (fs, zeta) = (opts.rate_hz, opts.damping);
    if !(fs > 0.0 && opts.duration_s > 0.0 && zeta > 0.0 && zeta < 1.0 && opts.noise_rel >= 0.0) {
        return Err(OmaError::Input(format!(
            "simulation needs rate > 0, duration > 0, 0 < damping < 1, noise ≥ 0 (got {fs} Hz, {} s, ζ {zeta}, noise {})",
            opts.duration_s, opts.noise_rel
        )));
    }
    let f_max = opts.max_frequency_hz.unwrap_or(0.4 * fs);
    let channels = model.channels();
    if channels.is_empty() {
        return Err(OmaError::Input(format!(
            "model `{}` has no channels to read",
            model.name
        )));
    }
    let pairs = modes_past(model, theta, f_max)?;
    let n = pairs.lambda.len();
    let modes: Vec<TrueMode> = (0..n)
        .filter(|&k| pairs.frequency_hz(k) <= f_max)
        .map(|k| {
            let col: Vec<f64> = pairs.phi.col(k).iter().copied().collect();
            TrueMode {
                frequency_hz: pairs.frequency_hz(k),
                damping: zeta,
                shape: channels.iter().map(|c| c.read(&col)).collect(),
            }
        })
        .collect();
    let names: Vec<String> = channels.iter().map(|c| c.name.clone()).collect();
    Ok(from_modes(modes, names, opts))
}

/// Few channels, light damping: 240 s of 6 channels at 256 Hz, nine modes of 0.2 %
/// damping from 1.1 to 14.6 Hz (two pairs 4 % apart), 2 % sensor noise; the size and kind
/// of the measured frame in `tests/data/pyoma-frame`.
pub fn light_damping_frame() -> Synthesized {
    let freqs = [1.1, 2.3, 3.9, 5.6, 7.4, 7.7, 12.2, 12.7, 14.6];
    let modes: Vec<TrueMode> = freqs
        .iter()
        .enumerate()
        .map(|(k, &f)| TrueMode {
            frequency_hz: f,
            damping: 0.002,
            shape: (0..6)
                .map(|c| ((k + 1) as f64 * (c + 1) as f64 * 0.7 + k as f64).sin())
                .collect(),
        })
        .collect();
    from_modes(
        modes,
        (1..=6).map(|c| format!("ch{c}")).collect(),
        &SynthOptions {
            rate_hz: 256.0,
            duration_s: 240.0,
            damping: 0.002,
            max_frequency_hz: None,
            noise_rel: 0.02,
            seed: 11,
            quantities: vec![],
        },
    )
}

/// A record of `modes` (each with its own damping; shapes one entry per channel of
/// `channels`) under white modal forces, as [`accelerations`] simulates a model's:
/// `opts.damping` and `opts.max_frequency_hz` are not used.
pub fn from_modes(modes: Vec<TrueMode>, channels: Vec<String>, opts: &SynthOptions) -> Synthesized {
    let fs = opts.rate_hz;
    let dt = 1.0 / fs;
    let samples = (opts.duration_s * fs).round() as usize;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(opts.seed);
    let unit = Normal::new(0.0, 1.0).expect("unit normal");
    let quantity = |c: usize| quantity_at(&opts.quantities, c);
    let lower = (0..channels.len()).any(|c| quantity(c) != Quantity::Acceleration);
    let response = modal_response(&modes, dt, samples, lower, &mut rng, &unit);
    let mut y = channel_signals(&modes, &response, channels.len(), lower, &opts.quantities);
    if opts.noise_rel > 0.0 {
        add_noise(&mut y, opts.noise_rel, samples, &mut rng, &unit);
    }
    Synthesized {
        record: Record {
            quantities: (0..channels.len()).map(quantity).collect(),
            channels,
            rate_hz: fs,
            samples: y,
        },
        modes,
    }
}

/// What channel `c` measures: its entry of `quantities`, an acceleration where there is none.
fn quantity_at(quantities: &[Quantity], c: usize) -> Quantity {
    quantities.get(c).copied().unwrap_or(Quantity::Acceleration)
}

/// The modal responses of a simulation, samples × modes.
struct ModalResponse {
    /// Modal accelerations.
    qdd: Mat<f64>,
    /// Modal velocities (0 × 0 when no channel reads them).
    qd: Mat<f64>,
    /// Modal displacements (0 × 0 when no channel reads them).
    q: Mat<f64>,
}

/// Each modal equation stepped exactly ([`zoh_step`]) under its white force from `rng`,
/// the burn-in of 10 time constants of the slowest-decaying mode dropped: `samples` modal
/// accelerations, and with `lower` the modal velocities and displacements too.
fn modal_response(
    modes: &[TrueMode],
    dt: f64,
    samples: usize,
    lower: bool,
    rng: &mut rand_chacha::ChaCha8Rng,
    unit: &Normal<f64>,
) -> ModalResponse {
    let m = modes.len();
    let slowest = modes
        .iter()
        .map(|md| md.damping * 2.0 * std::f64::consts::PI * md.frequency_hz)
        .fold(f64::INFINITY, f64::min);
    let burn = (10.0 / slowest / dt).ceil() as usize;
    // Modal accelerations, samples × modes.
    let mut qdd = Mat::<f64>::zeros(samples, m);
    let (mut qd, mut q) = if lower {
        (Mat::<f64>::zeros(samples, m), Mat::<f64>::zeros(samples, m))
    } else {
        (Mat::<f64>::zeros(0, 0), Mat::<f64>::zeros(0, 0))
    };
    let steps: Vec<[f64; 6]> = modes
        .iter()
        .map(|md| zoh_step(2.0 * std::f64::consts::PI * md.frequency_hz, md.damping, dt))
        .collect();
    let mut state = vec![(0.0_f64, 0.0_f64); m];
    for k in 0..burn + samples {
        for (j, st) in state.iter_mut().enumerate() {
            let p = unit.sample(rng);
            let [a00, a01, a10, a11, b0, b1] = steps[j];
            let (w, zeta) = (
                2.0 * std::f64::consts::PI * modes[j].frequency_hz,
                modes[j].damping,
            );
            if k >= burn {
                qdd[(k - burn, j)] = p - w * w * st.0 - 2.0 * zeta * w * st.1;
                if lower {
                    qd[(k - burn, j)] = st.1;
                    q[(k - burn, j)] = st.0;
                }
            }
            *st = (
                a00 * st.0 + a01 * st.1 + b0 * p,
                a10 * st.0 + a11 * st.1 + b1 * p,
            );
        }
    }
    ModalResponse { qdd, qd, q }
}

/// The channels' signals, samples × channels: the modal accelerations through the shapes,
/// and with `lower`, for a channel that measures a velocity or a displacement, the modal
/// velocities or displacements through them instead.
fn channel_signals(
    modes: &[TrueMode],
    response: &ModalResponse,
    n_channels: usize,
    lower: bool,
    quantities: &[Quantity],
) -> Mat<f64> {
    let m = modes.len();
    let phi = Mat::from_fn(m, n_channels, |j, c| modes[j].shape[c]);
    let mut y = &response.qdd * &phi;
    if lower {
        let (yd, yv) = (&response.q * &phi, &response.qd * &phi);
        for c in 0..n_channels {
            match quantity_at(quantities, c) {
                Quantity::Acceleration => {}
                Quantity::Velocity => y.col_mut(c).copy_from(yv.col(c)),
                Quantity::Displacement => y.col_mut(c).copy_from(yd.col(c)),
            }
        }
    }
    y
}

/// White sensor noise of `noise_rel` times each channel's RMS (over its `samples` rows)
/// added to `y`, channel by channel, from `rng`.
fn add_noise(
    y: &mut Mat<f64>,
    noise_rel: f64,
    samples: usize,
    rng: &mut rand_chacha::ChaCha8Rng,
    unit: &Normal<f64>,
) {
    for c in 0..y.ncols() {
        let rms = (y.col(c).iter().map(|v| v * v).sum::<f64>() / samples as f64).sqrt();
        let sd = noise_rel * rms;
        for k in 0..samples {
            y[(k, c)] += sd * unit.sample(rng);
        }
    }
}

/// The lowest modes of `model` at θ, enough to pass `f_max` (or every mode it has): 12,
/// then twice as many until the last is above `f_max`.
pub fn modes_past(model: &Model, theta: &[f64], f_max: f64) -> Result<EigenPairs, OmaError> {
    let mut solver = solver_for(model).map_err(|e| OmaError::Numerical(e.to_string()))?;
    let available = model.n_dof() - model.massless_dofs().len();
    let mut n = 12.min(available);
    loop {
        let pairs = solver
            .solve(model, theta, n)
            .map_err(|e| OmaError::Numerical(e.to_string()))?;
        if pairs.frequency_hz(n - 1) > f_max || n == available {
            return Ok(pairs);
        }
        n = (2 * n).min(available);
    }
}

/// The exact zero-order-hold step of `q̈ + 2ζω q̇ + ω² q = p` over `dt`:
/// `[q, q̇]_{k+1} = A_d [q, q̇]_k + B_d p_k`, returned as `[A00, A01, A10, A11, B0, B1]`.
/// `A_d = exp(A_c dt)` in closed form (underdamped), `B_d = A_c⁻¹ (A_d − I) [0, 1]ᵀ`.
pub fn zoh_step(w: f64, zeta: f64, dt: f64) -> [f64; 6] {
    let wd = w * (1.0 - zeta * zeta).sqrt();
    let e = (-zeta * w * dt).exp();
    let (s, c) = (wd * dt).sin_cos();
    let a00 = e * (c + zeta * w / wd * s);
    let a01 = e * s / wd;
    let a10 = -e * w * w / wd * s;
    let a11 = e * (c - zeta * w / wd * s);
    // A_c⁻¹ = [[−2ζ/ω, −1/ω²], [1, 0]].
    let b0 = -2.0 * zeta / w * a01 - (a11 - 1.0) / (w * w);
    let b1 = a01;
    [a00, a01, a10, a11, b0, b1]
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The closed-form step against a fine explicit integration (RK4 with 10⁴ substeps) of
    /// the same ODE under a constant force: agreement to 1e-10.
    #[test]
    fn zoh_step_is_the_exact_solution() {
        let (w, zeta, dt) = (2.0 * std::f64::consts::PI * 7.3, 0.03, 1e-3 * 3.0);
        let [a00, a01, a10, a11, b0, b1] = zoh_step(w, zeta, dt);
        let (q0, v0, p) = (0.7, -2.1, 3.3);
        let exact = (a00 * q0 + a01 * v0 + b0 * p, a10 * q0 + a11 * v0 + b1 * p);
        let f = |q: f64, v: f64| (v, p - w * w * q - 2.0 * zeta * w * v);
        let (mut q, mut v) = (q0, v0);
        let n = 10_000;
        let h = dt / n as f64;
        for _ in 0..n {
            let k1 = f(q, v);
            let k2 = f(q + h / 2.0 * k1.0, v + h / 2.0 * k1.1);
            let k3 = f(q + h / 2.0 * k2.0, v + h / 2.0 * k2.1);
            let k4 = f(q + h * k3.0, v + h * k3.1);
            q += h / 6.0 * (k1.0 + 2.0 * k2.0 + 2.0 * k3.0 + k4.0);
            v += h / 6.0 * (k1.1 + 2.0 * k2.1 + 2.0 * k3.1 + k4.1);
        }
        assert!(
            (exact.0 - q).abs() < 1e-10 * q.abs().max(1.0),
            "{exact:?} vs {q}"
        );
        assert!(
            (exact.1 - v).abs() < 1e-10 * v.abs().max(1.0),
            "{exact:?} vs {v}"
        );
    }
}
