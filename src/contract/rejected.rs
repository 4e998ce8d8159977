//! `boltwatch.rejected.v1` (DESIGN §3.3): an input that was not used, with the reason and
//! the field, and the start of its raw payload; or a count of sets dropped at a full queue.

use chrono::{DateTime, Utc};
use serde::{Deserialize, Serialize};

use super::wire::{Message, Schema, time};

/// Raw payload bytes kept in a rejection.
pub const REJECTED_PAYLOAD_LIMIT: usize = 4096;

/// One rejection (module docs).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Rejected {
    pub schema: Schema<Rejected>,
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
        let text = String::from_utf8_lossy(payload);
        let mut cut = text.len().min(REJECTED_PAYLOAD_LIMIT);
        while !text.is_char_boundary(cut) {
            cut -= 1;
        }
        Self {
            schema: Schema::new(),
            structure: structure.to_string(),
            time: received,
            received,
            reason: reason.to_string(),
            field: field.to_string(),
            payload: text[..cut].to_string(),
            payload_bytes: payload.len(),
            truncated: cut < text.len(),
            dropped: None,
        }
    }

    /// `n` sets dropped at a full queue, reported at `now`.
    pub fn dropped(structure: &str, now: DateTime<Utc>, n: u64, reason: String) -> Self {
        Self {
            schema: Schema::new(),
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
