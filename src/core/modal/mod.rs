//! Modal analysis: the generalized symmetric eigenproblem `K φ = λ M φ` behind one
//! interface ([`EigenSolver`]), eigenvalue and exact eigenvector sensitivities (Nelson's
//! method), MAC (26) and mode pairing (29).

pub mod dense;
pub mod eigen;
pub mod krylov;
pub mod mac;
mod rows;
pub mod sensitivity;
pub mod tridiag;
mod up_looking;

pub use dense::DenseEigen;
pub use eigen::{EigenPairs, EigenSolver};
pub use krylov::SparseEigen;
pub use mac::{mac, pair_modes};
pub use sensitivity::{Nelson, SharedStiffness};

/// Models with at least this many DOFs get the sparse solver from [`solver_for`]. Below it
/// the dense solver is as fast or faster from a cold start and is the reference; its full
/// tridiagonal reduction (`O(n³)`, [`dense`]'s `top_eigenvectors`) is kept below 500.
/// Measured (`cargo bench --bench space_frame -- eigen_solve`, one full solve): the 142-DOF
/// lab frame, 12 modes, dense 1.08 ms against sparse 1.75 ms; the 596-DOF space frame, 15
/// modes, dense 27.2 ms against sparse 12.7 ms (whole mode-matching updates of the space
/// frame 2–4× faster). Every planar bundled model stays dense.
pub const SPARSE_FROM_DOF: usize = 500;

/// The eigen solver for a model, chosen by size: [`SparseEigen`] from
/// [`SPARSE_FROM_DOF`] DOFs, [`DenseEigen`] below.
pub fn solver_for(
    model: &crate::core::model::Model,
) -> Result<Box<dyn EigenSolver + Send>, ModalError> {
    if model.n_dof() >= SPARSE_FROM_DOF {
        Ok(Box::new(SparseEigen::new(model)?))
    } else {
        Ok(Box::new(DenseEigen::new(model)?))
    }
}

/// Symbolic Cholesky factorization (AMD ordering, lower side) of the model's union
/// pattern of `K0`, every `K_l` and `M`: the one every sparse factorization of a
/// `K(θ) − σM` reuses.
pub(crate) fn union_symbolic_cholesky(
    model: &crate::core::model::Model,
) -> Result<faer::sparse::linalg::cholesky::SymbolicCholesky<usize>, ModalError> {
    faer::sparse::linalg::cholesky::factorize_symbolic_cholesky(
        model.union_pattern().pattern.symbolic(),
        faer::Side::Lower,
        faer::sparse::linalg::cholesky::SymmetricOrdering::Amd,
        Default::default(),
    )
    .map_err(|e| ModalError::Factorization(format!("{e:?}")))
}

/// The model's reordered pattern for sparse factorizations
/// ([`crate::core::model::Model::reordered`]).
pub(crate) fn reordered(
    model: &crate::core::model::Model,
) -> Result<&crate::core::model::Reordered, ModalError> {
    model
        .reordered()
        .map_err(|e| ModalError::Factorization(format!("{e:?}")))
}

/// Column `j` of a matrix whose columns are contiguous (an owned matrix's, or a column
/// range of one), as a slice.
pub(crate) fn col_slice(a: faer::MatRef<'_, f64>, j: usize) -> &[f64] {
    a.col(j)
        .try_as_col_major()
        .expect("columns of an owned matrix are contiguous")
        .as_slice()
}

/// [`col_slice`], mutable.
pub(crate) fn col_slice_mut(a: faer::MatMut<'_, f64>, j: usize) -> &mut [f64] {
    a.col_mut(j)
        .try_as_col_major_mut()
        .expect("columns of an owned matrix are contiguous")
        .as_slice_mut()
}

/// Failures of the modal layer.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ModalError {
    #[error("eigen solver failed: {0}")]
    EigenFailed(String),
    #[error(
        "asked for {asked} modes but the model has {available} (one per DOF that carries mass)"
    )]
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
