//! `boltwatch modes`: the lowest natural frequencies and mode shapes at the channels.

use std::path::PathBuf;

use anyhow::{Result, bail};
use serde_json::json;

use super::{ModelAtTheta, write_json};
use crate::core::modal::solver_for;

#[derive(Debug, clap::Args)]
pub struct ModesArgs {
    #[command(flatten)]
    pub at: ModelAtTheta,
    /// Number of modes.
    #[arg(short = 'n', long = "modes", default_value_t = 10)]
    pub n: usize,
    /// Output file (boltwatch.modes.v1).
    #[arg(short, long)]
    pub out: PathBuf,
}

pub fn run(args: &ModesArgs) -> Result<()> {
    let start = std::time::Instant::now();
    let (model, theta) = args.at.load()?;
    let assembled = start.elapsed().as_secs_f64();
    crate::core::numerics_for(&model);
    if args.n == 0 || args.n > model.n_dof() {
        bail!(
            "-n = {} must be between 1 and the model's {} DOFs",
            args.n,
            model.n_dof()
        );
    }
    let mut solver = solver_for(&model)?;
    let eig = solver.solve(&model, &theta, args.n)?;
    eprintln!(
        "{}: {} DOF assembled in {assembled:.2} s; {} modes ({} solver) in {:.2} s",
        model.name,
        model.n_dof(),
        args.n,
        if model.n_dof() >= crate::core::modal::SPARSE_FROM_DOF {
            "sparse shift-invert Krylov"
        } else {
            "dense"
        },
        start.elapsed().as_secs_f64() - assembled
    );
    let mut phi = vec![0.0; model.n_dof()];
    let mut shapes = Vec::with_capacity(args.n);
    for k in 0..args.n {
        for (i, v) in phi.iter_mut().enumerate() {
            *v = eig.phi[(i, k)];
        }
        shapes.push(
            model
                .channels()
                .iter()
                .map(|c| c.read(&phi))
                .collect::<Vec<f64>>(),
        );
    }
    let freqs: Vec<f64> = (0..args.n).map(|k| eig.frequency_hz(k)).collect();
    let out = json!({
        "schema": "boltwatch.modes.v1",
        "structure": model.name,
        "theta": theta,
        "normalization": "mass (φᵀMφ = 1), largest-magnitude DOF positive",
        "frequencies_hz": freqs,
        "channels": model.channels().iter().map(|c| c.name.clone()).collect::<Vec<_>>(),
        "shapes": shapes,
    });
    write_json(&args.out, &out)?;
    println!("{:>4}  {:>12}", "mode", "f [Hz]");
    for (k, f) in freqs.iter().enumerate() {
        println!("{:>4}  {:>12.4}", k + 1, f);
    }
    Ok(())
}
