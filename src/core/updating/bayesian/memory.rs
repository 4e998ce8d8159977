//! What the Bayesian MAP holds in memory on one model, estimated before it runs, so that a
//! process under a memory limit (the deployment's systemd unit: `MemoryMax=1G`) can refuse
//! a cross-check that would not fit instead of being killed in it (issue 27).
//!
//! The estimate counts the arrays the solver allocates, from the model's sizes (the
//! model's matrices are shared with the caller's, not copied): `K(θ)` on the union
//! pattern, and per mode in flight
//! ([`super::reduced`] runs two at a time) the φ substep's working set — on the sparse
//! path the `LDLᵀ` factor of `K(θ) − λ_m M` with its scratch, `A` on the union pattern,
//! `B` and the QR of `[σ_c B; I]`, and the `n × (1 + p)` blocks of the Schur complement;
//! on the dense path the QR of `C_m`, and the dense `K` and `M`. Measured against it (peak
//! RSS of `boltwatch update --method bayesian`, whole process, `/usr/bin/time -v`): the
//! four-bay solid frame (31,458 DOF, 6 modes, 66 channels) estimate 288 MB for the MAP
//! beside a process that holds the model and mode matching's solvers (570 MB alone) and
//! peaks at 0.86–0.89 GB with both.

use super::reduced::MODES_AT_ONCE;
use crate::core::modal::SPARSE_FROM_DOF;
use crate::core::model::Model;

/// Bytes of one `f64` or index.
const WORD: u64 = 8;

/// Blocks of `n × (1 + p)` the Schur complement of one mode holds at once: `J_y`, `E`,
/// `−E`, `s`, `u`, the residuals and corrections of the refinement, `h` and the
/// intermediate products (counted from `shifted.rs` and `reduced.rs`).
const SCHUR_BLOCKS: u64 = 14;

/// Bytes of a faer scratch requirement.
fn scratch_bytes(req: faer::dyn_stack::StackReq) -> u64 {
    req.size_bytes() as u64
}

/// Estimated peak working memory (bytes) of the Bayesian MAP of `model` for `n_modes`
/// measured modes with `n_measured` shape entries each (module docs). `None` if the
/// model's pattern cannot be analysed for factorization.
pub fn map_memory_bytes(model: &Model, n_modes: usize, n_measured: usize) -> Option<u64> {
    let n = model.n_dof() as u64;
    let p = model.n_params() as u64;
    let no = n_measured as u64;
    let nm = n_modes as u64;
    let in_flight = (MODES_AT_ONCE as u64).min(nm.max(1));
    let state = 4 * n * nm * WORD; // φ, its trial and the products of one mode per mode
    if model.n_dof() < SPARSE_FROM_DOF {
        // Dense: K and M, and per mode the QR of C (n + n_o) × n with its reflectors.
        let dense = 3 * n * n * WORD;
        let per_mode = 2 * (n + no) * n * WORD + SCHUR_BLOCKS * n * (1 + p) * WORD;
        return Some(dense + per_mode + state);
    }
    let order = model.reordered().ok()?;
    let union = model.union_pattern().pattern.val().len() as u64;
    let factor = order.symbolic.len_val() as u64 * WORD;
    let scratch = scratch_bytes(
        order
            .symbolic
            .factorize_numeric_ldlt_scratch::<f64>(faer::Par::Seq, Default::default()),
    )
    .max(scratch_bytes(order.symbolic.solve_in_place_scratch::<f64>(
        no.max(1 + p) as usize,
        faer::Par::Seq,
    )));
    let per_mode = factor
        + scratch
        + union * WORD // A on the union pattern
        + order.len() as u64 * WORD // A's lower triangle, while it is factored
        + 3 * n * no * WORD // B, [σ_c B; I] and its QR
        + SCHUR_BLOCKS * n * (1 + p) * WORD;
    Some(union * WORD + in_flight * per_mode + state)
}
