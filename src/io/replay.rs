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
use std::sync::Arc;
use std::time::Instant;

use anyhow::{Context, Result, anyhow, bail};
use serde::{Deserialize, Serialize};
use serde_json::{Value, json};

use super::checkpoint;
use super::driver::{OffPath, Pace, Sink, dispatch};
use super::mcap::{
    ChannelSpec, McapWriter, RecordedMessage, from_ns, read_modal_sets, read_tolerant, to_ns, topic,
};
use super::model::load_structure;
use crate::contract::{Alert, Checkpoint, Estimate, Output};
use crate::pipeline::{Tracker, TrackerConfig, TrackerState};
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
    /// Modal sets in the recording (all watched structures).
    pub sets: usize,
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
        }
    }
}

/// The output file with the summary kept alongside.
struct OutputFile {
    w: McapWriter,
    syncs: Vec<u64>,
    summary: ReplaySummary,
}

impl Sink for OutputFile {
    fn emit(&mut self, output: &Output, bytes: &[u8]) -> Result<()> {
        let t = to_ns(output.time())?;
        self.w
            .write(&topic(output.structure(), output.topic()), t, bytes)?;
        self.summary.note(output);
        Ok(())
    }
}

impl OutputFile {
    fn sync(&mut self) -> Result<()> {
        self.w.sync()?;
        if self.syncs.last() != Some(&self.w.written()) {
            self.syncs.push(self.w.written());
        }
        Ok(())
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
    })
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
    let (sets, skipped) = read_modal_sets(&opts.recording, &names)?;
    if sets.is_empty() {
        bail!(
            "recording {} has no modal sets of the watched structures ({}); its topics: {}",
            opts.recording.display(),
            names
                .iter()
                .map(|s| topic(s, "modal"))
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
    let mut models = HashMap::new();
    let mut channels = Vec::new();
    for s in &settings.structures {
        for suffix in Output::TOPICS {
            channels.push(ChannelSpec::for_structure(&s.name, suffix)?);
        }
        models.insert(s.name.clone(), Arc::new(load_structure(s)?));
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
    let mut summary = ReplaySummary {
        sets: sets.len(),
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
                let t = Tracker::restore(model.1.clone(), tracker_cfg.clone(), state)
                    .with_context(|| ctx(&format!("tracker of {name}")))?;
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
                trackers.insert(
                    name.clone(),
                    Tracker::new(model.1.clone(), tracker_cfg.clone())?,
                );
            }
            (0, McapWriter::create(&part, &channels)?, Vec::new())
        }
    };
    let mut out = OutputFile { w, syncs, summary };
    let mut lane = OffPath::start(
        "replay-offpath",
        models,
        settings.crosscheck.clone(),
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

    for (k, (structure, msg)) in sets.iter().enumerate().skip(start) {
        let tracker = trackers
            .get_mut(structure)
            .expect("a tracker per watched structure");
        let actions = tracker.handle(from_ns(msg.log_time), &msg.data);
        let d = dispatch(structure, actions, &mut lane, &mut out, Pace::Deterministic)?;
        if d.checkpoint_due {
            lane.drain(&mut out)?;
            out.sync()?;
            write_checkpoint(out.w.written(), &out.syncs, &trackers, k + 1, false)?;
        }
        out.summary.processed += 1;
        progress(k + 1, sets.len());
    }
    lane.drain(&mut out)?;
    drop(lane);
    let OutputFile {
        w,
        syncs,
        mut summary,
    } = out;
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
