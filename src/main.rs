//! The `boltwatch` command line: parses arguments, runs a command, maps errors to exit codes.

use std::process::ExitCode;

use boltwatch::commands::{
    diagnose, export, fleet, identify, modes, normalisation, plan, publish, replay, report, router,
    run, scenario, simulate, sweep, update,
};
use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(
    name = "boltwatch",
    version,
    about = "Bolted-connection stiffness monitoring by FE model updating"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Write a modal set simulated from a model at θ, with noise.
    Simulate(simulate::SimulateArgs),
    /// Write the lowest natural frequencies and mode shapes at the channels.
    Modes(modes::ModesArgs),
    /// Update the model's parameters to a modal set.
    Update(update::UpdateArgs),
    /// The σ_c study of the Bayesian MAP (paper Figs. 5, 7, 15, 18): JSON and an SVG plot.
    SweepSigma(sweep::SweepArgs),
    /// Find where the model and a modal set disagree, name the missing effect, add it.
    Diagnose(diagnose::DiagnoseArgs),
    /// Write a synthetic monitoring recording (MCAP): healthy, loosening, sudden, mass or
    /// seasonal.
    Scenario(scenario::ScenarioArgs),
    /// Run the tracker over a recording (MCAP) as fast as possible; outputs into an MCAP file.
    Replay(replay::ReplayArgs),
    /// Plot a replay's outputs: stiffness histories with bands and alerts, frequencies, ε.
    Report(report::ReportArgs),
    /// The daemon: track the configured structures live over Zenoh (Zenoh and a rolling
    /// MCAP log out), until SIGINT or SIGTERM.
    Run(run::RunArgs),
    /// A Zenoh router keeping the fleet's state in a replicated storage (Zenoh's storage
    /// manager), until SIGINT or SIGTERM.
    Router(router::RouterArgs),
    /// The fleet as the network sees it: members, each structure's owner, epoch and lag.
    #[command(subcommand)]
    Fleet(fleet::FleetCommand),
    /// Publish a recording's modal sets over Zenoh (a field simulator for demos and tests).
    Publish(publish::PublishArgs),
    /// Write a model's K0, K_l and M (Matrix Market) and its DOFs and channels, for other tools.
    ExportMatrices(export::ExportArgs),
    /// Identify modal sets, with uncertainties, from a raw vibration record (SSI-COV).
    Identify(identify::IdentifyArgs),
    /// Before installing: which connections the channels and modes let the tracker watch,
    /// the smallest loosening each will catch, and which sensors to add.
    Plan(plan::PlanArgs),
    /// What a tracker learned of its structure's seasons (show), or learn it again from a
    /// recording between two times (learn).
    #[command(subcommand)]
    Normalisation(normalisation::NormalisationCommand),
}

fn main() -> ExitCode {
    boltwatch::no_transparent_huge_pages();
    let cli = Cli::parse();
    boltwatch::core::sequential_numerics();
    let result = match &cli.command {
        Command::Simulate(a) => simulate::run(a),
        Command::Modes(a) => modes::run(a),
        Command::Update(a) => update::run(a),
        Command::SweepSigma(a) => sweep::run_sweep(a),
        Command::Diagnose(a) => diagnose::run(a),
        Command::Scenario(a) => scenario::run(a),
        Command::Replay(a) => replay::run(a),
        Command::Report(a) => report::run(a),
        Command::Run(a) => run::run(a),
        Command::Router(a) => router::run(a),
        Command::Fleet(a) => fleet::run(a),
        Command::Publish(a) => publish::run(a),
        Command::ExportMatrices(a) => export::run(a),
        Command::Identify(a) => identify::run(a),
        Command::Normalisation(a) => normalisation::run(a),
        Command::Plan(a) => plan::run(a),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::from(2)
        }
    }
}
