//! Solving Nelson's pinned system `A v_l = f_l` (`A = K − λM`, one component pinned):
//! the unpivoted sparse `LDLᵀ`, trusted only when the normwise backward error of the
//! summed system is within [`BACKWARD_TOL`], and the sparse LU with partial pivoting that
//! replaces it otherwise.

use faer::dyn_stack::MemStack;
use faer::linalg::cholesky::ldlt::factor::LdltRegularization;
use faer::linalg::solvers::Solve;
use faer::sparse::SparseColMatRef;
use faer::sparse::linalg::cholesky::{LdltRef, SymbolicCholeskyRaw};
use faer::sparse::linalg::solvers::{Lu, SymbolicLu};
use faer::{Conj, MatMut, Par, Side};

use super::Nelson;
use crate::core::modal::up_looking::Kind;
use crate::core::modal::{ModalError, col_slice, col_slice_mut, reordered, rows};
use crate::core::model::{Model, Reordered};

/// Largest normwise backward error accepted from the unpivoted `LDLᵀ` solve; a stable
/// solve gives ~1e-16 times a modest growth factor.
pub(crate) const BACKWARD_TOL: f64 = 1e-12;

impl Nelson {
    /// `A v_l = f_l` for every `l` by the unpivoted `LDLᵀ` of the pinned `A` in
    /// `self.values` (solutions in `self.rhs`, reordered numbering): whether it factorized
    /// and its backward error is within [`BACKWARD_TOL`].
    pub(super) fn solve_ldlt(&mut self, order: &Reordered) -> bool {
        let a = SparseColMatRef::new(order.lower.as_ref(), &self.values);
        let [f, r, s] = &mut self.work;
        self.rhs.copy_from(&self.f);
        let factorized = match &mut self.up_looking {
            Some(up) => up.factorize(&self.values, Kind::Ldlt, &mut self.l_values),
            None => order
                .symbolic
                .factorize_numeric_ldlt(
                    &mut self.l_values,
                    a,
                    Side::Lower,
                    LdltRegularization::default(),
                    Par::Seq,
                    MemStack::new(&mut self.mem),
                    Default::default(),
                )
                .is_ok(),
        };
        if !factorized {
            return false;
        }
        match (order.symbolic.raw(), order.symbolic.perm()) {
            // Row-wise, the same bits as faer's solve (`super::rows`).
            (SymbolicCholeskyRaw::Simplicial(simplicial), None) => {
                let l = SparseColMatRef::new(simplicial.factor(), &self.l_values);
                rows::solve_ldlt_in_place(l, self.rhs.as_mut());
            }
            _ => LdltRef::new(&order.symbolic, &self.l_values).solve_in_place_with_conj(
                Conj::No,
                self.rhs.as_mut(),
                Par::Seq,
                MemStack::new(&mut self.mem),
            ),
        }
        backward_error(
            a,
            self.rhs.as_ref(),
            self.f.as_ref(),
            [f.as_mut_slice(), r.as_mut_slice(), s.as_mut_slice()],
        ) <= BACKWARD_TOL
    }

    /// The fallback: `(K − λM) v_l = f_l` with component `k` pinned, by a sparse LU with
    /// partial pivoting on the union pattern (model numbering), into `v`.
    pub(super) fn solve_lu(
        &mut self,
        model: &Model,
        theta: &[f64],
        lambda: f64,
        k: usize,
        mut v: MatMut<'_, f64>,
    ) -> Result<(), ModalError> {
        let n = model.n_dof();
        let pattern = &model.union_pattern().pattern;
        let sym = pattern.symbolic();
        let mut values = vec![0.0; pattern.val().len()];
        model.shifted_stiffness_values(theta, lambda, &mut values);
        for j in 0..n {
            let rows = sym.row_idx_of_col_raw(j);
            let base = sym.col_ptr()[j];
            if j == k {
                for (pos, &i) in rows.iter().enumerate() {
                    values[base + pos] = if i == k { 1.0 } else { 0.0 };
                }
            } else if let Ok(pos) = rows.binary_search(&k) {
                values[base + pos] = 0.0;
            }
        }
        let a = SparseColMatRef::new(sym, &values);
        let symbolic = match &self.symbolic {
            Some(s) => s.clone(),
            None => {
                let s = SymbolicLu::try_new(sym)
                    .map_err(|e| ModalError::Factorization(format!("{e:?}")))?;
                self.symbolic.insert(s).clone()
            }
        };
        let lu = Lu::try_new_with_symbolic(symbolic, a)
            .map_err(|e| ModalError::Factorization(format!("{e:?}")))?;
        let order = reordered(model)?;
        for l in 0..v.ncols() {
            order.unpermute(col_slice(self.f.as_ref(), l), col_slice_mut(v.as_mut(), l));
        }
        lu.solve_in_place(v);
        Ok(())
    }
}

/// Normwise backward error `‖A v − f‖∞ / (‖|A||v|‖∞ + ‖f‖∞)` for `v = Σ_l v_l`,
/// `f = Σ_l f_l` over the columns of the solutions `v` of `A v = f`, `A` symmetric and
/// given by its lower triangle; infinite if not finite. `scratch`: three vectors of length n.
fn backward_error(
    a: SparseColMatRef<'_, usize, f64>,
    v: faer::MatRef<'_, f64>,
    f: faer::MatRef<'_, f64>,
    [vsum, r, s]: [&mut [f64]; 3],
) -> f64 {
    let n = a.nrows();
    let sym = a.symbolic();
    // Row sums, column after column (the columns are contiguous).
    let row_sums = |m: faer::MatRef<'_, f64>, out: &mut [f64]| {
        out.iter_mut().for_each(|x| *x = 0.0);
        for l in 0..m.ncols() {
            for (o, x) in out.iter_mut().zip(col_slice(m, l)) {
                *o += x;
            }
        }
    };
    row_sums(v, vsum);
    r.iter_mut().for_each(|x| *x = 0.0);
    s.iter_mut().for_each(|x| *x = 0.0);
    for j in 0..n {
        let vj = vsum[j];
        for (&i, &aij) in sym.row_idx_of_col_raw(j).iter().zip(a.val_of_col(j)) {
            r[i] += aij * vj;
            s[i] += (aij * vj).abs();
            if i != j {
                r[j] += aij * vsum[i];
                s[j] += (aij * vsum[i]).abs();
            }
        }
    }
    // The residual's sums are final: `vsum` now takes those of `f`.
    row_sums(f, vsum);
    let mut num: f64 = 0.0;
    let mut den: f64 = 0.0;
    for i in 0..n {
        let fi = vsum[i];
        num = num.max((r[i] - fi).abs());
        den = den.max(s[i]).max(fi.abs());
    }
    let e = if den > 0.0 { num / den } else { 0.0 };
    if e.is_finite() { e } else { f64::INFINITY }
}
