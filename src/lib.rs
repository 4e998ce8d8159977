//! boltwatch: structural health monitoring of bolted connections by FE model updating.
//!
//! See `README.md` and the paper map in `src/core/mod.rs`.

pub mod commands;
pub mod contract;
pub mod core;
pub mod io;
pub mod pipeline;
pub mod plot;
pub mod scenario;
pub mod settings;
