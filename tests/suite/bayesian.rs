//! Bayesian MAP (14): derivatives against central differences, and the Newton solver on the
//! reduced problem against the paper's alternating substeps (21)–(23).

use boltwatch::core::updating::bayesian::{BayesProblem, BayesSettings, BayesState};
use faer::Mat;

use super::common::{load_model, simulated_data};

/// 5-point central difference of `f` at `x` along coordinate `i` with step `h`.
fn fd5(f: &dyn Fn(&[f64]) -> f64, x: &[f64], i: usize, h: f64) -> f64 {
    let at = |d: f64| {
        let mut y = x.to_vec();
        y[i] += d;
        f(&y)
    };
    (-at(2.0 * h) + 8.0 * at(h) - 8.0 * at(-h) + at(-2.0 * h)) / (12.0 * h)
}

/// Spread connection stiffnesses of the lab frame (θ17: the modulus factor).
const LAB_TRUTH: [f64; 17] = [
    0.8, 1.6, 0.7, 1.2, 0.5, 1.1, 2.5, 0.9, 1.4, 0.6, 1.8, 0.75, 1.3, 0.55, 1.05, 2.2, 0.95,
];

fn cantilever_problem(sigma_c: f64) -> (BayesProblem, usize) {
    let truth = load_model("cantilever-truth");
    let model = load_model("cantilever-case1");
    let data = simulated_data(&truth, &[0.5], 4, 0.01, 0.01, true, 27);
    let settings = BayesSettings {
        sigma_c,
        prior_mean: vec![1.0],
        prior_std: vec![10.0],
    };
    (
        BayesProblem::new(&model, &data, &settings).unwrap(),
        model.n_dof(),
    )
}

/// The gradient of J_p (14) with respect to every λ_m, every entry of every φ_m and θ,
/// against 5-point central differences at a state away from the minimum (cantilever case
/// I data, σ_c = 10). Steps: 1e-4 relative for λ and θ, 1e-4 of max|φ| for φ. Tolerance
/// 1e-6 of the block's gradient norm: the truncation error of the 5-point rule is O(h⁴)
/// and J_p is a polynomial of degree ≤ 4 in each coordinate, so the differences are exact
/// up to rounding, ~ε·J_p/h ≈ 1e-10 relative here.
#[test]
fn objective_gradient_matches_central_differences() {
    let (prob, n) = cantilever_problem(10.0);
    let nm = prob.n_modes();
    let lambda: Vec<f64> = prob
        .lambda_hat()
        .iter()
        .enumerate()
        .map(|(m, l)| l * (1.0 + 0.01 * (m as f64 - 1.5)))
        .collect();
    let theta = vec![0.7];
    let mut phi = prob.optimal_phi(&lambda, &theta).unwrap();
    for m in 0..nm {
        for i in 0..n {
            phi[(i, m)] *= 1.0 + 0.05 * ((i * 7 + m * 3) % 5) as f64 / 5.0;
        }
    }
    let pack = |l: &[f64], ph: &Mat<f64>, t: &[f64]| -> Vec<f64> {
        let mut x = l.to_vec();
        for m in 0..nm {
            x.extend((0..n).map(|i| ph[(i, m)]));
        }
        x.extend_from_slice(t);
        x
    };
    let unpack = |x: &[f64]| BayesState {
        lambda: x[..nm].to_vec(),
        phi: Mat::from_fn(n, nm, |i, m| x[nm + m * n + i]),
        theta: x[nm + n * nm..].to_vec(),
    };
    let x = pack(&lambda, &phi, &theta);
    let g = prob.gradient(&unpack(&x));
    let f = |y: &[f64]| prob.objective(&unpack(y)).total;
    let phi_max = (0..n * nm).fold(0.0_f64, |a, i| a.max(x[nm + i].abs()));
    let blocks = [
        ("λ", 0..nm),
        ("φ", nm..nm + n * nm),
        ("θ", nm + n * nm..x.len()),
    ];
    for (name, range) in blocks {
        let mut err = 0.0_f64;
        let mut norm = 0.0_f64;
        for i in range {
            let h = if name == "φ" {
                1e-4 * phi_max
            } else {
                1e-4 * x[i].abs()
            };
            let d = fd5(&f, &x, i, h);
            err += (d - g[i]).powi(2);
            norm += g[i].powi(2);
        }
        let rel = (err / norm).sqrt();
        println!(
            "∂J_p/∂{name}: relative error {rel:.2e} (norm {:.3e})",
            norm.sqrt()
        );
        assert!(rel < 1e-6, "∂J_p/∂{name}: relative error {rel:e}");
    }
}

/// The reduced objective F(λ, θ) = min_φ J_p: its gradient against 5-point differences of
/// F, and its Hessian (the Schur complement of (16)) against differences of the gradient,
/// at a point away from the minimum. Tolerance 1e-5 relative (normwise per column): F is
/// not polynomial (φ* is rational in (λ, θ)), so truncation O(h⁴) with h = 1e-4 relative
/// plus the rounding of the φ solves bounds the agreement.
#[test]
fn reduced_gradient_and_hessian_match_central_differences() {
    let (prob, _) = cantilever_problem(10.0);
    let nm = prob.n_modes();
    let mut y: Vec<f64> = prob.lambda_hat().iter().map(|l| l * 1.003).collect();
    y.push(0.6);
    let red = prob.reduced(&y[..nm], &y[nm..]).unwrap();
    let f = |z: &[f64]| prob.reduced(&z[..nm], &z[nm..]).unwrap().value;
    let mut err = 0.0_f64;
    let mut norm = 0.0_f64;
    for i in 0..y.len() {
        let d = fd5(&f, &y, i, 1e-4 * y[i].abs());
        err += ((d - red.gradient[i]) * y[i]).powi(2);
        norm += (red.gradient[i] * y[i]).powi(2);
    }
    let rel_g = (err / norm).sqrt();
    println!("reduced gradient: relative error {rel_g:.2e}");
    assert!(rel_g < 1e-5, "reduced gradient: {rel_g:e}");
    for j in 0..y.len() {
        let h = 1e-4 * y[j].abs();
        let gj = |d: f64| {
            let mut z = y.clone();
            z[j] += d;
            prob.reduced(&z[..nm], &z[nm..]).unwrap().gradient
        };
        let (gp2, gp1, gm1, gm2) = (gj(2.0 * h), gj(h), gj(-h), gj(-2.0 * h));
        let mut err = 0.0_f64;
        let mut norm = 0.0_f64;
        for i in 0..y.len() {
            let d = (-gp2[i] + 8.0 * gp1[i] - 8.0 * gm1[i] + gm2[i]) / (12.0 * h);
            err += ((d - red.hessian[(i, j)]) * y[i] * y[j]).powi(2);
            norm += (red.hessian[(i, j)] * y[i] * y[j]).powi(2);
        }
        let rel = (err / norm).sqrt();
        println!("reduced Hessian column {j}: relative error {rel:.2e}");
        assert!(rel < 1e-5, "reduced Hessian column {j}: {rel:e}");
    }
}

/// Both solvers from θ0 = 1 on cantilever case I data (seed 27) at σ_c = 1e4 reach the
/// same minimum of J_p: θ to 1e-6 relative and J_p to 1e-9 relative (the issue's
/// criterion); Newton in under 100 iterations. Measured: Newton 4 iterations, alternating
/// 1835 (θ 0.28327150 vs 0.28327137, J_p equal to 11 digits). At σ_c = 3000 the
/// alternating solver needs 9529 iterations and its published stop (|Δθ| < 1e-9 per
/// iteration) leaves it 2.3e-6 short in θ, as a slowly contracting iteration does; at
/// σ_c = 10 and 100 it has not converged after 2·10⁵ iterations (Newton: 23 and 10; 90 and
/// 37 with the Levenberg–Marquardt damping it had before its trust region).
#[test]
fn newton_and_alternating_reach_the_same_minimum_cantilever() {
    let (prob, _) = cantilever_problem(1e4);
    let newton = prob.solve_newton(&[1.0], 100).unwrap();
    let alt = prob.solve_alternating(&[1.0], 100_000).unwrap();
    println!(
        "Newton θ = {:.10} J_p = {:.12e} in {} iterations; alternating θ = {:.10} J_p = {:.12e} in {} iterations",
        newton.state.theta[0],
        newton.terms.total,
        newton.iterations,
        alt.state.theta[0],
        alt.terms.total,
        alt.iterations
    );
    assert!(newton.converged && newton.iterations < 100);
    assert!(alt.converged, "alternating did not converge");
    let dt = (newton.state.theta[0] - alt.state.theta[0]).abs() / alt.state.theta[0];
    let dj = (newton.terms.total - alt.terms.total).abs() / alt.terms.total;
    assert!(dt < 1e-6, "θ differs by {dt:e}");
    assert!(dj < 1e-9, "J_p differs by {dj:e}");
    // The Newton point is a minimum of the reduced objective: positive definite Hessian.
    let red = prob
        .reduced(&newton.state.lambda, &newton.state.theta)
        .unwrap();
    assert!(
        red.hessian.llt(faer::Side::Lower).is_ok(),
        "Hessian not positive definite"
    );
}

/// Noise-free lab-frame data with no modelling error (simulated from the model itself at a
/// scattered truth, 9 modes, all 42 channels, stated 1 % / 5 % uncertainties), weak prior
/// (θ0 = 1, std 1000): the Newton solver recovers θ from θ0 = 1 to 1e-4 relative, and the
/// paper's alternating solver too at σ_c = 1e5 (at smaller σ_c it needs far more
/// iterations than a test can afford: 300 do not converge at 1e4). At the
/// truth e_M = e_C = 0, so only the prior moves the minimum, and it moves it further the
/// larger σ_c is (the model term, whose curvature holds θ, weakens as σ_c⁻²). Measured max
/// relative error: 5.5e-8 (σ_c = 100), 6.6e-8 (1e3), 4.6e-7 (1e4), 1.5e-5 (1e5); with a
/// prior std of 10 instead: 4.7e-4 … 0.10.
#[test]
fn both_solvers_recover_noise_free_lab_frame() {
    let model = load_model("lab-frame");
    let truth = LAB_TRUTH;
    let data = simulated_data(&model, &truth, 9, 0.01, 0.05, false, 1);
    let mut last = 0.0;
    for sigma_c in [1e3, 1e5] {
        let settings = BayesSettings {
            sigma_c,
            prior_mean: vec![1.0; 17],
            prior_std: vec![1000.0; 17],
        };
        let prob = BayesProblem::new(&model, &data, &settings).unwrap();
        let res = prob.solve_newton(&[1.0; 17], 100).unwrap();
        let err = res
            .state
            .theta
            .iter()
            .zip(&truth)
            .map(|(a, b)| ((a - b) / b).abs())
            .fold(0.0, f64::max);
        println!(
            "σ_c = {sigma_c:e}: {} iterations, J_p = {:.4e}, max rel. error {err:.2e}",
            res.iterations, res.terms.total
        );
        assert!(res.converged, "σ_c = {sigma_c}: not converged");
        assert!(err < 1e-4, "σ_c = {sigma_c}: max rel. error {err:e}");
        assert!(err > last, "the prior's bias should grow with σ_c");
        last = err;
        if sigma_c == 1e5 {
            // The paper's alternating substeps reach the same θ (measured: 1325
            // iterations, θ within 1.1e-7 of Newton's, J_p ≈ 6e-6 for both).
            let alt = prob.solve_alternating(&[1.0; 17], 20_000).unwrap();
            assert!(alt.converged, "alternating: not converged");
            let alt_err = alt
                .state
                .theta
                .iter()
                .zip(&truth)
                .map(|(a, b)| ((a - b) / b).abs())
                .fold(0.0, f64::max);
            let gap = alt
                .state
                .theta
                .iter()
                .zip(&res.state.theta)
                .map(|(a, b)| ((a - b) / b).abs())
                .fold(0.0, f64::max);
            println!(
                "alternating at σ_c = {sigma_c:e}: {} iterations, max rel. error {alt_err:.2e}, \
                 θ vs Newton {gap:.2e}",
                alt.iterations
            );
            assert!(alt_err < 1e-4, "alternating: max rel. error {alt_err:e}");
            assert!(gap < 1e-6, "alternating vs Newton θ: {gap:e}");
        }
    }
}

/// Uncertainty of the MAP θ against Monte Carlo: 200 noise draws of lab-frame data (9
/// modes, all channels, 1 % frequency CoV, 5 % NSD, simulated from the model at a scattered
/// truth), each solved at σ_c = 1e3 with the prior of the CLI (std 1000). The spread of
/// the 200 MAP θ is what a covariance of "θ given this data" has to predict. The
/// threshold-free sampling covariance `H⁻¹BBᵀH⁻¹` (reduced Hessian, data sensitivity), taken
/// at the first draw's MAP as a user would, must give every parameter's std within ±25 %
/// of the Monte Carlo std (the MC std itself is uncertain by ≈ 1/√(2·199) = 5 %). The
/// posterior std `√diag 2(∇²F)⁻¹`, which adds the modelling-error allowance σ_c, and the
/// paper's TSVD std (24)–(25) are printed beside it; the TSVD std is orders of magnitude
/// too small (the paper's own finding, §2.7: the truncation drops exactly the weak
/// directions that carry θ's variance), so it is reported, not asserted.
#[test]
#[cfg_attr(
    not(feature = "slow-tests"),
    ignore = "slow tier: cargo test --features slow-tests"
)]
fn sampling_std_matches_monte_carlo_lab_frame() {
    let model = load_model("lab-frame");
    let truth = LAB_TRUTH;
    let p = truth.len();
    let settings = BayesSettings {
        sigma_c: 1e3,
        prior_mean: vec![1.0; p],
        prior_std: vec![1000.0; p],
    };
    let draws = 200;
    let mut thetas: Vec<Vec<f64>> = Vec::with_capacity(draws);
    let mut predicted = None;
    for seed in 0..draws as u64 {
        let data = simulated_data(&model, &truth, 9, 0.01, 0.05, true, 1000 + seed);
        let prob = BayesProblem::new(&model, &data, &settings).unwrap();
        let res = prob.solve_newton(&truth, 100).unwrap();
        assert!(res.converged, "draw {seed}: not converged");
        if predicted.is_none() {
            let free = prob.threshold_free_covariance(&res.state).unwrap();
            let tsvd = prob.tsvd_covariance(&res.state).unwrap();
            predicted = Some((
                free.sampling_theta_std(),
                free.posterior_theta_std(),
                tsvd.theta_std(),
            ));
        }
        thetas.push(res.state.theta);
    }
    let (sampling, posterior, tsvd) = predicted.unwrap();
    println!(
        "{:>3} {:>10} {:>10} {:>10} {:>10} {:>10} {:>7}",
        "l", "mean θ", "MC std", "sampling", "posterior", "TSVD", "ratio"
    );
    let mut worst: f64 = 0.0;
    for l in 0..p {
        let mean = thetas.iter().map(|t| t[l]).sum::<f64>() / draws as f64;
        let var = thetas.iter().map(|t| (t[l] - mean).powi(2)).sum::<f64>() / (draws - 1) as f64;
        let mc = var.sqrt();
        let ratio = sampling[l] / mc;
        println!(
            "{l:>3} {mean:>10.5} {mc:>10.5} {:>10.5} {:>10.5} {:>10.2e} {ratio:>7.3}",
            sampling[l], posterior[l], tsvd[l]
        );
        worst = worst.max((ratio - 1.0).abs());
        assert!(
            (ratio - 1.0).abs() <= 0.25,
            "parameter {l}: sampling std {} vs Monte Carlo {mc} (ratio {ratio})",
            sampling[l]
        );
    }
    println!("largest |ratio − 1| = {worst:.3}");
}

/// Stage I → stage II (paper §4.2): every fine parameter takes the value of the simplified
/// parameter that scales all it scales; the reverse mapping covers nothing and falls back
/// to the nominal values.
#[test]
fn refine_theta_maps_simplified_onto_fine_lab_frame() {
    let fine = load_model("lab-frame");
    let coarse = load_model("lab-frame-simplified");
    let coarse_theta = [0.9, 1.7, 1.05];
    let refined = fine.refine_theta(&coarse, &coarse_theta).unwrap();
    assert_eq!(refined.len(), 17);
    for (l, (value, from)) in refined.iter().enumerate() {
        let name = &fine.parameters()[l].name;
        let expected = if name == "E" {
            2
        } else if name.starts_with('C') {
            0
        } else {
            1
        };
        assert_eq!(*from, Some(expected), "{name}");
        assert_eq!(*value, coarse_theta[expected], "{name}");
    }
    // A single fine connection does not cover the ten column connections.
    let back = coarse.refine_theta(&fine, &[2.0; 17]).unwrap();
    for (l, (value, from)) in back.iter().enumerate() {
        let name = &coarse.parameters()[l].name;
        if name == "E" {
            assert_eq!((*value, *from), (2.0, Some(16)), "{name}");
        } else {
            assert_eq!(
                (*value, *from),
                (coarse.parameters()[l].nominal, None),
                "{name}"
            );
        }
    }
}

/// The sparse φ substeps (the shifted stiffness's LDLᵀ and the Woodbury solution, refined;
/// `bayesian/shifted.rs`) against the small models' ones (a sparse Householder QR) on the lab frame, 9 noisy modes, at σ_c from 1 (the model equation nearly a
/// constraint: the Schur complement cancels ~1e10 of its terms) to 1e6, at a point off the
/// minimum: value, gradient, Hessian, data sensitivity and φ agree to 3e-8 relative (each
/// in the norm of its block). Both are backward stable, so they differ by a modest multiple
/// of the condition number of `C = [σ_c⁻¹A; W^{1/2}L_o]` times 1e-16, which grows like
/// 1/σ_c. None of these solves falls back to the augmented system's LU.
#[test]
fn sparse_and_dense_phi_substeps_agree() {
    let model = load_model("lab-frame");
    let truth = LAB_TRUTH;
    let data = simulated_data(&model, &truth, 9, 0.01, 0.05, true, 5);
    let rel = |a: &Mat<f64>, b: &Mat<f64>| (a - b).norm_l2() / b.norm_l2();
    let col = |v: &[f64]| Mat::from_fn(v.len(), 1, |i, _| v[i]);
    for sigma_c in [1.0, 1e2, 1e4, 1e6] {
        let settings = BayesSettings {
            sigma_c,
            prior_mean: vec![1.0; 17],
            prior_std: vec![1000.0; 17],
        };
        let dense = BayesProblem::new(&model, &data, &settings).unwrap();
        let mut sparse = BayesProblem::new(&model, &data, &settings).unwrap();
        assert!(!dense.is_sparse());
        sparse.force_sparse();
        let lambda: Vec<f64> = dense.lambda_hat().iter().map(|l| l * 0.998).collect();
        let theta: Vec<f64> = truth.iter().map(|t| t * 1.1).collect();
        let d = dense.reduced(&lambda, &theta).unwrap();
        let s = sparse.reduced(&lambda, &theta).unwrap();
        let errs = [
            (s.value - d.value).abs() / d.value.abs(),
            rel(&col(&s.gradient), &col(&d.gradient)),
            rel(&s.hessian, &d.hessian),
            rel(&s.data_sensitivity, &d.data_sensitivity),
            rel(&s.phi, &d.phi),
        ];
        println!(
            "σ_c = {sigma_c:e}: value {:.1e}, gradient {:.1e}, Hessian {:.1e}, data sensitivity {:.1e}, φ {:.1e}",
            errs[0], errs[1], errs[2], errs[3], errs[4]
        );
        for (what, e) in ["value", "gradient", "Hessian", "data sensitivity", "φ"]
            .iter()
            .zip(errs)
        {
            assert!(e < 3e-8, "σ_c = {sigma_c}: {what} differs by {e:e}");
        }
        assert_eq!(sparse.augmented_fallbacks(), 0, "σ_c = {sigma_c}");
    }
}

/// The sparse φ substeps where the shifted stiffness `K(θ) − λM` is singular to working
/// precision (λ an eigenvalue of `K(θ)` computed to rounding: κ ≈ 1e16, beyond what
/// refining the Woodbury solution can repair), one part in 1e9 from it, and one part in
/// 1e6: the first falls back to the augmented system's LU for every mode, the last for
/// none. All agree with the small models' path (a sparse Householder QR of `C_m`) to
/// 2e-6 relative: the two backward-stable paths differ by up to 1.1e-6 (the data
/// sensitivity one part in 1e6 from the eigenvalue, whose conditioning there is ~1e9 times
/// that of a solve; φ 1.7e-7, the Hessian 2e-9 at the eigenvalue and 5e-11 beside it),
/// measured.
#[test]
fn sparse_phi_substeps_at_an_eigenvalue_of_the_model() {
    use boltwatch::core::modal::{EigenSolver, dense::DenseEigen};
    let model = load_model("lab-frame");
    let truth = LAB_TRUTH;
    let data = simulated_data(&model, &truth, 9, 0.01, 0.05, true, 5);
    let theta: Vec<f64> = truth.iter().map(|t| t * 1.1).collect();
    let pairs = DenseEigen::new(&model)
        .unwrap()
        .solve(&model, &theta, 9)
        .unwrap();
    let rel = |a: &Mat<f64>, b: &Mat<f64>| (a - b).norm_l2() / b.norm_l2();
    for (offset, fallbacks) in [(0.0, Some(9)), (1e-9, None), (1e-6, Some(0))] {
        let tol = 2e-6;
        let settings = BayesSettings {
            sigma_c: 10.0,
            prior_mean: vec![1.0; 17],
            prior_std: vec![1000.0; 17],
        };
        let dense = BayesProblem::new(&model, &data, &settings).unwrap();
        let mut sparse = BayesProblem::new(&model, &data, &settings).unwrap();
        sparse.force_sparse();
        let lambda: Vec<f64> = pairs.lambda.iter().map(|l| l * (1.0 + offset)).collect();
        let d = dense.reduced(&lambda, &theta).unwrap();
        let s = sparse.reduced(&lambda, &theta).unwrap();
        let errs = [
            rel(&s.hessian, &d.hessian),
            rel(&s.data_sensitivity, &d.data_sensitivity),
            rel(&s.phi, &d.phi),
        ];
        println!(
            "λ = λ_model·(1 + {offset:e}): Hessian {:.1e}, data sensitivity {:.1e}, φ {:.1e}, {} fallbacks",
            errs[0],
            errs[1],
            errs[2],
            sparse.augmented_fallbacks()
        );
        for e in errs {
            assert!(e < tol, "offset {offset}: differs by {e:e}");
        }
        assert!(((s.value - d.value) / d.value).abs() < tol);
        if let Some(f) = fallbacks {
            assert_eq!(sparse.augmented_fallbacks(), f, "offset {offset}");
        }
    }
}

/// The automatic σ_c (discrepancy principle; regula falsi with the Illinois modification,
/// issue 27) on the cantilever, case I (the model's E is 1.5 times the truth's: a modelling
/// error the misfit sees at small σ_c): the rule is met, the σ_c found agrees with the
/// crossing a 49-point sweep of the same range interpolates within 10 % (the sweep's own
/// linear interpolation between points 1.47× apart is not closer), in fewer MAP solves
/// than bisection of the range to the same 5 % (11): 8, the root lying six decades above
/// the bottom of the range.
#[test]
fn automatic_sigma_c_meets_the_discrepancy_rule_in_few_solves() {
    use boltwatch::core::updating::bayesian::{
        AUTO_SIGMA_TOL, AutoSigma, SweepSettings, discrepancy_choice, log_grid, sweep_sigma,
    };
    let truth = load_model("cantilever-truth");
    let model = load_model("cantilever-case1");
    let data = simulated_data(&truth, &[0.5], 4, 0.01, 0.01, true, 27);
    let settings = SweepSettings {
        prior_mean: vec![1.0],
        prior_std: vec![10.0],
        theta0: vec![1.0],
        newton_max_iterations: 200,
        alternating_max_iterations: None,
        bounds: None,
    };
    let (from, to) = (1e-2, 1e6);
    let auto = AutoSigma::search(
        &model,
        &data,
        from,
        to,
        &settings,
        AUTO_SIGMA_TOL,
        &mut |_| {},
    )
    .unwrap();
    let grid = log_grid(from, to, 49).unwrap();
    let sweep = sweep_sigma(&model, &data, &grid, &settings, &mut |_, _| {}).unwrap();
    let fine = discrepancy_choice(&sweep, auto.target).unwrap();
    println!(
        "automatic σ_c {:.4e} (misfit {:.3} against ν = {}) in {} solves; 49-point sweep {:.4e}",
        auto.sigma_c,
        auto.misfit,
        auto.target,
        auto.trials.len(),
        fine.sigma_c
    );
    assert!(auto.met && fine.met);
    assert!(
        (auto.sigma_c / fine.sigma_c - 1.0).abs() < 0.1,
        "{} against {}",
        auto.sigma_c,
        fine.sigma_c
    );
    assert!(
        auto.trials.len() < 11,
        "{} solves: {:?}",
        auto.trials.len(),
        auto.trials
    );
}
