//! The four-bay solid frame (paper §5): its modes against SciPy, and both updates on it.

use boltwatch::core::model::Model;
use faer::Side;

use super::solid::{four_bay, four_bay_text, two_bay_coarse};

/// `boltwatch modes -n 12` on the four-bay model against SciPy's `eigsh` in shift-invert
/// mode (σ = 0, its ARPACK Lanczos on a SuperLU factorization) on the matrices
/// `boltwatch export-matrices` wrote: the same 12 frequencies to 1e-6 relative (both
/// converge the eigenvalues to near machine precision; 1e-6 is the issue's bound and leaves
/// room for the 17-digit round trip through the files). Both run as whole processes; their
/// times are printed (the figures in docs/design/models.md come from a release build), never
/// asserted.
#[test]
#[cfg_attr(
    not(feature = "slow-tests"),
    ignore = "slow tier: cargo test --features slow-tests"
)]
fn modes_match_scipy_eigsh_on_the_exported_four_bay_matrices() {
    use super::common::run_timed;
    let python = super::common::python_venv(
        "py-scipy-venv",
        "import scipy.sparse.linalg, scipy.io",
        &["scipy==1.14.1"],
    );
    let dir = std::env::temp_dir().join(format!("bw-solid-export-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let model = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/config/models/four-bay-solid.toml"
    );
    let bin = env!("CARGO_BIN_EXE_boltwatch");
    let matrices = dir.join("matrices");
    run_timed(
        bin,
        &[
            "export-matrices",
            "--model",
            model,
            "-o",
            matrices.to_str().unwrap(),
        ],
    );
    let ours_json = dir.join("modes.json");
    let (ours_s, _) = run_timed(
        bin,
        &[
            "modes",
            "--model",
            model,
            "-n",
            "12",
            "-o",
            ours_json.to_str().unwrap(),
        ],
    );
    let ours: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&ours_json).unwrap()).unwrap();
    let script = r#"
import json, sys
import numpy as np, scipy.io, scipy.sparse.linalg as sla
d = sys.argv[1]
meta = json.load(open(d + "/model.json"))
K = scipy.io.mmread(d + "/K0.mtx").tocsc()
for p in meta["parameters"]:
    K = K + p["nominal"] * scipy.io.mmread(d + "/" + p["file"]).tocsc()
M = scipy.io.mmread(d + "/M.mtx").tocsc()
lam = np.sort(sla.eigsh(K, k=12, M=M, sigma=0.0, which="LM", return_eigenvectors=False))
print(json.dumps((np.sqrt(lam) / (2 * np.pi)).tolist()))
"#;
    let (scipy_s, stdout) = run_timed(
        python.to_str().unwrap(),
        &["-c", script, matrices.to_str().unwrap()],
    );
    let scipy: Vec<f64> = serde_json::from_slice(&stdout).unwrap();
    let mut worst: f64 = 0.0;
    for (k, f) in scipy.iter().enumerate() {
        let mine = ours["frequencies_hz"][k].as_f64().unwrap();
        worst = worst.max((mine - f).abs() / f);
        println!(
            "mode {:>2}: boltwatch {mine:>10.4} Hz, scipy {f:>10.4} Hz",
            k + 1
        );
    }
    println!(
        "largest relative difference {worst:.1e}; whole process: boltwatch modes {ours_s:.2} s, \
         scipy eigsh (shift-invert) {scipy_s:.2} s"
    );
    assert!(worst < 1e-6, "frequencies differ by {worst:e}");
    std::fs::remove_dir_all(&dir).ok();
}

/// The issue's updating case on the four-bay model: data simulated at
/// θ = (0.36, 0.36, 0.36, 0.5), 6 modes at all 66 channels, 1 % eigenvalue CoV (0.5 %
/// frequency CoV) and 5 % NSD, with noise (seed 7); mode matching from θ0 = 1 converges in
/// at most 20 iterations to within 3σ (15) of the truth in every parameter. θ4 (every
/// out-of-plane spring) is practically unidentifiable from these modes (σ(θ4) = 0.43 at
/// the truth from noise-free data): for this noise draw ε keeps falling, by less than
/// 1e-3 per iteration, as θ4 → ∞, and unbounded the fit runs off and stalls. With the
/// `update` command's bounds (1e-3…1e3 × nominal) it stops at θ4 = 1000, reported at its
/// upper bound, σ(θ4) ≈ 1.7e6, while θ1–θ3 converge (measured: 7 iterations, θ1–θ3 within
/// 0.7σ).
#[test]
#[cfg_attr(
    not(feature = "slow-tests"),
    ignore = "slow tier: cargo test --features slow-tests"
)]
fn mode_matching_recovers_the_four_bay_truth() {
    use boltwatch::core::updating::{AtBound, Evaluator, ModeMatching, ModeMatchingOptions};
    let model = four_bay();
    let truth = [0.36, 0.36, 0.36, 0.5];
    let data = super::common::simulated_data(&model, &truth, 6, 0.005, 0.05, true, 7);
    let mut mm = ModeMatching::new(Evaluator::new(&model).unwrap());
    let opts = ModeMatchingOptions {
        bounds: Some((1e-3, 1e3)),
        ..Default::default()
    };
    let res = mm.run(&model, &data, &[1.0; 4], &opts).unwrap();
    let std = res.std();
    for (l, p) in model.parameters().iter().enumerate() {
        println!(
            "{:<12} {:.4} ± {:.4} (truth {}, {:+.2}σ) {:?}",
            p.name,
            res.theta[l],
            std[l],
            truth[l],
            (res.theta[l] - truth[l]) / std[l],
            res.at_bound[l]
        );
    }
    println!(
        "{:?} after {} iterations ({} evaluations), ε = {:.3}",
        res.termination,
        res.iterations,
        res.evaluations,
        res.epsilon()
    );
    assert!(
        res.converged() && res.iterations <= 20,
        "{:?}",
        res.termination
    );
    assert!(res.at_bound[..3].iter().all(Option::is_none));
    assert_ne!(res.at_bound[3], Some(AtBound::Lower));
    for l in 0..4 {
        assert!(
            (res.theta[l] - truth[l]).abs() < 3.0 * std[l],
            "{}: {} ± {} vs {}",
            model.parameters()[l].name,
            res.theta[l],
            std[l],
            truth[l]
        );
    }
}

/// The mode-matching Jacobian of a model large enough for the sparse path (two-bay frame,
/// 2,232 DOF: the paired modes are differentiated by Nelson's method on one thread per
/// core) against central differences of the residual, 6 noisy modes at all channels, at
/// θ = (0.5, 0.6, 0.7, 0.8), step 1e-3 relative. Each column's difference is measured
/// against the largest column's norm (θ4, the out-of-plane springs, does not move these
/// six modes, which are in-plane: its own column is ~4e-14 of the largest). Tolerance
/// 1e-5: the quotient's truncation error is O(h²) ≈ 1e-6, and the eigen solver's residual
/// divided by h adds ~1e-7 (the evaluator's relaxed solve targets 1e-7 for these modes
/// but reaches ≤ 6e-10, see `the_relaxed_sparse_solve_keeps_its_targets`); measured ≤
/// 1.8e-6. Smaller steps show the solver's noise
/// (1e-4: up to 2e-5; 1e-5: up to 4e-4), larger ones the truncation.
#[test]
fn sparse_jacobian_matches_central_differences() {
    use boltwatch::core::updating::Evaluator;
    let model = two_bay_coarse();
    boltwatch::core::numerics_for(&model);
    let data =
        super::common::simulated_data(&model, &[0.36, 0.36, 0.36, 0.5], 6, 0.005, 0.05, true, 3);
    let mut ev = Evaluator::new(&model).unwrap();
    let theta = [0.5, 0.6, 0.7, 0.8];
    let at = ev.evaluate(&model, &data, &theta).unwrap();
    let jac = ev.jacobian(&model, &data, &at).unwrap();
    let scale = (0..4).map(|l| jac.col(l).norm_l2()).fold(0.0_f64, f64::max);
    for l in 0..4 {
        let h = 1e-3 * theta[l];
        let mut r = |d: f64| {
            let mut t = theta;
            t[l] += d;
            let e = ev.evaluate(&model, &data, &t).unwrap();
            assert_eq!(e.pairing, at.pairing);
            e.r
        };
        let (rp, rm) = (r(h), r(-h));
        let err = (0..rp.len())
            .map(|i| ((rp[i] - rm[i]) / (2.0 * h) - jac[(i, l)]).powi(2))
            .sum::<f64>()
            .sqrt()
            / scale;
        println!("θ{}: difference {err:.2e} of the largest column", l + 1);
        assert!(err < 1e-5, "θ{}: {err:e}", l + 1);
    }
}

/// The Bayesian MAP's Newton solver on a coarser four-bay frame (the model file's
/// construction with 14 × 1 × 1 elements per beam: 9,096 DOF, sparse φ substeps), the
/// issue's case: 6 modes at all 66 channels, 0.5 % frequency CoV, 5 % NSD, σ_c = 1e3,
/// prior std 1000, from θ0 = 1, through [`BayesProblem::solve`] as the command runs it.
/// F has negative curvature between θ0 and the MAP; the Levenberg–Marquardt damping this
/// solver had before its trust region crept ~6 % per iteration there and had not converged
/// after 60 iterations on the noisy case. Now (measured): noise-free data, 10 iterations
/// to the truth within 5e-7 relative (the prior's pull); noisy (seed 1), 12 iterations to
/// a minimum within 2.5 posterior σ of the truth in every parameter. Asserted: the cold
/// start converges (one stage) within 20 iterations, at a positive definite reduced
/// Hessian; the truth recovered to 1e-4 from noise-free data, within 3σ from noisy data.
#[test]
#[cfg_attr(
    not(feature = "slow-tests"),
    ignore = "slow tier: cargo test --features slow-tests"
)]
fn bayesian_newton_converges_on_a_coarse_four_bay_frame() {
    use boltwatch::core::updating::bayesian::{BayesProblem, BayesSettings, BayesSolver};
    let text = four_bay_text().replace("divisions = [28, 1, 3]", "divisions = [14, 1, 1]");
    let model = Model::from_toml(&text).unwrap();
    assert_eq!(model.n_dof(), 9096);
    let truth = [0.36, 0.36, 0.36, 0.5];
    let settings = BayesSettings {
        sigma_c: 1e3,
        prior_mean: vec![1.0; 4],
        prior_std: vec![1000.0; 4],
    };
    for noisy in [false, true] {
        let data = super::common::simulated_data(&model, &truth, 6, 0.005, 0.05, noisy, 1);
        let mut prob = BayesProblem::new(&model, &data, &settings).unwrap();
        assert!(prob.is_sparse());
        let res = prob.solve(BayesSolver::Newton, &[1.0; 4], 100).unwrap();
        let std = prob
            .threshold_free_covariance(&res.state)
            .unwrap()
            .posterior_theta_std();
        println!(
            "noisy {noisy}: {} iterations, converged {}, stages {}, θ = {:?}, std {:?}",
            res.iterations,
            res.converged,
            res.stages.len(),
            res.state.theta,
            std
        );
        assert!(res.converged && res.stages.len() == 1 && res.iterations <= 20);
        let red = prob.reduced(&res.state.lambda, &res.state.theta).unwrap();
        assert!(red.hessian.llt(Side::Lower).is_ok(), "not a minimum");
        for l in 0..4 {
            let (t, want) = (res.state.theta[l], truth[l]);
            if noisy {
                assert!(
                    (t - want).abs() < 3.0 * std[l],
                    "θ{}: {t} ± {}",
                    l + 1,
                    std[l]
                );
            } else {
                assert!((t - want).abs() < 1e-4 * want, "θ{}: {t}", l + 1);
            }
        }
    }
}

/// Peak RSS (bytes) of a command run to completion: its `VmHWM`, read every 10 ms while it
/// runs (the high-water mark of its own address space; `wait4`'s `ru_maxrss` would include
/// this test process's RSS at the fork), its output to `log`.
fn peak_rss(cmd: &mut std::process::Command, log: &std::path::Path) -> u64 {
    use std::process::Stdio;
    let out = std::fs::File::create(log).unwrap();
    let mut child = cmd
        .stdout(Stdio::null())
        .stderr(Stdio::from(out))
        .spawn()
        .unwrap();
    let mut peak_kib = 0u64;
    let status = loop {
        if let Some(kib) = super::daemon::read_vm_hwm_kib(child.id() as i32) {
            peak_kib = peak_kib.max(kib);
        }
        if let Some(status) = child.try_wait().unwrap() {
            break status;
        }
        std::thread::sleep(std::time::Duration::from_millis(10));
    };
    assert!(
        status.success(),
        "{cmd:?} failed: {}",
        std::fs::read_to_string(log).unwrap_or_default()
    );
    peak_kib * 1024
}

/// Issue 27: the Bayesian MAP of the four-bay frame on the issue's data (seed 1, σ_c =
/// 1e3) peaks below 1 GiB, whole process; and its memory estimate
/// (`bayesian::map_memory_bytes`, what the daemon's budget check uses) covers what the
/// MAP adds to a process that holds the model and mode matching's solvers: the peak of
/// `update --method bayesian` (the MAP, its covariance and the mode-matching comparison)
/// is at most that of `update` (mode matching) plus the estimate, and the estimate is not
/// above the whole peak (it is an estimate, not a blanket).
#[test]
#[cfg_attr(
    not(feature = "slow-tests"),
    ignore = "slow tier: cargo test --features slow-tests"
)]
fn the_bayesian_map_stays_within_its_memory_estimate_on_the_four_bay_frame() {
    use std::process::Command;
    let dir = std::env::temp_dir().join(format!("bw-solid-memory-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let model = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/config/models/four-bay-solid.toml"
    );
    let bin = env!("CARGO_BIN_EXE_boltwatch");
    let data = dir.join("d.json");
    let data_s = data.to_str().unwrap();
    let out = Command::new(bin)
        .args([
            "simulate",
            "--model",
            model,
            "--theta",
            "0.36,0.36,0.36,0.5",
        ])
        .args([
            "--modes",
            "6",
            "--freq-cov",
            "0.005",
            "--seed",
            "1",
            "-o",
            data_s,
        ])
        .output()
        .unwrap();
    assert!(out.status.success());
    let mm = peak_rss(
        Command::new(bin)
            .args(["update", "--model", model, "--data", data_s, "-o"])
            .arg(dir.join("mm.json")),
        &dir.join("mm.log"),
    );
    let map = peak_rss(
        Command::new(bin)
            .args([
                "update",
                "--method",
                "bayesian",
                "--sigma-c",
                "1e3",
                "--no-tsvd",
            ])
            .args(["--model", model, "--data", data_s, "-o"])
            .arg(dir.join("map.json")),
        &dir.join("map.log"),
    );
    let estimate =
        boltwatch::core::updating::bayesian::map_memory_bytes(&four_bay(), 6, 66).unwrap();
    let mib = |b: u64| b as f64 / (1 << 20) as f64;
    println!(
        "four-bay peak RSS: mode matching {:.0} MiB, Bayesian MAP (with covariance and comparison) {:.0} MiB; MAP estimate {:.0} MiB",
        mib(mm),
        mib(map),
        mib(estimate)
    );
    assert!(map < 1 << 30, "the MAP peaked at {:.0} MiB", mib(map));
    assert!(
        map <= mm + estimate,
        "the MAP added {:.0} MiB, over its estimate",
        mib(map.saturating_sub(mm))
    );
    assert!(estimate <= map, "the estimate is above the whole peak");
}

/// Which models hand their assembly's and ordering's scratch back to the system
/// ([`boltwatch::release_scratch`]): the four-bay frame's hundreds of MB do, the space
/// frame's and the lab frame's few MB (reused by the next model a diagnosis builds) do not.
#[test]
#[cfg_attr(
    not(feature = "slow-tests"),
    ignore = "slow tier: cargo test --features slow-tests"
)]
fn only_large_models_release_their_scratch() {
    let limit = boltwatch::RELEASE_SCRATCH_FROM_BYTES;
    let big = four_bay().matrix_bytes();
    assert!(big >= limit, "four-bay: {big} bytes");
    for name in ["space-frame", "lab-frame"] {
        let small = 2 * super::common::load_model(name).matrix_bytes();
        assert!(small < limit / 4, "{name}: twice {small} bytes");
    }
}
