//! One measured mode, `modes[i]`, validated on its own: its fields, the frequency and its
//! CoV, the shape (one entry per channel, normalizable), the shape's uncertainty
//! (`shape_nsd` or `shape_std`), the damping and the label.

use serde_json::{Map, Value};

use super::{LABEL_LIMIT, MeasuredMode, Rejection, UNCERTAINTY_FLOOR};
use crate::contract::fields::{
    capped, kind, no_unknown_fields, number, positive, reject, required, string,
};
use crate::contract::nonfinite::nonfinite_token;

/// Fields of one mode.
const MODE_FIELDS: &[&str] = &[
    "frequency_hz",
    "frequency_cov",
    "shape",
    "shape_nsd",
    "shape_std",
    "damping_ratio",
    "damping_std",
    "label",
];

/// Parses and validates `modes[i]` on its own; `n_channels` is the length of `channels`.
pub(super) fn parse_mode(
    i: usize,
    v: &Value,
    n_channels: usize,
) -> Result<MeasuredMode, Rejection> {
    let path = format!("modes[{i}]");
    let Value::Object(obj) = v else {
        return Err(reject(path, format!("expected an object, got {}", kind(v))));
    };
    no_unknown_fields(obj, MODE_FIELDS, &format!("{path}."))?;

    let f_path = format!("{path}.frequency_hz");
    let frequency_hz = positive(required(obj, "frequency_hz", &f_path)?, &f_path)?;
    let frequency_cov = obj
        .get("frequency_cov")
        .map(|v| uncertainty(v, &format!("{path}.frequency_cov")))
        .transpose()?;

    let shape = obj
        .get("shape")
        .map(|v| parse_shape(v, n_channels, &format!("{path}.shape")))
        .transpose()?;
    let shape_nsd = parse_shape_nsd(obj, shape.is_some(), &path)?;
    let shape_std = obj
        .get("shape_std")
        .map(|v| shape_std(v, shape.as_deref(), &format!("{path}.shape_std")))
        .transpose()?;

    let damping_ratio = parse_damping_ratio(obj, &path)?;
    let damping_std = parse_damping_std(obj, damping_ratio.is_some(), &path)?;
    let label = obj
        .get("label")
        .map(|v| label(v, &format!("{path}.label")).map(str::to_string))
        .transpose()?;

    Ok(MeasuredMode {
        frequency_hz,
        frequency_cov,
        shape,
        shape_nsd,
        shape_std,
        damping_ratio,
        damping_std,
        label,
    })
}

/// An uncertainty (a CoV or an NSD): a finite number ≥ [`UNCERTAINTY_FLOOR`].
fn uncertainty(v: &Value, field: &str) -> Result<f64, Rejection> {
    let x = positive(v, field)?;
    if x >= UNCERTAINTY_FLOOR {
        Ok(x)
    } else {
        Err(reject(
            field,
            format!(
                "{x:e} is below the floor {UNCERTAINTY_FLOOR:e} (no identification resolves a mode that finely; the weights of (9) would be meaningless)"
            ),
        ))
    }
}

/// `modes[i].shape` (at `path`): an array of numbers and `null`s, one per channel
/// (`n_channels`), not empty, not all `null`, and normalizable.
fn parse_shape(v: &Value, n_channels: usize, path: &str) -> Result<Vec<Option<f64>>, Rejection> {
    let shape = shape_entries(v, path)?;
    if shape.is_empty() {
        return Err(reject(
            path,
            "must not be empty (omit it for a frequency-only mode)",
        ));
    }
    if shape.len() != n_channels {
        return Err(reject(
            path,
            format!("has {} entries but channels has {n_channels}", shape.len()),
        ));
    }
    if shape.iter().all(Option::is_none) {
        return Err(reject(
            path,
            format!(
                "all {} entries are null (omit it for a frequency-only mode)",
                shape.len()
            ),
        ));
    }
    check_normalizable(&shape, path)?;
    Ok(shape)
}

/// The entries of a shape (at `path`): an array of finite numbers and `null`s (unmeasured).
fn shape_entries(v: &Value, path: &str) -> Result<Vec<Option<f64>>, Rejection> {
    let Value::Array(entries) = v else {
        return Err(reject(path, format!("expected an array, got {}", kind(v))));
    };
    let mut shape = Vec::with_capacity(entries.len());
    for (k, e) in entries.iter().enumerate() {
        // The common case first, without building the entry's path.
        if let Some(x) = e.as_f64().filter(|x| x.is_finite()) {
            shape.push(Some(x));
            continue;
        }
        shape.push(match e {
            Value::Null => None,
            other => Some(number(other, &format!("{path}[{k}]")).map_err(|r| {
                if other.is_number() || nonfinite_token(other).is_some() {
                    r
                } else {
                    reject(
                        r.field,
                        format!("expected a number or null, got {}", kind(other)),
                    )
                }
            })?),
        });
    }
    Ok(shape)
}

/// `modes[i].shape_nsd` (under `path`): absent, or an uncertainty on a mode with a shape
/// (`has_shape`).
fn parse_shape_nsd(
    obj: &Map<String, Value>,
    has_shape: bool,
    path: &str,
) -> Result<Option<f64>, Rejection> {
    let nsd_path = format!("{path}.shape_nsd");
    let shape_nsd = obj
        .get("shape_nsd")
        .map(|v| uncertainty(v, &nsd_path))
        .transpose()?;
    if shape_nsd.is_some() && !has_shape {
        return Err(reject(nsd_path, "present on a mode without a shape"));
    }
    Ok(shape_nsd)
}

/// `modes[i].damping_ratio` (under `path`): absent, or a fraction in `[0, 1)`.
fn parse_damping_ratio(obj: &Map<String, Value>, path: &str) -> Result<Option<f64>, Rejection> {
    let z_path = format!("{path}.damping_ratio");
    let damping_ratio = match obj.get("damping_ratio") {
        None => None,
        Some(v) => {
            let z = number(v, &z_path)?;
            if !(0.0..1.0).contains(&z) {
                return Err(reject(
                    z_path,
                    format!("{z} is not a damping ratio (a fraction in [0, 1))"),
                ));
            }
            Some(z)
        }
    };
    Ok(damping_ratio)
}

/// `modes[i].damping_std` (under `path`): absent, or a number > 0 on a mode with a
/// damping ratio (`has_ratio`).
fn parse_damping_std(
    obj: &Map<String, Value>,
    has_ratio: bool,
    path: &str,
) -> Result<Option<f64>, Rejection> {
    let zs_path = format!("{path}.damping_std");
    let damping_std = obj
        .get("damping_std")
        .map(|v| positive(v, &zs_path))
        .transpose()?;
    if damping_std.is_some() && !has_ratio {
        return Err(reject(zs_path, "present on a mode without damping_ratio"));
    }
    Ok(damping_std)
}

/// A mode label: a non-empty string of at most [`LABEL_LIMIT`] bytes.
pub(super) fn label<'v>(v: &'v Value, path: &str) -> Result<&'v str, Rejection> {
    let l = string(v, path)?;
    if l.is_empty() || l.len() > LABEL_LIMIT {
        return Err(reject(
            path,
            format!(
                "a label has 1 to {LABEL_LIMIT} bytes, `{}` has {}",
                capped(l, LABEL_LIMIT),
                l.len()
            ),
        ));
    }
    Ok(l)
}

/// Rule: `shape_std` belongs to a mode with a shape, has one entry per shape entry, `null`
/// exactly where the shape is, numbers finite and ≥ 0, and at least one > 0 (a zero is the
/// reference entry of a normalized shape, floored later); the median of the positive ones
/// is at least [`UNCERTAINTY_FLOOR`] times the shape's RMS (below it the weights lose
/// their meaning, as for `shape_nsd`).
fn shape_std(
    v: &Value,
    shape: Option<&[Option<f64>]>,
    path: &str,
) -> Result<Vec<Option<f64>>, Rejection> {
    let Some(shape) = shape else {
        return Err(reject(path, "present on a mode without a shape"));
    };
    let Value::Array(entries) = v else {
        return Err(reject(path, format!("expected an array, got {}", kind(v))));
    };
    if entries.len() != shape.len() {
        return Err(reject(
            path,
            format!(
                "has {} entries but the shape has {}",
                entries.len(),
                shape.len()
            ),
        ));
    }
    let mut out = Vec::with_capacity(entries.len());
    for (k, (e, s)) in entries.iter().zip(shape).enumerate() {
        let field = format!("{path}[{k}]");
        out.push(match (e, s) {
            (Value::Null, None) => None,
            (Value::Null, Some(_)) => {
                return Err(reject(field, "null where the shape entry is a number"));
            }
            (_, None) => {
                return Err(reject(field, "a number where the shape entry is null"));
            }
            (e, Some(_)) => {
                let x = number(e, &field)?;
                if x < 0.0 {
                    return Err(reject(field, format!("{x} is negative")));
                }
                Some(x)
            }
        });
    }
    let Some(median) = crate::core::updating::data::positive_median(out.iter().flatten()) else {
        return Err(reject(path, "every entry is 0 (at least one must be > 0)"));
    };
    let measured: Vec<f64> = shape.iter().flatten().copied().collect();
    let rms = (measured.iter().map(|x| x * x).sum::<f64>() / measured.len() as f64).sqrt();
    if median < UNCERTAINTY_FLOOR * rms {
        return Err(reject(
            path,
            format!(
                "the median of its positive entries, {median:e}, is below {UNCERTAINTY_FLOOR:e} \
                 times the shape's RMS {rms:e} (the weights of (28) would be meaningless)"
            ),
        ));
    }
    Ok(out)
}

/// Rule: a shape has a direction that can be normalized: not all zero, and its norm and
/// the norm's reciprocal finite (entries of 1e-310 or 1e200 would overflow the MAC and the
/// scaling of (9)).
fn check_normalizable(shape: &[Option<f64>], path: &str) -> Result<(), Rejection> {
    let largest = shape.iter().flatten().fold(0.0_f64, |m, x| m.max(x.abs()));
    if largest == 0.0 {
        return Err(reject(
            path,
            "all measured entries are zero (a mode shape has a direction; omit it for a frequency-only mode)",
        ));
    }
    let norm = largest
        * shape
            .iter()
            .flatten()
            .map(|x| (x / largest).powi(2))
            .sum::<f64>()
            .sqrt();
    let sum_sq = norm * norm;
    if !(sum_sq.is_normal() && (1.0 / sum_sq).is_normal()) {
        return Err(reject(
            path,
            format!(
                "cannot be normalized: its norm {norm:e} is out of the range of f64 arithmetic (scale the entries to order 1)"
            ),
        ));
    }
    Ok(())
}
