//! The replay's output file and its checkpoints (parent module docs, **Resumable**): the
//! [`OutputFile`], written on a thread of its own ([`Writer`]); the checkpoint file that
//! records how far the output and the trackers got ([`Checkpoints`]); and `--resume` from
//! it: the checkpoint checked against the recording and the settings, the trackers
//! restored, `OUT.part` rebuilt up to the outputs it counts.

use std::collections::{BTreeMap, HashMap};
use std::path::PathBuf;
use std::sync::mpsc;

use anyhow::{Context, Result, anyhow, bail};
use serde::{Deserialize, Serialize};
use serde_json::{Value, json};

use super::{Recording, ReplayOptions, ReplaySummary, Start, with_suffix};
use crate::contract::{Checkpoint, Output};
use crate::io::checkpoint;
use crate::io::driver::{Sink, StructureModel};
use crate::io::job_thread::JobThread;
use crate::io::mcap::{ChannelSpec, McapWriter, read_all, read_tolerant, to_ns, topic};
use crate::io::model::adopt_law;
use crate::pipeline::{Tracker, TrackerState};
use crate::settings::Settings;

/// Schema of the replay checkpoint file.
pub const REPLAY_CHECKPOINT_SCHEMA: &str = "boltwatch.replay_checkpoint.v1";

/// The output file with the summary kept alongside. Outputs are encoded and written on
/// a thread of their own ([`Writer`]), so that work (on the lab frame ~70 µs a set, the
/// estimate's 8 KB of JSON and its compression) overlaps the tracking of the next set.
pub(super) struct OutputFile {
    writer: Writer,
    /// Outputs handed to the writer (all of them written once it has synced).
    written: u64,
    syncs: Vec<u64>,
    pub(super) summary: ReplaySummary,
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
    /// Goes on writing `w` (the output so far, synced at `syncs`) on a writer thread.
    pub(super) fn start(w: McapWriter, syncs: Vec<u64>, summary: ReplaySummary) -> Result<Self> {
        Ok(Self {
            written: w.written(),
            writer: start_writer(w)?,
            syncs,
            summary,
        })
    }

    /// Ends the output: waits for the writer thread, finishes the file, writes the final
    /// checkpoint, then moves `OUT.part` to `OUT`. Returns the summary, with the number of
    /// outputs in the file.
    pub(super) fn finish(
        self,
        trackers: &BTreeMap<String, Tracker>,
        checkpoints: &Checkpoints,
    ) -> Result<ReplaySummary> {
        let Self {
            writer,
            syncs,
            mut summary,
            ..
        } = self;
        let w = writer.finish()?;
        summary.outputs = w.written();
        w.finish()?;
        // The final checkpoint is written before the rename; a resume that finds it complete
        // with the rename not done does the rename.
        checkpoints.write(
            summary.outputs,
            &syncs,
            trackers,
            checkpoints.recording_sets,
            true,
        )?;
        let (part, out) = (checkpoints.opts.part(), &checkpoints.opts.out);
        std::fs::rename(&part, out)
            .with_context(|| format!("cannot move {} to {}", part.display(), out.display()))?;
        Ok(summary)
    }

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
type Writer = JobThread<WriterJob, McapWriter>;

/// Starts the [`Writer`] thread on `w`.
fn start_writer(mut w: McapWriter) -> Result<Writer> {
    JobThread::start(
        "replay-writer".into(),
        "the output writer",
        "writing the output file",
        WRITER_QUEUE,
        move |jobs| {
            for job in jobs {
                match job {
                    WriterJob::Output(o) => w.write(
                        &topic(o.structure(), o.topic()),
                        to_ns(o.time())?,
                        &o.to_wire(),
                    )?,
                    WriterJob::Encoded { topic, time, bytes } => w.write(&topic, time, &bytes)?,
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
        },
    )
}

/// The replay's checkpoint file: where to go on from, and every tracker's checkpoint.
#[derive(Debug, Serialize, Deserialize)]
pub(super) struct ReplayCheckpoint {
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

/// The replay's checkpoint file, and what a checkpoint in it must match to be resumed:
/// the recording (its size and number of inputs) and the settings' [`fingerprint`].
pub(super) struct Checkpoints<'a> {
    opts: &'a ReplayOptions,
    recording_bytes: u64,
    recording_sets: usize,
    settings: Value,
}

/// What a resume found to go on from.
pub(super) enum Resumed {
    /// The run the checkpoint counts was complete; the summary is that of its output.
    Complete,
    /// Go on from here (boxed: it holds the output's writer, a large value).
    From(Box<Start>),
}

impl<'a> Checkpoints<'a> {
    /// The checkpoint file of a replay of `recording` with `opts`.
    pub(super) fn new(opts: &'a ReplayOptions, recording: &Recording) -> Self {
        Self {
            opts,
            recording_bytes: recording.bytes,
            recording_sets: recording.inputs.len(),
            settings: fingerprint(&opts.settings),
        }
    }

    /// The checkpoint to resume from: with `--resume`, the one in the file if there is one.
    pub(super) fn previous(&self) -> Result<Option<ReplayCheckpoint>> {
        if self.opts.resume {
            checkpoint::read(&self.opts.checkpoint)
        } else {
            Ok(None)
        }
    }

    /// Makes the output durable, then checkpoints the run before input `next`.
    pub(super) fn save(
        &self,
        out: &mut OutputFile,
        trackers: &BTreeMap<String, Tracker>,
        next: usize,
    ) -> Result<()> {
        out.sync()?;
        self.write(out.written, &out.syncs, trackers, next, false)
    }

    /// Writes a checkpoint, atomically: `written` outputs synced at `syncs`, the trackers'
    /// states, the next input, and whether the run is complete.
    fn write(
        &self,
        written: u64,
        syncs: &[u64],
        trackers: &BTreeMap<String, Tracker>,
        next: usize,
        complete: bool,
    ) -> Result<()> {
        checkpoint::write_atomic(
            &self.opts.checkpoint,
            &ReplayCheckpoint {
                schema: REPLAY_CHECKPOINT_SCHEMA.into(),
                recording: self.opts.recording.clone(),
                recording_bytes: self.recording_bytes,
                recording_sets: self.recording_sets,
                settings: self.settings.clone(),
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
    }

    /// The text of an error about the checkpoint file.
    fn message(&self, what: &str) -> String {
        format!("checkpoint {}: {what}", self.opts.checkpoint.display())
    }

    /// Goes on from checkpoint `c`: checks it against the recording and the settings; if
    /// the run it counts was complete, summarises its output ([`Resumed::Complete`]);
    /// otherwise restores the trackers and rebuilds `OUT.part` up to the outputs it counts.
    /// `summary` notes the outputs found.
    pub(super) fn resume(
        &self,
        c: ReplayCheckpoint,
        recording: &Recording,
        summary: &mut ReplaySummary,
    ) -> Result<Resumed> {
        self.check(&c)?;
        if c.complete {
            self.summarise_complete(summary)?;
            return Ok(Resumed::Complete);
        }
        let ReplayCheckpoint {
            next_input: next,
            outputs_written: written,
            syncs,
            trackers: states,
            ..
        } = c;
        let trackers = self.restore_trackers(states, &recording.models)?;
        let writer = self.rebuild_part(&recording.channels, written, &syncs, summary)?;
        tracing::info!(
            next,
            outputs = written,
            "resumed from checkpoint {}",
            self.opts.checkpoint.display()
        );
        summary.resumed_from = Some(next);
        Ok(Resumed::From(Box::new(Start {
            next,
            trackers,
            writer,
            syncs,
        })))
    }

    /// Checks that `c` was written by a replay of this recording with these settings.
    fn check(&self, c: &ReplayCheckpoint) -> Result<()> {
        if c.schema != REPLAY_CHECKPOINT_SCHEMA {
            bail!(self.message(&format!(
                "schema is {}, expected {REPLAY_CHECKPOINT_SCHEMA}",
                c.schema
            )));
        }
        if c.recording_bytes != self.recording_bytes || c.recording_sets != self.recording_sets {
            bail!(self.message(&format!(
                "written for a recording of {} bytes and {} sets, {} has {} bytes and {} sets",
                c.recording_bytes,
                c.recording_sets,
                self.opts.recording.display(),
                self.recording_bytes,
                self.recording_sets
            )));
        }
        if c.settings != self.settings {
            bail!(self.message(
                "written with a different configuration (structures, tracker or crosscheck); replay without --resume"
            ));
        }
        Ok(())
    }

    /// Summarises the output of a complete run, moving `OUT.part` to `OUT` first if the
    /// run was stopped before that rename.
    fn summarise_complete(&self, summary: &mut ReplaySummary) -> Result<()> {
        let (part, out) = (self.opts.part(), &self.opts.out);
        if !out.exists() && part.exists() {
            std::fs::rename(&part, out)
                .with_context(|| format!("cannot move {} to {}", part.display(), out.display()))?;
        }
        summary.already_complete = true;
        let all = read_all(out)?;
        summary.outputs = all.len() as u64;
        for m in &all {
            summary.note_recorded(m);
        }
        Ok(())
    }

    /// Each watched structure's tracker, restored from its state in the checkpoint.
    fn restore_trackers(
        &self,
        mut states: BTreeMap<String, Checkpoint<TrackerState>>,
        models: &HashMap<String, StructureModel>,
    ) -> Result<BTreeMap<String, Tracker>> {
        let mut trackers = BTreeMap::new();
        for (name, model) in models {
            let state = states
                .remove(name)
                .ok_or_else(|| anyhow!(self.message(&format!("no tracker of {name}"))))?;
            let mut t =
                Tracker::restore(model.1.clone(), self.opts.settings.tracker.clone(), state)
                    .with_context(|| self.message(&format!("tracker of {name}")))?;
            adopt_law(&mut t)?;
            trackers.insert(name.clone(), t);
        }
        Ok(trackers)
    }

    /// Copies the first `written` messages of the unfinished `OUT.part` into a fresh file,
    /// syncing at the checkpoint's `syncs` (so its bytes equal those of an uninterrupted
    /// run), and puts it in place of `OUT.part`. Returns its writer, to go on with.
    fn rebuild_part(
        &self,
        channels: &[ChannelSpec],
        written: u64,
        syncs: &[u64],
        summary: &mut ReplaySummary,
    ) -> Result<McapWriter> {
        let part = self.opts.part();
        if !part.exists() {
            bail!(
                "{} is missing, so the outputs the checkpoint {} counts are gone: replay without --resume",
                part.display(),
                self.opts.checkpoint.display()
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
        let mut w = McapWriter::create(&fresh, channels)?;
        for (i, m) in kept.iter().take(written as usize).enumerate() {
            w.copy(m)?;
            summary.note_recorded(m);
            if syncs.binary_search(&(i as u64 + 1)).is_ok() {
                w.sync()?;
            }
        }
        w.sync()?;
        std::fs::rename(&fresh, &part)
            .with_context(|| format!("cannot move {} to {}", fresh.display(), part.display()))?;
        Ok(w)
    }
}
