//! The daemon's rolling MCAP log: every modal set received (log time: when it was received)
//! and every output (log time: the time of the set it answers), on the topics and schemas
//! of a replay's output, so `boltwatch replay LOG.mcap` reruns a live session.
//!
//! It is also the write-ahead log: a received set is written ([`RollingLog::write_input`])
//! and made durable ([`RollingLog::sync`], once for every set waiting: group commit) before
//! it is handled, and a checkpoint records the [`WalPosition`] of the first set not yet
//! handled; a restart handles again the sets logged after it ([`RollingLog::inputs_after`]).
//!
//! Files are `<dir>/<structure>-<UTC start>.mcap`. The file being written is
//! `….mcap.part`; it is finished (summary written) and renamed when it reaches the size or
//! age limit (the next file opens at once) and at shutdown, so every `.mcap` file is
//! complete. A `.part` file left by a crash is completed, up to its last readable message,
//! when the next log opens.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::{Context, Result};

use crate::contract::{Output, WalPosition};
use crate::io::mcap::{ChannelSpec, McapWriter, RecordedMessage, read_all, read_tolerant, topic};
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
    /// Modal sets written into it.
    inputs: u64,
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
        let mut channels = vec![
            ChannelSpec::for_structure(structure, "modal")?,
            ChannelSpec::for_structure(structure, "environment")?,
        ];
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
        for entry in std::fs::read_dir(&self.dir)? {
            let part = entry?.path();
            let name = part
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default();
            let Some(stem) = name.strip_suffix(".mcap.part") else {
                continue;
            };
            if file_order(&self.structure, &format!("{stem}.mcap")).is_none() {
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

    /// Writes one output, opening a file if none is open and rotating after it if the file
    /// has reached its size or age limit.
    pub fn write(&mut self, topic: &str, log_time: u64, data: &[u8]) -> Result<()> {
        self.write_message(topic, log_time, data).map(|_| ())
    }

    /// Writes one received input, a modal set or an environment reading (its topic suffix
    /// [`INPUTS`]; log time: its reception); returns its position. Durable once
    /// [`RollingLog::sync`] returns.
    pub fn write_input(&mut self, suffix: &str, log_time: u64, data: &[u8]) -> Result<WalPosition> {
        let key = topic(&self.structure, suffix);
        self.write_message(&key, log_time, data)
    }

    fn write_message(&mut self, topic: &str, log_time: u64, data: &[u8]) -> Result<WalPosition> {
        if self.current.is_none() {
            self.start()?;
        }
        let modal = is_input(topic);
        let f = self.current.as_mut().expect("a log file is open");
        f.w.write(topic, log_time, data)?;
        let at = WalPosition {
            file: file_name(&f.path),
            modal: f.inputs,
        };
        if modal {
            f.inputs += 1;
        }
        let due_size = f.w.written().is_multiple_of(SIZE_CHECK_EVERY)
            && std::fs::metadata(f.part()).map_or(0, |m| m.len()) >= self.rotate_bytes;
        if due_size || f.opened.elapsed() >= self.rotate_age {
            self.rotate()?;
        }
        Ok(at)
    }

    /// The position of the next modal set to be written (opens a file if none is open).
    pub fn next_input(&mut self) -> Result<WalPosition> {
        if self.current.is_none() {
            self.start()?;
        }
        let f = self.current.as_ref().expect("a log file is open");
        Ok(WalPosition {
            file: file_name(&f.path),
            modal: f.inputs,
        })
    }

    /// Closes the open file if it has reached its age limit (called when idle).
    pub fn tick(&mut self) -> Result<()> {
        if self
            .current
            .as_ref()
            .is_some_and(|f| f.opened.elapsed() >= self.rotate_age)
        {
            self.rotate()?;
        }
        Ok(())
    }

    /// Closes the open file and opens the next, so a position always names a file.
    fn rotate(&mut self) -> Result<()> {
        self.close_current()?;
        self.start()
    }

    /// The modal sets logged at and after `from` (in the complete files of the directory,
    /// oldest first), with their reception times: what a restart handles again. A file the
    /// position names that is gone (removed by hand) is reported and skipped.
    pub fn inputs_after(&self, from: &WalPosition) -> Result<Vec<RecordedMessage>> {
        let Some(start) = file_order(&self.structure, &from.file) else {
            anyhow::bail!(
                "write-ahead position {}: not a log file of {}",
                from.file,
                self.structure
            );
        };
        let mut files: Vec<_> = std::fs::read_dir(&self.dir)?
            .filter_map(|e| {
                let name = e.ok()?.file_name().to_string_lossy().into_owned();
                let order = file_order(&self.structure, &name)?;
                (order >= start).then_some((order, name))
            })
            .collect();
        files.sort();
        if files.first().is_none_or(|(o, _)| *o != start) {
            tracing::warn!(
                "write-ahead log file {} is gone: the sets it held after the checkpoint cannot be handled again",
                from.file
            );
        }
        let mut out = Vec::new();
        for (order, name) in files {
            let skip = if order == start { from.modal } else { 0 };
            let path = self.dir.join(&name);
            let inputs = read_all(&path)
                .with_context(|| format!("write-ahead log {}", path.display()))?
                .into_iter()
                .filter(|m| is_input(&m.topic))
                .skip(usize::try_from(skip).unwrap_or(usize::MAX));
            out.extend(inputs);
        }
        Ok(out)
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
            inputs: 0,
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

fn file_name(path: &Path) -> String {
    path.file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default()
}

/// The place of log file `name` among `structure`'s (its UTC start stamp, then its
/// collision counter), or `None` if it is not one: `<structure>-<YYYYmmddTHHMMSS.fffZ>`,
/// optionally `-<k>`, then `.mcap`. (A prefix test alone would take `lab-frame-…` files for
/// structure `lab`'s.)
pub fn file_order(structure: &str, name: &str) -> Option<(String, u64)> {
    let rest = name.strip_prefix(structure)?.strip_prefix('-')?;
    let rest = rest.strip_suffix(".mcap")?;
    let (stamp, k) = match rest.split_once('-') {
        Some((stamp, k)) => (stamp, k.parse().ok()?),
        None => (rest, 0),
    };
    chrono::NaiveDateTime::parse_from_str(stamp, "%Y%m%dT%H%M%S%.3fZ").ok()?;
    Some((stamp.to_string(), k))
}

/// The topic suffixes of the inputs a log holds ahead of their handling: modal sets and
/// environment readings. A [`WalPosition`] counts both (its `modal` field is the number of
/// inputs before it in its file).
pub const INPUTS: [&str; 2] = ["modal", "environment"];

fn is_input(topic: &str) -> bool {
    INPUTS
        .iter()
        .any(|s| topic.strip_suffix(s).is_some_and(|t| t.ends_with('/')))
}

#[cfg(test)]
mod tests {
    use super::file_order;

    #[test]
    fn log_files_are_told_apart_and_ordered() {
        let a = file_order("lab", "lab-20261124T101010.123Z.mcap").unwrap();
        let b = file_order("lab", "lab-20261124T101010.123Z-1.mcap").unwrap();
        let c = file_order("lab", "lab-20261124T101011.000Z.mcap").unwrap();
        assert!(a < b && b < c);
        assert_eq!(
            file_order("lab", "lab-frame-20261124T101010.123Z.mcap"),
            None
        );
        assert_eq!(
            file_order("lab", "lab-20261124T101010.123Z.mcap.part"),
            None
        );
        assert_eq!(
            file_order("frame", "frame-2-20261124T101010.123Z.mcap"),
            None
        );
    }
}
