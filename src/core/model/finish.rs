//! What every assembly (frame or solid) ends with: the checks shared by both and the
//! [`Model`] from its matrices.

use rayon::prelude::*;
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

/// `a` with its upper triangle replaced by the mirror of its lower one (`a` itself when it
/// is already exactly symmetric).
fn symmetric_from_lower(a: Csc) -> Csc {
    let n = a.ncols();
    let s = a.symbolic();
    let at = |i: usize, j: usize| -> f64 {
        match s.row_idx_of_col_raw(j).binary_search(&i) {
            Ok(k) => a.val_of_col(j)[k],
            Err(_) => 0.0,
        }
    };
    // Column by column on the worker threads: the check reads every entry (11 million in
    // a 100,000-DOF solid's K0).
    let symmetric = (0..n).into_par_iter().all(|j| {
        s.row_idx_of_col_raw(j)
            .iter()
            .zip(a.val_of_col(j))
            .all(|(&i, &v)| i <= j || at(j, i) == v)
    });
    if symmetric {
        return a;
    }
    // Structurally symmetric (every assembled pattern is): the upper entries take their
    // twins' values in place, without a second copy of the matrix (54 MB of the four-bay
    // solid frame's K0, with 40 MB of triplets besides).
    let twins = |s: faer::sparse::SymbolicSparseColMatRef<'_, usize>| {
        (0..n).into_par_iter().all(|j| {
            s.row_idx_of_col_raw(j)
                .iter()
                .all(|&i| i == j || s.row_idx_of_col_raw(i).binary_search(&j).is_ok())
        })
    };
    if twins(s) {
        let mut a = a;
        let (sym, val) = a.parts_mut();
        let ptr = sym.col_ptr();
        for j in 0..n {
            for k in ptr[j]..ptr[j + 1] {
                let i = sym.row_idx()[k];
                if i < j {
                    let rows = sym.row_idx_of_col_raw(i);
                    let t = rows.binary_search(&j).expect("the twin exists");
                    val[k] = val[ptr[i] + t];
                }
            }
        }
        return a;
    }
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

/// The common end of every assembly: takes `K0`, the `K_l` and `M` (in that order), finds
/// the DOFs without mass ([`massless_dofs`]) and forms the union pattern.
pub(super) fn finish(
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
    // Symmetric to the last bit: the solid elements' integration leaves roundoff
    // asymmetry (1e-14 of the largest entry), which the factorizations (one triangle) and
    // the products (both) would see differently, and which moves the lowest frequencies of
    // the ill-conditioned solid frame by ~1e-9. The lower triangle is kept.
    let mats: Vec<Csc> = mats.into_iter().map(symmetric_from_lower).collect();
    let massless = massless_dofs(&mats, &parameters, &labels)?;
    let refs: Vec<_> = mats.iter().collect();
    let union = UnionPattern::new(n, &refs);
    let mut it = mats.into_iter().skip(1); // K0 is the union's own matrix
    let k_params: Vec<_> = it.by_ref().take(p).collect();
    let m = it.next().expect("M is always assembled");
    // The assembly's scratch (twice the matrices on the four-bay frame) back to the
    // system: the allocator would keep it for later allocations of like sizes only.
    crate::release_free_memory();
    Ok(Model {
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
    })
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
