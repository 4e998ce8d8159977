//! What the daemon shares between its threads about each structure (counters, the latest
//! state for `status` queries) and its Prometheus endpoint: the text exposition format
//! (version 0.0.4) at `GET /metrics`, served by a minimal HTTP/1.1 responder on a loopback
//! port (`[metrics] listen`).

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use serde_json::{Value, json};
use tokio::io::{AsyncReadExt, AsyncWriteExt};

/// Upper bounds (s) of the update-latency histogram buckets.
pub const LATENCY_BUCKETS: [f64; 10] = [
    0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.25, 1.0,
];

/// A cumulative histogram with atomic counters.
#[derive(Debug, Default)]
pub struct Histogram {
    /// Count per bucket of [`LATENCY_BUCKETS`], then +Inf (not cumulative).
    counts: [AtomicU64; LATENCY_BUCKETS.len() + 1],
    sum_ns: AtomicU64,
}

impl Histogram {
    pub fn observe(&self, d: Duration) {
        let s = d.as_secs_f64();
        let k = LATENCY_BUCKETS
            .iter()
            .position(|&b| s <= b)
            .unwrap_or(LATENCY_BUCKETS.len());
        self.counts[k].fetch_add(1, Ordering::Relaxed);
        self.sum_ns
            .fetch_add(d.as_nanos() as u64, Ordering::Relaxed);
    }

    /// Cumulative counts per bucket (+Inf last), and the sum in seconds.
    pub fn snapshot(&self) -> (Vec<u64>, f64) {
        let mut acc = 0;
        let cum = self
            .counts
            .iter()
            .map(|c| {
                acc += c.load(Ordering::Relaxed);
                acc
            })
            .collect();
        (cum, self.sum_ns.load(Ordering::Relaxed) as f64 * 1e-9)
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
    /// The last `boltwatch.stiffness.v1` published.
    pub last_estimate: Option<Value>,
    /// The last alert per (kind, connection); a `cleared` one stays until replaced.
    pub alerts: BTreeMap<String, Value>,
    /// `(parameter, θ)` of the last estimate.
    pub theta: Vec<(String, f64)>,
    pub crosschecks: u64,
    /// Cross-checks not started because the previous one was still running.
    pub crosschecks_skipped: u64,
    pub publish_errors: u64,
    pub log_file: Option<String>,
    pub last_checkpoint: Option<String>,
}

/// One structure's shared counters and status.
#[derive(Debug)]
pub struct Shared {
    pub structure: String,
    pub queue_capacity: usize,
    pub started: chrono::DateTime<chrono::Utc>,
    /// Sets received from Zenoh (queued or dropped).
    pub received: AtomicU64,
    /// Sets dropped at a full queue.
    pub dropped: AtomicU64,
    /// Sets waiting in the queue.
    pub depth: AtomicU64,
    pub latency: Histogram,
    pub status: Mutex<Status>,
}

impl Shared {
    pub fn new(structure: &str, queue_capacity: usize) -> Arc<Self> {
        Arc::new(Self {
            structure: structure.to_string(),
            queue_capacity,
            started: chrono::Utc::now(),
            received: AtomicU64::new(0),
            dropped: AtomicU64::new(0),
            depth: AtomicU64::new(0),
            latency: Histogram::default(),
            status: Mutex::new(Status::default()),
        })
    }

    fn status(&self) -> Status {
        self.status
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .clone()
    }

    /// The reply to a `boltwatch/<structure>/status` query (`boltwatch.status.v1`).
    pub fn status_json(&self) -> Value {
        let st = self.status();
        let now = chrono::Utc::now();
        let (cum, sum) = self.latency.snapshot();
        let n = *cum.last().unwrap_or(&0);
        json!({
            "schema": STATUS_SCHEMA,
            "structure": self.structure,
            "time": crate::pipeline::rfc3339(now),
            "started": crate::pipeline::rfc3339(self.started),
            "uptime_s": (now - self.started).num_milliseconds() as f64 * 1e-3,
            "queue": {
                "depth": self.depth.load(Ordering::Relaxed),
                "capacity": self.queue_capacity,
            },
            "sets": {
                "received": self.received.load(Ordering::Relaxed),
                "dropped": self.dropped.load(Ordering::Relaxed),
                "accepted": st.accepted,
                "rejected": st.rejected,
                "unconverged": st.unconverged,
                "cold_starts": st.cold_starts,
            },
            "update_mean_ms": if n > 0 { Some(sum / n as f64 * 1e3) } else { None },
            "last_set_time": st.last_set_time,
            "last_estimate": st.last_estimate,
            "alerts": st.alerts.values().collect::<Vec<_>>(),
            "crosschecks": {"published": st.crosschecks, "skipped": st.crosschecks_skipped},
            "publish_errors": st.publish_errors,
            "log_file": st.log_file,
            "last_checkpoint": st.last_checkpoint,
        })
    }
}

/// Schema of a status reply.
pub const STATUS_SCHEMA: &str = "boltwatch.status.v1";

/// Escapes a Prometheus label value.
fn label(v: &str) -> String {
    v.replace('\\', "\\\\")
        .replace('"', "\\\"")
        .replace('\n', "\\n")
}

/// The metrics of every structure in the Prometheus text format.
pub fn render(all: &[Arc<Shared>]) -> String {
    use std::fmt::Write;
    let mut o = String::new();
    let family = |o: &mut String, name: &str, kind: &str, help: &str| {
        let _ = writeln!(o, "# HELP {name} {help}\n# TYPE {name} {kind}");
    };
    let statuses: Vec<(Arc<Shared>, Status)> =
        all.iter().map(|s| (s.clone(), s.status())).collect();
    type Getter = fn(&Shared, &Status) -> u64;
    let counters: [(&str, &str, Getter); 6] = [
        (
            "boltwatch_sets_received_total",
            "Modal sets received over Zenoh.",
            |s, _| s.received.load(Ordering::Relaxed),
        ),
        (
            "boltwatch_sets_processed_total",
            "Modal sets accepted and tracked.",
            |_, st| st.accepted,
        ),
        (
            "boltwatch_sets_rejected_total",
            "Modal sets rejected (published on rejected).",
            |_, st| st.rejected,
        ),
        (
            "boltwatch_sets_dropped_total",
            "Modal sets dropped at a full queue.",
            |s, _| s.dropped.load(Ordering::Relaxed),
        ),
        (
            "boltwatch_cold_starts_total",
            "Updates redone from the baseline.",
            |_, st| st.cold_starts,
        ),
        (
            "boltwatch_crosschecks_skipped_total",
            "Cross-checks skipped: the previous one was still running.",
            |_, st| st.crosschecks_skipped,
        ),
    ];
    for (name, help, get) in counters {
        family(&mut o, name, "counter", help);
        for (s, st) in &statuses {
            let _ = writeln!(
                o,
                "{name}{{structure=\"{}\"}} {}",
                label(&s.structure),
                get(s, st)
            );
        }
    }
    family(
        &mut o,
        "boltwatch_queue_depth",
        "gauge",
        "Modal sets waiting in the queue.",
    );
    for (s, _) in &statuses {
        let _ = writeln!(
            o,
            "boltwatch_queue_depth{{structure=\"{}\"}} {}",
            label(&s.structure),
            s.depth.load(Ordering::Relaxed)
        );
    }
    family(
        &mut o,
        "boltwatch_update_seconds",
        "histogram",
        "Time to process one modal set (validation, update, filters, alerts).",
    );
    for (s, _) in &statuses {
        let (cum, sum) = s.latency.snapshot();
        let st = label(&s.structure);
        for (b, c) in LATENCY_BUCKETS.iter().zip(&cum) {
            let _ = writeln!(
                o,
                "boltwatch_update_seconds_bucket{{structure=\"{st}\",le=\"{b}\"}} {c}"
            );
        }
        let n = cum.last().copied().unwrap_or(0);
        let _ = writeln!(
            o,
            "boltwatch_update_seconds_bucket{{structure=\"{st}\",le=\"+Inf\"}} {n}"
        );
        let _ = writeln!(
            o,
            "boltwatch_update_seconds_sum{{structure=\"{st}\"}} {sum}"
        );
        let _ = writeln!(
            o,
            "boltwatch_update_seconds_count{{structure=\"{st}\"}} {n}"
        );
    }
    family(
        &mut o,
        "boltwatch_theta",
        "gauge",
        "Latest estimate of each parameter θ (stiffness relative to nominal).",
    );
    for (s, st) in &statuses {
        for (p, v) in &st.theta {
            let _ = writeln!(
                o,
                "boltwatch_theta{{structure=\"{}\",parameter=\"{}\"}} {v}",
                label(&s.structure),
                label(p)
            );
        }
    }
    o
}

/// Serves `GET /metrics` on `listener` until the task is dropped.
pub async fn serve(listener: tokio::net::TcpListener, all: Vec<Arc<Shared>>) {
    loop {
        let Ok((mut stream, _)) = listener.accept().await else {
            continue;
        };
        let all = all.clone();
        tokio::spawn(async move {
            let mut buf = [0u8; 2048];
            let mut n = 0;
            // Read the request head (bounded; the body of a GET is ignored).
            while n < buf.len() {
                match tokio::time::timeout(Duration::from_secs(5), stream.read(&mut buf[n..])).await
                {
                    Ok(Ok(0)) | Err(_) | Ok(Err(_)) => break,
                    Ok(Ok(k)) => {
                        n += k;
                        if buf[..n].windows(4).any(|w| w == b"\r\n\r\n") {
                            break;
                        }
                    }
                }
            }
            let head = String::from_utf8_lossy(&buf[..n]);
            let line = head.lines().next().unwrap_or_default();
            let mut parts = line.split_whitespace();
            let (method, path) = (parts.next().unwrap_or(""), parts.next().unwrap_or(""));
            let (code, ctype, body) = if method == "GET" && (path == "/metrics" || path == "/") {
                (
                    "200 OK",
                    "text/plain; version=0.0.4; charset=utf-8",
                    render(&all),
                )
            } else {
                (
                    "404 Not Found",
                    "text/plain",
                    "only GET /metrics\n".to_string(),
                )
            };
            let reply = format!(
                "HTTP/1.1 {code}\r\nContent-Type: {ctype}\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{body}",
                body.len()
            );
            let _ = stream.write_all(reply.as_bytes()).await;
            let _ = stream.shutdown().await;
        });
    }
}
