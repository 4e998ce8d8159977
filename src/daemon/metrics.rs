//! What the daemon shares between its threads about each structure (counters, the latest
//! state for `status` queries) and its Prometheus endpoint: `GET /metrics` on
//! `[metrics] listen`, served by axum. A `prometheus-client` collector reads the shared state
//! at scrape time and encodes it in the Prometheus text format (version 0.0.4).

pub(crate) mod state;

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use axum::extract::State;
use axum::http::{HeaderValue, StatusCode, header};
use axum::response::Response;
use prometheus_client::collector::Collector;
use prometheus_client::encoding::{DescriptorEncoder, EncodeMetric, prometheus_text};
use prometheus_client::metrics::MetricType;
use prometheus_client::metrics::counter::ConstCounter;
use prometheus_client::metrics::gauge::ConstGauge;
use prometheus_client::registry::Registry;

use crate::contract::status::{CrosscheckCounts, QueueStatus, SetCounts, WalStatus};
use crate::contract::{self, Alert, AlertKind, Estimate, Output, Schema};

/// Upper bounds (s) of the update-latency histogram buckets.
pub const LATENCY_BUCKETS: [f64; 10] = [
    0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.25, 1.0,
];

/// The update-latency histogram. prometheus-client does not expose its histogram's count
/// and sum, so the two the status reply needs are kept beside it.
#[derive(Debug)]
pub struct Histogram {
    buckets: prometheus_client::metrics::histogram::Histogram,
    count: AtomicU64,
    sum_ns: AtomicU64,
}

impl Default for Histogram {
    fn default() -> Self {
        Self {
            buckets: prometheus_client::metrics::histogram::Histogram::new(LATENCY_BUCKETS),
            count: AtomicU64::new(0),
            sum_ns: AtomicU64::new(0),
        }
    }
}

impl Histogram {
    pub fn observe(&self, d: Duration) {
        self.buckets.observe(d.as_secs_f64());
        self.count.fetch_add(1, Ordering::Relaxed);
        self.sum_ns
            .fetch_add(d.as_nanos() as u64, Ordering::Relaxed);
    }

    /// Mean of the observations (ms), `None` before the first.
    fn mean_ms(&self) -> Option<f64> {
        let n = self.count.load(Ordering::Relaxed);
        (n > 0).then(|| self.sum_ns.load(Ordering::Relaxed) as f64 * 1e-6 / n as f64)
    }
}

/// The state a worker publishes for `status` queries and metrics.
#[derive(Debug, Default, Clone)]
pub struct Status {
    pub accepted: u64,
    pub rejected: u64,
    pub unconverged: u64,
    pub cold_starts: u64,
    pub last_set_time: Option<String>,
    /// The last estimate published.
    pub last_estimate: Option<Estimate>,
    /// The last alert per (kind, connection); a `cleared` one stays until replaced.
    pub alerts: BTreeMap<(AlertKind, Option<String>), Alert>,
    pub crosschecks: u64,
    /// The last cross-check published.
    pub last_crosscheck: Option<contract::Crosscheck>,
    /// Cross-checks not started because the previous one was still running.
    pub crosschecks_skipped: u64,
    /// Why this structure's cross-checks do not fit the memory budget, found at start.
    pub crosscheck_unavailable: Option<String>,
    pub publish_errors: u64,
    pub log_file: Option<String>,
    pub last_checkpoint: Option<String>,
    pub duplicates: u64,
    pub replayed: u64,
    pub failed: u64,
    pub wal: WalStatus,
    /// A fleet member's ownership of the structure.
    pub ownership: Option<contract::Ownership>,
    /// What would turn on the alerts commissioning left off ([`crate::daemon::advice`]).
    pub advice: Vec<contract::Advice>,
    pub advice_unavailable: Option<String>,
}

impl Status {
    /// Notes an output that was published.
    pub fn note(&mut self, output: &Output) {
        match output {
            Output::Estimate(e) => self.last_estimate = Some((**e).clone()),
            Output::Alert(a) => {
                self.alerts
                    .insert((a.kind, a.connection.clone()), (**a).clone());
            }
            Output::Crosscheck(c) => {
                self.crosschecks += 1;
                self.last_crosscheck = Some((**c).clone());
            }
            Output::Rejected(_) | Output::Modal(_) => {}
        }
    }
}

/// One structure's shared counters and status.
#[derive(Debug)]
pub struct Shared {
    pub structure: String,
    pub queue_capacity: usize,
    /// The queue's bound in payload bytes.
    pub queue_bytes: u64,
    /// Payloads larger than this are rejected unread.
    pub max_payload: usize,
    /// When the tracking loop last went round (ms since `started`), for the watchdog.
    pub heartbeat: AtomicU64,
    pub started: chrono::DateTime<chrono::Utc>,
    /// Sets received from Zenoh (queued or dropped).
    pub received: AtomicU64,
    /// When the last set was received (Unix ms; 0: none yet).
    pub last_received_ms: AtomicU64,
    /// Sets dropped at a full queue.
    pub dropped: AtomicU64,
    /// Sets waiting in the queue.
    pub depth: AtomicU64,
    /// Bytes of the payloads waiting in the queue.
    pub queued_bytes: AtomicU64,
    /// Sets a publisher sent that never arrived and could not be recovered from its cache.
    pub missed: AtomicU64,
    pub latency: Histogram,
    pub status: Mutex<Status>,
    /// The number of outputs noted so far, watched by the console's live pages.
    pub changed: tokio::sync::watch::Sender<u64>,
    /// The structure's model file and model, once its lane has loaded them (the console
    /// draws the structure from them).
    pub model: std::sync::OnceLock<Arc<StructureModel>>,
}

/// A structure's model file (absent for imported matrices) and its model.
pub type StructureModel = (
    Option<crate::core::model::spec::ModelSpec>,
    crate::core::model::Model,
);

impl Shared {
    /// Takes an input the worker took off the queue off the queue's depth and bytes.
    pub fn dequeued(&self, input: &super::worker::Input) {
        if input.counted() {
            self.depth.fetch_sub(1, Ordering::Relaxed);
            self.queued_bytes
                .fetch_sub(input.queued_bytes(), Ordering::Relaxed);
        }
    }

    pub fn new(
        structure: &str,
        queue_capacity: usize,
        queue_bytes: u64,
        max_payload: usize,
    ) -> Arc<Self> {
        Arc::new(Self {
            structure: structure.to_string(),
            queue_capacity,
            queue_bytes,
            max_payload,
            heartbeat: AtomicU64::new(0),
            started: chrono::Utc::now(),
            received: AtomicU64::new(0),
            last_received_ms: AtomicU64::new(0),
            dropped: AtomicU64::new(0),
            depth: AtomicU64::new(0),
            queued_bytes: AtomicU64::new(0),
            missed: AtomicU64::new(0),
            latency: Histogram::default(),
            status: Mutex::new(Status::default()),
            changed: tokio::sync::watch::Sender::new(0),
            model: std::sync::OnceLock::new(),
        })
    }

    /// Notes an output that was published, and tells the console's live pages.
    pub fn noted(&self, output: &Output) {
        self.with_status(|st| st.note(output));
        self.changed.send_modify(|n| *n += 1);
    }

    /// Notes that the tracking loop is alive.
    pub fn beat(&self) {
        let ms = (chrono::Utc::now() - self.started)
            .num_milliseconds()
            .max(0) as u64;
        self.heartbeat.store(ms, Ordering::Relaxed);
    }

    /// How long ago the tracking loop last went round.
    pub fn since_beat(&self) -> Duration {
        let now = (chrono::Utc::now() - self.started)
            .num_milliseconds()
            .max(0) as u64;
        Duration::from_millis(now.saturating_sub(self.heartbeat.load(Ordering::Relaxed)))
    }

    pub(crate) fn status(&self) -> Status {
        self.status
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .clone()
    }

    /// Changes the status under its lock.
    pub fn with_status(&self, f: impl FnOnce(&mut Status)) {
        let mut st = self.status.lock().unwrap_or_else(|p| p.into_inner());
        f(&mut st);
    }

    /// The reply to a `boltwatch/<structure>/status` query.
    pub fn status_reply(&self) -> contract::Status {
        let st = self.status();
        let now = chrono::Utc::now();
        contract::Status {
            schema: Schema::new(),
            structure: self.structure.clone(),
            time: now,
            started: self.started,
            uptime_s: (now - self.started).num_milliseconds() as f64 * 1e-3,
            queue: QueueStatus {
                depth: self.depth.load(Ordering::Relaxed),
                capacity: self.queue_capacity,
            },
            sets: SetCounts {
                received: self.received.load(Ordering::Relaxed),
                dropped: self.dropped.load(Ordering::Relaxed),
                accepted: st.accepted,
                rejected: st.rejected,
                unconverged: st.unconverged,
                cold_starts: st.cold_starts,
                duplicates: st.duplicates,
                replayed: st.replayed,
                failed: st.failed,
            },
            update_mean_ms: self.latency.mean_ms(),
            last_set_time: st.last_set_time,
            last_estimate: st.last_estimate,
            alerts: st.alerts.into_values().collect(),
            crosschecks: CrosscheckCounts {
                published: st.crosschecks,
                skipped: st.crosschecks_skipped,
                unavailable: st.crosscheck_unavailable,
            },
            publish_errors: st.publish_errors,
            log_file: st.log_file,
            last_checkpoint: st.last_checkpoint,
            wal: st.wal,
            ownership: st.ownership,
            advice: st.advice,
            advice_unavailable: st.advice_unavailable,
        }
    }
}

/// Every structure's metrics, read from the shared state at each scrape. Counter names
/// leave out `_total`: the encoder appends it.
#[derive(Debug)]
struct Structures(Watched);

/// The structures the daemon watches now (a fleet member's change as ownership moves).
pub type Watched = Arc<std::sync::RwLock<Vec<Arc<Shared>>>>;

impl Collector for Structures {
    fn encode(&self, mut enc: DescriptorEncoder) -> std::fmt::Result {
        let now: Vec<Arc<Shared>> = self.0.read().map(|v| v.clone()).unwrap_or_default();
        let all: Vec<(&Shared, Status)> = now.iter().map(|s| (&**s, s.status())).collect();
        encode_counters(&mut enc, &all)?;
        encode_queue_depth(&mut enc, &all)?;
        encode_latency(&mut enc, &all)?;
        encode_theta(&mut enc, &all)?;
        state::encode(&mut enc, &all)?;
        encode_ownership(&mut enc, &all)
    }
}

/// How a counter's value is read from a structure's shared state and status.
type Getter = fn(&Shared, &Status) -> u64;

/// The counters: name, help and how each is read.
fn counters() -> [(&'static str, &'static str, Getter); 10] {
    [
        (
            "boltwatch_sets_received",
            "Modal sets received over Zenoh.",
            |s, _| s.received.load(Ordering::Relaxed),
        ),
        (
            "boltwatch_sets_processed",
            "Modal sets accepted and tracked.",
            |_, st| st.accepted,
        ),
        (
            "boltwatch_sets_rejected",
            "Modal sets rejected (published on rejected).",
            |_, st| st.rejected,
        ),
        (
            "boltwatch_sets_dropped",
            "Modal sets dropped at a full queue.",
            |s, _| s.dropped.load(Ordering::Relaxed),
        ),
        (
            "boltwatch_cold_starts",
            "Updates redone from the baseline.",
            |_, st| st.cold_starts,
        ),
        (
            "boltwatch_crosschecks_skipped",
            "Cross-checks skipped: the previous one was still running.",
            |_, st| st.crosschecks_skipped,
        ),
        (
            "boltwatch_sets_duplicate",
            "Modal sets skipped as already handled (re-delivered after a restart).",
            |_, st| st.duplicates,
        ),
        (
            "boltwatch_sets_replayed",
            "Modal sets handled again at start from the write-ahead log.",
            |_, st| st.replayed,
        ),
        (
            "boltwatch_sets_failed",
            "Modal sets rejected because tracking them failed (an error or a panic).",
            |_, st| st.failed,
        ),
        (
            "boltwatch_wal_syncs",
            "Group commits (fsyncs) of the write-ahead log.",
            |_, st| st.wal.syncs,
        ),
    ]
}

/// Each counter of [`counters`], one sample per structure.
fn encode_counters(enc: &mut DescriptorEncoder, all: &[(&Shared, Status)]) -> std::fmt::Result {
    for (name, help, get) in counters() {
        let mut family = enc.encode_descriptor(name, help, None, MetricType::Counter)?;
        for (s, st) in all {
            let labels = [("structure", s.structure.as_str())];
            ConstCounter::new(get(s, st)).encode(family.encode_family(&labels)?)?;
        }
    }
    Ok(())
}

/// The queue depth gauge, one sample per structure.
fn encode_queue_depth(enc: &mut DescriptorEncoder, all: &[(&Shared, Status)]) -> std::fmt::Result {
    let mut family = enc.encode_descriptor(
        "boltwatch_queue_depth",
        "Modal sets waiting in the queue.",
        None,
        MetricType::Gauge,
    )?;
    for (s, _) in all {
        let labels = [("structure", s.structure.as_str())];
        ConstGauge::new(s.depth.load(Ordering::Relaxed)).encode(family.encode_family(&labels)?)?;
    }
    Ok(())
}

/// The update-latency histogram, one per structure.
fn encode_latency(enc: &mut DescriptorEncoder, all: &[(&Shared, Status)]) -> std::fmt::Result {
    let mut family = enc.encode_descriptor(
        "boltwatch_update_seconds",
        "Time to process one modal set (validation, update, filters, alerts).",
        None,
        MetricType::Histogram,
    )?;
    for (s, _) in all {
        let labels = [("structure", s.structure.as_str())];
        s.latency.buckets.encode(family.encode_family(&labels)?)?;
    }
    Ok(())
}

/// The latest θ of each parameter, one gauge per structure and parameter.
fn encode_theta(enc: &mut DescriptorEncoder, all: &[(&Shared, Status)]) -> std::fmt::Result {
    let mut family = enc.encode_descriptor(
        "boltwatch_theta",
        "Latest estimate of each parameter θ (stiffness relative to nominal).",
        None,
        MetricType::Gauge,
    )?;
    for (s, st) in all {
        for p in st.last_estimate.iter().flat_map(|e| &e.parameters) {
            let labels = [("structure", s.structure.as_str()), ("parameter", &p.name)];
            ConstGauge::new(p.theta).encode(family.encode_family(&labels)?)?;
        }
    }
    Ok(())
}

/// A fleet member's structures: the ownership epoch (labelled with the owner), when this
/// member took the structure over (Unix time), and the outputs its fence held back.
fn encode_ownership(enc: &mut DescriptorEncoder, all: &[(&Shared, Status)]) -> std::fmt::Result {
    let owned: Vec<(&Shared, &contract::Ownership)> = all
        .iter()
        .filter_map(|(s, st)| Some((*s, st.ownership.as_ref()?)))
        .collect();
    if owned.is_empty() {
        return Ok(());
    }
    let mut family = enc.encode_descriptor(
        "boltwatch_ownership_epoch",
        "Ownership epoch of each structure this fleet member tracks.",
        None,
        MetricType::Gauge,
    )?;
    for (s, o) in &owned {
        let labels = [("structure", s.structure.as_str()), ("owner", &o.owner)];
        ConstGauge::new(o.epoch as i64).encode(family.encode_family(&labels)?)?;
    }
    let mut family = enc.encode_descriptor(
        "boltwatch_ownership_since_seconds",
        "When this member took the structure over (Unix time).",
        None,
        MetricType::Gauge,
    )?;
    for (s, o) in &owned {
        let t = chrono::DateTime::parse_from_rfc3339(&o.since).map_or(0, |t| t.timestamp());
        let labels = [("structure", s.structure.as_str())];
        ConstGauge::new(t).encode(family.encode_family(&labels)?)?;
    }
    let mut family = enc.encode_descriptor(
        "boltwatch_fence_held",
        "Outputs the fence held back (the epoch moved on, or could not be confirmed).",
        None,
        MetricType::Counter,
    )?;
    for (s, o) in &owned {
        let labels = [("structure", s.structure.as_str())];
        ConstCounter::new(o.held).encode(family.encode_family(&labels)?)?;
    }
    Ok(())
}

/// Serves `GET /metrics` (and `GET /`) on `listener` until the task is dropped.
pub async fn serve(listener: tokio::net::TcpListener, all: Watched) {
    let mut registry = Registry::default();
    registry.register_collector(Box::new(Structures(all)));
    let scrape = |State(registry): State<Arc<Registry>>| async move {
        let mut body = String::new();
        // Writing into a String cannot fail, nor can the collector.
        let _ = prometheus_text::encode(&mut body, &registry);
        (
            [(header::CONTENT_TYPE, prometheus_text::CONTENT_TYPE)],
            body,
        )
    };
    let app = axum::Router::new()
        .route("/metrics", axum::routing::get(scrape))
        .route("/", axum::routing::get(scrape))
        .fallback(|| async { (StatusCode::NOT_FOUND, "only GET /metrics\n") })
        .with_state(Arc::new(registry))
        // One request per connection, as before: clients that read to the end (curl, the
        // tests) get EOF, and an idle connection holds nothing.
        .layer(axum::middleware::map_response(|mut r: Response| async {
            r.headers_mut()
                .insert(header::CONNECTION, HeaderValue::from_static("close"));
            r
        }));
    if let Err(e) = axum::serve(listener, app).await {
        tracing::error!("metrics endpoint stopped: {e}");
    }
}
