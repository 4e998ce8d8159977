//! One structure's tracking thread: takes modal sets from the bounded queue the Zenoh
//! subscriber fills, runs the [`Tracker`], publishes its outputs over Zenoh, writes inputs
//! and outputs into the rolling log, checkpoints, and hands cross-checks to a thread of
//! their own so a slow one never holds up tracking.

use std::path::PathBuf;
use std::sync::atomic::Ordering;
use std::sync::mpsc::{Receiver, RecvTimeoutError, SyncSender, TryRecvError, TrySendError};
use std::sync::{Arc, mpsc};
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use chrono::{DateTime, Utc};
use serde_json::{Value, json};
use zenoh::Wait;
use zenoh::qos::CongestionControl;

use super::log::RollingLog;
use super::metrics::Shared;
use crate::core::model::Model;
use crate::core::model::spec::ModelSpec;
use crate::io::checkpoint;
use crate::io::mcap::{to_ns, topic};
use crate::io::replay::Job;
use crate::pipeline::crosscheck::{CrosscheckConfig, crosscheck};
use crate::pipeline::verdict::diagnosis_alert;
use crate::pipeline::{Action, REJECTED_SCHEMA, Tracker, rfc3339};

/// What the subscriber hands the worker.
pub enum Input {
    Set {
        received: DateTime<Utc>,
        payload: Vec<u8>,
    },
    /// Finish: every set queued before this one is processed first.
    Shutdown,
}

/// How long the worker waits for a set before doing its housekeeping.
const IDLE_TICK: Duration = Duration::from_millis(200);

/// How long shutdown waits for a running cross-check.
const CROSSCHECK_SHUTDOWN_WAIT: Duration = Duration::from_secs(60);

/// Diagnoses (rare: one per model-inadequacy episode) that may wait behind a running job.
const DIAGNOSES_QUEUED: usize = 4;

/// The thread of one structure's work off the tracking path: cross-checks (one at a time:
/// one requested while another job runs is skipped) and diagnoses (queued, up to
/// [`DIAGNOSES_QUEUED`]).
struct CrosscheckLane {
    jobs: Option<SyncSender<(u64, Job)>>,
    results: Receiver<(u64, &'static str, Value)>,
    pending: usize,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl CrosscheckLane {
    fn start(
        spec: ModelSpec,
        model: Model,
        cfg: CrosscheckConfig,
        shape_weight: f64,
    ) -> Result<Self> {
        let (jtx, jrx) = mpsc::sync_channel::<(u64, Job)>(DIAGNOSES_QUEUED + 1);
        let (rtx, rrx) = mpsc::channel();
        let thread = std::thread::Builder::new()
            .name(format!("crosscheck-{}", model.name))
            .spawn(move || {
                crate::core::sequential_numerics();
                for (t, job) in jrx {
                    let r = match job {
                        Job::Crosscheck(req) => {
                            ("crosscheck", crosscheck(&model, &cfg, shape_weight, &req))
                        }
                        Job::Diagnose(req) => {
                            ("alerts", diagnosis_alert(&spec, &model, shape_weight, &req))
                        }
                    };
                    if rtx.send((t, r.0, r.1)).is_err() {
                        return;
                    }
                }
            })?;
        Ok(Self {
            jobs: Some(jtx),
            results: rrx,
            pending: 0,
            thread: Some(thread),
        })
    }

    /// Queues a job unless the rules above skip it; false if it was skipped.
    fn submit(&mut self, t: u64, job: Job) -> bool {
        let limit = match job {
            Job::Crosscheck(_) => 1,
            Job::Diagnose(_) => DIAGNOSES_QUEUED + 1,
        };
        if self.pending >= limit {
            return false;
        }
        match self.jobs.as_ref().map(|j| j.try_send((t, job))) {
            Some(Ok(())) => {
                self.pending += 1;
                true
            }
            _ => false,
        }
    }

    fn try_result(&mut self) -> Option<(u64, &'static str, Value)> {
        match self.results.try_recv() {
            Ok(r) => {
                self.pending -= 1;
                Some(r)
            }
            Err(TryRecvError::Empty | TryRecvError::Disconnected) => None,
        }
    }

    /// Waits up to `limit` for every pending job.
    fn wait_results(&mut self, limit: Duration) -> Vec<(u64, &'static str, Value)> {
        let deadline = Instant::now() + limit;
        let mut out = Vec::new();
        while self.pending > 0 {
            let left = deadline.saturating_duration_since(Instant::now());
            match self.results.recv_timeout(left) {
                Ok(r) => {
                    self.pending -= 1;
                    out.push(r);
                }
                Err(_) => break,
            }
        }
        out
    }
}

impl Drop for CrosscheckLane {
    fn drop(&mut self) {
        self.jobs.take();
        if let Some(t) = self.thread.take() {
            if self.pending > 0 {
                // A job that outlived the shutdown wait: do not block on it.
                return;
            }
            let _ = t.join();
        }
    }
}

/// One structure's worker (module docs).
pub struct Worker {
    pub tracker: Tracker,
    pub session: zenoh::Session,
    pub log: RollingLog,
    pub checkpoint_path: PathBuf,
    pub checkpoint_every: Duration,
    pub shared: Arc<Shared>,
    lane: CrosscheckLane,
    last_checkpoint: Instant,
    dirty: bool,
    dropped_reported: u64,
}

impl Worker {
    #[allow(clippy::too_many_arguments)] // each is a distinct part the worker owns
    pub fn new(
        spec: ModelSpec,
        tracker: Tracker,
        session: zenoh::Session,
        log: RollingLog,
        checkpoint_path: PathBuf,
        checkpoint_every: Duration,
        shared: Arc<Shared>,
        crosscheck_cfg: CrosscheckConfig,
    ) -> Result<Self> {
        let lane = CrosscheckLane::start(
            spec,
            tracker.model().clone(),
            crosscheck_cfg,
            tracker.config().shape_weight,
        )?;
        let w = Self {
            tracker,
            session,
            log,
            checkpoint_path,
            checkpoint_every,
            shared,
            lane,
            last_checkpoint: Instant::now(),
            dirty: false,
            dropped_reported: 0,
        };
        w.update_status();
        Ok(w)
    }

    fn structure(&self) -> &str {
        &self.shared.structure
    }

    /// Runs until [`Input::Shutdown`] (or the queue closes), then waits for a running
    /// cross-check, checkpoints and closes the log.
    pub fn run(mut self, rx: Receiver<Input>) -> Result<()> {
        loop {
            match rx.recv_timeout(IDLE_TICK) {
                Ok(Input::Set { received, payload }) => {
                    self.shared.depth.fetch_sub(1, Ordering::Relaxed);
                    self.handle(received, &payload)?;
                }
                Ok(Input::Shutdown) | Err(RecvTimeoutError::Disconnected) => break,
                Err(RecvTimeoutError::Timeout) => self.log.tick()?,
            }
            while let Some((t, suffix, v)) = self.lane.try_result() {
                self.publish_offpath(t, suffix, &v)?;
            }
            self.report_drops()?;
            if self.dirty && self.last_checkpoint.elapsed() >= self.checkpoint_every {
                self.checkpoint()?;
            }
        }
        for (t, suffix, v) in self.lane.wait_results(CROSSCHECK_SHUTDOWN_WAIT) {
            self.publish_offpath(t, suffix, &v)?;
        }
        self.report_drops()?;
        self.checkpoint()?;
        let Self { log, shared, .. } = self;
        let closed = log.close()?;
        tracing::info!(
            structure = shared.structure,
            "tracker stopped; checkpoint written; log files closed: {}",
            closed.len()
        );
        Ok(())
    }

    fn handle(&mut self, received: DateTime<Utc>, payload: &[u8]) -> Result<()> {
        let s = self.structure().to_string();
        self.log
            .write(&topic(&s, "modal"), to_ns(received)?, payload)?;
        let start = Instant::now();
        let actions = self.tracker.handle(received, payload);
        self.shared.latency.observe(start.elapsed());
        self.dirty = true;
        let mut checkpoint_due = false;
        for a in actions {
            match a {
                Action::Publish {
                    topic: suffix,
                    time,
                    payload,
                    ..
                } => {
                    crate::pipeline::log_output(&s, suffix, &payload);
                    self.output(suffix, to_ns(time)?, &payload)?;
                }
                Action::Diagnose(req) => {
                    let t = to_ns(req.set.time)?;
                    if !self.lane.submit(t, Job::Diagnose(req)) {
                        tracing::warn!(
                            structure = s,
                            "diagnosis of a model-inadequacy warning skipped: {DIAGNOSES_QUEUED} already wait"
                        );
                    }
                }
                Action::Crosscheck(req) => {
                    let t = to_ns(req.set.time)?;
                    if !self.lane.submit(t, Job::Crosscheck(req)) {
                        tracing::warn!(
                            structure = s,
                            "cross-check skipped: the previous one is still running"
                        );
                        self.with_status(|st| st.crosschecks_skipped += 1);
                    }
                }
                Action::Checkpoint(_) => checkpoint_due = true,
            }
        }
        self.update_status();
        if checkpoint_due {
            self.checkpoint()?;
        }
        Ok(())
    }

    /// Publishes an output over Zenoh, writes it into the log and notes it in the status.
    fn output(&mut self, suffix: &str, log_time: u64, payload: &Value) -> Result<()> {
        let s = self.structure().to_string();
        let key = topic(&s, suffix);
        let bytes = serde_json::to_vec(payload)?;
        if let Err(e) = self
            .session
            .put(&key, bytes.clone())
            .congestion_control(CongestionControl::Block)
            .wait()
        {
            tracing::warn!(structure = s, "cannot publish on {key}: {e}");
            self.with_status(|st| st.publish_errors += 1);
        }
        self.log.write(&key, log_time, &bytes)?;
        self.with_status(|st| match suffix {
            "stiffness" => {
                st.theta = payload["parameters"]
                    .as_array()
                    .map(|ps| {
                        ps.iter()
                            .filter_map(|p| {
                                Some((p["name"].as_str()?.to_string(), p["theta"].as_f64()?))
                            })
                            .collect()
                    })
                    .unwrap_or_default();
                st.last_estimate = Some(payload.clone());
            }
            "alerts" => {
                let k = format!(
                    "{}:{}",
                    payload["kind"].as_str().unwrap_or_default(),
                    payload["connection"].as_str().unwrap_or_default()
                );
                st.alerts.insert(k, payload.clone());
            }
            "crosscheck" => st.crosschecks += 1,
            _ => {}
        });
        Ok(())
    }

    /// Publishes a result of the off-path thread (a cross-check, a diagnosis verdict).
    fn publish_offpath(&mut self, t: u64, suffix: &str, v: &Value) -> Result<()> {
        crate::pipeline::log_output(self.structure(), suffix, v);
        self.output(suffix, t, v)
    }

    /// Publishes one `rejected` message for the sets dropped at a full queue since the last
    /// report.
    fn report_drops(&mut self) -> Result<()> {
        let dropped = self.shared.dropped.load(Ordering::Relaxed);
        if dropped == self.dropped_reported {
            return Ok(());
        }
        let n = dropped - self.dropped_reported;
        self.dropped_reported = dropped;
        let now = Utc::now();
        let reason = format!(
            "queue full: {n} modal set(s) dropped unprocessed ({dropped} since start; the queue holds {})",
            self.shared.queue_capacity
        );
        tracing::warn!(structure = self.structure(), "{reason}");
        let payload = json!({
            "schema": REJECTED_SCHEMA,
            "structure": self.structure(),
            "time": rfc3339(now),
            "received": rfc3339(now),
            "reason": reason,
            "field": "",
            "payload": "",
            "payload_bytes": 0,
            "truncated": false,
            "dropped": n,
        });
        self.output("rejected", to_ns(now)?, &payload)
    }

    /// Makes the log durable, then writes the tracker's state atomically.
    fn checkpoint(&mut self) -> Result<()> {
        self.log.sync()?;
        checkpoint::write_atomic(&self.checkpoint_path, &self.tracker.checkpoint())
            .with_context(|| format!("checkpoint of {}", self.structure()))?;
        self.last_checkpoint = Instant::now();
        self.dirty = false;
        let now = rfc3339(Utc::now());
        self.with_status(|st| st.last_checkpoint = Some(now));
        Ok(())
    }

    fn with_status(&self, f: impl FnOnce(&mut super::metrics::Status)) {
        let mut st = self.shared.status.lock().unwrap_or_else(|p| p.into_inner());
        f(&mut st);
    }

    fn update_status(&self) {
        let t = self.tracker.state();
        let log = self.log.current().map(|p| p.display().to_string());
        self.with_status(|st| {
            st.accepted = t.accepted;
            st.rejected = t.rejected;
            st.unconverged = t.unconverged;
            st.cold_starts = t.cold_starts;
            st.last_set_time = t.last_time.map(rfc3339);
            st.log_file = log;
        });
    }
}

/// The subscriber side of the queue: `try_send`, and count a set that does not fit.
pub fn enqueue(tx: &SyncSender<Input>, shared: &Shared, payload: Vec<u8>) {
    shared.received.fetch_add(1, Ordering::Relaxed);
    shared.depth.fetch_add(1, Ordering::Relaxed);
    let input = Input::Set {
        received: Utc::now(),
        payload,
    };
    match tx.try_send(input) {
        Ok(()) => {}
        Err(TrySendError::Full(_) | TrySendError::Disconnected(_)) => {
            shared.depth.fetch_sub(1, Ordering::Relaxed);
            shared.dropped.fetch_add(1, Ordering::Relaxed);
        }
    }
}
