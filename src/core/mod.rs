//! Pure numerics: no I/O, clocks or environment. This is where the paper lives.

#![allow(non_snake_case)]

pub mod diagnosis;
pub mod modal;
pub mod model;
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
