//! The messages of the tracker's alerts (DESIGN §3.3).

use super::alerts::AlertThresholds;
use crate::contract::AlertLevel;

/// The message of a loosening alert of parameter `name`: against the baseline, or with
/// normalisation against the θ `expected` under the set's conditions (`at -4.3 °C`).
pub(super) fn loosening_message(
    name: &str,
    level: AlertLevel,
    drop: f64,
    confidence: f64,
    inadequate: bool,
    against: Option<&(f64, String)>,
) -> String {
    let reference = match against {
        None => "baseline".to_string(),
        Some((expected, at)) => format!("the {expected:.3} expected {at}"),
    };
    let base = match level {
        AlertLevel::Cleared => format!(
            "{name}: stiffness recovered ({:.0} % below {reference})",
            100.0 * drop
        ),
        _ => format!(
            "{name}: stiffness {:.0} % below {reference} ({}, confidence {:.3})",
            100.0 * drop,
            level.as_str(),
            confidence
        ),
    };
    if inadequate && level != AlertLevel::Cleared {
        format!(
            "{base}; the model is flagged inadequate, so the loss may be a missing effect, not this bolt"
        )
    } else {
        base
    }
}

/// The message of a model-inadequacy alert.
pub(super) fn inadequacy_message(
    level: AlertLevel,
    epsilon: f64,
    bound: f64,
    t: &AlertThresholds,
) -> String {
    if level == AlertLevel::Cleared {
        format!("ε = {epsilon:.1} back within its χ² bound {bound:.1}")
    } else {
        format!(
            "ε = {epsilon:.1} (χ² bound {bound:.1}): ε above its χ² bound, alone or summed over the last {} sets, \
             on {} successive sets: the model class misses an effect; loosening verdicts are unreliable until diagnosed",
            t.inadequacy_window, t.persistence
        )
    }
}
