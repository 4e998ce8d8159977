//! Peak memory of whole processes (issue 27, item 4): `modes -n 12`, `update` (mode
//! matching) and `update --method bayesian` (the MAP the daemon's cross-check runs, with
//! its covariance and the mode-matching comparison) on the lab frame and the four-bay
//! solid frame, each the peak resident set (`VmHWM`) of the command, read every 10 ms
//! while it runs. Figures, not assertions (the tests assert the bounds): `cargo bench
//! --bench memory`.

use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// Peak RSS (MiB) and wall time of `args` run to completion, from `wait4`'s resource usage
/// of that child. Its `ru_maxrss` also counts this process's RSS at the fork, a few MiB
/// here (it would not be in a test binary holding large models, which polls `VmHWM`
/// instead); polling would miss the lab frame's commands, done in milliseconds.
fn peak(bin: &str, args: &[&str]) -> (f64, Duration) {
    let start = Instant::now();
    // Reaped by wait4 below, which gives its resource usage, not by Child::wait.
    #[allow(clippy::zombie_processes)]
    let child = Command::new(bin)
        .args(args)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("boltwatch starts");
    let pid = child.id() as i32;
    let mut status = 0;
    // SAFETY: a zeroed rusage is a valid value for wait4 to fill.
    let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
    // SAFETY: pid is our own child, not yet waited for; the pointers are to live locals.
    let r = unsafe { libc::wait4(pid, &mut status, 0, &mut usage) };
    assert_eq!(r, pid, "wait4");
    assert!(
        libc::WIFEXITED(status) && libc::WEXITSTATUS(status) == 0,
        "boltwatch {args:?} failed"
    );
    (usage.ru_maxrss as f64 / 1024.0, start.elapsed())
}

fn main() {
    let bin = env!("CARGO_BIN_EXE_boltwatch");
    let root = env!("CARGO_MANIFEST_DIR");
    let dir = std::env::temp_dir().join(format!("bw-bench-memory-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temporary directory");
    let s = |p: &Path| p.to_str().expect("UTF-8 path").to_string();
    let cases = [
        (
            "lab-frame",
            "0.8,1.6,0.7,1.2,0.5,1.1,2.5,0.9,1.4,0.6,1.8,0.75,1.3,0.55,1.05,2.2,0.95",
            "9",
        ),
        ("four-bay-solid", "0.36,0.36,0.36,0.5", "6"),
    ];
    println!(
        "{:<16} {:<44} {:>10} {:>9}",
        "model", "command", "peak MiB", "wall s"
    );
    for (name, theta, modes) in cases {
        let model = format!("{root}/config/models/{name}.toml");
        let data = s(&dir.join(format!("{name}.json")));
        let out = s(&dir.join("out.json"));
        let (_, _) = peak(
            bin,
            &[
                "simulate",
                "--model",
                &model,
                "--theta",
                theta,
                "--modes",
                modes,
                "--freq-cov",
                "0.005",
                "--seed",
                "1",
                "-o",
                &data,
            ],
        );
        let commands: [(&str, Vec<&str>); 3] = [
            (
                "modes -n 12",
                vec!["modes", "--model", &model, "-n", "12", "-o", &out],
            ),
            (
                "update (mode matching)",
                vec!["update", "--model", &model, "--data", &data, "-o", &out],
            ),
            (
                "update --method bayesian --sigma-c 1e3",
                vec![
                    "update",
                    "--method",
                    "bayesian",
                    "--sigma-c",
                    "1e3",
                    "--no-tsvd",
                    "--model",
                    &model,
                    "--data",
                    &data,
                    "-o",
                    &out,
                ],
            ),
        ];
        for (label, args) in commands {
            let (mib, t) = peak(bin, &args);
            println!(
                "{name:<16} {label:<44} {mib:>10.0} {:>9.2}",
                t.as_secs_f64()
            );
        }
    }
}
