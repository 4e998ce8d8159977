//! The wire conventions every message follows (DESIGN §3): a `schema` field naming the
//! message and its version, times in RFC 3339 with milliseconds and `Z`, non-finite numbers
//! as `null`, and the object keys of the v1 form in sorted order (how the first version,
//! built as `serde_json` maps, wrote them), whatever the field order of the Rust types.

use std::fmt;
use std::marker::PhantomData;

use chrono::{DateTime, SecondsFormat, Utc};
use serde::de::{self, Deserializer};
use serde::{Deserialize, Serialize, Serializer};

/// The times every output format holds: MCAP log times are unsigned and chrono's
/// nanosecond timestamps signed 64-bit nanoseconds since 1970, so the common range is
/// 1970-01-01T00:00:00Z to 2262-04-11T23:47:16.854775807Z.
pub const TIME_RANGE: &str = "1970-01-01T00:00:00Z to 2262-04-11T23:47:16Z";

/// Whether `t` is in [`TIME_RANGE`].
pub fn representable(t: DateTime<Utc>) -> bool {
    t.timestamp_nanos_opt().is_some_and(|n| n >= 0)
}

/// A wire message: its schema name (with its version) and the topic suffix it goes out on.
pub trait Message {
    /// `boltwatch.<name>.v<version>`.
    const SCHEMA: &'static str;
}

/// The `schema` field of message `M`: writes `M::SCHEMA`, and a reader refuses any other
/// name (another message, or another version of this one).
pub struct Schema<M>(PhantomData<M>);

impl<M> Schema<M> {
    pub const fn new() -> Self {
        Self(PhantomData)
    }
}

impl<M> Default for Schema<M> {
    fn default() -> Self {
        Self::new()
    }
}

impl<M> Clone for Schema<M> {
    fn clone(&self) -> Self {
        *self
    }
}

impl<M> Copy for Schema<M> {}

impl<M> PartialEq for Schema<M> {
    fn eq(&self, _: &Self) -> bool {
        true
    }
}

impl<M: Message> fmt::Debug for Schema<M> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(M::SCHEMA)
    }
}

impl<M: Message> Serialize for Schema<M> {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(M::SCHEMA)
    }
}

impl<'de, M: Message> Deserialize<'de> for Schema<M> {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let name = String::deserialize(d)?;
        if name == M::SCHEMA {
            Ok(Self::new())
        } else {
            Err(de::Error::custom(format!(
                "schema is `{name}`, expected `{}`",
                M::SCHEMA
            )))
        }
    }
}

/// The bytes of a message on the wire (Zenoh payload, MCAP message): compact JSON, keys
/// sorted (module docs).
pub fn to_wire<T: Serialize>(message: &T) -> Vec<u8> {
    // Through a `Value`, whose maps are sorted: the v1 key order, independent of how the
    // types nest (`flatten`) or order their fields.
    let v = serde_json::to_value(message).expect("messages hold only strings, numbers and maps");
    serde_json::to_vec(&v).expect("a Value serializes")
}

/// RFC 3339 with milliseconds and `Z`.
pub fn rfc3339(t: DateTime<Utc>) -> String {
    t.to_rfc3339_opts(SecondsFormat::Millis, true)
}

/// The first 128 bits of the SHA-256 of `bytes`: the content digest of a payload (the
/// dedup of re-delivered sets; in hex, `{:032x}`, the ids of rejections).
pub fn digest(bytes: &[u8]) -> u128 {
    digest_parts([bytes])
}

/// [`digest`] of the concatenation of `parts` (a payload in several slices).
pub fn digest_parts<'a>(parts: impl IntoIterator<Item = &'a [u8]>) -> u128 {
    use sha2::Digest;
    let mut hasher = sha2::Sha256::new();
    for p in parts {
        hasher.update(p);
    }
    let d = hasher.finalize();
    u128::from_be_bytes(d[..16].try_into().expect("SHA-256 has 32 bytes"))
}

/// The stable id of an output: `<structure>/<time>/<kind>/<sequence>`, where `time` is the
/// time of the set it answers ([`rfc3339`]; for a rejection, the reception time), `kind`
/// says what it is (`stiffness`, `alert`, `diagnosis`, `crosscheck`, `rejected`, `dropped`)
/// and `sequence` tells apart the outputs of one kind for one set (the alerts of a set in
/// order; a rejection's payload digest; a queue report's running count). The same input
/// gives the same id, in a replay and after a restart, so a subscriber can deduplicate.
pub fn output_id(
    structure: &str,
    time: DateTime<Utc>,
    kind: &str,
    sequence: impl fmt::Display,
) -> String {
    format!("{structure}/{}/{kind}/{sequence}", rfc3339(time))
}

/// `null` for a non-finite number (JSON has none).
pub fn finite(v: f64) -> Option<f64> {
    v.is_finite().then_some(v)
}

/// Serde for a time as [`rfc3339`] (`#[serde(with = "time")]`); any RFC 3339 time reads.
pub mod time {
    use super::*;

    pub fn serialize<S: Serializer>(t: &DateTime<Utc>, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(&rfc3339(*t))
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<DateTime<Utc>, D::Error> {
        let text = String::deserialize(d)?;
        DateTime::parse_from_rfc3339(&text)
            .map(|t| t.with_timezone(&Utc))
            .map_err(|e| de::Error::custom(format!("time `{text}`: {e}")))
    }
}
