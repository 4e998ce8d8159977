//! `boltwatch plan` on the space frame (78 channels, 15 modes, 28 connections): 12 sensors
//! added greedily from every free translation of the mesh, with everything plan.json
//! holds (both assessments, the modes' value, effective independence and 100 random
//! placements), as the command runs it. Target: under 10 s on 2 cores.

use boltwatch::commands::plan::{Candidates, PlanArgs, run};
use criterion::{Criterion, criterion_group, criterion_main};

fn plan_12(c: &mut Criterion) {
    boltwatch::core::sequential_numerics();
    let out = std::env::temp_dir().join("boltwatch-bench-plan");
    let args = PlanArgs {
        model: format!(
            "{}/config/models/space-frame.toml",
            env!("CARGO_MANIFEST_DIR")
        )
        .into(),
        channels: None,
        candidates: Candidates::Dofs,
        add: Some(12),
        budget: None,
        target_loss: 0.2,
        modes: 15,
        noise: "0.01,0.05".into(),
        sets: 20,
        per_day: 4.0,
        config: None,
        verify: 0,
        out,
    };
    let mut group = c.benchmark_group("plan");
    group.sample_size(10);
    group.bench_function("space frame, 12 sensors added", |b| {
        b.iter(|| run(&args).unwrap())
    });
    group.finish();
}

criterion_group!(benches, plan_12);
criterion_main!(benches);
