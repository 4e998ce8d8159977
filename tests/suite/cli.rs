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

/// Cantilever data (paper §2.7): `cantilever-truth` at θ = 0.5, 4 modes, 1 % CoV and NSD,
/// with noise (seed 27), written by `simulate`.
fn cantilever_data(name: &str) -> std::path::PathBuf {
    let data = tmp(name);
    let s = boltwatch(&[
        "simulate",
        "--model",
        &model_path("cantilever-truth"),
        "--theta",
        "0.5",
        "--modes",
        "4",
        "--freq-cov",
        "0.01",
        "--shape-nsd",
        "0.01",
        "--seed",
        "27",
        "-o",
        data.to_str().unwrap(),
    ]);
    assert!(s.status.success(), "{}", String::from_utf8_lossy(&s.stderr));
    data
}

fn read_json(path: &std::path::Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
}

/// `update --method bayesian` on cantilever case I at σ_c = 1e4, by both solvers: the
/// result carries the Bayesian fields of the contract, both solvers reach the same θ (1e-6
/// relative) and J_p (1e-9), Newton in under 100 iterations.
#[test]
fn bayesian_update_both_solvers_agree() {
    let data = cantilever_data("cant-bayes.json");
    let model = model_path("cantilever-case1");
    let run = |solver: &str, out: &str, extra: &[&str]| {
        let out = tmp(out);
        let mut args = vec![
            "--method",
            "bayesian",
            "--sigma-c",
            "1e4",
            "--solver",
            solver,
        ];
        args.extend_from_slice(extra);
        let u = update(&model, data.to_str().unwrap(), &out, &args);
        assert!(u.status.success(), "{}", String::from_utf8_lossy(&u.stderr));
        read_json(&out)
    };
    let newton = run("newton", "cant-newton.json", &[]);
    let alt = run(
        "alternating",
        "cant-alt.json",
        &["--max-iter", "20000", "--no-tsvd"],
    );
    for r in [&newton, &alt] {
        assert_eq!(r["schema"], "boltwatch.update.v1");
        assert_eq!(r["method"], "bayesian");
        assert_eq!(r["converged"], true, "{}", r["solver"]);
        let b = &r["bayesian"];
        assert_eq!(b["sigma_c"], 1e4);
        for key in ["J_p", "measurement_misfit", "modelling_error", "misfit_dof"] {
            assert!(b[key].as_f64().unwrap().is_finite(), "{key}");
        }
        assert!(r["epsilon"].as_f64().unwrap() > 0.0);
        let modes = r["modes"].as_array().unwrap();
        assert_eq!(modes.len(), 4);
        for m in modes {
            assert!(m["mac_most_probable_to_measured"].as_f64().unwrap() > 0.9);
            assert!(m["most_probable_lambda"].as_f64().unwrap() > 0.0);
        }
        assert!(r["parameters"][0]["sampling_std"].as_f64().unwrap() > 0.0);
    }
    assert!(newton["iterations"].as_u64().unwrap() < 100);
    assert!(alt["iterations"].as_u64().unwrap() > newton["iterations"].as_u64().unwrap());
    let t = |r: &serde_json::Value| r["parameters"][0]["theta"].as_f64().unwrap();
    let j = |r: &serde_json::Value| r["bayesian"]["J_p"].as_f64().unwrap();
    assert!((t(&newton) - t(&alt)).abs() <= 1e-6 * t(&newton));
    assert!((j(&newton) - j(&alt)).abs() <= 1e-9 * j(&newton));
    let tsvd = &newton["bayesian"]["tsvd"];
    assert!(tsvd["s_tol"].as_f64().unwrap() > 0.0);
    assert!(!tsvd["l_curve"].as_array().unwrap().is_empty());
    assert!(alt["bayesian"]["tsvd"].is_null());
}

/// `update --method bayesian --sigma-c auto` without a terminal (stderr to a pipe): each
/// trial of the σ_c search is reported as it starts and as it ends, in order, and the
/// trials reported are the ones the result lists (σ_c and misfit, as printed).
#[test]
fn automatic_sigma_search_reports_each_trial() {
    let data = cantilever_data("cant-auto.json");
    let out = tmp("cant-auto-out.json");
    let u = update(
        &model_path("cantilever-case1"),
        data.to_str().unwrap(),
        &out,
        &["--method", "bayesian", "--sigma-c", "auto", "--no-tsvd"],
    );
    let stderr = String::from_utf8_lossy(&u.stderr);
    assert!(u.status.success(), "{stderr}");
    let trials = read_json(&out)["bayesian"]["sigma_c_auto"]["trials"]
        .as_array()
        .expect("the automatic choice lists its trials")
        .clone();
    assert!(!trials.is_empty());
    let lines: Vec<&str> = stderr
        .lines()
        .filter(|l| l.starts_with("σ_c trial "))
        .collect();
    assert_eq!(lines.len(), 2 * trials.len(), "{stderr}");
    for (i, t) in trials.iter().enumerate() {
        let sigma = format!("{:.4e}", t["sigma_c"].as_f64().unwrap());
        let misfit = format!("{:.1}", t["misfit"].as_f64().unwrap());
        assert_eq!(
            lines[2 * i],
            format!("σ_c trial {}: the MAP at σ_c = {sigma}", i + 1)
        );
        assert!(
            lines[2 * i + 1].starts_with(&format!(
                "σ_c trial {}: σ_c = {sigma}, misfit {misfit} (target ν = ",
                i + 1
            )),
            "{}",
            lines[2 * i + 1]
        );
    }
}

/// `sweep-sigma` writes the σ_c study as JSON (every point, both solvers' iterations, the
/// automatic choice and its rule) and as an SVG figure.
#[test]
fn sweep_sigma_writes_json_and_svg() {
    let data = cantilever_data("cant-sweep.json");
    let dir = tmp("sweep");
    let s = boltwatch(&[
        "sweep-sigma",
        "--model",
        &model_path("cantilever-case1"),
        "--data",
        data.to_str().unwrap(),
        "--from",
        "1e2",
        "--to",
        "1e5",
        "--points",
        "4",
        "--truth",
        "0.5",
        "--alternating-max-iter",
        "20000",
        "-o",
        dir.to_str().unwrap(),
    ]);
    assert!(s.status.success(), "{}", String::from_utf8_lossy(&s.stderr));
    let sweep = read_json(&dir.join("sweep.json"));
    assert_eq!(sweep["schema"], "boltwatch.sigma_sweep.v1");
    let points = sweep["points"].as_array().unwrap();
    assert_eq!(points.len(), 4);
    let mut last_misfit = f64::INFINITY;
    for p in points {
        assert_eq!(p["newton"]["converged"], true);
        assert!(p["alternating"]["iterations"].as_u64().unwrap() > 0);
        // The measurement misfit falls as σ_c grows (the MAP modes move to the data).
        let m = p["measurement_misfit"].as_f64().unwrap();
        assert!(
            m < last_misfit,
            "misfit not decreasing: {m} after {last_misfit}"
        );
        last_misfit = m;
    }
    assert!(sweep["auto"]["sigma_c"].as_f64().unwrap() > 0.0);
    assert!(sweep["auto"]["rule"].as_str().unwrap().contains("ν"));
    let svg = std::fs::read_to_string(dir.join("sweep.svg")).unwrap();
    assert!(svg.starts_with("<svg") && svg.trim_end().ends_with("</svg>"));
    assert!(svg.contains("σ_c") && svg.contains("polyline"));
}

/// The paper's two-stage use (§4.2): stage I on the simplified lab frame with 5 modes,
/// stage II on the full parameterization starting from stage I's θ mapped onto it.
#[test]
fn two_stage_bayesian_update() {
    let data = format!(
        "{}/recordings/lab-frame-modal-set.json",
        env!("CARGO_MANIFEST_DIR")
    );
    let out = tmp("two-stage.json");
    let simplified = model_path("lab-frame-simplified");
    let u = update(
        &model_path("lab-frame"),
        &data,
        &out,
        &[
            "--method",
            "bayesian",
            "--sigma-c",
            "1e4",
            "--stage1-model",
            &simplified,
            "--stage1-modes",
            "5",
            "--no-tsvd",
        ],
    );
    assert!(u.status.success(), "{}", String::from_utf8_lossy(&u.stderr));
    let r = read_json(&out);
    assert_eq!(r["converged"], true);
    assert_eq!(r["start"], "stage I");
    let s1 = &r["stage1"];
    assert_eq!(s1["modes"], 5);
    assert!(s1["parameters"].as_array().unwrap().len() < 17);
    let mapping = s1["mapping"].as_array().unwrap();
    assert_eq!(mapping.len(), 17);
    assert!(mapping.iter().all(|m| m["theta0"].as_f64().unwrap() > 0.0));
    assert_eq!(r["parameters"].as_array().unwrap().len(), 17);
}

/// Bad Bayesian options are refused with exit 2 and the flag named.
#[test]
fn bad_bayesian_options_exit_2() {
    let data = format!(
        "{}/recordings/lab-frame-modal-set.json",
        env!("CARGO_MANIFEST_DIR")
    );
    let model = model_path("lab-frame");
    for (extra, needle) in [
        (vec!["--sigma-c", "-3"], "--sigma-c"),
        (vec!["--sigma-c", "abc"], "--sigma-c"),
        (vec!["--sigma-range", "5,1"], "--sigma-range"),
        (vec!["--prior-std", "1,2"], "--prior-std"),
    ] {
        let mut args = vec!["--method", "bayesian"];
        args.extend_from_slice(&extra);
        let u = update(&model, &data, &tmp("bad-bayes.json"), &args);
        let err = String::from_utf8_lossy(&u.stderr);
        assert_eq!(u.status.code(), Some(2), "{extra:?}: {err}");
        assert!(err.contains(needle), "{extra:?}: {err}");
    }
}

/// The global search's options and a model's bounds, refused with exit 2 and the value
/// named: `--starts 0`, a seed that is not a number, `lower > upper`, a nominal θ outside
/// its bounds.
#[test]
fn bad_search_options_and_bounds_exit_2_naming_the_value() {
    let case = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/data/smu-four-storey");
    let model = format!("{case}/model.json");
    let data = format!("{case}/data.json");
    let out = tmp("search-bad.json");
    for (extra, named) in [
        (&["--starts", "0"][..], "--starts 0"),
        (&["--seed", "abc"][..], "abc"),
        (&["--seed", "-1"][..], "-1"),
    ] {
        let u = update(&model, &data, &out, extra);
        let err = String::from_utf8_lossy(&u.stderr);
        assert_eq!(u.status.code(), Some(2), "{extra:?}: {err}");
        assert!(err.contains(named), "{extra:?}: {err}");
    }
    // The same case with its first parameter's bounds edited.
    for (edit, named) in [
        (("lower", 1.5, "upper", 1.2), "lower 1.5"),
        (("lower", 1.2, "upper", 2.0), "nominal 1"),
    ] {
        let dir = tmp(&format!("bounds-{}", edit.1));
        std::fs::create_dir_all(&dir).unwrap();
        for entry in std::fs::read_dir(case).unwrap() {
            let p = entry.unwrap().path();
            std::fs::copy(&p, dir.join(p.file_name().unwrap())).unwrap();
        }
        let mut m: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(dir.join("model.json")).unwrap())
                .unwrap();
        m["parameters"][0][edit.0] = edit.1.into();
        m["parameters"][0][edit.2] = edit.3.into();
        std::fs::write(dir.join("model.json"), m.to_string()).unwrap();
        let u = update(dir.join("model.json").to_str().unwrap(), &data, &out, &[]);
        let err = String::from_utf8_lossy(&u.stderr);
        assert_eq!(u.status.code(), Some(2), "{edit:?}: {err}");
        assert!(
            err.contains(named) && err.contains("storey1"),
            "{edit:?}: {err}"
        );
    }
}

/// `scenario --event-day` on a scenario without an event is refused (exit 2) by what the
/// scenario is: the healthy one has no event; the seasonal one's is a loss set by
/// `--loosen`, `--drop` and `--day`. No recording is written.
#[test]
fn event_day_without_an_event_names_the_scenario() {
    for (name, says) in [
        ("healthy", "the healthy scenario has no event"),
        ("seasonal", "--loosen, --drop and --day"),
    ] {
        let out = tmp(&format!("event-day-{name}.mcap"));
        let r = boltwatch(&[
            "scenario",
            name,
            "--event-day",
            "3",
            "-o",
            out.to_str().unwrap(),
        ]);
        let err = String::from_utf8_lossy(&r.stderr);
        assert_eq!(r.status.code(), Some(2), "{name}: {err}");
        assert!(err.contains(says), "{name}: {err}");
        assert!(!out.exists(), "{name}: a recording was written");
    }
}

/// `plan` on the lab frame: plan.json with every connection judged before and after two
/// added sensors (no σ higher after), and the drawing; bad input exits 2 naming it.
#[test]
fn plan_judges_every_connection_and_refuses_bad_input() {
    let model = model_path("lab-frame");
    let out = tmp("plan");
    let o = boltwatch(&[
        "plan",
        "--model",
        &model,
        "--add",
        "2",
        "-o",
        out.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let plan = read_json(&out.join("plan.json"));
    assert_eq!(plan["schema"], "boltwatch.plan.v1");
    let rows = |key: &str| plan[key]["connections"].as_array().unwrap().clone();
    let (before, after) = (rows("current"), rows("planned"));
    assert_eq!(before.len(), 16, "the lab frame's 16 connections");
    for (b, a) in before.iter().zip(&after) {
        let (sb, sa) = (
            b["sigma_per_set"].as_f64().unwrap(),
            a["sigma_per_set"].as_f64().unwrap(),
        );
        assert!(sa <= sb * (1.0 + 1e-9), "{}: {sb} → {sa}", b["name"]);
        let warn = b["detectable_warning"].as_f64().unwrap();
        assert!(warn > 0.10 && warn < 1.0, "{warn}");
    }
    assert_eq!(plan["added"].as_array().unwrap().len(), 2);
    assert_eq!(plan["planned"]["channels"].as_array().unwrap().len(), 44);
    assert!(
        std::fs::read_to_string(out.join("plan.svg"))
            .unwrap()
            .contains("<svg")
    );

    let installed = tmp("installed.toml");
    std::fs::write(&installed, "channels = [\"C1L.1\", \"nowhere.x\"]\n").unwrap();
    let o_dir = tmp("plan-bad");
    let dir = o_dir.to_str().unwrap();
    let cases: [(&[&str], &str); 5] = [
        (
            &["--channels", installed.to_str().unwrap()],
            "`nowhere.x` is not a channel",
        ),
        (&["--budget", "100000"], "--budget 100000"),
        (&["--modes", "0"], "--modes"),
        (&["--per-day", "0"], "--per-day 0"),
        (&["--verify", "5"], "commissioning sets"),
    ];
    for (extra, says) in cases {
        let mut args = vec!["plan", "--model", &model, "-o", dir];
        args.extend_from_slice(extra);
        let o = boltwatch(&args);
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{extra:?}: {err}");
        assert!(err.contains(says), "{extra:?}: {err}");
    }
}
