//! Thin adapters between the sans-I/O [`crate::pipeline`] and the outside world (DESIGN §1):
//! MCAP recordings in and out ([`mcap`]), the JSON schemas of the messages ([`schemas`]),
//! the atomic checkpoint store ([`checkpoint`]), model files ([`model`]), and what the replay
//! and daemon drivers share ([`driver`]).

pub mod checkpoint;
pub mod driver;
pub mod job_thread;
pub mod mcap;
pub mod model;
pub mod record;
pub mod replay;
pub mod schemas;
pub mod zenoh;
