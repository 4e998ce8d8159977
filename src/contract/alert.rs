//! `boltwatch.alert.v1` (DESIGN §3.3, §7): a change of alert level, of a connection's
//! loosening or of the model class's adequacy, with the diagnosis verdict that follows a
//! model-inadequacy warning.

use chrono::{DateTime, Utc};
use serde::{Deserialize, Serialize};

use super::wire::{Message, Schema, time};

/// One alert (module docs).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Alert {
    pub schema: Schema<Alert>,
    /// Stable id ([`super::output_id`]); absent (empty) in messages written before ids.
    #[serde(default)]
    pub id: String,
    pub structure: String,
    /// Time of the modal set that raised it.
    #[serde(with = "time")]
    pub time: DateTime<Utc>,
    /// The connection parameter (`null` for the model).
    pub connection: Option<String>,
    pub kind: AlertKind,
    pub level: AlertLevel,
    /// Confidence of a loosening level (`null` for the model).
    pub confidence: Option<f64>,
    pub message: String,
    #[serde(flatten)]
    pub detail: AlertDetail,
}

impl Message for Alert {
    const SCHEMA: &'static str = "boltwatch.alert.v1";
}

/// What an alert is about.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum AlertKind {
    Loosening,
    ModelInadequate,
}

impl AlertKind {
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Loosening => "loosening",
            Self::ModelInadequate => "model-inadequate",
        }
    }
}

/// The level an alert reports.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum AlertLevel {
    Warning,
    Alarm,
    /// Back to normal.
    Cleared,
}

impl AlertLevel {
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Warning => "warning",
            Self::Alarm => "alarm",
            Self::Cleared => "cleared",
        }
    }

    /// How severe: 0 when none is active (`None` or cleared), 1 warning, 2 alarm. The
    /// order the console, the report and the metrics sort connections by.
    pub fn severity(level: Option<Self>) -> u8 {
        match level {
            Some(Self::Warning) => 1,
            Some(Self::Alarm) => 2,
            Some(Self::Cleared) | None => 0,
        }
    }
}

/// The fields of each kind of alert.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum AlertDetail {
    /// A connection's filtered stiffness against its baseline.
    Loosening {
        /// Filtered θ and its 95 % band.
        theta: f64,
        lower95: f64,
        upper95: f64,
        baseline: f64,
        /// (baseline − filtered θ)/baseline.
        drop: f64,
        /// Raised while the model is flagged inadequate.
        model_inadequate: bool,
        /// With normalisation: the θ expected under the set's conditions (`drop` is then
        /// the loss against it) and those conditions.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        expected: Option<f64>,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        conditions: Option<String>,
    },
    /// ε against its χ² bound; after a warning, the diagnosis verdict.
    Inadequacy {
        epsilon: f64,
        epsilon_bound: f64,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        diagnosis: Option<Verdict>,
    },
}

/// The verdict of the discrepancy workflow on the set that raised a model-inadequacy
/// warning.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum Verdict {
    Found {
        named: Vec<NamedEffect>,
        epsilon_before: f64,
        epsilon_after: f64,
        /// Candidates screened, and the likelihood-ratio threshold of the test.
        candidates: usize,
        threshold: f64,
    },
    Failed {
        error: String,
    },
}

/// An effect the diagnosis named.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct NamedEffect {
    pub effect: String,
    pub location: String,
    pub value: f64,
    pub std: Option<f64>,
    pub unit: String,
    pub likelihood_ratio: f64,
    /// `effect@location` of the candidates the data cannot tell from it.
    pub indistinguishable_from: Vec<String>,
}
