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
use crate::io::checkpoint;
use crate::io::mcap::{to_ns, topic};
use crate::pipeline::crosscheck::{CrosscheckConfig, crosscheck};
use crate::pipeline::{Action, CrosscheckRequest, REJECTED_SCHEMA, Tracker, rfc3339};

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

/// The cross-check thread of one structure: one job at a time, none queued.
struct CrosscheckLane {
    jobs: Option<SyncSender<(u64, Box<CrosscheckRequest>)>>,
    results: Receiver<(u64, Value)>,
    running: bool,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl CrosscheckLane {
    fn start(model: Model, cfg: CrosscheckConfig, shape_weight: f64) -> Result<Self> {
        let (jtx, jrx) = mpsc::sync_channel::<(u64, Box<CrosscheckRequest>)>(1);
        let (rtx, rrx) = mpsc::channel();
        let thread = std::thread::Builder::new()
            .name(format!("crosscheck-{}", model.name))
            .spawn(move || {
                for (t, req) in jrx {
                    let v = crosscheck(&model, &cfg, shape_weight, &req);
                    if rtx.send((t, v)).is_err() {
                        return;
                    }
                }
            })?;
        Ok(Self {
            jobs: Some(jtx),
            results: rrx,
            running: false,
            thread: Some(thread),
        })
    }

    /// Starts a cross-check unless one is running; false if it was skipped.
    fn submit(&mut self, t: u64, req: Box<CrosscheckRequest>) -> bool {
        if self.running {
            return false;
        }
        match self.jobs.as_ref().map(|j| j.try_send((t, req))) {
            Some(Ok(())) => {
                self.running = true;
                true
            }
            _ => false,
        }
    }

    fn try_result(&mut self) -> Option<(u64, Value)> {
        match self.results.try_recv() {
            Ok(r) => {
                self.running = false;
                Some(r)
            }
            Err(TryRecvError::Empty | TryRecvError::Disconnected) => None,
        }
    }

    fn wait_result(&mut self, limit: Duration) -> Option<(u64, Value)> {
        if !self.running {
            return None;
        }
        let r = self.results.recv_timeout(limit).ok();
        self.running = false;
        r
    }
}

impl Drop for CrosscheckLane {
    fn drop(&mut self) {
        self.jobs.take();
        if let Some(t) = self.thread.take() {
            if self.running {
                // A cross-check that outlived the shutdown wait: do not block on it.
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
        tracker: Tracker,
        session: zenoh::Session,
        log: RollingLog,
        checkpoint_path: PathBuf,
        checkpoint_every: Duration,
        shared: Arc<Shared>,
        crosscheck_cfg: CrosscheckConfig,
    ) -> Result<Self> {
        let lane = CrosscheckLane::start(
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
            while let Some((t, v)) = self.lane.try_result() {
                self.publish_crosscheck(t, &v)?;
            }
            self.report_drops()?;
            if self.dirty && self.last_checkpoint.elapsed() >= self.checkpoint_every {
                self.checkpoint()?;
            }
        }
        if let Some((t, v)) = self.lane.wait_result(CROSSCHECK_SHUTDOWN_WAIT) {
            self.publish_crosscheck(t, &v)?;
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
                    match suffix {
                        "rejected" => tracing::warn!(
                            structure = s,
                            field = payload["field"].as_str().unwrap_or_default(),
                            "rejected set: {}",
                            payload["reason"].as_str().unwrap_or_default()
                        ),
                        "alerts" => tracing::info!(
                            structure = s,
                            "alert: {}",
                            payload["message"].as_str().unwrap_or_default()
                        ),
                        _ => {}
                    }
                    self.output(suffix, to_ns(time)?, &payload)?;
                }
                Action::Crosscheck(req) => {
                    let t = to_ns(req.set.time)?;
                    if !self.lane.submit(t, req) {
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

    fn publish_crosscheck(&mut self, t: u64, v: &Value) -> Result<()> {
        self.output("crosscheck", t, v)
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
