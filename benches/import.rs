//! Issue 24: a 100,000-DOF model imported from matrices. The four-bay solid frame refined
//! to 56 × 1 × 6 elements per beam (100,113 DOF; `K0` 5.7 million and `M` 1.9 million
//! stored entries, 257 MB of Matrix Market text) is exported once, then:
//!
//! - `load`: `read_matrices` as `--model DIR/model.json` runs it: parsing, the checks
//!   (symmetry, massless DOFs, `M` and `K(θ0)` factorized), the union pattern and its AMD
//!   reordering (which the sparse solver then reuses);
//! - `modes_12`: the 12 lowest modes of the imported model with the sparse solver, as
//!   `boltwatch modes -n 12` computes them after the load.

use std::hint::black_box;
use std::path::PathBuf;

use boltwatch::commands::export::{ExportArgs, run as export};
use boltwatch::core::model::import::read_matrices;
use criterion::{Criterion, criterion_group, criterion_main};

fn exported() -> PathBuf {
    let dir = std::env::temp_dir().join(format!("bw-bench-import-{}", std::process::id()));
    let toml = std::fs::read_to_string(format!(
        "{}/config/models/four-bay-solid.toml",
        env!("CARGO_MANIFEST_DIR")
    ))
    .expect("shipped model exists")
    .replace("divisions = [28, 1, 3]", "divisions = [56, 1, 6]");
    std::fs::create_dir_all(&dir).unwrap();
    let model = dir.join("solid-100k.toml");
    std::fs::write(&model, toml).unwrap();
    let out = dir.join("matrices");
    export(&ExportArgs {
        model,
        out: out.clone(),
    })
    .unwrap();
    out.join("model.json")
}

fn bench_import(c: &mut Criterion) {
    boltwatch::no_transparent_huge_pages();
    let json = exported();
    let mut group = c.benchmark_group("import_100k");
    group.sample_size(10);
    group.bench_function("load", |b| {
        b.iter(|| black_box(read_matrices(&json).unwrap()))
    });
    let model = read_matrices(&json).unwrap();
    assert_eq!(model.n_dof(), 100_113);
    boltwatch::core::numerics_for(&model);
    let theta = model.nominal_theta();
    group.bench_function("modes_12", |b| {
        b.iter(|| {
            let mut solver = boltwatch::core::modal::solver_for(&model).unwrap();
            black_box(solver.solve(&model, &theta, 12).unwrap())
        })
    });
    group.finish();
    let _ = std::fs::remove_dir_all(json.parent().unwrap().parent().unwrap());
}

criterion_group!(benches, bench_import);
criterion_main!(benches);
