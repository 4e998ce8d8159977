//! Uncertainty of the Bayesian MAP, paper §2.4 and §2.7: the Hessian (16) with TSVD and the
//! L-curve (24)–(25) as published, and two θ covariances that need no truncation threshold.
//!
//! * **Posterior** (Laplace): `Σ = H⁻¹` with the paper's `H = ½∇²J_p` (16). Its `(λ, θ)`
//!   block is the inverse of the Schur complement that eliminates φ, which is `½∇²F` of the
//!   reduced objective: `Σ_(λ,θ) = 2 (∇²F)⁻¹`. The Schur complement is well conditioned
//!   (the huge `σ_c⁻²A²` directions of φ are eliminated exactly), so no truncation is needed.
//! * **Sampling**: the spread of the MAP estimate itself under measurement noise, by the
//!   implicit-function theorem on `∇F(ŷ; d) = 0`: `cov ŷ = (∇²F)⁻¹ B Bᵀ (∇²F)⁻¹` with
//!   `B = ∂²F/∂y∂d Σ_M^{1/2}` ([`Reduced::data_sensitivity`]). This is what a Monte Carlo
//!   over noise draws measures. It is smaller than the posterior, which also carries the
//!   modelling-error allowance σ_c; the two meet as σ_c → 0, where both tend to the mode
//!   matching covariance (15).

use faer::linalg::solvers::Solve;
use faer::{Mat, Side};

use super::{BayesError, BayesProblem, BayesState, dot, spmv};

/// θ (and λ) covariances at a MAP point, no truncation threshold involved.
#[derive(Debug, Clone)]
pub struct ThresholdFree {
    /// Posterior covariance of `(λ, θ)`, λ first: `2 (∇²F)⁻¹`.
    pub posterior: Mat<f64>,
    /// Sampling covariance of the MAP `(λ, θ)` under measurement noise.
    pub sampling: Mat<f64>,
    n_modes: usize,
}

impl ThresholdFree {
    /// Posterior standard deviations of θ.
    pub fn posterior_theta_std(&self) -> Vec<f64> {
        self.diag_std(&self.posterior, self.n_modes)
    }
    /// Sampling standard deviations of θ.
    pub fn sampling_theta_std(&self) -> Vec<f64> {
        self.diag_std(&self.sampling, self.n_modes)
    }
    /// Posterior standard deviations of the most probable eigenvalues λ.
    pub fn posterior_lambda_std(&self) -> Vec<f64> {
        (0..self.n_modes)
            .map(|i| self.posterior[(i, i)].sqrt())
            .collect()
    }
    fn diag_std(&self, c: &Mat<f64>, from: usize) -> Vec<f64> {
        (from..c.nrows()).map(|i| c[(i, i)].sqrt()).collect()
    }
}

/// One point of the L-curve: keep the singular values `≥ s_tol`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LCurvePoint {
    pub s_tol: f64,
    /// Singular values kept.
    pub kept: usize,
    /// `E(s_tol)`, (25), evaluated in floating point as published.
    pub error: f64,
    /// `‖Σ̃(s_tol)‖_F`.
    pub norm: f64,
    /// Some variance on the diagonal of `Σ̃(s_tol)` is negative (the paper's red dots).
    pub negative_variance: bool,
}

/// The TSVD covariance (24) at the L-curve corner.
#[derive(Debug, Clone)]
pub struct Tsvd {
    /// Singular values of `H`, descending.
    pub singular_values: Vec<f64>,
    pub curve: Vec<LCurvePoint>,
    /// Index into `curve` of the chosen threshold.
    pub chosen: usize,
    /// `Σ̃_θθ(s_tol)` at the chosen threshold.
    pub theta_cov: Mat<f64>,
}

impl Tsvd {
    pub fn s_tol(&self) -> f64 {
        self.curve[self.chosen].s_tol
    }
    /// `s_max / s_min`.
    pub fn condition(&self) -> f64 {
        self.singular_values[0] / self.singular_values[self.singular_values.len() - 1]
    }
    /// TSVD standard deviations of θ (NaN where the variance is negative).
    pub fn theta_std(&self) -> Vec<f64> {
        (0..self.theta_cov.nrows())
            .map(|i| {
                let v = self.theta_cov[(i, i)];
                if v >= 0.0 { v.sqrt() } else { f64::NAN }
            })
            .collect()
    }
}

/// The L-curve corner. Keeping more singular values lowers `E` (25) (the truncated inverse
/// gets closer to an inverse) while `‖Σ̃‖_F` grows; in floating point, once the kept
/// values reach the level where `H v_i` is swamped by rounding (`‖H‖·ε_mach`), `E` stops
/// falling and shoots up with the norm. The corner is that turn: the point of **least
/// `E`**, among points with no negative variance (the paper's red dots). With a
/// well-conditioned `H` it is the full inverse. Returns an index into `curve`.
///
/// (The paper picks the corner by eye on a lin–lin plot, its log–log curve having no
/// visible corner; the least-`E` point is an operational version of the same turn.)
pub fn l_curve_corner(curve: &[LCurvePoint]) -> usize {
    (0..curve.len())
        .filter(|&i| !curve[i].negative_variance && curve[i].error.is_finite())
        .min_by(|&a, &b| curve[a].error.total_cmp(&curve[b].error))
        .unwrap_or(0)
}

impl BayesProblem {
    /// Posterior and sampling covariances of `(λ, θ)` at a MAP point (module docs).
    pub fn threshold_free_covariance(
        &self,
        state: &BayesState,
    ) -> Result<ThresholdFree, BayesError> {
        let red = self.reduced(&state.lambda, &state.theta)?;
        let llt = red
            .hessian
            .llt(Side::Lower)
            .map_err(|_| BayesError::NotAMinimum)?;
        let ny = red.hessian.nrows();
        let inv = llt.solve(Mat::<f64>::identity(ny, ny));
        let posterior = &inv * faer::Scale(2.0);
        let hb = llt.solve(&red.data_sensitivity);
        let sampling = &hb * hb.transpose();
        Ok(ThresholdFree {
            posterior,
            sampling,
            n_modes: self.n_modes(),
        })
    }

    /// The paper's Hessian (16), `H = ½∇²J_p` over `(λ, φ (column-major), θ)`, dense.
    fn full_hessian(&self, s: &BayesState) -> Mat<f64> {
        let (n, nm, p) = (self.n, self.n_modes(), self.p);
        let dim = nm + n * nm + p;
        let mut h = Mat::zeros(dim, dim);
        let s2 = self.inv_s2;
        let k = self.stiffness(&s.theta);
        let th = nm + n * nm;
        for (m, mode) in self.modes.iter().enumerate() {
            let ph: Vec<f64> = s.phi.col(m).iter().copied().collect();
            let pr = self.products(s.lambda[m], &ph, &s.theta);
            let a = &k
                - self.m_dense.as_ref().expect("checked by the caller") * faer::Scale(s.lambda[m]);
            let f = nm + m * n;
            // λλ: σ⁻² φᵀM²φ + w_λ (G_λ).
            h[(m, m)] = s2 * dot(&pr.mphi, &pr.mphi) + mode.w_lambda;
            // λφ: −σ⁻² (M A φ + A M φ) (the paper's −2σ⁻²L₁, symmetrized).
            let maphi = spmv(self.model.mass(), &pr.aphi);
            let amphi = self.apply_a(s.lambda[m], &s.theta, &pr.mphi);
            for i in 0..n {
                let v = -s2 * (maphi[i] + amphi[i]);
                h[(m, f + i)] = v;
                h[(f + i, m)] = v;
            }
            // φφ: σ⁻² A² + L_oᵀ W L_o (G_φ).
            let a2 = &a * &a;
            for j in 0..n {
                for i in 0..n {
                    h[(f + i, f + j)] = s2 * a2[(i, j)];
                }
            }
            for row in &mode.rows {
                for &(i, ci) in &row.dofs {
                    for &(j, cj) in &row.dofs {
                        h[(f + i, f + j)] += row.w * ci * cj;
                    }
                }
            }
            for l in 0..p {
                // λθ: −σ⁻² φᵀ M K_l φ (L₂).
                let v = -s2 * dot(&pr.mphi, &pr.klphi[l]);
                h[(m, th + l)] = v;
                h[(th + l, m)] = v;
                // φθ: σ⁻² (A K_l + K_l A) φ (L₃).
                let aklphi = self.apply_a(s.lambda[m], &s.theta, &pr.klphi[l]);
                let klaphi = spmv(self.model.k_param(l), &pr.aphi);
                for i in 0..n {
                    let v = s2 * (aklphi[i] + klaphi[i]);
                    h[(f + i, th + l)] = v;
                    h[(th + l, f + i)] = v;
                }
                // θθ: σ⁻² G_θᵀG_θ.
                for q in 0..p {
                    h[(th + l, th + q)] += s2 * dot(&pr.klphi[l], &pr.klphi[q]);
                }
            }
        }
        for l in 0..p {
            h[(th + l, th + l)] += self.prior_w[l];
        }
        h
    }

    /// TSVD of (16) and the L-curve (24)–(25), one point per singular value kept; the
    /// threshold at the corner ([`l_curve_corner`]). `H` is symmetric, so its SVD comes
    /// from its eigendecomposition `H = V diag(e) Vᵀ`: `s_i = |e_i|`, `u_i = sign(e_i) v_i`,
    /// and `Σ̃ = Σ_kept v_i v_iᵀ / e_i`. `E` (25) is evaluated in floating point, as the
    /// paper does, from `HΣ̃ = Σ_kept (H v_i / e_i) v_iᵀ`; in exact arithmetic it would be
    /// `√(N − kept)`, and its departure from that shows the ill-conditioning.
    pub fn tsvd_covariance(&self, s: &BayesState) -> Result<Tsvd, BayesError> {
        if self.m_dense.is_none() {
            return Err(BayesError::TooLarge {
                what: "the Hessian (16) for the TSVD covariance",
                n_dof: self.n,
                limit: crate::core::modal::SPARSE_FROM_DOF,
            });
        }
        let h = self.full_hessian(s);
        let dim = h.nrows();
        let evd = h
            .self_adjoint_eigen(Side::Lower)
            .map_err(|_| BayesError::NotAMinimum)?;
        let e_raw = evd.S().column_vector();
        let mut order: Vec<usize> = (0..dim).collect();
        order.sort_by(|&a, &b| e_raw[b].abs().total_cmp(&e_raw[a].abs()));
        let e: Vec<f64> = order.iter().map(|&i| e_raw[i]).collect();
        let v = Mat::from_fn(dim, dim, |r, c| evd.U()[(r, order[c])]);
        // A = H V diag(1/e): column i is H v_i / e_i. Gram terms for ‖½(P + Pᵀ) − I‖_F with
        // P = Σ_kept a_i v_iᵀ: ‖P‖² = Σ_kept ‖a_i‖² (V orthonormal), tr P² = Σ_kept
        // (v_iᵀa_j)(v_jᵀa_i), tr P = Σ_kept v_iᵀa_i.
        let mut a = &h * &v;
        for (c, &ec) in e.iter().enumerate() {
            a.col_mut(c).iter_mut().for_each(|x| *x /= ec);
        }
        let gva = v.transpose() * &a;
        let mut diag = vec![0.0; dim];
        let (mut pp, mut tr2, mut tr, mut inv_s2) = (0.0, 0.0, 0.0, 0.0);
        let mut curve = Vec::with_capacity(dim);
        for k in 0..dim {
            pp += a.col(k).squared_norm_l2();
            for i in 0..k {
                tr2 += 2.0 * gva[(i, k)] * gva[(k, i)];
            }
            tr2 += gva[(k, k)] * gva[(k, k)];
            tr += gva[(k, k)];
            inv_s2 += 1.0 / (e[k] * e[k]);
            let mut negative = false;
            for (r, d) in diag.iter_mut().enumerate() {
                *d += v[(r, k)] * v[(r, k)] / e[k];
                negative |= *d < 0.0;
            }
            let x2 = 0.5 * (pp + tr2);
            curve.push(LCurvePoint {
                s_tol: e[k].abs(),
                kept: k + 1,
                error: (x2 - 2.0 * tr + dim as f64).max(0.0).sqrt(),
                norm: inv_s2.sqrt(),
                negative_variance: negative,
            });
        }
        let chosen = l_curve_corner(&curve);
        let keep = curve[chosen].kept;
        let th = dim - self.p;
        let theta_cov = Mat::from_fn(self.p, self.p, |i, j| {
            (0..keep)
                .map(|c| v[(th + i, c)] * v[(th + j, c)] / e[c])
                .sum()
        });
        Ok(Tsvd {
            singular_values: e.iter().map(|x| x.abs()).collect(),
            curve,
            chosen,
            theta_cov,
        })
    }
}
