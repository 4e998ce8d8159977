//! Pure numerics: no I/O, clocks or environment. This is where the paper lives.

#![allow(non_snake_case)]

pub mod modal;
pub mod model;
pub mod simulate;
pub mod updating;
