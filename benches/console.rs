//! The operator's console: the structure page of the space frame (28 connections, 30
//! parameters) with 10,000 estimates in its logged history, drawn server-side as the
//! daemon serves it, over every window; and the memory the history cache takes for them.
//!
//! The history is written by the daemon's own rolling log: a real estimate of the space
//! frame (the tracker on the healthy scenario, 15 modes) repeated every 6 minutes for
//! 10,000 sets (41.7 days), its levels varied and one connection losing 40 % from set 8,000.

use std::sync::{Arc, RwLock};
use std::time::{Duration, Instant};

use boltwatch::contract::{Estimate, Output};
use boltwatch::core::model::Model;
use boltwatch::core::model::spec::ModelSpec;
use boltwatch::daemon::console::{Console, Window};
use boltwatch::daemon::log::RollingLog;
use boltwatch::daemon::metrics::Shared;
use boltwatch::io::mcap::topic;
use boltwatch::pipeline::{Action, Tracker, TrackerConfig};
use boltwatch::scenario::Scenario;
use boltwatch::settings::ConsoleSettings;
use criterion::{Criterion, criterion_group, criterion_main};

const SETS: usize = 10_000;
const STRUCTURE: &str = "space-frame";

fn spec() -> ModelSpec {
    let path = format!(
        "{}/config/models/{STRUCTURE}.toml",
        env!("CARGO_MANIFEST_DIR")
    );
    toml::from_str(&std::fs::read_to_string(path).expect("shipped model")).expect("model parses")
}

/// A real estimate of the space frame: the tracker's after 25 sets of the healthy scenario.
fn real_estimate(spec: &ModelSpec, model: &Model) -> Estimate {
    let mut sc = Scenario::named("healthy", model, None, None).unwrap();
    sc.modes = 15;
    sc.sets = 25;
    sc.days = 25.0 * 0.006;
    let mut sets = Vec::new();
    sc.generate(spec, |_, set, _| {
        sets.push(serde_json::to_vec(&set.to_json()).unwrap());
        Ok(())
    })
    .unwrap();
    let config = TrackerConfig {
        crosscheck_every_sets: 0,
        crosscheck_every_s: 0.0,
        ..TrackerConfig::default()
    };
    let mut tracker = Tracker::new(model.clone(), config).unwrap();
    let mut last = None;
    for s in &sets {
        for a in tracker.handle(chrono::Utc::now(), s) {
            if let Action::Publish(Output::Estimate(e)) = a {
                last = Some(*e);
            }
        }
    }
    last.expect("the tracker estimated")
}

/// Estimate `i` of the history: `e` 6 minutes apart, levels varied, the first parameter
/// losing 40 % from set 8,000 on.
fn estimate_at(e: &Estimate, i: usize) -> Estimate {
    let mut e = e.clone();
    e.time += chrono::TimeDelta::seconds(360 * i as i64);
    for (l, p) in e.parameters.iter_mut().enumerate() {
        let wobble = 0.02 * ((i as f64) * 0.01 * (l + 1) as f64).sin();
        let drop = if l == 0 && i >= 8_000 { 0.4 } else { 0.0 };
        let level = 1.0 + wobble - drop;
        p.theta = level + 0.01 * ((i * 7 + l) as f64).cos();
        p.filtered.level = level;
        p.filtered.lower95 = level - 0.03;
        p.filtered.upper95 = level + 0.03;
    }
    e
}

/// The console over a log directory holding the 10,000 estimates, the last one noted; with
/// the log still open (its file being written) when `live`, else closed. Also the template
/// estimate.
fn console_with_history(
    dir: &std::path::Path,
    live: bool,
) -> (Arc<Console>, Option<RollingLog>, Estimate) {
    let spec = spec();
    let model = Model::from_spec(&spec).unwrap();
    let e = real_estimate(&spec, &model);
    assert_eq!(e.parameters.len(), 30);
    let log_dir = dir.join("log");
    let mut log =
        RollingLog::open(&log_dir, STRUCTURE, 64 << 20, Duration::from_secs(1 << 30)).unwrap();
    let key = topic(STRUCTURE, "stiffness");
    let mut last = None;
    for i in 0..SETS {
        let ei = estimate_at(&e, i);
        let ns = ei.time.timestamp_nanos_opt().unwrap() as u64;
        log.write(&key, ns, &serde_json::to_vec(&ei).unwrap())
            .unwrap();
        last = Some(ei);
    }
    let log = if live {
        log.sync().unwrap();
        Some(log)
    } else {
        let files = log.close().unwrap();
        println!(
            "history: {SETS} estimates in {} closed log files",
            files.len()
        );
        None
    };
    let shared = Shared::new(STRUCTURE, 64, 1 << 20, 1 << 20);
    let _ = shared.model.set(Arc::new((Some(spec), model)));
    shared.noted(&Output::Estimate(Box::new(last.unwrap())));
    let settings = ConsoleSettings {
        listen: String::new(),
        silent_after_s: 3600.0,
        cache_mib: 64,
        tls_cert: Default::default(),
        tls_key: Default::default(),
        users_file: Default::default(),
    };
    let console = Console::new(&settings, Arc::new(RwLock::new(vec![shared])), log_dir);
    (console, log, e)
}

/// The process's resident memory once the allocator has returned what is free, bytes.
fn resident() -> usize {
    boltwatch::release_free_memory();
    let status = std::fs::read_to_string("/proc/self/status").unwrap();
    let kb: usize = status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.split_whitespace().next()?.parse().ok())
        .unwrap();
    kb * 1024
}

fn bench_structure_page(c: &mut Criterion) {
    let dir = std::env::temp_dir().join(format!("bw-bench-console-{}", std::process::id()));
    let (console, _, _) = console_with_history(&dir.join("closed"), false);
    let before = resident();
    let start = Instant::now();
    let page = console.structure_page(STRUCTURE, Window::All).unwrap();
    let ms = start.elapsed().as_secs_f64() * 1e3;
    assert!(page.contains("<h2>The structure</h2>"));
    let html = page.len();
    drop(page);
    println!(
        "first page (reads the logs): {ms:.0} ms, {:.2} MB of HTML; history cache: {:.2} MB \
         by its count, resident memory +{:.2} MB after the page",
        html as f64 / 1e6,
        console.cache_bytes() as f64 / 1e6,
        resident().saturating_sub(before) as f64 / 1e6
    );
    let mut group = c.benchmark_group("console_space_frame_10000_sets");
    group.sample_size(20);
    for (name, window) in [
        ("all", Window::All),
        ("30d", Window::Month),
        ("24h", Window::Day),
    ] {
        group.bench_function(format!("structure_page_{name}"), |b| {
            b.iter(|| console.structure_page(STRUCTURE, window).unwrap())
        });
    }
    group.finish();
    let _ = std::fs::remove_dir_all(dir);
}

/// The page while its history's file is still being written: one estimate more before
/// each page, as a live page sees (the new messages are read, not the whole file again).
fn bench_live_page(c: &mut Criterion) {
    let dir = std::env::temp_dir().join(format!("bw-bench-live-{}", std::process::id()));
    let (console, log, e) = console_with_history(&dir, true);
    let mut log = log.unwrap();
    let start = Instant::now();
    console.structure_page(STRUCTURE, Window::All).unwrap();
    println!(
        "first page of a file being written (reads it all): {:.0} ms",
        start.elapsed().as_secs_f64() * 1e3
    );
    let key = topic(STRUCTURE, "stiffness");
    let mut i = SETS;
    c.bench_function(
        "console_space_frame_10000_sets/live_page_after_one_more_set",
        |b| {
            b.iter_custom(|iters| {
                let mut total = Duration::ZERO;
                for _ in 0..iters {
                    let ei = estimate_at(&e, i);
                    let ns = ei.time.timestamp_nanos_opt().unwrap() as u64;
                    log.write(&key, ns, &serde_json::to_vec(&ei).unwrap())
                        .unwrap();
                    log.sync().unwrap();
                    i += 1;
                    let start = Instant::now();
                    console.structure_page(STRUCTURE, Window::All).unwrap();
                    total += start.elapsed();
                }
                total
            })
        },
    );
    drop(log);
    let _ = std::fs::remove_dir_all(dir);
}

criterion_group!(benches, bench_structure_page, bench_live_page);
criterion_main!(benches);
