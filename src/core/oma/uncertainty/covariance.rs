//! Step 1 of the module docs of [`super`]: the lag covariances of a record cut into
//! contiguous blocks, their mean and each block's scaled difference from it.

use faer::{Mat, MatRef, Par};

use crate::core::oma::OmaError;

/// Lag covariances of a record cut into blocks (module docs, step 1).
#[derive(Debug, Clone)]
pub struct BlockCovariances {
    /// The mean over the blocks of `R_0 … R_L` (`r × r0` each).
    pub mean: Vec<Mat<f64>>,
    /// Per block, `(R_i^(k) − R_i)/√(n_b(n_b − 1))` for `i = 0 … L`.
    pub deltas: Vec<Vec<Mat<f64>>>,
}

/// The lag covariances `0 … lags` of `n_blocks` contiguous blocks of `y` (module docs).
pub fn block_covariances(
    y: MatRef<'_, f64>,
    refs: &[usize],
    lags: usize,
    n_blocks: usize,
) -> Result<BlockCovariances, OmaError> {
    use rayon::prelude::*;
    let n = y.nrows();
    let usable = n.saturating_sub(lags);
    let nb = usable / n_blocks.max(1);
    if n_blocks < 2 || nb < 2 * lags {
        return Err(OmaError::TooShort {
            samples: n,
            lags,
            need: n_blocks.max(2) * 2 * lags + lags,
        });
    }
    let per_block: Vec<Vec<Mat<f64>>> = (0..n_blocks)
        .into_par_iter()
        .map(|b| lagged_products(y.subrows(b * nb, nb + lags), refs, nb, lags))
        .collect();
    let mean: Vec<Mat<f64>> = (0..=lags)
        .map(|i| {
            let mut m = Mat::zeros(y.ncols(), refs.len());
            for blk in &per_block {
                m += &blk[i];
            }
            m * faer::Scale(1.0 / n_blocks as f64)
        })
        .collect();
    let scale = 1.0 / ((n_blocks * (n_blocks - 1)) as f64).sqrt();
    let deltas = per_block
        .into_iter()
        .map(|blk| {
            blk.into_iter()
                .zip(&mean)
                .map(|(r, m)| (r - m) * faer::Scale(scale))
                .collect()
        })
        .collect();
    Ok(BlockCovariances { mean, deltas })
}

/// `R_i = Σ_{t<nb} y_{t+i} y_{t,ref}ᵀ / nb` for `i = 0 … lags` of `y` (`nb + lags` rows):
/// per reference one product of `yᵀ` with the Hankel matrix of that reference's samples
/// (zero-padded `lags` on both sides), whose column `j` is the reference delayed by
/// `lags − j`. One product per reference rather than one per lag: each operand is packed
/// for the multiplication once, not `lags + 1` times.
fn lagged_products(y: MatRef<'_, f64>, refs: &[usize], nb: usize, lags: usize) -> Vec<Mat<f64>> {
    let mut out = vec![Mat::zeros(y.ncols(), refs.len()); lags + 1];
    let mut padded = vec![0.0; nb + 2 * lags];
    let mut product = Mat::zeros(y.ncols(), lags + 1);
    for (q, &j) in refs.iter().enumerate() {
        for (p, v) in padded[lags..lags + nb].iter_mut().zip(y.col(j).iter()) {
            *p = *v;
        }
        faer::linalg::matmul::matmul(
            product.as_mut(),
            faer::Accum::Replace,
            y.transpose(),
            hankel_view(&padded, nb + lags, lags + 1),
            1.0 / nb as f64,
            Par::Seq,
        );
        for (i, r) in out.iter_mut().enumerate() {
            r.col_mut(q).copy_from(product.col(lags - i));
        }
    }
    out
}

/// The `rows × cols` Hankel matrix `H[a, b] = buf[a + b]`, a view of `buf`.
fn hankel_view(buf: &[f64], rows: usize, cols: usize) -> MatRef<'_, f64> {
    assert!(rows + cols <= buf.len() + 1 && rows > 0 && cols > 0);
    // SAFETY: every entry read, `buf[a + b]` with `a < rows`, `b < cols`, lies inside
    // `buf` (asserted above), which the returned view borrows, so it is initialised and
    // not written while the view lives; overlapping rows and columns are only read.
    unsafe { MatRef::from_raw_parts(buf.as_ptr(), rows, cols, 1, 1) }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The lag products by Hankel view against their definition `Σ_t y_{t+i} y_{t,ref}ᵀ / nb`,
    /// every lag and reference; 1e-12 relative: both sum the same products, in another order.
    #[test]
    fn lagged_products_match_their_definition() {
        // Two modes as discrete AR(2) processes seen by three channels with noise.
        let modes = [(1.9, 0.02, [1.0, 0.6, -0.3]), (4.7, 0.02, [0.4, -1.0, 0.8])];
        let rec = crate::core::oma::ssi::ar2_record(50.0, &modes, 400, 3, 0.5);
        let (nb, lags, refs) = (300, 7, [2usize, 0]);
        let y = rec.samples.subrows(5, nb + lags);
        let fast = lagged_products(y, &refs, nb, lags);
        for (i, r) in fast.iter().enumerate() {
            for (q, &j) in refs.iter().enumerate() {
                for c in 0..y.ncols() {
                    let direct =
                        (0..nb).map(|t| y[(t + i, c)] * y[(t, j)]).sum::<f64>() / nb as f64;
                    let scale = direct.abs().max(1e-3);
                    assert!(
                        (r[(c, q)] - direct).abs() < 1e-12 * scale.max(1.0),
                        "lag {i}, channel {c}, reference {j}: {} against {direct}",
                        r[(c, q)]
                    );
                }
            }
        }
    }
}
