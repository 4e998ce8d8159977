//! Timing of a full mode-matching update of the lab frame, of one residual + Jacobian, of
//! a full Bayesian MAP solve (setup and Newton with σ_c continuation, paper (14)), and of
//! the measured footbridge's update with its global search.
//!
//! Data: noise-drawn modal data simulated once (outside the timed loop) at a fixed truth,
//! 9 modes, all 42 channels, frequency CoV 0.01, shape NSD 0.05, seed 42. The solver is
//! built once and reused across iterations, as in a long-running daemon.

use std::hint::black_box;

use boltwatch::core::model::Model;
use boltwatch::core::simulate::{Noise, simulated_measured_data};
use boltwatch::core::updating::bayesian::{BayesProblem, BayesSettings, BayesSolver};
use boltwatch::core::updating::strategy::{UpdatePolicy, update};
use boltwatch::core::updating::{
    Evaluator, MeasuredData, ModeMatching, ModeMatchingOptions, Pairing,
};
use criterion::{Criterion, criterion_group, criterion_main};

const TRUTH: [f64; 17] = [
    0.8, 1.6, 0.7, 1.2, 0.5, 1.1, 2.5, 0.9, 1.4, 0.6, 1.8, 0.75, 1.3, 0.55, 1.05, 2.2, 0.95,
];
const COV: f64 = 0.01;
const NSD: f64 = 0.05;

fn lab_frame() -> Model {
    let path = format!(
        "{}/config/models/lab-frame.toml",
        env!("CARGO_MANIFEST_DIR")
    );
    let text = std::fs::read_to_string(path).expect("shipped model exists");
    Model::from_toml(&text).expect("shipped model assembles")
}

fn noisy_data(model: &Model) -> MeasuredData {
    let stated = Noise {
        frequency_cov: COV,
        shape_nsd: NSD,
    };
    simulated_measured_data(model, &TRUTH, 9, stated, true, 42).unwrap()
}

fn bench_update(c: &mut Criterion) {
    boltwatch::core::sequential_numerics();
    let model = lab_frame();
    assert_eq!(model.n_params(), 17);
    assert_eq!(model.channels().len(), 42);
    let data = noisy_data(&model);
    let theta0 = [1.0; 17];
    let opts = ModeMatchingOptions::default();

    let mut mm = ModeMatching::new(Evaluator::new(&model).unwrap());
    // Sanity check outside the timing: the benchmarked update converges.
    let res = mm.run(&model, &data, &theta0, &opts).unwrap();
    assert!(
        res.converged(),
        "benchmark update did not converge: {:?}",
        res.termination
    );
    c.bench_function("lab_frame_update_from_theta0_1", |b| {
        b.iter(|| {
            mm.run(
                black_box(&model),
                black_box(&data),
                black_box(&theta0),
                &opts,
            )
            .unwrap()
        })
    });

    // The evaluator remembers the eigenpairs and sensitivities of the last θ: alternate
    // between two θ so every call computes.
    let theta1 = [1.01; 17];
    let mut evaluator = Evaluator::new(&model).unwrap();
    let mut flip = false;
    c.bench_function("lab_frame_evaluate", |b| {
        b.iter(|| {
            flip = !flip;
            let t = if flip { &theta0 } else { &theta1 };
            evaluator
                .evaluate(black_box(&model), black_box(&data), black_box(t))
                .unwrap()
        })
    });
    // The tracker's evaluator: warm eigen solves from the last Ritz block (θ alternating
    // between two points 1 % apart, so every call solves).
    let mut warm = Evaluator::new(&model).unwrap();
    warm.set_warm_start(true);
    c.bench_function("lab_frame_evaluate_warm", |b| {
        b.iter(|| {
            flip = !flip;
            let t = if flip { &theta0 } else { &theta1 };
            warm.evaluate(black_box(&model), black_box(&data), black_box(t))
                .unwrap()
        })
    });
    c.bench_function("lab_frame_evaluate_and_jacobian", |b| {
        b.iter(|| {
            flip = !flip;
            let t = if flip { &theta0 } else { &theta1 };
            let ev = evaluator
                .evaluate(black_box(&model), black_box(&data), black_box(t))
                .unwrap();
            let jac = evaluator.jacobian(&model, &data, &ev).unwrap();
            (ev, jac)
        })
    });
}

/// One full MAP solve from θ0 = 1: setting up (14), then Newton (with σ_c continuation
/// where a cold start stalls). σ_c = 1e4 converges from a cold start; σ_c = 1e2 needs the
/// continuation (a stalled cold start, a cold start at 1e3, two warm stages).
fn bench_bayesian(c: &mut Criterion) {
    boltwatch::core::sequential_numerics();
    let model = lab_frame();
    let data = noisy_data(&model);
    let theta0 = [1.0; 17];
    let mut group = c.benchmark_group("lab_frame_bayesian_map");
    group.sample_size(10);
    for sigma_c in [1e4, 1e2] {
        let settings = BayesSettings {
            sigma_c,
            prior_mean: vec![1.0; 17],
            prior_std: vec![1000.0; 17],
        };
        let solve = || {
            let mut prob = BayesProblem::new(&model, &data, &settings).unwrap();
            prob.solve(BayesSolver::Newton, &theta0, 200).unwrap()
        };
        let res = solve();
        assert!(
            res.converged,
            "benchmark MAP at σ_c = {sigma_c:e} did not converge"
        );
        println!(
            "σ_c = {sigma_c:e}: {} Newton iterations over {} stages",
            res.iterations,
            res.stages.len()
        );
        group.bench_function(format!("sigma_c_{sigma_c:e}"), |b| {
            b.iter(|| black_box(solve()))
        });
    }
    group.finish();
}

/// The lab frame's eigen problem in the dense solver's reduced form: the 27 largest
/// eigenpairs (19 pairing candidates and 8 guard modes) of a 142 × 142 symmetric matrix,
/// by tridiagonalization and inverse iteration, against the full decomposition.
fn bench_dense_eigen(c: &mut Criterion) {
    boltwatch::core::sequential_numerics();
    let n = 142;
    let q = 27;
    let mut s: u64 = 7;
    let r = faer::Mat::<f64>::from_fn(n, n, |_, _| {
        s = s
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (s >> 11) as f64 / (1u64 << 53) as f64 - 0.5
    });
    let qm = r.qr().compute_Q();
    let d = faer::Mat::<f64>::from_fn(
        n,
        n,
        |i, j| if i == j { 1.1_f64.powi(i as i32) } else { 0.0 },
    );
    let b = &qm * &d * qm.transpose();
    let mut partial = boltwatch::core::modal::tridiag::PartialSymEvd::new(n, q);
    c.bench_function("dense_partial_evd_142_largest_27", |bch| {
        bch.iter(|| partial.largest(black_box(&b), q).unwrap())
    });
    c.bench_function("dense_full_evd_142", |bch| {
        bch.iter(|| black_box(&b).self_adjoint_eigen(faer::Side::Lower).unwrap())
    });
}

/// The measured footbridge of the SMU repository (`tests/data/smu-footbridge`: 946 DOFs,
/// 17 bounded parameters, 5 modes on 58 channels), updated as `boltwatch update` does from
/// nominal θ: the fit from θ0, the shape σ rescaled, the global search (32 Sobol starts,
/// seed 1) on every core. The whole update, timed as one.
fn bench_footbridge_search(c: &mut Criterion) {
    let dir = format!("{}/tests/data/smu-footbridge", env!("CARGO_MANIFEST_DIR"));
    let inputs = boltwatch::commands::inputs::load_inputs(
        std::path::Path::new(&format!("{dir}/model.json")),
        std::path::Path::new(&format!("{dir}/data.json")),
        None,
        1.0,
    )
    .unwrap();
    let opts = ModeMatchingOptions {
        bounds: Some((1e-3, 1e3)),
        ..Default::default()
    };
    let run = || {
        let mut ev = Evaluator::new(&inputs.model).unwrap();
        ev.set_warm_start(true);
        ev.set_pairing(Pairing::Misfit);
        let mut mm = ModeMatching::new(ev);
        let policy = UpdatePolicy::default();
        update(
            &mut mm,
            &inputs.model,
            &inputs.data,
            &inputs.theta0,
            &opts,
            &policy,
        )
        .unwrap()
    };
    let up = run();
    assert!(up.search.is_some(), "the footbridge's search did not run");
    let mut group = c.benchmark_group("footbridge");
    group.sample_size(10);
    group.bench_function("update_with_global_search", |b| b.iter(|| black_box(run())));
    group.finish();
}

criterion_group!(
    benches,
    bench_update,
    bench_bayesian,
    bench_dense_eigen,
    bench_footbridge_search
);
criterion_main!(benches);
