//! The fleet (module docs to come).
pub mod rendezvous;
