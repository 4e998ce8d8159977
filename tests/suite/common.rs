//! Shared helpers for the integration tests.

use boltwatch::core::model::Model;

/// Path of a shipped model file.
pub fn model_path(name: &str) -> String {
    format!("{}/config/models/{name}.toml", env!("CARGO_MANIFEST_DIR"))
}

/// Loads a shipped model.
pub fn load_model(name: &str) -> Model {
    // As the binary does: faer's threading only adds scheduler time on these sizes.
    boltwatch::core::sequential_numerics();
    let text = std::fs::read_to_string(model_path(name)).expect("shipped model exists");
    Model::from_toml(&text).expect("shipped model assembles")
}

/// A straight steel flat-bar cantilever of length 0.6 m along x, clamped at x = 0, with
/// `elements` elements, optionally on a rotational spring `k_base` at the clamp, with one
/// `y` channel per interior node.
pub fn cantilever_toml(elements: usize, k_base: Option<f64>) -> String {
    let mut s = String::from(
        r#"name = "beam"
[[materials]]
name = "steel"
E = 2.1e11
rho = 7840.0
[[sections]]
name = "bar"
A = 5.5e-4
I = 5.5458e-9
[[nodes]]
name = "base"
x = 0.0
y = 0.0
[[nodes]]
name = "tip"
x = 0.6
y = 0.0
[[supports]]
node = "base"
"#,
    );
    s += &format!(
        "[[members]]\nname = \"b\"\nfrom = \"base\"\nto = \"tip\"\nsection = \"bar\"\nmaterial = \"steel\"\nelements = {elements}\n"
    );
    if let Some(k) = k_base {
        s += &format!(
            "[[connections]]\nname = \"root\"\nmember = \"b\"\nnode = \"base\"\nk = {k:e}\n[[parameters]]\nname = \"root\"\nconnections = [\"root\"]\n"
        );
    }
    for k in 1..elements {
        s += &format!("[[channels]]\nname = \"b.{k}\"\nat = \"b.{k}\"\ndir = \"y\"\n");
    }
    s
}

/// Bisection for a sign change of `f` on `[a, b]`, to machine precision.
pub fn bisect(f: impl Fn(f64) -> f64, mut a: f64, mut b: f64) -> f64 {
    let mut fa = f(a);
    for _ in 0..200 {
        let m = 0.5 * (a + b);
        let fm = f(m);
        if fm == 0.0 {
            return m;
        }
        if (fm < 0.0) == (fa < 0.0) {
            a = m;
            fa = fm;
        } else {
            b = m;
        }
    }
    0.5 * (a + b)
}

use boltwatch::core::simulate::{Noise, simulated_measured_data};
use boltwatch::core::updating::MeasuredData;

/// Measured data simulated from `model` at `theta` (all channels), with stated
/// uncertainties `cov`/`nsd` and noise of the same size if `noisy`.
pub fn simulated_data(
    model: &Model,
    theta: &[f64],
    n_modes: usize,
    cov: f64,
    nsd: f64,
    noisy: bool,
    seed: u64,
) -> MeasuredData {
    let stated = Noise {
        frequency_cov: cov,
        shape_nsd: nsd,
    };
    simulated_measured_data(model, theta, n_modes, stated, noisy, seed).unwrap()
}

/// Runs `program` with `args` to completion as a whole process: its wall time in seconds
/// and its standard output. Panics, with its standard error, if it fails.
pub fn run_timed(program: &str, args: &[&str]) -> (f64, Vec<u8>) {
    let start = std::time::Instant::now();
    let out = std::process::Command::new(program)
        .args(args)
        .output()
        .unwrap();
    let secs = start.elapsed().as_secs_f64();
    assert!(
        out.status.success(),
        "{program} {args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    (secs, out.stdout)
}

/// A Python virtual environment `target/<name>` (made once per target directory) in which
/// `import_check` runs; `packages` are pip-installed into it when it does not.
pub fn python_venv(name: &str, import_check: &str, packages: &[&str]) -> std::path::PathBuf {
    use std::process::Command;
    let target = std::env::current_exe()
        .unwrap()
        .ancestors()
        .nth(3)
        .unwrap()
        .to_path_buf();
    let venv = target.join(name);
    let python = venv.join("bin/python");
    if !python.exists() {
        let ok = Command::new("python3")
            .args(["-m", "venv"])
            .arg(&venv)
            .status()
            .unwrap()
            .success();
        assert!(ok, "python3 -m venv {} failed", venv.display());
    }
    let imports = || {
        Command::new(&python)
            .args(["-c", import_check])
            .stderr(std::process::Stdio::null())
            .status()
            .unwrap()
            .success()
    };
    if !imports() {
        let ok = Command::new(&python)
            .args(["-m", "pip", "install", "--quiet"])
            .args(packages)
            .status()
            .unwrap()
            .success();
        assert!(ok, "pip install {packages:?} failed");
        assert!(
            imports(),
            "`{import_check}` fails after pip install {packages:?}"
        );
    }
    python
}

/// What an independent validator (the `jsonschema` crate) finds wrong with `instance`
/// against the JSON schema `schema` (text).
pub fn schema_errors(schema: &str, instance: &serde_json::Value) -> Vec<String> {
    let schema: serde_json::Value = serde_json::from_str(schema).unwrap();
    jsonschema::validator_for(&schema)
        .unwrap()
        .iter_errors(instance)
        .map(|e| e.to_string())
        .collect()
}
