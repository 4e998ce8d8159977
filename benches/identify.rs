//! Issue 26: a 5-minute, 42-channel, 1 kHz record of the lab frame (simulated: its 11 modes
//! below 400 Hz, 1 % damping, 2 % sensor noise), written once as CSV (124 MB), then:
//!
//! - `csv_read`: [`read_csv`], the parsing `boltwatch identify --input` does;
//! - `identify`: SSI-COV with the automatic mode choice and every mode's first-order
//!   standard deviations (30 blocks), the default options;
//! - `identify_of_csv_record`: the identification of the record read from the CSV;
//! - `csv_and_identify`: both, the target (< 2 s on two cores).
//!
//! And `identify_240s_6ch_256hz`: a record the size of the measured frame in
//! `tests/data/pyoma-frame` (target < 0.5 s).
//!
//! `cargo bench --bench identify`.

use std::hint::black_box;

use boltwatch::core::model::Model;
use boltwatch::core::model::spec::ModelSpec;
use boltwatch::core::oma::identify::{IdentifyOptions, identify};
use boltwatch::core::oma::synth::{SynthOptions, accelerations, light_damping_frame};
use boltwatch::io::record::{read_csv, write_csv};
use criterion::{Criterion, criterion_group, criterion_main};

fn bench_identify(c: &mut Criterion) {
    let text = std::fs::read_to_string(format!(
        "{}/config/models/lab-frame.toml",
        env!("CARGO_MANIFEST_DIR")
    ))
    .expect("shipped model exists");
    let spec: ModelSpec = toml::from_str(&text).unwrap();
    let model = Model::from_spec(&spec).unwrap();
    let sim = accelerations(
        &model,
        &model.nominal_theta(),
        &SynthOptions {
            rate_hz: 1000.0,
            duration_s: 300.0,
            damping: 0.01,
            max_frequency_hz: Some(400.0),
            noise_rel: 0.02,
            seed: 1,
            quantities: vec![],
        },
    )
    .unwrap();
    let dir = std::env::temp_dir().join(format!("bw-bench-identify-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let csv = dir.join("lab-frame-5min.csv");
    write_csv(&csv, &sim.record, 0.0).unwrap();
    let opts = IdentifyOptions::default();
    let mut g = c.benchmark_group("identify_5min_42ch_1khz");
    g.sample_size(10);
    g.bench_function("csv_read", |b| {
        b.iter(|| black_box(read_csv(&csv).unwrap()))
    });
    g.bench_function("identify", |b| {
        b.iter(|| black_box(identify(&sim.record, &opts).unwrap()))
    });
    let from_csv = read_csv(&csv).unwrap();
    g.bench_function("identify_of_csv_record", |b| {
        b.iter(|| black_box(identify(&from_csv.record, &opts).unwrap()))
    });
    g.bench_function("csv_and_identify", |b| {
        b.iter(|| {
            let f = read_csv(&csv).unwrap();
            black_box(identify(&f.record, &opts).unwrap())
        })
    });
    g.finish();
    let _ = std::fs::remove_dir_all(&dir);
}

/// A 240-s record of 6 channels at 256 Hz with nine modes of 0.2 % damping from 1.1 to
/// 14.6 Hz (the size of the measured frame in `tests/data/pyoma-frame`): the whole
/// identification with settings from the record (target < 0.5 s).
fn bench_few_channels(c: &mut Criterion) {
    let sim = light_damping_frame();
    let opts = IdentifyOptions::default();
    let mut g = c.benchmark_group("identify_240s_6ch_256hz");
    g.sample_size(10);
    g.bench_function("identify", |b| {
        b.iter(|| black_box(identify(&sim.record, &opts).unwrap()))
    });
    g.finish();
}

criterion_group!(benches, bench_identify, bench_few_channels);
criterion_main!(benches);
