//! Steps 2–3 of the module docs of [`super`]: the first-order changes of the observability
//! matrix from each block's Hankel difference (the perturbed thin SVD), kept as their
//! projections per block at the largest order.

use faer::Mat;
use faer::linalg::solvers::Svd;

use super::covariance::BlockCovariances;
use crate::core::oma::OmaError;
use crate::core::oma::ssi::block_hankel;

/// The first-order changes of the observability matrix's projections, one set per block
/// (module docs, steps 2–3), at the largest order `n_max`.
#[derive(Debug, Clone)]
pub struct Sensitivities {
    pub n_max: usize,
    /// Output rows per block row.
    pub r: usize,
    pub rate_hz: f64,
    /// `O` at `n_max` (`(s·r) × n_max`).
    pub o: Mat<f64>,
    /// Per block: `Q1, Q2, Q3` (`n_max × n_max`) and `Q4` (`r × n_max`).
    pub q: Vec<[Mat<f64>; 4]>,
    /// Per channel, the power of the continuous pole its shape entry is multiplied by
    /// (channels of mixed quantities, [`crate::core::oma::Quantity`]); all 0 for
    /// accelerations.
    pub powers: Vec<i32>,
}

/// Steps 2–3 of the module docs for the SVD
/// ([`hankel_svd`](crate::core::oma::ssi::hankel_svd)) of the Hankel matrix (the mean of
/// the blocks), its blocks' lag differences `cov.deltas`, and `s` block rows.
pub fn sensitivities(
    svd: &Svd<f64>,
    cov: &BlockCovariances,
    s: usize,
    n_max: usize,
    rate_hz: f64,
) -> Result<Sensitivities, OmaError> {
    use rayon::prelude::*;
    let r = cov.mean[0].nrows();
    let (u, v) = (svd.U(), svd.V());
    let sig: Vec<f64> = svd.S().column_vector().iter().copied().collect();
    let k = sig.len();
    if n_max > k || sig[n_max - 1] <= 0.0 {
        return Err(OmaError::Numerical(format!(
            "order {n_max} exceeds the rank of the Hankel matrix"
        )));
    }
    let m = u.nrows();
    let o = Mat::from_fn(m, n_max, |i, j| u[(i, j)] * sig[j].sqrt());
    let rows = m - r;
    let up = o.subrows(0, rows);
    let down = o.subrows(r, rows);
    let u1 = u.subcols(0, n_max);
    let v1 = v.subcols(0, n_max);
    let q: Vec<[Mat<f64>; 4]> = cov
        .deltas
        .par_iter()
        .map(|dl| {
            let d = block_hankel(dl, s);
            let z = &d * v1;
            let y = d.transpose() * u1;
            let a_hat = u.transpose() * &z;
            let b_hat = v.transpose() * &y;
            // ΔU₁ = U X + (I − U Uᵀ) Z Σ₁⁻¹ = U (X − Â Σ₁⁻¹) + Z Σ₁⁻¹, one product with U.
            let x = Mat::from_fn(k, n_max, |i, j| {
                let in_span = if i == j {
                    0.0
                } else {
                    (sig[j] * a_hat[(i, j)] + sig[i] * b_hat[(i, j)])
                        / (sig[j] * sig[j] - sig[i] * sig[i])
                };
                in_span - a_hat[(i, j)] / sig[j]
            });
            let mut du = u * &x;
            for j in 0..n_max {
                for i in 0..m {
                    du[(i, j)] += z[(i, j)] / sig[j];
                }
            }
            let d_o = Mat::from_fn(m, n_max, |i, j| {
                du[(i, j)] * sig[j].sqrt() + u[(i, j)] * a_hat[(j, j)] / (2.0 * sig[j].sqrt())
            });
            let d_up = d_o.subrows(0, rows);
            let d_down = d_o.subrows(r, rows);
            [
                up.transpose() * d_up,
                down.transpose() * d_up,
                up.transpose() * d_down,
                d_o.subrows(0, r).to_owned(),
            ]
        })
        .collect();
    Ok(Sensitivities {
        n_max,
        r,
        rate_hz,
        o,
        q,
        powers: vec![0; r],
    })
}
