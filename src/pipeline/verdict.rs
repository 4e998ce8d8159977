//! The diagnosis verdict of a model-inadequacy warning (issue 6 item 3): the discrepancy
//! workflow ([`crate::core::diagnosis`]) on the set that raised the warning, published as a
//! follow-up `model-inadequate` alert (same set time, level `warning`) that carries the
//! verdict under `diagnosis` and names it in its message. Pure: the drivers run it off the
//! tracking path (the replay's and the daemon's worker threads).

use super::{DiagnoseRequest, measured_data};
use crate::contract::alert::NamedEffect;
use crate::contract::{Alert, AlertDetail, AlertKind, AlertLevel, Schema, Verdict, finite};
use crate::core::diagnosis::{Description, Diagnosis, DiagnosisOptions, Named, diagnose};
use crate::core::model::Model;
use crate::core::model::spec::ModelSpec;

/// The follow-up alert payload (module docs).
pub fn diagnosis_alert(
    spec: Option<&ModelSpec>,
    model: &Model,
    shape_weight: f64,
    req: &DiagnoseRequest,
) -> Alert {
    let data = measured_data(&req.set, model, shape_weight);
    // An imported model is copied only here, when a warning is diagnosed.
    let description = match spec {
        Some(spec) => Description::File(spec.clone()),
        None => Description::matrices(std::sync::Arc::new(model.clone())),
    };
    let diagnosed = diagnose(
        &description,
        &data,
        &DiagnosisOptions::default(),
        |_, _, _| {},
    )
    .map_err(|e| e.to_string());
    let (diagnosis, message) = match diagnosed {
        Ok(d) => found(&d),
        Err(e) => (
            Verdict::Failed { error: e.clone() },
            format!("diagnosis of the model-inadequacy warning failed: {e}"),
        ),
    };
    Alert {
        schema: Schema::new(),
        id: crate::contract::output_id(&model.name, req.set.time, "diagnosis", 0),
        structure: model.name.clone(),
        time: req.set.time,
        connection: None,
        kind: AlertKind::ModelInadequate,
        level: AlertLevel::Warning,
        confidence: None,
        message,
        detail: AlertDetail::Inadequacy {
            epsilon: req.epsilon,
            epsilon_bound: req.epsilon_bound,
            diagnosis: Some(diagnosis),
        },
    }
}

/// The verdict of a diagnosis that ran, and the alert's message naming it.
fn found(d: &Diagnosis) -> (Verdict, String) {
    let named = d.named.iter().map(named_effect).collect();
    let message = found_message(d);
    (
        Verdict::Found {
            named,
            epsilon_before: d.before.epsilon,
            epsilon_after: d.after.epsilon,
            candidates: d.n_candidates,
            threshold: d.threshold,
        },
        message,
    )
}

/// One named effect as the alert carries it.
fn named_effect(n: &Named) -> NamedEffect {
    NamedEffect {
        effect: n.refit.effect.into(),
        location: n.refit.location.clone(),
        value: n.refit.value,
        std: finite(n.refit.std),
        unit: n.refit.unit.into(),
        likelihood_ratio: n.likelihood_ratio,
        indistinguishable_from: n
            .indistinguishable_from
            .iter()
            .map(|o| format!("{}@{}", o.effect, o.location))
            .collect(),
    }
}

/// The message of a diagnosis that ran: the effects named and ε with them in the model,
/// or that none is significant.
fn found_message(d: &Diagnosis) -> String {
    if d.named.is_empty() {
        format!(
            "diagnosis of the model-inadequacy warning: no candidate effect is significant \
             (ε {:.1} of the fitted model; {} candidates, Λ threshold {:.1}); \
             the misfit is not one of the catalogued effects",
            d.before.epsilon, d.n_candidates, d.threshold
        )
    } else {
        format!(
            "diagnosis of the model-inadequacy warning: {}; ε {:.1} -> {:.1} with it in the model",
            d.named
                .iter()
                .map(effect_summary)
                .collect::<Vec<_>>()
                .join(", "),
            d.before.epsilon,
            d.after.epsilon
        )
    }
}

/// One named effect in the message: `effect@location (or …) = value ± std unit`.
fn effect_summary(n: &Named) -> String {
    let alt = if n.indistinguishable_from.is_empty() {
        String::new()
    } else {
        format!(
            " (or {})",
            n.indistinguishable_from
                .iter()
                .map(|o| o.location.as_str())
                .collect::<Vec<_>>()
                .join(", ")
        )
    };
    format!(
        "{}@{}{alt} = {:.3e} ± {:.1e} {}",
        n.refit.effect, n.refit.location, n.refit.value, n.refit.std, n.refit.unit
    )
}
