//! The discrepancy workflow (issue 6) on data that carry an effect the model lacks: the lab
//! frame, 9 modes at all 42 channels, 1 % frequency CoV and 5 % shape NSD, noise drawn.
//!
//! Sizes are "moderate" in the sense the issue's ε criterion needs: large enough that the
//! nominal model class (16 bolt stiffnesses and E, which absorb part of any effect) fits
//! with ε at least 3.3 times its noise level, so that explaining the effect can bring ε
//! down to 30 % of it.

use boltwatch::core::diagnosis::injection::Injection;
use boltwatch::core::diagnosis::{Description, Diagnosis, DiagnosisOptions, diagnose};
use boltwatch::core::model::Model;
use boltwatch::core::model::spec::ModelSpec;
use boltwatch::core::simulate::{Noise, simulated_measured_data};
use boltwatch::core::updating::MeasuredData;
use rand::{Rng, SeedableRng};

fn lab_spec() -> Description {
    Description::File(lab_file())
}

fn lab_file() -> ModelSpec {
    let text = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/config/models/lab-frame.toml"
    ))
    .unwrap();
    toml::from_str(&text).unwrap()
}

/// The lab frame without its modulus parameter (so that a modulus change is missing).
fn lab_spec_without_modulus() -> Description {
    let mut s = lab_file();
    s.parameters.retain(|p| p.members.is_empty());
    Description::File(s)
}

const NOISE: Noise = Noise {
    frequency_cov: 0.01,
    shape_nsd: 0.05,
};

/// 9 noisy modes of `spec` with `injections` added, at θ (default nominal).
fn data(spec: &Description, injections: &[&str], theta: Option<&[f64]>, seed: u64) -> MeasuredData {
    let mut s = spec.clone();
    for i in injections {
        Injection::parse(i).unwrap().apply(&mut s).unwrap();
    }
    let model = s.build().unwrap();
    let theta = theta.map_or_else(|| model.nominal_theta(), <[f64]>::to_vec);
    simulated_measured_data(&model, &theta, 9, NOISE, true, seed).unwrap()
}

fn run(spec: &Description, data: &MeasuredData) -> Diagnosis {
    boltwatch::core::sequential_numerics();
    diagnose(spec, data, &DiagnosisOptions::default(), |_, _, _| {}).unwrap()
}

/// One hidden effect: named with the right effect and location, ε after at most 30 % of
/// ε before, the fitted value within 3σ of the truth.
fn hidden_effect_is_named(spec: &Description, injection: &str, seed: u64) {
    let inj = Injection::parse(injection).unwrap();
    let d = run(spec, &data(spec, &[injection], None, seed));
    let ratio = d.after.epsilon / d.before.epsilon;
    println!(
        "{injection} (seed {seed}): named {:?}; ε {:.1} -> {:.1} ({:.0} %)",
        d.named
            .iter()
            .map(|n| format!(
                "{}@{} = {:.4e} ± {:.2e} {} (Λ {:.1})",
                n.refit.effect,
                n.refit.location,
                n.refit.value,
                n.refit.std,
                n.refit.unit,
                n.likelihood_ratio
            ))
            .collect::<Vec<_>>(),
        d.before.epsilon,
        d.after.epsilon,
        100.0 * ratio
    );
    let n = d.named.first().expect("an effect is named");
    assert_eq!(n.refit.effect, inj.effect.kind(), "{injection}");
    assert_eq!(n.refit.location, inj.location, "{injection}");
    assert!(
        ratio <= 0.3,
        "{injection}: ε after is {:.0} % of before",
        100.0 * ratio
    );
    let z = (n.refit.value - inj.value) / n.refit.std;
    assert!(
        z.abs() <= 3.0,
        "{injection}: fitted {} ± {}, {z:.1}σ from the truth",
        n.refit.value,
        n.refit.std
    );
}

#[test]
fn a_hidden_added_mass_is_named() {
    hidden_effect_is_named(&lab_spec(), "added-mass@B2.3=1", 1);
}

#[test]
fn a_hidden_support_flexibility_is_named() {
    hidden_effect_is_named(&lab_spec(), "support-flexibility@BL.rz=3000", 2);
}

#[test]
fn a_hidden_member_stiffness_change_is_named() {
    hidden_effect_is_named(&lab_spec(), "member-stiffness@C1L=-0.5", 3);
}

/// A uniform change of E moves every frequency and no mode shape, and the bolt stiffnesses
/// absorb part of it, so only a large change brings the ε of the nominal class to 3.3 times
/// its noise level (at −25 %, ε after is still 37 % of before); a few per cent are *named*
/// (the detectability table in `docs/design/diagnosis.md`).
#[test]
fn a_hidden_modulus_change_is_named() {
    hidden_effect_is_named(&lab_spec_without_modulus(), "modulus@global=-0.4", 4);
}

/// A mass at either end of an axially rigid floor beam moves the sway modes alike: the
/// workflow names the effect and says the data cannot tell the two joints apart.
#[test]
fn indistinguishable_locations_are_reported() {
    let spec = lab_spec();
    let d = run(&spec, &data(&spec, &["added-mass@J2R=3"], None, 1));
    let n = d.named.first().expect("an effect is named");
    assert_eq!(n.refit.effect, "added-mass");
    let mut places: Vec<&str> = std::iter::once(n.refit.location.as_str())
        .chain(n.indistinguishable_from.iter().map(|o| o.location.as_str()))
        .collect();
    places.sort_unstable();
    println!(
        "added-mass@J2R=3: named {} = {:.3} ± {:.3} kg, indistinguishable from {:?}",
        n.refit.location,
        n.refit.value,
        n.refit.std,
        n.indistinguishable_from
            .iter()
            .map(|o| (&o.location, o.epsilon - n.refit.epsilon))
            .collect::<Vec<_>>()
    );
    assert!(
        places.contains(&"J2L") && places.contains(&"J2R"),
        "{places:?}"
    );
}

#[test]
fn a_hidden_joint_inertia_error_is_named() {
    hidden_effect_is_named(&lab_spec(), "joint-inertia@J1L=0.005", 5);
}

/// Bolt-stiffness changes (inside the model class) and noise only, 20 seeds: nothing named.
#[test]
fn nothing_is_named_without_a_hidden_effect() {
    let spec = lab_spec();
    let model = spec.build().unwrap();
    let mut largest = (0.0, String::new());
    for seed in 0..20 {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(100 + seed);
        let theta: Vec<f64> = model
            .parameters()
            .iter()
            .map(|p| {
                if p.name == "E" {
                    1.0
                } else {
                    rng.random_range(0.4..1.6)
                }
            })
            .collect();
        let d = run(&spec, &data(&spec, &[], Some(&theta), seed));
        assert!(
            d.named.is_empty(),
            "seed {seed}: named {}@{} (Λ {:.1} > {:.1})",
            d.named[0].refit.effect,
            d.named[0].refit.location,
            d.named[0].likelihood_ratio,
            d.threshold
        );
        if let Some(r) = d.rounds[0].refits.first() {
            let lr = d.before.epsilon - r.epsilon;
            if lr > largest.0 {
                largest = (lr, format!("seed {seed}: {}@{}", r.effect, r.location));
            }
        }
    }
    println!(
        "largest likelihood ratio without an effect: {:.1} ({}); threshold {:.1}",
        largest.0,
        largest.1,
        run(&spec, &data(&spec, &[], None, 0)).threshold
    );
}

/// Two hidden effects at once: both named, the larger (by the ε it explains) first.
#[test]
fn two_hidden_effects_are_both_named_larger_first() {
    let spec = lab_spec();
    let d = run(
        &spec,
        &data(
            &spec,
            &["support-flexibility@BL.rz=3000", "added-mass@B2.3=0.5"],
            None,
            6,
        ),
    );
    let named: Vec<String> = d
        .named
        .iter()
        .map(|n| format!("{}@{}", n.refit.effect, n.refit.location))
        .collect();
    println!(
        "named {named:?}; ε {:.1} -> {:.1}; values {:?}",
        d.before.epsilon,
        d.after.epsilon,
        d.named
            .iter()
            .map(|n| (n.refit.value, n.refit.std))
            .collect::<Vec<_>>()
    );
    assert!(named.len() >= 2, "{named:?}");
    assert_eq!(named[0], "support-flexibility@BL.rz");
    assert_eq!(named[1], "added-mass@B2.3");
}

#[test]
fn a_hidden_splice_is_named() {
    hidden_effect_is_named(&lab_spec(), "splice@C2L.2=2000", 7);
}

/// The lab frame's flat bars are slender about their weak axis: a column carries −32 kN
/// (70 % of its Euler load, 58 MPa) before its geometric stiffness moves the modes enough
/// for the ε criterion.
#[test]
fn a_hidden_axial_force_is_named() {
    hidden_effect_is_named(&lab_spec(), "axial-force@C1L=-32000", 8);
}

/// The splice effect is exactly a member in two parts joined by a bolted connection: a
/// cantilever spliced at mid-span has the frequencies of the same cantilever written as two
/// members and a connection (identical meshes; 1e-10 relative).
#[test]
fn a_splice_is_a_two_part_member_with_a_connection() {
    let head = r#"name = "c"
[[materials]]
name = "steel"
E = 2.1e11
rho = 7840.0
[[sections]]
name = "flat"
A = 5.5e-4
I = 5.5458e-9
[[nodes]]
name = "A"
x = 0.0
y = 0.0
[[nodes]]
name = "B"
x = 0.0
y = 1.0
[[supports]]
node = "A"
"#;
    let one = format!(
        "{head}[[members]]\nname = \"AB\"\nfrom = \"A\"\nto = \"B\"\nsection = \"flat\"\nmaterial = \"steel\"\nelements = 10\n"
    );
    let two = format!(
        "{head}[[nodes]]\nname = \"S\"\nx = 0.0\ny = 0.5\n\
         [[members]]\nname = \"AS\"\nfrom = \"A\"\nto = \"S\"\nsection = \"flat\"\nmaterial = \"steel\"\nelements = 5\n\
         [[members]]\nname = \"SB\"\nfrom = \"S\"\nto = \"B\"\nsection = \"flat\"\nmaterial = \"steel\"\nelements = 5\n\
         [[connections]]\nmember = \"SB\"\nnode = \"S\"\nk = 1500.0\n"
    );
    let mut spliced = Description::File(toml::from_str(&one).unwrap());
    Injection::parse("splice@AB.5=1500")
        .unwrap()
        .apply(&mut spliced)
        .unwrap();
    let freqs = |m: &Model| {
        let mut s = boltwatch::core::modal::DenseEigen::new(m).unwrap();
        let e =
            boltwatch::core::modal::EigenSolver::solve(&mut s, m, &m.nominal_theta(), 6).unwrap();
        (0..6).map(|k| e.frequency_hz(k)).collect::<Vec<_>>()
    };
    let (a, b) = (
        freqs(&spliced.build().unwrap()),
        freqs(&Model::from_toml(&two).unwrap()),
    );
    let plain = freqs(&Model::from_toml(&one).unwrap());
    for k in 0..6 {
        assert!(
            ((a[k] - b[k]) / b[k]).abs() < 1e-10,
            "mode {k}: {} vs {}",
            a[k],
            b[k]
        );
    }
    assert!(a[0] < plain[0] * 0.99, "the splice softens the cantilever");
}

/// As a user runs it: `simulate --inject` hides an effect in the data, `diagnose` names it
/// and writes the `boltwatch.diagnosis.v1` contract and both plots; a bad injection is a
/// one-line error naming the problem.
#[test]
fn diagnose_command_writes_the_contract_and_plots() {
    let dir = std::env::temp_dir().join(format!("bw-diagnose-cli-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let bin = || {
        let mut c = std::process::Command::new(env!("CARGO_BIN_EXE_boltwatch"));
        c.current_dir(env!("CARGO_MANIFEST_DIR"));
        c
    };
    let data = dir.join("data.json");
    let o = bin()
        .args([
            "simulate",
            "--model",
            "config/models/lab-frame.toml",
            "--seed",
            "2",
        ])
        .args(["--inject", "support-flexibility@BL.rz=3000", "-o"])
        .arg(&data)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let set: serde_json::Value = serde_json::from_slice(&std::fs::read(&data).unwrap()).unwrap();
    assert!(
        set["source"]
            .as_str()
            .unwrap()
            .contains("--inject support-flexibility@BL.rz=3000")
    );
    let out = dir.join("diag");
    let o = bin()
        .args([
            "diagnose",
            "--model",
            "config/models/lab-frame.toml",
            "--data",
        ])
        .arg(&data)
        .arg("-o")
        .arg(&out)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(
        stdout.contains("named: support-flexibility@BL.rz"),
        "{stdout}"
    );
    let d: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("diagnosis.json")).unwrap()).unwrap();
    assert_eq!(d["schema"], "boltwatch.diagnosis.v1");
    assert!(d["epsilon_after"].as_f64().unwrap() < 0.3 * d["epsilon_before"].as_f64().unwrap());
    let n = &d["named"][0];
    assert_eq!(n["effect"], "support-flexibility");
    assert_eq!(n["location"], "BL.rz");
    assert_eq!(n["unit"], "N·m/rad");
    for key in ["value", "std", "epsilon_before", "epsilon_after"] {
        assert!(n[key].is_f64(), "{key}: {n:#}");
    }
    assert!(n["evidence"]["log_bayes_factor"].as_f64().unwrap() > 100.0);
    let c = &d["candidates"][0];
    assert!(c["effect"].is_string() && c["location"].is_string() && c["score"].is_f64());
    assert_eq!(d["before"]["modes"].as_array().unwrap().len(), 9);
    assert_eq!(d["after"]["channels"].as_array().unwrap().len(), 42);
    for plot in ["modes.svg", "structure.svg"] {
        let svg = std::fs::read_to_string(out.join(plot)).unwrap();
        assert!(
            svg.starts_with("<svg") && svg.trim_end().ends_with("</svg>"),
            "{plot}"
        );
    }
    assert!(
        std::fs::read_to_string(out.join("structure.svg"))
            .unwrap()
            .contains("support-flexibility@BL.rz")
    );
    // Bad injections.
    for (inject, says) in [
        ("added-mass@J9X=1", "not a location"),
        ("added-mass@J2R=-1", "must be > 0"),
        ("rust@J2R=1", "unknown effect"),
        ("added-mass@J2R", "no `=`"),
    ] {
        let o = bin()
            .args([
                "simulate",
                "--model",
                "config/models/lab-frame.toml",
                "--inject",
                inject,
                "-o",
            ])
            .arg(dir.join("bad.json"))
            .output()
            .unwrap();
        assert_eq!(o.status.code(), Some(2), "{inject}");
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(
            err.contains(says) && err.lines().count() == 1,
            "{inject}: {err}"
        );
    }
}

/// The detectability table (issue 6): for each effect type, the smallest size on a ladder
/// that is named (right effect; right location, or one the data cannot tell from it) in at
/// least 4 of 5 noise seeds. A study, not a check (minutes in release):
/// `cargo test --release --test tests detectability -- --ignored --nocapture`.
#[test]
#[ignore = "a study of several minutes; its table is in docs/design/diagnosis.md"]
fn detectability_table() {
    let ladders: [(&str, &str, &[f64], bool); 7] = [
        ("added-mass", "B2.3", &[0.05, 0.1, 0.2, 0.4, 0.8], false),
        (
            "support-flexibility",
            "BL.rz",
            &[1e7, 3e6, 1e6, 3e5, 1e5],
            false,
        ),
        (
            "member-stiffness",
            "C1L",
            &[-0.05, -0.1, -0.2, -0.3, -0.5],
            false,
        ),
        ("modulus", "global", &[-0.02, -0.05, -0.1, -0.2], true),
        (
            "joint-inertia",
            "J1L",
            &[2e-4, 5e-4, 1e-3, 2e-3, 4e-3],
            false,
        ),
        ("splice", "C2L.2", &[1e5, 5e4, 2e4, 1e4, 5e3], false),
        (
            "axial-force",
            "C1L",
            &[-2000.0, -5000.0, -10000.0, -20000.0],
            false,
        ),
    ];
    println!("| effect | location | smallest size named in ≥ 4 of 5 seeds | named per size |");
    println!("|---|---|---|---|");
    for (kind, location, sizes, without_modulus) in ladders {
        let spec = if without_modulus {
            lab_spec_without_modulus()
        } else {
            lab_spec()
        };
        let mut found = None;
        let mut counts = Vec::new();
        for &size in sizes {
            let injection = format!("{kind}@{location}={size}");
            let hits = (0..5)
                .filter(|&seed| {
                    let d = run(&spec, &data(&spec, &[&injection], None, 200 + seed));
                    d.named.first().is_some_and(|n| {
                        n.refit.effect == kind
                            && (n.refit.location == location
                                || n.indistinguishable_from
                                    .iter()
                                    .any(|o| o.effect == kind && o.location == location))
                    })
                })
                .count();
            counts.push(format!("{size}: {hits}/5"));
            if hits >= 4 {
                found = Some(size);
                break;
            }
        }
        println!(
            "| {kind} | {location} | {} | {} |",
            found.map_or("beyond the ladder".to_string(), |s| s.to_string()),
            counts.join(", ")
        );
    }
}

/// The lab frame exported to matrices, with every node's translations as a named location
/// (`J2R` = `J2R.x`, `J2R.y`; `B2.3` = `B2.3.x`, `B2.3.y`), imported. With
/// `fold_modulus`, the modulus parameter `E` is folded into `K0` (so `stiffness-scale@K0`
/// is what the model lacks, as `modulus@global` in `lab_spec_without_modulus`).
fn imported_lab(fold_modulus: bool) -> Description {
    let json = imported_lab_json(fold_modulus, "library");
    let model = boltwatch::io::model::load_model(&json).unwrap();
    Description::matrices(std::sync::Arc::new(model))
}

/// The `model.json` of [`imported_lab`].
/// The exported lab frame in a directory of its own per `tag`: two tests running at once
/// must not share one (`tmp_dir` empties it), or one deletes the other's outputs.
fn imported_lab_json(fold_modulus: bool, tag: &str) -> std::path::PathBuf {
    let dir = super::tracker::tmp_dir(&format!("diagnose-imported-{fold_modulus}-{tag}"));
    let o = std::process::Command::new(env!("CARGO_BIN_EXE_boltwatch"))
        .args(["export-matrices", "--model"])
        .arg(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/config/models/lab-frame.toml"
        ))
        .arg("-o")
        .arg(&dir)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let labels = std::fs::read_to_string(dir.join("dofs.txt")).unwrap();
    let mut nodes: Vec<(String, Vec<usize>)> = Vec::new();
    for (i, l) in labels.lines().enumerate() {
        let Some(node) = l.strip_suffix(".x").or_else(|| l.strip_suffix(".y")) else {
            continue;
        };
        match nodes.iter_mut().find(|(n, _)| n == node) {
            Some((_, d)) => d.push(i),
            None => nodes.push((node.to_string(), vec![i])),
        }
    }
    let locations: Vec<serde_json::Value> = nodes
        .iter()
        .map(|(n, d)| serde_json::json!({"name": n, "dofs": d}))
        .collect();
    let json = dir.join("model.json");
    let mut doc: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    doc["locations"] = serde_json::Value::Array(locations);
    if fold_modulus {
        let params = doc["parameters"].as_array_mut().unwrap();
        let e = params.iter().position(|p| p["name"] == "E").unwrap();
        let file = params.remove(e)["file"].as_str().unwrap().to_string();
        doc["k0"] = serde_json::json!(file);
    }
    std::fs::write(&json, serde_json::to_string_pretty(&doc).unwrap()).unwrap();
    json
}

/// Issue 24 item 4: diagnosis on a model imported from matrices, with the effects that need
/// no geometry. An added mass at a named location is the file's added mass at that node
/// (frequencies to 1e-10); hidden in the data, an added mass, a grounded spring and a
/// stiffness scale of `K0` are each named at the right place, with ε after at most 30 % of
/// before and the value within 3σ; effects that need geometry are refused by name.
#[test]
fn diagnosis_of_an_imported_model_names_the_hidden_effect() {
    let imported = imported_lab(false);
    let freqs = |d: &Description| {
        let m = d.build().unwrap();
        let mut s = boltwatch::core::modal::solver_for(&m).unwrap();
        let e = s.solve(&m, &m.nominal_theta(), 9).unwrap();
        (0..9).map(|k| e.frequency_hz(k)).collect::<Vec<_>>()
    };
    let (mut a, mut b) = (imported.clone(), lab_spec());
    for d in [&mut a, &mut b] {
        Injection::parse("added-mass@J2R=0.5")
            .unwrap()
            .apply(d)
            .unwrap();
    }
    for (k, (x, y)) in freqs(&a).iter().zip(freqs(&b)).enumerate() {
        assert!(((x - y) / y).abs() < 1e-10, "mode {}: {x} vs {y}", k + 1);
    }
    let err = Injection::parse("support-flexibility@BL.rz=3000")
        .unwrap()
        .apply(&mut imported.clone())
        .unwrap_err()
        .to_string();
    assert!(err.contains("grounded-spring"), "{err}");

    hidden_effect_is_named(&imported, "added-mass@B2.3=1", 1);
    hidden_effect_is_named(&imported, "grounded-spring@C2L.2=200000", 2);
    hidden_effect_is_named(&imported_lab(true), "stiffness-scale@K0=-0.4", 4);

    // As a user runs it: simulate --inject and diagnose with the model.json.
    let json = imported_lab_json(false, "cli");
    let dir = json.parent().unwrap();
    let run = |args: &[&str]| {
        let o = std::process::Command::new(env!("CARGO_BIN_EXE_boltwatch"))
            .args(args)
            .output()
            .unwrap();
        assert!(
            o.status.success(),
            "{args:?}: {}",
            String::from_utf8_lossy(&o.stderr)
        );
    };
    let (model, data, out) = (
        json.to_str().unwrap(),
        dir.join("data.json"),
        dir.join("diag"),
    );
    run(&[
        "simulate",
        "--model",
        model,
        "--seed",
        "1",
        "--inject",
        "added-mass@B2.3=1",
        "-o",
        data.to_str().unwrap(),
    ]);
    run(&[
        "diagnose",
        "--model",
        model,
        "--data",
        data.to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
    ]);
    let doc: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("diagnosis.json")).unwrap()).unwrap();
    let first = &doc["named"][0];
    assert_eq!(
        (first["effect"].as_str(), first["location"].as_str()),
        (Some("added-mass"), Some("B2.3")),
        "{doc}"
    );
    assert!(out.join("modes.svg").exists() && !out.join("structure.svg").exists());
}

/// The daemon's and replay's verdict on a model-inadequacy warning
/// (`pipeline::verdict::diagnosis_alert`) for a structure whose model was imported from
/// matrices: the diagnosis runs (it no longer fails as "not done") and names the hidden
/// added mass at the file's location.
#[test]
fn the_warning_verdict_diagnoses_an_imported_model() {
    use boltwatch::contract::{AlertDetail, Verdict};
    use boltwatch::pipeline::DiagnoseRequest;
    let json = imported_lab_json(false, "warning");
    let model = boltwatch::io::model::load_model(&json).unwrap();
    let data = json.with_file_name("warned.json");
    let o = std::process::Command::new(env!("CARGO_BIN_EXE_boltwatch"))
        .args(["simulate", "--model"])
        .arg(&json)
        .args(["--seed", "1", "--inject", "added-mass@B2.3=1", "-o"])
        .arg(&data)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let set = boltwatch::commands::inputs::load_set(&model, &data).unwrap();
    let req = DiagnoseRequest {
        set,
        epsilon: 2000.0,
        epsilon_bound: 450.0,
    };
    boltwatch::core::sequential_numerics();
    let alert = boltwatch::pipeline::verdict::diagnosis_alert(None, &model, 1.0, &req);
    let AlertDetail::Inadequacy {
        diagnosis: Some(Verdict::Found { named, .. }),
        ..
    } = &alert.detail
    else {
        panic!("no diagnosis found: {}", alert.message);
    };
    assert_eq!(
        (named[0].effect.as_str(), named[0].location.as_str()),
        ("added-mass", "B2.3"),
        "{}",
        alert.message
    );
}
