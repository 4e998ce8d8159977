//! `boltwatch.accel.v1`: a block of raw vibration samples of one structure, on
//! `boltwatch/<structure>/accel` (issue 26).
//!
//! A JSON object, so MCAP tools read it with its JSON Schema (`src/io/schemas/accel.json`),
//! whose bulk is binary: the samples travel as little-endian IEEE floats in one base64
//! string (`data`), sample after sample, the channels of one sample together (row-major,
//! `samples × channels`). `f32le` (the default writers use: 24-bit mantissa, as much as any
//! accelerometer's converter resolves) costs 5.3 bytes per value on the wire, `f64le` 10.7;
//! a decimal JSON array of the same numbers costs about 20.
//!
//! ```json
//! {"schema": "boltwatch.accel.v1", "structure": "lab-frame",
//!  "start": "2026-03-01T00:00:00.000Z", "rate_hz": 1000.0,
//!  "channels": ["N3.uy", "N4.uy"], "units": ["m/s^2", "mm/s"],
//!  "encoding": "f32le", "samples": 2, "data": "AACAPwAAAEAAAEBAAACAQA=="}
//! ```
//!
//! `start` is the time of the first sample; sample `k` is at `start + k / rate_hz`. Blocks
//! of a stream follow one another without gap or overlap (the windowing,
//! [`crate::pipeline::accel`], checks it). `units` name what each channel measures
//! ([`crate::core::oma::UNITS`]: accelerations, velocities or displacements, mixed freely).

use base64::Engine;
use base64::engine::general_purpose::STANDARD as BASE64;
use chrono::{DateTime, Utc};
use serde::{Deserialize, Serialize};

use super::modal_set::Rejection;
use super::wire::{Message, Schema, time};
use crate::core::oma::{Quantity, parse_unit};

/// The most values (samples × channels) one block may carry: 32 MiB decoded, a minute of
/// 64 channels at 1 kHz. A stream sends blocks of a second or less.
pub const MAX_BLOCK_VALUES: usize = 1 << 22;

/// One block on the wire (module docs).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Accel {
    pub schema: Schema<Accel>,
    pub structure: String,
    /// Time of the first sample.
    #[serde(with = "time")]
    pub start: DateTime<Utc>,
    pub rate_hz: f64,
    pub channels: Vec<String>,
    /// One per channel.
    pub units: Vec<String>,
    /// `f32le` or `f64le`.
    pub encoding: String,
    /// Samples per channel.
    pub samples: usize,
    /// The values, base64 (module docs).
    pub data: String,
}

impl Message for Accel {
    const SCHEMA: &'static str = "boltwatch.accel.v1";
}

/// A block, decoded and checked.
#[derive(Debug, Clone, PartialEq)]
pub struct AccelBlock {
    pub structure: String,
    pub start: DateTime<Utc>,
    pub rate_hz: f64,
    pub channels: Vec<String>,
    pub quantities: Vec<Quantity>,
    /// Row-major `samples × channels`, in SI units.
    pub values: Vec<f64>,
}

impl AccelBlock {
    /// Samples per channel.
    pub fn len(&self) -> usize {
        self.values.len() / self.channels.len().max(1)
    }

    pub fn is_empty(&self) -> bool {
        self.values.is_empty()
    }
}

impl Accel {
    /// A block of `values` (row-major `samples × channels`, each channel in its `units`),
    /// encoded as `f32le` (module docs).
    pub fn encode(
        structure: &str,
        start: DateTime<Utc>,
        rate_hz: f64,
        channels: &[String],
        units: &[String],
        values: &[f64],
    ) -> Self {
        let mut bytes = Vec::with_capacity(4 * values.len());
        for v in values {
            bytes.extend_from_slice(&(*v as f32).to_le_bytes());
        }
        Self {
            schema: Schema::new(),
            structure: structure.to_string(),
            start,
            rate_hz,
            channels: channels.to_vec(),
            units: units.to_vec(),
            encoding: "f32le".into(),
            samples: values.len() / channels.len().max(1),
            data: BASE64.encode(&bytes),
        }
    }
}

fn reject(field: &str, reason: impl Into<String>) -> Rejection {
    Rejection {
        field: field.to_string(),
        reason: reason.into(),
    }
}

/// Decodes and checks one payload: every rejection names the field and says why.
///
/// The checks run in wire-contract order: the rate, the channels, the units, the encoding,
/// the sample count, then the data.
pub fn parse_accel(payload: &[u8]) -> Result<AccelBlock, Rejection> {
    let a: Accel = serde_json::from_slice(payload)
        .map_err(|e| reject("payload", format!("not a boltwatch.accel.v1 block: {e}")))?;
    if !(a.rate_hz.is_finite() && a.rate_hz > 0.0) {
        return Err(reject(
            "rate_hz",
            format!("{} is not a rate (finite, > 0)", a.rate_hz),
        ));
    }
    check_channels(&a.channels)?;
    let (quantities, factors) = parse_units(&a.units, a.channels.len())?;
    let width = encoding_width(&a.encoding)?;
    let count = value_count(a.samples, a.channels.len())?;
    let values = decode_values(&a, width, count, &factors)?;
    Ok(AccelBlock {
        structure: a.structure,
        start: a.start,
        rate_hz: a.rate_hz,
        channels: a.channels,
        quantities,
        values,
    })
}

/// Refuses a block without channels, and the first channel that is unnamed or named twice.
fn check_channels(channels: &[String]) -> Result<(), Rejection> {
    if channels.is_empty() {
        return Err(reject("channels", "no channels"));
    }
    let mut seen = std::collections::HashSet::new();
    if let Some((i, c)) = channels
        .iter()
        .enumerate()
        .find(|(_, c)| c.is_empty() || !seen.insert(c.as_str()))
    {
        return Err(reject(
            &format!("channels[{i}]"),
            format!("`{c}` is empty or named twice"),
        ));
    }
    Ok(())
}

/// One unit per channel (`r` of them): each channel's quantity and its factor to SI.
fn parse_units(units: &[String], r: usize) -> Result<(Vec<Quantity>, Vec<f64>), Rejection> {
    if units.len() != r {
        return Err(reject(
            "units",
            format!("{} units for {r} channels", units.len()),
        ));
    }
    let mut quantities = Vec::with_capacity(r);
    let mut factors = Vec::with_capacity(r);
    for (i, u) in units.iter().enumerate() {
        let (q, f) = parse_unit(u).map_err(|e| reject(&format!("units[{i}]"), e))?;
        quantities.push(q);
        factors.push(f);
    }
    Ok((quantities, factors))
}

/// Bytes per value of `encoding`: 4 for `f32le`, 8 for `f64le`.
fn encoding_width(encoding: &str) -> Result<usize, Rejection> {
    match encoding {
        "f32le" => Ok(4),
        "f64le" => Ok(8),
        e => Err(reject(
            "encoding",
            format!("`{e}` is not an encoding (f32le, f64le)"),
        )),
    }
}

/// The values (`samples` × `r` channels) a block carries: at least one sample, at most
/// [`MAX_BLOCK_VALUES`].
fn value_count(samples: usize, r: usize) -> Result<usize, Rejection> {
    if samples == 0 {
        return Err(reject("samples", "no samples"));
    }
    let count = samples.checked_mul(r).filter(|&n| n <= MAX_BLOCK_VALUES);
    let Some(count) = count else {
        return Err(reject(
            "samples",
            format!(
                "{samples} samples of {r} channels exceed the {MAX_BLOCK_VALUES} values a block may carry"
            ),
        ));
    };
    Ok(count)
}

/// The `count` values of `data`, `width` bytes each, scaled to SI by their channel's factor:
/// base64 of exactly that many bytes, every value finite.
fn decode_values(
    a: &Accel,
    width: usize,
    count: usize,
    factors: &[f64],
) -> Result<Vec<f64>, Rejection> {
    let r = a.channels.len();
    let bytes = BASE64
        .decode(a.data.as_bytes())
        .map_err(|e| reject("data", format!("not base64: {e}")))?;
    if bytes.len() != count * width {
        return Err(reject(
            "data",
            format!(
                "{} bytes, {} samples × {r} channels of {} need {}",
                bytes.len(),
                a.samples,
                a.encoding,
                count * width
            ),
        ));
    }
    let mut values = Vec::with_capacity(count);
    for (k, chunk) in bytes.chunks_exact(width).enumerate() {
        let v = if width == 4 {
            f32::from_le_bytes(chunk.try_into().expect("4 bytes")) as f64
        } else {
            f64::from_le_bytes(chunk.try_into().expect("8 bytes"))
        };
        if !v.is_finite() {
            return Err(reject(
                "data",
                format!("sample {} of channel `{}` is {v}", k / r, a.channels[k % r]),
            ));
        }
        values.push(v * factors[k % r]);
    }
    Ok(values)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn block() -> Accel {
        let t = DateTime::parse_from_rfc3339("2026-03-01T00:00:00Z")
            .unwrap()
            .with_timezone(&Utc);
        Accel::encode(
            "frame",
            t,
            1000.0,
            &["a".into(), "b".into()],
            &["m/s^2".into(), "mm/s".into()],
            &[1.0, 2.0, 3.0, 4.0],
        )
    }

    /// Encoded and decoded: values (f32-exact here) in SI, the quantity of each channel.
    #[test]
    fn a_block_reads_back() {
        let bytes = super::super::to_wire(&block());
        let b = parse_accel(&bytes).unwrap();
        assert_eq!(b.len(), 2);
        assert_eq!(b.values, vec![1.0, 2e-3, 3.0, 4e-3]);
        assert_eq!(
            b.quantities,
            vec![Quantity::Acceleration, Quantity::Velocity]
        );
        // The module docs' example is this block.
        assert!(
            String::from_utf8(bytes)
                .unwrap()
                .contains("AACAPwAAAEAAAEBAAACAQA==")
        );
    }

    /// Each defect is named by its field.
    #[test]
    fn defects_name_their_field() {
        let field = |edit: &dyn Fn(&mut Accel)| {
            let mut a = block();
            edit(&mut a);
            parse_accel(&super::super::to_wire(&a)).unwrap_err().field
        };
        assert_eq!(field(&|a| a.rate_hz = 0.0), "rate_hz");
        assert_eq!(field(&|a| a.channels[1] = "a".into()), "channels[1]");
        assert_eq!(field(&|a| a.units.pop().map(|_| ()).unwrap()), "units");
        assert_eq!(field(&|a| a.units[1] = "furlong".into()), "units[1]");
        assert_eq!(field(&|a| a.encoding = "i16".into()), "encoding");
        assert_eq!(field(&|a| a.samples = 3), "data");
        assert_eq!(field(&|a| a.samples = usize::MAX / 2), "samples");
        assert_eq!(field(&|a| a.data = "not base64!".into()), "data");
        assert_eq!(
            field(&|a| a.data = BASE64.encode([0u8, 0, 0xc0, 0x7f].repeat(4))),
            "data"
        );
        let mut v = serde_json::to_value(block()).unwrap();
        v["extra"] = 1.into();
        assert_eq!(
            parse_accel(v.to_string().as_bytes()).unwrap_err().field,
            "payload"
        );
    }
}
