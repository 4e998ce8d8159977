//! Eigenvalue and exact eigenvector sensitivities.
//!
//! For a mass-normalized mode `(λ, φ)` of `K(θ) φ = λ M φ` with `M` constant:
//! `∂λ/∂θ_l = φᵀ K_l φ`, and the eigenvector derivative by Nelson's method (R. B. Nelson,
//! "Simplified calculation of eigenvector derivatives", AIAA J. 14 (1976) 1201–1205):
//! `∂φ/∂θ_l = v_l + c_l φ`, where `(K − λM) v_l = −(K_l − ∂λ/∂θ_l M) φ` is solved with the
//! component `k` of largest `|φ_k|` pinned to `v_k = 0` (row and column `k` replaced by the
//! identity), and `c_l = −φᵀ M v_l` keeps the mass normalization. The result is exact (no
//! modal truncation) for a simple eigenvalue, and needs only a sparse factorization of
//! `K − λM`, so it serves large models too. The LU's symbolic part depends only on the
//! pattern and is computed once per model.

use faer::linalg::solvers::Solve;
use faer::sparse::SparseColMatRef;
use faer::sparse::linalg::solvers::{Lu, SymbolicLu};
use faer::{Mat, MatMut};

use super::ModalError;
use crate::core::model::Model;
use crate::core::model::sparse::{bilinear, spmv_add};

/// Workspace for Nelson's method on one model.
pub struct Nelson {
    symbolic: SymbolicLu<usize>,
    values: Vec<f64>,
    m_phi: Vec<f64>,
    rhs: Mat<f64>,
}

impl Nelson {
    /// Builds the symbolic LU of the union pattern of `K0`, every `K_l` and `M`.
    pub fn new(model: &Model) -> Result<Self, ModalError> {
        let pattern = &model.union_pattern().pattern;
        let symbolic = SymbolicLu::try_new(pattern.symbolic())
            .map_err(|e| ModalError::Factorization(format!("{e:?}")))?;
        let n = model.n_dof();
        Ok(Self {
            symbolic,
            values: vec![0.0; pattern.val().len()],
            m_phi: vec![0.0; n],
            rhs: Mat::zeros(n, model.n_params()),
        })
    }

    /// Eigenvalue derivatives `dlambda[l] = ∂λ/∂θ_l` and eigenvector derivatives
    /// `dphi[:, l] = ∂φ/∂θ_l` (n_dof × n_params) of the mass-normalized mode `(lambda, phi)`
    /// of `K(θ)`. `mode` (1-based) only labels errors.
    #[allow(clippy::too_many_arguments)] // the quantities of the formula, each distinct
    pub fn derivatives(
        &mut self,
        model: &Model,
        theta: &[f64],
        mode: usize,
        lambda: f64,
        phi: &[f64],
        dlambda: &mut [f64],
        mut dphi: MatMut<'_, f64>,
    ) -> Result<(), ModalError> {
        let n = model.n_dof();
        let p = model.n_params();
        // Pinned component: largest |φ_k|.
        let k = (0..n)
            .max_by(|&a, &b| phi[a].abs().total_cmp(&phi[b].abs()))
            .unwrap_or(0);

        // A = K(θ) − λM on the union pattern, row and column k replaced by the identity.
        model.shifted_stiffness_values(theta, lambda, &mut self.values);
        let pattern = &model.union_pattern().pattern;
        let sym = pattern.symbolic();
        for j in 0..n {
            let rows = sym.row_idx_of_col_raw(j);
            let base = sym.col_ptr()[j];
            if j == k {
                for (pos, &i) in rows.iter().enumerate() {
                    self.values[base + pos] = if i == k { 1.0 } else { 0.0 };
                }
            } else if let Ok(pos) = rows.binary_search(&k) {
                self.values[base + pos] = 0.0;
            }
        }
        let a = SparseColMatRef::new(sym, &self.values);
        let lu = Lu::try_new_with_symbolic(self.symbolic.clone(), a)
            .map_err(|e| ModalError::Factorization(format!("{e:?}")))?;

        // Right-hand sides f_l = −(K_l − ∂λ_l M) φ with f_l[k] = 0.
        self.m_phi.iter_mut().for_each(|v| *v = 0.0);
        spmv_add(model.mass(), phi, 1.0, &mut self.m_phi);
        let mut f = vec![0.0; n];
        for (l, dl) in dlambda.iter_mut().enumerate().take(p) {
            let kl = model.k_param(l);
            *dl = bilinear(kl, phi, phi);
            f.iter_mut()
                .zip(&self.m_phi)
                .for_each(|(fi, mp)| *fi = *dl * mp);
            spmv_add(kl, phi, -1.0, &mut f);
            f[k] = 0.0;
            for (i, &v) in f.iter().enumerate() {
                self.rhs[(i, l)] = v;
            }
        }
        lu.solve_in_place(self.rhs.as_mut());

        // ∂φ_l = v_l + c_l φ, c_l = −φᵀ M v_l.
        for l in 0..p {
            let v = self.rhs.col(l);
            let c: f64 = -(0..n).map(|i| self.m_phi[i] * v[i]).sum::<f64>();
            for i in 0..n {
                dphi[(i, l)] = v[i] + c * phi[i];
            }
            if !(0..n).all(|i| dphi[(i, l)].is_finite()) {
                return Err(ModalError::RepeatedEigenvalue { mode });
            }
        }
        Ok(())
    }
}
