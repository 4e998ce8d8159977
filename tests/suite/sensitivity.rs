//! Sensitivities against central differences.
//!
//! Five-point central differences, f' ≈ [f(−2h) − 8f(−h) + 8f(h) − f(2h)] / 12h, with
//! h = 1e-3 θ_l: truncation O(h⁴) ≈ 1e-12 relative. Round-off: the lab frame's lowest
//! eigenvalues carry ~3e-10 relative noise (Kφ cancels the beams' axial stiffness, see the
//! eigen residual test), which a difference amplifies by ~1/(h·∂ln λ/∂θ) ≈ 1e3 to ~3e-7,
//! well inside the 1e-5. (A two-point difference with h = 1e-4 θ amplified it to
//! 1.4e-5 and failed.) Errors are normwise per mode: for ∂λ_k,
//! |FD − analytic| / max_l |∂λ_k/∂θ_l|; for ∂φ_k at the channels, ‖FD − analytic‖ /
//! max_l ‖∂φ_k/∂θ_l‖. (A parameter that barely moves a mode, e.g. ∂λ2/∂θ8 = 0.03 against
//! λ2 = 3.5e4, has a near-zero entry whose own relative error only measures FD noise.)

use boltwatch::core::modal::{DenseEigen, EigenSolver, Nelson};
use boltwatch::core::model::Model;
use boltwatch::core::updating::Evaluator;
use faer::Mat;

use super::common::{load_model, simulated_data};

/// Channel readings of mode k, with its sign aligned to `reference` if given.
fn channel_shape(model: &Model, phi: &Mat<f64>, k: usize, reference: Option<&[f64]>) -> Vec<f64> {
    let col: Vec<f64> = (0..phi.nrows()).map(|i| phi[(i, k)]).collect();
    let mut v: Vec<f64> = model.channels().iter().map(|c| c.read(&col)).collect();
    if let Some(r) = reference
        && v.iter().zip(r).map(|(a, b)| a * b).sum::<f64>() < 0.0
    {
        v.iter_mut().for_each(|x| *x = -*x);
    }
    v
}

/// Five-point central difference from f(−2h), f(−h), f(h), f(2h).
fn stencil(m2: f64, m1: f64, p1: f64, p2: f64, h: f64) -> f64 {
    (m2 - 8.0 * m1 + 8.0 * p1 - p2) / (12.0 * h)
}

fn norm(v: &[f64]) -> f64 {
    v.iter().map(|x| x * x).sum::<f64>().sqrt()
}

fn check_modal_sensitivities(model: &Model, theta: &[f64], modes: usize) {
    let mut solver = DenseEigen::new(model).unwrap();
    let mut nelson = Nelson::new(model).unwrap();
    let base = solver.solve(model, theta, modes + 2).unwrap();
    let p = model.n_params();
    let mut worst = (0.0_f64, 0.0_f64);
    for k in 0..modes {
        let phi: Vec<f64> = (0..model.n_dof()).map(|i| base.phi[(i, k)]).collect();
        let mut dl = vec![0.0; p];
        let mut dphi = Mat::zeros(model.n_dof(), p);
        nelson
            .derivatives(
                model,
                theta,
                k + 1,
                base.lambda[k],
                &phi,
                &mut dl,
                dphi.as_mut(),
            )
            .unwrap();
        let shape0 = channel_shape(model, &base.phi, k, None);
        let an_cols: Vec<Vec<f64>> = (0..p)
            .map(|l| {
                let col: Vec<f64> = (0..model.n_dof()).map(|i| dphi[(i, l)]).collect();
                model.channels().iter().map(|c| c.read(&col)).collect()
            })
            .collect();
        let scale_l = dl.iter().fold(0.0_f64, |a, b| a.max(b.abs()));
        let scale_phi = an_cols.iter().map(|c| norm(c)).fold(0.0_f64, f64::max);
        for l in 0..p {
            let h = 1e-3 * theta[l];
            let at = |j: f64, solver: &mut DenseEigen| {
                let mut t = theta.to_vec();
                t[l] += j * h;
                let e = solver.solve(model, &t, modes + 2).unwrap();
                (e.lambda[k], channel_shape(model, &e.phi, k, Some(&shape0)))
            };
            let pts: Vec<(f64, Vec<f64>)> = [-2.0, -1.0, 1.0, 2.0]
                .iter()
                .map(|&j| at(j, &mut solver))
                .collect();
            let fd_l = stencil(pts[0].0, pts[1].0, pts[2].0, pts[3].0, h);
            let rel_l = (fd_l - dl[l]).abs() / scale_l;
            let fd: Vec<f64> = (0..shape0.len())
                .map(|i| stencil(pts[0].1[i], pts[1].1[i], pts[2].1[i], pts[3].1[i], h))
                .collect();
            let diff: Vec<f64> = fd.iter().zip(&an_cols[l]).map(|(a, b)| a - b).collect();
            let rel_phi = norm(&diff) / scale_phi;
            worst = (worst.0.max(rel_l), worst.1.max(rel_phi));
            assert!(
                rel_l < 1e-5,
                "mode {} θ{}: ∂λ {} vs FD {fd_l}, rel {rel_l:e}",
                k + 1,
                l + 1,
                dl[l]
            );
            assert!(
                rel_phi < 1e-5,
                "mode {} θ{}: ∂φ rel error {rel_phi:e}",
                k + 1,
                l + 1
            );
        }
    }
    println!(
        "{}: worst rel. error ∂λ {:.1e}, ∂φ at channels {:.1e}",
        model.name, worst.0, worst.1
    );
}

#[test]
fn eigen_sensitivities_match_central_differences_cantilever() {
    let model = load_model("cantilever-case1");
    check_modal_sensitivities(&model, &[0.7], 4);
}

#[test]
fn eigen_sensitivities_match_central_differences_lab_frame() {
    let model = load_model("lab-frame");
    let theta: Vec<f64> = (0..17).map(|l| 0.5 + 0.17 * l as f64).collect();
    check_modal_sensitivities(&model, &theta, 9);
}

/// The whole whitened residual Jacobian, c_m(θ) included, against central differences of
/// the residual (same pairing at θ ± h, checked).
fn check_jacobian(model: &Model, theta: &[f64], truth: &[f64], modes: usize) {
    let data = simulated_data(model, truth, modes, 0.01, 0.05, true, 7);
    let mut ev = Evaluator::new(model).unwrap();
    let base = ev.evaluate(model, &data, theta).unwrap();
    let jac = ev.jacobian(model, &data, &base).unwrap();
    let mut worst = 0.0_f64;
    for l in 0..model.n_params() {
        let h = 1e-3 * theta[l];
        let pts: Vec<Vec<f64>> = [-2.0, -1.0, 1.0, 2.0]
            .iter()
            .map(|&j| {
                let mut t = theta.to_vec();
                t[l] += j * h;
                let e = ev.evaluate(model, &data, &t).unwrap();
                assert_eq!(e.pairing, base.pairing);
                e.r
            })
            .collect();
        let fd: Vec<f64> = (0..base.r.len())
            .map(|i| stencil(pts[0][i], pts[1][i], pts[2][i], pts[3][i], h))
            .collect();
        let an: Vec<f64> = (0..jac.nrows()).map(|i| jac[(i, l)]).collect();
        let diff: Vec<f64> = fd.iter().zip(&an).map(|(a, b)| a - b).collect();
        let rel = norm(&diff) / norm(&an);
        worst = worst.max(rel);
        assert!(rel < 1e-5, "θ{}: Jacobian column rel. error {rel:e}", l + 1);
    }
    println!(
        "{}: worst Jacobian column rel. error {worst:.1e}",
        model.name
    );
}

#[test]
fn residual_jacobian_matches_central_differences_cantilever() {
    let model = load_model("cantilever-case1");
    check_jacobian(&model, &[0.8], &[0.5], 4);
}

#[test]
fn residual_jacobian_matches_central_differences_lab_frame() {
    let model = load_model("lab-frame");
    let theta: Vec<f64> = (0..17).map(|l| 0.6 + 0.1 * l as f64).collect();
    let mut truth = vec![1.0; 17];
    truth[3] = 0.5;
    truth[12] = 2.0;
    check_jacobian(&model, &theta, &truth, 9);
}
