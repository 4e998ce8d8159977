//! Thin adapters between the sans-I/O [`crate::pipeline`] and the outside world (DESIGN §1):
//! MCAP recordings in and out ([`mcap`]), the JSON schemas of the messages ([`schemas`]) and
//! the atomic checkpoint store ([`checkpoint`]).

pub mod checkpoint;
pub mod mcap;
pub mod replay;
pub mod schemas;
pub mod zenoh;
