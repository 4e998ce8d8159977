//! The space frame of `space-frame.md` (issue 25): `config/models/space-frame.toml` is that
//! structure exactly (names, parameter order, channels), and its 15 lowest frequencies are
//! the table's, at θ = 1 and with rigid connections.

use boltwatch::core::model::Model;
use boltwatch::core::model::spec::ModelSpec;

/// The table of `space-frame.md` §9 (Hz, 9 significant figures).
const AT_NOMINAL: [f64; 15] = [
    16.1239218, 17.1694069, 20.2621162, 31.6032829, 32.9327522, 60.2850115, 63.1439468, 69.2685868,
    75.0974306, 77.4431947, 145.640700, 158.016116, 158.841054, 159.026372, 165.638978,
];
const RIGID: [f64; 15] = [
    24.0871275, 24.2066717, 27.4821041, 53.9573088, 54.5427621, 71.3302388, 72.5786165, 80.5619038,
    92.4779051, 94.6847010, 154.370758, 183.504033, 203.136161, 212.925175, 228.727485,
];

fn spec() -> ModelSpec {
    let text = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/config/models/space-frame.toml"
    ))
    .unwrap();
    toml::from_str(&text).unwrap()
}

fn frequencies(model: &Model, theta: &[f64]) -> Vec<f64> {
    let mut solver = boltwatch::core::modal::solver_for(model).unwrap();
    let pairs = solver.solve(model, theta, 15).unwrap();
    (0..15).map(|k| pairs.frequency_hz(k)).collect()
}

/// Largest relative difference.
fn gap(a: &[f64], b: &[f64]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(x, y)| ((x - y) / y).abs())
        .fold(0.0, f64::max)
}

/// Size, names and order as the document states them; the 15 frequencies at θ = 1 within
/// 1e-6 (measured 3.2e-9: the table's 9 significant figures).
#[test]
fn the_space_frame_model_is_the_reference_structure() {
    let model = Model::from_spec(&spec()).unwrap();
    assert_eq!(model.n_dof(), 596);
    let names: Vec<&str> = model.parameters().iter().map(|p| p.name.as_str()).collect();
    assert_eq!(names.len(), 30);
    assert_eq!(
        (
            names[0], names[13], names[14], names[27], names[28], names[29]
        ),
        (
            "BX11a@J1A1",
            "BZ1C@J1C2",
            "BX21a@J2A1",
            "BZ2C@J2C2",
            "weak",
            "E"
        )
    );
    let channels = model.channels();
    assert_eq!(channels.len(), 78);
    assert_eq!(
        (channels[0].name.as_str(), channels[77].name.as_str()),
        ("A1-1.2.x", "BZ2C.2.z")
    );
    let f = frequencies(&model, &model.nominal_theta());
    let g = gap(&f, &AT_NOMINAL);
    println!("θ = 1: largest relative difference from the table {g:.1e}");
    assert!(g < 1e-6, "{f:?}");
}

/// Springs → ∞ reproduce the rigid connection: the model without its connections (only E
/// as a parameter) gives the table's rigid column within 1e-6, and so do the springs at
/// θ = 1e8 (a spring 1e8 times stiffer than nominal leaves ~1e-8).
#[test]
fn stiff_springs_and_rigid_connections_give_the_rigid_frequencies() {
    let mut rigid = spec();
    let frame = rigid.space_frame.as_mut().unwrap();
    frame.connections.clear();
    frame.parameters.retain(|p| p.name == "E");
    let model = Model::from_spec(&rigid).unwrap();
    assert_eq!(model.n_dof(), 596 - 56);
    let g = gap(&frequencies(&model, &[1.0]), &RIGID);
    println!("rigid connections: {g:.1e}");
    assert!(g < 1e-6);
    let model = Model::from_spec(&spec()).unwrap();
    let mut theta = vec![1e8; 29];
    theta.push(1.0);
    let g = gap(&frequencies(&model, &theta), &RIGID);
    println!("springs at θ = 1e8: {g:.1e}");
    assert!(g < 1e-6);
}

/// Bad references are named: a parameter naming a connection axis that has no spring.
#[test]
fn space_frame_references_are_checked() {
    let mut s = spec();
    s.space_frame.as_mut().unwrap().parameters[0].connections = vec!["BX11a@J1A1.torsion".into()];
    let e = Model::from_spec(&s).unwrap_err().to_string();
    assert!(e.contains("BX11a@J1A1.torsion"), "{e}");
}

/// `simulate` lists the noisy modes by frequency: the space frame's modes 12–14 lie within
/// 0.7 %, and 1 % noise swapped two of them with seed 1, which the modal-set contract then
/// rejected. The set now validates, and `update` from θ0 = 1 converges on it.
#[test]
fn a_noisy_set_of_close_modes_is_valid() {
    let dir = super::tracker::tmp_dir("space-frame-noisy");
    let model = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/config/models/space-frame.toml"
    );
    let set = dir.join("set.json");
    let run = |args: &[&std::ffi::OsStr]| {
        let o = std::process::Command::new(env!("CARGO_BIN_EXE_boltwatch"))
            .args(args)
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    };
    run(&[
        "simulate".as_ref(),
        "--model".as_ref(),
        model.as_ref(),
        "--modes".as_ref(),
        "15".as_ref(),
        "--seed".as_ref(),
        "1".as_ref(),
        "-o".as_ref(),
        set.as_os_str(),
    ]);
    run(&[
        "update".as_ref(),
        "--model".as_ref(),
        model.as_ref(),
        "--data".as_ref(),
        set.as_os_str(),
        "-o".as_ref(),
        dir.join("update.json").as_os_str(),
    ]);
}

/// A plane-frame model file (`[[nodes]]`, `[[members]]`, …) written as a space frame in
/// its x–y plane with the out-of-plane DOFs restrained everywhere: the same sections
/// (in-plane bending about the members' strong axes), joints with their offsets and
/// inertia about z, supports, connections as `strong` springs, masses, springs, channels
/// and parameters.
fn planar_as_space(planar: &str) -> String {
    use toml::Value;
    let p: toml::Table = toml::from_str(planar).unwrap();
    let list = |key: &str| -> Vec<toml::Table> {
        p.get(key)
            .and_then(Value::as_array)
            .map(|a| a.iter().map(|v| v.as_table().unwrap().clone()).collect())
            .unwrap_or_default()
    };
    let z3 = |v: &Value| Value::Array(vec![0.0.into(), 0.0.into(), v.clone()]);
    let mut sf = toml::Table::new();
    let mut put = |key: &str, items: Vec<toml::Table>| {
        sf.insert(
            key.into(),
            Value::Array(items.into_iter().map(Value::Table).collect()),
        );
    };
    put(
        "materials",
        list("materials")
            .into_iter()
            .map(|mut m| {
                m.insert("nu".into(), 0.3.into());
                m
            })
            .collect(),
    );
    put(
        "sections",
        list("sections")
            .into_iter()
            .map(|mut s| {
                let i = s.remove("I").unwrap();
                for key in ["Iz", "Iy", "J"] {
                    s.insert(key.into(), i.clone());
                }
                s
            })
            .collect(),
    );
    put(
        "nodes",
        list("nodes")
            .into_iter()
            .map(|mut n| {
                n.insert("z".into(), 0.0.into());
                n
            })
            .collect(),
    );
    // Each member's local y in the plane, 90° anticlockwise from its axis, so that its
    // local z (the strong axis, about which the plane frame bends) is +z: a connection's
    // own rotation is then the plane frame's, sign included.
    let node_xy = |name: &Value| -> (f64, f64) {
        let n = list("nodes")
            .into_iter()
            .find(|n| n["name"] == *name)
            .unwrap();
        let f = |v: &Value| v.as_float().or(v.as_integer().map(|i| i as f64)).unwrap();
        (f(&n["x"]), f(&n["y"]))
    };
    put(
        "members",
        list("members")
            .into_iter()
            .map(|mut m| {
                let ((xa, ya), (xb, yb)) = (node_xy(&m["from"]), node_xy(&m["to"]));
                let reference = vec![(ya - yb).into(), (xb - xa).into(), 0.0.into()];
                m.insert("orientation".into(), Value::Array(reference));
                m
            })
            .collect(),
    );
    put(
        "joints",
        list("joints")
            .into_iter()
            .map(|mut j| {
                if let Some(i) = j.remove("inertia") {
                    j.insert("inertia".into(), z3(&i));
                }
                j
            })
            .collect(),
    );
    put("supports", list("supports"));
    put(
        "connections",
        list("connections")
            .into_iter()
            .map(|mut c| {
                let k = c.remove("k").unwrap();
                c.insert("strong".into(), k);
                c
            })
            .collect(),
    );
    put(
        "masses",
        list("masses")
            .into_iter()
            .map(|mut m| {
                if let Some(i) = m.remove("inertia") {
                    m.insert("inertia".into(), z3(&i));
                }
                m
            })
            .collect(),
    );
    put("springs", list("springs"));
    put("channels", list("channels"));
    put(
        "parameters",
        list("parameters")
            .into_iter()
            .map(|mut q| {
                if let Some(Value::Array(c)) = q.get_mut("connections") {
                    for x in c.iter_mut() {
                        *x = format!("{}.strong", x.as_str().unwrap()).into();
                    }
                }
                q
            })
            .collect(),
    );
    sf.insert(
        "restrain".into(),
        Value::Array(vec!["z".into(), "rx".into(), "ry".into()]),
    );
    let mut out = toml::Table::new();
    out.insert("name".into(), p["name"].clone());
    if let Some(b) = p.get("bayesian") {
        out.insert("bayesian".into(), b.clone());
    }
    out.insert("space_frame".into(), Value::Table(sf));
    toml::to_string(&out).unwrap()
}

/// All eigenvalues of `K(θ) φ = λ M φ` as frequencies (Hz), ascending, by a full dense
/// decomposition of `L⁻¹ M L⁻ᵀ` (`K = L Lᵀ`): eigenvalues 1/λ, accurate relative to the
/// largest, so the low modes to round-off.
fn all_frequencies(m: &Model, theta: &[f64]) -> Vec<f64> {
    let n = m.n_dof();
    let mut k = faer::Mat::<f64>::zeros(n, n);
    m.stiffness_dense_into(theta, k.as_mut());
    let llt = k.llt(faer::Side::Lower).unwrap();
    let l = llt.L();
    let mut c = m.mass_dense();
    l.solve_lower_triangular_in_place(c.as_mut());
    let mut b = c.transpose().to_owned();
    l.solve_lower_triangular_in_place(b.as_mut());
    let mut f: Vec<f64> = b
        .self_adjoint_eigenvalues(faer::Side::Lower)
        .unwrap()
        .iter()
        .map(|mu| mu.recip().sqrt() / (2.0 * std::f64::consts::PI))
        .collect();
    f.sort_by(f64::total_cmp);
    f
}

/// The planar lab frame written as a space frame (out-of-plane DOFs restrained, members
/// oriented with their strong axis along +z) is the same model, at θ = 1 and at a θ with
/// every parameter moved, and also with an axial force in a column (whose geometric
/// stiffness then enters both):
/// - the same DOFs in the same order (a connection's `.rz` is its `.strong`), and `K0`,
///   every `K_l` and `M` equal entry by entry within 1e-13 of the diagonal (measured
///   1.0e-14: the round-off of the rotation to global axes);
/// - by a full dense decomposition, every frequency below 100 times the first (the 21
///   modes up to 1 kHz, more than any measurement holds) within 1e-10 relative (measured
///   ≤ 2.5e-11), and all 142 within 1e-8: that decomposition's own round-off on mode k is
///   ~ε·(f_k/f_1)², 5e-9 for the highest;
/// - by boltwatch's own solver, the same mode shapes at the channels (MAC > 1 − 1e-10) and
///   the lowest 12 frequencies within 1e-8: the solver's own accuracy, 5e-10 on some modes
///   of this frame against the full decomposition, not the models', bounds this one.
#[test]
fn the_planar_lab_frame_as_a_space_frame_gives_the_same_modes() {
    let planar_text = std::fs::read_to_string(super::common::model_path("lab-frame")).unwrap();
    let with_force = planar_text.replace(
        "name = \"C2L\"\n",
        "name = \"C2L\"\naxial_force = -2000.0\n",
    );
    assert_ne!(with_force, planar_text, "the column entry was found");
    for text in [planar_text, with_force] {
        let planar = Model::from_toml(&text).unwrap();
        let space = Model::from_toml(&planar_as_space(&text)).unwrap();
        let n = planar.n_dof();
        assert_eq!(space.n_dof(), n);
        let labels: Vec<String> = space
            .dof_labels()
            .iter()
            .map(|l| l.replace(".strong", ".rz"))
            .collect();
        assert_eq!(labels, planar.dof_labels());
        assert_eq!(space.n_params(), planar.n_params());
        assert_eq!(space.channels().len(), planar.channels().len());
        let mut pairs = vec![
            (
                "K0".to_string(),
                planar.k0().to_dense(),
                space.k0().to_dense(),
            ),
            (
                "M".to_string(),
                planar.mass().to_dense(),
                space.mass().to_dense(),
            ),
        ];
        for l in 0..n_params(&planar) {
            pairs.push((
                format!("K_{}", l + 1),
                planar.k_param(l).to_dense(),
                space.k_param(l).to_dense(),
            ));
        }
        for (name, a, b) in pairs {
            let mut worst = 0.0f64;
            for i in 0..n {
                for j in 0..n {
                    let scale = a[(i, i)].abs().max(a[(j, j)].abs());
                    if scale > 0.0 {
                        worst = worst.max((a[(i, j)] - b[(i, j)]).abs() / scale);
                    } else {
                        assert_eq!(b[(i, j)], 0.0, "{name}[{i}, {j}]");
                    }
                }
            }
            assert!(worst < 1e-13, "{name}: {worst:e}");
        }
        let moved: Vec<f64> = (0..planar.n_params())
            .map(|l| 0.6 + 0.05 * l as f64)
            .collect();
        for theta in [planar.nominal_theta(), moved] {
            let (fa, fb) = (
                all_frequencies(&planar, &theta),
                all_frequencies(&space, &theta),
            );
            let low = fa.iter().take_while(|f| **f < 100.0 * fa[0]).count();
            let (g_low, g) = (gap(&fb[..low], &fa[..low]), gap(&fb, &fa));
            println!(
                "lowest {low} frequencies: largest relative difference {g_low:.1e}; all {n}: {g:.1e}"
            );
            assert!(low >= 15 && g_low < 1e-10, "{fa:?}\n{fb:?}");
            assert!(g < 1e-8, "{fa:?}\n{fb:?}");
            let solve = |m: &Model| {
                let mut solver = boltwatch::core::modal::solver_for(m).unwrap();
                solver.solve(m, &theta, 12).unwrap()
            };
            let (a, b) = (solve(&planar), solve(&space));
            let fa: Vec<f64> = (0..12).map(|k| a.frequency_hz(k)).collect();
            let fb: Vec<f64> = (0..12).map(|k| b.frequency_hz(k)).collect();
            println!("boltwatch's solver, 12 modes: {:.1e}", gap(&fb, &fa));
            assert!(gap(&fb, &fa) < 1e-8);
            for k in 0..12 {
                let shape = |m: &Model, pairs: &boltwatch::core::modal::EigenPairs| {
                    let col: Vec<f64> = (0..m.n_dof()).map(|i| pairs.phi[(i, k)]).collect();
                    m.channels()
                        .iter()
                        .map(|c| c.read(&col))
                        .collect::<Vec<f64>>()
                };
                let mac = boltwatch::core::modal::mac(&shape(&planar, &a), &shape(&space, &b));
                assert!(mac > 1.0 - 1e-10, "mode {k}: MAC {mac}");
            }
        }
    }
}

fn n_params(m: &Model) -> usize {
    m.n_params()
}

/// The geometric stiffness of an axial force, in both bending planes: a simply supported
/// beam along x (I_y ≠ I_z) under tension T = P_E/2 and compression −P_E/4 of its weaker
/// plane. The first frequency of each plane is
/// `f = (π/L)² √(EI/ρA) / 2π · √(1 + T L²/(π² EI))`; 16 elements are within 1e-5
/// (measured ≤ 1.4e-6: the cubic element's discretization error).
#[test]
fn axial_force_changes_both_bending_frequencies_as_the_closed_form() {
    let (e, rho, a, iy, iz, l) = (2.1e11, 7850.0, 8.0e-4, 2.0e-8, 1.0e-7, 2.0);
    let pe = std::f64::consts::PI.powi(2) * e * iy / (l * l);
    for t in [0.5 * pe, -0.25 * pe] {
        let toml = format!(
            r#"name = "ss-beam"
[space_frame]
materials = [{{ name = "steel", E = {e:e}, nu = 0.3, rho = {rho} }}]
sections = [{{ name = "s", A = {a:e}, Iy = {iy:e}, Iz = {iz:e}, J = 3e-8 }}]
nodes = [{{ name = "a", x = 0.0, y = 0.0, z = 0.0 }}, {{ name = "b", x = {l}, y = 0.0, z = 0.0 }}]
members = [{{ name = "m", from = "a", to = "b", section = "s", material = "steel", elements = 16, axial_force = {t:e} }}]
supports = [{{ node = "a", fix = ["x", "y", "z", "rx"] }}, {{ node = "b", fix = ["y", "z"] }}]
channels = [{{ name = "mid.y", at = "m.8", dir = "y" }}, {{ name = "mid.z", at = "m.8", dir = "z" }}]
"#
        );
        let model = Model::from_toml(&toml).unwrap();
        let mut solver = boltwatch::core::modal::solver_for(&model).unwrap();
        let pairs = solver.solve(&model, &[], 6).unwrap();
        for (plane, i, channel) in [("weak (w)", iy, 1), ("strong (v)", iz, 0)] {
            let exact = (std::f64::consts::PI / l).powi(2) * (e * i / (rho * a)).sqrt()
                / (2.0 * std::f64::consts::PI)
                * (1.0 + t * l * l / (std::f64::consts::PI.powi(2) * e * i)).sqrt();
            // The mode of this plane: the lowest one that moves the mid-span channel.
            let k = (0..6)
                .find(|&k| {
                    let col: Vec<f64> = (0..model.n_dof()).map(|r| pairs.phi[(r, k)]).collect();
                    let y = model
                        .channels()
                        .iter()
                        .map(|c| c.read(&col).abs())
                        .collect::<Vec<_>>();
                    y[channel] > 10.0 * y[1 - channel]
                })
                .unwrap();
            let f = pairs.frequency_hz(k);
            println!("T = {t:.1} N, {plane}: {f:.6} Hz, closed form {exact:.6} Hz");
            assert!(((f - exact) / exact).abs() < 1e-5, "{f} vs {exact}");
        }
    }
}

/// Mode matching on the space frame (issue 25): 20 noisy simulated sets (15 modes, 1 %
/// frequency CoV, 5 % shape NSD), each from its own truth (connection θ drawn in 0.6–1.4,
/// the weak-axis group in 0.8–1.2, E in 0.95–1.05), fitted from θ0 = 1 as `update` fits
/// (restarted from spread starts when a run ends in a local minimum). |θ − θ_true| < 3σ
/// (σ from (15)) holds for at least 95 % of the 600 estimates.
///
/// Also reports which parameters the data identify poorly (mean σ > 0.3) and why: the
/// largest share of a measured mode's strain energy that the parameter's springs store
/// (`θ_l φᵀ K_l φ / λ`, which is also the relative sensitivity `∂ln λ/∂ln θ_l`), the σ it
/// would have were every other parameter known (`1/√(C⁻¹)_ll`), and the parameter it is
/// most correlated with. A σ far above its σ-alone means the data see it only in a
/// combination with others, not that they do not see it.
#[test]
fn mode_matching_recovers_the_space_frame_within_its_uncertainty() {
    use boltwatch::core::updating::{Evaluator, ModeMatching, ModeMatchingOptions};
    use rand::{Rng, SeedableRng};
    boltwatch::core::sequential_numerics();
    let model = Model::from_spec(&spec()).unwrap();
    let p = model.n_params();
    let names: Vec<String> = model.parameters().iter().map(|q| q.name.clone()).collect();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(25);
    let mut mm = ModeMatching::new(Evaluator::new(&model).unwrap());
    // `update`'s default bounds: θ within 1e-3…1e3 of nominal.
    let opts = ModeMatchingOptions {
        bounds: Some((1e-3, 1e3)),
        ..ModeMatchingOptions::default()
    };
    let (mut inside, mut total) = (0, 0);
    let mut sigma_sum = vec![0.0; p];
    let mut misses: Vec<String> = Vec::new();
    let mut at_bound: Vec<String> = Vec::new();
    let mut sigma_alone = vec![0.0; p];
    let mut partner = vec![(String::new(), 0.0); p];
    let draws = 20;
    for draw in 0..draws {
        let truth: Vec<f64> = names
            .iter()
            .map(|n| match n.as_str() {
                "E" => rng.random_range(0.95..1.05),
                "weak" => rng.random_range(0.8..1.2),
                _ => rng.random_range(0.6..1.4),
            })
            .collect();
        let data = super::common::simulated_data(&model, &truth, 15, 0.01, 0.05, true, 500 + draw);
        // As `boltwatch update` fits: from θ0 = 1, restarted from spread starts if that
        // run ends in a local minimum.
        let (r, path) = mm.run_global(&model, &data, &vec![1.0; p], &opts).unwrap();
        assert!(r.converged(), "draw {draw}: {:?}", r.termination);
        let std = r.std();
        for (l, b) in r.at_bound.iter().enumerate() {
            if let Some(b) = b {
                at_bound.push(format!("draw {draw} {} at {b:?}", names[l]));
            }
        }
        // σ of each parameter were the others known, and its most correlated partner.
        let c = r.covariance.as_ref().unwrap();
        let info = {
            use faer::linalg::solvers::Solve;
            c.partial_piv_lu().solve(faer::Mat::<f64>::identity(p, p))
        };
        for l in 0..p {
            sigma_alone[l] += info[(l, l)].recip().sqrt() / draws as f64;
            let (m, rho) = (0..p)
                .filter(|&m| m != l)
                .map(|m| (m, c[(l, m)] / (c[(l, l)] * c[(m, m)]).sqrt()))
                .fold(
                    (l, 0.0f64),
                    |a, b| if b.1.abs() > a.1.abs() { b } else { a },
                );
            partner[l] = (names[m].clone(), rho);
        }
        for l in 0..p {
            total += 1;
            sigma_sum[l] += std[l];
            let z = (r.theta[l] - truth[l]) / std[l];
            if z.abs() < 3.0 {
                inside += 1;
            } else {
                misses.push(format!("draw {draw} {}: z = {z:.2}", names[l]));
            }
        }
        println!(
            "draw {draw}: {} iterations, ε {:.3}, found from {path:?}",
            r.iterations,
            r.epsilon()
        );
    }
    let share = inside as f64 / total as f64;
    println!(
        "|θ − θ_true| < 3σ: {inside} of {total} ({:.1} %); outside: {misses:?}; at a bound: {at_bound:?}",
        100.0 * share
    );
    // Strain-energy shares at θ = 1 over the 15 modes.
    let mut solver = boltwatch::core::modal::solver_for(&model).unwrap();
    let pairs = solver.solve(&model, &model.nominal_theta(), 15).unwrap();
    for l in 0..p {
        let mean_sigma = sigma_sum[l] / draws as f64;
        let energy_share = (0..15)
            .map(|k| {
                let col = pairs.phi.col(k).to_owned();
                let kc = model.k_param(l) * &col;
                let energy: f64 = (0..col.nrows()).map(|i| col[i] * kc[i]).sum();
                energy / pairs.lambda[k]
            })
            .fold(0.0, f64::max);
        let flag = if mean_sigma > 0.3 {
            "  <- poorly identified"
        } else {
            ""
        };
        println!(
            "{:>12}: mean σ {mean_sigma:.3} (alone {:.3}); strain-energy share ≤ {energy_share:.1e}; most correlated with {} ({:+.2}, last draw){flag}",
            names[l], sigma_alone[l], partner[l].0, partner[l].1
        );
    }
    assert!(share >= 0.95, "{share}");
}

/// A `loosening` scenario on the space frame (`scenario --model`, 15 modes): the
/// connection BX21a@J2A1 (its strong-axis spring, a second-storey beam end) loses 50 %
/// over days 40–50 of 60 (300 sets). Replayed with the space frame as the structure, the
/// tracker raises an alarm on that parameter, naming the connection axis it scales, and no
/// alarm on any other. The connections the data do not resolve on their own (per-set σ
/// above `max_std` = 0.3 at commissioning: the first-storey beam ends, see
/// `mode_matching_recovers_the_space_frame_within_its_uncertainty`) are marked
/// `alerts_off`; without that rule their wandering levels raised five false alarms here.
#[test]
fn a_loosening_space_frame_connection_raises_its_alarm_alone() {
    use boltwatch::commands::scenario::{ScenarioArgs, run as scenario};
    use boltwatch::io::mcap::{read_all, topic};
    use boltwatch::settings::StructureSettings;
    boltwatch::core::sequential_numerics();
    let d = super::tracker::tmp_dir("space-loosening");
    let (rec, out) = (d.join("rec.mcap"), d.join("out.mcap"));
    let model = super::common::model_path("space-frame");
    scenario(&ScenarioArgs {
        name: "loosening".into(),
        model: model.clone().into(),
        sets: Some(300),
        days: Some(60.0),
        seed: 3,
        modes: 15,
        connection: Some("BX21a@J2A1".into()),
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
    let mut settings = super::tracker::settings(&super::tracker::NO_CROSSCHECK);
    settings.structures = vec![StructureSettings {
        name: "space-frame".into(),
        model: model.into(),
    }];
    let summary = super::tracker::run_replay(&rec, &out, settings);
    println!("{summary:?}");
    let msgs = read_all(&out).unwrap();
    let on = |suffix: &str| -> Vec<serde_json::Value> {
        msgs.iter()
            .filter(|m| m.topic == topic("space-frame", suffix))
            .map(|m| serde_json::from_slice(&m.data).unwrap())
            .collect()
    };
    let alerts = on("alerts");
    // The connections the data do not resolve on their own are marked, and raise nothing.
    let last = on("stiffness").pop().unwrap();
    let off: Vec<&str> = last["parameters"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|p| p.get("alerts_off").is_some())
        .map(|p| p["name"].as_str().unwrap())
        .collect();
    println!("alerts off: {off:?}");
    assert!(!off.contains(&"BX21a@J2A1"));
    for a in &alerts {
        println!(
            "{} {} {}: {}",
            a["time"], a["level"], a["connection"], a["message"]
        );
    }
    let alarms: Vec<&serde_json::Value> = alerts.iter().filter(|a| a["level"] == "alarm").collect();
    assert!(
        alarms.iter().any(|a| a["connection"] == "BX21a@J2A1"
            && a["message"].as_str().unwrap().contains("BX21a@J2A1.strong")),
        "no alarm on BX21a@J2A1 naming its strong axis"
    );
    assert!(
        alarms.iter().all(|a| a["connection"] == "BX21a@J2A1"),
        "an alarm on another connection"
    );
}

/// The diagnosis catalogue on a space frame (`src/core/diagnosis/space.rs`): each effect
/// is offered at its 3D locations, applies (`simulate --inject` and the diagnosis use the
/// same path), and moves the 15 frequencies the way its physics says. Softening or added
/// inertia lowers none above the base and lowers some by > 1e-4; stiffening or tension
/// raises likewise. The injected model is also drawn (isometric `structure.svg` path).
#[test]
fn the_3d_diagnosis_catalogue_applies_at_every_kind_of_location() {
    use boltwatch::core::diagnosis::Description;
    use boltwatch::core::diagnosis::effects::by_kind;
    let base_model = Model::from_spec(&spec()).unwrap();
    let theta = base_model.nominal_theta();
    let base = frequencies(&base_model, &theta);
    let cases: [(&str, &str, f64, bool); 8] = [
        ("added-mass", "BX21a.2", 0.6, true),
        ("added-mass", "J2B1", 0.6, true),
        ("support-flexibility", "A1.ry", 2e3, true),
        ("member-stiffness", "A1-1.weak", -0.5, true),
        ("member-stiffness", "BZ2B.strong", 0.5, false),
        ("joint-inertia", "J2B1.rx", 0.01, true),
        ("splice", "BZ2B.2.strong", 500.0, true),
        ("axial-force", "BX21a", 2e4, false),
    ];
    for (kind, location, value, lowers) in cases {
        let effect = by_kind(kind).unwrap();
        let mut d = Description::File(spec());
        assert!(
            effect.locations(&d).iter().any(|l| l == location),
            "{kind} not offered at {location}"
        );
        effect
            .apply(&mut d, location, effect.coordinate(value))
            .unwrap();
        let model = d.build().unwrap();
        let f = frequencies(&model, &theta);
        let change: Vec<f64> = f.iter().zip(&base).map(|(a, b)| a / b - 1.0).collect();
        let (lo, hi) = change
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |a, &c| {
                (a.0.min(c), a.1.max(c))
            });
        println!("{kind}@{location} = {value}: frequency changes {lo:+.2e} … {hi:+.2e}");
        if lowers {
            assert!(hi < 1e-9 && lo < -1e-4, "{kind}@{location}: {change:?}");
        } else {
            assert!(lo > -1e-9 && hi > 1e-4, "{kind}@{location}: {change:?}");
        }
        let geometry = boltwatch::draw::Geometry::of(d.spec().unwrap()).unwrap();
        let svg = boltwatch::draw::Canvas::new(&geometry, 720.0, 640.0, kind).finish();
        assert_eq!(svg.matches("<line").count(), geometry.members.len() + 3);
    }
    // A location that is not one is refused, naming it.
    let mut d = Description::File(spec());
    let e = by_kind("splice")
        .unwrap()
        .apply(&mut d, "BZ2B.9.strong", 1e-3)
        .unwrap_err()
        .to_string();
    assert!(e.contains("BZ2B.9.strong"), "{e}");
}

/// `diagnose` on the space frame (~400 candidates of the 3D catalogue): a 0.6 kg mass at
/// mid-span of the second-storey beam BX21a (16 % of the beam's own mass), 15 noisy modes.
/// The mass splits the cluster of the identical beams' local modes near 157 Hz (MAC of the
/// nominal fit down to 0.46), so its first-order screening column is undefined (the step
/// changes the mode pairing) and the candidate is scored at finite values instead. Named
/// alone, at the right node, its value within 3σ, ε brought to a few per cent of before.
#[test]
fn a_hidden_mass_on_the_space_frame_is_named() {
    use boltwatch::core::diagnosis::injection::Injection;
    use boltwatch::core::diagnosis::{Description, DiagnosisOptions, diagnose};
    use boltwatch::core::simulate::{Noise, simulated_measured_data};
    boltwatch::core::sequential_numerics();
    let nominal = Description::File(spec());
    let inj = Injection::parse("added-mass@BX21a.2=0.6").unwrap();
    let mut truth = nominal.clone();
    inj.apply(&mut truth).unwrap();
    let model = truth.build().unwrap();
    let noise = Noise {
        frequency_cov: 0.01,
        shape_nsd: 0.05,
    };
    let data = simulated_measured_data(&model, &model.nominal_theta(), 15, noise, true, 7).unwrap();
    let started = std::time::Instant::now();
    let d = diagnose(&nominal, &data, &DiagnosisOptions::default(), |_, _, _| {}).unwrap();
    let named: Vec<String> = d
        .named
        .iter()
        .map(|n| {
            format!(
                "{}@{} = {:.4} ± {:.4} {}",
                n.refit.effect, n.refit.location, n.refit.value, n.refit.std, n.refit.unit
            )
        })
        .collect();
    println!(
        "{} candidates; named {named:?}; ε {:.1} -> {:.1}; {:.1} s",
        d.n_candidates,
        d.before.epsilon,
        d.after.epsilon,
        started.elapsed().as_secs_f64()
    );
    assert_eq!(d.named.len(), 1, "{named:?}");
    let n = &d.named[0].refit;
    assert_eq!((n.effect, n.location.as_str()), ("added-mass", "BX21a.2"));
    assert!((n.value - 0.6).abs() <= 3.0 * n.std, "{named:?}");
    assert!(d.after.epsilon <= 0.1 * d.before.epsilon);
}

/// The Bayesian MAP on the space frame (596 DOF: the sparse φ substeps and the
/// threshold-free covariance; the dense TSVD Hessian (16) is refused above 500 DOF, as the
/// CLI warns): noise-free data of 15 modes at a truth with every connection moved, σ_c = 1e3,
/// the CLI's prior (std 1000). Newton from θ0 = 1 recovers every θ, the poorly identified
/// first-storey ends too (the data are exact), and the posterior σ are finite and ordered as
/// mode matching finds them (the first storey's largest).
#[test]
fn the_bayesian_map_recovers_the_space_frame() {
    use boltwatch::core::updating::bayesian::{BayesProblem, BayesSettings};
    boltwatch::core::sequential_numerics();
    let model = Model::from_spec(&spec()).unwrap();
    let p = model.n_params();
    let truth: Vec<f64> = (0..p)
        .map(|l| {
            if l + 2 < p {
                0.7 + 0.6 * (l % 7) as f64 / 6.0
            } else {
                1.0
            }
        })
        .collect();
    let data = super::common::simulated_data(&model, &truth, 15, 0.01, 0.05, false, 3);
    let settings = BayesSettings {
        sigma_c: 1e3,
        prior_mean: vec![1.0; p],
        prior_std: vec![1000.0; p],
    };
    let prob = BayesProblem::new(&model, &data, &settings).unwrap();
    assert!(prob.is_sparse());
    let started = std::time::Instant::now();
    let res = prob.solve_newton(&vec![1.0; p], 100).unwrap();
    let err = res
        .state
        .theta
        .iter()
        .zip(&truth)
        .map(|(a, b)| ((a - b) / b).abs())
        .fold(0.0, f64::max);
    let cov = prob.threshold_free_covariance(&res.state).unwrap();
    let std = cov.posterior_theta_std();
    let first_storey = std[..8].iter().cloned().fold(f64::INFINITY, f64::min);
    let second_storey = std[14..28].iter().cloned().fold(0.0, f64::max);
    println!(
        "space frame MAP, σ_c = 1e3: {} iterations, J_p = {:.4e}, max rel. error {err:.2e}, \
         posterior σ first-storey X ends ≥ {first_storey:.3}, second storey ≤ {second_storey:.3}; {:.1} s",
        res.iterations,
        res.terms.total,
        started.elapsed().as_secs_f64()
    );
    assert!(res.converged);
    assert!(err < 1e-4, "max rel. error {err:e}");
    assert!(std.iter().all(|s| s.is_finite() && *s > 0.0), "{std:?}");
    assert!(first_storey > second_storey, "{std:?}");
}
