//! `boltwatch simulate`: a modal set from a model at θ, with noise.

use std::path::PathBuf;

use anyhow::{Result, bail};
use chrono::{DateTime, Utc};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use super::{ModelAtTheta, write_json};
use crate::contract::modal_set::{MeasuredMode, ModalSet};
use crate::core::diagnosis::injection::Injection;
use crate::core::modal::solver_for;
use crate::core::model::Model;
use crate::core::simulate::{Noise, SimulatedMode, simulate_modes};

#[derive(Debug, clap::Args)]
pub struct SimulateArgs {
    #[command(flatten)]
    pub at: ModelAtTheta,
    /// Number of modes (the lowest ones).
    #[arg(long, default_value_t = 9)]
    pub modes: usize,
    /// Frequency coefficient of variation: noise level and stated uncertainty (0: none).
    #[arg(long, default_value_t = 0.01)]
    pub freq_cov: f64,
    /// Mode-shape normalized standard deviation (27): noise level and stated uncertainty.
    #[arg(long, default_value_t = 0.05)]
    pub shape_nsd: f64,
    /// State the uncertainties but add no noise.
    #[arg(long)]
    pub noise_free: bool,
    /// Random seed (ChaCha8).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Time stamp of the set (RFC 3339).
    #[arg(long, default_value = "2026-01-01T00:00:00Z")]
    pub time: String,
    /// Add an effect the model file lacks, `kind@location=value` (repeatable), e.g.
    /// `added-mass@J2R=0.5` (kg), `support-flexibility@BL.rz=2e4` (N·m/rad),
    /// `member-stiffness@C2L=-0.2`, `modulus@global=0.05`, `joint-inertia@J1L=1e-3` (kg·m²);
    /// on a model imported from matrices, at a `locations` name or a DOF label:
    /// `added-mass@floor2=150` (kg on each of its DOFs), `grounded-spring@bearing=1e6`,
    /// `stiffness-scale@K0=-0.05`.
    #[arg(long)]
    pub inject: Vec<String>,
    /// Output file (boltwatch.modal_set.v1).
    #[arg(short, long)]
    pub out: PathBuf,
}

/// `boltwatch simulate`: the model at θ (with any injected effects), its lowest modes with
/// noise, written as a modal set and listed on stdout.
pub fn run(args: &SimulateArgs) -> Result<()> {
    let (model, theta) = model_at_theta(args)?;
    crate::core::numerics_for(&model);
    check_args(args, &model)?;
    let time = chrono::DateTime::parse_from_rfc3339(&args.time)
        .map_err(|e| anyhow::anyhow!("--time `{}`: {e}", args.time))?
        .with_timezone(&chrono::Utc);
    let modes = simulate(args, &model, &theta)?;
    let set = modal_set(args, &model, &theta, time, &modes);
    write_json(&args.out, &set.to_json())?;
    print_modes(args, &model, &modes);
    Ok(())
}

/// The model and θ of `--model`/`--theta`, with the `--inject` effects added to the model's
/// description before it is built.
fn model_at_theta(args: &SimulateArgs) -> Result<(Model, Vec<f64>)> {
    if args.inject.is_empty() {
        return args.at.load();
    }
    let (mut description, _) = super::load_description(&args.at.model)?;
    for s in &args.inject {
        Injection::parse(s)
            .and_then(|i| i.apply(&mut description))
            .map_err(|e| anyhow::anyhow!("--inject {e}"))?;
    }
    let model = description
        .build()
        .map_err(|e| anyhow::anyhow!("--inject: the model with the effects added: {e}"))?;
    let theta = super::parse_theta(&model, args.at.theta.as_deref(), "--theta")?;
    Ok((model, theta))
}

/// Refuses a negative or non-finite noise level, and a number of modes outside 1..=DOFs.
fn check_args(args: &SimulateArgs, model: &Model) -> Result<()> {
    for (name, v) in [
        ("--freq-cov", args.freq_cov),
        ("--shape-nsd", args.shape_nsd),
    ] {
        if !(v.is_finite() && v >= 0.0) {
            bail!("{name} = {v} must be a finite number ≥ 0");
        }
    }
    if args.modes == 0 || args.modes > model.n_dof() {
        bail!(
            "--modes = {} must be between 1 and the model's {} DOFs",
            args.modes,
            model.n_dof()
        );
    }
    Ok(())
}

/// The lowest `--modes` modes of the model at θ, with the noise asked for (none with
/// `--noise-free`) drawn from ChaCha8 seeded by `--seed`.
fn simulate(args: &SimulateArgs, model: &Model, theta: &[f64]) -> Result<Vec<SimulatedMode>> {
    let noise = if args.noise_free {
        Noise {
            frequency_cov: 0.0,
            shape_nsd: 0.0,
        }
    } else {
        Noise {
            frequency_cov: args.freq_cov,
            shape_nsd: args.shape_nsd,
        }
    };
    let mut solver = solver_for(model)?;
    let mut rng = ChaCha8Rng::seed_from_u64(args.seed);
    let modes = simulate_modes(model, &mut *solver, theta, args.modes, noise, &mut rng)?;
    Ok(modes)
}

/// The modal set of the simulated modes: the stated uncertainties (where positive) and, as
/// its source, the command line that reproduces it.
fn modal_set(
    args: &SimulateArgs,
    model: &Model,
    theta: &[f64],
    time: DateTime<Utc>,
    modes: &[SimulatedMode],
) -> ModalSet {
    let positive = |v: f64| (v > 0.0).then_some(v);
    ModalSet {
        structure: model.name.clone(),
        time,
        channels: model.channels().iter().map(|c| c.name.clone()).collect(),
        modes: modes
            .iter()
            .map(|m| MeasuredMode {
                frequency_hz: m.frequency_hz,
                frequency_cov: positive(args.freq_cov),
                shape: Some(m.shape.iter().map(|&v| Some(v)).collect()),
                shape_nsd: positive(args.shape_nsd),
                shape_std: None,
                damping_ratio: None,
                damping_std: None,
                label: None,
            })
            .collect(),
        temperature_c: None,
        source: Some(source(args, theta)),
        missing: Vec::new(),
        unexplained_peaks: Vec::new(),
        covariates: Default::default(),
    }
}

/// The `boltwatch simulate` command line (θ, seed, noise, injections) that made the set.
fn source(args: &SimulateArgs, theta: &[f64]) -> String {
    format!(
        "boltwatch simulate --theta {} --seed {}{}{}",
        theta
            .iter()
            .map(|v| v.to_string())
            .collect::<Vec<_>>()
            .join(","),
        args.seed,
        if args.noise_free { " --noise-free" } else { "" },
        args.inject
            .iter()
            .map(|i| format!(" --inject {i}"))
            .collect::<String>()
    )
}

/// Where the set went, then its frequencies, one mode a line.
fn print_modes(args: &SimulateArgs, model: &Model, modes: &[SimulatedMode]) {
    println!(
        "{} modes of `{}` written to {}",
        modes.len(),
        model.name,
        args.out.display()
    );
    println!("{:>4}  {:>12}", "mode", "f [Hz]");
    for (k, m) in modes.iter().enumerate() {
        println!("{:>4}  {:>12.4}", k + 1, m.frequency_hz);
    }
}
