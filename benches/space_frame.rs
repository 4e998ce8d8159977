//! The space frame's speed (issue 25): one full mode-matching update from θ0 = 1 (15
//! noisy modes, 1 % frequency CoV, 5 % shape NSD; 596 DOF, 30 parameters, 78 channels),
//! and one warm-started tracker update per modal set (the healthy scenario with 15 modes,
//! commissioned outside the timing); and the two eigen solvers on the space frame and the
//! lab frame, the measurement behind `SPARSE_FROM_DOF`.

use std::hint::black_box;
use std::time::{Duration, Instant};

use boltwatch::core::model::Model;
use boltwatch::core::model::spec::ModelSpec;
use boltwatch::core::simulate::{Noise, simulated_measured_data};
use boltwatch::core::updating::{Evaluator, ModeMatching, ModeMatchingOptions};
use boltwatch::pipeline::{Tracker, TrackerConfig};
use boltwatch::scenario::Scenario;
use criterion::{Criterion, criterion_group, criterion_main};

fn spec() -> ModelSpec {
    model_spec("space-frame")
}

fn model_spec(name: &str) -> ModelSpec {
    let path = format!("{}/config/models/{name}.toml", env!("CARGO_MANIFEST_DIR"));
    toml::from_str(&std::fs::read_to_string(path).expect("shipped model")).expect("model parses")
}

fn bench_full_update(c: &mut Criterion) {
    boltwatch::core::sequential_numerics();
    let model = Model::from_spec(&spec()).unwrap();
    let p = model.n_params();
    // A truth with every connection moved (0.7 … 1.3), the weak-axis group and E at 1.
    let truth: Vec<f64> = (0..p)
        .map(|l| {
            if l + 2 < p {
                0.7 + 0.6 * (l % 7) as f64 / 6.0
            } else {
                1.0
            }
        })
        .collect();
    let stated = Noise {
        frequency_cov: 0.01,
        shape_nsd: 0.05,
    };
    let data = simulated_measured_data(&model, &truth, 15, stated, true, 42).unwrap();
    let theta0 = vec![1.0; p];
    let opts = ModeMatchingOptions::default();
    let mut mm = ModeMatching::new(Evaluator::new(&model).unwrap());
    let res = mm.run(&model, &data, &theta0, &opts).unwrap();
    assert!(res.converged(), "{:?}", res.termination);
    println!(
        "space frame update from θ0 = 1: {} iterations, {} evaluations",
        res.iterations, res.evaluations
    );
    let mut group = c.benchmark_group("space_frame");
    group.sample_size(20);
    group.bench_function("update_from_theta0_1", |b| {
        b.iter(|| {
            mm.run(black_box(&model), black_box(&data), &theta0, &opts)
                .unwrap()
        })
    });
    group.finish();
}

fn bench_warm_update(c: &mut Criterion) {
    boltwatch::core::sequential_numerics();
    let spec = spec();
    let model = Model::from_spec(&spec).unwrap();
    let mut sc = Scenario::named("healthy", &model, None, None).unwrap();
    sc.modes = 15;
    sc.sets = 600;
    sc.days = 600.0 * 0.006;
    let mut sets = Vec::new();
    sc.generate(&spec, |_, set, _| {
        sets.push(serde_json::to_vec(&set.to_json()).unwrap());
        Ok(())
    })
    .unwrap();
    let config = TrackerConfig {
        crosscheck_every_sets: 0,
        crosscheck_every_s: 0.0,
        ..TrackerConfig::default()
    };
    let t0 = chrono::Utc::now();
    let mut tracker = Tracker::new(model.clone(), config.clone()).unwrap();
    for s in &sets[..50] {
        tracker.handle(t0, s);
    }
    let commissioned = tracker.checkpoint();
    let mut next = 50;
    c.bench_function("space_frame_tracker_warm_update_per_set", |b| {
        b.iter_custom(|iters| {
            let mut total = Duration::ZERO;
            for _ in 0..iters {
                if next == sets.len() {
                    tracker = Tracker::restore(model.clone(), config.clone(), commissioned.clone())
                        .unwrap();
                    next = 50;
                }
                let start = Instant::now();
                black_box(tracker.handle(t0, &sets[next]));
                total += start.elapsed();
                next += 1;
            }
            total
        })
    });
    // The timed sets include any cold restart the tracker needed: the figure is what a
    // deployment sees. How many there were is printed beside it.
    println!(
        "space frame tracker: {} cold starts (the first set's included) since the last restore",
        tracker.state().cold_starts
    );
}

/// One full solve of the lowest modes by each solver: the dense one's `O(n³)` reduction
/// against the sparse shift-invert Krylov solver, on the 142-DOF lab frame (12 modes) and
/// the 596-DOF space frame (15 modes).
fn bench_solvers(c: &mut Criterion) {
    use boltwatch::core::modal::{DenseEigen, EigenSolver, SparseEigen};
    boltwatch::core::sequential_numerics();
    let mut group = c.benchmark_group("eigen_solve");
    for (name, modes) in [("lab-frame", 12), ("space-frame", 15)] {
        let model = Model::from_spec(&model_spec(name)).unwrap();
        let theta = model.nominal_theta();
        let mut dense = DenseEigen::new(&model).unwrap();
        let mut sparse = SparseEigen::new(&model).unwrap();
        group.bench_function(format!("{name}_{}_dof_dense", model.n_dof()), |b| {
            b.iter(|| dense.solve(black_box(&model), &theta, modes).unwrap())
        });
        group.bench_function(format!("{name}_{}_dof_sparse", model.n_dof()), |b| {
            b.iter(|| sparse.solve(black_box(&model), &theta, modes).unwrap())
        });
    }
    group.finish();
}

criterion_group!(benches, bench_solvers, bench_full_update, bench_warm_update);
criterion_main!(benches);
