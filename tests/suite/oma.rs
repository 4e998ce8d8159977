//! Operational modal analysis (issue 26) on records simulated from the lab frame: the exact
//! truth is the model's modes.

use boltwatch::core::oma::ssi::{SsiOptions, identify_poles, mac_real};
use boltwatch::core::oma::stabilize::{Criteria, select_modes};
use boltwatch::core::oma::synth::{SynthOptions, accelerations};

use super::common::load_model;

/// 5 minutes of the lab frame's 42 channels at 1 kHz (its 11 modes below 400 Hz, 1 % modal
/// damping, white modal forces, 2 % sensor noise). SSI-COV (40 block rows: lags up to
/// 79 ms, 0.77 of the lowest mode's period; orders 2 … 80) with the automatic selection
/// finds every mode within 0.5 % in frequency, MAC ≥ 0.95 and damping within 30 %, and no
/// mode that is not there. Measured: frequencies within 1.02e-3 (the lowest mode; the
/// others 4.6e-4), damping within 5.7 %, MAC 1.0000, 11 modes (all 42 channels as
/// references: 9.5e-4 and 4.1 %). With 20 block rows (lags up to 0.38
/// of the lowest period) and 120 s the lowest mode came out 0.7 % high. 12 reference
/// channels chosen automatically (pivoted QR of R_0): 0.75 s for the identification, against
/// 4.7 s with all 42 as references (the same modes to the same accuracy).
#[test]
fn ssi_cov_finds_the_lab_frame_modes_from_simulated_accelerations() {
    let model = load_model("lab-frame");
    let theta = model.nominal_theta();
    let sim = accelerations(
        &model,
        &theta,
        &SynthOptions {
            rate_hz: 1000.0,
            duration_s: 300.0,
            damping: 0.01,
            max_frequency_hz: Some(400.0),
            noise_rel: 0.02,
            seed: 1,
            quantities: vec![],
        },
    )
    .unwrap();
    let started = std::time::Instant::now();
    let poles = identify_poles(
        &sim.record,
        &SsiOptions {
            block_rows: 40,
            order_max: 80,
            order_step: 2,
            references: vec![],
        },
    )
    .unwrap();
    let modes = select_modes(&poles, &Criteria::default());
    println!(
        "{} samples × {} channels: {} poles, {} modes selected in {:.2} s",
        sim.record.len(),
        sim.record.channels.len(),
        poles.poles.len(),
        modes.len(),
        started.elapsed().as_secs_f64()
    );
    for m in &modes {
        println!(
            "  {:9.4} Hz  ζ {:.4}  order {:3}  members {:3}  spread {:.1e}  MPC {:.3}",
            m.pole.frequency_hz, m.pole.damping, m.pole.order, m.members, m.frequency_spread, m.mpc
        );
    }
    for t in &sim.modes {
        let best = modes
            .iter()
            .map(|m| (m, mac_real(&m.shape, &t.shape)))
            .max_by(|a, b| a.1.total_cmp(&b.1));
        let Some((m, mac)) = best else {
            panic!("no mode found for {:.3} Hz", t.frequency_hz)
        };
        let df = m.pole.frequency_hz / t.frequency_hz - 1.0;
        let dz = m.pole.damping / t.damping - 1.0;
        println!(
            "true {:9.4} Hz: found {:9.4} Hz ({:+.2e}), ζ {:+.1} %, MAC {mac:.4}",
            t.frequency_hz,
            m.pole.frequency_hz,
            df,
            100.0 * dz
        );
        assert!(df.abs() <= 5e-3 && mac >= 0.95 && dz.abs() <= 0.3);
    }
    assert_eq!(modes.len(), sim.modes.len(), "spurious modes selected");
}

/// The reported σ of frequency and damping against the truth over independent noise
/// realisations of the lab frame record (each 120 s, 42 channels, 1 kHz, 1 % damping, 2 %
/// sensor noise): |error| < 2σ in 90–98 % of the (mode, realisation) cases, as a
/// calibrated normal σ gives 95 %. Measured: 97.1 % (frequency) and 96.9 % (damping) of 549
/// cases, one true mode left out by the noise rule.
#[test]
#[cfg_attr(
    not(feature = "slow-tests"),
    ignore = "slow tier: cargo test --features slow-tests"
)]
fn identified_sigmas_are_calibrated_by_monte_carlo() {
    use boltwatch::core::oma::identify::{IdentifyOptions, identify};
    let model = load_model("lab-frame");
    let theta = model.nominal_theta();
    let draws: u64 = 50;
    let (mut inside_f, mut inside_z, mut total) = (0, 0, 0);
    let mut missed = 0;
    for seed in 0..draws {
        let sim = accelerations(
            &model,
            &theta,
            &SynthOptions {
                rate_hz: 1000.0,
                duration_s: 120.0,
                damping: 0.01,
                max_frequency_hz: Some(400.0),
                noise_rel: 0.02,
                seed: 1000 + seed,
                quantities: vec![],
            },
        )
        .unwrap();
        let modes = identify(&sim.record, &IdentifyOptions::default()).unwrap();
        for t in &sim.modes {
            let Some(m) = modes
                .iter()
                .find(|m| (m.frequency_hz / t.frequency_hz - 1.0).abs() < 0.01)
            else {
                println!("realisation {seed}: {:.3} Hz not found", t.frequency_hz);
                missed += 1;
                continue;
            };
            total += 1;
            let zf = (m.frequency_hz - t.frequency_hz) / m.frequency_std;
            let zz = (m.damping - t.damping) / m.damping_std;
            inside_f += usize::from(zf.abs() < 2.0);
            inside_z += usize::from(zz.abs() < 2.0);
            if seed == 0 {
                println!(
                    "{:9.4} Hz: f error {:+.2}σ (σ_f/f {:.1e}), ζ error {:+.2}σ (σ_ζ/ζ {:.2})",
                    t.frequency_hz,
                    zf,
                    m.frequency_std / m.frequency_hz,
                    zz,
                    m.damping_std / m.damping
                );
            }
        }
    }
    let (pf, pz) = (
        inside_f as f64 / total as f64,
        inside_z as f64 / total as f64,
    );
    println!(
        "{draws} realisations, {total} modes found ({missed} missed): within 2σ frequency {:.1} %, damping {:.1} %",
        100.0 * pf,
        100.0 * pz
    );
    // The noise rule (σ_ζ ≥ ζ and σ_f/f ≥ 1 %) may leave out a true mode whose estimate
    // in a record is that poor: measured once in the 550 cases (0.2 %); allowed 1 %.
    assert!(missed * 100 <= total + missed, "{missed} missed");
    assert!((0.90..=0.98).contains(&pf), "frequency: {pf}");
    assert!((0.90..=0.98).contains(&pz), "damping: {pz}");
}

/// `boltwatch identify` on a CSV record written from a simulation (60 s of the lab frame,
/// split into two 30 s windows): each window's modal set passes the contract's validation
/// against the model and holds the true modes within 0.5 %, with their uncertainties.
/// A malformed record is refused with exit code 2, naming the file, line and column.
#[test]
fn identify_command_writes_valid_modal_sets() {
    use boltwatch::contract::modal_set::{ValidationContext, parse_modal_set};
    use std::process::Command;
    let model = load_model("lab-frame");
    let sim = accelerations(
        &model,
        &model.nominal_theta(),
        &SynthOptions {
            rate_hz: 1000.0,
            duration_s: 60.0,
            damping: 0.01,
            max_frequency_hz: Some(400.0),
            noise_rel: 0.02,
            seed: 5,
            quantities: vec![],
        },
    )
    .unwrap();
    let dir = std::env::temp_dir().join(format!("bw-oma-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let csv = dir.join("rec.csv");
    boltwatch::io::record::write_csv(&csv, &sim.record, 0.0).unwrap();
    std::fs::write(
        dir.join("rec.json"),
        r#"{"rate_hz": 1000, "unit": "m/s^2", "start": "2026-03-01T00:00:00Z"}"#,
    )
    .unwrap();
    let out = dir.join("sets.json");
    let toml = super::common::model_path("lab-frame");
    let run = Command::new(env!("CARGO_BIN_EXE_boltwatch"))
        .args(["identify", "--window", "30", "--input"])
        .arg(&csv)
        .arg("--model")
        .arg(&toml)
        .arg("-o")
        .arg(&out)
        .output()
        .unwrap();
    println!("{}", String::from_utf8_lossy(&run.stdout));
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let sets: Vec<serde_json::Value> =
        serde_json::from_str(&std::fs::read_to_string(&out).unwrap()).unwrap();
    assert_eq!(sets.len(), 2);
    let channels: Vec<String> = model.channels().iter().map(|c| c.name.clone()).collect();
    for set in &sets {
        let ctx = ValidationContext {
            structures: &["lab-frame"],
            model_channels: &channels,
            last_time: None,
            allow_equal_time: false,
            max_future: None,
        };
        let parsed = parse_modal_set(set.to_string().as_bytes(), &ctx).unwrap();
        for t in &sim.modes {
            let m = parsed
                .modes
                .iter()
                .find(|m| (m.frequency_hz / t.frequency_hz - 1.0).abs() < 5e-3)
                .unwrap_or_else(|| panic!("{:.3} Hz not found", t.frequency_hz));
            assert!(m.frequency_cov.is_some() && m.shape_std.is_some() && m.damping_std.is_some());
        }
    }
    // A malformed record.
    let bad = dir.join("bad.csv");
    std::fs::write(&bad, "time_s,a,b\n0,1,2\n0.001,1,x\n0.002,3,4\n").unwrap();
    let run = Command::new(env!("CARGO_BIN_EXE_boltwatch"))
        .args(["identify", "--input"])
        .arg(&bad)
        .arg("-o")
        .arg(dir.join("bad.json"))
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&run.stderr);
    assert_eq!(run.status.code(), Some(2), "{err}");
    assert!(
        err.contains("bad.csv: line 3, column 3 (`b`): `x` is not a number"),
        "{err}"
    );
}

/// Channels of mixed quantities: the lab frame's 42 channels read as accelerations (m/s²),
/// velocities (mm/s) and displacements (mm), a third each, written as CSV with a sidecar of
/// per-column `units`. Every mode comes out at its frequency (0.5 %) with its shape, brought
/// to acceleration entry by entry, at MAC ≥ 0.95 against the true shape; without the units
/// (every column taken as an acceleration) the velocity entries lie 90° out of phase and the
/// real shapes lose them (MAC below 0.9 on most modes), so the test shows the conversion
/// does the work. 120 s at 1 kHz, 1 % damping, 2 % noise; the displacement channels see the
/// upper modes ~ (f/f₁)² weaker, which the sensor noise of 2 % of each channel's RMS hides
/// partly: only the modes found in both runs are compared.
#[test]
fn channels_of_mixed_units_identify_together() {
    use boltwatch::core::oma::Quantity;
    use boltwatch::core::oma::identify::{IdentifyOptions, identify};
    let model = load_model("lab-frame");
    let r = model.channels().len();
    let quantities: Vec<Quantity> = (0..r)
        .map(|c| match c % 3 {
            0 => Quantity::Acceleration,
            1 => Quantity::Velocity,
            _ => Quantity::Displacement,
        })
        .collect();
    let sim = accelerations(
        &model,
        &model.nominal_theta(),
        &SynthOptions {
            rate_hz: 1000.0,
            duration_s: 120.0,
            damping: 0.01,
            max_frequency_hz: Some(400.0),
            noise_rel: 0.02,
            seed: 8,
            quantities: quantities.clone(),
        },
    )
    .unwrap();
    // Through CSV: velocities in mm/s, displacements in mm.
    let dir = std::env::temp_dir().join(format!("bw-oma-units-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let mut scaled = sim.record.clone();
    let units: Vec<&str> = quantities
        .iter()
        .enumerate()
        .map(|(c, q)| match q {
            Quantity::Acceleration => "m/s^2",
            Quantity::Velocity | Quantity::Displacement => {
                for k in 0..scaled.len() {
                    scaled.samples[(k, c)] *= 1e3;
                }
                if *q == Quantity::Velocity {
                    "mm/s"
                } else {
                    "mm"
                }
            }
        })
        .collect();
    let csv = dir.join("mixed.csv");
    boltwatch::io::record::write_csv(&csv, &scaled, 0.0).unwrap();
    std::fs::write(
        dir.join("mixed.json"),
        serde_json::json!({ "rate_hz": 1000, "units": units }).to_string(),
    )
    .unwrap();
    let read = boltwatch::io::record::read_csv(&csv).unwrap().record;
    assert_eq!(read.quantities, quantities);
    let opts = IdentifyOptions::default();
    let with_units = identify(&read, &opts).unwrap();
    let mut as_accel = read.clone();
    as_accel.quantities = vec![Quantity::Acceleration; r];
    let without = identify(&as_accel, &opts).unwrap();
    let _ = std::fs::remove_dir_all(&dir);
    let (mut compared, mut worse) = (0, 0);
    for t in &sim.modes {
        let near = |ms: &[boltwatch::core::oma::identify::IdentifiedMode]| {
            ms.iter()
                .find(|m| (m.frequency_hz / t.frequency_hz - 1.0).abs() < 5e-3)
                .map(|m| mac_real(&m.shape, &t.shape))
        };
        let (Some(good), Some(bad)) = (near(&with_units), near(&without)) else {
            println!("{:8.3} Hz: not found in both runs", t.frequency_hz);
            continue;
        };
        println!(
            "{:8.3} Hz: MAC {good:.4} with the units, {bad:.4} taken as accelerations",
            t.frequency_hz
        );
        assert!(good >= 0.95, "{:.3} Hz: MAC {good:.4}", t.frequency_hz);
        compared += 1;
        worse += usize::from(bad < 0.9);
    }
    assert!(compared >= 8, "only {compared} modes found in both runs");
    assert!(worse * 2 > compared, "the units made no difference");
}

/// The whole chain, accelerations → modal sets → θ → alerts: `scenario loosening --accel`
/// writes 20 bursts of 30 s of the lab frame's 42 channels at 500 Hz (its 5 modes below
/// 0.4 × 500 Hz simulated; 1 % damping, 2 % sensor noise), one every 3 days over 60 days, while
/// C1L@J1L loses 50 % from day 40 to day 50. `replay` identifies each burst (SSI-COV with
/// uncertainties), publishes the 20 modal sets on `modal`, tracks them (10 sets of
/// baseline), and raises the loosening alarm on C1L@J1L and no alert on any other
/// connection. The JSON Schema of the accel blocks validates them; a second replay gives the
/// same bytes (the identification is deterministic).
#[test]
fn accelerations_of_a_loosening_raise_the_alarm_on_the_right_connection() {
    use boltwatch::contract::Output;
    use std::process::Command;
    let dir = std::env::temp_dir().join(format!("bw-oma-chain-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let bin = || {
        let mut c = Command::new(env!("CARGO_BIN_EXE_boltwatch"));
        c.current_dir(env!("CARGO_MANIFEST_DIR"))
            .env("BOLTWATCH__LOG__LEVEL", "warn");
        c
    };
    let rec = dir.join("accel.mcap");
    let run = bin()
        .args(["scenario", "loosening", "--accel", "30", "--rate", "500"])
        .args(["--sets", "20", "--days", "60", "-o"])
        .arg(&rec)
        .output()
        .unwrap();
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let blocks = boltwatch::io::mcap::read_all(&rec).unwrap();
    let accel: Vec<_> = blocks
        .iter()
        .filter(|m| m.topic == "boltwatch/lab-frame/accel")
        .collect();
    assert_eq!(accel.len(), 20 * 30);
    let schema = boltwatch::io::schemas::for_topic("accel").unwrap().1;
    let first: serde_json::Value = serde_json::from_slice(&accel[0].data).unwrap();
    assert_eq!(
        super::common::schema_errors(schema, &first),
        Vec::<String>::new()
    );
    drop(blocks);
    let cfg = dir.join("chain.toml");
    std::fs::write(
        &cfg,
        "[tracker]\nbaseline_sets = 10\n[identify]\nwindow_s = 30.0\n",
    )
    .unwrap();
    let replay = |out: &std::path::Path| {
        let run = bin()
            .arg("replay")
            .arg(&rec)
            .arg("--config")
            .arg(&cfg)
            .arg("-o")
            .arg(out)
            .output()
            .unwrap();
        let stdout = String::from_utf8_lossy(&run.stdout).into_owned();
        assert!(
            run.status.success(),
            "{stdout}{}",
            String::from_utf8_lossy(&run.stderr)
        );
        stdout
    };
    let out = dir.join("out.mcap");
    println!("{}", replay(&out));
    let mut alarms = Vec::new();
    let mut others = Vec::new();
    let mut sets = 0;
    let mut modes = Vec::new();
    for m in boltwatch::io::mcap::read_all(&out).unwrap() {
        let suffix = m.topic.rsplit('/').next().unwrap();
        match Output::from_wire(suffix, &m.data).unwrap() {
            Output::Modal(s) => {
                sets += 1;
                let f: Vec<String> = s
                    .modes
                    .iter()
                    .map(|m| format!("{:.2}", m.frequency_hz))
                    .collect();
                println!("{}: {}", s.time, f.join(" "));
                modes.push(s.modes.len());
            }
            Output::Alert(a) if a.connection.as_deref() == Some("C1L@J1L") => {
                alarms.push(format!("{:?}", a.level))
            }
            Output::Alert(a) => others.push(a.message.clone()),
            Output::Rejected(r) => panic!("rejected: {}", r.reason),
            _ => {}
        }
    }
    assert_eq!(sets, 20);
    // The 5 simulated modes (9.7 … 179 Hz), and nothing else (the noise rule). Measured:
    // all 5 in 18 of the 20 windows; in two, one mode of poorly resolved damping and
    // frequency was left out as noise (and reported missing). Before the noise rule a
    // spurious mode came out in 4 windows of the 20.
    assert!(modes.iter().all(|&n| (4..=5).contains(&n)), "{modes:?}");
    assert!(modes.iter().filter(|&&n| n == 4).count() <= 2, "{modes:?}");
    assert!(alarms.iter().any(|l| l == "Alarm"), "{alarms:?}");
    assert!(others.is_empty(), "other alerts: {others:?}");
    let again = dir.join("again.mcap");
    replay(&again);
    assert!(
        std::fs::read(&out).unwrap() == std::fs::read(&again).unwrap(),
        "a second replay of the accel recording differs"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// A gap in the time column is named by its line in the file, comments and blank lines
/// counted.
#[test]
fn a_gap_is_named_by_its_line_in_the_file() {
    let dir = std::env::temp_dir().join(format!("bw-oma-gap-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let csv = dir.join("gap.csv");
    std::fs::write(
        &csv,
        "time_s,a\n# comment\n0,1\n\n0.001,2\n0.002,3\n0.005,4\n0.006,1\n",
    )
    .unwrap();
    let err = boltwatch::io::record::read_csv(&csv)
        .unwrap_err()
        .to_string();
    let _ = std::fs::remove_dir_all(&dir);
    assert!(err.contains("line 7 steps 3.000000e-3 s"), "{err}");
}

/// Against a reference SSI-COV a user could run instead: `tests/python/ssi_cov_reference.py`
/// (numpy only, written independently: its own covariances, stabilization and clustering,
/// references of largest variance, jackknife σ over 10 blocks), in a virtual environment
/// the test makes. On the 5-minute, 42-channel, 1 kHz lab-frame record both find the 11
/// modes, and every frequency agrees within twice the combined σ, which the two estimates
/// from the same data should (they differ by method, not by noise). Times, CSV parsing
/// included, are printed (the note quotes them; no assertion on times).
#[test]
fn boltwatch_and_a_numpy_ssi_cov_agree_on_the_lab_frame() {
    use std::process::Command;
    let python = super::common::python_venv("py-numpy-venv", "import numpy", &["numpy==2.2.6"]);
    let model = load_model("lab-frame");
    let sim = accelerations(
        &model,
        &model.nominal_theta(),
        &SynthOptions {
            rate_hz: 1000.0,
            duration_s: 300.0,
            damping: 0.01,
            max_frequency_hz: Some(400.0),
            noise_rel: 0.02,
            seed: 11,
            quantities: vec![],
        },
    )
    .unwrap();
    let dir = std::env::temp_dir().join(format!("bw-oma-numpy-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let csv = dir.join("lab.csv");
    boltwatch::io::record::write_csv(&csv, &sim.record, 0.0).unwrap();
    let ours = dir.join("boltwatch-modes.json");
    let started = std::time::Instant::now();
    let run = Command::new(env!("CARGO_BIN_EXE_boltwatch"))
        .args(["identify", "--input"])
        .arg(&csv)
        .arg("-o")
        .arg(&ours)
        .output()
        .unwrap();
    let t_ours = started.elapsed().as_secs_f64();
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let theirs = dir.join("numpy-modes.json");
    let started = std::time::Instant::now();
    let run = Command::new(&python)
        .arg(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/tests/python/ssi_cov_reference.py"
        ))
        .arg(&csv)
        .arg("--out")
        .arg(&theirs)
        .output()
        .unwrap();
    let t_theirs = started.elapsed().as_secs_f64();
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let ours: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&ours).unwrap()).unwrap();
    let theirs: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&theirs).unwrap()).unwrap();
    let _ = std::fs::remove_dir_all(&dir);
    println!(
        "boltwatch identify: {t_ours:.2} s; numpy SSI-COV: {t_theirs:.2} s (parse {:.2} s, identify {:.2} s)",
        theirs["seconds_parse"], theirs["seconds_identify"]
    );
    let reference: Vec<(f64, f64)> = theirs["modes"]
        .as_array()
        .unwrap()
        .iter()
        .map(|m| {
            (
                m["frequency_hz"].as_f64().unwrap(),
                m["frequency_std"].as_f64().unwrap(),
            )
        })
        .collect();
    let modes = ours["modes"].as_array().unwrap();
    assert_eq!(modes.len(), 11);
    assert_eq!(reference.len(), 11, "{reference:?}");
    for m in modes {
        let f = m["frequency_hz"].as_f64().unwrap();
        let s = f * m["frequency_cov"].as_f64().unwrap();
        let &(fr, sr) = reference
            .iter()
            .min_by(|a, b| (a.0 - f).abs().total_cmp(&(b.0 - f).abs()))
            .unwrap();
        let combined = (s * s + sr * sr).sqrt();
        println!(
            "{f:9.4} ± {s:.4} Hz vs numpy {fr:9.4} ± {sr:.4} Hz: {:+.2} combined σ",
            (f - fr) / combined
        );
        assert!((f - fr).abs() <= 2.0 * combined);
    }
}

/// Tracking across windows, with the model: three 60-s windows of the lab frame (42
/// channels, 1 kHz) where the middle one lacks the two modes above 300 Hz (simulated
/// without them). Every identified mode is named after the model's mode it is (`mode k`,
/// the true k: frequency within 0.5 %), the middle window lists `mode 10` and `mode 11` as
/// missing while the others keep their names, and the third window finds them again under
/// the same names.
#[test]
fn modes_keep_their_names_across_windows_and_dropouts_are_reported() {
    use std::process::Command;
    let model = load_model("lab-frame");
    let part = |max: f64, seed: u64| {
        accelerations(
            &model,
            &model.nominal_theta(),
            &SynthOptions {
                rate_hz: 1000.0,
                duration_s: 60.0,
                damping: 0.01,
                max_frequency_hz: Some(max),
                noise_rel: 0.02,
                seed,
                quantities: vec![],
            },
        )
        .unwrap()
    };
    let (a, b, c) = (part(400.0, 21), part(300.0, 22), part(400.0, 23));
    let truth: Vec<f64> = a.modes.iter().map(|m| m.frequency_hz).collect();
    assert_eq!(truth.len(), 11);
    let n = a.record.len();
    let mut rec = a.record.clone();
    rec.samples = faer::Mat::from_fn(3 * n, rec.channels.len(), |k, j| match k / n {
        0 => a.record.samples[(k, j)],
        1 => b.record.samples[(k - n, j)],
        _ => c.record.samples[(k - 2 * n, j)],
    });
    let dir = std::env::temp_dir().join(format!("bw-oma-track-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let csv = dir.join("three.csv");
    boltwatch::io::record::write_csv(&csv, &rec, 0.0).unwrap();
    let out = dir.join("sets.json");
    let run = Command::new(env!("CARGO_BIN_EXE_boltwatch"))
        .args(["identify", "--window", "60", "--input"])
        .arg(&csv)
        .arg("--model")
        .arg(super::common::model_path("lab-frame"))
        .arg("-o")
        .arg(&out)
        .output()
        .unwrap();
    println!("{}", String::from_utf8_lossy(&run.stdout));
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let sets: Vec<serde_json::Value> =
        serde_json::from_str(&std::fs::read_to_string(&out).unwrap()).unwrap();
    let _ = std::fs::remove_dir_all(&dir);
    assert_eq!(sets.len(), 3);
    for (w, set) in sets.iter().enumerate() {
        let mut names = Vec::new();
        for m in set["modes"].as_array().unwrap() {
            let label = m["label"].as_str().unwrap();
            let k: usize = label.strip_prefix("mode ").unwrap().parse().unwrap();
            let f = m["frequency_hz"].as_f64().unwrap();
            assert!(
                (f / truth[k - 1] - 1.0).abs() < 5e-3,
                "window {w}: {label} at {f:.3} Hz, the model's is {:.3}",
                truth[k - 1]
            );
            names.push(k);
        }
        let missing: Vec<&str> = set["missing"]
            .as_array()
            .map(|a| a.iter().map(|v| v.as_str().unwrap()).collect())
            .unwrap_or_default();
        if w == 1 {
            assert_eq!(names, (1..=9).collect::<Vec<_>>());
            assert_eq!(missing, ["mode 10", "mode 11"]);
        } else {
            assert_eq!(names, (1..=11).collect::<Vec<_>>());
            assert!(missing.is_empty(), "window {w}: {missing:?}");
        }
    }
}

/// `identify` reads an MCAP recording of accel blocks: two 30-s bursts of `scenario
/// --accel` give two modal sets with the five simulated modes named after the model's;
/// without `--window` the recording (two bursts, a gap between) is refused with exit code
/// 2, saying so.
#[test]
fn identify_reads_accel_recordings() {
    use std::process::Command;
    let dir = std::env::temp_dir().join(format!("bw-oma-mcap-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let bin = || {
        let mut c = Command::new(env!("CARGO_BIN_EXE_boltwatch"));
        c.current_dir(env!("CARGO_MANIFEST_DIR"));
        c
    };
    let rec = dir.join("two.mcap");
    let run = bin()
        .args(["scenario", "healthy", "--accel", "30", "--rate", "500"])
        .args(["--sets", "2", "--days", "1", "-o"])
        .arg(&rec)
        .output()
        .unwrap();
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let out = dir.join("sets.json");
    let run = bin()
        .args(["identify", "--window", "30", "--model"])
        .arg(super::common::model_path("lab-frame"))
        .arg("--input")
        .arg(&rec)
        .arg("-o")
        .arg(&out)
        .output()
        .unwrap();
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let sets: Vec<serde_json::Value> =
        serde_json::from_str(&std::fs::read_to_string(&out).unwrap()).unwrap();
    assert_eq!(sets.len(), 2);
    for s in &sets {
        let labels: Vec<&str> = s["modes"]
            .as_array()
            .unwrap()
            .iter()
            .map(|m| m["label"].as_str().unwrap())
            .collect();
        assert_eq!(labels, ["mode 1", "mode 2", "mode 3", "mode 4", "mode 5"]);
    }
    let run = bin()
        .args(["identify", "--input"])
        .arg(&rec)
        .arg("-o")
        .arg(dir.join("one.json"))
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&run.stderr).into_owned();
    let _ = std::fs::remove_dir_all(&dir);
    assert_eq!(run.status.code(), Some(2), "{err}");
    assert!(
        err.contains("gap of") && err.contains("give --window"),
        "{err}"
    );
}

/// `.npy` bytes (format 1.0) of a float64 array of `shape` in Fortran (column-major) order.
fn npy_fortran(shape: (usize, usize), column_major: &[f64]) -> Vec<u8> {
    let mut header = format!(
        "{{'descr': '<f8', 'fortran_order': True, 'shape': ({}, {}), }}",
        shape.0, shape.1
    );
    while (10 + header.len() + 1) % 64 != 0 {
        header.push(' ');
    }
    header.push('\n');
    let mut out = b"\x93NUMPY\x01\x00".to_vec();
    out.extend((header.len() as u16).to_le_bytes());
    out.extend(header.as_bytes());
    for v in column_major {
        out.extend(v.to_le_bytes());
    }
    out
}

/// A `.npy` record in Fortran order, its sidecar naming two of three columns (`null`
/// leaves the middle one out) in mixed units: the samples land in their rows and columns,
/// converted to SI. Without `rate_hz` the file is refused, saying the sidecar must give it.
#[test]
fn a_npy_record_reads_with_its_sidecar() {
    use boltwatch::core::oma::Quantity;
    let dir = std::env::temp_dir().join(format!("bw-oma-npy-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let npy = dir.join("rec.npy");
    // Column c, sample k: 10·c + k.
    let values: Vec<f64> = (0..3)
        .flat_map(|c| (0..4).map(move |k| (10 * c + k) as f64))
        .collect();
    std::fs::write(&npy, npy_fortran((4, 3), &values)).unwrap();
    let err = boltwatch::io::record::read_record(&npy)
        .unwrap_err()
        .to_string();
    assert!(err.contains("must give rate_hz"), "{err}");
    std::fs::write(
        dir.join("rec.json"),
        r#"{"rate_hz": 100, "units": ["mm/s", "g", "m/s^2"], "channels": ["a", null, "c"]}"#,
    )
    .unwrap();
    let rec = boltwatch::io::record::read_record(&npy).unwrap().record;
    let _ = std::fs::remove_dir_all(&dir);
    assert_eq!(rec.channels, ["a", "c"]);
    assert_eq!(rec.rate_hz, 100.0);
    assert_eq!(rec.quantities, [Quantity::Velocity, Quantity::Acceleration]);
    assert_eq!(rec.samples.nrows(), 4);
    for k in 0..4 {
        assert_eq!(rec.samples[(k, 0)], k as f64 * 1e-3);
        assert_eq!(rec.samples[(k, 1)], (20 + k) as f64);
    }
}

/// The measured bolted frame of pyOMA (`tests/data/pyoma-frame`, 5 channels of velocity
/// and acceleration at 256 Hz, 240 s, damping about 0.2 %): with default settings every
/// mode its authors list (their merged means over 15 setups) is found within 1 % in each
/// of the three setups, with MAC ≥ 0.95 against their shape at our channels, and no
/// prominent peak of the spectrum is left unexplained. 1 % and 0.95: the bars we hold to;
/// measured, the largest error is 0.16 % (setup 1, 1.2302 against 1.2283 Hz) and the
/// lowest MAC 0.979 (setup 3, the weakest mode at 13.86 Hz; ≥ 0.999 for the other ten).
#[test]
fn every_mode_the_authors_list_is_found_in_the_measured_frame() {
    use boltwatch::core::oma::identify::{IdentifyOptions, identify_all};
    let dir = format!("{}/tests/data/pyoma-frame", env!("CARGO_MANIFEST_DIR"));
    let authors: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(format!("{dir}/authors-modes.json")).unwrap(),
    )
    .unwrap();
    let merged: Vec<f64> = authors["merged"]
        .as_array()
        .unwrap()
        .iter()
        .map(|m| m["frequency_hz"].as_f64().unwrap())
        .collect();
    assert_eq!(merged.len(), 11);
    let shapes: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(format!("{dir}/authors-shapes.json")).unwrap(),
    )
    .unwrap();
    let shapes = shapes["modes"].as_array().unwrap();
    assert_eq!(shapes.len(), 11);
    for setup in 1..=3 {
        let path = std::path::PathBuf::from(format!("{dir}/setup{setup}/record.npy"));
        let record = boltwatch::io::record::read_record(&path).unwrap().record;
        let found = identify_all(&record, &IdentifyOptions::default()).unwrap();
        for &f in &merged {
            let m = found
                .modes
                .iter()
                .min_by(|a, b| {
                    let e = |m: &&boltwatch::core::oma::identify::IdentifiedMode| {
                        (m.frequency_hz / f - 1.0).abs()
                    };
                    e(a).total_cmp(&e(b))
                })
                .unwrap();
            let best = m.frequency_hz;
            println!(
                "setup {setup}: authors {f:.4} Hz, ours {best:.4} Hz ({:+.3} %), σ_f {:.4} Hz, \
                 ζ {:.3} % ± {:.3} %",
                100.0 * (best / f - 1.0),
                m.frequency_std,
                100.0 * m.damping,
                100.0 * m.damping_std
            );
            assert!((best / f - 1.0).abs() < 0.01, "setup {setup}: {f:.4} Hz");
            let theirs = shapes
                .iter()
                .min_by(|a, b| {
                    let e = |v: &serde_json::Value| (v["frequency_hz"].as_f64().unwrap() - f).abs();
                    e(a).total_cmp(&e(b))
                })
                .unwrap();
            let theirs: Vec<f64> = theirs[format!("setup{setup}")]
                .as_array()
                .unwrap()
                .iter()
                .map(|v| v.as_f64().unwrap())
                .collect();
            let mac = mac_real(&m.shape, &theirs);
            println!("setup {setup}: {f:.4} Hz, MAC {mac:.4} with the authors' shape");
            assert!(mac >= 0.95, "setup {setup}: {f:.4} Hz, MAC {mac:.3}");
            // The setups, measured one after another, agree on every frequency within
            // 0.2 %: a σ_f above 0.5 % of it is not the uncertainty of this record.
            assert!(
                m.frequency_std < 0.005 * f,
                "setup {setup}: σ_f of {best:.4} Hz"
            );
        }
        assert!(
            found.unexplained_peaks.is_empty(),
            "setup {setup}: {:?}",
            found.unexplained_peaks
        );
        if setup == 2 {
            stabilization_diagram_is_written(&found);
        }
    }
}

/// `identify --plot`: the PNG, the SVG and the poles behind them, one CSV row per pole with
/// what the selection made of it; the SVG names both axes and every kind of pole.
fn stabilization_diagram_is_written(found: &boltwatch::core::oma::identify::Identification) {
    let dir = std::env::temp_dir().join(format!("bw-oma-plot-{}", std::process::id()));
    boltwatch::commands::identify_plot::write(&dir, "stab", found).unwrap();
    let png = std::fs::read(dir.join("stab.png")).unwrap();
    assert_eq!(&png[1..4], b"PNG");
    let svg = std::fs::read_to_string(dir.join("stab.svg")).unwrap();
    for text in [
        "Model order",
        "Frequency (Hz)",
        "pole of a chosen mode",
        "unstable pole",
    ] {
        assert!(svg.contains(text), "the SVG lacks {text:?}");
    }
    let csv = std::fs::read_to_string(dir.join("stab-poles.csv")).unwrap();
    let _ = std::fs::remove_dir_all(&dir);
    let poles: usize = found.bands.iter().map(|b| b.poles.poles.len()).sum();
    assert_eq!(csv.lines().count(), poles + 1);
    let in_modes = csv
        .lines()
        .filter(|l| l.contains(",mode,") || l.contains(",noise,"))
        .count();
    let members: usize = found
        .bands
        .iter()
        .flat_map(|b| &b.selection.modes)
        .map(|m| m.members)
        .sum();
    assert_eq!(in_modes, members);
}

/// Six channels, 0.2 % damping, nine modes from 1.1 to 14.6 Hz (two pairs 4 % apart), 240 s
/// at 256 Hz, 2 % sensor noise: the settings the record gives find every mode within 0.5 %
/// in frequency and with MAC ≥ 0.95, and nothing else. 0.5 %: the bar we hold to; the
/// frequency resolution of 240 s is 1/240 Hz, 0.4 % of the lowest mode.
#[test]
fn few_channels_and_light_damping_give_every_mode() {
    use boltwatch::core::oma::identify::{IdentifyOptions, identify_all};
    let sim = boltwatch::core::oma::synth::light_damping_frame();
    let found = identify_all(&sim.record, &IdentifyOptions::default()).unwrap();
    for b in &found.settings.bands {
        println!("{b:?}");
    }
    for m in &found.modes {
        println!(
            "{:8.4} ± {:.4} Hz, ζ {:.3} ± {:.3} %",
            m.frequency_hz,
            m.frequency_std,
            100.0 * m.damping,
            100.0 * m.damping_std
        );
    }
    for t in &sim.modes {
        let m = found
            .modes
            .iter()
            .find(|m| (m.frequency_hz / t.frequency_hz - 1.0).abs() < 0.005)
            .unwrap_or_else(|| panic!("{:.2} Hz not found", t.frequency_hz));
        let mac = mac_real(&m.shape, &t.shape);
        assert!(mac >= 0.95, "{:.2} Hz: MAC {mac:.3}", t.frequency_hz);
    }
    assert_eq!(found.modes.len(), sim.modes.len(), "spurious modes");
}

/// The 5-minute, 42-channel lab-frame record (as above) through `identify` with the
/// settings it gives (48 block rows, orders to 88, no decimation, one band): every mode
/// within 0.5 % and MAC ≥ 0.95, no unexplained peak, and nothing else.
#[test]
#[cfg_attr(
    not(feature = "slow-tests"),
    ignore = "slow tier: cargo test --features slow-tests"
)]
fn the_lab_frame_record_gives_its_modes_and_nothing_else_with_derived_settings() {
    use boltwatch::core::oma::identify::{IdentifyOptions, identify_all};
    let model = load_model("lab-frame");
    let sim = accelerations(
        &model,
        &model.nominal_theta(),
        &SynthOptions {
            rate_hz: 1000.0,
            duration_s: 300.0,
            damping: 0.01,
            max_frequency_hz: Some(400.0),
            noise_rel: 0.02,
            seed: 1,
            quantities: vec![],
        },
    )
    .unwrap();
    let found = identify_all(&sim.record, &IdentifyOptions::default()).unwrap();
    println!("{:?}", found.settings.bands);
    for t in &sim.modes {
        let m = found
            .modes
            .iter()
            .find(|m| (m.frequency_hz / t.frequency_hz - 1.0).abs() < 0.005)
            .unwrap_or_else(|| panic!("{:.3} Hz not found", t.frequency_hz));
        assert!(
            mac_real(&m.shape, &t.shape) >= 0.95,
            "{:.3} Hz",
            t.frequency_hz
        );
    }
    let extra: Vec<f64> = found.modes.iter().map(|m| m.frequency_hz).collect();
    assert_eq!(found.modes.len(), sim.modes.len(), "modes {extra:?}");
    assert!(
        found.unexplained_peaks.is_empty(),
        "{:?}",
        found.unexplained_peaks
    );
}
