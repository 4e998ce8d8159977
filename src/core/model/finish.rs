//! What every assembly (frame or solid) ends with: the checks shared by both and the
//! [`Model`] from its matrices.

use std::sync::Arc;

use super::sparse::{Csc, UnionPattern, csc_from_lower, diagonal};
use super::spec::BayesSpec;
use super::{Channel, Connection, Model, ModelError, Parameter};

/// `v` must be a finite number > 0; the error names `field`.
pub(super) fn check_positive(field: String, v: f64) -> Result<(), ModelError> {
    if v.is_finite() && v > 0.0 {
        Ok(())
    } else {
        Err(ModelError::Invalid {
            field,
            reason: format!("must be a finite number > 0, got {v}"),
        })
    }
}

/// `v` must be a finite number ≥ 0; the error names `field`.
pub(super) fn check_non_negative(field: String, v: f64) -> Result<(), ModelError> {
    if v.is_finite() && v >= 0.0 {
        Ok(())
    } else {
        Err(ModelError::Invalid {
            field,
            reason: format!("must be a finite number ≥ 0, got {v}"),
        })
    }
}

/// `a` with its upper triangle replaced by the mirror of its lower one (its own arrays,
/// mended in place, when its pattern is structurally symmetric, as every assembled pattern
/// is; a new matrix from the lower triangle otherwise).
pub(super) fn symmetric_from_lower(a: Csc) -> Csc {
    let n = a.ncols();
    let mut a = a;
    let (sym, val) = a.parts_mut();
    if mirror_lower(sym.col_ptr(), sym.row_idx(), &mut [val]) {
        return a;
    }
    let s = a.symbolic();
    let lower: Vec<(usize, usize, f64)> = (0..n)
        .flat_map(|j| {
            s.row_idx_of_col_raw(j)
                .iter()
                .zip(a.val_of_col(j))
                .filter(move |&(&i, _)| i >= j)
                .map(move |(&i, &v)| (i, j, v))
        })
        .collect();
    csc_from_lower(n, &lower)
}

/// Copies every lower entry `(i, j)`, `i > j`, of square CSC matrices on one pattern (rows
/// sorted within each column) onto its twin `(j, i)`, and says whether every upper entry
/// had a twin (structural symmetry). One pass, no search: visiting the columns `j` in
/// order, the twins in column `i` are met in the order of their rows, so a cursor per
/// column finds each (on the four-bay solid frame, 3.4 million entries: ~10 ms, where a
/// binary search per entry took 60 ms). When it answers `false` only upper entries have
/// been written, so the lower triangles are intact for a rebuild from them.
pub(super) fn mirror_lower(col_ptr: &[usize], row_idx: &[usize], vals: &mut [&mut [f64]]) -> bool {
    let n = col_ptr.len() - 1;
    let mut cursor = col_ptr[..n].to_vec();
    for j in 0..n {
        for k in col_ptr[j]..col_ptr[j + 1] {
            let i = row_idx[k];
            if i <= j {
                continue;
            }
            let t = cursor[i];
            if t == col_ptr[i + 1] || row_idx[t] != j {
                return false; // column i skips row j, or holds a row < j left without twin
            }
            for val in vals.iter_mut() {
                val[t] = val[k];
            }
            cursor[i] += 1;
        }
    }
    // Every upper entry was met: each cursor now stands on its column's diagonal or below.
    (0..n).all(|i| cursor[i] == col_ptr[i + 1] || row_idx[cursor[i]] >= i)
}

/// The common end of every assembly: takes `K0`, the `K_l` and `M` (in that order), makes
/// them symmetric to the last bit and goes on as [`finish_symmetric`]. The solid elements'
/// integration leaves roundoff asymmetry (1e-14 of the largest entry), which the
/// factorizations (one triangle) and the products (both) would see differently, and which
/// moves the lowest frequencies of the ill-conditioned solid frame by ~1e-9. The lower
/// triangle is kept.
pub(super) fn finish(
    name: &str,
    labels: Vec<String>,
    mats: Vec<Csc>,
    parameters: Vec<Parameter>,
    connections: Vec<Connection>,
    channels: Vec<Channel>,
    bayesian: BayesSpec,
) -> Result<Model, ModelError> {
    let mats: Vec<Csc> = mats.into_iter().map(symmetric_from_lower).collect();
    finish_symmetric(
        name,
        labels,
        mats,
        parameters,
        connections,
        channels,
        bayesian,
    )
}

/// [`finish`] for matrices that are exactly symmetric already (the solid assembly mirrors
/// its lower triangles itself, and a second pass over the four-bay frame's took 16 ms):
/// finds the DOFs without mass ([`massless_dofs`]) and forms the union pattern.
pub(super) fn finish_symmetric(
    name: &str,
    labels: Vec<String>,
    mats: Vec<Csc>,
    parameters: Vec<Parameter>,
    connections: Vec<Connection>,
    channels: Vec<Channel>,
    bayesian: BayesSpec,
) -> Result<Model, ModelError> {
    let n = labels.len();
    if n == 0 {
        return Err(ModelError::Invalid {
            field: "nodes".into(),
            reason: "the model has no free DOF".into(),
        });
    }
    let p = parameters.len();
    debug_assert_eq!(mats.len(), p + 2);
    let massless = massless_dofs(&mats, &parameters, &labels)?;
    let mut it = mats.into_iter();
    let k0 = it.next().expect("K0 is always assembled");
    let k_params: Vec<_> = it.by_ref().take(p).collect();
    let m = it.next().expect("M is always assembled");
    let others: Vec<&Csc> = k_params.iter().chain([&m]).collect();
    let union = UnionPattern::with_first(n, k0, &others); // K0 is the union's own matrix
    let model = Model {
        name: name.to_string(),
        dof_labels: labels,
        k_params: Arc::new(k_params),
        m: Arc::new(m),
        parameters,
        connections,
        channels,
        union: Arc::new(union),
        massless,
        locations: Vec::new(),
        reordered: Default::default(),
        bayesian,
    };
    // The assembly's scratch (twice the matrices on the four-bay frame) back to the
    // system, when it is large: the allocator would keep it for later allocations of like
    // sizes only.
    crate::release_scratch(2 * model.matrix_bytes());
    Ok(model)
}

/// The DOFs that carry no mass (a zero diagonal of `M`; lumped-mass models leave rotations
/// and interior nodes without), ascending. They make `M` singular, which the solvers
/// accept: they factorize only `K(θ)` and work in `range(K⁻¹M)`, where the massless DOFs
/// follow the others statically (exactly what static condensation gives). Refused, naming
/// the entry: a negative diagonal mass, a massless DOF coupled to another through `M`
/// (either makes `M` indefinite), a massless DOF without stiffness at nominal θ (`K(θ0)`
/// singular there), a model whose every DOF is massless.
fn massless_dofs(
    mats: &[Csc],
    parameters: &[Parameter],
    labels: &[String],
) -> Result<Vec<usize>, ModelError> {
    let p = parameters.len();
    let m = &mats[p + 1];
    let diag = diagonal(m);
    if let Some(j) = diag.iter().position(|v| v.is_nan() || *v < 0.0) {
        return Err(ModelError::Mass {
            dof: labels[j].clone(),
            reason: format!(
                "diagonal entry {} is negative or not a number, so M has a negative eigenvalue",
                diag[j]
            ),
        });
    }
    let massless: Vec<usize> = (0..diag.len()).filter(|&j| diag[j] == 0.0).collect();
    if massless.is_empty() {
        return Ok(massless);
    }
    if massless.len() == diag.len() {
        return Err(ModelError::Invalid {
            field: "M".into(),
            reason: "no DOF carries mass".into(),
        });
    }
    let s = m.symbolic();
    for &j in &massless {
        if let Some((&i, &v)) = s
            .row_idx_of_col_raw(j)
            .iter()
            .zip(m.val_of_col(j))
            .find(|&(_, &v)| v != 0.0)
        {
            return Err(ModelError::Mass {
                dof: labels[j].clone(),
                reason: format!(
                    "no diagonal mass but M couples it to `{}` ({v}), so M has a negative \
                     eigenvalue",
                    labels[i]
                ),
            });
        }
    }
    let mut k_diag = diagonal(&mats[0]);
    for (l, par) in parameters.iter().enumerate() {
        for (d, v) in k_diag.iter_mut().zip(diagonal(&mats[l + 1])) {
            *d += par.nominal * v;
        }
    }
    if let Some(&j) = massless
        .iter()
        .find(|&&j| k_diag[j].is_nan() || k_diag[j] <= 0.0)
    {
        return Err(ModelError::MasslessSingular {
            dof: labels[j].clone(),
        });
    }
    Ok(massless)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 3 × 3 pattern, full but for (0, 2) and (2, 0), in CSC arrays.
    fn arrays() -> (Vec<usize>, Vec<usize>) {
        (vec![0, 2, 5, 7], vec![0, 1, 0, 1, 2, 1, 2])
    }

    #[test]
    fn the_upper_triangle_takes_the_lower_values_in_place() {
        let (ptr, rows) = arrays();
        // Column 1's (0, 1) is 2.5 where its twin (1, 0) is 2; (1, 2) is 7 where (2, 1) is 6.
        let mut val = vec![1.0, 2.0, 2.5, 3.0, 6.0, 7.0, 4.0];
        assert!(mirror_lower(&ptr, &rows, &mut [&mut val]));
        assert_eq!(val, [1.0, 2.0, 2.0, 3.0, 6.0, 6.0, 4.0]);
    }

    #[test]
    fn an_upper_entry_without_twin_is_found_and_the_lower_triangle_kept() {
        // (0, 2) stored in column 2, (2, 0) not stored in column 0.
        let ptr = vec![0, 2, 5, 8];
        let rows = vec![0, 1, 0, 1, 2, 0, 1, 2];
        let val = vec![1.0, 2.0, 2.5, 3.0, 6.0, 9.0, 7.0, 4.0];
        let mut mended = val.clone();
        assert!(!mirror_lower(&ptr, &rows, &mut [&mut mended]));
        for j in 0..3 {
            for k in ptr[j]..ptr[j + 1] {
                if rows[k] >= j {
                    assert_eq!(mended[k], val[k], "lower entry ({}, {j})", rows[k]);
                }
            }
        }
        // The same matrix through `symmetric_from_lower`: rebuilt from its lower triangle.
        let a = Csc::new(
            faer::sparse::SymbolicSparseColMat::new_checked(3, 3, ptr, None, rows),
            val,
        );
        let s = symmetric_from_lower(a).to_dense();
        let want = [[1.0, 2.0, 0.0], [2.0, 3.0, 6.0], [0.0, 6.0, 4.0]];
        for (i, row) in want.iter().enumerate() {
            for (j, &w) in row.iter().enumerate() {
                assert_eq!(s[(i, j)], w, "({i}, {j})");
            }
        }
    }

    #[test]
    fn a_lower_entry_without_twin_is_found() {
        // (2, 0) stored in column 0, (0, 2) not stored in column 2.
        let ptr = vec![0, 3, 5, 7];
        let rows = vec![0, 1, 2, 0, 1, 1, 2];
        let mut val = vec![1.0; 7];
        assert!(!mirror_lower(&ptr, &rows, &mut [&mut val]));
    }
}
