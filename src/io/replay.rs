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
use std::sync::mpsc;
use std::time::Instant;

use anyhow::{Context, Result, anyhow, bail};
use serde_json::{Value, json};

use super::checkpoint;
use super::mcap::{
    ChannelSpec, McapWriter, RecordedMessage, from_ns, read_modal_sets, read_tolerant, to_ns, topic,
};
use crate::commands::load_structure;
use crate::core::model::Model;
use crate::core::model::spec::ModelSpec;
use crate::pipeline::crosscheck::{CrosscheckConfig, crosscheck};
use crate::pipeline::verdict::diagnosis_alert;
use crate::pipeline::{Action, CrosscheckRequest, DiagnoseRequest, Tracker, TrackerConfig};
use crate::settings::Settings;

/// Schema of the replay checkpoint file.
pub const REPLAY_CHECKPOINT_SCHEMA: &str = "boltwatch.replay_checkpoint.v1";

/// Output topics of each structure, in declaration order.
pub const OUTPUT_SUFFIXES: [&str; 4] = ["stiffness", "alerts", "crosscheck", "rejected"];

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
    /// Alert payloads, in output order.
    pub alerts: Vec<Value>,
    /// The last estimate of each structure.
    pub last_estimate: BTreeMap<String, Value>,
    /// Counters of each structure's tracker.
    pub counters: BTreeMap<String, Value>,
    pub crosschecks: usize,
    pub rejected: usize,
    /// Messages in the output file.
    pub outputs: u64,
    /// Inputs processed by this run (not counting those before a resume).
    pub processed: usize,
    pub seconds: f64,
}

impl ReplaySummary {
    /// Notes a message read back from a file.
    fn note(&mut self, m: &RecordedMessage) {
        if let Ok(v) = serde_json::from_slice::<Value>(&m.data) {
            self.note_value(&m.topic, &v);
        }
    }

    /// Notes an output by its topic and payload.
    fn note_value(&mut self, topic: &str, v: &Value) {
        match topic.rsplit('/').next().unwrap_or_default() {
            "alerts" => self.alerts.push(v.clone()),
            "stiffness" => {
                let s = v["structure"].as_str().unwrap_or_default().to_string();
                self.last_estimate.insert(s, v.clone());
            }
            "crosscheck" => self.crosschecks += 1,
            "rejected" => self.rejected += 1,
            _ => {}
        }
    }
}

/// Work done off the tracking path.
pub enum Job {
    Crosscheck(Box<CrosscheckRequest>),
    Diagnose(Box<DiagnoseRequest>),
}

/// Runs the cross-checks and diagnoses of every structure on one worker thread, in request
/// order.
struct CrosscheckWorker {
    jobs: Option<mpsc::Sender<(String, u64, Job)>>,
    results: mpsc::Receiver<(String, u64, &'static str, Value)>,
    pending: usize,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl CrosscheckWorker {
    fn start(
        models: HashMap<String, (ModelSpec, Model)>,
        cfg: CrosscheckConfig,
        shape_weight: f64,
    ) -> Self {
        let (jtx, jrx) = mpsc::channel::<(String, u64, Job)>();
        let (rtx, rrx) = mpsc::channel();
        let thread = std::thread::spawn(move || {
            crate::core::sequential_numerics();
            for (s, t, job) in jrx {
                let (spec, model) = &models[&s];
                let r = match job {
                    Job::Crosscheck(req) => {
                        ("crosscheck", crosscheck(model, &cfg, shape_weight, &req))
                    }
                    Job::Diagnose(req) => {
                        ("alerts", diagnosis_alert(spec, model, shape_weight, &req))
                    }
                };
                if rtx.send((s, t, r.0, r.1)).is_err() {
                    return;
                }
            }
        });
        Self {
            jobs: Some(jtx),
            results: rrx,
            pending: 0,
            thread: Some(thread),
        }
    }

    fn submit(&mut self, structure: String, log_time: u64, job: Job) -> Result<()> {
        self.jobs
            .as_ref()
            .ok_or_else(|| anyhow!("cross-check worker stopped"))?
            .send((structure, log_time, job))
            .map_err(|_| anyhow!("cross-check worker stopped"))?;
        self.pending += 1;
        Ok(())
    }

    /// Waits for every submitted job and writes its result.
    fn drain(&mut self, out: &mut Output) -> Result<()> {
        while self.pending > 0 {
            let (s, t, suffix, v) = self
                .results
                .recv()
                .map_err(|_| anyhow!("cross-check worker died"))?;
            self.pending -= 1;
            crate::pipeline::log_output(&s, suffix, &v);
            out.write(&topic(&s, suffix), t, &v)?;
        }
        Ok(())
    }
}

impl Drop for CrosscheckWorker {
    fn drop(&mut self) {
        self.jobs.take();
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// The output file with the summary kept alongside.
struct Output {
    w: McapWriter,
    syncs: Vec<u64>,
    summary: ReplaySummary,
}

impl Output {
    fn write(&mut self, topic: &str, log_time: u64, payload: &Value) -> Result<()> {
        self.w
            .write(topic, log_time, &serde_json::to_vec(payload)?)?;
        self.summary.note_value(topic, payload);
        Ok(())
    }

    fn sync(&mut self) -> Result<()> {
        self.w.sync()?;
        if self.syncs.last() != Some(&self.w.written()) {
            self.syncs.push(self.w.written());
        }
        Ok(())
    }
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
        for suffix in OUTPUT_SUFFIXES {
            channels.push(ChannelSpec::for_structure(&s.name, suffix)?);
        }
        models.insert(s.name.clone(), load_structure(s)?);
    }
    let tracker_cfg: TrackerConfig = settings.tracker.clone();
    let fp = fingerprint(settings);
    let part = opts.part();

    let previous = if opts.resume {
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
            if c["schema"] != REPLAY_CHECKPOINT_SCHEMA {
                bail!(ctx(&format!(
                    "schema is {}, expected {REPLAY_CHECKPOINT_SCHEMA}",
                    c["schema"]
                )));
            }
            if c["recording_bytes"] != recording_bytes || c["recording_sets"] != sets.len() {
                bail!(ctx(&format!(
                    "written for a recording of {} bytes and {} sets, {} has {recording_bytes} bytes and {} sets",
                    c["recording_bytes"],
                    c["recording_sets"],
                    opts.recording.display(),
                    sets.len()
                )));
            }
            if c["settings"] != fp {
                bail!(ctx(
                    "written with a different configuration (structures, tracker or crosscheck); replay without --resume"
                ));
            }
            if c["complete"] == true {
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
                    s.note(m);
                }
                s.seconds = started.elapsed().as_secs_f64();
                return Ok(s);
            }
            let next = c["next_input"]
                .as_u64()
                .ok_or_else(|| anyhow!(ctx("no next_input")))? as usize;
            let written = c["outputs_written"]
                .as_u64()
                .ok_or_else(|| anyhow!(ctx("no outputs_written")))?;
            let syncs: Vec<u64> = serde_json::from_value(c["syncs"].clone())
                .map_err(|e| anyhow!(ctx(&e.to_string())))?;
            for (name, model) in &models {
                let t =
                    Tracker::restore(model.1.clone(), tracker_cfg.clone(), &c["trackers"][name])
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
                summary.note(m);
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
    let mut out = Output { w, syncs, summary };
    let mut worker = CrosscheckWorker::start(
        models,
        settings.crosscheck.clone(),
        tracker_cfg.shape_weight,
    );

    let write_checkpoint = |written: u64,
                            syncs: &[u64],
                            trackers: &BTreeMap<String, Tracker>,
                            next: usize,
                            complete: bool|
     -> Result<()> {
        let states: serde_json::Map<String, Value> = trackers
            .iter()
            .map(|(n, t)| (n.clone(), t.checkpoint()))
            .collect();
        checkpoint::write_atomic(
            &opts.checkpoint,
            &json!({
                "schema": REPLAY_CHECKPOINT_SCHEMA,
                "recording": opts.recording,
                "recording_bytes": recording_bytes,
                "recording_sets": sets.len(),
                "settings": fp,
                "next_input": next,
                "outputs_written": written,
                "syncs": syncs,
                "complete": complete,
                "trackers": states,
            }),
        )
    };

    for (k, (structure, msg)) in sets.iter().enumerate().skip(start) {
        let tracker = trackers
            .get_mut(structure)
            .expect("a tracker per watched structure");
        let actions = tracker.handle(from_ns(msg.log_time), &msg.data);
        let mut checkpoint_due = false;
        for a in actions {
            match a {
                Action::Publish {
                    topic: suffix,
                    time,
                    payload,
                    ..
                } => {
                    let t = to_ns(time)?;
                    crate::pipeline::log_output(structure, suffix, &payload);
                    out.write(&topic(structure, suffix), t, &payload)?;
                }
                Action::Crosscheck(req) => {
                    worker.drain(&mut out)?;
                    let t = to_ns(req.set.time)?;
                    worker.submit(structure.clone(), t, Job::Crosscheck(req))?;
                }
                Action::Diagnose(req) => {
                    worker.drain(&mut out)?;
                    let t = to_ns(req.set.time)?;
                    worker.submit(structure.clone(), t, Job::Diagnose(req))?;
                }
                Action::Checkpoint(_) => checkpoint_due = true,
            }
        }
        if checkpoint_due {
            worker.drain(&mut out)?;
            out.sync()?;
            write_checkpoint(out.w.written(), &out.syncs, &trackers, k + 1, false)?;
        }
        out.summary.processed += 1;
        progress(k + 1, sets.len());
    }
    worker.drain(&mut out)?;
    drop(worker);
    let Output {
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
            json!({
                "accepted": st.accepted, "rejected": st.rejected,
                "unconverged": st.unconverged, "cold_starts": st.cold_starts,
            }),
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
