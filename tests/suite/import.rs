//! Models from matrices (`boltwatch.matrices.v1`, issue 24): what `export-matrices` writes
//! reads back as the same model.

use std::path::{Path, PathBuf};
use std::process::Command;

use boltwatch::core::model::sparse::column_pairs;
use boltwatch::core::model::{Csc, Model};
use boltwatch::core::updating::{Evaluator, ModeMatching, ModeMatchingOptions};
use boltwatch::io::model::load_model;

use super::common::simulated_data;
use super::tracker::tmp_dir;

fn export(model: &Path, dir: &Path) -> PathBuf {
    let out = Command::new(env!("CARGO_BIN_EXE_boltwatch"))
        .args(["export-matrices", "--model"])
        .arg(model)
        .arg("-o")
        .arg(dir)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "export-matrices: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    dir.join("model.json")
}

/// The same matrix, entry for entry (an entry stored in one only must be zero), values bit
/// for bit (the export writes the lower triangle with 17 significant digits, and every
/// model's matrices are exactly symmetric).
fn same_matrix(a: &Csc, b: &Csc, what: &str) {
    assert_eq!((a.nrows(), a.ncols()), (b.nrows(), b.ncols()), "{what}");
    for j in 0..a.ncols() {
        for (i, x, y) in column_pairs(a, b, j) {
            assert!(
                x == y,
                "{what}: entry ({i}, {j}) is {x:e} in the model, {y:e} imported"
            );
        }
    }
}

/// Export, import and compare: the same DOFs, parameters, channels and matrices (bit for
/// bit: 17 significant digits read back exactly), the same 12 lowest frequencies (1e-10
/// relative; in fact identical), and for a model with channels the same mode-matching
/// update from θ0 = 1 on noisy simulated data (θ and σ to 1e-10 relative).
fn round_trip(name: &str) {
    let toml = PathBuf::from(format!(
        "{}/config/models/{name}.toml",
        env!("CARGO_MANIFEST_DIR")
    ));
    let dir = tmp_dir(&format!("import-{name}"));
    let json = export(&toml, &dir);
    // The file fits its schema (an independent validator).
    let instance: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let errors = super::common::schema_errors(
        include_str!(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/src/io/schemas/matrices.json"
        )),
        &instance,
    );
    assert!(
        errors.is_empty(),
        "{name}: model.json against its schema: {errors:?}"
    );
    let a = load_model(&toml).unwrap();
    let b = load_model(&json).unwrap();
    assert_eq!(a.name, b.name);
    assert_eq!(a.dof_labels(), b.dof_labels());
    assert_eq!(a.nominal_theta(), b.nominal_theta());
    let names = |m: &Model| {
        m.parameters()
            .iter()
            .map(|p| p.name.clone())
            .collect::<Vec<_>>()
    };
    assert_eq!(names(&a), names(&b));
    let chans = |m: &Model| {
        m.channels()
            .iter()
            .map(|c| (c.name.clone(), c.dofs.clone()))
            .collect::<Vec<_>>()
    };
    assert_eq!(chans(&a), chans(&b));
    same_matrix(a.k0(), b.k0(), "K0");
    for l in 0..a.n_params() {
        same_matrix(a.k_param(l), b.k_param(l), &format!("K_{l}"));
    }
    same_matrix(a.mass(), b.mass(), "M");

    let n_modes = 12.min(a.n_dof());
    let theta = a.nominal_theta();
    let fa = boltwatch::core::modal::solver_for(&a)
        .unwrap()
        .solve(&a, &theta, n_modes)
        .unwrap();
    let fb = boltwatch::core::modal::solver_for(&b)
        .unwrap()
        .solve(&b, &theta, n_modes)
        .unwrap();
    for k in 0..n_modes {
        let (x, y) = (fa.frequency_hz(k), fb.frequency_hz(k));
        assert!(
            ((x - y) / x).abs() <= 1e-10,
            "{name} mode {}: {x} Hz from the TOML, {y} Hz imported",
            k + 1
        );
    }

    if a.channels().is_empty() {
        return;
    }
    let truth: Vec<f64> = theta
        .iter()
        .enumerate()
        .map(|(l, t)| t * (0.9 + 0.02 * l as f64))
        .collect();
    let data = simulated_data(&a, &truth, 6.min(n_modes), 0.01, 0.05, true, 24);
    let start = vec![1.0; a.n_params()];
    let ra = ModeMatching::new(Evaluator::new(&a).unwrap())
        .run(&a, &data, &start, &ModeMatchingOptions::default())
        .unwrap();
    let rb = ModeMatching::new(Evaluator::new(&b).unwrap())
        .run(&b, &data, &start, &ModeMatchingOptions::default())
        .unwrap();
    for l in 0..a.n_params() {
        let (x, y) = (ra.theta[l], rb.theta[l]);
        assert!(
            ((x - y) / x).abs() <= 1e-10,
            "{name} θ{}: {x} vs {y}",
            l + 1
        );
        let (ca, cb) = (
            ra.covariance.as_ref().unwrap(),
            rb.covariance.as_ref().unwrap(),
        );
        let (sx, sy) = (ca[(l, l)].sqrt(), cb[(l, l)].sqrt());
        assert!(
            ((sx - sy) / sx).abs() <= 1e-10,
            "{name} σ{}: {sx} vs {sy}",
            l + 1
        );
    }
}

#[test]
fn exported_frame_models_import_as_the_same_model() {
    for name in [
        "lab-frame",
        "lab-frame-simplified",
        "cantilever-case1",
        "cantilever-case2",
        "cantilever-truth",
    ] {
        round_trip(name);
    }
}

/// The 31,458-DOF solid frame (sparse solver) through the same round trip.
#[test]
#[cfg_attr(
    not(feature = "slow-tests"),
    ignore = "slow tier: cargo test --features slow-tests"
)]
fn exported_solid_model_imports_as_the_same_model() {
    round_trip("four-bay-solid");
}

/// A broken `model.json` or a missing file: an error naming the file and the entry, exit
/// code 2 from a command.
#[test]
fn a_broken_matrices_directory_is_refused_naming_the_file() {
    let toml = format!(
        "{}/config/models/lab-frame.toml",
        env!("CARGO_MANIFEST_DIR")
    );
    let dir = tmp_dir("import-broken");
    let json = export(Path::new(&toml), &dir);
    let text = std::fs::read_to_string(&json).unwrap();
    let modes = |json: &Path| {
        Command::new(env!("CARGO_BIN_EXE_boltwatch"))
            .args(["modes", "--model"])
            .arg(json)
            .arg("-o")
            .arg(dir.join("modes.json"))
            .output()
            .unwrap()
    };
    let cases: Vec<(&str, String, &str)> = vec![
        (
            "dup-channel",
            text.replacen("\"channels\": [", "\"channels\": [{\"name\": \"x\", \"dofs\": [[0, 1.0]]}, {\"name\": \"x\", \"dofs\": [[1, 1.0]]},", 1),
            "channels[1].name: `x` is defined twice",
        ),
        (
            "range",
            text.replacen("\"channels\": [", "\"channels\": [{\"name\": \"far\", \"dofs\": [[100000, 1.0]]},", 1),
            "channels.far.dofs: DOF 100000 is out of range",
        ),
        (
            "missing",
            text.replacen("\"file\": \"K_", "\"file\": \"nowhere-K_", 1),
            "nowhere-K_",
        ),
        (
            "schema",
            text.replacen("boltwatch.matrices.v1", "boltwatch.matrices.v9", 1),
            "schema: expected \"boltwatch.matrices.v1\"",
        ),
    ];
    for (name, body, want) in cases {
        let p = dir.join(format!("{name}.json"));
        std::fs::write(&p, &body).unwrap();
        let out = modes(&p);
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{name}: {err}");
        assert!(err.contains(want), "{name}: {err}");
        assert!(
            err.contains(name) || err.contains("nowhere"),
            "{name}: the file is named: {err}"
        );
    }
}

/// `replay` with the lab frame imported from its exported matrices writes the same bytes
/// as with its TOML model file (estimates, cross-checks and the file itself).
#[test]
fn replay_with_the_imported_lab_frame_gives_the_same_bytes() {
    let dir = tmp_dir("import-replay");
    let toml = format!(
        "{}/config/models/lab-frame.toml",
        env!("CARGO_MANIFEST_DIR")
    );
    let json = export(Path::new(&toml), &dir.join("matrices"));
    let rec = dir.join("rec.mcap");
    super::tracker::make_scenario("healthy", 150, 3.0, &rec);
    let run = |model: &Path, name: &str| -> Vec<u8> {
        let cfg = dir.join(format!("{name}.toml"));
        std::fs::write(
            &cfg,
            format!(
                "[[structures]]\nname = \"lab-frame\"\nmodel = {:?}\n",
                model.to_str().unwrap()
            ),
        )
        .unwrap();
        let out = dir.join(format!("{name}.mcap"));
        let r = Command::new(env!("CARGO_BIN_EXE_boltwatch"))
            .env("BOLTWATCH__LOG__LEVEL", "warn")
            .env("BOLTWATCH__TRACKER__CROSSCHECK_EVERY_SETS", "50")
            .arg("replay")
            .arg(&rec)
            .arg("-o")
            .arg(&out)
            .arg("--config")
            .arg(&cfg)
            .output()
            .unwrap();
        assert!(
            r.status.success(),
            "replay with {}: {}",
            model.display(),
            String::from_utf8_lossy(&r.stderr)
        );
        std::fs::read(&out).unwrap()
    };
    let a = run(Path::new(&toml), "toml");
    let b = run(&json, "imported");
    let topics = |bytes: &[u8], dir: &Path, name: &str| {
        let p = dir.join(format!("{name}.check.mcap"));
        std::fs::write(&p, bytes).unwrap();
        boltwatch::io::mcap::read_all(&p)
            .unwrap()
            .into_iter()
            .map(|m| (m.topic, m.data))
            .collect::<Vec<_>>()
    };
    let (ma, mb) = (topics(&a, &dir, "a"), topics(&b, &dir, "b"));
    assert!(
        ma.iter().any(|(t, _)| t.ends_with("/crosscheck")),
        "cross-checks ran"
    );
    assert_eq!(ma.len(), mb.len());
    for (x, y) in ma.iter().zip(&mb) {
        assert_eq!(x.0, y.0);
        assert_eq!(
            String::from_utf8_lossy(&x.1),
            String::from_utf8_lossy(&y.1),
            "{}",
            x.0
        );
    }
    assert!(a == b, "the output files differ byte for byte");
}
