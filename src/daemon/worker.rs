//! One structure's tracking thread: takes modal sets from the bounded queue the Zenoh
//! subscriber fills, makes them durable in the write-ahead log (one fsync for all the sets
//! waiting: group commit), runs the [`Tracker`], publishes its outputs over Zenoh, writes
//! them into the rolling log, checkpoints, and hands cross-checks to a thread of their own
//! so a slow one never holds up tracking.
//!
//! No input stops it: an error or a panic while tracking one set, or while writing that
//! set's outputs, rejects the set (published on `rejected`, with the error) and the thread
//! goes on, the tracker's state as it was before the set. Only a failure to write the log or
//! a checkpoint (a full or broken disk) is fatal: the thread returns the error and the
//! process exits non-zero, so systemd restarts it.

use std::collections::HashMap;
use std::panic::AssertUnwindSafe;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::sync::mpsc::{Receiver, RecvTimeoutError, SyncSender, TryRecvError, TrySendError};
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use chrono::{DateTime, Utc};
use zenoh::Wait;
use zenoh::bytes::ZBytes;
use zenoh::qos::CongestionControl;
use zenoh::sample::Locality;

use super::log::RollingLog;
use super::metrics::Shared;
use crate::contract::modal_set::Rejection;
use crate::contract::rejected::REJECTED_PAYLOAD_LIMIT;
use crate::contract::wire::digest_parts;
use crate::contract::{Checkpoint, Output, Rejected, Schema, WalPosition, rfc3339};
use crate::io::checkpoint;
use crate::io::driver::{
    CrosscheckLane, JobKind, OffPath, Pace, Sink, StructureModel, dispatch, emit,
};
use crate::io::mcap::{from_ns, to_ns, topic};
use crate::pipeline::accel::{AccelFront, FrontEvent, IdentifySettings};
use crate::pipeline::{Action, Tracker, TrackerState};

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

/// How long the worker waits for a set before doing its housekeeping.
const IDLE_TICK: Duration = Duration::from_millis(200);

/// How long shutdown waits for a running cross-check.
const CROSSCHECK_SHUTDOWN_WAIT: Duration = Duration::from_secs(60);

/// The most sets made durable by one fsync (group commit): all that wait, up to this.
const GROUP_MAX: usize = 256;

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
        // A modal set identified here goes to the others only (this daemon's own modal
        // subscriber would take it again), and it is in the log already, as an input.
        let modal = matches!(output, Output::Modal(_));
        let destination = if modal {
            Locality::Remote
        } else {
            Locality::Any
        };
        if let Err(e) = self
            .session
            .put(&key, bytes.to_vec())
            .congestion_control(CongestionControl::Block)
            .allowed_destination(destination)
            .wait()
        {
            tracing::warn!(
                structure = output.structure(),
                "cannot publish on {key}: {e}"
            );
            self.shared.with_status(|st| st.publish_errors += 1);
        }
        if !modal {
            self.log.write(&key, to_ns(output.time())?, bytes)?;
        }
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
    missed_reported: u64,
    /// The first logged set not yet handled (what a checkpoint records).
    handled_upto: Option<WalPosition>,
    /// Raw data to modal sets ([`crate::pipeline::accel`]).
    front: AccelFront,
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
            HashMap::from([(name, model)]),
            crosscheck,
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
            missed_reported: 0,
            handled_upto: None,
            front,
        };
        w.update_status();
        Ok(w)
    }

    fn structure(&self) -> &str {
        &self.out.shared.structure
    }

    /// Handles again the sets logged at and after `from` (the checkpoint's write-ahead
    /// position; `None` for a fresh state), without logging them again, then checkpoints
    /// so that a further restart starts after them. Their outputs are published again,
    /// byte-identical and with the same ids as before the crash (the tracker is
    /// deterministic and resumes bit for bit).
    pub fn resume(&mut self, from: Option<WalPosition>) -> Result<()> {
        if let Some(pos) = from {
            let inputs = self.out.log.inputs_after(&pos)?;
            let n = inputs.len() as u64;
            for m in inputs {
                if m.topic.ends_with("/environment") {
                    let actions = self
                        .tracker
                        .handle_environment(from_ns(m.log_time), &m.data);
                    self.publish_guarded(from_ns(m.log_time), &m.data, actions)?;
                } else {
                    self.handle(from_ns(m.log_time), &m.data)?;
                }
                self.out.shared.beat();
            }
            self.out.shared.with_status(|st| st.replayed += n);
            if n > 0 {
                tracing::info!(
                    structure = self.structure(),
                    sets = n,
                    "handled again the sets logged after the checkpoint (write-ahead log from {} #{})",
                    pos.file,
                    pos.modal
                );
            }
        }
        self.handled_upto = Some(self.out.log.next_input()?);
        self.checkpoint()
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
        if let Some(e) = self.front.finish() {
            self.front_event(Utc::now(), &[], e)?;
        }
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

    /// Write-ahead: logs every set of `batch`, makes them durable with one fsync, then
    /// handles them in order.
    fn commit_and_handle(&mut self, batch: Vec<Input>) -> Result<()> {
        let shared = self.out.shared.clone();
        let mut positions = Vec::with_capacity(batch.len());
        for input in &batch {
            let pos = match input {
                Input::Set { received, payload } => {
                    shared.depth.fetch_sub(1, Ordering::Relaxed);
                    shared
                        .queued_bytes
                        .fetch_sub(payload.len() as u64, Ordering::Relaxed);
                    Some(
                        self.out
                            .log
                            .write_input("modal", to_ns(*received)?, payload)?,
                    )
                }
                Input::Oversize { .. } => {
                    shared.depth.fetch_sub(1, Ordering::Relaxed);
                    None
                }
                // Raw blocks are not logged (a day of 42 channels at 1 kHz is 19 GB); the
                // modal set of each window is, as an input, when it is identified.
                Input::Accel { payload, .. } => {
                    shared.depth.fetch_sub(1, Ordering::Relaxed);
                    shared
                        .queued_bytes
                        .fetch_sub(payload.len() as u64, Ordering::Relaxed);
                    None
                }
                Input::Environment { received, payload } => {
                    shared.depth.fetch_sub(1, Ordering::Relaxed);
                    shared
                        .queued_bytes
                        .fetch_sub(payload.len() as u64, Ordering::Relaxed);
                    Some(
                        self.out
                            .log
                            .write_input("environment", to_ns(*received)?, payload)?,
                    )
                }
                Input::Shutdown => None,
            };
            positions.push(pos);
        }
        let logged = positions.iter().flatten().count() as u64;
        if logged > 0 {
            let t = Instant::now();
            self.out.log.sync()?;
            let ms = t.elapsed().as_secs_f64() * 1e3;
            shared.with_status(|st| {
                st.wal.syncs += 1;
                st.wal.sets += logged;
                st.wal.sync_ms += ms;
            });
        }
        for (input, pos) in batch.into_iter().zip(positions) {
            match input {
                Input::Set { received, payload } => {
                    self.handle(received, &payload)?;
                    if let Some(p) = pos {
                        self.handled_upto = Some(p.after());
                    }
                }
                Input::Oversize {
                    received,
                    size,
                    head,
                    digest,
                } => {
                    let rej = Rejection {
                        field: "payload".into(),
                        reason: format!(
                            "{size} bytes exceeds the limit of {} bytes (daemon.max_payload_bytes)",
                            shared.max_payload
                        ),
                    };
                    let o = self.tracker.refuse(received, &rej, &head, size, digest);
                    self.publish_guarded(received, &head, vec![Action::Publish(o)])?;
                }
                Input::Accel { received, payload } => self.handle_accel(received, &payload)?,
                Input::Environment { received, payload } => {
                    let actions = self.tracker.handle_environment(received, &payload);
                    self.dirty = true;
                    self.publish_guarded(received, &payload, actions)?;
                    if let Some(p) = pos {
                        self.handled_upto = Some(p.after());
                    }
                }
                Input::Shutdown => {}
            }
            shared.beat();
        }
        self.update_status();
        Ok(())
    }

    /// Feeds one raw block to the accel front; a panic there rejects the block.
    fn handle_accel(&mut self, received: DateTime<Utc>, payload: &[u8]) -> Result<()> {
        let events = std::panic::catch_unwind(AssertUnwindSafe(|| self.front.handle(payload)))
            .unwrap_or_else(|panic| {
                vec![FrontEvent::Refused(Rejection {
                    field: "payload".into(),
                    reason: format!(
                        "identifying this block's window failed (internal error: {})",
                        panic_message(&*panic)
                    ),
                })]
            });
        for e in events {
            self.front_event(received, payload, e)?;
        }
        Ok(())
    }

    /// A window's modal set is logged as an input (write-ahead), published for others
    /// and tracked like a received set; a refused block or a dropped window is published
    /// on `rejected`.
    fn front_event(
        &mut self,
        received: DateTime<Utc>,
        payload: &[u8],
        e: FrontEvent,
    ) -> Result<()> {
        match e {
            FrontEvent::Set(set) => {
                let bytes = serde_json::to_vec(&set.to_json())?;
                let pos = self
                    .out
                    .log
                    .write_input("modal", to_ns(received)?, &bytes)?;
                self.out.log.sync()?;
                emit(&mut self.out, Output::Modal(set))?;
                self.handle(received, &bytes)?;
                self.handled_upto = Some(pos.after());
            }
            FrontEvent::Refused(rej) => {
                let head = &payload[..payload.len().min(REJECTED_PAYLOAD_LIMIT)];
                let o = self.tracker.refuse(
                    received,
                    &rej,
                    head,
                    payload.len(),
                    crate::contract::digest(payload),
                );
                self.publish_guarded(received, head, vec![Action::Publish(o)])?;
            }
            FrontEvent::Dropped(rej) => {
                let o = self
                    .tracker
                    .refuse(received, &rej, &[], 0, crate::contract::digest(&[]));
                self.publish_guarded(received, &[], vec![Action::Publish(o)])?;
            }
        }
        Ok(())
    }

    /// Tracks one set: a panic in the tracker rejects the set and restores the state from
    /// before it.
    fn handle(&mut self, received: DateTime<Utc>, payload: &[u8]) -> Result<()> {
        let before = self.tracker.state().clone();
        let start = Instant::now();
        let tracked =
            std::panic::catch_unwind(AssertUnwindSafe(|| self.tracker.handle(received, payload)));
        self.out.shared.latency.observe(start.elapsed());
        self.dirty = true;
        let actions = match tracked {
            Ok(actions) => actions,
            Err(panic) => {
                let why = panic_message(&*panic);
                tracing::error!(
                    structure = self.structure(),
                    "tracking a set panicked ({why}); the set is rejected and the state restored"
                );
                self.restore(before)?;
                self.out.shared.with_status(|st| st.failed += 1);
                let rej = Rejection {
                    field: "payload".into(),
                    reason: format!(
                        "tracking this set failed (internal error: {why}); the state is as before it"
                    ),
                };
                self.tracker.reject(received, &rej, payload)
            }
        };
        self.publish_guarded(received, payload, actions)
    }

    /// Carries out one set's actions; an error or a panic while writing its outputs
    /// becomes the set's rejection. Only a failure to publish that rejection is fatal.
    fn publish_guarded(
        &mut self,
        received: DateTime<Utc>,
        payload: &[u8],
        actions: Vec<Action>,
    ) -> Result<()> {
        let s = self.structure().to_string();
        let done = std::panic::catch_unwind(AssertUnwindSafe(|| {
            dispatch(&s, actions, &mut self.lane, &mut self.out, Pace::Live)
        }));
        let failure = match done {
            Ok(Ok(d)) => {
                if d.checkpoint_due {
                    self.checkpoint()?;
                }
                return Ok(());
            }
            Ok(Err(e)) => format!("{e:#}"),
            Err(panic) => format!("internal error: {}", panic_message(&*panic)),
        };
        tracing::error!(
            structure = s,
            "writing the outputs of a set failed: {failure}"
        );
        self.out.shared.with_status(|st| st.failed += 1);
        let r = Rejected::payload(
            &s,
            received,
            "payload",
            &format!("writing this set's outputs failed: {failure}"),
            payload,
        );
        emit(&mut self.out, Output::Rejected(Box::new(r)))
            .context("cannot even publish the rejection of a set whose outputs failed")
    }

    /// Rebuilds the tracker from `state` (after a panic mid-update), without the eigen
    /// solver's warm block, which the panic may have left half-written.
    fn restore(&mut self, state: TrackerState) -> Result<()> {
        let model = self.tracker.model().clone();
        let cfg = self.tracker.config().clone();
        let max_future = self.tracker.max_future();
        self.tracker = Tracker::restore(
            model,
            cfg,
            Checkpoint {
                schema: Schema::new(),
                state,
                eigen_block: None,
                wal: None,
            },
        )?;
        self.tracker.set_max_future(max_future);
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
        self.out.log.sync()?;
        let mut c = self.tracker.checkpoint();
        c.wal = self.handled_upto.clone();
        checkpoint::write_atomic(&self.checkpoint_path, &c)
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
            st.duplicates = t.duplicates;
            st.last_set_time = t.last_time.map(rfc3339);
            st.log_file = log;
        });
    }
}

/// What a caught panic said.
pub fn panic_message(panic: &(dyn std::any::Any + Send)) -> String {
    panic
        .downcast_ref::<&str>()
        .map(|s| s.to_string())
        .or_else(|| panic.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "a panic without a message".into())
}

/// What [`enqueue`] does with a set that does not fit the queue.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum WhenFull {
    /// Drop it and count it (live sets: the Zenoh callback must not block).
    Drop,
    /// Wait for room (sets fetched from a publisher's cache, on their own thread), for at
    /// most [`QUEUE_WAIT`], then drop and count it.
    Wait,
}

/// How long [`WhenFull::Wait`] waits for room in the queue.
pub const QUEUE_WAIT: Duration = Duration::from_secs(60);

/// The subscriber side of the queue: a payload over the size limit is passed on as its
/// start and digest only; a set that does not fit the queue (by count or by bytes) is
/// dropped and counted, or waited for (`when_full`).
pub fn enqueue(tx: &SyncSender<Input>, shared: &Shared, payload: &ZBytes, when_full: WhenFull) {
    enqueue_as(tx, shared, payload, when_full, Kind::Set);
}

/// [`enqueue`] for a raw block (`boltwatch/<s>/accel`), handed to the accel front.
pub fn enqueue_accel(tx: &SyncSender<Input>, shared: &Shared, payload: &ZBytes) {
    enqueue_as(tx, shared, payload, WhenFull::Drop, Kind::Accel);
}

/// [`enqueue`] for an environment reading (`boltwatch/<s>/environment`).
pub fn enqueue_environment(tx: &SyncSender<Input>, shared: &Shared, payload: &ZBytes) {
    enqueue_as(tx, shared, payload, WhenFull::Wait, Kind::Environment);
}

/// What a queued payload is.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Kind {
    Set,
    Accel,
    Environment,
}

fn enqueue_as(
    tx: &SyncSender<Input>,
    shared: &Shared,
    payload: &ZBytes,
    when_full: WhenFull,
    kind: Kind,
) {
    shared.received.fetch_add(1, Ordering::Relaxed);
    let received = Utc::now();
    let size = payload.len();
    let deadline = Instant::now() + QUEUE_WAIT;
    let input = if size > shared.max_payload {
        let mut head = Vec::with_capacity(REJECTED_PAYLOAD_LIMIT);
        for slice in payload.slices() {
            let room = REJECTED_PAYLOAD_LIMIT - head.len();
            head.extend_from_slice(&slice[..slice.len().min(room)]);
        }
        Input::Oversize {
            received,
            size,
            head,
            digest: digest_parts(payload.slices()),
        }
    } else {
        while shared.queued_bytes.load(Ordering::Relaxed) + size as u64 > shared.queue_bytes {
            if when_full == WhenFull::Drop || Instant::now() >= deadline {
                shared.dropped.fetch_add(1, Ordering::Relaxed);
                return;
            }
            std::thread::sleep(Duration::from_millis(5));
        }
        shared
            .queued_bytes
            .fetch_add(size as u64, Ordering::Relaxed);
        let payload = payload.to_bytes().into_owned();
        match kind {
            Kind::Accel => Input::Accel { received, payload },
            Kind::Environment => Input::Environment { received, payload },
            Kind::Set => Input::Set { received, payload },
        }
    };
    shared.depth.fetch_add(1, Ordering::Relaxed);
    let bytes = match &input {
        Input::Set { payload, .. }
        | Input::Accel { payload, .. }
        | Input::Environment { payload, .. } => payload.len() as u64,
        _ => 0,
    };
    let sent = match when_full {
        WhenFull::Drop => tx.try_send(input).is_ok(),
        WhenFull::Wait => {
            let mut input = input;
            loop {
                match tx.try_send(input) {
                    Ok(()) => break true,
                    Err(TrySendError::Full(back)) if Instant::now() < deadline => {
                        input = back;
                        std::thread::sleep(Duration::from_millis(5));
                    }
                    Err(_) => break false,
                }
            }
        }
    };
    if !sent {
        shared.depth.fetch_sub(1, Ordering::Relaxed);
        shared.queued_bytes.fetch_sub(bytes, Ordering::Relaxed);
        shared.dropped.fetch_add(1, Ordering::Relaxed);
    }
}
