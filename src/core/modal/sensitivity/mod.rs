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
//! `solve::BACKWARD_TOL` (a tiny pivot grew the factors)
//! the system is solved again by a sparse LU with partial pivoting. Both symbolic
//! factorizations depend only on the pattern: the `LDLᵀ`'s is the model's, computed once;
//! the LU's is computed by a workspace when it first falls back. On a simplicial pattern
//! (small models) the `LDLᵀ`'s numeric step keeps its symbolic work
//! ([`super::up_looking`]) and its solves run row by row ([`super::rows`]), with faer's
//! arithmetic either way.

use faer::dyn_stack::{MemBuffer, StackReq};
use faer::sparse::linalg::solvers::SymbolicLu;
use faer::{Mat, MatMut, Par, Side};

use std::sync::{Arc, PoisonError, RwLock};

use super::up_looking::UpLooking;
use super::{ModalError, col_slice, col_slice_mut};

mod solve;
use crate::core::model::sparse::spmv_add;
use crate::core::model::{Model, Reordered};

/// `K(θ)` on the lower triangle of [`Model::reordered`], for the θ it was formed at (empty:
/// none yet): shared by the Nelson workspaces of one evaluator, whose modes of one Jacobian
/// each need only `− λM` on top. Kept in place: a fresh copy per Jacobian cost 20–60 ms in
/// page faults on the four-bay solid frame, and one copy per workspace 13.5 MB each.
#[derive(Clone, Default)]
pub struct SharedStiffness(Arc<RwLock<(Vec<f64>, Vec<f64>)>>);

impl SharedStiffness {
    /// `K(θ)` into `out` (the reordered lower triangle's length), formed first if the
    /// shared copy is of another θ.
    fn copy_at(&self, model: &Model, order: &Reordered, theta: &[f64], out: &mut [f64]) {
        {
            let held = self.0.read().unwrap_or_else(PoisonError::into_inner);
            if held.0 == theta {
                out.copy_from_slice(&held.1);
                return;
            }
        }
        let mut held = self.0.write().unwrap_or_else(PoisonError::into_inner);
        if held.0 != theta {
            held.1.resize(order.len(), 0.0);
            model.shifted_stiffness_reordered(order, theta, 0.0, &mut held.1);
            held.0.clear();
            held.0.extend_from_slice(theta);
        }
        out.copy_from_slice(&held.1);
    }
}

/// Workspace for Nelson's method on one model.
pub struct Nelson {
    /// Symbolic LU of the union pattern (the fallback), analysed on first use: the
    /// analysis holds ~60 MB at its peak on the four-bay solid frame, and the fallback is
    /// rare.
    symbolic: Option<SymbolicLu<usize>>,
    /// The `LDLᵀ`'s numeric step with its symbolic work done once (`None`: supernodal).
    up_looking: Option<UpLooking>,
    l_values: Vec<f64>,
    mem: MemBuffer,
    /// The pinned `K(θ) − λM`, lower triangle in the reordered numbering
    /// ([`Model::reordered`]; its symbolic `LDLᵀ` analysis is the model's).
    values: Vec<f64>,
    /// `K(θ)` there.
    k_theta: SharedStiffness,
    m_phi: Vec<f64>,
    /// Per parameter, the columns of `K_l` that hold entries and the rows they reach
    /// (ascending): a connection's `K_l` touches a few DOFs, so `K_l φ` and `φᵀ K_l φ` are
    /// formed there only.
    k_cols: Vec<Vec<usize>>,
    k_rows: Vec<Vec<usize>>,
    /// Right-hand sides and solutions, in the reordered numbering.
    rhs: Mat<f64>,
    f: Mat<f64>,
    /// Scratch of length n: one right-hand side, and the two sums of the backward error.
    work: [Vec<f64>; 3],
    /// Solves that fell back to the LU since this workspace was built.
    pub lu_fallbacks: usize,
}

impl Nelson {
    /// Sizes the `LDLᵀ` on the model's reordered pattern.
    pub fn new(model: &Model) -> Result<Self, ModalError> {
        Self::sharing(model, SharedStiffness::default())
    }

    /// Sizes the `LDLᵀ` on the model's reordered pattern; `K(θ)` is held by `k_theta`,
    /// which other workspaces of the same model may share.
    pub fn sharing(model: &Model, k_theta: SharedStiffness) -> Result<Self, ModalError> {
        let order = super::reordered(model)?;
        let cholesky = &order.symbolic;
        let n = model.n_dof();
        let p = model.n_params();
        let mem = MemBuffer::new(StackReq::any_of(&[
            cholesky.factorize_numeric_ldlt_scratch::<f64>(Par::Seq, Default::default()),
            cholesky.solve_in_place_scratch::<f64>(p, Par::Seq),
        ]));
        let (k_cols, k_rows) = (0..p)
            .map(|l| {
                let kl = model.k_param(l);
                let sym = kl.symbolic();
                let cols: Vec<usize> = (0..kl.ncols())
                    .filter(|&j| !sym.row_idx_of_col_raw(j).is_empty())
                    .collect();
                let mut rows: Vec<usize> = cols
                    .iter()
                    .flat_map(|&j| sym.row_idx_of_col_raw(j).iter().copied())
                    .collect();
                rows.sort_unstable();
                rows.dedup();
                (cols, rows)
            })
            .unzip();
        Ok(Self {
            symbolic: None,
            up_looking: UpLooking::new(cholesky, order.lower.as_ref(), Side::Lower),
            l_values: vec![0.0; cholesky.len_val()],
            mem,
            values: vec![0.0; order.len()],
            k_theta,
            m_phi: vec![0.0; n],
            k_cols,
            k_rows,
            work: [vec![0.0; n], vec![0.0; n], vec![0.0; n]],
            rhs: Mat::zeros(n, p),
            f: Mat::zeros(n, p),
            lu_fallbacks: 0,
        })
    }

    /// Eigenvalue derivatives `dlambda[l] = ∂λ/∂θ_l` and eigenvector derivatives
    /// `dphi[:, l] = ∂φ/∂θ_l` (n_dof × n_params) of the mass-normalized mode `(lambda, phi)`
    /// of `K(θ)`. `mode` (1-based) only labels errors. The columns of `dphi` must be
    /// contiguous (an owned matrix's, or a column range of one). Steps: the pinned
    /// `K − λM`, the right-hand sides (and `∂λ`), the `LDLᵀ` solve (the LU when that fails
    /// or its backward error is too large), and the mass normalization.
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
        let p = model.n_params();
        let order = super::reordered(model)?;
        if self.solve_pinned(model, order, theta, lambda, phi, dlambda) {
            // The solutions v_l, back in the model's numbering (in `dphi`).
            for l in 0..p {
                order.unpermute(
                    col_slice(self.rhs.as_ref(), l),
                    col_slice_mut(dphi.as_mut(), l),
                );
            }
            mass_normalize(&self.m_phi, phi, dphi, p, mode)
        } else {
            self.fallback(model, theta, mode, lambda, phi, dphi)
        }
    }

    /// [`Nelson::derivatives`] on some rows only: `dphi_rows[r, l] = ∂φ_{rows[r]}/∂θ_l`
    /// (`rows` in the model's numbering), the same values bit for bit. A tracker needs ∂φ
    /// at its channels only, so the other rows are never formed: `c_l = −φᵀ M v_l` is
    /// summed in the same order straight from the solutions in the reordered numbering.
    #[allow(clippy::too_many_arguments)] // those of `derivatives`, and the rows
    pub fn derivatives_on_rows(
        &mut self,
        model: &Model,
        theta: &[f64],
        mode: usize,
        lambda: f64,
        phi: &[f64],
        dlambda: &mut [f64],
        rows: &[usize],
        mut dphi_rows: MatMut<'_, f64>,
    ) -> Result<(), ModalError> {
        let p = model.n_params();
        let order = super::reordered(model)?;
        if !self.solve_pinned(model, order, theta, lambda, phi, dlambda) {
            // The fallback (rare): the LU on every row, then the wanted ones.
            let mut dphi = Mat::zeros(model.n_dof(), p);
            self.fallback(model, theta, mode, lambda, phi, dphi.as_mut())?;
            for l in 0..p {
                for (r, &i) in rows.iter().enumerate() {
                    dphi_rows[(r, l)] = dphi[(i, l)];
                }
            }
            return Ok(());
        }
        let inv = &order.inv;
        for l in 0..p {
            let v = col_slice(self.rhs.as_ref(), l);
            // As in `mass_normalize`: c_l = −φᵀ M v_l over the model's numbering.
            let c: f64 = -self
                .m_phi
                .iter()
                .zip(inv)
                .map(|(m, &new)| m * v[new])
                .sum::<f64>();
            // A non-finite solution makes c_l non-finite (0 · ∞ is NaN).
            if !c.is_finite() {
                return Err(ModalError::RepeatedEigenvalue { mode });
            }
            for (r, &i) in rows.iter().enumerate() {
                let d = v[inv[i]] + c * phi[i];
                if !d.is_finite() {
                    return Err(ModalError::RepeatedEigenvalue { mode });
                }
                dphi_rows[(r, l)] = d;
            }
        }
        Ok(())
    }

    /// The pinned `K − λM`, the right-hand sides (and `∂λ` into `dlambda`) and their
    /// `LDLᵀ` solve (in `self.rhs`, reordered numbering): whether that solve holds (else
    /// the LU fallback must be used).
    fn solve_pinned(
        &mut self,
        model: &Model,
        order: &Reordered,
        theta: &[f64],
        lambda: f64,
        phi: &[f64],
        dlambda: &mut [f64],
    ) -> bool {
        // `kp`: the pinned component in the reordered numbering.
        let kp = order.inv[pinned_component(phi)];
        self.pin_shifted(model, order, theta, lambda, kp);
        self.right_hand_sides(model, order, phi, kp, dlambda);
        self.solve_ldlt(order)
    }

    /// The rare case where the `LDLᵀ` solve failed: the LU solve, then the mass
    /// normalization, into `dphi` (model numbering).
    fn fallback(
        &mut self,
        model: &Model,
        theta: &[f64],
        mode: usize,
        lambda: f64,
        phi: &[f64],
        mut dphi: MatMut<'_, f64>,
    ) -> Result<(), ModalError> {
        self.lu_fallbacks += 1;
        self.solve_lu(model, theta, lambda, pinned_component(phi), dphi.as_mut())?;
        mass_normalize(&self.m_phi, phi, dphi, model.n_params(), mode)
    }

    /// `A = K(θ) − λM` into `self.values`, row and column `kp` (reordered numbering)
    /// replaced by the identity.
    fn pin_shifted(
        &mut self,
        model: &Model,
        order: &Reordered,
        theta: &[f64],
        lambda: f64,
        kp: usize,
    ) {
        self.k_theta.copy_at(model, order, theta, &mut self.values);
        model.subtract_mass_reordered(order, lambda, &mut self.values);
        let lower = order.lower.as_ref();
        // Column kp holds rows kp.. (the diagonal first); row kp lies in columns ..kp.
        let first = lower.col_ptr()[kp];
        for (pos, v) in self.values[first..lower.col_ptr()[kp + 1]]
            .iter_mut()
            .enumerate()
        {
            *v = if pos == 0 { 1.0 } else { 0.0 };
        }
        for j in 0..kp {
            if let Ok(pos) = lower.row_idx_of_col_raw(j).binary_search(&kp) {
                self.values[lower.col_ptr()[j] + pos] = 0.0;
            }
        }
    }

    /// `M φ` (into `self.m_phi`), the eigenvalue derivatives `dlambda[l] = φᵀ K_l φ`, and
    /// the right-hand sides `f_l = −(K_l − ∂λ_l M) φ` with `f_l[kp] = 0`, in the reordered
    /// numbering (into `self.f`).
    fn right_hand_sides(
        &mut self,
        model: &Model,
        order: &Reordered,
        phi: &[f64],
        kp: usize,
        dlambda: &mut [f64],
    ) {
        let p = model.n_params();
        // Right-hand sides f_l = −(K_l − ∂λ_l M) φ with f_l[k] = 0, in the reordered
        // numbering: ∂λ_l M φ, less K_l φ on the rows K_l reaches. The sums run in the
        // order of a dense product (terms that are exactly zero left out), so the values
        // are those of one.
        self.m_phi.iter_mut().for_each(|v| *v = 0.0);
        spmv_add(model.mass(), phi, 1.0, &mut self.m_phi);
        let [f, _, s] = &mut self.work;
        f.iter_mut().for_each(|v| *v = 0.0);
        // `s`: M φ in the reordered numbering.
        order.permute(&self.m_phi, s);
        for (l, dl) in dlambda.iter_mut().enumerate().take(p) {
            // K_l φ once (into `f`, zero outside the rows K_l reaches): ∂λ_l = φᵀ K_l φ.
            let kl = model.k_param(l);
            let sym = kl.symbolic();
            for &j in &self.k_cols[l] {
                let xj = phi[j];
                if xj == 0.0 {
                    continue;
                }
                for (&i, &v) in sym.row_idx_of_col_raw(j).iter().zip(kl.val_of_col(j)) {
                    f[i] += v * xj;
                }
            }
            *dl = self.k_rows[l].iter().map(|&i| f[i] * phi[i]).sum();
            let col = col_slice_mut(self.f.as_mut(), l);
            for (c, mp) in col.iter_mut().zip(s.iter()) {
                *c = *dl * mp;
            }
            for &i in &self.k_rows[l] {
                col[order.inv[i]] = *dl * self.m_phi[i] - f[i];
                f[i] = 0.0;
            }
            col[kp] = 0.0;
        }
    }
}

/// The component Nelson's method pins: the largest `|φ_k|`.
fn pinned_component(phi: &[f64]) -> usize {
    (0..phi.len())
        .max_by(|&a, &b| phi[a].abs().total_cmp(&phi[b].abs()))
        .unwrap_or(0)
}

/// `∂φ_l = v_l + c_l φ` with `c_l = −φᵀ M v_l` (`m_phi` is `M φ`), in place of the
/// solutions `v_l` in the first `p` columns of `dphi`; a non-finite result means a repeated
/// eigenvalue ([`ModalError::RepeatedEigenvalue`] of `mode`).
fn mass_normalize(
    m_phi: &[f64],
    phi: &[f64],
    mut dphi: MatMut<'_, f64>,
    p: usize,
    mode: usize,
) -> Result<(), ModalError> {
    // ∂φ_l = v_l + c_l φ, c_l = −φᵀ M v_l.
    for l in 0..p {
        let d = col_slice_mut(dphi.as_mut(), l);
        let c: f64 = -m_phi.iter().zip(d.iter()).map(|(m, v)| m * v).sum::<f64>();
        for (di, ph) in d.iter_mut().zip(phi) {
            *di += c * ph;
        }
        if !d.iter().all(|v| v.is_finite()) {
            return Err(ModalError::RepeatedEigenvalue { mode });
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::modal::{DenseEigen, EigenSolver};

    /// The lab frame at θ_l = `base + step · l` and its lowest 9 modes (cold solve).
    fn lab_frame_modes(base: f64, step: f64) -> (Model, Vec<f64>, crate::core::modal::EigenPairs) {
        let model = crate::core::model::lab_frame();
        let theta: Vec<f64> = (0..model.n_params())
            .map(|l| base + step * l as f64)
            .collect();
        let eig = DenseEigen::new(&model)
            .unwrap()
            .solve(&model, &theta, 9)
            .unwrap();
        (model, theta, eig)
    }

    /// `derivatives_on_rows` gives the rows of `derivatives`, bit for bit, and the same
    /// `∂λ` (lab frame, θ away from nominal, modes 1, 5 and 9, rows of the channels and a
    /// few others in any order).
    #[test]
    fn derivatives_on_rows_are_those_of_the_full_derivatives() {
        let (model, theta, eig) = lab_frame_modes(0.7, 0.05);
        let (n, p) = (model.n_dof(), model.n_params());
        let rows = [n - 1, 0, 17, 3, 64, 17];
        let mut nelson = Nelson::new(&model).unwrap();
        for mode in [0, 4, 8] {
            let phi: Vec<f64> = (0..n).map(|i| eig.phi[(i, mode)]).collect();
            let (mut dl_full, mut dl_rows) = (vec![0.0; p], vec![0.0; p]);
            let mut dphi = Mat::zeros(n, p);
            let mut dphi_rows = Mat::zeros(rows.len(), p);
            let lambda = eig.lambda[mode];
            nelson
                .derivatives(
                    &model,
                    &theta,
                    mode + 1,
                    lambda,
                    &phi,
                    &mut dl_full,
                    dphi.as_mut(),
                )
                .unwrap();
            nelson
                .derivatives_on_rows(
                    &model,
                    &theta,
                    mode + 1,
                    lambda,
                    &phi,
                    &mut dl_rows,
                    &rows,
                    dphi_rows.as_mut(),
                )
                .unwrap();
            assert_eq!(dl_full, dl_rows, "∂λ of mode {}", mode + 1);
            for l in 0..p {
                for (r, &i) in rows.iter().enumerate() {
                    assert_eq!(
                        dphi_rows[(r, l)].to_bits(),
                        dphi[(i, l)].to_bits(),
                        "mode {}, θ{}, DOF {i}",
                        mode + 1,
                        l + 1
                    );
                }
            }
        }
    }

    /// The `LU` fallback solves the same pinned system as the `LDLᵀ` (lab frame, θ away
    /// from nominal, modes 1, 4 and 9): both derivatives agree to 1e-9 of the largest
    /// entry (two backward-stable solves of the same system differ by its condition times
    /// rounding; measured 4.5e-11, 1.1e-13, 1.2e-12), and the `LDLᵀ` path did not fall
    /// back.
    #[test]
    fn lu_fallback_matches_the_ldlt_solve() {
        let (model, theta, eig) = lab_frame_modes(0.6, 0.1);
        let (n, p) = (model.n_dof(), model.n_params());
        let mut nelson = Nelson::new(&model).unwrap();
        for mode in [0, 3, 8] {
            let phi: Vec<f64> = (0..n).map(|i| eig.phi[(i, mode)]).collect();
            let mut dlambda = vec![0.0; p];
            let mut dphi = Mat::zeros(n, p);
            nelson
                .derivatives(
                    &model,
                    &theta,
                    mode + 1,
                    eig.lambda[mode],
                    &phi,
                    &mut dlambda,
                    dphi.as_mut(),
                )
                .unwrap();
            assert_eq!(nelson.lu_fallbacks, 0);
            // The same right-hand sides (left in `f` by the call) through the LU.
            let k = pinned_component(&phi);
            let mut v = Mat::zeros(n, p);
            nelson
                .solve_lu(&model, &theta, eig.lambda[mode], k, v.as_mut())
                .unwrap();
            let m_phi = &nelson.m_phi;
            let scale = (0..p)
                .flat_map(|l| (0..n).map(move |i| (i, l)))
                .map(|(i, l)| dphi[(i, l)].abs())
                .fold(0.0, f64::max);
            let mut worst: f64 = 0.0;
            for l in 0..p {
                let c: f64 = -(0..n).map(|i| m_phi[i] * v[(i, l)]).sum::<f64>();
                for i in 0..n {
                    let lu = v[(i, l)] + c * phi[i];
                    worst = worst.max((lu - dphi[(i, l)]).abs() / scale);
                    assert!(
                        (lu - dphi[(i, l)]).abs() <= 1e-9 * scale,
                        "mode {}, θ{}, DOF {i}: LU {lu:e} against LDLᵀ {:e}",
                        mode + 1,
                        l + 1,
                        dphi[(i, l)]
                    );
                }
            }
            println!(
                "mode {}: LU against LDLᵀ {worst:.1e} of the largest entry",
                mode + 1
            );
        }
    }
}
