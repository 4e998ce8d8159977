//! The φ elimination (substep (21)) and the reduced objective `F(λ, θ)`: for fixed
//! `(λ, θ)` each `φ_m` solves a linear least-squares problem (a sparse Householder QR for
//! small models, the shifted stiffness's sparse factorization for large ones), and `F`'s
//! gradient and Hessian are the Schur complement of (16) (module docs of [`super`]).

use super::*;

/// `K(θ)` for the φ substeps of one θ.
pub(super) enum ThetaMatrices {
    /// Values on the model's union pattern, for the QR of a small model ([`sparse_qr`]).
    SparseQr(Vec<f64>),
    /// Values on the model's union pattern, and θ (each mode's shifted matrix is formed
    /// on the reordered pattern for its factorization).
    Sparse { values: Vec<f64>, theta: Vec<f64> },
}

/// The factorization of one mode's φ substep.
pub(super) enum ModeFactor {
    /// The sparse Householder QR of `C_m` ([`sparse_qr`]), for a small model.
    SparseQr(Box<SparsePhiFactor>),
    /// The shifted stiffness and the Woodbury solution ([`shifted`]).
    Shifted(Box<ShiftedFactor>),
    /// The augmented system's LU ([`augmented`]): the fallback of [`ModeFactor::Shifted`].
    Augmented(Box<AugmentedFactor>),
}

impl BayesProblem {
    /// The per-mode block of the reduced Hessian (before the factor 2) and
    /// `Z = N⁻¹(CᵀJ_y + E)`, from `J_y` (`(n + n_o) × (1 + p)`) and `E` (`n × (1 + p)`); see
    /// [`BayesProblem::reduced`]. A shifted factorization whose refinement does not converge
    /// is replaced by the augmented LU (`kt`, `m`, `lambda` rebuild it).
    pub(super) fn schur_block(
        &self,
        kt: &ThetaMatrices,
        m: usize,
        lambda: f64,
        fact: &ModeFactor,
        jy: Mat<f64>,
        e: Mat<f64>,
    ) -> Result<(Mat<f64>, Mat<f64>), BayesError> {
        // Sparse: s = P⊥J_y − C N⁻¹E, u = N⁻¹(CᵀJ_y + E), and J_yᵀs − Eᵀu is the block.
        let minus_e = &e * faer::Scale(-1.0);
        let (s, u) = match fact {
            ModeFactor::SparseQr(fact) => {
                let (x1, x2) = fact.apply_qt(jy.as_ref());
                let y = fact.solve_rt(e.as_ref());
                let block = x2.transpose() * &x2
                    - x1.transpose() * &y
                    - y.transpose() * &x1
                    - y.transpose() * &y;
                let z = fact.solve_r(x1 + &y); // P R⁻¹(X₁ + Y)
                return Ok((block, z));
            }
            ModeFactor::Shifted(fact) => {
                match fact.solve(&self.model, jy.as_ref(), Some(minus_e.as_ref())) {
                    Some(su) => su,
                    None => self
                        .augmented_factor(kt, m, lambda)?
                        .solve(jy.as_ref(), Some(minus_e.as_ref())),
                }
            }
            ModeFactor::Augmented(fact) => fact.solve(jy.as_ref(), Some(minus_e.as_ref())),
        };
        let b = jy.transpose() * &s - e.transpose() * &u;
        Ok(((&b + b.transpose()) * faer::Scale(0.5), u))
    }

    /// The augmented system's LU for mode `m` at `(λ_m, θ)`: the fallback of the shifted
    /// factorization, counted in [`BayesProblem::augmented_fallbacks`].
    fn augmented_factor(
        &self,
        kt: &ThetaMatrices,
        m: usize,
        lambda: f64,
    ) -> Result<AugmentedFactor, BayesError> {
        let ThetaMatrices::Sparse { values, .. } = kt else {
            unreachable!("the augmented system serves the sparse path only")
        };
        let n_dof = self.model.n_dof();
        if n_dof > AUGMENTED_FALLBACK_MAX_DOF {
            return Err(BayesError::ShiftedSingular {
                mode: m + 1,
                n_dof,
                limit: AUGMENTED_FALLBACK_MAX_DOF,
            });
        }
        self.fallbacks
            .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let mut a = values.clone();
        self.model.subtract_mass_values(lambda, &mut a);
        AugmentedFactor::new(
            &self.model,
            &self.augmented,
            m,
            &a,
            self.inv_s2.sqrt(),
            &self.modes[m].rows,
        )
    }

    /// Dense `K(θ)`.
    pub(super) fn stiffness(&self, theta: &[f64]) -> Mat<f64> {
        let mut k = Mat::zeros(self.n, self.n);
        self.model.stiffness_dense_into(theta, k.as_mut());
        k
    }

    /// `K(θ)` for the φ substeps at one θ: its values on the union pattern.
    pub(super) fn theta_matrices(&self, theta: &[f64]) -> ThetaMatrices {
        let mut v = vec![0.0; self.model.union_pattern().pattern.val().len()];
        self.model.shifted_stiffness_values(theta, 0.0, &mut v);
        if self.m_dense.is_some() {
            ThetaMatrices::SparseQr(v)
        } else {
            ThetaMatrices::Sparse {
                values: v,
                theta: theta.to_vec(),
            }
        }
    }

    /// The optimal `φ_m` for fixed `(λ_m, θ)`, substep (21), and its factorization. `φ_m`
    /// minimizes `‖C_m φ − [0; W^{1/2} ψ̂]‖²`, solved by Householder QR of `C_m` (small models) or
    /// through the augmented system (sparse), rather than through `N_m = C_mᵀC_m`, whose
    /// condition number (~1e14 for σ_c = 10 on the cantilever) is the square of `C_m`'s.
    pub(super) fn mode_factor(
        &self,
        k: &ThetaMatrices,
        m: usize,
        lambda: f64,
    ) -> Result<(Vec<f64>, ModeFactor), BayesError> {
        let n = self.n;
        let mode = &self.modes[m];
        let no = mode.rows.len();
        let sigma_inv = self.inv_s2.sqrt();
        let mut d = Mat::<f64>::zeros(n + no, 1);
        for (i, row) in mode.rows.iter().enumerate() {
            d[(n + i, 0)] = row.w.sqrt() * row.psi;
        }
        match k {
            ThetaMatrices::SparseQr(values) => {
                let mut a = values.clone();
                self.model.subtract_mass_values(lambda, &mut a);
                let symbolic = self.phi_qr[m]
                    .get_or_init(|| PhiQrSymbolic::new(&self.model, &mode.rows))
                    .as_ref()
                    .ok_or(BayesError::PhiSystemSingular { mode: m + 1 })?;
                let fact = SparsePhiFactor::new(symbolic, &self.model, &a, sigma_inv)
                    .ok_or(BayesError::PhiSystemSingular { mode: m + 1 })?;
                let (q1d, _) = fact.apply_qt(d.as_ref());
                let x = fact.solve_r(q1d);
                Ok((
                    x.col(0).iter().copied().collect(),
                    ModeFactor::SparseQr(Box::new(fact)),
                ))
            }
            ThetaMatrices::Sparse { values, theta } => {
                let mut a = values.clone();
                self.model.subtract_mass_values(lambda, &mut a);
                if let Some(fact) =
                    ShiftedFactor::new(&self.model, theta, lambda, a, 1.0 / sigma_inv, &mode.rows)
                    && let Some((_, u)) = fact.solve(&self.model, d.as_ref(), None)
                {
                    let phi: Vec<f64> = u.col(0).iter().copied().collect();
                    if phi.iter().all(|v| v.is_finite()) {
                        return Ok((phi, ModeFactor::Shifted(Box::new(fact))));
                    }
                }
                let fact = self.augmented_factor(k, m, lambda)?;
                let (_, u) = fact.solve(d.as_ref(), None);
                let phi: Vec<f64> = u.col(0).iter().copied().collect();
                if !phi.iter().all(|v| v.is_finite()) {
                    return Err(BayesError::PhiSystemSingular { mode: m + 1 });
                }
                Ok((phi, ModeFactor::Augmented(Box::new(fact))))
            }
        }
    }

    /// The optimal φ for fixed `(λ, θ)`, substep (21), every mode.
    pub(super) fn phi_star(&self, lambda: &[f64], theta: &[f64]) -> Result<Mat<f64>, BayesError> {
        let k = self.theta_matrices(theta);
        let mut phi = Mat::zeros(self.n, self.modes.len());
        let cols = self.per_mode(|m| Ok(self.mode_factor(&k, m, lambda[m])?.0))?;
        for (m, ph) in cols.into_iter().enumerate() {
            phi.col_mut(m)
                .iter_mut()
                .zip(&ph)
                .for_each(|(a, b)| *a = *b);
        }
        Ok(phi)
    }

    /// The optimal φ at `(λ, θ)` (substep (21)).
    pub fn optimal_phi(&self, lambda: &[f64], theta: &[f64]) -> Result<Mat<f64>, BayesError> {
        self.phi_star(lambda, theta)
    }

    /// Reduced objective `F(λ, θ)` with its exact gradient and Hessian, the Schur complement
    /// of (16) with φ eliminated (twice the paper's `H`, which is the Hessian of `J_p/2`).
    ///
    /// Per mode, with `r_C = σ_c⁻¹ A φ` linear in `y` for fixed φ, `J_y = ∂[r_C; r_ψ]/∂y =
    /// [σ_c⁻¹(−Mφ | K_lφ); 0]`, `C = QR` and `E = [−σ_c⁻² M A φ | σ_c⁻² K_l A φ]` (the
    /// second-order coupling `Σ r_i ∂²r_i/∂φ∂y`): `J_φφ = 2CᵀC`, `J_φy = 2(CᵀJ_y + E)`,
    /// `J_yy = 2J_yᵀJ_y` (+ `2w_λ` and the prior), and with `X₁ = Q₁ᵀJ_y`, `X₂ = Q₂ᵀJ_y`,
    /// `Y = R⁻ᵀE` the Schur complement is `2[X₂ᵀX₂ − X₁ᵀY − YᵀX₁ − YᵀY]`. That is
    /// `2[J_yᵀP⊥J_y − J_yᵀCN⁻¹E − EᵀN⁻¹CᵀJ_y − EᵀN⁻¹E]`, which the sparse path evaluates as
    /// `2[J_yᵀs − Eᵀu]` from the augmented system's `s` and `u` ([`augmented`]).
    ///
    /// The data sensitivity: `∂F/∂y = ∂J_p/∂y` at `φ*` (envelope theorem) and
    /// `∂φ*/∂ψ̂ = N⁻¹L_oᵀW`, so `∂²F/∂y∂ψ̂ = J_yφ N⁻¹ L_oᵀ W = 2 (X₁ + Y)ᵀ R⁻ᵀ L_oᵀ W`;
    /// weighted by `Σ_ψ^{1/2} = W^{-1/2}` it is `2 (X₁ + Y)ᵀ R⁻ᵀ L_oᵀ W^{1/2}`. For the
    /// eigenvalues `∂²F/∂λ_m∂λ̂_m = −2 w_λm`, weighted by `σ_λ = w_λ^{-1/2}`.
    pub fn reduced(&self, lambda: &[f64], theta: &[f64]) -> Result<Reduced, BayesError> {
        let (n, nm, p) = (self.n, self.modes.len(), self.p);
        let kt = self.theta_matrices(theta);
        let parts = self.per_mode(|m| self.reduced_mode(&kt, m, lambda[m], theta))?;
        let mut phi = Mat::zeros(n, nm);
        // J_p (14) at (λ, φ*, θ), accumulated from the per-mode parts in mode order.
        let mut value = self.prior_term(theta);
        let ny = nm + p;
        let mut g = vec![0.0; ny];
        let mut h = Mat::zeros(ny, ny);
        let mut sens = Mat::zeros(ny, self.n_data());
        let mut col0 = 0;
        let idx = |m: usize, j: usize| if j == 0 { m } else { nm + j - 1 };
        for (m, (mode, part)) in self.modes.iter().zip(parts).enumerate() {
            phi.col_mut(m)
                .iter_mut()
                .zip(&part.phi)
                .for_each(|(a, b)| *a = *b);
            value += part.value;
            g[m] = part.g_lambda;
            for l in 0..p {
                g[nm + l] += part.g_theta[l];
            }
            for i in 0..=p {
                for j in 0..=p {
                    h[(idx(m, i), idx(m, j))] += 2.0 * part.block[(i, j)];
                }
            }
            h[(m, m)] += 2.0 * mode.w_lambda;
            // Data sensitivity: λ̂_m, then ψ̂_m's entries: 2 (X₁+Y)ᵀ R⁻ᵀ L_oᵀ W^{1/2}.
            sens[(m, col0)] = -2.0 * mode.w_lambda.sqrt();
            for (i, row) in mode.rows.iter().enumerate() {
                let sw = row.w.sqrt();
                for j in 0..=p {
                    let v: f64 = row.dofs.iter().map(|&(d, c)| c * part.z[(d, j)]).sum();
                    sens[(idx(m, j), col0 + 1 + i)] = 2.0 * sw * v;
                }
            }
            col0 += 1 + mode.rows.len();
        }
        for l in 0..p {
            g[nm + l] += 2.0 * self.prior_w[l] * (theta[l] - self.prior_mean[l]);
            h[(nm + l, nm + l)] += 2.0 * self.prior_w[l];
        }
        Ok(Reduced {
            value,
            gradient: g,
            hessian: h,
            data_sensitivity: sens,
            phi,
        })
    }

    /// `f(m)` for every mode, in mode order. Large models run two modes at a time: a sparse
    /// φ substep is sequential inside (its factorization and solves). Each holds the
    /// `LDLᵀ` of one shifted stiffness, `B` and a few `n × (1 + p)` blocks: on the four-bay
    /// frame a Bayesian update peaks at 0.86–0.89 GB, the model and the mode-matching
    /// comparison included (4.45 GB with the augmented LU, ~1.9 GB per mode).
    pub(super) fn per_mode<T: Send>(
        &self,
        f: impl Fn(usize) -> Result<T, BayesError> + Sync,
    ) -> Result<Vec<T>, BayesError> {
        let nm = self.modes.len();
        if self.m_dense.is_some() || nm < 2 {
            return (0..nm).map(f).collect();
        }
        use rayon::prelude::*;
        (0..nm)
            .into_par_iter()
            .with_min_len(nm.div_ceil(MODES_AT_ONCE))
            .map(&f)
            .collect()
    }

    /// One mode's share of [`Self::reduced`]: `φ*_m`, its terms of `J_p`, of the gradient
    /// and of the Hessian (the Schur block, before the factor 2), and `Z` for the data
    /// sensitivity.
    pub(super) fn reduced_mode(
        &self,
        kt: &ThetaMatrices,
        m: usize,
        lambda: f64,
        theta: &[f64],
    ) -> Result<ModePart, BayesError> {
        let (n, p) = (self.n, self.p);
        let mode = &self.modes[m];
        let s2 = self.inv_s2;
        let sig = s2.sqrt();
        let (ph, fact) = self.mode_factor(kt, m, lambda)?;
        let pr = self.products(lambda, &ph, theta);
        let dl = mode.lambda_hat - lambda;
        let value = mode.w_lambda * dl * dl + self.shape_misfit(m, &ph) + s2 * dot_self(&pr.aphi);
        let g_lambda = -2.0 * mode.w_lambda * dl - 2.0 * s2 * dot(&pr.mphi, &pr.aphi);
        let g_theta = (0..p)
            .map(|l| 2.0 * s2 * dot(&pr.klphi[l], &pr.aphi))
            .collect();
        // Hessian of F per mode (see `reduced`).
        let rows = n + mode.rows.len();
        let mut jy = Mat::zeros(rows, 1 + p);
        let mut e = Mat::zeros(n, 1 + p);
        let maphi = spmv(self.model.mass(), &pr.aphi);
        for i in 0..n {
            jy[(i, 0)] = -sig * pr.mphi[i];
            e[(i, 0)] = -s2 * maphi[i];
        }
        for l in 0..p {
            let klaphi = spmv(self.model.k_param(l), &pr.aphi);
            for i in 0..n {
                jy[(i, 1 + l)] = sig * pr.klphi[l][i];
                e[(i, 1 + l)] = s2 * klaphi[i];
            }
        }
        let (block, z) = self.schur_block(kt, m, lambda, &fact, jy, e)?;
        Ok(ModePart {
            phi: ph,
            value,
            g_lambda,
            g_theta,
            block,
            z,
        })
    }
}

/// One mode's share of the reduced objective, its gradient and Hessian.
pub(super) struct ModePart {
    phi: Vec<f64>,
    value: f64,
    g_lambda: f64,
    g_theta: Vec<f64>,
    block: Mat<f64>,
    z: Mat<f64>,
}

/// The augmented system's LU replaces a singular shifted factorization only up to this many
/// DOFs: its fill grows far faster than the model (1.9 GB per mode on the 31,458-DOF
/// four-bay frame, past the deployment's memory), so a larger model's MAP reports the
/// singular point as an error instead.
pub const AUGMENTED_FALLBACK_MAX_DOF: usize = 5_000;

/// Modes whose sparse φ substeps run at once (see [`BayesProblem::per_mode`]).
pub(super) const MODES_AT_ONCE: usize = 2;
