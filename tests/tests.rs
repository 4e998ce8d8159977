//! One integration-test binary; modules under `tests/suite/`.

mod suite;
