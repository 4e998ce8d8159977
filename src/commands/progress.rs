//! Progress on stderr for long commands: spinners, and one line per iteration (printed as
//! lines when stderr is not a terminal, so a log can follow a long run).

use indicatif::ProgressBar;

/// A spinner with `msg`.
pub fn spinner(msg: String) -> ProgressBar {
    let pb = ProgressBar::new_spinner();
    pb.set_message(msg);
    pb.enable_steady_tick(std::time::Duration::from_millis(120));
    pb
}

/// A spinner on stderr for an iterative update, its message replaced at every iterate
/// (hidden when stderr is not a terminal).
pub fn iteration_progress(what: &str) -> indicatif::ProgressBar {
    let pb = indicatif::ProgressBar::new_spinner();
    pb.set_style(
        indicatif::ProgressStyle::with_template("{spinner} {prefix} [{elapsed}] {msg}")
            .expect("valid template"),
    );
    pb.set_prefix(what.to_string());
    pb.enable_steady_tick(std::time::Duration::from_millis(120));
    pb
}

/// Shows an iteration's line on `bar`; without a terminal (a log file, a service) the bar
/// is hidden, so the line goes to stderr instead and a long run can still be followed.
pub fn progress_line(bar: &indicatif::ProgressBar, line: String) {
    if bar.is_hidden() {
        eprintln!("{line}");
    }
    bar.set_message(line);
}

/// θ as `(0.3600, 1.0000, …)`.
pub fn fmt_theta(theta: &[f64]) -> String {
    let v: Vec<String> = theta.iter().map(|t| format!("{t:.4}")).collect();
    format!("({})", v.join(", "))
}
