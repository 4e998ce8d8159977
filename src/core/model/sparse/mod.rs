//! Sparse symmetric matrices as the model holds them, and the union pattern on which
//! `K(θ) − λM` is formed without re-deriving structure.
//!
//! The CSC type and building it from entries (`csc`), products with vectors and blocks
//! (`product`), the union pattern and the value layouts its sources scatter into
//! (`union`), fill-reducing orderings (`ordering`), and the union reordered with its
//! symbolic Cholesky factorization (`reorder`). Every item is re-exported here.

mod csc;
mod ordering;
mod product;
mod reorder;
mod union;

pub(crate) use csc::Accumulator;
pub use csc::{
    Csc, column_pairs, csc_from_lower, csc_from_one_triangle, csc_from_triplets, diagonal,
};
pub use ordering::QUOTIENT_ORDERING_FROM_DOF;
pub use product::{spmm_symmetric, spmv_add};
pub use reorder::Reordered;
pub(super) use union::column_blocks;
pub use union::{MIRROR, UnionPattern, ValueLayout};
