//! `boltwatch.rejected.v1` (DESIGN §3.3): an input that was not used, with the reason and
//! the field, and the start of its raw payload; or a count of sets dropped at a full queue.

use chrono::{DateTime, Utc};
use serde::{Deserialize, Serialize};

use super::wire::{Message, Schema, digest, output_id, time};

/// Raw payload bytes kept in a rejection.
pub const REJECTED_PAYLOAD_LIMIT: usize = 4096;

/// One rejection (module docs).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Rejected {
    pub schema: Schema<Rejected>,
    /// Stable id ([`super::output_id`]); absent (empty) in messages written before ids.
    #[serde(default)]
    pub id: String,
    pub structure: String,
    /// The log time of the message: when the input was received.
    #[serde(with = "time")]
    pub time: DateTime<Utc>,
    #[serde(with = "time")]
    pub received: DateTime<Utc>,
    pub reason: String,
    /// The offending field (`modes[2].shape`, …; empty when no field is to blame).
    pub field: String,
    /// The payload as text, cut at [`REJECTED_PAYLOAD_LIMIT`] bytes.
    pub payload: String,
    pub payload_bytes: usize,
    pub truncated: bool,
    /// Sets dropped unprocessed at a full queue (a queue report, not one payload).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dropped: Option<u64>,
}

impl Message for Rejected {
    const SCHEMA: &'static str = "boltwatch.rejected.v1";
}

impl Rejected {
    /// `payload`, received at `received`, rejected for `reason` in `field`.
    pub fn payload(
        structure: &str,
        received: DateTime<Utc>,
        field: &str,
        reason: &str,
        payload: &[u8],
    ) -> Self {
        Self::cut(
            structure,
            received,
            field,
            reason,
            payload,
            payload.len(),
            digest(payload),
        )
    }

    /// A payload of `size` bytes (with digest `digest`) rejected for `reason` in `field`,
    /// of which only `head` was kept (an oversized payload is never copied whole).
    pub fn cut(
        structure: &str,
        received: DateTime<Utc>,
        field: &str,
        reason: &str,
        head: &[u8],
        size: usize,
        digest: u128,
    ) -> Self {
        let head = &head[..head.len().min(REJECTED_PAYLOAD_LIMIT)];
        let text = String::from_utf8_lossy(head);
        let mut cut = text.len().min(REJECTED_PAYLOAD_LIMIT);
        while !text.is_char_boundary(cut) {
            cut -= 1;
        }
        Self {
            schema: Schema::new(),
            id: output_id(
                structure,
                received,
                "rejected",
                format_args!("{digest:032x}"),
            ),
            structure: structure.to_string(),
            time: received,
            received,
            reason: super::modal_set::capped(reason, super::modal_set::REASON_LIMIT),
            field: super::modal_set::capped(field, super::modal_set::FIELD_LIMIT),
            payload: text[..cut].to_string(),
            payload_bytes: size,
            truncated: head.len() < size || cut < text.len(),
            dropped: None,
        }
    }

    /// `n` sets dropped at a full queue, reported at `now`; `total` since start.
    pub fn dropped(
        structure: &str,
        now: DateTime<Utc>,
        n: u64,
        total: u64,
        reason: String,
    ) -> Self {
        Self {
            schema: Schema::new(),
            id: output_id(structure, now, "dropped", total),
            structure: structure.to_string(),
            time: now,
            received: now,
            reason,
            field: String::new(),
            payload: String::new(),
            payload_bytes: 0,
            truncated: false,
            dropped: Some(n),
        }
    }
}
