//! Step 4 of the module docs of [`super`]: the state matrix at one order, its poles and
//! shapes, and their first-order standard deviations from the per-block projections.

use faer::linalg::solvers::{DenseSolveCore, Solve};
use faer::{Mat, c64};

use super::projections::Sensitivities;
use crate::core::oma::OmaError;

/// A mode with its first-order standard deviations.
#[derive(Debug, Clone)]
pub struct ModeStd {
    pub frequency_hz: f64,
    pub frequency_std: f64,
    pub damping: f64,
    pub damping_std: f64,
    /// Real shape: unit norm, largest entry positive (`Re φ̂`).
    pub shape: Vec<f64>,
    /// Standard deviation of each entry of `shape`.
    pub shape_std: Vec<f64>,
}

/// The eigen-decomposition of the state matrix at one order, with what every pole's
/// standard deviations need (module docs, step 4).
pub struct OrderSolve {
    pub n: usize,
    pub lam: Vec<c64>,
    psi: Mat<c64>,
    /// `Ψ⁻¹ M⁻¹`.
    p: Mat<c64>,
    /// `C Ψ`.
    c_psi: Mat<c64>,
}

impl Sensitivities {
    /// The modes of order `n` (one of each conjugate pair, `Im λ > 0`) with their standard
    /// deviations (module docs, step 4), ascending in frequency.
    pub fn modes_at(&self, n: usize) -> Result<Vec<ModeStd>, OmaError> {
        let o = self.order(n)?;
        let mut out: Vec<ModeStd> = (0..n)
            .filter(|&j| o.lam[j].im > 0.0)
            .map(|j| self.mode_std(&o, j))
            .collect();
        out.sort_by(|a, b| a.frequency_hz.total_cmp(&b.frequency_hz));
        Ok(out)
    }

    /// The pole of order `n` nearest to `frequency_hz` (`Im λ > 0`), with its standard
    /// deviations.
    pub fn mode_near(&self, o: &OrderSolve, frequency_hz: f64) -> Option<ModeStd> {
        self.nearest(o, frequency_hz).map(|j| self.mode_std(o, j))
    }

    /// The state matrix of order `n` (`A = M⁻¹N`) and its eigen-decomposition.
    pub fn order(&self, n: usize) -> Result<OrderSolve, OmaError> {
        if n == 0 || n > self.n_max {
            return Err(OmaError::Input(format!(
                "order {n} is outside 1 … {}",
                self.n_max
            )));
        }
        let r = self.r;
        let rows = self.o.nrows() - r;
        let on = self.o.subcols(0, n);
        let up = on.subrows(0, rows);
        let down = on.subrows(r, rows);
        let mm = up.transpose() * up;
        let nn = up.transpose() * down;
        let m_llt = mm
            .llt(faer::Side::Lower)
            .map_err(|_| OmaError::Numerical(format!("O↑ is rank-deficient at order {n}")))?;
        let a = m_llt.solve(&nn);
        let eig = a
            .eigen()
            .map_err(|e| OmaError::Numerical(format!("eigenvalues of A at order {n}: {e:?}")))?;
        let psi: Mat<c64> = eig.U().to_owned();
        let lam: Vec<c64> = (0..n).map(|i| eig.S()[i]).collect();
        let psi_inv = psi.partial_piv_lu().inverse();
        let m_inv_real = m_llt.inverse();
        let m_inv = Mat::from_fn(n, n, |i, j| c64::new(m_inv_real[(i, j)], 0.0));
        let p = &psi_inv * &m_inv;
        let c_n = Mat::from_fn(r, n, |i, j| c64::new(on[(i, j)], 0.0));
        let c_psi = &c_n * &psi;
        Ok(OrderSolve {
            n,
            lam,
            psi,
            p,
            c_psi,
        })
    }

    /// The first-order σ of the frequency of the pole of `o` nearest `frequency_hz`, and
    /// that pole's frequency: what choosing among a cluster's poles needs, without the
    /// shape's terms.
    pub fn frequency_std_near(&self, o: &OrderSolve, frequency_hz: f64) -> Option<(f64, f64)> {
        let j = self.nearest(o, frequency_hz)?;
        let pole = PoleTerms::new(self, o, j);
        let var = self
            .q
            .iter()
            .map(|qk| {
                let w = pole.w(qk, o.n);
                let df = pole.frequency_change(pole.eigenvalue_change(&w));
                df * df
            })
            .sum::<f64>();
        Some((pole.wabs / (2.0 * std::f64::consts::PI), var.sqrt()))
    }

    /// Pole `j` of an order's decomposition with its standard deviations.
    fn mode_std(&self, o: &OrderSolve, j: usize) -> ModeStd {
        let (n, r) = (o.n, self.r);
        let pole = PoleTerms::new(self, o, j);
        // K = C Ψ Γ_j P, Γ_j = diag(1/(λ_j − λ_i)), 0 at i = j.
        let gamma = Mat::from_fn(n, n, |a, b| {
            if a == b && a != j {
                (pole.l - o.lam[a]).inv()
            } else {
                c64::new(0.0, 0.0)
            }
        });
        let kmat = &o.c_psi * &gamma * &o.p;
        let phi: Vec<c64> = pole
            .raw
            .iter()
            .zip(&pole.scale)
            .map(|(z, s_)| z * s_)
            .collect();
        let kappa = (0..r)
            .max_by(|&a_, &b_| phi[a_].norm().total_cmp(&phi[b_].norm()))
            .expect("r > 0");
        let norm = phi.iter().map(|z| z.norm_sqr()).sum::<f64>().sqrt();
        let alpha = phi[kappa].im.atan2(phi[kappa].re);
        let rot = c64::new(alpha.cos(), -alpha.sin());
        let hat: Vec<c64> = phi.iter().map(|z| z * rot / norm).collect();
        let (mut vf, mut vz) = (0.0, 0.0);
        let mut vshape = vec![0.0; r];
        for qk in &self.q {
            let w = pole.w(qk, n);
            let dmu = pole.eigenvalue_change(&w);
            let df = pole.frequency_change(dmu);
            let mu = pole.mu;
            let dz = (-(mu.im * mu.im) * dmu.re + mu.re * mu.im * dmu.im) / pole.wabs.powi(3);
            vf += df * df;
            vz += dz * dz;
            // dφ = (Q4 ψ_j + K w) scaled per channel, plus the scale's change along μ.
            let q4psi = qk[3].subcols(0, n) * &pole.psi_ri;
            let kw = &kmat * &w;
            let dphi: Vec<c64> = (0..r)
                .map(|a_| {
                    (c64::new(q4psi[(a_, 0)], q4psi[(a_, 1)]) + kw[(a_, 0)]) * pole.scale[a_]
                        + pole.raw[a_] * pole.dscale[a_] * dmu
                })
                .collect();
            let dalpha = (dphi[kappa] / phi[kappa]).im;
            let dw: Vec<c64> = dphi
                .iter()
                .zip(&phi)
                .map(|(d_, p_)| (d_ - c64::new(0.0, dalpha) * p_) * rot)
                .collect();
            let proj = hat
                .iter()
                .zip(&dw)
                .fold(c64::new(0.0, 0.0), |acc, (h_, d_)| acc + h_.conj() * d_)
                .re;
            for i in 0..r {
                let dh = (dw[i] - hat[i] * proj) / norm;
                vshape[i] += dh.re * dh.re;
            }
        }
        ModeStd {
            frequency_hz: pole.wabs / (2.0 * std::f64::consts::PI),
            frequency_std: vf.sqrt(),
            damping: -pole.mu.re / pole.wabs,
            damping_std: vz.sqrt(),
            shape: hat.iter().map(|z| z.re).collect(),
            shape_std: vshape.iter().map(|v| v.sqrt()).collect(),
        }
    }

    /// The pole (`Im λ > 0`) of `o` nearest `frequency_hz`.
    fn nearest(&self, o: &OrderSolve, frequency_hz: f64) -> Option<usize> {
        (0..o.n).filter(|&j| o.lam[j].im > 0.0).min_by(|&a, &b| {
            (self.continuous(o.lam[a]).norm() - 2.0 * std::f64::consts::PI * frequency_hz)
                .abs()
                .total_cmp(
                    &(self.continuous(o.lam[b]).norm() - 2.0 * std::f64::consts::PI * frequency_hz)
                        .abs(),
                )
        })
    }

    /// The continuous pole `μ = ln(λ)·f_s` of a discrete one.
    fn continuous(&self, l: c64) -> c64 {
        c64::new(l.norm().ln(), l.im.atan2(l.re)) * self.rate_hz
    }
}

/// What every block's first-order terms of one pole share (module docs, step 4).
struct PoleTerms {
    /// Discrete and continuous pole, `|μ|`.
    l: c64,
    mu: c64,
    wabs: f64,
    dt: f64,
    /// `ψ_j` as an `n × 2` real matrix (real and imaginary parts).
    psi_ri: Mat<f64>,
    /// `g = ℓ_j M⁻¹` (row `j` of `P`).
    g: Vec<c64>,
    /// `C ψ_j` and, per channel, `μ^{p_i}` and its derivative along `μ`.
    raw: Vec<c64>,
    scale: Vec<c64>,
    dscale: Vec<c64>,
}

impl PoleTerms {
    fn new(sens: &Sensitivities, o: &OrderSolve, j: usize) -> Self {
        let n = o.n;
        let l = o.lam[j];
        let mu = sens.continuous(l);
        let scale = sens.powers.iter().map(|&p| mu.powi(p)).collect();
        let dscale = sens
            .powers
            .iter()
            .map(|&p| {
                if p == 0 {
                    c64::new(0.0, 0.0)
                } else {
                    mu.powi(p - 1) * p as f64
                }
            })
            .collect();
        PoleTerms {
            l,
            mu,
            wabs: mu.norm(),
            dt: 1.0 / sens.rate_hz,
            psi_ri: Mat::from_fn(n, 2, |i, c| {
                let z = o.psi[(i, j)];
                if c == 0 { z.re } else { z.im }
            }),
            g: (0..n).map(|i| o.p[(j, i)]).collect(),
            raw: (0..sens.r).map(|i| o.c_psi[(i, j)]).collect(),
            scale,
            dscale,
        }
    }

    /// `w = (Q3 − λQ1)ψ + (Q2 − λQ1)ᵀψ` of one block, as an `n × 1` column.
    fn w(&self, qk: &[Mat<f64>; 4], n: usize) -> Mat<c64> {
        let [q1, q2, q3, _] = qk;
        let (q1, q2, q3) = (
            q1.submatrix(0, 0, n, n),
            q2.submatrix(0, 0, n, n),
            q3.submatrix(0, 0, n, n),
        );
        let m = q3 * &self.psi_ri + q2.transpose() * &self.psi_ri;
        let s = q1 * &self.psi_ri + q1.transpose() * &self.psi_ri;
        Mat::from_fn(n, 1, |a, _| {
            c64::new(m[(a, 0)], m[(a, 1)]) - self.l * c64::new(s[(a, 0)], s[(a, 1)])
        })
    }

    /// The change of the continuous pole `μ` for a block's `w`: `Δλ = g w`, `Δμ = Δλ/(λ Δt)`.
    fn eigenvalue_change(&self, w: &Mat<c64>) -> c64 {
        let dl = self
            .g
            .iter()
            .enumerate()
            .fold(c64::new(0.0, 0.0), |acc, (a, g)| acc + g * w[(a, 0)]);
        dl / (self.l * self.dt)
    }

    /// The change of the frequency (Hz) for a change `dmu` of `μ`.
    fn frequency_change(&self, dmu: c64) -> f64 {
        (self.mu.conj() * dmu).re / (2.0 * std::f64::consts::PI * self.wabs)
    }
}
