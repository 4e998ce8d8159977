//! Message bodies of the tracker's outputs (DESIGN §3.3): alert payloads and their
//! messages, and the JSON conventions (times in RFC 3339, non-finite numbers as `null`).

use chrono::{DateTime, SecondsFormat, Utc};
use serde_json::{Value, json};

use super::alerts::Level;
use super::{ALERT_SCHEMA, Action};

pub(super) fn loosening_message(
    name: &str,
    level: &str,
    drop: f64,
    confidence: f64,
    inadequate: bool,
) -> String {
    let base = match level {
        "cleared" => format!(
            "{name}: stiffness recovered ({:.0} % below baseline)",
            100.0 * drop
        ),
        _ => format!(
            "{name}: stiffness {:.0} % below baseline ({level}, confidence {:.3})",
            100.0 * drop,
            confidence
        ),
    };
    if inadequate && level != "cleared" {
        format!(
            "{base}; the model is flagged inadequate, so the loss may be a missing effect, not this bolt"
        )
    } else {
        base
    }
}

pub(super) fn alert(structure: &str, time: DateTime<Utc>, body: Value) -> Action {
    let mut payload = json!({
        "schema": ALERT_SCHEMA,
        "structure": structure,
        "time": rfc3339(time),
    });
    if let (Some(p), Value::Object(b)) = (payload.as_object_mut(), body) {
        p.extend(b);
    }
    Action::Publish {
        topic: "alerts",
        schema: ALERT_SCHEMA,
        time,
        payload,
    }
}

/// `null` for a non-finite number (JSON has none).
pub(super) fn finite(v: f64) -> Option<f64> {
    v.is_finite().then_some(v)
}

/// RFC 3339 with milliseconds and `Z`.
pub fn rfc3339(t: DateTime<Utc>) -> String {
    t.to_rfc3339_opts(SecondsFormat::Millis, true)
}

/// Level of a loosening state, as a string.
pub fn level_name(level: Level) -> &'static str {
    match level {
        Level::Normal => "normal",
        Level::Warning => "warning",
        Level::Alarm => "alarm",
    }
}
