//! `boltwatch replay REC.mcap [--config C] [-o OUT.mcap] [--resume]`: the tracker over a
//! recording ([`crate::io::replay`]), a progress bar on stderr, and a summary of the alerts
//! raised and the final stiffnesses on stdout.

use std::fmt::Write;
use std::path::PathBuf;

use anyhow::Result;
use indicatif::{ProgressBar, ProgressStyle};

use crate::contract::{Alert, AlertDetail, Estimate, rfc3339};

use crate::io::replay::{ReplayOptions, ReplaySummary, replay, with_suffix};
use crate::settings::Settings;

#[derive(Debug, clap::Args)]
pub struct ReplayArgs {
    /// Recording with `boltwatch/<structure>/modal` messages.
    pub recording: PathBuf,
    /// Configuration file on top of the bundled defaults.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Output recording (default: `<recording stem>.out.mcap` in the working directory).
    #[arg(short, long)]
    pub out: Option<PathBuf>,
    /// Checkpoint file (default: `OUT.checkpoint.json`).
    #[arg(long)]
    pub checkpoint: Option<PathBuf>,
    /// Go on from the checkpoint of an interrupted replay of the same recording.
    #[arg(long)]
    pub resume: bool,
}

pub fn run(args: &ReplayArgs) -> Result<()> {
    let settings = Settings::load(args.config.as_deref())?;
    super::init_logging(&settings.log)?;
    let out = args.out.clone().unwrap_or_else(|| {
        let stem = args
            .recording
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_else(|| "replay".into());
        PathBuf::from(format!("{stem}.out.mcap"))
    });
    let checkpoint = args
        .checkpoint
        .clone()
        .unwrap_or_else(|| with_suffix(&out, ".checkpoint.json"));
    let opts = ReplayOptions {
        recording: args.recording.clone(),
        out,
        checkpoint,
        resume: args.resume,
        settings,
    };
    let pb = ProgressBar::hidden();
    let mut started = false;
    let summary = replay(&opts, |done, total| {
        if !started {
            started = true;
            pb.set_draw_target(indicatif::ProgressDrawTarget::stderr());
            pb.set_length(total as u64);
            pb.set_position(done as u64 - 1);
            pb.set_style(
                ProgressStyle::with_template(
                    "replay {bar:40} {pos}/{len} sets {per_sec} ({eta} left)",
                )
                .expect("template"),
            );
        }
        pb.set_position(done as u64);
    })?;
    pb.finish_and_clear();
    print!("{}", summary_table(&opts, &summary));
    Ok(())
}

fn num(v: Option<f64>, digits: usize) -> String {
    v.filter(|x| x.is_finite())
        .map_or_else(|| "-".into(), |x| format!("{x:.digits$}"))
}

/// The human summary printed after a replay.
pub fn summary_table(opts: &ReplayOptions, s: &ReplaySummary) -> String {
    let mut t = String::new();
    write_run(&mut t, opts, s);
    write_alerts(&mut t, &s.alerts);
    for (name, est) in &s.last_estimate {
        write_final_stiffness(&mut t, name, est);
    }
    t
}

/// What the run read and wrote: the sets and readings replayed, the output, the windows
/// identified, each tracker's counters and the topics not read.
fn write_run(t: &mut String, opts: &ReplayOptions, s: &ReplaySummary) {
    if s.already_complete {
        let _ = writeln!(
            t,
            "{} was already replayed to the end; its outputs:",
            opts.recording.display()
        );
    }
    let _ = writeln!(
        t,
        "replayed {} modal sets{} of {} ({}{:.1} s, {:.0} inputs/s) -> {} ({} messages)",
        s.sets,
        match s.readings {
            0 => String::new(),
            n => format!(" and {n} environment readings"),
        },
        opts.recording.display(),
        s.resumed_from
            .map(|k| format!("resumed at set {k}, "))
            .unwrap_or_default(),
        s.seconds,
        s.processed as f64 / s.seconds.max(1e-9),
        opts.out.display(),
        s.outputs,
    );
    if s.windows > 0 {
        let _ = writeln!(
            t,
            "  of which {} identified from windows of raw data (accel blocks), published on …/modal",
            s.windows
        );
    }
    for (name, c) in &s.counters {
        let _ = writeln!(
            t,
            "  {name}: {} accepted, {} rejected, {} not converged, {} cold starts; {} cross-checks",
            c.accepted, c.rejected, c.unconverged, c.cold_starts, s.crosschecks
        );
    }
    for (topic, n) in &s.skipped_topics {
        let _ = writeln!(t, "  not read: {topic} ({n} messages)");
    }
}

/// The alerts raised, one row each (time, structure, connection, kind, drop, confidence),
/// or `none`.
fn write_alerts(t: &mut String, alerts: &[Alert]) {
    let _ = writeln!(t, "\nalerts ({}):", alerts.len());
    if alerts.is_empty() {
        let _ = writeln!(t, "  none");
        return;
    }
    let _ = writeln!(
        t,
        "  {:<24} {:<11} {:<16} {:<17} {:>7} {:>10}",
        "time", "structure", "connection", "kind / level", "drop", "confidence"
    );
    for a in alerts {
        let drop = match a.detail {
            AlertDetail::Loosening { drop, .. } => Some(drop),
            AlertDetail::Inadequacy { .. } => None,
        };
        let _ = writeln!(
            t,
            "  {:<24} {:<11} {:<16} {:<17} {:>7} {:>10}",
            rfc3339(a.time),
            a.structure,
            a.connection.as_deref().unwrap_or("(model)"),
            format!("{} {}", a.kind.as_str(), a.level.as_str()),
            drop.map_or_else(|| "-".into(), |d| format!("{:.1} %", 100.0 * d)),
            num(a.confidence, 3),
        );
    }
}

/// The last estimate of structure `name`: its time and ε, then one row per parameter
/// (θ, filtered level and band, baseline, change, stiffness).
fn write_final_stiffness(t: &mut String, name: &str, est: &Estimate) {
    let _ = writeln!(
        t,
        "\nfinal stiffness of {name} at {} (ε = {}, bound {}):",
        rfc3339(est.time),
        num(Some(est.epsilon), 1),
        num(Some(est.epsilon_bound), 1)
    );
    let _ = writeln!(
        t,
        "  {:<10} {:>8} {:>8} {:>17} {:>8} {:>8} {:>12}",
        "parameter", "θ", "filtered", "95 % band", "baseline", "change", "k_R·θ N·m/rad"
    );
    for p in &est.parameters {
        let f = &p.filtered;
        let _ = writeln!(
            t,
            "  {:<10} {:>8} {:>8} {:>17} {:>8} {:>8} {:>12}",
            p.name,
            num(Some(p.theta), 3),
            num(Some(f.level), 3),
            format!("[{}, {}]", num(Some(f.lower95), 3), num(Some(f.upper95), 3)),
            num(p.baseline, 3),
            f.change
                .map_or_else(|| "-".into(), |c| format!("{:+.1} %", 100.0 * c)),
            num(p.stiffness, 0),
        );
    }
}
