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
//!
//! The output file, its checkpoints and `--resume` are in the submodule `output`.

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use anyhow::{Result, bail};

use super::driver::{CrosscheckLane, OffPath, Pace, StructureModel, dispatch};
use super::mcap::{
    ChannelSpec, McapWriter, RecordedMessage, for_each_message, from_ns, to_ns, topic,
};
use super::model::{adopt_law, load_structure};
use crate::contract::modal_set::{ModalSet, Rejection};
use crate::contract::{Alert, Estimate, Output};
use crate::pipeline::accel::{AccelFront, FrontEvent, IdentifySettings};
use crate::pipeline::{Action, Prepared, SetScreen, Tracker, TrackerState};
use crate::settings::Settings;

mod output;

pub use output::REPLAY_CHECKPOINT_SCHEMA;
use output::{Checkpoints, OutputFile, Resumed};

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

impl Counters {
    /// The counters in a tracker's state.
    fn of(st: &TrackerState) -> Self {
        Self {
            accepted: st.accepted,
            rejected: st.rejected,
            unconverged: st.unconverged,
            cold_starts: st.cold_starts,
        }
    }
}

impl ReplaySummary {
    /// The summary of a replay of `inputs`, before any is processed.
    fn for_inputs(inputs: &[(String, Input)], skipped_topics: BTreeMap<String, u64>) -> Self {
        let readings = inputs
            .iter()
            .filter(|(_, i)| matches!(i, Input::Environment(_)))
            .count();
        Self {
            sets: inputs.len() - readings,
            readings,
            skipped_topics,
            ..Default::default()
        }
    }

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

/// The input of structure `s` that an [`AccelFront`] event makes: an identified modal set,
/// or a refusal at `log_time` (of the accel block `payload`, or of a window left unfinished).
fn front_input(s: &str, log_time: u64, e: FrontEvent, payload: &[u8]) -> (String, Input) {
    match e {
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
    }
}

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
                    inputs.push(front_input(s, m.log_time, e, &m.data));
                }
            }
            None => *skipped.entry(m.topic).or_insert(0) += 1,
        }
        Ok(())
    })?;
    for (s, (front, last)) in &mut fronts {
        if let Some(e) = front.finish() {
            inputs.push(front_input(s, *last, e, &[]));
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

/// A recording opened for replay.
struct Recording {
    /// The watched structures' models, by name.
    models: HashMap<String, StructureModel>,
    /// The inputs, in log-time order ([`read_inputs`]).
    inputs: Vec<(String, Input)>,
    /// The recording's size in bytes.
    bytes: u64,
    /// The output file's channels ([`output_channels`]).
    channels: Vec<ChannelSpec>,
}

/// Where a replay starts from: the next input, the trackers, and the output file so far
/// (synced at `syncs`).
struct Start {
    next: usize,
    trackers: BTreeMap<String, Tracker>,
    writer: McapWriter,
    syncs: Vec<u64>,
}

/// A replay under way: the off-path lane, the output file, and a tracker per structure.
struct Run {
    lane: OffPath,
    out: OutputFile,
    trackers: BTreeMap<String, Tracker>,
}

/// Replays `opts.recording` (module docs); `progress(done, total)` after every input.
pub fn replay(opts: &ReplayOptions, progress: impl FnMut(usize, usize)) -> Result<ReplaySummary> {
    let started = Instant::now();
    let (recording, skipped) = open_recording(opts)?;
    let checkpoints = Checkpoints::new(opts, &recording);
    let previous = checkpoints.previous()?;
    let mut summary = ReplaySummary::for_inputs(&recording.inputs, skipped);
    let start = match previous {
        Some(c) => match checkpoints.resume(c, &recording, &mut summary)? {
            Resumed::Complete => {
                summary.seconds = started.elapsed().as_secs_f64();
                return Ok(summary);
            }
            Resumed::From(start) => *start,
        },
        None => start_afresh(opts, &recording)?,
    };
    let Recording { models, inputs, .. } = recording;
    let next = start.next;
    let mut run = Run::start(start, summary, models, &opts.settings)?;
    feed(&mut run, &inputs, next, &checkpoints, progress)?;
    finish(opts, run, &checkpoints, started)
}

/// Opens `opts.recording`: loads the watched structures' models, reads their inputs (an
/// error if there are none) and lays out the output file's channels. Returns it with the
/// topics not read and their message counts.
fn open_recording(opts: &ReplayOptions) -> Result<(Recording, BTreeMap<String, u64>)> {
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
    let (inputs, skipped) = read_inputs(&opts.recording, &models, &settings.identify)?;
    if inputs.is_empty() {
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
    let bytes = std::fs::metadata(&opts.recording)?.len();
    tracing::info!(
        sets = inputs.len(),
        structures = names.join(","),
        "replaying {} into {}",
        opts.recording.display(),
        opts.out.display()
    );
    let channels = output_channels(settings, &inputs)?;
    let recording = Recording {
        models,
        inputs,
        bytes,
        channels,
    };
    Ok((recording, skipped))
}

/// The output file's channels: each watched structure's output topics, and `modal` when
/// the recording has raw data (the modal sets identified from it go out there).
fn output_channels(settings: &Settings, inputs: &[(String, Input)]) -> Result<Vec<ChannelSpec>> {
    let raw = inputs
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
    Ok(channels)
}

/// A start from the first input, with no checkpoint: new trackers, an empty `OUT.part`.
fn start_afresh(opts: &ReplayOptions, recording: &Recording) -> Result<Start> {
    if opts.resume {
        tracing::info!(
            "no checkpoint at {}: replaying from the start",
            opts.checkpoint.display()
        );
    }
    let mut trackers = BTreeMap::new();
    for (name, model) in &recording.models {
        let mut t = Tracker::new(model.1.clone(), opts.settings.tracker.clone())?;
        adopt_law(&mut t)?;
        trackers.insert(name.clone(), t);
    }
    Ok(Start {
        next: 0,
        trackers,
        writer: McapWriter::create(&opts.part(), &recording.channels)?,
        syncs: Vec::new(),
    })
}

impl Run {
    /// Starts the writer thread on the output file so far (`start`), and the off-path lane
    /// for `models`.
    fn start(
        start: Start,
        summary: ReplaySummary,
        models: HashMap<String, StructureModel>,
        settings: &Settings,
    ) -> Result<Self> {
        let Start {
            trackers,
            writer,
            syncs,
            ..
        } = start;
        let out = OutputFile::start(writer, syncs, summary)?;
        let lane = OffPath::start(
            "replay-offpath",
            models,
            CrosscheckLane {
                cfg: settings.crosscheck.clone(),
                budget: None,
            },
            settings.tracker.shape_weight,
        )?;
        Ok(Self {
            lane,
            out,
            trackers,
        })
    }
}

/// Feeds the inputs from `next` on, in log-time order, through the shared driver
/// ([`dispatch`]); where a tracker asks for a checkpoint, waits for the off-path lane and
/// checkpoints the run. `progress(done, total)` after every input. A reader thread makes
/// each recorded payload's digest and JSON ([`Prepared`]) a few inputs ahead.
fn feed(
    run: &mut Run,
    inputs: &[(String, Input)],
    next: usize,
    checkpoints: &Checkpoints,
    mut progress: impl FnMut(usize, usize),
) -> Result<()> {
    let ahead = inputs.get(next..).unwrap_or_default();
    let screens: HashMap<String, SetScreen> = run
        .trackers
        .iter()
        .map(|(s, t)| (s.clone(), t.screen().clone()))
        .collect();
    std::thread::scope(|scope| {
        let (tx, rx) = std::sync::mpsc::sync_channel(PREPARED_AHEAD);
        std::thread::Builder::new()
            .name("replay-reader".into())
            .spawn_scoped(scope, move || {
                for (structure, input) in ahead {
                    let prepared = match (input, screens.get(structure.as_str())) {
                        (Input::Recorded(msg), Some(screen)) => Some(screen.prepare(&msg.data)),
                        _ => None,
                    };
                    // The tracking side stopped (an error): nothing left to prepare.
                    if tx.send(prepared).is_err() {
                        break;
                    }
                }
            })?;
        for (k, (structure, input)) in inputs.iter().enumerate().skip(next) {
            let prepared = rx.recv()?;
            let tracker = run
                .trackers
                .get_mut(structure)
                .expect("a tracker per watched structure");
            let actions = track(tracker, input, prepared)?;
            let d = dispatch(
                structure,
                actions,
                &mut run.lane,
                &mut run.out,
                Pace::Deterministic,
            )?;
            if d.checkpoint_due {
                run.lane.drain(&mut run.out)?;
                checkpoints.save(&mut run.out, &run.trackers, k + 1)?;
            }
            run.out.summary.processed += 1;
            progress(k + 1, inputs.len());
        }
        Ok(())
    })
}

/// Recorded payloads the reader thread prepares ahead of the tracking.
const PREPARED_AHEAD: usize = 64;

/// What `tracker` makes of one input (`prepared`: a recorded set's [`Prepared`] payload). A
/// modal set identified from raw data is published (on `modal`) before it is tracked; a
/// refused accel block or window is published as rejected.
fn track(
    tracker: &mut Tracker,
    input: &Input,
    prepared: Option<Prepared<'_>>,
) -> Result<Vec<Action>> {
    Ok(match input {
        Input::Recorded(msg) => {
            let p = prepared.unwrap_or_else(|| tracker.screen().prepare(&msg.data));
            tracker.handle_prepared(from_ns(msg.log_time), p)
        }
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
    })
}

/// Ends the run: waits for the off-path jobs, finishes the output (the final checkpoint,
/// then `OUT`), and completes the summary with the trackers' counters.
fn finish(
    opts: &ReplayOptions,
    mut run: Run,
    checkpoints: &Checkpoints,
    started: Instant,
) -> Result<ReplaySummary> {
    run.lane.drain(&mut run.out)?;
    let Run {
        lane,
        out,
        trackers,
    } = run;
    drop(lane);
    let mut summary = out.finish(&trackers, checkpoints)?;
    for (name, t) in &trackers {
        summary
            .counters
            .insert(name.clone(), Counters::of(t.state()));
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
