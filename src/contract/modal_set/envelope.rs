//! The set's own fields, outside its modes: the schema, the watched structure, the time
//! (against the receiver's clock and the last accepted set), the channels, the source and
//! the unexplained peaks of the record's spectrum.

use chrono::{DateTime, TimeDelta, Utc};
use serde_json::{Map, Value};

use super::{MODAL_SET_SCHEMA, Rejection, SpectrumPeak, ValidationContext};
use crate::contract::fields::{capped, format_time, kind, positive, reject, required, string};
use crate::contract::nonfinite::nonfinite_token;

/// Rule: `schema` is present and is [`MODAL_SET_SCHEMA`].
pub(super) fn check_schema(obj: &Map<String, Value>) -> Result<(), Rejection> {
    let schema = required(obj, "schema", "schema")?;
    if schema.as_str() != Some(MODAL_SET_SCHEMA) {
        let got = match schema.as_str() {
            Some(s) if nonfinite_token(schema).is_none() => format!("{s:?}"),
            _ => kind(schema),
        };
        return Err(reject(
            "schema",
            format!("expected {MODAL_SET_SCHEMA:?}, got {got}"),
        ));
    }
    Ok(())
}

/// `structure`: a string naming one of the structures this process watches.
pub(super) fn watched_structure<'v>(
    obj: &'v Map<String, Value>,
    ctx: &ValidationContext,
) -> Result<&'v str, Rejection> {
    let structure = string(required(obj, "structure", "structure")?, "structure")?;
    if !ctx.structures.contains(&structure) {
        return Err(reject(
            "structure",
            format!(
                "{structure:?} is not a watched structure (watched: {:?})",
                ctx.structures
            ),
        ));
    }
    Ok(structure)
}

/// Rules of `time` (an RFC 3339 time every output format holds, `fields::time_field`)
/// against the receiver: not too far ahead of its clock, and not before
/// the last accepted set's (nor equal to it, outside replays).
pub(super) fn check_time(time: DateTime<Utc>, ctx: &ValidationContext) -> Result<(), Rejection> {
    check_not_ahead(time, ctx.max_future)?;
    check_after_last(time, ctx)
}

/// Rule: live, `time` is at most the allowed margin ahead of the receiver's clock.
fn check_not_ahead(
    time: DateTime<Utc>,
    max_future: Option<(DateTime<Utc>, TimeDelta)>,
) -> Result<(), Rejection> {
    if let Some((now, ahead)) = max_future
        && time > now + ahead
    {
        return Err(reject(
            "time",
            format!(
                "{} is {:.0} s ahead of the receiver's clock ({}); at most {} s allowed (daemon.max_future_s)",
                format_time(&time),
                (time - now).as_seconds_f64(),
                format_time(&now),
                ahead.num_seconds()
            ),
        ));
    }
    Ok(())
}

/// Rule: `time` is not before the last accepted set's, and equal to it only when
/// `ctx.allow_equal_time`.
fn check_after_last(time: DateTime<Utc>, ctx: &ValidationContext) -> Result<(), Rejection> {
    if let Some(last) = ctx.last_time {
        if time < last {
            return Err(reject(
                "time",
                format!(
                    "{} is earlier than the last accepted set's {}",
                    format_time(&time),
                    format_time(&last)
                ),
            ));
        }
        if time == last && !ctx.allow_equal_time {
            return Err(reject(
                "time",
                format!(
                    "{} equals the last accepted set's {} (equal times allowed only in replays)",
                    format_time(&time),
                    format_time(&last)
                ),
            ));
        }
    }
    Ok(())
}

/// `channels`: absent (empty), or an array of names, each a channel of the model
/// (`model_channels`) and none repeated.
pub(super) fn parse_channels(
    obj: &Map<String, Value>,
    model_channels: &[String],
) -> Result<Vec<String>, Rejection> {
    let mut channels: Vec<String> = Vec::new();
    if let Some(v) = obj.get("channels") {
        let Value::Array(items) = v else {
            return Err(reject(
                "channels",
                format!("expected an array, got {}", kind(v)),
            ));
        };
        for (j, item) in items.iter().enumerate() {
            let field = || format!("channels[{j}]");
            let name = match item.as_str() {
                Some(s) if nonfinite_token(item).is_none() => s,
                _ => string(item, &field())?,
            };
            if !model_channels.iter().any(|c| c == name) {
                return Err(reject(
                    field(),
                    format!("unknown channel {name:?} (not a channel of the model)"),
                ));
            }
            if let Some(k) = channels.iter().position(|c| c == name) {
                return Err(reject(
                    field(),
                    format!("duplicate channel {name:?} (also channels[{k}])"),
                ));
            }
            channels.push(name.to_string());
        }
    }
    Ok(channels)
}

/// `source`: absent, or a string.
pub(super) fn parse_source(obj: &Map<String, Value>) -> Result<Option<String>, Rejection> {
    obj.get("source")
        .map(|v| string(v, "source").map(str::to_string))
        .transpose()
}

/// `unexplained_peaks`: absent, or an array of `{frequency_hz, prominence_db}`, both > 0.
pub(super) fn parse_peaks(v: Option<&Value>) -> Result<Vec<SpectrumPeak>, Rejection> {
    let items = match v {
        None => return Ok(Vec::new()),
        Some(Value::Array(items)) => items,
        Some(other) => {
            return Err(reject(
                "unexplained_peaks",
                format!("expected an array of peaks, got {}", kind(other)),
            ));
        }
    };
    items
        .iter()
        .enumerate()
        .map(|(i, item)| {
            let path = format!("unexplained_peaks[{i}]");
            let Value::Object(o) = item else {
                return Err(reject(
                    &path,
                    format!("expected an object, got {}", kind(item)),
                ));
            };
            if let Some(k) = o
                .keys()
                .find(|k| !["frequency_hz", "prominence_db"].contains(&k.as_str()))
            {
                return Err(reject(format!("{path}.{}", capped(k, 64)), "unknown field"));
            }
            let field = |name: &str| {
                let f = format!("{path}.{name}");
                o.get(name)
                    .ok_or_else(|| reject(&f, "missing (required)"))
                    .and_then(|v| positive(v, &f))
            };
            Ok(SpectrumPeak {
                frequency_hz: field("frequency_hz")?,
                prominence_db: field("prominence_db")?,
            })
        })
        .collect()
}
