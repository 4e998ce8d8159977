//! The daemon's rolling MCAP log: every modal set received (log time: when it was received)
//! and every output (log time: the time of the set it answers), on the topics and schemas
//! of a replay's output, so `boltwatch replay LOG.mcap` reruns a live session.
//!
//! Files are `<dir>/<structure>-<UTC start>.mcap`. The file being written is
//! `….mcap.part`; it is finished (summary written) and renamed when it reaches the size or
//! age limit and at shutdown, so every `.mcap` file is complete. [`RollingLog::sync`] (at
//! every checkpoint) makes everything written so far durable; a `.part` file left by a crash
//! is completed, up to its last readable message, when the next log opens.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::{Context, Result};

use crate::contract::Output;
use crate::io::mcap::{ChannelSpec, McapWriter, read_tolerant};
use crate::io::replay::with_suffix;

/// Messages between two size checks of the open file.
const SIZE_CHECK_EVERY: u64 = 64;

/// The rolling log of one structure (module docs).
pub struct RollingLog {
    dir: PathBuf,
    structure: String,
    channels: Vec<ChannelSpec>,
    rotate_bytes: u64,
    rotate_age: Duration,
    current: Option<OpenFile>,
    /// Files closed (finished) by this log, oldest first.
    pub closed: Vec<PathBuf>,
}

struct OpenFile {
    path: PathBuf,
    w: McapWriter,
    opened: Instant,
}

impl OpenFile {
    fn part(&self) -> PathBuf {
        with_suffix(&self.path, ".part")
    }
}

impl RollingLog {
    /// A log in `dir` (created if missing); completes the `.part` files of `structure` a
    /// crash left there. No file is created until the first message.
    pub fn open(
        dir: &Path,
        structure: &str,
        rotate_bytes: u64,
        rotate_age: Duration,
    ) -> Result<Self> {
        std::fs::create_dir_all(dir)
            .with_context(|| format!("cannot create log directory {}", dir.display()))?;
        let mut channels = vec![ChannelSpec::for_structure(structure, "modal")?];
        for suffix in Output::TOPICS {
            channels.push(ChannelSpec::for_structure(structure, suffix)?);
        }
        let log = Self {
            dir: dir.to_path_buf(),
            structure: structure.to_string(),
            channels,
            rotate_bytes,
            rotate_age,
            current: None,
            closed: Vec::new(),
        };
        log.recover()?;
        Ok(log)
    }

    /// Completes every `<structure>-*.mcap.part` in the directory.
    fn recover(&self) -> Result<()> {
        let prefix = format!("{}-", self.structure);
        for entry in std::fs::read_dir(&self.dir)? {
            let part = entry?.path();
            let name = part
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default();
            let Some(stem) = name.strip_suffix(".mcap.part") else {
                continue;
            };
            if !stem.starts_with(&prefix) {
                continue;
            }
            let target = part.with_file_name(format!("{stem}.mcap"));
            let (messages, stop) = match read_tolerant(&part) {
                Ok(x) => x,
                Err(e) => {
                    tracing::warn!(
                        "log {} left by a crash is unreadable ({e:#}); kept as it is",
                        part.display()
                    );
                    continue;
                }
            };
            let tmp = with_suffix(&part, ".recover");
            let mut w = McapWriter::create(&tmp, &self.channels)?;
            for m in &messages {
                w.copy(m)?;
            }
            w.finish()?;
            std::fs::rename(&tmp, &target).with_context(|| {
                format!("cannot move {} to {}", tmp.display(), target.display())
            })?;
            std::fs::remove_file(&part)
                .with_context(|| format!("cannot remove {}", part.display()))?;
            tracing::warn!(
                messages = messages.len(),
                "log {} was left unfinished by a crash: completed as {}{}",
                part.display(),
                target.display(),
                stop.map(|s| format!(" (the rest was unreadable: {s})"))
                    .unwrap_or_default()
            );
        }
        Ok(())
    }

    /// Writes one message, opening a file if none is open and rotating after it if the file
    /// has reached its size or age limit.
    pub fn write(&mut self, topic: &str, log_time: u64, data: &[u8]) -> Result<()> {
        if self.current.is_none() {
            self.start()?;
        }
        let f = self.current.as_mut().expect("a log file is open");
        f.w.write(topic, log_time, data)?;
        let due_size = f.w.written().is_multiple_of(SIZE_CHECK_EVERY)
            && std::fs::metadata(f.part()).map_or(0, |m| m.len()) >= self.rotate_bytes;
        if due_size || f.opened.elapsed() >= self.rotate_age {
            self.close_current()?;
        }
        Ok(())
    }

    /// Closes the open file if it has reached its age limit (called when idle).
    pub fn tick(&mut self) -> Result<()> {
        if self
            .current
            .as_ref()
            .is_some_and(|f| f.opened.elapsed() >= self.rotate_age)
        {
            self.close_current()?;
        }
        Ok(())
    }

    /// Makes everything written so far durable.
    pub fn sync(&mut self) -> Result<()> {
        if let Some(f) = self.current.as_mut() {
            f.w.sync()?;
        }
        Ok(())
    }

    /// The file being written (its final name), if any.
    pub fn current(&self) -> Option<&Path> {
        self.current.as_ref().map(|f| f.path.as_path())
    }

    /// Finishes and renames the open file (shutdown).
    pub fn close(mut self) -> Result<Vec<PathBuf>> {
        self.close_current()?;
        Ok(self.closed)
    }

    fn start(&mut self) -> Result<()> {
        let stamp = chrono::Utc::now().format("%Y%m%dT%H%M%S%.3fZ");
        let mut path = self.dir.join(format!("{}-{stamp}.mcap", self.structure));
        let mut k = 1;
        while path.exists() || with_suffix(&path, ".part").exists() {
            path = self
                .dir
                .join(format!("{}-{stamp}-{k}.mcap", self.structure));
            k += 1;
        }
        let w = McapWriter::create(&with_suffix(&path, ".part"), &self.channels)?;
        tracing::info!("logging {} into {}", self.structure, path.display());
        self.current = Some(OpenFile {
            path,
            w,
            opened: Instant::now(),
        });
        Ok(())
    }

    fn close_current(&mut self) -> Result<()> {
        if let Some(f) = self.current.take() {
            let part = f.part();
            f.w.finish()?;
            std::fs::rename(&part, &f.path).with_context(|| {
                format!("cannot move {} to {}", part.display(), f.path.display())
            })?;
            tracing::info!("log file closed: {}", f.path.display());
            self.closed.push(f.path);
        }
        Ok(())
    }
}
