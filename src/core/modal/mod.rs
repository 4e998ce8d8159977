//! Modal analysis: the generalized symmetric eigenproblem `K φ = λ M φ` behind one
//! interface ([`EigenSolver`]), eigenvalue and exact eigenvector sensitivities (Nelson's
//! method), MAC (26) and mode pairing (29).

pub mod eigen;
pub mod mac;
pub mod sensitivity;

pub use eigen::{DenseEigen, EigenPairs, EigenSolver};
pub use mac::{mac, pair_modes};
pub use sensitivity::Nelson;

/// Failures of the modal layer.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ModalError {
    #[error("mass matrix is not positive definite (Cholesky failed)")]
    MassNotPositiveDefinite,
    #[error("eigen solver failed: {0}")]
    EigenFailed(String),
    #[error("asked for {asked} modes but the model has {available} DOFs")]
    TooManyModes { asked: usize, available: usize },
    #[error(
        "non-positive or non-finite eigenvalue λ_{index} = {value}: K(θ) is not positive definite"
    )]
    NotPositive { index: usize, value: f64 },
    #[error(
        "mode {mode}: eigenvalue is repeated or nearly so; its eigenvector derivative is undefined"
    )]
    RepeatedEigenvalue { mode: usize },
    #[error("sparse factorization of K − λM failed: {0}")]
    Factorization(String),
}
