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
use crate::core::updating::bayesian::map_memory_bytes;
use crate::pipeline::crosscheck::{CrosscheckConfig, crosscheck, skipped};
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

/// The memory the cross-checks may use (`daemon.memory_mib`, matching the deployment's
/// `MemoryMax`): a cross-check runs only if the process's resident memory now plus the
/// MAP's estimated working set ([`map_memory_bytes`]) stays under it. One that would not
/// is skipped and published with the reason, never started to be OOM-killed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct MemoryBudget {
    pub bytes: u64,
}

/// The advice's working set over the MAP's estimate for the same modes on the model's own
/// channels: on the four-bay solid (16 modes, 957 channels with the candidates) the advice
/// raised the process's peak by 481 MiB where that estimate is 359 MiB (1.34).
pub const ADVICE_OVER_MAP: f64 = 1.5;

/// What the off-path cross-checks run with: their settings and, for the daemon, the
/// memory budget.
#[derive(Debug, Clone)]
pub struct CrosscheckLane {
    pub cfg: CrosscheckConfig,
    pub budget: Option<MemoryBudget>,
}

/// Modes a MAP works on at once ([`map_memory_bytes`] counts that many in flight): the
/// mode count the start-up check assumes, before any set has come.
const START_CHECK_MODES: usize = 2;

impl MemoryBudget {
    /// From `daemon.memory_mib`.
    pub fn from_mib(mib: u64) -> Self {
        Self {
            bytes: mib.saturating_mul(1 << 20),
        }
    }

    /// Why a cross-check of `model` on a set of `n_modes` modes and `n_channels` channels
    /// would not fit now, or `None` when it fits.
    pub fn refuses(&self, model: &Model, n_modes: usize, n_channels: usize) -> Option<String> {
        let mib = |b: u64| b.div_ceil(1 << 20);
        let Some(need) = map_memory_bytes(model, n_modes, n_channels) else {
            return Some(format!(
                "cross-check of {} skipped: its memory cannot be estimated (the model's \
                 pattern cannot be analysed)",
                model.name
            ));
        };
        let held = resident_bytes().unwrap_or(0);
        (held.saturating_add(need) > self.bytes).then(|| {
            format!(
                "cross-check of {} skipped: the Bayesian MAP needs about {} MiB beside the {} \
                 MiB the process holds, over daemon.memory_mib = {}",
                model.name,
                mib(need),
                mib(held),
                mib(self.bytes)
            )
        })
    }

    /// Why the advice on connections with alerts off ([`crate::daemon::advice`]), planned
    /// with `n_modes` modes, would not fit now, or `None` when it fits. Its working set is
    /// taken as [`ADVICE_OVER_MAP`] times a MAP's on the model's own channels.
    pub fn refuses_advice(&self, model: &Model, n_modes: usize) -> Option<String> {
        let mib = |b: u64| b.div_ceil(1 << 20);
        let map = map_memory_bytes(model, n_modes, model.channels().len())?;
        let need = (map as f64 * ADVICE_OVER_MAP) as u64;
        let held = resident_bytes().unwrap_or(0);
        (held.saturating_add(need) > self.bytes).then(|| {
            format!(
                "not computed: planning with {n_modes} modes needs about {} MiB beside the {}                  MiB the process holds, over daemon.memory_mib = {}; run `boltwatch plan`                  with the structure's model on another machine",
                mib(need),
                mib(held),
                mib(self.bytes)
            )
        })
    }

    /// The start-up check of a structure ([`START_CHECK_MODES`] modes on every channel of
    /// the model): why its cross-checks will not fit, if they will not.
    pub fn refuses_at_start(&self, model: &Model) -> Option<String> {
        self.refuses(model, START_CHECK_MODES, model.channels().len())
    }
}

/// The process's resident memory (Linux `/proc/self/statm`), if it can be read.
pub fn resident_bytes() -> Option<u64> {
    let statm = std::fs::read_to_string("/proc/self/statm").ok()?;
    let pages: u64 = statm.split_whitespace().nth(1)?.parse().ok()?;
    // SAFETY: sysconf has no preconditions; it returns -1 for an unknown name.
    let page = unsafe { libc::sysconf(libc::_SC_PAGESIZE) };
    (page > 0).then(|| pages * page as u64)
}

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
    /// Starts the thread (`name`) for `models`, keyed by structure name; cross-checks
    /// keep within the lane's budget when it has one.
    pub fn start(
        name: &str,
        models: HashMap<String, StructureModel>,
        lane: CrosscheckLane,
        shape_weight: f64,
    ) -> Result<Self> {
        let CrosscheckLane { cfg, budget } = lane;
        let (jtx, jrx) = mpsc::sync_channel::<(String, Job)>(DIAGNOSES_QUEUED + 1);
        let (rtx, rrx) = mpsc::channel();
        let thread = std::thread::Builder::new()
            .name(name.to_string())
            .spawn(move || {
                crate::core::sequential_numerics();
                for (s, job) in jrx {
                    let (spec, model) = &*models[&s];
                    let out = match job {
                        Job::Crosscheck(req) => Output::Crosscheck(Box::new(
                            match budget.and_then(|b| {
                                b.refuses(model, req.set.modes.len(), req.set.channels.len())
                            }) {
                                Some(reason) => {
                                    tracing::warn!(structure = s, "{reason}");
                                    skipped(model, &cfg, &req, reason)
                                }
                                None => crosscheck(model, &cfg, shape_weight, &req),
                            },
                        )),
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

#[cfg(test)]
mod tests {
    use super::*;

    /// The budget refuses a cross-check that would not fit, naming the key and both
    /// figures, and lets one through that fits (the lab frame's MAP needs a few MiB).
    #[test]
    fn the_memory_budget_refuses_what_does_not_fit() {
        let model = crate::core::model::lab_frame();
        let need = map_memory_bytes(&model, 9, 42).unwrap();
        assert!(need > 0 && need < 64 << 20, "{need} bytes");
        let reason = MemoryBudget { bytes: need }
            .refuses(&model, 9, 42)
            .expect("the process holds memory besides the MAP");
        assert!(
            reason.contains("daemon.memory_mib") && reason.contains("lab-frame"),
            "{reason}"
        );
        assert_eq!(MemoryBudget::from_mib(1 << 30).refuses(&model, 9, 42), None);
        assert!(MemoryBudget::from_mib(1).refuses_at_start(&model).is_some());
    }
}
