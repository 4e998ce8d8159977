//! One mode-matching iteration on the four-bay solid frame (issue 7, paper §5: 7.6 s per
//! iteration on six cores), and its parts: the sparse Cholesky factorization of `K(θ)`, the
//! eigen solve (that factorization and the shift-invert Krylov cycles; full, and relaxed as
//! the evaluator runs it), and the Jacobian (Nelson's method: one `LDLᵀ` of `K − λ_k M`
//! per paired mode, 6 modes × 4 parameters).
//!
//! Data: 6 modes at all 66 channels simulated at the issue's truth θ = (0.36, 0.36, 0.36,
//! 0.5) with 1 % eigenvalue CoV (0.5 % frequency CoV) and 5 % NSD, noise seed 7. Each timed
//! call alternates between θ0 = 1 and a point 1 % away, so nothing is served from the
//! evaluator's memory of the last θ. faer runs on every core (`numerics_for`), as the
//! commands do for a model this size.

use std::hint::black_box;

use boltwatch::core::modal::{EigenSolver, SparseEigen};
use boltwatch::core::model::Model;
use boltwatch::core::simulate::{Noise, simulated_measured_data};
use boltwatch::core::updating::{Evaluator, MeasuredData};
use criterion::{Criterion, criterion_group, criterion_main};
use faer::dyn_stack::{MemBuffer, MemStack};
use faer::linalg::cholesky::llt::factor::LltRegularization;
use faer::sparse::SparseColMatRef;
use faer::{Par, Side};

const TRUTH: [f64; 4] = [0.36, 0.36, 0.36, 0.5];

fn four_bay() -> Model {
    let path = format!(
        "{}/config/models/four-bay-solid.toml",
        env!("CARGO_MANIFEST_DIR")
    );
    Model::from_toml(&std::fs::read_to_string(path).expect("shipped model exists"))
        .expect("shipped model assembles")
}

/// The issue's data (see the module documentation), with faer and the process set up for
/// the model as the commands do.
fn issue_data(model: &Model) -> MeasuredData {
    boltwatch::no_transparent_huge_pages();
    boltwatch::core::numerics_for(model);
    let stated = Noise {
        frequency_cov: 0.005,
        shape_nsd: 0.05,
    };
    simulated_measured_data(model, &TRUTH, 6, stated, true, 7).unwrap()
}

fn bench_iteration(c: &mut Criterion) {
    let model = four_bay();
    let data = issue_data(&model);
    let thetas = [[1.0; 4], [1.01; 4]];
    let mut flip = 0;
    let mut group = c.benchmark_group("four_bay_solid");
    group.sample_size(10);

    // As the eigen solver factorizes: sequentially, into storage kept between calls, on the
    // model's reordered lower triangle (`Model::reordered`).
    let order = model.reordered().unwrap();
    let symbolic = &order.symbolic;
    let mut l_values = vec![0.0; symbolic.len_val()];
    let mut mem =
        MemBuffer::new(symbolic.factorize_numeric_llt_scratch::<f64>(Par::Seq, Default::default()));
    let mut values = vec![0.0; order.len()];
    group.bench_function("factorization", |b| {
        b.iter(|| {
            flip ^= 1;
            model.shifted_stiffness_reordered(order, &thetas[flip], 0.0, &mut values);
            let k = SparseColMatRef::new(order.lower.as_ref(), &values);
            symbolic
                .factorize_numeric_llt(
                    &mut l_values,
                    k,
                    Side::Lower,
                    LltRegularization::default(),
                    Par::Seq,
                    MemStack::new(&mut mem),
                    Default::default(),
                )
                .unwrap();
            black_box(&l_values);
        })
    });

    // The evaluator's solve: 16 modes (the 6 measured and 10 candidates for pairing).
    let n_cand = boltwatch::core::updating::residual::candidate_count(6, model.n_dof());
    let mut solver = SparseEigen::new(&model).unwrap();
    group.bench_function("eigen_solve", |b| {
        b.iter(|| {
            flip ^= 1;
            black_box(solver.solve(&model, &thetas[flip], n_cand).unwrap())
        })
    });

    // As the evaluator solves: the 6 measured modes exact, the 10 candidates to pairing
    // accuracy ([`EigenSolver::solve_relaxed`]).
    group.bench_function("eigen_solve_relaxed", |b| {
        b.iter(|| {
            flip ^= 1;
            black_box(
                solver
                    .solve_relaxed(&model, &thetas[flip], n_cand, 6)
                    .unwrap(),
            )
        })
    });

    let mut evaluator = Evaluator::new(&model).unwrap();
    let evs = thetas.map(|t| evaluator.evaluate(&model, &data, &t).unwrap());
    group.bench_function("jacobian", |b| {
        b.iter(|| {
            // Alternate the evaluation so the sensitivities are never reused.
            flip ^= 1;
            black_box(evaluator.jacobian(&model, &data, &evs[flip]).unwrap())
        })
    });

    group.bench_function("iteration", |b| {
        b.iter(|| {
            flip ^= 1;
            let ev = evaluator.evaluate(&model, &data, &thetas[flip]).unwrap();
            black_box(evaluator.jacobian(&model, &data, &ev).unwrap())
        })
    });
    group.finish();
}

/// One iteration of the Bayesian MAP on the same data (σ_c = 100, at λ̂ and θ0 = 1, and 1 %
/// away): the φ substep (21) for the six modes, which is the alternating solver's
/// iteration (its substeps (22)–(23) are a few sparse products), and the reduced
/// objective with its gradient and Hessian, which is a Newton iteration. Each mode is one
/// sparse LDLᵀ of its shifted stiffness (31,458 unknowns) and 66 solves for the data term
/// (`bayesian/shifted.rs`).
fn bench_bayesian(c: &mut Criterion) {
    use boltwatch::core::updating::bayesian::{BayesProblem, BayesSettings};
    let model = four_bay();
    let data = issue_data(&model);
    let settings = BayesSettings {
        sigma_c: 100.0,
        prior_mean: vec![1.0; 4],
        prior_std: vec![1e5; 4],
    };
    let prob = BayesProblem::new(&model, &data, &settings).unwrap();
    let lambda = prob.lambda_hat();
    let thetas = [[1.0; 4], [1.01; 4]];
    let mut flip = 0;
    let mut group = c.benchmark_group("four_bay_bayesian");
    group.sample_size(10);
    group.bench_function("phi_substep", |b| {
        b.iter(|| {
            flip ^= 1;
            black_box(prob.optimal_phi(&lambda, &thetas[flip]).unwrap())
        })
    });
    group.bench_function("reduced_newton", |b| {
        b.iter(|| {
            flip ^= 1;
            black_box(prob.reduced(&lambda, &thetas[flip]).unwrap())
        })
    });
    group.finish();
}

criterion_group!(benches, bench_iteration, bench_bayesian);
criterion_main!(benches);
