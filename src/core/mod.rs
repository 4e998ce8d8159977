//! Pure numerics: no I/O, clocks or environment. This is where the paper lives.

#![allow(non_snake_case)]

pub mod diagnosis;
pub mod modal;
pub mod model;
pub mod normalisation;
pub mod oma;
pub mod plan;
pub mod simulate;
pub mod stats;
pub mod updating;

/// Runs faer's dense kernels on the calling thread. The matrices of a model update are small
/// (at most a few hundred columns), and on this class of machine (2 cores) faer's
/// fine-grained threading spent 30 % of an update in the kernel scheduler (measured with
/// `perf` on the lab frame) for no gain. Concurrency in boltwatch is per structure instead.
pub fn sequential_numerics() {
    faer::set_global_parallelism(faer::Par::Seq);
}

/// For a command working on one model: faer on every core when the model is one the sparse
/// solver handles (its factorizations and block products are large enough to gain), else
/// sequential.
pub fn numerics_for(model: &model::Model) {
    if model.n_dof() >= modal::SPARSE_FROM_DOF {
        faer::set_global_parallelism(faer::Par::rayon(0));
    } else {
        sequential_numerics();
    }
}

/// Helper threads for a tracking thread's short parallel steps (a small model's Nelson
/// shares): one per core but one (at most three), kept for the process (a thread spawned
/// per Jacobian cost as much as it saved on the lab frame), and apart from rayon's global
/// pool, which long jobs keep busy. The caller does its own share and waits for the rest.
/// `None` on one core. Hand-offs are not free: splitting the lab frame's warm eigen
/// solves (4 block solves of ~35 µs each) this way made a replay 20 % slower.
pub fn helpers() -> Option<&'static rayon::ThreadPool> {
    static POOL: std::sync::OnceLock<Option<rayon::ThreadPool>> = std::sync::OnceLock::new();
    POOL.get_or_init(|| {
        let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
        if cores < 2 {
            return None;
        }
        rayon::ThreadPoolBuilder::new()
            .num_threads((cores - 1).min(3))
            .thread_name(|i| format!("helper-{i}"))
            .build()
            .map_err(|e| tracing::warn!("no helper threads: {e}"))
            .ok()
    })
    .as_ref()
}
