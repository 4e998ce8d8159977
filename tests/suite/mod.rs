mod common;
mod fe;
