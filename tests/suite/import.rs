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

pub(crate) fn export(model: &Path, dir: &Path) -> PathBuf {
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
        "space-frame",
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

/// `replay` with a bundled model imported from its exported matrices writes the same bytes
/// as with its TOML model file (estimates, cross-checks and the file itself): the lab frame
/// over 150 healthy sets (cross-checks every 50), the simplified lab frame, a cantilever and
/// the space frame (sparse solver) over 40 (cross-checks every 20).
#[test]
fn replay_with_imported_models_gives_the_same_bytes() {
    for (name, structure, sets, modes, every) in [
        ("lab-frame", "lab-frame", 150, 9, "50"),
        ("lab-frame-simplified", "lab-frame-simplified", 40, 9, "20"),
        ("cantilever-case1", "cantilever", 40, 3, "20"),
        ("space-frame", "space-frame", 40, 15, "20"),
    ] {
        replay_bytes(name, structure, sets, modes, every);
    }
}

/// Replays a healthy scenario of the bundled model `name` (structure `structure`) with
/// its TOML file and with its exported matrices, and compares the outputs.
fn replay_bytes(name: &str, structure: &str, sets: usize, modes: usize, crosscheck_every: &str) {
    use boltwatch::commands::scenario::{ScenarioArgs, run as scenario};
    boltwatch::core::sequential_numerics();
    let dir = tmp_dir(&format!("import-replay-{name}"));
    let toml = format!("{}/config/models/{name}.toml", env!("CARGO_MANIFEST_DIR"));
    let json = export(Path::new(&toml), &dir.join("matrices"));
    let rec = dir.join("rec.mcap");
    scenario(&ScenarioArgs {
        name: "healthy".into(),
        model: toml.clone().into(),
        sets: Some(sets),
        days: Some(3.0),
        seed: 1,
        modes,
        connection: None,
        at: None,
        event_day: None,
        loosen: None,
        drop: None,
        day: None,
        environment: false,
        shape_digits: 0,
        out: rec.clone(),
        raw: Default::default(),
    })
    .unwrap();
    let run = |model: &Path, tag: &str| -> Vec<u8> {
        let cfg = dir.join(format!("{tag}.toml"));
        std::fs::write(
            &cfg,
            format!(
                "[[structures]]\nname = \"{structure}\"\nmodel = {:?}\n",
                model.to_str().unwrap()
            ),
        )
        .unwrap();
        let out = dir.join(format!("{tag}.mcap"));
        let r = Command::new(env!("CARGO_BIN_EXE_boltwatch"))
            .env("BOLTWATCH__LOG__LEVEL", "warn")
            .env(
                "BOLTWATCH__TRACKER__CROSSCHECK_EVERY_SETS",
                crosscheck_every,
            )
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
            "{name}: replay with {}: {}",
            model.display(),
            String::from_utf8_lossy(&r.stderr)
        );
        std::fs::read(&out).unwrap()
    };
    let a = run(Path::new(&toml), "toml");
    let b = run(&json, "imported");
    let topics = |bytes: &[u8], tag: &str| {
        let p = dir.join(format!("{tag}.check.mcap"));
        std::fs::write(&p, bytes).unwrap();
        boltwatch::io::mcap::read_all(&p)
            .unwrap()
            .into_iter()
            .map(|m| (m.topic, m.data))
            .collect::<Vec<_>>()
    };
    let (ma, mb) = (topics(&a, "a"), topics(&b, "b"));
    assert!(
        ma.iter().any(|(t, _)| t.ends_with("/stiffness")),
        "{name}: estimates written"
    );
    assert!(
        ma.iter().any(|(t, _)| t.ends_with("/crosscheck")),
        "{name}: cross-checks ran"
    );
    assert_eq!(ma.len(), mb.len(), "{name}");
    for (x, y) in ma.iter().zip(&mb) {
        assert_eq!(x.0, y.0, "{name}");
        assert_eq!(
            String::from_utf8_lossy(&x.1),
            String::from_utf8_lossy(&y.1),
            "{name}: {}",
            x.0
        );
    }
    assert!(a == b, "{name}: the output files differ byte for byte");
    println!(
        "{name}: {} messages, {} bytes, identical",
        ma.len(),
        a.len()
    );
}

/// The lab frame exported, its `M` replaced by a lumped one: each translation keeps its
/// consistent-mass diagonal, the 58 rotations carry no mass (as an FE program's lumped
/// masses leave them).
fn lumped_lab_frame(dir: &Path) -> PathBuf {
    let toml = format!(
        "{}/config/models/lab-frame.toml",
        env!("CARGO_MANIFEST_DIR")
    );
    let json = export(Path::new(&toml), dir);
    let consistent = load_model(&json).unwrap();
    let m = consistent.mass_dense();
    let n = consistent.n_dof();
    let mut text = String::from(
        "%%MatrixMarket matrix coordinate real symmetric\n% lumped: rotations massless\n",
    );
    let kept: Vec<usize> = (0..n)
        .filter(|&i| !consistent.dof_labels()[i].ends_with(".rz"))
        .collect();
    text.push_str(&format!("{n} {n} {}\n", kept.len()));
    for &i in &kept {
        text.push_str(&format!("{} {} {:.17e}\n", i + 1, i + 1, m[(i, i)]));
    }
    std::fs::write(dir.join("M.mtx"), text).unwrap();
    json
}

/// The `n` lowest eigenvalues of `K(θ) φ = λ M φ` with the massless DOFs condensed out
/// statically, `K̂ = K_mm − K_ms K_ss⁻¹ K_sm` (dense, independent of the solvers), solved in
/// the inverse form `L⁻¹ M_mm L⁻ᵀ` with `K̂ = L Lᵀ` so the lowest come out to full
/// relative precision; with the condensed massless part of each mode, `−K_ss⁻¹ K_sm φ_m`.
fn condensed_modes(model: &Model, theta: &[f64], n_modes: usize) -> (Vec<f64>, faer::Mat<f64>) {
    use faer::linalg::solvers::Solve;
    use faer::{Mat, Side};
    let n = model.n_dof();
    let mut k = Mat::zeros(n, n);
    model.stiffness_dense_into(theta, k.as_mut());
    let m = model.mass_dense();
    let s: Vec<usize> = model.massless_dofs().to_vec();
    let r: Vec<usize> = (0..n).filter(|i| !s.contains(i)).collect();
    let sub = |a: &Mat<f64>, rows: &[usize], cols: &[usize]| {
        Mat::from_fn(rows.len(), cols.len(), |i, j| a[(rows[i], cols[j])])
    };
    let kss = sub(&k, &s, &s).llt(Side::Lower).unwrap();
    let ksr = sub(&k, &s, &r);
    let x = kss.solve(&ksr); // K_ss⁻¹ K_sm
    let khat = sub(&k, &r, &r) - ksr.transpose() * &x;
    let khat = Mat::from_fn(r.len(), r.len(), |i, j| 0.5 * (khat[(i, j)] + khat[(j, i)]));
    let l = khat.llt(Side::Lower).unwrap();
    let mrr = sub(&m, &r, &r);
    let mut c = mrr.clone();
    l.L().solve_lower_triangular_in_place(c.as_mut());
    let mut b = c.transpose().to_owned();
    l.L().solve_lower_triangular_in_place(b.as_mut());
    let b = Mat::from_fn(r.len(), r.len(), |i, j| 0.5 * (b[(i, j)] + b[(j, i)]));
    let evd = b.self_adjoint_eigen(Side::Lower).unwrap();
    let mu = evd.S().column_vector();
    let nr = r.len();
    let lambda: Vec<f64> = (0..n_modes).map(|q| 1.0 / mu[nr - 1 - q]).collect();
    let mut phi = Mat::zeros(n, n_modes);
    for q in 0..n_modes {
        let mut z = Mat::from_fn(nr, 1, |i, _| evd.U()[(i, nr - 1 - q)]);
        l.L()
            .transpose()
            .solve_upper_triangular_in_place(z.as_mut());
        let norm = (z.transpose() * &mrr * &z)[(0, 0)].sqrt();
        let phis = &x * &z * faer::Scale(-1.0 / norm);
        for (a, &i) in r.iter().enumerate() {
            phi[(i, q)] = z[(a, 0)] / norm;
        }
        for (a, &i) in s.iter().enumerate() {
            phi[(i, q)] = phis[(a, 0)];
        }
    }
    (lambda, phi)
}

/// Largest difference between two mode shapes up to sign, relative to the largest entry.
fn shape_gap(a: faer::ColRef<'_, f64>, b: faer::ColRef<'_, f64>) -> f64 {
    let dot: f64 = (0..a.nrows()).map(|i| a[i] * b[i]).sum();
    let sign = dot.signum();
    let scale = (0..a.nrows()).map(|i| a[i].abs()).fold(0.0, f64::max);
    (0..a.nrows())
        .map(|i| (a[i] - sign * b[i]).abs())
        .fold(0.0, f64::max)
        / scale
}

/// Massless DOFs (item 2 of issue 24): the lab frame with lumped masses (58 of 142 DOFs
/// without mass). Both eigen solvers, cold and warm, give the frequencies of the statically
/// condensed problem (1e-10 relative: both are exact to a few ε times the condition of the
/// lowest modes) and its shapes, massless DOFs included (cold: 1e-8 of the largest entry,
/// an eigenvector's error being about its residual, ~1e-10, over the relative gap to the
/// next mode); Nelson's derivatives match central differences; mode matching and the
/// Bayesian MAP (dense and sparse paths) recover θ from noise-free data, and mode matching
/// within 3σ from noisy.
#[test]
fn massless_dofs_are_condensed_exactly() {
    use boltwatch::core::modal::{DenseEigen, EigenSolver, Nelson, SparseEigen};
    use boltwatch::core::updating::bayesian::{BayesProblem, BayesSettings, BayesSolver};
    let dir = tmp_dir("import-massless");
    let json = lumped_lab_frame(&dir);
    let model = load_model(&json).unwrap();
    assert_eq!(model.massless_dofs().len(), 58);
    assert_eq!(model.n_finite_modes(), 84);
    let p = model.n_params();
    let truth: Vec<f64> = (0..p).map(|l| 0.6 + 0.05 * (l % 9) as f64).collect();
    let n_modes = 12;
    let (want, want_phi) = condensed_modes(&model, &truth, n_modes);
    let check = |pairs: &boltwatch::core::modal::EigenPairs, what: &str, shape_tol: f64| {
        for (q, &w) in want.iter().enumerate() {
            let got = pairs.lambda[q];
            assert!(
                ((got - w) / w).abs() <= 1e-10,
                "{what}, mode {}: λ = {got}, condensed {w}",
                q + 1
            );
            let gap = shape_gap(pairs.phi.col(q), want_phi.col(q));
            assert!(
                gap <= shape_tol,
                "{what}, mode {}: shape off by {gap:e}",
                q + 1
            );
        }
    };
    let mut dense = DenseEigen::new(&model).unwrap();
    check(
        &dense.solve(&model, &truth, n_modes).unwrap(),
        "dense",
        1e-8,
    );
    let mut sparse = SparseEigen::new(&model).unwrap();
    check(
        &sparse.solve(&model, &truth, n_modes).unwrap(),
        "sparse",
        1e-8,
    );
    // Warm: from the block at θ0 = 1 to the truth.
    dense.set_warm(true);
    dense.solve(&model, &vec![1.0; p], n_modes).unwrap();
    let (warm, _) = dense
        .solve_warm(&model, &truth, n_modes, n_modes)
        .unwrap()
        .expect("the warm solve converges from θ0 = 1");
    // A warm solve stops at residual STRICT_RESIDUAL = 1e-7: shapes to ~1e-6 (residual
    // over relative gap), eigenvalues to ~1e-14.
    check(&warm, "dense warm", 1e-6);
    // Asking for more modes than DOFs with mass is an error naming the count.
    let err = dense.solve(&model, &truth, 85).unwrap_err().to_string();
    assert!(err.contains("84"), "{err}");

    // Nelson against central differences, step 1e-4 relative: the lowest eigenvalues are
    // exact to ~3e-11 relative (above), which a step of 1e-6 would turn into 1e-4 of the
    // derivative; at 1e-4, truncation (~1e-8) and that error (~1e-6) stay below 1e-5.
    let pairs = dense.solve(&model, &truth, n_modes).unwrap();
    let mut nelson = Nelson::new(&model).unwrap();
    let n = model.n_dof();
    for (q, l) in [(0, 0), (3, 5), (8, p - 1)] {
        let mut dl = vec![0.0; p];
        let mut dphi = faer::Mat::zeros(n, p);
        let phi: Vec<f64> = (0..n).map(|i| pairs.phi[(i, q)]).collect();
        nelson
            .derivatives(
                &model,
                &truth,
                q + 1,
                pairs.lambda[q],
                &phi,
                &mut dl,
                dphi.as_mut(),
            )
            .unwrap();
        let h = 1e-4 * truth[l];
        let at = |sign: f64| {
            let mut t = truth.clone();
            t[l] += sign * h;
            let mut e = DenseEigen::new(&model).unwrap();
            e.solve(&model, &t, n_modes).unwrap()
        };
        let (plus, minus) = (at(1.0), at(-1.0));
        let fd = (plus.lambda[q] - minus.lambda[q]) / (2.0 * h);
        assert!(
            ((dl[l] - fd) / fd).abs() < 1e-5,
            "mode {} θ{}: ∂λ {} against {fd}",
            q + 1,
            l + 1,
            dl[l]
        );
        let scale = (0..n).map(|i| dphi[(i, l)].abs()).fold(0.0, f64::max);
        for i in 0..n {
            let fd = (plus.phi[(i, q)] - minus.phi[(i, q)]) / (2.0 * h);
            assert!(
                (dphi[(i, l)] - fd).abs() < 1e-5 * scale,
                "mode {} θ{} DOF {}: ∂φ {} against {fd}",
                q + 1,
                l + 1,
                model.dof_labels()[i],
                dphi[(i, l)]
            );
        }
    }

    let start = vec![1.0; p];
    let exact = simulated_data(&model, &truth, 9, 0.01, 0.05, false, 3);
    let fit = ModeMatching::new(Evaluator::new(&model).unwrap())
        .run(&model, &exact, &start, &ModeMatchingOptions::default())
        .unwrap();
    for (l, &t) in truth.iter().enumerate() {
        assert!(
            ((fit.theta[l] - t) / t).abs() < 1e-6,
            "mode matching θ{}: {} against {t}",
            l + 1,
            fit.theta[l],
        );
    }
    let settings = BayesSettings {
        sigma_c: 1e3,
        prior_mean: vec![1.0; p],
        prior_std: vec![1000.0; p],
    };
    let mut prob = BayesProblem::new(&model, &exact, &settings).unwrap();
    let res = prob.solve(BayesSolver::Newton, &start, 200).unwrap();
    assert!(res.converged);
    for (l, &t) in truth.iter().enumerate() {
        assert!(
            ((res.state.theta[l] - t) / t).abs() < 1e-4,
            "Bayesian MAP θ{}: {} against {t}",
            l + 1,
            res.state.theta[l],
        );
    }
    // The sparse path of the MAP (large models: sparse φ substeps) reaches the same θ.
    let mut sparse_prob = BayesProblem::new(&model, &exact, &settings).unwrap();
    sparse_prob.force_sparse();
    let sparse_res = sparse_prob.solve(BayesSolver::Newton, &start, 200).unwrap();
    assert!(sparse_res.converged);
    for (l, (x, y)) in res
        .state
        .theta
        .iter()
        .zip(&sparse_res.state.theta)
        .enumerate()
    {
        assert!(
            ((x - y) / x).abs() < 1e-8,
            "Bayesian MAP θ{}: dense {x}, sparse {y}",
            l + 1
        );
    }
    let noisy = simulated_data(&model, &truth, 9, 0.01, 0.05, true, 3);
    let fit = ModeMatching::new(Evaluator::new(&model).unwrap())
        .run(&model, &noisy, &start, &ModeMatchingOptions::default())
        .unwrap();
    let cov = fit.covariance.unwrap();
    for l in 0..p {
        let s = cov[(l, l)].sqrt();
        assert!(
            (fit.theta[l] - truth[l]).abs() < 3.0 * s,
            "noisy θ{}: {} ± {s} against {}",
            l + 1,
            fit.theta[l],
            truth[l]
        );
    }
}

/// A four-DOF model written by hand: `a.x` and `b.x` carry mass, `c.r` and `d.r` none;
/// one parameter `k` (file `K_k.mtx`, lower triangle as given), no `K0` (`null`).
/// `json_extra` is spliced into `model.json`'s top level.
fn tiny_model(
    dir: &Path,
    k: &[(usize, usize, f64)],
    m: &[(usize, usize, f64)],
    json_extra: &str,
) -> PathBuf {
    std::fs::create_dir_all(dir).unwrap();
    let mtx = |entries: &[(usize, usize, f64)]| {
        let mut t = format!(
            "%%MatrixMarket matrix coordinate real symmetric\n4 4 {}\n",
            entries.len()
        );
        for (i, j, v) in entries {
            t.push_str(&format!("{i} {j} {v}\n"));
        }
        t
    };
    std::fs::write(dir.join("K_k.mtx"), mtx(k)).unwrap();
    std::fs::write(dir.join("M.mtx"), mtx(m)).unwrap();
    std::fs::write(dir.join("dofs.txt"), "a.x\nb.x\nc.r\nd.r\n").unwrap();
    let json = dir.join("model.json");
    std::fs::write(
        &json,
        format!(
            r#"{{"schema": "boltwatch.matrices.v1", "structure": "tiny", "n_dof": 4, "k0": null,
 "parameters": [{{"name": "k", "file": "K_k.mtx", "kind": "spring"}}],
 "channels": [{{"name": "a", "dofs": [[0, 1.0]]}}, {{"name": "b", "dofs": [[1, 1.0]]}}]{json_extra}}}"#
        ),
    )
    .unwrap();
    json
}

/// The tiny model's healthy matrices: `a` and `b` grounded and coupled, `c.r` grounded and
/// coupled to `a`, `d.r` grounded.
const TINY_K: [(usize, usize, f64); 7] = [
    (1, 1, 150.0),
    (2, 1, -50.0),
    (2, 2, 130.0),
    (3, 1, -5.0),
    (3, 3, 10.0),
    (4, 4, 20.0),
    (4, 2, 0.0),
];
const TINY_M: [(usize, usize, f64); 2] = [(1, 1, 1.0), (2, 2, 2.0)];

/// Item 5 of issue 24: each malformed model is refused by a command with exit code 2 and
/// a one-line error naming the file and the entry; the healthy tiny model (two massless
/// DOFs, no `K0`) loads and gives its two condensed frequencies.
#[test]
fn malformed_matrices_are_refused_naming_the_file_and_entry() {
    let root = tmp_dir("import-malformed");
    let modes = |json: &Path| {
        Command::new(env!("CARGO_BIN_EXE_boltwatch"))
            .args(["modes", "-n", "2", "--model"])
            .arg(json)
            .arg("-o")
            .arg(json.with_file_name("modes.json"))
            .output()
            .unwrap()
    };
    // Healthy: K̂ = K_mm − K_ms K_ss⁻¹ K_sm on (a, b), then the pencil with diag(1, 2).
    let json = tiny_model(&root.join("healthy"), &TINY_K, &TINY_M, "");
    let out = modes(&json);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let model = load_model(&json).unwrap();
    assert_eq!(model.massless_dofs(), &[2, 3]);
    let (kaa, kab, kbb): (f64, f64, f64) = (150.0 - 5.0 * 5.0 / 10.0, -50.0, 130.0);
    let (m1, m2) = (1.0_f64, 2.0_f64);
    // det(K̂ − λ diag(m1, m2)) = 0.
    let (qa, qb, qc) = (m1 * m2, -(kaa * m2 + kbb * m1), kaa * kbb - kab * kab);
    let disc = (qb * qb - 4.0 * qa * qc).sqrt();
    let want = [(-qb - disc) / (2.0 * qa), (-qb + disc) / (2.0 * qa)];
    let pairs = boltwatch::core::modal::solver_for(&model)
        .unwrap()
        .solve(&model, &[1.0], 2)
        .unwrap();
    for (q, &w) in want.iter().enumerate() {
        assert!(
            ((pairs.lambda[q] - w) / w).abs() < 1e-13,
            "λ{}: {} against {w}",
            q + 1,
            pairs.lambda[q],
        );
    }

    let with = |k: &[(usize, usize, f64)], m: &[(usize, usize, f64)]| (k.to_vec(), m.to_vec());
    let replace = |at: usize, e: (usize, usize, f64)| {
        let mut k = TINY_K.to_vec();
        k[at] = e;
        k
    };
    type Case = (
        &'static str,
        (Vec<(usize, usize, f64)>, Vec<(usize, usize, f64)>),
        &'static str,
        &'static str,
        &'static str,
    );
    let cases: Vec<Case> = vec![
        (
            "negative-mass",
            with(&TINY_K, &[(1, 1, -1.0), (2, 2, 2.0)]),
            "",
            "M.mtx",
            "M, DOF `a.x`: diagonal entry -1 is negative",
        ),
        (
            "indefinite-mass",
            with(&TINY_K, &[(1, 1, 1.0), (2, 2, 2.0), (2, 1, 5.0)]),
            "",
            "M.mtx",
            "M is not positive definite on the DOFs that carry mass",
        ),
        (
            "massless-coupled-mass",
            with(&TINY_K, &[(1, 1, 1.0), (2, 2, 2.0), (3, 1, 0.5)]),
            "",
            "M.mtx",
            "DOF `c.r`: no diagonal mass but M couples it to `a.x`",
        ),
        (
            "massless-unheld",
            (replace(5, (4, 4, 0.0)), TINY_M.to_vec()),
            "",
            "model.json",
            "DOF `d.r` has no mass and K(θ0) is singular on it",
        ),
        (
            "massless-mechanism",
            // c.r and d.r held only by a spring between them.
            (
                vec![
                    (1, 1, 150.0),
                    (2, 1, -50.0),
                    (2, 2, 130.0),
                    (3, 3, 10.0),
                    (4, 3, -10.0),
                    (4, 4, 10.0),
                ],
                TINY_M.to_vec(),
            ),
            "",
            "model.json",
            "K(θ0) at nominal θ is singular on the DOFs without mass",
        ),
        (
            "indefinite-stiffness",
            (replace(1, (2, 1, -500.0)), TINY_M.to_vec()),
            "",
            "model.json",
            "K(θ0) at nominal θ is not positive semi-definite",
        ),
        (
            "free-floating",
            (
                vec![
                    (1, 1, 50.0),
                    (2, 1, -50.0),
                    (2, 2, 50.0),
                    (3, 3, 10.0),
                    (4, 4, 20.0),
                ],
                TINY_M.to_vec(),
            ),
            "",
            "model.json",
            "K(θ0) at nominal θ is singular (to 1e-9 of its largest diagonal entry): its factorization broke down at DOF",
        ),
        (
            "bounds",
            with(&TINY_K, &TINY_M),
            "PARAM:\"nominal\": 1.0, \"lower\": 2.0,",
            "model.json",
            "parameters.k: need 0 ≤ lower ≤ nominal ≤ upper < ∞",
        ),
        (
            "duplicate-parameter",
            with(&TINY_K, &TINY_M),
            ", \"parameters\": [{\"name\": \"k\", \"file\": \"K_k.mtx\"}, {\"name\": \"k\", \"file\": \"K_k.mtx\"}]",
            "model.json",
            "parameters[1].name: `k` is defined twice",
        ),
        (
            "duplicate-location",
            with(&TINY_K, &TINY_M),
            ", \"locations\": [{\"name\": \"top\", \"dofs\": [0]}, {\"name\": \"top\", \"dofs\": [1]}]",
            "model.json",
            "locations[1].name: `top` is defined twice",
        ),
        (
            "location-range",
            with(&TINY_K, &TINY_M),
            ", \"locations\": [{\"name\": \"top\", \"dofs\": [0, 4]}]",
            "model.json",
            "locations.top.dofs: DOF 4 is out of range",
        ),
    ];
    for (name, (k, m), extra, file, want) in cases {
        let dir = root.join(name);
        let json = if let Some(param) = extra.strip_prefix("PARAM:") {
            let json = tiny_model(&dir, &k, &m, "");
            let text = std::fs::read_to_string(&json).unwrap();
            std::fs::write(
                &json,
                text.replace("\"name\": \"k\",", &format!("\"name\": \"k\", {param}")),
            )
            .unwrap();
            json
        } else if extra.contains("\"parameters\"") {
            let json = tiny_model(&dir, &k, &m, "");
            let text = std::fs::read_to_string(&json).unwrap();
            let start = text.find(" \"parameters\"").unwrap();
            let end = text.find("\n \"channels\"").unwrap();
            let text = format!("{}{}{}", &text[..start], &extra[2..], &text[end - 1..]);
            std::fs::write(&json, text).unwrap();
            json
        } else {
            tiny_model(&dir, &k, &m, extra)
        };
        let out = modes(&json);
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{name}: {err}");
        assert!(err.contains(want), "{name}: {err}");
        assert!(
            err.contains(&format!("{name}/{file}")),
            "{name}: the file is named: {err}"
        );
        assert_eq!(err.trim().lines().count(), 1, "{name}: one line: {err}");
    }

    // Files: a non-symmetric `general` matrix, a wrong size, NaN and inf.
    let text = |k: &str| format!("%%MatrixMarket matrix coordinate real {k}\n");
    let file_cases: Vec<(&str, String, &str)> = vec![
        (
            "non-symmetric",
            text("general")
                + "4 4 8\n1 1 150\n2 1 -50\n1 2 -49\n2 2 130\n3 1 -5\n1 3 -5\n3 3 10\n4 4 20\n",
            "not symmetric: entry (2, 1) is -5e1, entry (1, 2) is -4.9e1",
        ),
        (
            "wrong-size",
            text("symmetric") + "3 3 1\n1 1 150\n",
            "line 2: the matrix is 3 × 3, the model has 4 DOFs",
        ),
        (
            "nan",
            text("symmetric") + "4 4 2\n1 1 150\n2 2 NaN\n",
            "line 4: entry (2, 2) is NaN",
        ),
        (
            "inf",
            text("symmetric") + "4 4 2\n1 1 inf\n2 2 130\n",
            "line 3: entry (1, 1) is inf",
        ),
    ];
    for (name, body, want) in file_cases {
        let dir = root.join(name);
        let json = tiny_model(&dir, &TINY_K, &TINY_M, "");
        std::fs::write(dir.join("K_k.mtx"), body).unwrap();
        let out = modes(&json);
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{name}: {err}");
        assert!(err.contains(want), "{name}: {err}");
        assert!(
            err.contains(&format!("{name}/K_k.mtx")),
            "{name}: the file is named: {err}"
        );
    }
}

/// A parameter's `lower` and `upper` in `model.json` hold in mode matching (with no
/// `--bounds`): θ_E of the lab frame, bounded to [0.5, 1] with the data at 1.1, stops at 1
/// and is reported there, the other parameters still fitted; bounds and `locations`
/// survive `export-matrices` of the imported model.
#[test]
fn parameter_bounds_of_an_imported_model_hold() {
    use boltwatch::core::updating::AtBound;
    let toml = format!(
        "{}/config/models/lab-frame.toml",
        env!("CARGO_MANIFEST_DIR")
    );
    let dir = tmp_dir("import-bounds");
    let json = export(Path::new(&toml), &dir.join("a"));
    let text = std::fs::read_to_string(&json).unwrap();
    let text = text
        .replace(
            "\"name\": \"E\",",
            "\"name\": \"E\", \"lower\": 0.5, \"upper\": 1.0,",
        )
        .replace(
            "\"locations\": []",
            "\"locations\": [{\"name\": \"roof\", \"dofs\": [0, 1]}]",
        );
    std::fs::write(&json, &text).unwrap();
    let model = load_model(&json).unwrap();
    let p = model.n_params();
    let e = p - 1;
    assert_eq!(model.parameters()[e].name, "E");
    assert_eq!(model.locations()[0].dofs, vec![0, 1]);
    let mut truth = vec![1.0; p];
    truth[e] = 1.1;
    let data = simulated_data(&model, &truth, 9, 0.01, 0.05, false, 1);
    let fit = ModeMatching::new(Evaluator::new(&model).unwrap())
        .run(
            &model,
            &data,
            &vec![0.7; p],
            &ModeMatchingOptions::default(),
        )
        .unwrap();
    assert_eq!(fit.theta[e], 1.0, "θ_E held at its upper bound");
    assert_eq!(fit.at_bound[e], Some(AtBound::Upper));
    assert!(fit.at_bound[..e].iter().all(|b| b.is_none()));

    let again = export(&json, &dir.join("b"));
    let b = load_model(&again).unwrap();
    assert_eq!(b.parameters()[e].lower, Some(0.5));
    assert_eq!(b.parameters()[e].upper, Some(1.0));
    assert_eq!(b.locations(), model.locations());
}

/// Must-show of issue 24: a model built by another program. `tests/python/
/// independent_model.py` (numpy and scipy, not boltwatch) assembles a 200-DOF cantilever
/// with five segment stiffnesses as parameters and lumped masses (100 massless rotations),
/// writes it with `scipy.io.mmwrite`, and simulates 200 noisy modal sets at θ_true (8
/// modes, 1 % frequency CoV, shapes with per-entry `shape_std` of 1–5 % that differs from
/// channel to channel). boltwatch's frequencies equal the script's (static condensation,
/// `scipy.linalg.eigh`) within what rounding the stiffness entries allows (about 1e-9 in
/// the first mode of this fine beam, 1e-12 and less above); `update` from θ0 = 1 recovers θ_true within 3σ for every
/// parameter of the first set; over all 200 sets the 95 % intervals θ ± 1.96σ cover θ_true
/// in 90–98 % of the 1,000 cases (each parameter's own coverage is printed).
#[test]
fn a_scipy_built_model_is_updated_with_calibrated_sigma() {
    const DRAWS: usize = 200;
    let python = super::common::python_venv(
        "py-scipy-venv",
        "import scipy.sparse.linalg, scipy.io",
        &["scipy==1.14.1"],
    );
    let dir = tmp_dir("import-scipy");
    let script = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/tests/python/independent_model.py"
    );
    let out = Command::new(&python)
        .arg(script)
        .arg(&dir)
        .arg(DRAWS.to_string())
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let truth: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("truth.json")).unwrap()).unwrap();
    let theta_true: Vec<f64> = serde_json::from_value(truth["theta"].clone()).unwrap();
    let json = dir.join("model/model.json");
    let model = load_model(&json).unwrap();
    assert_eq!((model.n_dof(), model.n_params()), (200, 5));
    assert_eq!(model.massless_dofs().len(), 100);
    for (theta, key) in [
        (theta_true.clone(), "frequencies_hz"),
        (vec![1.0; 5], "frequencies_hz_nominal"),
    ] {
        let want: Vec<f64> = serde_json::from_value(truth[key].clone()).unwrap();
        let pairs = boltwatch::core::modal::solver_for(&model)
            .unwrap()
            .solve(&model, &theta, want.len())
            .unwrap();
        // Rounding the stiffness entries alone (relative ε each) moves λ_q by up to
        // ε φᵀ|K|φ: a fine beam's K cancels to ~1e-9 of |K| in its first mode, so two
        // backward-stable solvers agree within that, not to 1e-10.
        let mut k = faer::Mat::zeros(200, 200);
        model.stiffness_dense_into(&theta, k.as_mut());
        for (q, w) in want.iter().enumerate() {
            let f = pairs.frequency_hz(q);
            let phi = pairs.phi.col(q);
            let mut abs_form = 0.0;
            for j in 0..200 {
                for i in 0..200 {
                    abs_form += phi[i].abs() * k[(i, j)].abs() * phi[j].abs();
                }
            }
            let tol = f64::EPSILON * abs_form / pairs.lambda[q];
            assert!(
                ((f - w) / w).abs() <= tol.max(1e-12),
                "{key}, mode {}: {f} Hz, scipy {w} Hz (tolerance {tol:e})",
                q + 1
            );
            if q == 0 {
                println!(
                    "{key}, mode 1: relative difference {:e}, tolerance {tol:e}",
                    (f - w) / w
                );
            }
        }
    }

    let bin = env!("CARGO_BIN_EXE_boltwatch");
    let mut covered = [0usize; 5];
    for k in 0..DRAWS {
        let result = dir.join(format!("update-{k}.json"));
        let out = Command::new(bin)
            .args(["update", "--model"])
            .arg(&json)
            .arg("--data")
            .arg(dir.join(format!("sets/{k}.json")))
            .arg("-o")
            .arg(&result)
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "set {k}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        let doc: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(&result).unwrap()).unwrap();
        assert_eq!(doc["converged"], true, "set {k}");
        assert_eq!(doc["weighting"], "covariance (8)", "set {k}");
        for (l, par) in doc["parameters"].as_array().unwrap().iter().enumerate() {
            let (t, s) = (par["theta"].as_f64().unwrap(), par["std"].as_f64().unwrap());
            let z = (t - theta_true[l]).abs() / s;
            if k == 0 {
                assert!(
                    z < 3.0,
                    "set 0, {}: θ = {t} ± {s}, true {}",
                    par["name"],
                    theta_true[l]
                );
            }
            if z <= 1.96 {
                covered[l] += 1;
            }
        }
    }
    let pooled = covered.iter().sum::<usize>() as f64 / (5 * DRAWS) as f64;
    println!(
        "95 % intervals cover θ_true in {:.1} % of {} cases; per parameter {:?} of {DRAWS}",
        100.0 * pooled,
        5 * DRAWS,
        covered
    );
    assert!(
        (0.90..=0.98).contains(&pooled),
        "coverage {pooled} (per parameter {covered:?} of {DRAWS})"
    );
}

/// `update --method bayesian --stage1-model` (the two-stage update, paper §4.2) with both
/// models imported gives the θ of the same update with the TOML files: each parameter's
/// `elements` carry what it scales, so stage I's θ maps onto stage II as it does for the
/// model files.
#[test]
fn two_stage_update_of_imported_models_matches_the_model_files() {
    let dir = tmp_dir("import-two-stage");
    let models = format!("{}/config/models", env!("CARGO_MANIFEST_DIR"));
    let fine_toml = PathBuf::from(format!("{models}/lab-frame.toml"));
    let coarse_toml = PathBuf::from(format!("{models}/lab-frame-simplified.toml"));
    let fine = export(&fine_toml, &dir.join("fine"));
    let coarse = export(&coarse_toml, &dir.join("coarse"));
    let data = dir.join("set.json");
    let run = |args: &[&std::ffi::OsStr]| {
        let o = Command::new(env!("CARGO_BIN_EXE_boltwatch"))
            .args(args)
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    };
    run(&[
        "simulate".as_ref(),
        "--model".as_ref(),
        fine.as_os_str(),
        "--seed".as_ref(),
        "1".as_ref(),
        "-o".as_ref(),
        data.as_os_str(),
    ]);
    let update = |fine: &Path, coarse: &Path, out: &Path| {
        run(&[
            "update".as_ref(),
            "--method".as_ref(),
            "bayesian".as_ref(),
            "--sigma-c".as_ref(),
            "1e4".as_ref(),
            "--model".as_ref(),
            fine.as_os_str(),
            "--stage1-model".as_ref(),
            coarse.as_os_str(),
            "--data".as_ref(),
            data.as_os_str(),
            "-o".as_ref(),
            out.as_os_str(),
        ]);
        let doc: serde_json::Value = serde_json::from_slice(&std::fs::read(out).unwrap()).unwrap();
        let theta: Vec<f64> = doc["parameters"]
            .as_array()
            .unwrap()
            .iter()
            .map(|p| p["theta"].as_f64().unwrap())
            .collect();
        let from: Vec<String> = doc["stage1"]["mapping"]
            .as_array()
            .unwrap()
            .iter()
            .map(|m| m["from"].to_string())
            .collect();
        (theta, from)
    };
    let (a, from_a) = update(&fine_toml, &coarse_toml, &dir.join("toml.json"));
    let (b, from_b) = update(&fine, &coarse, &dir.join("imported.json"));
    assert_eq!(from_a, from_b, "stage I maps onto the same parameters");
    assert!(from_b.iter().all(|f| f != "null"), "{from_b:?}");
    for (l, (x, y)) in a.iter().zip(&b).enumerate() {
        assert!(((x - y) / x).abs() <= 1e-10, "θ{}: {x} vs {y}", l + 1);
    }
}
