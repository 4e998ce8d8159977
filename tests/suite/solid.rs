//! The solid model (issue 7): the 20-node hexahedron's patch test, a slender solid
//! cantilever against Euler–Bernoulli with mesh convergence, the multi-bay solid frame's
//! assembly, and the sparse eigen solver against the dense one on a frame small enough for
//! both.

use boltwatch::core::modal::{DenseEigen, EigenSolver, SparseEigen};
use boltwatch::core::model::Model;
use boltwatch::core::model::hex20::{self, Material};
use boltwatch::core::model::mesh::BoxMesh;
use boltwatch::core::model::solid::solid_cantilever;
use faer::linalg::solvers::Solve;
use faer::{Mat, Side};

const STEEL: Material = Material {
    e: 2.1e11,
    nu: 0.3,
    rho: 7840.0,
};

/// The patch test (Zienkiewicz & Taylor, vol. 1, ch. 10): a 2 × 2 × 2 patch of elements
/// whose shared centre node is moved off the grid (the elements are then neither
/// parallelepipeds nor alike), with the displacements of a linear field `u = A x + b`
/// imposed on the boundary nodes: the free (interior) nodes must take the same linear
/// field, exactly up to rounding. Tolerance 1e-10 of the field's size (the solve of a
/// well-conditioned 21-DOF system loses a few digits).
#[test]
fn hex20_patch_test_reproduces_a_linear_field() {
    let mesh = BoxMesh::new([0.0; 3], [1.0, 0.8, 0.6], [2, 2, 2]);
    let shift = [0.07, -0.05, 0.04];
    let coord = |n: usize| {
        let h = mesh.nodes[n];
        let mut x = mesh.coord(n);
        // The centre (2,2,2) and the midpoints of the edges from it (one index 1 or 3, the
        // others 2) move: the centre by `shift`, the midpoints by half of it, so edges stay
        // straight.
        let off = h.iter().filter(|&&i| i != 2).count();
        let odd_inner = h.iter().filter(|&&i| i == 1 || i == 3).count();
        if off == 0 {
            (0..3).for_each(|r| x[r] += shift[r]);
        } else if off == 1 && odd_inner == 1 {
            (0..3).for_each(|r| x[r] += 0.5 * shift[r]);
        }
        x
    };
    let n = mesh.nodes.len();
    let mut k = Mat::<f64>::zeros(3 * n, 3 * n);
    for el in mesh.elements() {
        let x = el.map(coord);
        let (ke, _) = hex20::element(&x, &STEEL).unwrap();
        for a in 0..hex20::DOFS {
            for b in 0..hex20::DOFS {
                k[(3 * el[a / 3] + a % 3, 3 * el[b / 3] + b % 3)] += ke[a][b];
            }
        }
    }
    let a = [
        [1e-3, 2e-4, -3e-4],
        [5e-4, -1e-3, 2e-4],
        [-1e-4, 3e-4, 7e-4],
    ];
    let b = [1e-4, -2e-4, 3e-4];
    let field = |x: [f64; 3]| -> [f64; 3] {
        std::array::from_fn(|i| b[i] + (0..3).map(|j| a[i][j] * x[j]).sum::<f64>())
    };
    let interior: Vec<usize> = (0..n)
        .filter(|&m| mesh.nodes[m].iter().all(|&i| i > 0 && i < 4))
        .collect();
    assert_eq!(
        interior.len(),
        7,
        "the centre node and its six edge midpoints"
    );
    let free: Vec<usize> = interior
        .iter()
        .flat_map(|&m| (0..3).map(move |r| 3 * m + r))
        .collect();
    let fixed: Vec<usize> = (0..3 * n).filter(|d| !free.contains(d)).collect();
    let u_fixed: Vec<f64> = fixed.iter().map(|&d| field(coord(d / 3))[d % 3]).collect();
    // K_ff u_f = −K_fc u_c.
    let kff = Mat::<f64>::from_fn(free.len(), free.len(), |i, j| k[(free[i], free[j])]);
    let rhs = Mat::<f64>::from_fn(free.len(), 1, |i, _| {
        -fixed
            .iter()
            .zip(&u_fixed)
            .map(|(&c, &u)| k[(free[i], c)] * u)
            .sum::<f64>()
    });
    let u = kff.llt(Side::Lower).unwrap().solve(&rhs);
    let scale = 1e-3;
    let mut worst: f64 = 0.0;
    for (i, &d) in free.iter().enumerate() {
        let want = field(coord(d / 3))[d % 3];
        worst = worst.max((u[(i, 0)] - want).abs() / scale);
    }
    println!("patch test: largest interior error {worst:.1e} of the field's size");
    assert!(
        worst < 1e-10,
        "the patch does not reproduce a linear field: {worst:e}"
    );
}

/// First bending frequency of a clamped–free Euler–Bernoulli beam, `(β₁L)² / (2π L²) ·
/// √(EI/ρA)`, β₁L = 1.875104.
fn euler_first(length: f64, e: f64, i: f64, rho: f64, area: f64) -> f64 {
    let b = 1.875_104_068_711_961;
    b * b / (2.0 * std::f64::consts::PI * length * length) * (e * i / (rho * area)).sqrt()
}

/// A slender solid cantilever (1 m, 20 × 10 mm, L/h = 100) meshed ever finer along its
/// length: its first bending frequencies about both axes converge to Euler–Bernoulli's and
/// end within 1 %. The solid differs from the beam theory by shear (∝ (h/L)², ~1e-4 here)
/// and by the root's clamped Poisson contraction (a ν²-sized effect on a short length), so
/// the converged gap stays well under 1 %; coarse meshes are stiffer (a conforming element
/// converges from above).
#[test]
fn a_slender_solid_cantilever_converges_to_euler_bernoulli() {
    let (l, w, h): (f64, f64, f64) = (1.0, 0.02, 0.01);
    let area = w * h;
    // Weak axis: bending in z (I = w h³/12); strong axis: in y (I = h w³/12).
    let f_weak = euler_first(l, STEEL.e, w * h.powi(3) / 12.0, STEEL.rho, area);
    let f_strong = euler_first(l, STEEL.e, h * w.powi(3) / 12.0, STEEL.rho, area);
    let mut previous = (f64::INFINITY, f64::INFINITY);
    let mut last = (0.0, 0.0);
    for n in [2, 4, 8, 16] {
        let model = solid_cantilever(l, w, h, [n, 2, 1], STEEL).unwrap();
        let mut solver = DenseEigen::new(&model).unwrap();
        let eig = solver.solve(&model, &[], 4).unwrap();
        // The two lowest are the first weak- and strong-axis bending modes; tell them apart
        // by the tip channel they move.
        let (ty, tz) = (
            model.channel_index("tip.y").unwrap(),
            model.channel_index("tip.z").unwrap(),
        );
        let mut weak = None;
        let mut strong = None;
        for k in 0..4 {
            let phi: Vec<f64> = (0..model.n_dof()).map(|i| eig.phi[(i, k)]).collect();
            let (y, z) = (
                model.channels()[ty].read(&phi),
                model.channels()[tz].read(&phi),
            );
            if z.abs() > 10.0 * y.abs() && weak.is_none() {
                weak = Some(eig.frequency_hz(k));
            } else if y.abs() > 10.0 * z.abs() && strong.is_none() {
                strong = Some(eig.frequency_hz(k));
            }
        }
        let (fw, fs) = (weak.unwrap(), strong.unwrap());
        println!(
            "{n:>2} elements along ({:>5} DOF): weak {fw:.4} Hz ({:+.3} %), strong {fs:.4} Hz ({:+.3} %)",
            model.n_dof(),
            100.0 * (fw / f_weak - 1.0),
            100.0 * (fs / f_strong - 1.0)
        );
        assert!(
            fw <= previous.0 * (1.0 + 1e-9) && fs <= previous.1 * (1.0 + 1e-9),
            "refinement must not stiffen"
        );
        previous = (fw, fs);
        last = (fw, fs);
    }
    assert!(
        (last.0 / f_weak - 1.0).abs() < 0.01,
        "weak axis {} vs {f_weak}",
        last.0
    );
    assert!(
        (last.1 / f_strong - 1.0).abs() < 0.01,
        "strong axis {} vs {f_strong}",
        last.1
    );
}

/// The shipped four-bay model file's text.
fn four_bay_text() -> String {
    std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/config/models/four-bay-solid.toml"
    ))
    .unwrap()
}

fn four_bay() -> Model {
    Model::from_toml(&four_bay_text()).unwrap()
}

/// A two-bay frame with a coarse mesh: the same construction, small enough for the dense
/// solver.
fn two_bay_coarse() -> Model {
    Model::from_toml(
        r#"
name = "two-bay-coarse"
[solid_frame]
bays = 2
spring_factor = 50.0
beam = { length = 0.49, in_plane = 0.008, out_of_plane = 0.08, divisions = [6, 1, 1] }
coupler = { size = 0.04, divisions = 5 }
material = { E = 2.1e11, nu = 0.3, rho = 7840.0 }
"#,
    )
    .unwrap()
}

/// The four-bay model file: size within the issue's 28,000–36,000 DOF, 4 parameters, 18
/// connections with two springs each, 22 sensor locations × 3 channels, the springs'
/// constants `50 · 4EI/L`, and the mass equal to the steel's volume × density (the rigid
/// interfaces move mass onto masters but must not create or lose any: a unit translation
/// of everything has kinetic "mass" `1ᵀM1`).
#[test]
fn the_four_bay_model_is_assembled_as_specified() {
    let m = four_bay();
    println!("four-bay-solid: {} DOF", m.n_dof());
    assert!((28_000..=36_000).contains(&m.n_dof()), "{} DOF", m.n_dof());
    let names: Vec<&str> = m.parameters().iter().map(|p| p.name.as_str()).collect();
    assert_eq!(names, ["ip-left", "ip-right", "ip-vertical", "op"]);
    assert_eq!(m.connections().len(), 36);
    assert_eq!(m.channels().len(), 66);
    let e = 2.1e11;
    let (l, w, t): (f64, f64, f64) = (0.49, 0.008, 0.08);
    let k_ip = 50.0 * 4.0 * e * t * w.powi(3) / 12.0 / l;
    let k_op = 50.0 * 4.0 * e * w * t.powi(3) / 12.0 / l;
    for c in m.connections() {
        let want = if c.name.ends_with(".op") { k_op } else { k_ip };
        assert!((c.k / want - 1.0).abs() < 1e-12, "{}: {}", c.name, c.k);
    }
    for (l, p) in m.parameters().iter().enumerate() {
        let boltwatch::core::model::ParameterKind::Connections(c) = &p.kind else {
            panic!("{} scales connections", p.name)
        };
        assert_eq!(c.len(), if l == 3 { 18 } else { 6 }, "{}", p.name);
    }
    // Total mass along each axis: a rigid translation q = L·1 moves every node by one.
    let volume = 11.0 * l * w * t + 6.0 * 0.04 * 0.04 * t;
    let mass = m.mass();
    let s = mass.symbolic();
    for axis in 0..3 {
        let q: Vec<f64> = m
            .dof_labels()
            .iter()
            .map(|d| {
                let want = format!(".u{}", ["x", "y", "z"][axis]);
                let own = format!(".{}", ["x", "y", "z"][axis]);
                if d.ends_with(&want) || (d.contains(".n") && d.ends_with(&own)) {
                    1.0
                } else {
                    0.0
                }
            })
            .collect();
        let mut total = 0.0;
        for j in 0..m.n_dof() {
            for (&i, &v) in s.row_idx_of_col_raw(j).iter().zip(mass.val_of_col(j)) {
                total += q[i] * v * q[j];
            }
        }
        // Clamped end faces hold mass that no DOF carries: 4 faces of quadratic-element
        // nodes; compare against the free steel within that share.
        let steel = volume * 7840.0;
        println!("axis {axis}: 1ᵀM1 = {total:.4} kg of {steel:.4} kg of steel");
        assert!(
            total < steel && total > 0.98 * steel,
            "axis {axis}: {total} kg"
        );
    }
}

/// Sparse and dense eigenpairs on the two-bay coarse frame (both solvers can run): the 12
/// lowest eigenvalues and mass-normalized eigenvectors (2-norm of the difference over the
/// 2-norm) to 1e-8 relative (the issue's bound), at θ nominal and at the issue's truth
/// (measured: λ 3.3e-9 and 5.1e-10, φ 8.1e-9 and 1.6e-9).
#[test]
fn sparse_and_dense_agree_on_a_small_solid_frame() {
    let model = two_bay_coarse();
    println!("two-bay coarse frame: {} DOF", model.n_dof());
    let mut dense = DenseEigen::new(&model).unwrap();
    let mut sparse = SparseEigen::new(&model).unwrap();
    for theta in [vec![1.0; 4], vec![0.36, 0.36, 0.36, 0.5]] {
        let d = dense.solve(&model, &theta, 12).unwrap();
        let s = sparse.solve(&model, &theta, 12).unwrap();
        let mut worst_l: f64 = 0.0;
        let mut worst_v: f64 = 0.0;
        for k in 0..12 {
            worst_l = worst_l.max((d.lambda[k] - s.lambda[k]).abs() / d.lambda[k]);
            let norm = (0..model.n_dof())
                .map(|i| d.phi[(i, k)].powi(2))
                .sum::<f64>()
                .sqrt();
            // Up to sign: the frame is mirror-symmetric, so a mode's largest-magnitude entry
            // is tied between mirror DOFs and the sign rule may pick either.
            let diff = |sign: f64| {
                (0..model.n_dof())
                    .map(|i| (d.phi[(i, k)] - sign * s.phi[(i, k)]).powi(2))
                    .sum::<f64>()
                    .sqrt()
                    / norm
            };
            worst_v = worst_v.max(diff(1.0).min(diff(-1.0)));
        }
        println!(
            "θ = {theta:?}: f1 = {:.3} Hz, f12 = {:.3} Hz; λ {worst_l:.1e}, φ {worst_v:.1e}",
            d.frequency_hz(0),
            d.frequency_hz(11)
        );
        assert!(worst_l < 1e-8, "eigenvalues differ by {worst_l:e}");
        assert!(worst_v < 1e-8, "eigenvectors differ by {worst_v:e}");
    }
}

/// The sparse solver's relaxed solve (the evaluator's: 16 modes, the first 6 exact, the
/// others for pairing) on the two-bay coarse frame, at θ nominal and the issue's truth,
/// against the full solve. The residuals it reports are checked by recomputing them from
/// `K(θ)` and `M` products (those carry rounding of about 1e-10 of `‖Kφ‖` themselves, so
/// each is bounded by its target plus 1e-9); the six exact modes' eigenvalues agree with
/// the full solve's to 1e-10 (an eigenvalue's error is of the order of the squared
/// residual, 1e-14, plus the rounding the one cycle's carried `KV` leaves in the Rayleigh
/// quotient: measured 4.4e-12) and their eigenvectors to 1e-5 (a residual ρ moves the
/// eigenvector by about ρ over the relative gap to the nearest mode, ≥ 1 % here; measured
/// 2.4e-12: the first cycle converges these modes to the rounding floor); the others'
/// eigenvalues to 1e-6 (squared residual, at most 1e-6 for the pairing target 1e-3;
/// measured 8.7e-12).
#[test]
fn the_relaxed_sparse_solve_keeps_its_targets() {
    use boltwatch::core::modal::eigen::{LOOSE_RESIDUAL, STRICT_RESIDUAL};
    use boltwatch::core::model::sparse::spmv_add;
    let model = two_bay_coarse();
    let n = model.n_dof();
    let mut sparse = SparseEigen::new(&model).unwrap();
    for theta in [vec![1.0; 4], vec![0.36, 0.36, 0.36, 0.5]] {
        let full = sparse.solve(&model, &theta, 16).unwrap();
        let (relaxed, reported) = sparse
            .solve_relaxed(&model, &theta, 16, 6)
            .unwrap()
            .expect("the sparse solver has a relaxed solve");
        let mut k = model.union_pattern().pattern.clone();
        model.shifted_stiffness_values(&theta, 0.0, k.val_mut());
        let (mut worst_l, mut worst_v, mut worst_loose_l) = (0.0_f64, 0.0_f64, 0.0_f64);
        for (j, &reported_j) in reported.iter().enumerate() {
            let phi: Vec<f64> = (0..n).map(|i| relaxed.phi[(i, j)]).collect();
            let (mut kphi, mut mphi) = (vec![0.0; n], vec![0.0; n]);
            spmv_add(&k, &phi, 1.0, &mut kphi);
            spmv_add(model.mass(), &phi, 1.0, &mut mphi);
            let num: f64 = (0..n)
                .map(|i| (kphi[i] - relaxed.lambda[j] * mphi[i]).powi(2))
                .sum::<f64>()
                .sqrt();
            let residual = num / kphi.iter().map(|v| v * v).sum::<f64>().sqrt();
            let target = if j < 6 {
                STRICT_RESIDUAL
            } else {
                LOOSE_RESIDUAL
            };
            assert!(
                reported_j <= target && residual <= target + 1e-9,
                "mode {}: reported {reported_j:e}, recomputed {residual:e}, target {target:e}",
                j + 1,
            );
            let dl = (relaxed.lambda[j] - full.lambda[j]).abs() / full.lambda[j];
            if j < 6 {
                worst_l = worst_l.max(dl);
                let diff = |sign: f64| {
                    (0..n)
                        .map(|i| (full.phi[(i, j)] - sign * relaxed.phi[(i, j)]).powi(2))
                        .sum::<f64>()
                        .sqrt()
                        / (0..n).map(|i| full.phi[(i, j)].powi(2)).sum::<f64>().sqrt()
                };
                worst_v = worst_v.max(diff(1.0).min(diff(-1.0)));
            } else {
                worst_loose_l = worst_loose_l.max(dl);
            }
        }
        println!(
            "θ = {theta:?}: residuals {:?}; modes 1–6 λ {worst_l:.1e}, φ {worst_v:.1e}; \
             modes 7–16 λ {worst_loose_l:.1e}",
            reported
                .iter()
                .map(|r| format!("{r:.0e}"))
                .collect::<Vec<_>>()
        );
        assert!(
            worst_l < 1e-10,
            "exact modes' eigenvalues differ by {worst_l:e}"
        );
        assert!(
            worst_v < 1e-5,
            "exact modes' eigenvectors differ by {worst_v:e}"
        );
        assert!(
            worst_loose_l < 1e-6,
            "eigenvalues differ by {worst_loose_l:e}"
        );
    }
}

/// `boltwatch modes -n 12` on the four-bay model against SciPy's `eigsh` in shift-invert
/// mode (σ = 0, its ARPACK Lanczos on a SuperLU factorization) on the matrices
/// `boltwatch export-matrices` wrote: the same 12 frequencies to 1e-6 relative (both
/// converge the eigenvalues to near machine precision; 1e-6 is the issue's bound and leaves
/// room for the 17-digit round trip through the files). Both run as whole processes; their
/// times are printed (the figures in the README come from a release build), never
/// asserted.
#[test]
#[cfg_attr(
    not(feature = "slow-tests"),
    ignore = "slow tier: cargo test --features slow-tests"
)]
fn modes_match_scipy_eigsh_on_the_exported_four_bay_matrices() {
    use std::process::Command;
    use std::time::Instant;
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
    let run = |args: &[&str]| {
        let out = Command::new(bin).args(args).output().unwrap();
        assert!(
            out.status.success(),
            "boltwatch {args:?}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
    };
    let matrices = dir.join("matrices");
    run(&[
        "export-matrices",
        "--model",
        model,
        "-o",
        matrices.to_str().unwrap(),
    ]);
    let ours_json = dir.join("modes.json");
    let start = Instant::now();
    run(&[
        "modes",
        "--model",
        model,
        "-n",
        "12",
        "-o",
        ours_json.to_str().unwrap(),
    ]);
    let ours_s = start.elapsed().as_secs_f64();
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
    let start = Instant::now();
    let out = Command::new(&python)
        .args(["-c", script, matrices.to_str().unwrap()])
        .output()
        .unwrap();
    let scipy_s = start.elapsed().as_secs_f64();
    assert!(
        out.status.success(),
        "scipy: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let scipy: Vec<f64> = serde_json::from_slice(&out.stdout).unwrap();
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
