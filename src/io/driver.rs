//! What `replay` and `run` share around the sans-I/O tracker: [`dispatch`], which carries
//! out a tracker's [`Action`]s against a [`Sink`] (where outputs go: an MCAP file, or Zenoh
//! and the rolling log), and [`OffPath`], the thread that runs cross-checks and diagnoses
//! off the tracking path.
//!
//! The two drivers differ only in [`Pace`]: a replay waits for the previous off-path job
//! before handing over the next, so its results land at points fixed by the inputs and the
//! output file is deterministic; the daemon never waits, and a job that finds the lane busy
//! is skipped (cross-checks) or queued up to a bound (diagnoses), and counted.

use std::collections::HashMap;
use std::sync::Arc;
use std::sync::mpsc::{self, Receiver, SyncSender, TryRecvError};
use std::time::{Duration, Instant};

use anyhow::{Result, anyhow};

use crate::contract::Output;
use crate::core::model::Model;
use crate::core::model::spec::ModelSpec;
use crate::pipeline::crosscheck::{CrosscheckConfig, crosscheck};
use crate::pipeline::verdict::diagnosis_alert;
use crate::pipeline::{Action, CrosscheckRequest, DiagnoseRequest};

/// Where a driver's outputs go.
pub trait Sink {
    /// Publishes one output; `bytes` is its wire form ([`Output::to_wire`]).
    fn emit(&mut self, output: &Output, bytes: &[u8]) -> Result<()>;

    /// Publishes one output, encoding it here; a sink that writes on another thread
    /// takes it as it is and encodes it there.
    fn emit_owned(&mut self, output: Output) -> Result<()> {
        let bytes = output.to_wire();
        self.emit(&output, &bytes)
    }

    /// An off-path job was not run because the lane was busy ([`Pace::Live`]).
    fn skipped(&mut self, _structure: &str, _job: JobKind) {}
}

/// Publishes `output` on `sink`, encoded once, and logs it.
pub fn emit(sink: &mut impl Sink, output: Output) -> Result<()> {
    output.log();
    sink.emit_owned(output)
}

/// How a driver hands work to the off-path lane (module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Pace {
    /// Wait for the running job before submitting the next (replay).
    Deterministic,
    /// Never wait; skip a job the lane has no room for (daemon).
    Live,
}

/// What [`dispatch`] leaves to the driver.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Dispatched {
    /// The tracker asked for its state to be persisted ([`Action::Checkpoint`]).
    pub checkpoint_due: bool,
}

/// Carries out one set's actions: outputs to `sink`, cross-checks and diagnoses to `lane`.
pub fn dispatch(
    structure: &str,
    actions: Vec<Action>,
    lane: &mut OffPath,
    sink: &mut impl Sink,
    pace: Pace,
) -> Result<Dispatched> {
    let mut d = Dispatched::default();
    for a in actions {
        let job = match a {
            Action::Publish(o) => {
                emit(sink, o)?;
                continue;
            }
            Action::Checkpoint => {
                d.checkpoint_due = true;
                continue;
            }
            Action::Crosscheck(req) => Job::Crosscheck(req),
            Action::Diagnose(req) => Job::Diagnose(req),
        };
        if pace == Pace::Deterministic {
            lane.drain(sink)?;
        }
        let kind = job.kind();
        if !lane.submit(structure, job)? {
            match kind {
                JobKind::Crosscheck => tracing::warn!(
                    structure,
                    "cross-check skipped: the previous one is still running"
                ),
                JobKind::Diagnose => tracing::warn!(
                    structure,
                    "diagnosis of a model-inadequacy warning skipped: {DIAGNOSES_QUEUED} already wait"
                ),
            }
            sink.skipped(structure, kind);
        }
    }
    Ok(d)
}

/// Work done off the tracking path.
#[derive(Debug)]
pub enum Job {
    Crosscheck(Box<CrosscheckRequest>),
    Diagnose(Box<DiagnoseRequest>),
}

/// The kind of a [`Job`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum JobKind {
    Crosscheck,
    Diagnose,
}

impl Job {
    pub fn kind(&self) -> JobKind {
        match self {
            Self::Crosscheck(_) => JobKind::Crosscheck,
            Self::Diagnose(_) => JobKind::Diagnose,
        }
    }
}

/// Diagnoses (rare: one per model-inadequacy episode) that may wait behind a running job.
pub const DIAGNOSES_QUEUED: usize = 4;

/// A watched structure's model, in its text form (the diagnosis enriches it; none for a
/// model imported from matrices) and assembled.
pub type StructureModel = Arc<(Option<ModelSpec>, Model)>;

/// The thread that runs cross-checks and diagnoses, in submission order, for the
/// structures it is given. At most one cross-check is pending (one requested while another
/// job is pending is skipped) and at most [`DIAGNOSES_QUEUED`] diagnoses wait behind the
/// running job.
pub struct OffPath {
    jobs: Option<SyncSender<(String, Job)>>,
    results: Receiver<Output>,
    pending: usize,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl OffPath {
    /// Starts the thread (`name`) for `models`, keyed by structure name.
    pub fn start(
        name: &str,
        models: HashMap<String, StructureModel>,
        cfg: CrosscheckConfig,
        shape_weight: f64,
    ) -> Result<Self> {
        let (jtx, jrx) = mpsc::sync_channel::<(String, Job)>(DIAGNOSES_QUEUED + 1);
        let (rtx, rrx) = mpsc::channel();
        let thread = std::thread::Builder::new()
            .name(name.to_string())
            .spawn(move || {
                crate::core::sequential_numerics();
                for (s, job) in jrx {
                    let (spec, model) = &*models[&s];
                    let out = match job {
                        Job::Crosscheck(req) => Output::Crosscheck(Box::new(crosscheck(
                            model,
                            &cfg,
                            shape_weight,
                            &req,
                        ))),
                        Job::Diagnose(req) => Output::Alert(Box::new(diagnosis_alert(
                            spec.as_ref(),
                            model,
                            shape_weight,
                            &req,
                        ))),
                    };
                    if rtx.send(out).is_err() {
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

    /// Queues a job unless the limits above skip it; false if it was skipped.
    pub fn submit(&mut self, structure: &str, job: Job) -> Result<bool> {
        let limit = match job {
            Job::Crosscheck(_) => 1,
            Job::Diagnose(_) => DIAGNOSES_QUEUED + 1,
        };
        if self.pending >= limit {
            return Ok(false);
        }
        let jobs = self
            .jobs
            .as_ref()
            .ok_or_else(|| anyhow!("the off-path thread has stopped"))?;
        match jobs.try_send((structure.to_string(), job)) {
            Ok(()) => {
                self.pending += 1;
                Ok(true)
            }
            Err(mpsc::TrySendError::Full(_)) => Ok(false),
            Err(mpsc::TrySendError::Disconnected(_)) => {
                Err(anyhow!("the off-path thread has stopped"))
            }
        }
    }

    /// A finished job's output, if one is ready.
    pub fn try_result(&mut self) -> Option<Output> {
        match self.results.try_recv() {
            Ok(r) => {
                self.pending -= 1;
                Some(r)
            }
            Err(TryRecvError::Empty | TryRecvError::Disconnected) => None,
        }
    }

    /// Waits for every pending job and emits its output.
    pub fn drain(&mut self, sink: &mut impl Sink) -> Result<()> {
        while self.pending > 0 {
            let out = self
                .results
                .recv()
                .map_err(|_| anyhow!("the off-path thread died"))?;
            self.pending -= 1;
            emit(sink, out)?;
        }
        Ok(())
    }

    /// Waits up to `limit` for the pending jobs; emits what finished, and says how many
    /// did not.
    pub fn drain_for(&mut self, limit: Duration, sink: &mut impl Sink) -> Result<usize> {
        let deadline = Instant::now() + limit;
        while self.pending > 0 {
            let left = deadline.saturating_duration_since(Instant::now());
            match self.results.recv_timeout(left) {
                Ok(out) => {
                    self.pending -= 1;
                    emit(sink, out)?;
                }
                Err(_) => break,
            }
        }
        Ok(self.pending)
    }

    /// Emits the outputs of the jobs finished so far.
    pub fn emit_ready(&mut self, sink: &mut impl Sink) -> Result<()> {
        while let Some(out) = self.try_result() {
            emit(sink, out)?;
        }
        Ok(())
    }
}

impl Drop for OffPath {
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
