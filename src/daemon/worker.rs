//! One structure's tracking thread: takes modal sets from the bounded queue the Zenoh
//! subscriber fills, makes them durable in the write-ahead log (one fsync for all the sets
//! waiting: group commit), runs the [`Tracker`], hands its outputs to the writer thread
//! ([`LiveSink`]), which publishes them over Zenoh and writes them into the rolling log,
//! checkpoints, and hands cross-checks to a thread of their own so a slow one never holds
//! up tracking.
//!
//! No input stops it: an error or a panic while tracking one set, or while writing that
//! set's outputs, rejects the set (published on `rejected`, with the error) and the thread
//! goes on, the tracker's state as it was before the set. Only a failure to write the log or
//! a checkpoint (a full or broken disk) is fatal: the thread returns the error and the
//! process exits non-zero, so systemd restarts it.

mod guard;
mod ingest;
mod queue;
mod remote;
mod sink;

use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::atomic::Ordering;
use std::sync::mpsc::{Receiver, RecvTimeoutError, TryRecvError};
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use chrono::{DateTime, Utc};

pub use guard::panic_message;
pub use queue::{QUEUE_WAIT, WhenFull, enqueue, enqueue_accel, enqueue_environment};
pub use remote::Remote;
pub use sink::LiveSink;

use crate::contract::{Output, Rejected, WalPosition, rfc3339};
use crate::daemon::fleet::state::WalEntry;
use crate::io::checkpoint;
use crate::io::driver::{CrosscheckLane, OffPath, StructureModel, emit};
use crate::io::mcap::from_ns;
use crate::pipeline::Tracker;
use crate::pipeline::accel::{AccelFront, IdentifySettings};

/// What the subscriber hands the worker.
pub enum Input {
    Set {
        received: DateTime<Utc>,
        payload: Vec<u8>,
    },
    /// A payload over `daemon.max_payload_bytes`: only its start and digest were kept.
    Oversize {
        received: DateTime<Utc>,
        size: usize,
        head: Vec<u8>,
        digest: u128,
    },
    /// A block of raw data (`boltwatch.accel.v1`) for the structure's accel front.
    Accel {
        received: DateTime<Utc>,
        payload: Vec<u8>,
    },
    /// An environment reading (`boltwatch.environment.v1`).
    Environment {
        received: DateTime<Utc>,
        payload: Vec<u8>,
    },
    /// Finish: every set queued before this one is processed first.
    Shutdown,
}

impl Input {
    /// The payload bytes this input holds in the queue's byte budget.
    pub fn queued_bytes(&self) -> u64 {
        match self {
            Input::Set { payload, .. }
            | Input::Accel { payload, .. }
            | Input::Environment { payload, .. } => payload.len() as u64,
            Input::Oversize { .. } | Input::Shutdown => 0,
        }
    }

    /// Whether the input is counted in the queue's depth (all but [`Input::Shutdown`]).
    pub fn counted(&self) -> bool {
        !matches!(self, Input::Shutdown)
    }
}

/// How long the worker waits for a set before doing its housekeeping.
const IDLE_TICK: Duration = Duration::from_millis(200);

/// How long shutdown waits for a running cross-check.
const CROSSCHECK_SHUTDOWN_WAIT: Duration = Duration::from_secs(60);

/// The most sets made durable by one fsync (group commit): all that wait, up to this.
const GROUP_MAX: usize = 256;

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
    missed_reported: u64,
    /// The first logged set not yet handled (what a checkpoint records).
    handled_upto: Option<WalPosition>,
    /// Raw data to modal sets ([`crate::pipeline::accel`]).
    front: AccelFront,
    /// The state in the fleet's storages instead of `checkpoint_path` (`daemon.state =
    /// "zenoh"`).
    remote: Option<Remote>,
    /// Inputs are being handled again ([`Worker::resume`]): no checkpoint until all are,
    /// since none could say where among them it stands.
    replaying: bool,
    /// The structure's model, for the advice on connections with alerts off.
    model: StructureModel,
    /// The advice has been started ([`super::advice`]): once the tracker has a baseline.
    advised: bool,
    /// The memory the advice, like a cross-check, must fit in.
    budget: Option<crate::io::driver::MemoryBudget>,
}

/// Where a starting worker finds the inputs it must handle again.
pub enum Resume {
    /// The local rolling log, after the checkpoint's position (`None`: a fresh state).
    Log(Option<WalPosition>),
    /// The write-ahead tail fetched from the storages.
    Remote(Vec<WalEntry>),
}

impl Worker {
    pub fn new(
        model: StructureModel,
        tracker: Tracker,
        out: LiveSink,
        checkpoint_path: PathBuf,
        checkpoint_every: Duration,
        crosscheck: CrosscheckLane,
        identify: IdentifySettings,
    ) -> Result<Self> {
        let name = tracker.model().name.clone();
        let budget = crosscheck.budget;
        let front = AccelFront::for_model(model.clone(), identify);
        // A structure whose cross-check would not fit the memory budget is reported now;
        // each cross-check is checked again when it is due (the process grows meanwhile).
        if let Some(reason) = crosscheck.budget.and_then(|b| b.refuses_at_start(&model.1)) {
            tracing::warn!(structure = name, "{reason}");
            out.shared
                .with_status(|st| st.crosscheck_unavailable = Some(reason));
        }
        let lane = OffPath::start(
            &format!("crosscheck-{name}"),
            HashMap::from([(name, model.clone())]),
            crosscheck,
            tracker.config().shape_weight,
        )?;
        let mut w = Self {
            tracker,
            out,
            checkpoint_path,
            checkpoint_every,
            lane,
            last_checkpoint: Instant::now(),
            dirty: false,
            dropped_reported: 0,
            missed_reported: 0,
            handled_upto: None,
            front,
            remote: None,
            replaying: false,
            model,
            advised: false,
            budget,
        };
        w.update_status()?;
        Ok(w)
    }

    /// Keeps the state in the fleet's storages through `remote` instead of the local file.
    pub fn with_remote(mut self, remote: Remote) -> Self {
        self.remote = Some(remote);
        self
    }

    fn structure(&self) -> &str {
        &self.out.shared.structure
    }

    /// Handles again the inputs a restart or a takeover must ([`Resume`]), then
    /// checkpoints so that a further restart starts after them. Their outputs are published
    /// again, byte-identical and with the same ids as before (the tracker is deterministic
    /// and resumes bit for bit).
    pub fn resume(&mut self, from: Resume) -> Result<()> {
        match from {
            Resume::Log(Some(pos)) => {
                let after = pos.clone();
                let inputs = self.out.log(move |log| log.inputs_after(&after))?;
                let inputs = inputs
                    .into_iter()
                    .map(|m| (m.topic.ends_with("/environment"), m.log_time, m.data))
                    .collect();
                let what = format!("write-ahead log from {} #{}", pos.file, pos.modal);
                self.handle_again(inputs, &what)?;
            }
            Resume::Log(None) => {}
            Resume::Remote(entries) => {
                let inputs = entries
                    .into_iter()
                    .map(|e| (e.suffix == "environment", e.time_ns, e.bytes))
                    .collect();
                self.handle_again(inputs, "the fleet's state storage")?;
            }
        }
        self.handled_upto = Some(self.out.log(|log| log.next_input())?);
        if let Some(r) = self.remote.as_mut() {
            r.resumed();
        }
        self.checkpoint()
    }

    /// Handles inputs (environment reading or not, log time, bytes) again, in order.
    fn handle_again(&mut self, inputs: Vec<(bool, u64, Vec<u8>)>, what: &str) -> Result<()> {
        let n = inputs.len() as u64;
        self.replaying = true;
        for (environment, time, data) in inputs {
            if environment {
                let actions = self.tracker.handle_environment(from_ns(time), &data);
                self.publish_guarded(from_ns(time), &data, actions)?;
            } else {
                self.handle(from_ns(time), &data)?;
            }
            self.out.shared.beat();
        }
        self.replaying = false;
        self.out.shared.with_status(|st| st.replayed += n);
        if n > 0 {
            tracing::info!(
                structure = self.structure(),
                sets = n,
                "handled again the sets written after the checkpoint ({what})"
            );
        }
        Ok(())
    }

    /// Runs until [`Input::Shutdown`] (or the queue closes), then waits for a running
    /// cross-check, checkpoints and closes the log.
    pub fn run(mut self, rx: Receiver<Input>) -> Result<()> {
        loop {
            self.out.shared.beat();
            match rx.recv_timeout(IDLE_TICK) {
                Ok(Input::Shutdown) | Err(RecvTimeoutError::Disconnected) => break,
                Ok(first) => {
                    let mut batch = vec![first];
                    let mut stop = false;
                    while batch.len() < GROUP_MAX {
                        match rx.try_recv() {
                            Ok(Input::Shutdown) => {
                                stop = true;
                                break;
                            }
                            Ok(input) => batch.push(input),
                            Err(TryRecvError::Empty | TryRecvError::Disconnected) => break,
                        }
                    }
                    self.commit_and_handle(batch)?;
                    if stop {
                        break;
                    }
                }
                Err(RecvTimeoutError::Timeout) => self.out.log(|log| log.tick())?,
            }
            self.lane.emit_ready(&mut self.out)?;
            self.report_drops()?;
            if self.dirty && self.last_checkpoint.elapsed() >= self.checkpoint_every {
                self.checkpoint()?;
            }
        }
        // A fenced lane publishes nothing more: no cross-check is worth waiting for.
        let fenced = self.remote.as_ref().is_some_and(|r| r.fence.is_fenced());
        if !fenced {
            self.lane
                .drain_for(CROSSCHECK_SHUTDOWN_WAIT, &mut self.out)?;
        }
        if let Some(e) = self.front.finish() {
            self.front_event(Utc::now(), &[], e)?;
        }
        self.report_drops()?;
        self.checkpoint()?;
        let Self { out, lane, .. } = self;
        drop(lane);
        let structure = out.shared.structure.clone();
        let closed = out.close()?;
        tracing::info!(
            structure,
            "tracker stopped; checkpoint written; log files closed: {}",
            closed.len()
        );
        Ok(())
    }

    /// Publishes one `rejected` message for the sets dropped at a full queue since the last
    /// report, and one for the sets lost in transport.
    fn report_drops(&mut self) -> Result<()> {
        let shared = self.out.shared.clone();
        let missed = shared.missed.load(Ordering::Relaxed);
        if missed != self.missed_reported {
            let n = missed - self.missed_reported;
            self.missed_reported = missed;
            let reason = format!(
                "{n} modal set(s) lost in transport, no longer in the publisher's cache ({missed} since start)"
            );
            let mut r = Rejected::dropped(&shared.structure, Utc::now(), n, missed, reason);
            r.id = crate::contract::output_id(&shared.structure, r.time, "missed", missed);
            emit(&mut self.out, Output::Rejected(Box::new(r)))?;
        }
        let dropped = shared.dropped.load(Ordering::Relaxed);
        if dropped == self.dropped_reported {
            return Ok(());
        }
        let n = dropped - self.dropped_reported;
        self.dropped_reported = dropped;
        let reason = format!(
            "queue full: {n} modal set(s) dropped unprocessed ({dropped} since start; the queue holds {} sets or {} MiB)",
            shared.queue_capacity,
            shared.queue_bytes >> 20
        );
        let r = Rejected::dropped(&shared.structure, Utc::now(), n, dropped, reason);
        emit(&mut self.out, Output::Rejected(Box::new(r)))
    }

    /// Makes the log durable, then writes the tracker's state, with the write-ahead
    /// position of the first set not yet handled, atomically.
    fn checkpoint(&mut self) -> Result<()> {
        self.out.log(|log| log.sync())?;
        let mut c = self.tracker.checkpoint();
        c.wal = self.handled_upto.clone();
        match self.remote.as_mut() {
            Some(remote) => remote.put_checkpoint(c)?,
            None => checkpoint::write_atomic(&self.checkpoint_path, &c)
                .with_context(|| format!("checkpoint of {}", self.structure()))?,
        }
        self.last_checkpoint = Instant::now();
        self.dirty = false;
        let now = rfc3339(Utc::now());
        self.out
            .shared
            .with_status(|st| st.last_checkpoint = Some(now));
        Ok(())
    }

    fn update_status(&mut self) -> Result<()> {
        let log = self
            .out
            .log(|log| Ok(log.current().map(|p| p.display().to_string())))?;
        let t = self.tracker.state();
        self.out.shared.with_status(|st| {
            st.accepted = t.accepted;
            st.rejected = t.rejected;
            st.unconverged = t.unconverged;
            st.cold_starts = t.cold_starts;
            st.duplicates = t.duplicates;
            st.last_set_time = t.last_time.map(rfc3339);
            st.log_file = log;
        });
        if !self.advised && t.baseline.is_some() {
            let shared = self.out.shared.clone();
            self.advised = true;
            super::advice::advise(self.model.clone(), &self.tracker, shared, self.budget);
        }
        Ok(())
    }
}
