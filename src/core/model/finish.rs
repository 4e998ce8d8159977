//! What every assembly (frame or solid) ends with: the checks shared by both and the
//! [`Model`] from its matrices.

use super::sparse::{Csc, UnionPattern};
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
