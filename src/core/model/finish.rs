//! What every assembly (frame or solid) ends with: the checks shared by both and the
//! [`Model`] from its matrices.

use super::sparse::{Csc, UnionPattern, csc_from_lower};
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
    let symmetric = (0..n).all(|j| {
        s.row_idx_of_col_raw(j)
            .iter()
            .zip(a.val_of_col(j))
            .all(|(&i, &v)| i <= j || at(j, i) == v)
    });
    if symmetric {
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

/// The common end of every assembly: takes `K0`, the `K_l` and `M` (in that order), checks
/// that every DOF has mass (a DOF without makes `M` singular; name it rather than fail in
/// the eigen solver) and forms the union pattern.
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
    let m = mats[p + 1].clone();
    let mut diag = vec![0.0; n];
    {
        let s = m.symbolic();
        for (j, d) in diag.iter_mut().enumerate() {
            for (&i, &v) in s.row_idx_of_col_raw(j).iter().zip(m.val_of_col(j)) {
                if i == j {
                    *d = v;
                }
            }
        }
    }
    if let Some(j) = diag.iter().position(|&v| v <= 0.0) {
        return Err(ModelError::MasslessDof {
            dof: labels[j].clone(),
        });
    }
    let refs: Vec<_> = mats.iter().collect();
    let union = UnionPattern::new(n, &refs);
    let mut it = mats.into_iter();
    let k0 = it.next().expect("K0 is always assembled");
    let k_params: Vec<_> = it.by_ref().take(p).collect();
    Ok(Model {
        name: name.to_string(),
        dof_labels: labels,
        k0,
        k_params,
        m,
        parameters,
        connections,
        channels,
        union,
        reordered: Default::default(),
        bayesian,
    })
}
