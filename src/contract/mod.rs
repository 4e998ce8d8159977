//! Wire contracts: the JSON messages boltwatch accepts and emits, with strict validation.

pub mod modal_set;
