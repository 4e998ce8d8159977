//! Where a candidate differs from the fitted model: its DOFs matched to the fitted model's
//! by label ([`DofMap`]), and the entries of `K′ − K` and `M′ − M` gathered at the DOFs
//! they touch ([`Changes`]).

use std::collections::HashMap;

use faer::Mat;

use super::ReducedBasis;
use crate::core::model::Model;

/// Most DOFs a candidate may touch: a member's stiffness or axial force touches those of
/// its nodes (20 on the space frame's members).
pub(super) const REDUCED_MAX_TOUCHED: usize = 60;

/// Most DOFs a candidate may add (a splice adds one, its hinge).
const REDUCED_MAX_NEW: usize = 6;

/// A candidate's DOFs in the fitted model's numbering, extended by the candidate's new
/// DOFs: `ext[j]` is the fitted model's DOF at candidate DOF `j`'s place, or `n + ν` for
/// the candidate's `ν`-th new DOF (`n` the fitted model's DOF count).
pub(super) struct DofMap {
    pub(super) ext: Vec<usize>,
    pub(super) new: usize,
}

impl DofMap {
    pub(super) fn is_identity(&self) -> bool {
        self.new == 0 && self.ext.iter().enumerate().all(|(j, &e)| j == e)
    }
}

/// Where a candidate's matrices differ from the fitted model's: the DOFs `t`, in the
/// extended numbering of [`DofMap`] (ascending, so the fitted model's come first, `old` of
/// them), and the changes there (dense, `|t| × |t|`).
pub(super) struct Changes {
    pub(super) t: Vec<usize>,
    pub(super) old: usize,
    pub(super) dk: Mat<f64>,
    pub(super) dm: Mat<f64>,
}

impl Changes {
    /// The touched DOFs of the fitted model.
    pub(super) fn t_old(&self) -> &[usize] {
        &self.t[..self.old]
    }
}

/// The entries of `K′ − K` and `M′ − M` as they are found.
struct Difference {
    n: usize,
    entries: Vec<(usize, usize, f64, f64)>,
}

impl Difference {
    fn new(n: usize) -> Self {
        Self {
            n,
            entries: Vec::new(),
        }
    }

    fn add(&mut self, i: usize, j: usize, dk: f64, dm: f64) {
        self.entries.push((i, j, dk, dm));
    }

    /// The touched DOFs and the dense changes there; `None` when the candidate touches
    /// none of the fitted model's DOFs or more than [`REDUCED_MAX_TOUCHED`].
    fn into_changes(self, n_old: usize) -> Option<Changes> {
        let mut at = vec![usize::MAX; self.n];
        let mut t = Vec::new();
        for &(i, j, _, _) in &self.entries {
            for d in [i, j] {
                if at[d] == usize::MAX {
                    at[d] = 0;
                    t.push(d);
                }
            }
        }
        t.sort_unstable();
        let old = t.partition_point(|&d| d < n_old);
        if old == 0 || old > REDUCED_MAX_TOUCHED {
            return None;
        }
        for (a, &d) in t.iter().enumerate() {
            at[d] = a;
        }
        let (mut dk, mut dm) = (Mat::zeros(t.len(), t.len()), Mat::zeros(t.len(), t.len()));
        for &(i, j, k, m) in &self.entries {
            dk[(at[i], at[j])] += k;
            dm[(at[i], at[j])] += m;
        }
        Some(Changes { t, old, dk, dm })
    }
}

impl ReducedBasis<'_> {
    /// The candidate's DOFs matched to the fitted model's by label; `None` when one of the
    /// fitted model's is missing, the parameters differ, or the candidate adds more than
    /// [`REDUCED_MAX_NEW`] DOFs.
    pub(super) fn dof_map(&self, c: &Model, relabel: &dyn Fn(&str) -> String) -> Option<DofMap> {
        let base = self.model.dof_labels();
        if c.n_params() != self.theta.len() {
            return None;
        }
        if c.dof_labels() == base {
            let ext = (0..base.len()).collect();
            return Some(DofMap { ext, new: 0 });
        }
        let at: HashMap<&str, usize> = c
            .dof_labels()
            .iter()
            .enumerate()
            .map(|(j, l)| (l.as_str(), j))
            .collect();
        let mut ext = vec![usize::MAX; c.n_dof()];
        for (i, label) in base.iter().enumerate() {
            let j = *at.get(relabel(label).as_str())?;
            if ext[j] != usize::MAX {
                return None;
            }
            ext[j] = i;
        }
        let mut new = 0;
        for e in ext.iter_mut().filter(|e| **e == usize::MAX) {
            *e = base.len() + new;
            new += 1;
        }
        (new <= REDUCED_MAX_NEW).then_some(DofMap { ext, new })
    }

    /// Where `c` differs from the fitted model, in the numbering of `map`.
    pub(super) fn changes(&self, c: &Model, map: &DofMap) -> Option<Changes> {
        let mut k = vec![0.0; c.k0().val().len()];
        c.shifted_stiffness_values(&self.theta, 0.0, &mut k);
        let m = mass_values(c);
        let n = self.model.n_dof();
        let mut diff = Difference::new(n + map.new);
        self.differences(c, map, (&k, &m), &mut diff);
        diff.into_changes(n)
    }

    /// The entries of `K′ − K` and `M′ − M` into `diff`, column by column (the two
    /// patterns may differ; the fitted model has nothing at the new DOFs).
    fn differences(
        &self,
        c: &Model,
        map: &DofMap,
        (k, m): (&[f64], &[f64]),
        diff: &mut Difference,
    ) {
        let (cp, ci) = (c.k0().symbolic().col_ptr(), c.k0().symbolic().row_idx());
        let base = self.model.k0().symbolic();
        let (bp, bi) = (base.col_ptr(), base.row_idx());
        let size = self.model.n_dof() + map.new;
        let (mut col_k, mut col_m, mut rows) = (vec![0.0; size], vec![0.0; size], Vec::new());
        for (jc, &j) in map.ext.iter().enumerate() {
            rows.clear();
            for e in cp[jc]..cp[jc + 1] {
                let i = map.ext[ci[e]];
                col_k[i] += k[e];
                col_m[i] += m[e];
                rows.push(i);
            }
            if j < self.model.n_dof() {
                for e in bp[j]..bp[j + 1] {
                    col_k[bi[e]] -= self.k[e];
                    col_m[bi[e]] -= self.m[e];
                    rows.push(bi[e]);
                }
            }
            for &i in &rows {
                if col_k[i] != 0.0 || col_m[i] != 0.0 {
                    diff.add(i, j, col_k[i], col_m[i]);
                }
                col_k[i] = 0.0;
                col_m[i] = 0.0;
            }
        }
    }
}

/// `M` on the model's union pattern.
pub(super) fn mass_values(model: &Model) -> Vec<f64> {
    let mut m = vec![0.0; model.k0().val().len()];
    model.subtract_mass_values(-1.0, &mut m);
    m
}
