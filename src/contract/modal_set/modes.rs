//! The modes of a set as a list: how many a set may carry, each mode parsed in order
//! ([`super::mode`]), and the rules across modes: increasing frequencies, uncertainties on
//! all modes or none, labels unique, and `missing` naming no mode of the set.

use std::collections::HashSet;

use serde_json::{Map, Value};

use super::mode::{label, parse_mode};
use super::{FREQUENCY_ORDER_TOLERANCE, MAX_MODES, MeasuredMode, Rejection};
use crate::contract::fields::{capped, kind, reject, required};

/// `modes`: a non-empty array of at most [`MAX_MODES`] modes, each valid on its own
/// (`n_channels` is the length of `channels`), then the rules across them: frequencies in
/// order, and uncertainties on all modes or none.
pub(super) fn parse_modes(
    obj: &Map<String, Value>,
    n_channels: usize,
) -> Result<Vec<MeasuredMode>, Rejection> {
    let modes_value = required(obj, "modes", "modes")?;
    let Value::Array(items) = modes_value else {
        return Err(reject(
            "modes",
            format!("expected an array, got {}", kind(modes_value)),
        ));
    };
    if items.is_empty() {
        return Err(reject("modes", "must not be empty"));
    }
    if items.len() > MAX_MODES {
        return Err(reject(
            "modes",
            format!(
                "{} modes, more than the {MAX_MODES} a set may carry",
                items.len()
            ),
        ));
    }
    let modes = items
        .iter()
        .enumerate()
        .map(|(i, v)| parse_mode(i, v, n_channels))
        .collect::<Result<Vec<_>, _>>()?;
    check_frequency_order(&modes)?;
    check_uncertainty_consistency(&modes)?;
    Ok(modes)
}

/// Rule: frequencies increase, equality within [`FREQUENCY_ORDER_TOLERANCE`] accepted
/// (close modes), but not a mode repeated: the same frequency and the same shape.
fn check_frequency_order(modes: &[MeasuredMode]) -> Result<(), Rejection> {
    for (i, pair) in modes.windows(2).enumerate() {
        let (prev, cur) = (pair[0].frequency_hz, pair[1].frequency_hz);
        if cur < prev * (1.0 - FREQUENCY_ORDER_TOLERANCE) {
            return Err(reject(
                format!("modes[{}].frequency_hz", i + 1),
                format!("frequencies must increase: {cur} after modes[{i}].frequency_hz = {prev}"),
            ));
        }
        if cur <= prev * (1.0 + FREQUENCY_ORDER_TOLERANCE) && pair[0].shape == pair[1].shape {
            return Err(reject(
                format!("modes[{}]", i + 1),
                format!("repeats modes[{i}] (the same frequency {cur} Hz and the same shape)"),
            ));
        }
    }
    Ok(())
}

/// Rule: `frequency_cov` on all modes or none; `shape_nsd` on all modes with a shape or none.
fn check_uncertainty_consistency(modes: &[MeasuredMode]) -> Result<(), Rejection> {
    let mixed = |i: usize, name: &str, first: usize, first_has: bool| {
        let (here, there) = if first_has {
            ("absent", "present")
        } else {
            ("present", "absent")
        };
        reject(
            format!("modes[{i}].{name}"),
            format!(
                "present on some modes but not others ({here} here, {there} on modes[{first}])"
            ),
        )
    };
    if let Some(first) = modes.first() {
        let has = first.frequency_cov.is_some();
        if let Some(i) = modes.iter().position(|m| m.frequency_cov.is_some() != has) {
            return Err(mixed(i, "frequency_cov", 0, has));
        }
    }
    let mut shaped = modes.iter().enumerate().filter(|(_, m)| m.shape.is_some());
    if let Some((first, m0)) = shaped.next() {
        let has = m0.has_shape_uncertainty();
        if let Some((i, m)) = shaped.find(|(_, m)| m.has_shape_uncertainty() != has) {
            // A mode's shape uncertainty is its shape_nsd or its shape_std.
            let name = if m.shape_nsd.is_none() && m.shape_std.is_some() {
                "shape_std"
            } else {
                "shape_nsd"
            };
            return Err(mixed(i, name, first, has));
        }
    }
    Ok(())
}

/// Rule: no two modes share a label. The set of the modes' labels.
pub(super) fn unique_labels(modes: &[MeasuredMode]) -> Result<HashSet<&str>, Rejection> {
    let mut labels = HashSet::new();
    for (i, m) in modes.iter().enumerate() {
        if let Some(l) = &m.label
            && !labels.insert(l.as_str())
        {
            return Err(reject(
                format!("modes[{i}].label"),
                format!("`{}` labels an earlier mode too", capped(l, 64)),
            ));
        }
    }
    Ok(labels)
}

/// `missing`: absent (empty), or an array of labels, none of a mode of this set (`labels`).
pub(super) fn parse_missing(
    v: Option<&Value>,
    labels: &HashSet<&str>,
) -> Result<Vec<String>, Rejection> {
    let missing = match v {
        None => Vec::new(),
        Some(Value::Array(items)) => {
            let mut out = Vec::with_capacity(items.len());
            for (i, v) in items.iter().enumerate() {
                let path = format!("missing[{i}]");
                let l = label(v, &path)?;
                if labels.contains(l) {
                    return Err(reject(path, format!("`{l}` labels a mode of this set")));
                }
                out.push(l.to_string());
            }
            out
        }
        Some(other) => {
            return Err(reject(
                "missing",
                format!("expected an array of labels, got {}", kind(other)),
            ));
        }
    };
    Ok(missing)
}
