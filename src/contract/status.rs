//! `boltwatch.status.v1`: the reply to a `boltwatch/<structure>/status` query, the daemon's
//! latest state of one structure.

use chrono::{DateTime, Utc};
use serde::{Deserialize, Serialize};

use super::alert::Alert;
use super::stiffness::Estimate;
use super::wire::{Message, Schema, time};

/// One status reply (module docs).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Status {
    pub schema: Schema<Status>,
    pub structure: String,
    /// When the reply was made.
    #[serde(with = "time")]
    pub time: DateTime<Utc>,
    #[serde(with = "time")]
    pub started: DateTime<Utc>,
    pub uptime_s: f64,
    pub queue: QueueStatus,
    pub sets: SetCounts,
    /// Mean time of an update (ms), once there is one.
    pub update_mean_ms: Option<f64>,
    /// Time of the last accepted set.
    pub last_set_time: Option<String>,
    pub last_estimate: Option<Estimate>,
    /// The last alert per (kind, connection); a `cleared` one stays until replaced.
    pub alerts: Vec<Alert>,
    pub crosschecks: CrosscheckCounts,
    pub publish_errors: u64,
    /// The write-ahead log's group commits.
    #[serde(default)]
    pub wal: WalStatus,
    /// The log file being written.
    pub log_file: Option<String>,
    /// When the state was last checkpointed.
    pub last_checkpoint: Option<String>,
    /// A fleet daemon's ownership of the structure (absent outside a fleet).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ownership: Option<Ownership>,
    /// Per connection whose alerts the commissioning left off, what would turn them on
    /// (absent when every connection's alerts are on, or before the advice is computed).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub advice: Vec<Advice>,
    /// Why no advice could be computed for connections with alerts off.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub advice_unavailable: Option<String>,
}

/// What would turn on the loosening alerts of a connection that commissioning left off:
/// the planner's prediction for the installed channels and modes, scaled to the σ the
/// commissioning sets had, and the same prediction with sensors added or more modes.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Advice {
    pub connection: String,
    /// Mean per-set σ over the commissioning sets, relative to the baseline.
    pub measured_std: f64,
    /// The per-set relative σ predicted for the installed channels and modes.
    pub predicted_std: f64,
    /// The channels and modes the commissioning sets had.
    pub channels: usize,
    pub modes: usize,
    /// Candidate places to add sensors at, first first, after which the alerts come on.
    pub sensors: Option<AdviceSensors>,
    /// The lowest modes to identify instead, with the installed channels.
    pub more_modes: Option<AdviceModes>,
    /// The same in one sentence.
    pub summary: String,
}

/// Sensors that would turn a connection's alerts on, and its per-set σ then.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AdviceSensors {
    pub add: Vec<String>,
    pub std: f64,
}

/// The number of lowest modes that would turn a connection's alerts on, and its σ then.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AdviceModes {
    pub modes: usize,
    pub std: f64,
}

/// Which fleet member tracks the structure, since when, in which epoch.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Ownership {
    pub group: String,
    pub owner: String,
    pub epoch: u64,
    /// When this member took the structure over (RFC 3339).
    pub since: String,
    /// Outputs and state writes the fence held back (the epoch had moved on, or could
    /// not be confirmed).
    pub held: u64,
}

impl Message for Status {
    const SCHEMA: &'static str = "boltwatch.status.v1";
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct QueueStatus {
    pub depth: u64,
    pub capacity: usize,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SetCounts {
    /// Received from Zenoh (queued or dropped).
    pub received: u64,
    /// Dropped at a full queue.
    pub dropped: u64,
    pub accepted: u64,
    pub rejected: u64,
    /// Accepted, but the update did not converge.
    pub unconverged: u64,
    pub cold_starts: u64,
    /// Skipped as already handled (a re-delivery after a restart), neither accepted nor
    /// rejected.
    #[serde(default)]
    pub duplicates: u64,
    /// Handled again at start from the write-ahead log (logged before a crash, not yet
    /// handled).
    #[serde(default)]
    pub replayed: u64,
    /// Rejected because tracking them failed (an error or a panic), included in `rejected`.
    #[serde(default)]
    pub failed: u64,
}

/// Group commits of the write-ahead log: `syncs` fsyncs made `sets` sets durable in
/// `sync_ms` milliseconds in all; `redeliveries` inputs were not logged because the same
/// bytes had been handled (or logged in the same batch) already.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct WalStatus {
    pub syncs: u64,
    pub sets: u64,
    pub sync_ms: f64,
    #[serde(default)]
    pub redeliveries: u64,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CrosscheckCounts {
    pub published: u64,
    /// Not started because the previous one was still running.
    pub skipped: u64,
    /// Why the structure's cross-checks do not fit the memory budget (`daemon.memory_mib`),
    /// found at start; absent when they fit. Each cross-check is checked again when due, and
    /// one that does not fit is published with `ok: false` and the reason.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub unavailable: Option<String>,
}
