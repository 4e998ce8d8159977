//! The field rules every incoming JSON message shares (the modal set, the environment
//! reading): the payload as a JSON object, finite numbers (bare `NaN`/`Infinity` named),
//! strings, required and unknown fields, RFC 3339 times, and the [`Rejection`] naming the
//! field and the reason, capped in size.

use chrono::{DateTime, SecondsFormat, Utc};
use serde_json::{Map, Value};

use super::modal_set::{FIELD_LIMIT, REASON_LIMIT, Rejection};
use super::nonfinite::{nonfinite_reason, nonfinite_token, sanitize};

/// The payload as a JSON object (UTF-8, JSON with bare non-finite numbers recognised).
pub(crate) fn json_object(payload: &[u8]) -> Result<Map<String, Value>, Rejection> {
    let text =
        std::str::from_utf8(payload).map_err(|e| reject("payload", format!("not UTF-8: {e}")))?;
    let value: Value = serde_json::from_str(&sanitize(text))
        .map_err(|e| reject("payload", format!("not JSON: {e}")))?;
    let Value::Object(obj) = value else {
        return Err(reject(
            "payload",
            format!("expected a JSON object, got {}", kind(&value)),
        ));
    };

    Ok(obj)
}

/// The required `time` field: an RFC 3339 time every output format holds.
pub(crate) fn time_field(obj: &Map<String, Value>) -> Result<DateTime<Utc>, Rejection> {
    let time_text = string(required(obj, "time", "time")?, "time")?;
    let time = DateTime::parse_from_rfc3339(time_text)
        .map_err(|e| {
            reject(
                "time",
                format!("{time_text:?} is not an RFC 3339 time: {e}"),
            )
        })?
        .with_timezone(&Utc);
    if !super::wire::representable(time) {
        return Err(reject(
            "time",
            format!(
                "{time_text:?} is outside the range every output format holds ({})",
                super::wire::TIME_RANGE
            ),
        ));
    }
    Ok(time)
}

/// `text` cut to at most `limit` bytes (at a character boundary), with `…` when cut.
pub fn capped(text: &str, limit: usize) -> String {
    if text.len() <= limit {
        return text.to_string();
    }
    let mut cut = limit.saturating_sub('…'.len_utf8());
    while !text.is_char_boundary(cut) {
        cut -= 1;
    }
    format!("{}…", &text[..cut])
}

pub(crate) fn reject(field: impl Into<String>, reason: impl Into<String>) -> Rejection {
    Rejection {
        field: capped(&field.into(), FIELD_LIMIT),
        reason: capped(&reason.into(), REASON_LIMIT),
    }
}

/// What kind of JSON value `v` is, for "expected …, got …" reasons.
pub(crate) fn kind(v: &Value) -> String {
    if let Some(token) = nonfinite_token(v) {
        return format!("a non-finite number ({token})");
    }
    match v {
        Value::Null => "null",
        Value::Bool(_) => "a boolean",
        Value::Number(_) => "a number",
        Value::String(_) => "a string",
        Value::Array(_) => "an array",
        Value::Object(_) => "an object",
    }
    .to_string()
}

/// A finite number, or a rejection naming `field`.
pub(crate) fn number(v: &Value, field: &str) -> Result<f64, Rejection> {
    if let Some(token) = nonfinite_token(v) {
        return Err(reject(field, nonfinite_reason(token)));
    }
    match v {
        Value::Number(n) => match n.as_f64() {
            Some(x) if x.is_finite() => Ok(x),
            _ => Err(reject(field, format!("not a finite number ({n})"))),
        },
        other => Err(reject(
            field,
            format!("expected a number, got {}", kind(other)),
        )),
    }
}

/// A finite number > 0, or a rejection naming `field`.
pub(crate) fn positive(v: &Value, field: &str) -> Result<f64, Rejection> {
    let x = number(v, field)?;
    if x > 0.0 {
        Ok(x)
    } else {
        Err(reject(field, format!("must be > 0, got {x}")))
    }
}

/// A string (not a substituted non-finite number), or a rejection naming `field`.
pub(crate) fn string<'v>(v: &'v Value, field: &str) -> Result<&'v str, Rejection> {
    match v {
        Value::String(s) if nonfinite_token(v).is_none() => Ok(s),
        other => Err(reject(
            field,
            format!("expected a string, got {}", kind(other)),
        )),
    }
}

/// The field `key` of `obj`, or a "missing" rejection naming `path`.
pub(crate) fn required<'v>(
    obj: &'v Map<String, Value>,
    key: &str,
    path: &str,
) -> Result<&'v Value, Rejection> {
    obj.get(key)
        .ok_or_else(|| reject(path, "missing (required)"))
}

/// Rejects the first field of `obj` not in `allowed`.
pub(crate) fn no_unknown_fields(
    obj: &Map<String, Value>,
    allowed: &[&str],
    prefix: &str,
) -> Result<(), Rejection> {
    match obj.keys().find(|k| !allowed.contains(&k.as_str())) {
        Some(k) => Err(reject(
            format!("{prefix}{}", k.escape_debug()),
            format!("unknown field (allowed: {})", allowed.join(", ")),
        )),
        None => Ok(()),
    }
}

pub(crate) fn format_time(t: &DateTime<Utc>) -> String {
    t.to_rfc3339_opts(SecondsFormat::AutoSi, true)
}
