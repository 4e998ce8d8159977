//! One structure's tracking thread: takes modal sets from the bounded queue the Zenoh
//! subscriber fills, runs the [`Tracker`], publishes its outputs over Zenoh, writes inputs
//! and outputs into the rolling log, checkpoints, and hands cross-checks to a thread of
//! their own so a slow one never holds up tracking.

use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::sync::mpsc::{Receiver, RecvTimeoutError, SyncSender, TrySendError};
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use chrono::{DateTime, Utc};
use zenoh::Wait;
use zenoh::qos::CongestionControl;

use super::log::RollingLog;
use super::metrics::Shared;
use crate::contract::{Output, Rejected, rfc3339};
use crate::io::checkpoint;
use crate::io::driver::{JobKind, OffPath, Pace, Sink, StructureModel, dispatch, emit};
use crate::io::mcap::{to_ns, topic};
use crate::pipeline::Tracker;
use crate::pipeline::crosscheck::CrosscheckConfig;

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

/// Where a structure's outputs go live: Zenoh, the rolling log, the status.
pub struct LiveSink {
    pub session: zenoh::Session,
    pub log: RollingLog,
    pub shared: Arc<Shared>,
}

impl Sink for LiveSink {
    /// Publishes an output over Zenoh, writes it into the log and notes it in the status.
    fn emit(&mut self, output: &Output, bytes: &[u8]) -> Result<()> {
        let key = topic(output.structure(), output.topic());
        if let Err(e) = self
            .session
            .put(&key, bytes.to_vec())
            .congestion_control(CongestionControl::Block)
            .wait()
        {
            tracing::warn!(
                structure = output.structure(),
                "cannot publish on {key}: {e}"
            );
            self.shared.with_status(|st| st.publish_errors += 1);
        }
        self.log.write(&key, to_ns(output.time())?, bytes)?;
        self.shared.with_status(|st| st.note(output));
        Ok(())
    }

    fn skipped(&mut self, _structure: &str, job: JobKind) {
        if job == JobKind::Crosscheck {
            self.shared.with_status(|st| st.crosschecks_skipped += 1);
        }
    }
}

/// One structure's worker (module docs).
pub struct Worker {
    pub tracker: Tracker,
    pub out: LiveSink,
    pub checkpoint_path: PathBuf,
    pub checkpoint_every: Duration,
    lane: OffPath,
    last_checkpoint: Instant,
    dirty: bool,
    dropped_reported: u64,
}

impl Worker {
    pub fn new(
        model: StructureModel,
        tracker: Tracker,
        out: LiveSink,
        checkpoint_path: PathBuf,
        checkpoint_every: Duration,
        crosscheck_cfg: CrosscheckConfig,
    ) -> Result<Self> {
        let name = tracker.model().name.clone();
        let lane = OffPath::start(
            &format!("crosscheck-{name}"),
            HashMap::from([(name, model)]),
            crosscheck_cfg,
            tracker.config().shape_weight,
        )?;
        let w = Self {
            tracker,
            out,
            checkpoint_path,
            checkpoint_every,
            lane,
            last_checkpoint: Instant::now(),
            dirty: false,
            dropped_reported: 0,
        };
        w.update_status();
        Ok(w)
    }

    fn structure(&self) -> &str {
        &self.out.shared.structure
    }

    /// Runs until [`Input::Shutdown`] (or the queue closes), then waits for a running
    /// cross-check, checkpoints and closes the log.
    pub fn run(mut self, rx: Receiver<Input>) -> Result<()> {
        loop {
            match rx.recv_timeout(IDLE_TICK) {
                Ok(Input::Set { received, payload }) => {
                    self.out.shared.depth.fetch_sub(1, Ordering::Relaxed);
                    self.handle(received, &payload)?;
                }
                Ok(Input::Shutdown) | Err(RecvTimeoutError::Disconnected) => break,
                Err(RecvTimeoutError::Timeout) => self.out.log.tick()?,
            }
            self.lane.emit_ready(&mut self.out)?;
            self.report_drops()?;
            if self.dirty && self.last_checkpoint.elapsed() >= self.checkpoint_every {
                self.checkpoint()?;
            }
        }
        self.lane
            .drain_for(CROSSCHECK_SHUTDOWN_WAIT, &mut self.out)?;
        self.report_drops()?;
        self.checkpoint()?;
        let Self { out, lane, .. } = self;
        drop(lane);
        let closed = out.log.close()?;
        tracing::info!(
            structure = out.shared.structure,
            "tracker stopped; checkpoint written; log files closed: {}",
            closed.len()
        );
        Ok(())
    }

    fn handle(&mut self, received: DateTime<Utc>, payload: &[u8]) -> Result<()> {
        let s = self.structure().to_string();
        self.out
            .log
            .write(&topic(&s, "modal"), to_ns(received)?, payload)?;
        let start = Instant::now();
        let actions = self.tracker.handle(received, payload);
        self.out.shared.latency.observe(start.elapsed());
        self.dirty = true;
        let d = dispatch(&s, actions, &mut self.lane, &mut self.out, Pace::Live)?;
        self.update_status();
        if d.checkpoint_due {
            self.checkpoint()?;
        }
        Ok(())
    }

    /// Publishes one `rejected` message for the sets dropped at a full queue since the last
    /// report.
    fn report_drops(&mut self) -> Result<()> {
        let shared = &self.out.shared;
        let dropped = shared.dropped.load(Ordering::Relaxed);
        if dropped == self.dropped_reported {
            return Ok(());
        }
        let n = dropped - self.dropped_reported;
        self.dropped_reported = dropped;
        let reason = format!(
            "queue full: {n} modal set(s) dropped unprocessed ({dropped} since start; the queue holds {})",
            shared.queue_capacity
        );
        let r = Rejected::dropped(&shared.structure, Utc::now(), n, reason);
        emit(&mut self.out, &Output::Rejected(Box::new(r)))
    }

    /// Makes the log durable, then writes the tracker's state atomically.
    fn checkpoint(&mut self) -> Result<()> {
        self.out.log.sync()?;
        checkpoint::write_atomic(&self.checkpoint_path, &self.tracker.checkpoint())
            .with_context(|| format!("checkpoint of {}", self.structure()))?;
        self.last_checkpoint = Instant::now();
        self.dirty = false;
        let now = rfc3339(Utc::now());
        self.out
            .shared
            .with_status(|st| st.last_checkpoint = Some(now));
        Ok(())
    }

    fn update_status(&self) {
        let t = self.tracker.state();
        let log = self.out.log.current().map(|p| p.display().to_string());
        self.out.shared.with_status(|st| {
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
