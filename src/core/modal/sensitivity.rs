//! Eigenvalue and exact eigenvector sensitivities.
//!
//! For a mass-normalized mode `(λ, φ)` of `K(θ) φ = λ M φ` with `M` constant:
//! `∂λ/∂θ_l = φᵀ K_l φ`, and the eigenvector derivative by Nelson's method (R. B. Nelson,
//! "Simplified calculation of eigenvector derivatives", AIAA J. 14 (1976) 1201–1205):
//! `∂φ/∂θ_l = v_l + c_l φ`, where `(K − λM) v_l = −(K_l − ∂λ/∂θ_l M) φ` is solved with the
//! component `k` of largest `|φ_k|` pinned to `v_k = 0` (row and column `k` replaced by the
//! identity), and `c_l = −φᵀ M v_l` keeps the mass normalization. The result is exact (no
//! modal truncation) for a simple eigenvalue, and needs only a sparse factorization of
//! `K − λM`, so it serves large models too.
//!
//! The pinned matrix is symmetric but indefinite (the modes below λ give negative
//! directions). It is factorized by a sparse `LDLᵀ` without pivoting (half the work of an
//! LU, the usual practice for shifted stiffness matrices in structural eigen solvers),
//! whose stability is checked on every solve through the normwise backward error
//! `‖Av − f‖∞ / (‖|A||v|‖∞ + ‖f‖∞)` of the summed system (`v = Σ v_l`, `f = Σ f_l`: one
//! generic right-hand side, as an unstable factorization spoils every solve); above
//! `BACKWARD_TOL` (a tiny pivot grew the factors)
//! the system is solved again by a sparse LU with partial pivoting. Both symbolic
//! factorizations depend only on the pattern and are computed once per model.

use faer::dyn_stack::{MemBuffer, MemStack, StackReq};
use faer::linalg::cholesky::ldlt::factor::LdltRegularization;
use faer::linalg::solvers::Solve;
use faer::sparse::SparseColMatRef;
use faer::sparse::linalg::cholesky::SymbolicCholesky;
use faer::sparse::linalg::solvers::{Lu, SymbolicLu};
use faer::{Conj, Mat, MatMut, Par, Side};

use super::ModalError;
use crate::core::model::Model;
use crate::core::model::sparse::spmv_add;

/// Largest normwise backward error accepted from the unpivoted `LDLᵀ` solve; a stable
/// solve gives ~1e-16 times a modest growth factor.
pub const BACKWARD_TOL: f64 = 1e-12;

/// Workspace for Nelson's method on one model.
pub struct Nelson {
    symbolic: SymbolicLu<usize>,
    cholesky: SymbolicCholesky<usize>,
    l_values: Vec<f64>,
    mem: MemBuffer,
    values: Vec<f64>,
    /// `K(θ)` on the union pattern, for the θ in `k_theta` (empty: none yet), shared by
    /// the modes of one Jacobian: each needs only `− λM` on top. Kept in place: a fresh
    /// 27 MB copy per Jacobian (four-bay solid frame) cost 20–60 ms in page faults.
    k_values: Vec<f64>,
    k_theta: Vec<f64>,
    m_phi: Vec<f64>,
    rhs: Mat<f64>,
    f: Mat<f64>,
    /// Scratch of length n: one right-hand side, and the two sums of the backward error.
    work: [Vec<f64>; 3],
    /// Solves that fell back to the LU since this workspace was built.
    pub lu_fallbacks: usize,
}

impl Nelson {
    /// Builds the symbolic LU of the union pattern of `K0`, every `K_l` and `M`.
    pub fn new(model: &Model) -> Result<Self, ModalError> {
        let pattern = &model.union_pattern().pattern;
        let symbolic = SymbolicLu::try_new(pattern.symbolic())
            .map_err(|e| ModalError::Factorization(format!("{e:?}")))?;
        let cholesky = super::union_symbolic_cholesky(model)?;
        let n = model.n_dof();
        let p = model.n_params();
        let mem = MemBuffer::new(StackReq::any_of(&[
            cholesky.factorize_numeric_ldlt_scratch::<f64>(Par::Seq, Default::default()),
            cholesky.solve_in_place_scratch::<f64>(p, Par::Seq),
        ]));
        Ok(Self {
            symbolic,
            l_values: vec![0.0; cholesky.len_val()],
            cholesky,
            mem,
            values: vec![0.0; pattern.val().len()],
            k_values: vec![0.0; pattern.val().len()],
            k_theta: Vec::new(),
            m_phi: vec![0.0; n],
            work: [vec![0.0; n], vec![0.0; n], vec![0.0; n]],
            rhs: Mat::zeros(n, p),
            f: Mat::zeros(n, p),
            lu_fallbacks: 0,
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
        if self.k_theta != theta {
            model.shifted_stiffness_values(theta, 0.0, &mut self.k_values);
            self.k_theta.clear();
            self.k_theta.extend_from_slice(theta);
        }
        self.values.copy_from_slice(&self.k_values);
        model.subtract_mass_values(lambda, &mut self.values);
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

        // Right-hand sides f_l = −(K_l − ∂λ_l M) φ with f_l[k] = 0.
        self.m_phi.iter_mut().for_each(|v| *v = 0.0);
        spmv_add(model.mass(), phi, 1.0, &mut self.m_phi);
        let [f, r, s] = &mut self.work;
        for (l, dl) in dlambda.iter_mut().enumerate().take(p) {
            // K_l φ once: ∂λ_l = φᵀ K_l φ and f_l = ∂λ_l M φ − K_l φ.
            let kl = model.k_param(l);
            f.iter_mut().for_each(|v| *v = 0.0);
            spmv_add(kl, phi, 1.0, f);
            *dl = f.iter().zip(phi).map(|(a, b)| a * b).sum();
            f.iter_mut()
                .zip(&self.m_phi)
                .for_each(|(fi, mp)| *fi = *dl * mp - *fi);
            f[k] = 0.0;
            for (i, &v) in f.iter().enumerate() {
                self.f[(i, l)] = v;
            }
        }
        self.rhs.copy_from(&self.f);
        let ldlt_ok = match self.cholesky.factorize_numeric_ldlt(
            &mut self.l_values,
            a,
            Side::Lower,
            LdltRegularization::default(),
            Par::Seq,
            MemStack::new(&mut self.mem),
            Default::default(),
        ) {
            Ok(ldlt) => {
                ldlt.solve_in_place_with_conj(
                    Conj::No,
                    self.rhs.as_mut(),
                    Par::Seq,
                    MemStack::new(&mut self.mem),
                );
                backward_error(a, self.rhs.as_ref(), self.f.as_ref(), r, s) <= BACKWARD_TOL
            }
            Err(_) => false,
        };
        if !ldlt_ok {
            self.lu_fallbacks += 1;
            let lu = Lu::try_new_with_symbolic(self.symbolic.clone(), a)
                .map_err(|e| ModalError::Factorization(format!("{e:?}")))?;
            self.rhs.copy_from(&self.f);
            lu.solve_in_place(self.rhs.as_mut());
        }

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

/// Normwise backward error `‖A v − f‖∞ / (‖|A||v|‖∞ + ‖f‖∞)` for `v = Σ_l v_l`,
/// `f = Σ_l f_l` over the columns of the solutions `v` of `A v = f`; infinite if not finite.
/// `r` and `s` are scratch of length n.
fn backward_error(
    a: SparseColMatRef<'_, usize, f64>,
    v: faer::MatRef<'_, f64>,
    f: faer::MatRef<'_, f64>,
    r: &mut [f64],
    s: &mut [f64],
) -> f64 {
    let n = a.nrows();
    let sym = a.symbolic();
    r.iter_mut().for_each(|x| *x = 0.0);
    s.iter_mut().for_each(|x| *x = 0.0);
    for j in 0..n {
        let vj: f64 = v.row(j).iter().sum();
        for (&i, &aij) in sym.row_idx_of_col_raw(j).iter().zip(a.val_of_col(j)) {
            r[i] += aij * vj;
            s[i] += (aij * vj).abs();
        }
    }
    let mut num: f64 = 0.0;
    let mut den: f64 = 0.0;
    for i in 0..n {
        let fi: f64 = f.row(i).iter().sum();
        num = num.max((r[i] - fi).abs());
        den = den.max(s[i]).max(fi.abs());
    }
    let e = if den > 0.0 { num / den } else { 0.0 };
    if e.is_finite() { e } else { f64::INFINITY }
}
