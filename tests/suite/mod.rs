mod calibration;
mod cantilever_cases;
mod cli;
mod common;
mod fe;
mod modal_set;
mod mode_matching;
mod sensitivity;
