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
