//! The replay driver (`boltwatch replay`, issue 4 item 6): feeds a recording's modal sets,
//! in log-time order, through one [`Tracker`] per watched structure and writes every output
//! into an MCAP file, as fast as the tracker goes.
//!
//! **Deterministic.** Outputs are written in input order; a cross-check runs on a worker
//! thread, off the tracking path, and its result is written at a point fixed by the inputs
//! alone (when the next cross-check is requested, before a checkpoint, at the end). The same
//! recording and configuration give a byte-identical output file.
//!
//! **Resumable.** The output goes to `OUT.part` until the end, when it is finished and
//! renamed to `OUT`. Each checkpoint first makes the output durable ([`McapWriter::sync`]),
//! then writes, atomically, the trackers' states, the next input and the number of outputs
//! written and the sync points. `--resume` copies that many messages from the unfinished
//! `OUT.part` into a fresh file, ending chunks at the same sync points (so the bytes equal
//! those of an uninterrupted run), and goes on from the next input: nothing is lost or
//! written twice, wherever the process was killed.

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::sync::{Arc, mpsc};
use std::time::Instant;

use anyhow::{Context, Result, anyhow, bail};
use serde::{Deserialize, Serialize};
use serde_json::{Value, json};

use super::checkpoint;
use super::driver::{CrosscheckLane, OffPath, Pace, Sink, dispatch};
use super::mcap::{
    ChannelSpec, McapWriter, RecordedMessage, for_each_message, from_ns, read_tolerant, to_ns,
    topic,
};
use super::model::load_structure;
use crate::contract::modal_set::{ModalSet, Rejection};
use crate::contract::{Alert, Checkpoint, Estimate, Output};
use crate::pipeline::accel::{AccelFront, FrontEvent, IdentifySettings};
use crate::pipeline::{Action, Tracker, TrackerConfig, TrackerState};
use crate::settings::Settings;

/// Schema of the replay checkpoint file.
pub const REPLAY_CHECKPOINT_SCHEMA: &str = "boltwatch.replay_checkpoint.v1";

/// What to replay, where to.
#[derive(Debug, Clone)]
pub struct ReplayOptions {
    pub recording: PathBuf,
    pub out: PathBuf,
    pub checkpoint: PathBuf,
    pub resume: bool,
    pub settings: Settings,
}

impl ReplayOptions {
    /// The file written until the replay is complete.
    pub fn part(&self) -> PathBuf {
        with_suffix(&self.out, ".part")
    }
}

/// `path` with `suffix` appended to its file name.
pub fn with_suffix(path: &Path, suffix: &str) -> PathBuf {
    let mut name = path.file_name().unwrap_or_default().to_os_string();
    name.push(suffix);
    path.with_file_name(name)
}

/// The outcome of a replay.
#[derive(Debug, Clone, Default)]
pub struct ReplaySummary {
    /// Modal sets (or accel blocks) in the recording (all watched structures).
    pub sets: usize,
    /// Environment readings in the recording (all watched structures).
    pub readings: usize,
    /// Input index the run resumed from.
    pub resumed_from: Option<usize>,
    /// The recording was already replayed to the end (`--resume` on a complete run).
    pub already_complete: bool,
    /// Topics present in the recording and not read, with their message counts.
    pub skipped_topics: BTreeMap<String, u64>,
    /// Alerts, in output order.
    pub alerts: Vec<Alert>,
    /// The last estimate of each structure.
    pub last_estimate: BTreeMap<String, Estimate>,
    /// Counters of each structure's tracker.
    pub counters: BTreeMap<String, Counters>,
    pub crosschecks: usize,
    pub rejected: usize,
    /// Modal sets identified from raw data (windows of accel blocks).
    pub windows: usize,
    /// Messages in the output file.
    pub outputs: u64,
    /// Inputs processed by this run (not counting those before a resume).
    pub processed: usize,
    pub seconds: f64,
}

/// A tracker's counters at the end of a replay.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Counters {
    pub accepted: u64,
    pub rejected: u64,
    pub unconverged: u64,
    pub cold_starts: u64,
}

impl ReplaySummary {
    /// Notes a message read back from a file.
    fn note_recorded(&mut self, m: &RecordedMessage) {
        let suffix = m.topic.rsplit('/').next().unwrap_or_default();
        if let Ok(o) = Output::from_wire(suffix, &m.data) {
            self.note(&o);
        }
    }

    /// Notes an output.
    fn note(&mut self, o: &Output) {
        match o {
            Output::Alert(a) => self.alerts.push((**a).clone()),
            Output::Estimate(e) => {
                self.last_estimate
                    .insert(e.structure.clone(), (**e).clone());
            }
            Output::Crosscheck(_) => self.crosschecks += 1,
            Output::Rejected(_) => self.rejected += 1,
            Output::Modal(_) => self.windows += 1,
        }
    }
}

/// The output file with the summary kept alongside. Outputs are encoded and written on
/// a thread of their own ([`Writer`]), so that work (on the lab frame ~70 µs a set, the
/// estimate's 8 KB of JSON and its compression) overlaps the tracking of the next set.
struct OutputFile {
    writer: Writer,
    /// Outputs handed to the writer (all of them written once it has synced).
    written: u64,
    syncs: Vec<u64>,
    summary: ReplaySummary,
}

impl Sink for OutputFile {
    fn emit(&mut self, output: &Output, bytes: &[u8]) -> Result<()> {
        self.writer.send(WriterJob::Encoded {
            topic: topic(output.structure(), output.topic()),
            time: to_ns(output.time())?,
            bytes: bytes.to_vec(),
        })?;
        self.summary.note(output);
        self.written += 1;
        Ok(())
    }

    fn emit_owned(&mut self, output: Output) -> Result<()> {
        self.summary.note(&output);
        self.writer.send(WriterJob::Output(output))?;
        self.written += 1;
        Ok(())
    }
}

impl OutputFile {
    /// Waits until everything handed over is written and synced.
    fn sync(&mut self) -> Result<()> {
        let (tx, rx) = mpsc::channel();
        self.writer.send(WriterJob::Sync(tx))?;
        match rx.recv() {
            Ok(r) => r?,
            Err(_) => return Err(self.writer.failure()),
        }
        if self.syncs.last() != Some(&self.written) {
            self.syncs.push(self.written);
        }
        Ok(())
    }
}

/// Work for the [`Writer`] thread.
enum WriterJob {
    Output(Output),
    Encoded {
        topic: String,
        time: u64,
        bytes: Vec<u8>,
    },
    Sync(mpsc::Sender<Result<()>>),
}

/// Outputs waiting for the writer thread at most (then the tracking waits).
const WRITER_QUEUE: usize = 256;

/// The thread that owns the output [`McapWriter`].
struct Writer {
    jobs: Option<mpsc::SyncSender<WriterJob>>,
    thread: Option<std::thread::JoinHandle<Result<McapWriter>>>,
}

impl Writer {
    fn start(mut w: McapWriter) -> Result<Self> {
        let (tx, rx) = mpsc::sync_channel::<WriterJob>(WRITER_QUEUE);
        let thread = std::thread::Builder::new()
            .name("replay-writer".into())
            .spawn(move || -> Result<McapWriter> {
                for job in rx {
                    match job {
                        WriterJob::Output(o) => w.write(
                            &topic(o.structure(), o.topic()),
                            to_ns(o.time())?,
                            &o.to_wire(),
                        )?,
                        WriterJob::Encoded { topic, time, bytes } => {
                            w.write(&topic, time, &bytes)?
                        }
                        WriterJob::Sync(reply) => {
                            let r = w.sync();
                            let failed = r.is_err();
                            let _ = reply.send(r);
                            if failed {
                                bail!("the output file could not be synced");
                            }
                        }
                    }
                }
                Ok(w)
            })
            .context("cannot start the output writer thread")?;
        Ok(Self {
            jobs: Some(tx),
            thread: Some(thread),
        })
    }

    fn send(&mut self, job: WriterJob) -> Result<()> {
        let jobs = self
            .jobs
            .as_ref()
            .ok_or_else(|| anyhow!("the output writer has stopped"))?;
        match jobs.send(job) {
            Ok(()) => Ok(()),
            Err(_) => Err(self.failure()),
        }
    }

    /// The error that stopped the writer thread.
    fn failure(&mut self) -> anyhow::Error {
        self.jobs.take();
        match self.thread.take().map(|t| t.join()) {
            Some(Ok(Err(e))) => e.context("writing the output file"),
            Some(Ok(Ok(_))) => anyhow!("the output writer stopped"),
            Some(Err(_)) => anyhow!("the output writer thread panicked"),
            None => anyhow!("the output writer has stopped"),
        }
    }

    /// Waits for everything handed over and returns the file's writer.
    fn finish(mut self) -> Result<McapWriter> {
        self.jobs.take();
        match self.thread.take().map(|t| t.join()) {
            Some(Ok(r)) => r.context("writing the output file"),
            Some(Err(_)) => bail!("the output writer thread panicked"),
            None => bail!("the output writer has stopped"),
        }
    }
}

/// The replay's checkpoint file: where to go on from, and every tracker's checkpoint.
#[derive(Debug, Serialize, Deserialize)]
struct ReplayCheckpoint {
    schema: String,
    recording: PathBuf,
    recording_bytes: u64,
    recording_sets: usize,
    /// [`fingerprint`] of the settings.
    settings: Value,
    next_input: usize,
    outputs_written: u64,
    /// Output counts at which the file was synced (chunk ends).
    syncs: Vec<u64>,
    complete: bool,
    trackers: BTreeMap<String, Checkpoint<TrackerState>>,
}

/// The part of the settings a checkpoint must match to be resumed.
fn fingerprint(settings: &Settings) -> Value {
    json!({
        "structures": settings.structures.iter().map(|s| json!({"name": s.name, "model": s.model})).collect::<Vec<_>>(),
        "tracker": settings.tracker,
        "crosscheck": settings.crosscheck,
        "identify": settings.identify,
    })
}

/// One input of a replay, for one structure.
#[derive(Debug)]
pub enum Input {
    /// A modal set as recorded.
    Recorded(RecordedMessage),
    /// An environment reading as recorded (`boltwatch/<structure>/environment`).
    Environment(RecordedMessage),
    /// A modal set identified from a window of accel blocks ([`AccelFront`]).
    Identified(Box<ModalSet>),
    /// An accel block rejected, or a window left unfinished: at `log_time`, with the
    /// first bytes of the payload, its size and digest.
    Refused {
        log_time: u64,
        rejection: Rejection,
        head: Vec<u8>,
        size: usize,
        digest: u128,
    },
}

impl Input {
    fn log_time(&self) -> Result<u64> {
        match self {
            Self::Recorded(m) | Self::Environment(m) => Ok(m.log_time),
            Self::Identified(s) => to_ns(s.time),
            Self::Refused { log_time, .. } => Ok(*log_time),
        }
    }
}

/// The input topics of a structure.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Source {
    Modal,
    Accel,
    Environment,
}

/// Inputs of each structure, in log-time order (a window's modal set at the time of its
/// first sample), and the topics not read with their message counts.
pub type Inputs = (Vec<(String, Input)>, BTreeMap<String, u64>);

/// The inputs of the watched structures in `path`: modal sets as recorded, and accel blocks
/// streamed through one [`AccelFront`] per structure (windows identified as the file is
/// read, so only one window of raw data per structure is held; the samples left over at
/// the end, short of a window, are reported).
pub fn read_inputs(
    path: &Path,
    models: &HashMap<String, crate::io::driver::StructureModel>,
    identify: &IdentifySettings,
) -> Result<Inputs> {
    let mut wanted: HashMap<String, (&str, Source)> = HashMap::new();
    for name in models.keys() {
        wanted.insert(topic(name, "modal"), (name.as_str(), Source::Modal));
        wanted.insert(topic(name, "accel"), (name.as_str(), Source::Accel));
        wanted.insert(
            topic(name, "environment"),
            (name.as_str(), Source::Environment),
        );
    }
    let mut fronts: BTreeMap<&str, (AccelFront, u64)> = BTreeMap::new();
    let mut inputs = Vec::new();
    let mut skipped = BTreeMap::new();
    let mut blocks = 0usize;
    let started = Instant::now();
    let take = |s: &str, log_time: u64, e: FrontEvent, payload: &[u8]| match e {
        FrontEvent::Set(set) => (s.to_string(), Input::Identified(set)),
        FrontEvent::Dropped(rejection) => (
            s.to_string(),
            Input::Refused {
                log_time,
                rejection,
                head: Vec::new(),
                size: 0,
                digest: crate::contract::digest(&[]),
            },
        ),
        FrontEvent::Refused(rejection) => (
            s.to_string(),
            Input::Refused {
                log_time,
                rejection,
                head: payload[..payload.len().min(crate::contract::REJECTED_PAYLOAD_LIMIT)]
                    .to_vec(),
                size: payload.len(),
                digest: crate::contract::digest(payload),
            },
        ),
    };
    for_each_message(path, |m| {
        match wanted.get(&m.topic) {
            Some(&(s, Source::Modal)) => inputs.push((s.to_string(), Input::Recorded(m))),
            Some(&(s, Source::Environment)) => inputs.push((s.to_string(), Input::Environment(m))),
            Some(&(s, Source::Accel)) => {
                blocks += 1;
                let (front, last) = fronts.entry(s).or_insert_with(|| {
                    (
                        AccelFront::for_model(models[s].clone(), identify.clone()),
                        0,
                    )
                });
                *last = m.log_time;
                for e in front.handle(&m.data) {
                    inputs.push(take(s, m.log_time, e, &m.data));
                }
            }
            None => *skipped.entry(m.topic).or_insert(0) += 1,
        }
        Ok(())
    })?;
    for (s, (front, last)) in &mut fronts {
        if let Some(e) = front.finish() {
            inputs.push(take(s, *last, e, &[]));
        }
    }
    if blocks > 0 {
        tracing::info!(
            blocks,
            windows = inputs
                .iter()
                .filter(|(_, i)| matches!(i, Input::Identified(_)))
                .count(),
            seconds = started.elapsed().as_secs_f64(),
            "identified the accel blocks of {}",
            path.display()
        );
    }
    let mut keyed = Vec::with_capacity(inputs.len());
    for i in inputs {
        keyed.push((i.1.log_time()?, i));
    }
    // Stable: blocks and the windows they make keep their stream order.
    keyed.sort_by_key(|(t, _)| *t);
    Ok((keyed.into_iter().map(|(_, i)| i).collect(), skipped))
}

/// Replays `opts.recording` (module docs); `progress(done, total)` after every input.
pub fn replay(
    opts: &ReplayOptions,
    mut progress: impl FnMut(usize, usize),
) -> Result<ReplaySummary> {
    let started = Instant::now();
    let settings = &opts.settings;
    let names: Vec<&str> = settings
        .structures
        .iter()
        .map(|s| s.name.as_str())
        .collect();
    let mut models = HashMap::new();
    for s in &settings.structures {
        models.insert(s.name.clone(), Arc::new(load_structure(s)?));
    }
    let (sets, skipped) = read_inputs(&opts.recording, &models, &settings.identify)?;
    if sets.is_empty() {
        bail!(
            "recording {} has no modal sets or accel blocks of the watched structures ({}); its topics: {}",
            opts.recording.display(),
            names
                .iter()
                .flat_map(|s| [topic(s, "modal"), topic(s, "accel")])
                .collect::<Vec<_>>()
                .join(", "),
            if skipped.is_empty() {
                "none".to_string()
            } else {
                skipped.keys().cloned().collect::<Vec<_>>().join(", ")
            }
        );
    }
    let recording_bytes = std::fs::metadata(&opts.recording)?.len();
    tracing::info!(
        sets = sets.len(),
        structures = names.join(","),
        "replaying {} into {}",
        opts.recording.display(),
        opts.out.display()
    );
    // The identified modal sets go out on `modal` when the recording has raw data.
    let raw = sets
        .iter()
        .any(|(_, i)| !matches!(i, Input::Recorded(_) | Input::Environment(_)));
    let mut channels = Vec::new();
    for s in &settings.structures {
        for suffix in Output::TOPICS {
            channels.push(ChannelSpec::for_structure(&s.name, suffix)?);
        }
        if raw {
            channels.push(ChannelSpec::for_structure(&s.name, "modal")?);
        }
    }
    let tracker_cfg: TrackerConfig = settings.tracker.clone();
    let fp = fingerprint(settings);
    let part = opts.part();

    let previous: Option<ReplayCheckpoint> = if opts.resume {
        checkpoint::read(&opts.checkpoint)?
    } else {
        None
    };
    let mut trackers: BTreeMap<String, Tracker> = BTreeMap::new();
    let readings = sets
        .iter()
        .filter(|(_, i)| matches!(i, Input::Environment(_)))
        .count();
    let mut summary = ReplaySummary {
        sets: sets.len() - readings,
        readings,
        skipped_topics: skipped,
        ..Default::default()
    };
    let (start, w, syncs) = match previous {
        Some(c) => {
            let ctx = |what: &str| format!("checkpoint {}: {what}", opts.checkpoint.display());
            if c.schema != REPLAY_CHECKPOINT_SCHEMA {
                bail!(ctx(&format!(
                    "schema is {}, expected {REPLAY_CHECKPOINT_SCHEMA}",
                    c.schema
                )));
            }
            if c.recording_bytes != recording_bytes || c.recording_sets != sets.len() {
                bail!(ctx(&format!(
                    "written for a recording of {} bytes and {} sets, {} has {recording_bytes} bytes and {} sets",
                    c.recording_bytes,
                    c.recording_sets,
                    opts.recording.display(),
                    sets.len()
                )));
            }
            if c.settings != fp {
                bail!(ctx(
                    "written with a different configuration (structures, tracker or crosscheck); replay without --resume"
                ));
            }
            if c.complete {
                if !opts.out.exists() && part.exists() {
                    std::fs::rename(&part, &opts.out).with_context(|| {
                        format!("cannot move {} to {}", part.display(), opts.out.display())
                    })?;
                }
                let mut s = summary;
                s.already_complete = true;
                let all = super::mcap::read_all(&opts.out)?;
                s.outputs = all.len() as u64;
                for m in &all {
                    s.note_recorded(m);
                }
                s.seconds = started.elapsed().as_secs_f64();
                return Ok(s);
            }
            let (next, written, syncs) = (c.next_input, c.outputs_written, c.syncs);
            let mut states = c.trackers;
            for (name, model) in &models {
                let state = states
                    .remove(name)
                    .ok_or_else(|| anyhow!(ctx(&format!("no tracker of {name}"))))?;
                let mut t = Tracker::restore(model.1.clone(), tracker_cfg.clone(), state)
                    .with_context(|| ctx(&format!("tracker of {name}")))?;
                crate::io::model::adopt_law(&mut t)?;
                trackers.insert(name.clone(), t);
            }
            if !part.exists() {
                bail!(
                    "{} is missing, so the outputs the checkpoint {} counts are gone: replay without --resume",
                    part.display(),
                    opts.checkpoint.display()
                );
            }
            let (kept, stop) = read_tolerant(&part)?;
            if (kept.len() as u64) < written {
                bail!(
                    "{} holds {} readable messages but the checkpoint counts {written}{}: cannot resume; replay without --resume",
                    part.display(),
                    kept.len(),
                    stop.map(|s| format!(" (reading stopped: {s})"))
                        .unwrap_or_default()
                );
            }
            let fresh = with_suffix(&part, ".new");
            let mut w = McapWriter::create(&fresh, &channels)?;
            for (i, m) in kept.iter().take(written as usize).enumerate() {
                w.copy(m)?;
                summary.note_recorded(m);
                if syncs.binary_search(&(i as u64 + 1)).is_ok() {
                    w.sync()?;
                }
            }
            w.sync()?;
            std::fs::rename(&fresh, &part).with_context(|| {
                format!("cannot move {} to {}", fresh.display(), part.display())
            })?;
            tracing::info!(
                next,
                outputs = written,
                "resumed from checkpoint {}",
                opts.checkpoint.display()
            );
            summary.resumed_from = Some(next);
            (next, w, syncs)
        }
        None => {
            if opts.resume {
                tracing::info!(
                    "no checkpoint at {}: replaying from the start",
                    opts.checkpoint.display()
                );
            }
            for (name, model) in &models {
                let mut t = Tracker::new(model.1.clone(), tracker_cfg.clone())?;
                crate::io::model::adopt_law(&mut t)?;
                trackers.insert(name.clone(), t);
            }
            (0, McapWriter::create(&part, &channels)?, Vec::new())
        }
    };
    let mut out = OutputFile {
        written: w.written(),
        writer: Writer::start(w)?,
        syncs,
        summary,
    };
    let mut lane = OffPath::start(
        "replay-offpath",
        models,
        CrosscheckLane {
            cfg: settings.crosscheck.clone(),
            budget: None,
        },
        tracker_cfg.shape_weight,
    )?;

    let write_checkpoint = |written: u64,
                            syncs: &[u64],
                            trackers: &BTreeMap<String, Tracker>,
                            next: usize,
                            complete: bool|
     -> Result<()> {
        checkpoint::write_atomic(
            &opts.checkpoint,
            &ReplayCheckpoint {
                schema: REPLAY_CHECKPOINT_SCHEMA.into(),
                recording: opts.recording.clone(),
                recording_bytes,
                recording_sets: sets.len(),
                settings: fp.clone(),
                next_input: next,
                outputs_written: written,
                syncs: syncs.to_vec(),
                complete,
                trackers: trackers
                    .iter()
                    .map(|(n, t)| (n.clone(), t.checkpoint()))
                    .collect(),
            },
        )
    };

    for (k, (structure, input)) in sets.iter().enumerate().skip(start) {
        let tracker = trackers
            .get_mut(structure)
            .expect("a tracker per watched structure");
        let actions = match input {
            Input::Recorded(msg) => tracker.handle(from_ns(msg.log_time), &msg.data),
            Input::Environment(msg) => tracker.handle_environment(from_ns(msg.log_time), &msg.data),
            Input::Identified(set) => {
                let bytes = serde_json::to_vec(&set.to_json())?;
                let mut a = vec![Action::Publish(Output::Modal(set.clone()))];
                a.extend(tracker.handle(set.time, &bytes));
                a
            }
            Input::Refused {
                log_time,
                rejection,
                head,
                size,
                digest,
            } => vec![Action::Publish(tracker.refuse(
                from_ns(*log_time),
                rejection,
                head,
                *size,
                *digest,
            ))],
        };
        let d = dispatch(structure, actions, &mut lane, &mut out, Pace::Deterministic)?;
        if d.checkpoint_due {
            lane.drain(&mut out)?;
            out.sync()?;
            write_checkpoint(out.written, &out.syncs, &trackers, k + 1, false)?;
        }
        out.summary.processed += 1;
        progress(k + 1, sets.len());
    }
    lane.drain(&mut out)?;
    drop(lane);
    let OutputFile {
        writer,
        syncs,
        mut summary,
        ..
    } = out;
    let w = writer.finish()?;
    summary.outputs = w.written();
    w.finish()?;
    // The final checkpoint is written before the rename; a resume that finds it complete
    // with the rename not done does the rename.
    write_checkpoint(summary.outputs, &syncs, &trackers, sets.len(), true)?;
    std::fs::rename(&part, &opts.out)
        .with_context(|| format!("cannot move {} to {}", part.display(), opts.out.display()))?;
    for (name, t) in &trackers {
        let st = t.state();
        summary.counters.insert(
            name.clone(),
            Counters {
                accepted: st.accepted,
                rejected: st.rejected,
                unconverged: st.unconverged,
                cold_starts: st.cold_starts,
            },
        );
    }
    summary.seconds = started.elapsed().as_secs_f64();
    tracing::info!(
        sets = summary.processed,
        outputs = summary.outputs,
        seconds = summary.seconds,
        "replay complete: {}",
        opts.out.display()
    );
    Ok(summary)
}
