//! boltwatch: structural health monitoring of bolted connections by FE model updating.
//!
//! See `README.md` and the paper map in `src/core/mod.rs`.

pub mod commands;
pub mod contract;
pub mod core;
pub mod daemon;
pub mod io;
pub mod pipeline;
pub mod plot;
pub mod scenario;
pub mod settings;

/// mimalloc instead of the system allocator: the tracking path allocates and frees many
/// short-lived vectors and matrices per modal set, and glibc's malloc spent ~10 % of a
/// replay in consolidating free chunks (measured with `perf`, issue 4).
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;
