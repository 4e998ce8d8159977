//! Wire contracts (DESIGN §3): every JSON message boltwatch accepts or emits, as a serde
//! type with its schema name and version. The modal set in ([`modal_set`], validated
//! strictly); out, per structure, the estimate ([`Estimate`], `stiffness`), alerts
//! ([`Alert`], `alerts`), cross-checks ([`Crosscheck`], `crosscheck`), rejections
//! ([`Rejected`], `rejected`), the status reply ([`Status`], `status`), the diagnosis
//! document ([`diagnosis`]) and the checkpoint ([`Checkpoint`]). [`wire`] states the
//! conventions they share; `src/io/schemas` holds their JSON Schemas, tested against these
//! types.
//!
//! Schema version: every message is at v1 (`boltwatch.<name>.v1`); the v1 bytes are pinned
//! by digests of every bundled replay and command output (`tests/suite/golden.rs`).

pub mod accel;
pub mod alert;
pub mod checkpoint;
pub mod crosscheck;
pub mod diagnosis;
pub mod environment;
mod fields;
pub mod modal_set;
mod nonfinite;
pub mod rejected;
pub mod status;
pub mod stiffness;
pub mod sweep;
pub mod update;
pub mod wire;

use chrono::{DateTime, Utc};

pub use alert::{Alert, AlertDetail, AlertKind, AlertLevel, Verdict};
pub use checkpoint::WalPosition;
pub use checkpoint::{Checkpoint, EigenBlock, FleetPosition};
pub use crosscheck::Crosscheck;
pub use rejected::{REJECTED_PAYLOAD_LIMIT, Rejected};
pub use status::{Advice, AdviceModes, AdviceSensors, Ownership, Status};
pub use stiffness::{Estimate, ModeComparison, Termination};
pub use wire::{Message, Schema, digest, finite, output_id, rfc3339, to_wire};

/// One output of a structure's tracker, on `boltwatch/<structure>/<topic>`.
#[derive(Debug, Clone, PartialEq)]
pub enum Output {
    Estimate(Box<Estimate>),
    Alert(Box<Alert>),
    Crosscheck(Box<Crosscheck>),
    Rejected(Box<Rejected>),
    /// A modal set identified from raw data ([`crate::pipeline::accel`]), published for
    /// others on `modal` before it is tracked.
    Modal(Box<modal_set::ModalSet>),
}

impl Output {
    /// Topic suffixes of the outputs, in the order output files declare their channels.
    pub const TOPICS: [&'static str; 4] = ["stiffness", "alerts", "crosscheck", "rejected"];

    /// The topic suffix.
    pub fn topic(&self) -> &'static str {
        match self {
            Self::Estimate(_) => "stiffness",
            Self::Alert(_) => "alerts",
            Self::Crosscheck(_) => "crosscheck",
            Self::Rejected(_) => "rejected",
            Self::Modal(_) => "modal",
        }
    }

    /// The schema name.
    pub fn schema(&self) -> &'static str {
        match self {
            Self::Estimate(_) => Estimate::SCHEMA,
            Self::Alert(_) => Alert::SCHEMA,
            Self::Crosscheck(_) => Crosscheck::SCHEMA,
            Self::Rejected(_) => Rejected::SCHEMA,
            Self::Modal(_) => modal_set::MODAL_SET_SCHEMA,
        }
    }

    /// The time of the modal set it answers (of a rejection: when it was received): the
    /// output's log time.
    pub fn time(&self) -> DateTime<Utc> {
        match self {
            Self::Estimate(m) => m.time,
            Self::Alert(m) => m.time,
            Self::Crosscheck(m) => m.time,
            Self::Rejected(m) => m.time,
            Self::Modal(m) => m.time,
        }
    }

    pub fn structure(&self) -> &str {
        match self {
            Self::Estimate(m) => &m.structure,
            Self::Alert(m) => &m.structure,
            Self::Crosscheck(m) => &m.structure,
            Self::Rejected(m) => &m.structure,
            Self::Modal(m) => &m.structure,
        }
    }

    /// The wire bytes.
    pub fn to_wire(&self) -> Vec<u8> {
        match self {
            Self::Estimate(m) => to_wire(m),
            Self::Alert(m) => to_wire(m),
            Self::Crosscheck(m) => to_wire(m),
            Self::Rejected(m) => to_wire(m),
            Self::Modal(m) => serde_json::to_vec(&m.to_json()).expect("a Value serializes"),
        }
    }

    /// Reads an output from its topic suffix and wire bytes.
    pub fn from_wire(topic: &str, bytes: &[u8]) -> Result<Self, String> {
        let bad = |e: serde_json::Error| format!("{topic}: {e}");
        Ok(match topic {
            "stiffness" => Self::Estimate(serde_json::from_slice(bytes).map_err(bad)?),
            "alerts" => Self::Alert(serde_json::from_slice(bytes).map_err(bad)?),
            "crosscheck" => Self::Crosscheck(serde_json::from_slice(bytes).map_err(bad)?),
            "rejected" => Self::Rejected(serde_json::from_slice(bytes).map_err(bad)?),
            "modal" => {
                let v: serde_json::Value = serde_json::from_slice(bytes).map_err(bad)?;
                let structure = v["structure"].as_str().unwrap_or_default();
                let channels: Vec<String> = v["channels"]
                    .as_array()
                    .map(|a| {
                        a.iter()
                            .filter_map(|c| c.as_str().map(String::from))
                            .collect()
                    })
                    .unwrap_or_default();
                let ctx = modal_set::ValidationContext {
                    structures: &[structure],
                    model_channels: &channels,
                    last_time: None,
                    allow_equal_time: true,
                    max_future: None,
                };
                let set = modal_set::parse_modal_set(bytes, &ctx)
                    .map_err(|r| format!("{topic}: {}: {}", r.field, r.reason))?;
                Self::Modal(Box::new(set))
            }
            _ => return Err(format!("`{topic}` is not an output topic")),
        })
    }

    /// Logs the output: a rejection as a warning, an alert as information.
    pub fn log(&self) {
        match self {
            Self::Rejected(r) => tracing::warn!(
                structure = r.structure,
                field = r.field,
                "rejected set: {}",
                r.reason
            ),
            Self::Alert(a) => tracing::info!(structure = a.structure, "alert: {}", a.message),
            _ => {}
        }
    }
}
