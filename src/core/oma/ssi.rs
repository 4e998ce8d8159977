//! Covariance-driven stochastic subspace identification (SSI-COV), after Peeters & De
//! Roeck (MSSP 13(6), 1999, §3) in the notation of Döhler & Mevel (MSSP 38(2), 2013, §2).
//!
//! The output `y_k ∈ ℝ^r` of a linear system driven by white noise has covariances
//! `R_i = E[y_{k+i} y_{k,ref}ᵀ] = C Aⁱ⁻¹ G` (`r × r0`, the `r0` reference channels). The
//! block Hankel matrix of lags `1 … 2s − 1`,
//!
//! ```text
//!     H = [R_1 R_2 … R_s; R_2 R_3 … R_{s+1}; … ; R_s … R_{2s−1}]   ((s·r) × (s·r0))
//! ```
//!
//! factors as `H = O Q` with the observability matrix `O = [C; CA; …; CA^{s−1}]`. Its SVD
//! `H = U Σ Vᵀ` truncated at the model order `n` gives `O = U_1 Σ_1^{1/2}`, `C` its first
//! block row, and `A` from the shift invariance `O↑ A = O↓` (`O` without its last and its
//! first block row) in the least-squares sense. Each eigenvalue `λ` of `A` (one of each
//! complex-conjugate pair) is a discrete pole: `μ = f_s ln λ`, natural frequency
//! `|μ| / 2π`, damping ratio `−Re μ / |μ|`, and mode shape `C ψ` for its eigenvector `ψ`.
//! One SVD serves every model order.

use faer::linalg::solvers::Svd;
use faer::{Mat, MatRef, Par, c64};
use rayon::prelude::*;

use super::{OmaError, Record};

/// Options of [`identify_poles`].
#[derive(Debug, Clone)]
pub struct SsiOptions {
    /// Block rows `s` of the Hankel matrix (also its block columns): lags `1 … 2s − 1`.
    /// The largest model order is `s · min(r, r0)`.
    pub block_rows: usize,
    /// Model orders `order_step, 2·order_step, …, order_max`.
    pub order_max: usize,
    pub order_step: usize,
    /// Reference channels (indices into the record's channels); when empty, chosen by
    /// [`choose_references`] (at most [`AUTO_REFERENCES`]).
    pub references: Vec<usize>,
}

/// Reference channels chosen automatically when none are given. The covariances cost
/// `N · r · r0 · 2s` flops and the SVD `(s·r)(s·r0)²`: with 42 channels, 12 references cut
/// both 3.5-fold, and 12 independent directions of response are more than the modes of a
/// band need to be seen (every mode a reference sees is identified at every channel).
pub const AUTO_REFERENCES: usize = 12;

/// The `k` channels whose responses are the most independent: the first `k` pivots of a
/// column-pivoted QR of the zero-lag covariance `R_0` (`r × r`; channels scaled to unit
/// variance first, so units and gains do not decide). All channels when `k ≥ r`.
pub fn choose_references(y: MatRef<'_, f64>, k: usize) -> Vec<usize> {
    let r = y.ncols();
    if k >= r {
        return (0..r).collect();
    }
    let n = y.nrows() as f64;
    let r0 = y.transpose() * y * faer::Scale(1.0 / n);
    let scaled = Mat::from_fn(r, r, |i, j| {
        r0[(i, j)] / (r0[(i, i)] * r0[(j, j)]).sqrt().max(f64::MIN_POSITIVE)
    });
    let qr = scaled.col_piv_qr();
    let perm = qr.P();
    let (fwd, _) = perm.arrays();
    let mut refs: Vec<usize> = fwd[..k].to_vec();
    refs.sort_unstable();
    refs
}

/// One pole of the identified state matrix at one model order.
#[derive(Debug, Clone)]
pub struct Pole {
    pub order: usize,
    pub frequency_hz: f64,
    /// Damping ratio (a fraction).
    pub damping: f64,
    /// Complex mode shape `C ψ`, one entry per channel.
    pub shape: Vec<c64>,
}

/// The poles of every model order of one record.
#[derive(Debug, Clone)]
pub struct PoleSet {
    pub orders: Vec<usize>,
    pub poles: Vec<Pole>,
    /// Singular values of the block Hankel matrix, descending.
    pub singular_values: Vec<f64>,
}

/// Output covariances `R_0 … R_lags` (each `r × r0`) of a record, unbiased:
/// `R_i = Σ_k y_{k+i} y_{k,ref}ᵀ / (N − i)`.
pub fn output_covariances(y: MatRef<'_, f64>, refs: &[usize], lags: usize) -> Vec<Mat<f64>> {
    use rayon::prelude::*;
    let n = y.nrows();
    let yr = Mat::from_fn(n, refs.len(), |k, j| y[(k, refs[j])]);
    (0..=lags)
        .into_par_iter()
        .map(|i| {
            let m = n - i;
            let mut r = Mat::zeros(y.ncols(), refs.len());
            faer::linalg::matmul::matmul(
                r.as_mut(),
                faer::Accum::Replace,
                y.subrows(i, m).transpose(),
                yr.subrows(0, m),
                1.0 / m as f64,
                Par::Seq,
            );
            r
        })
        .collect()
}

/// The block Hankel matrix of lags `1 … 2s − 1` from covariances `R_0 …`.
pub fn block_hankel(cov: &[Mat<f64>], s: usize) -> Mat<f64> {
    let (r, r0) = (cov[0].nrows(), cov[0].ncols());
    Mat::from_fn(s * r, s * r0, |i, j| {
        let (a, b) = (i / r, j / r0);
        cov[a + b + 1][(i % r, j % r0)]
    })
}

/// The poles of `record` at every model order (module docs).
pub fn identify_poles(record: &Record, opts: &SsiOptions) -> Result<PoleSet, OmaError> {
    let r = record.channels.len();
    let refs: Vec<usize> = if opts.references.is_empty() {
        choose_references(record.samples.as_ref(), AUTO_REFERENCES)
    } else {
        opts.references.clone()
    };
    if let Some(&bad) = refs.iter().find(|&&j| j >= r) {
        return Err(OmaError::Input(format!(
            "reference channel {bad} is out of range (the record has {r} channels)"
        )));
    }
    let s = opts.block_rows;
    if s < 2 {
        return Err(OmaError::Input(format!(
            "block_rows = {s}: need at least 2"
        )));
    }
    let lags = 2 * s - 1;
    let need = 10 * lags;
    if record.len() < need {
        return Err(OmaError::TooShort {
            samples: record.len(),
            lags,
            need,
        });
    }
    let cov = output_covariances(record.samples.as_ref(), &refs, lags);
    let h = block_hankel(&cov, s);
    let mut poles = poles_from_hankel(h.as_ref(), r, record.rate_hz, opts)?;
    shapes_to_acceleration(&mut poles, &powers(record));
    Ok(poles)
}

/// The thin SVD of a block Hankel matrix: the identification and its uncertainty share it.
pub fn hankel_svd(h: MatRef<'_, f64>) -> Result<Svd<f64>, OmaError> {
    h.thin_svd()
        .map_err(|e| OmaError::Numerical(format!("SVD of the Hankel matrix: {e:?}")))
}

/// The poles of every model order from a block Hankel matrix of `r` output rows per block.
pub fn poles_from_hankel(
    h: MatRef<'_, f64>,
    r: usize,
    rate_hz: f64,
    opts: &SsiOptions,
) -> Result<PoleSet, OmaError> {
    poles_from_svd(&hankel_svd(h)?, r, rate_hz, opts)
}

/// [`poles_from_hankel`] from the Hankel matrix's SVD ([`hankel_svd`]).
pub fn poles_from_svd(
    svd: &Svd<f64>,
    r: usize,
    rate_hz: f64,
    opts: &SsiOptions,
) -> Result<PoleSet, OmaError> {
    let s = svd.U().nrows() / r;
    let sv: Vec<f64> = svd.S().column_vector().iter().copied().collect();
    let max_order = sv.len().min((s - 1) * r);
    let step = opts.order_step.max(1);
    let orders: Vec<usize> = (1..)
        .map(|k| k * step)
        .take_while(|&n| n <= opts.order_max.min(max_order))
        .collect();
    // O = U_1 Σ_1^{1/2} at the largest order. One QR of O↑ there gives A of every order
    // (Döhler & Mevel 2012, fast multi-order SSI): O↑_n = Q_n R_n with the leading columns
    // and block, so A_n = R_n⁻¹ (Qᵀ O↓)_n, its leading n × n block.
    let n_top = orders.last().copied().unwrap_or(0);
    let u = svd.U();
    let o = Mat::from_fn(s * r, n_top, |i, j| u[(i, j)] * sv[j].sqrt());
    let rows = (s - 1) * r;
    let qr = o.subrows(0, rows).qr();
    let qt_down = qr.compute_thin_Q().transpose() * o.subrows(r, rows);
    let r_top = qr.thin_R();
    let per_order: Vec<Vec<Pole>> = orders
        .par_iter()
        .map(|&n| {
            let mut a = qt_down.submatrix(0, 0, n, n).to_owned();
            faer::linalg::triangular_solve::solve_upper_triangular_in_place(
                r_top.submatrix(0, 0, n, n),
                a.as_mut(),
                Par::Seq,
            );
            poles_of_order(a.as_ref(), o.as_ref(), r, rate_hz)
                .map_err(|e| OmaError::Numerical(format!("eigenvalues of A at order {n}: {e}")))
        })
        .collect::<Result<_, _>>()?;
    let poles = per_order.into_iter().flatten().collect();
    Ok(PoleSet {
        orders,
        poles,
        singular_values: sv,
    })
}

/// The poles of one state matrix `a` (order `n`), shapes from the leading `r` rows of the
/// observability matrix `o`: one of each conjugate pair; real poles are not modes.
fn poles_of_order(
    a: MatRef<'_, f64>,
    o: MatRef<'_, f64>,
    r: usize,
    rate_hz: f64,
) -> Result<Vec<Pole>, String> {
    let n = a.nrows();
    let eig = a.eigen().map_err(|e| format!("{e:?}"))?;
    let (vals, vecs) = (eig.S(), eig.U());
    let mut poles = Vec::new();
    for k in 0..n {
        let lam = vals[k];
        if lam.im <= 0.0 {
            continue;
        }
        let mu = c64::new(lam.norm().ln(), lam.im.atan2(lam.re)) * rate_hz;
        let w = mu.norm();
        if !w.is_finite() || w == 0.0 {
            continue;
        }
        let shape: Vec<c64> = (0..r)
            .map(|i| {
                (0..n)
                    .map(|j| vecs[(j, k)] * o[(i, j)])
                    .fold(c64::new(0.0, 0.0), |acc, x| acc + x)
            })
            .collect();
        poles.push(Pole {
            order: n,
            frequency_hz: w / (2.0 * std::f64::consts::PI),
            damping: -mu.re / w,
            shape,
        });
    }
    Ok(poles)
}

/// Brings every pole's shape entries to acceleration: entry `i` times `μ^{powers[i]}`, μ
/// the continuous pole (channels of mixed quantities, [`super::Quantity`]).
pub fn shapes_to_acceleration(poles: &mut PoleSet, powers: &[i32]) {
    if powers.iter().all(|&p| p == 0) {
        return;
    }
    for p in &mut poles.poles {
        let w = 2.0 * std::f64::consts::PI * p.frequency_hz;
        let mu = c64::new(
            -p.damping * w,
            w * (1.0 - p.damping * p.damping).max(0.0).sqrt(),
        );
        for (z, &k) in p.shape.iter_mut().zip(powers) {
            *z *= mu.powi(k);
        }
    }
}

/// The power of the continuous pole each channel's shape entry is multiplied by to read as
/// an acceleration ([`super::Quantity::to_acceleration`]).
pub fn powers(record: &Record) -> Vec<i32> {
    record
        .quantities
        .iter()
        .map(|q| q.to_acceleration())
        .collect()
}

/// A complex mode shape as a real one: rotated by the angle that makes it as real as
/// possible (the principal direction of its entries in the complex plane), then scaled to
/// unit Euclidean norm with its largest entry positive. Also returns the modal phase
/// collinearity (MPC, 1 for a real mode; Pappa, Elliott & Schenk 1993).
pub fn real_shape(shape: &[c64]) -> (Vec<f64>, f64) {
    let (sxx, syy, sxy) = shape.iter().fold((0.0, 0.0, 0.0), |(a, b, c), z| {
        (a + z.re * z.re, b + z.im * z.im, c + z.re * z.im)
    });
    let angle = 0.5 * (2.0 * sxy).atan2(sxx - syy);
    let rot = c64::new(angle.cos(), -angle.sin());
    let mut v: Vec<f64> = shape.iter().map(|z| (z * rot).re).collect();
    // MPC from the eigenvalues of the 2×2 scatter matrix of (Re, Im).
    let tr = sxx + syy;
    let det = sxx * syy - sxy * sxy;
    let disc = ((tr * tr / 4.0) - det).max(0.0).sqrt();
    let (l1, l2) = (tr / 2.0 + disc, tr / 2.0 - disc);
    let mpc = if l1 + l2 > 0.0 {
        ((l1 - l2) / (l1 + l2)).powi(2)
    } else {
        0.0
    };
    let norm = v.iter().map(|x| x * x).sum::<f64>().sqrt();
    let big = v
        .iter()
        .copied()
        .fold(0.0_f64, |a, x| if x.abs() > a.abs() { x } else { a });
    let scale = if norm > 0.0 { big.signum() / norm } else { 1.0 };
    v.iter_mut().for_each(|x| *x *= scale);
    (v, mpc)
}

/// MAC (26) of two real shapes.
pub fn mac_real(a: &[f64], b: &[f64]) -> f64 {
    let ab: f64 = a.iter().zip(b).map(|(x, y)| x * y).sum();
    let aa: f64 = a.iter().map(|x| x * x).sum();
    let bb: f64 = b.iter().map(|x| x * x).sum();
    ab * ab / (aa * bb)
}

/// MAC of two complex shapes, `|aᴴb|² / (aᴴa · bᴴb)`.
pub fn mac_complex(a: &[c64], b: &[c64]) -> f64 {
    let ab = a
        .iter()
        .zip(b)
        .fold(c64::new(0.0, 0.0), |acc, (x, y)| acc + x.conj() * y);
    let aa: f64 = a.iter().map(|x| x.norm_sqr()).sum();
    let bb: f64 = b.iter().map(|x| x.norm_sqr()).sum();
    ab.norm_sqr() / (aa * bb)
}

/// A test record of three channels: each mode a discrete second-order process with the
/// exact poles `exp((−ζω ± iω√(1−ζ²))/f_s)` driven by unit white noise
/// (`x_{k+1} = 2 Re λ x_k − |λ|² x_{k−1} + e_k`), seen with its shape, plus white sensor
/// noise of std `noise`.
#[cfg(test)]
pub(crate) fn ar2_record(
    fs: f64,
    modes: &[(f64, f64, [f64; 3])],
    n: usize,
    seed: u64,
    noise: f64,
) -> Record {
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let unit = Normal::new(0.0, 1.0).unwrap();
    let mut y = Mat::zeros(n, 3);
    for &(f, z, shape) in modes {
        let w = 2.0 * std::f64::consts::PI * f;
        let lam = (c64::new(-z * w, w * (1.0 - z * z).sqrt()) / fs).exp();
        let (a1, a2) = (2.0 * lam.re, -lam.norm_sqr());
        let (mut x1, mut x0) = (0.0, 0.0);
        for k in 0..n {
            let x = a1 * x1 + a2 * x0 + unit.sample(&mut rng);
            x0 = x1;
            x1 = x;
            for c in 0..3 {
                y[(k, c)] += shape[c] * x;
            }
        }
    }
    if noise > 0.0 {
        for k in 0..n {
            for c in 0..3 {
                y[(k, c)] += noise * unit.sample(&mut rng);
            }
        }
    }
    Record::accelerations(vec!["a".into(), "b".into(), "c".into()], fs, y)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A two-mode system written in state space (discrete, known poles), driven by white
    /// noise: the poles SSI-COV finds at order 4 are the true ones within the estimation
    /// error of a 200,000-sample record (frequency 0.2 %, damping 20 %, shapes MAC > 0.999).
    #[test]
    fn ssi_cov_finds_the_poles_of_a_known_state_space_system() {
        let fs = 100.0;
        let modes = [
            (5.0, 0.02, [1.0, 0.6, -0.3]),
            (12.0, 0.03, [0.4, -1.0, 0.8]),
        ];
        let record = ar2_record(fs, &modes, 200_000, 1, 0.0);
        let opts = SsiOptions {
            block_rows: 10,
            order_max: 4,
            order_step: 4,
            references: vec![],
        };
        let set = identify_poles(&record, &opts).unwrap();
        let mut found: Vec<&Pole> = set.poles.iter().filter(|p| p.order == 4).collect();
        found.sort_by(|a, b| a.frequency_hz.total_cmp(&b.frequency_hz));
        assert_eq!(found.len(), 2, "{found:?}");
        for (p, (f, z, shape)) in found.iter().zip(modes) {
            let (real, mpc) = real_shape(&p.shape);
            let mac = mac_real(&real, &shape);
            println!(
                "f {:.4} (true {f}), ζ {:.4} (true {z}), MAC {mac:.6}, MPC {mpc:.4}",
                p.frequency_hz, p.damping
            );
            assert!((p.frequency_hz / f - 1.0).abs() < 2e-3);
            assert!((p.damping / z - 1.0).abs() < 0.2);
            assert!(mac > 0.999 && mpc > 0.99);
        }
    }

    /// The state matrices of every order from one QR at the largest order against a
    /// least-squares solve at each order: the same poles to 1e-9 relative in frequency and
    /// 1e-6 in damping (rounding of two different factorisations of the same system).
    #[test]
    fn one_qr_gives_the_poles_of_every_order() {
        use faer::linalg::solvers::SolveLstsq;
        let modes = [
            (5.0, 0.02, [1.0, 0.6, -0.3]),
            (12.0, 0.03, [0.4, -1.0, 0.8]),
        ];
        let record = ar2_record(100.0, &modes, 20_000, 2, 0.3);
        let cov = output_covariances(record.samples.as_ref(), &[0, 1, 2], 19);
        let svd = hankel_svd(block_hankel(&cov, 10).as_ref()).unwrap();
        let opts = SsiOptions {
            block_rows: 10,
            order_max: 12,
            order_step: 2,
            references: vec![],
        };
        let set = poles_from_svd(&svd, 3, 100.0, &opts).unwrap();
        let (u, sv) = (svd.U(), svd.S().column_vector());
        for &n in &set.orders {
            let o = Mat::from_fn(30, n, |i, j| u[(i, j)] * sv[j].sqrt());
            let a = o.subrows(0, 27).qr().solve_lstsq(o.subrows(3, 27));
            let mut direct: Vec<c64> = a
                .eigenvalues()
                .unwrap()
                .into_iter()
                .filter(|l| l.im > 0.0)
                .map(|l| c64::new(l.norm().ln(), l.im.atan2(l.re)) * 100.0)
                .collect();
            direct.sort_by(|a, b| a.norm().total_cmp(&b.norm()));
            let mut fast: Vec<&Pole> = set.poles.iter().filter(|p| p.order == n).collect();
            fast.sort_by(|a, b| a.frequency_hz.total_cmp(&b.frequency_hz));
            assert_eq!(fast.len(), direct.len(), "order {n}");
            for (p, mu) in fast.iter().zip(&direct) {
                let f = mu.norm() / (2.0 * std::f64::consts::PI);
                assert!((p.frequency_hz / f - 1.0).abs() < 1e-9, "order {n}: {f}");
                assert!((p.damping - (-mu.re / mu.norm())).abs() < 1e-6, "order {n}");
            }
        }
    }

    #[test]
    fn a_real_shape_is_rotated_back_and_its_mpc_is_one() {
        let v = [1.0, -0.5, 0.25];
        let rot = c64::new(0.3_f64.cos(), 0.3_f64.sin()) * 2.0;
        let z: Vec<c64> = v.iter().map(|&x| rot * x).collect();
        let (real, mpc) = real_shape(&z);
        let norm = (1.0_f64 + 0.25 + 0.0625).sqrt();
        for (a, b) in real.iter().zip(v) {
            assert!((a - b / norm).abs() < 1e-14, "{real:?}");
        }
        assert!((mpc - 1.0).abs() < 1e-12);
    }
}
