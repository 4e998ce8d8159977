//! The command line end to end: simulate → update, and bad input → exit 2 naming the field.

use std::process::Command;

use super::common::model_path;

fn boltwatch(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_boltwatch"))
        .args(args)
        .output()
        .expect("binary runs")
}

fn tmp(name: &str) -> std::path::PathBuf {
    let dir = std::env::temp_dir().join(format!("boltwatch-cli-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

/// `boltwatch update --model M --data D -o OUT [extra…]`.
fn update(model: &str, data: &str, out: &std::path::Path, extra: &[&str]) -> std::process::Output {
    let mut args = vec![
        "update",
        "--model",
        model,
        "--data",
        data,
        "-o",
        out.to_str().unwrap(),
    ];
    args.extend_from_slice(extra);
    boltwatch(&args)
}

/// Noise-free data at a truth, updated from nominal θ: θ recovered to 1e-6 relative (as the
/// recovery test), and the result carries the `boltwatch.update.v1` fields.
#[test]
fn simulate_then_update_recovers_theta() {
    let model = model_path("lab-frame");
    let data = tmp("data.json");
    let out = tmp("result.json");
    let truth = "0.8,1.6,0.7,1.2,0.5,1.1,2.5,0.9,1.4,0.6,1.8,0.75,1.3,0.55,1.05,2.2,0.95";
    let s = boltwatch(&[
        "simulate",
        "--model",
        &model,
        "--theta",
        truth,
        "--noise-free",
        "-o",
        data.to_str().unwrap(),
    ]);
    assert!(s.status.success(), "{}", String::from_utf8_lossy(&s.stderr));
    let u = update(&model, data.to_str().unwrap(), &out, &[]);
    assert!(u.status.success(), "{}", String::from_utf8_lossy(&u.stderr));
    let stdout = String::from_utf8_lossy(&u.stdout);
    assert!(
        stdout.contains("C2R@J1R") && stdout.contains("MAC"),
        "{stdout}"
    );
    let result: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&out).unwrap()).unwrap();
    assert_eq!(result["schema"], "boltwatch.update.v1");
    assert_eq!(result["converged"], true);
    let params = result["parameters"].as_array().unwrap();
    assert_eq!(params.len(), 17);
    for (p, t) in params.iter().zip(truth.split(',')) {
        let t: f64 = t.parse().unwrap();
        let th = p["theta"].as_f64().unwrap();
        assert!((th - t).abs() / t < 1e-6, "{}: {th} vs {t}", p["name"]);
        assert!(p["std"].as_f64().unwrap() > 0.0);
    }
    assert_eq!(result["modes"].as_array().unwrap().len(), 9);
    assert_eq!(result["modes"][0]["paired_with"], 1);
}

/// A rejected modal set: exit code 2, one line on stderr naming the offending field.
#[test]
fn rejected_modal_set_exits_2_naming_the_field() {
    let model = model_path("lab-frame");
    let data = tmp("bad.json");
    std::fs::write(
        &data,
        r#"{"schema": "boltwatch.modal_set.v1", "structure": "lab-frame", "time": "2026-11-21T10:00:00Z",
            "channels": ["C1L.1", "NOPE.3"],
            "modes": [{"frequency_hz": 9.7, "frequency_cov": 0.01, "shape": [0.1, 0.2], "shape_nsd": 0.05}]}"#,
    )
    .unwrap();
    let u = update(&model, data.to_str().unwrap(), &tmp("r.json"), &[]);
    assert_eq!(u.status.code(), Some(2));
    let err = String::from_utf8_lossy(&u.stderr);
    assert!(
        err.contains("channels[1]") && err.contains("NOPE.3"),
        "{err}"
    );
    assert_eq!(err.trim().lines().count(), 1, "{err}");
}

/// A θ0 of the wrong length is refused with the parameter count.
#[test]
fn wrong_theta0_length_exits_2() {
    let model = model_path("lab-frame");
    let data = format!(
        "{}/recordings/lab-frame-modal-set.json",
        env!("CARGO_MANIFEST_DIR")
    );
    let u = update(&model, &data, &tmp("r2.json"), &["--theta0", "1,1"]);
    assert_eq!(u.status.code(), Some(2));
    let err = String::from_utf8_lossy(&u.stderr);
    assert!(
        err.contains("--theta0") && err.contains("17 parameters"),
        "{err}"
    );
}
