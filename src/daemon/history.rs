//! A structure's history read back from the daemon's own rolling logs (no second database):
//! per estimate, each parameter's θ, filtered level, its 95 % band and the baseline, and
//! every alert. Closed log files never change, so what was read from one is kept in a cache
//! bounded in bytes (least recently used first out); the file still being written
//! (`.mcap.part`) is read again each time, up to its last complete chunk.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::{Context, Result};

use crate::contract::{Alert, AlertKind, AlertLevel, Estimate};
use crate::io::mcap::{RecordedMessage, for_each_message, read_tolerant};

/// One parameter in one estimate (f32: the console draws it; NaN when absent).
#[derive(Debug, Clone, Copy)]
pub struct Point {
    pub theta: f32,
    pub level: f32,
    pub lower95: f32,
    pub upper95: f32,
    pub baseline: f32,
    /// θ expected of a healthy structure under the set's conditions (normalised
    /// structures).
    pub expected: f32,
}

/// One estimate: its set's time (ms since the Unix epoch) and its parameters, in the
/// model's order.
#[derive(Debug, Clone)]
pub struct Sample {
    pub time_ms: i64,
    /// ε (6) of the estimate and its χ² bound.
    pub epsilon: f32,
    pub epsilon_bound: f32,
    pub points: Vec<Point>,
}

/// An alert on the time axis.
#[derive(Debug, Clone, PartialEq)]
pub struct Mark {
    pub time_ms: i64,
    pub connection: Option<String>,
    pub kind: AlertKind,
    pub level: AlertLevel,
}

/// What one log file (or the whole history) holds of a structure's outputs.
#[derive(Debug, Clone, Default)]
pub struct History {
    /// The parameters' names, in the order of [`Sample::points`].
    pub names: Vec<String>,
    pub samples: Vec<Sample>,
    pub marks: Vec<Mark>,
}

impl History {
    /// Its size in memory, roughly (what the cache counts).
    pub fn bytes(&self) -> usize {
        let points: usize = self.samples.iter().map(|s| s.points.len()).sum();
        points * std::mem::size_of::<Point>()
            + self.samples.len() * std::mem::size_of::<Sample>()
            + self.marks.len() * (std::mem::size_of::<Mark>() + 16)
    }

    /// Files one logged message of `structure`; others are ignored.
    fn add(&mut self, structure: &str, m: &RecordedMessage) -> Result<()> {
        let Some(suffix) = m
            .topic
            .strip_prefix("boltwatch/")
            .and_then(|t| t.strip_prefix(structure))
            .and_then(|t| t.strip_prefix('/'))
        else {
            return Ok(());
        };
        match suffix {
            "stiffness" => {
                let e: Estimate = serde_json::from_slice(&m.data).context("a logged estimate")?;
                self.add_estimate(&e);
            }
            "alerts" => {
                let a: Alert = serde_json::from_slice(&m.data).context("a logged alert")?;
                self.marks.push(Mark {
                    time_ms: a.time.timestamp_millis(),
                    connection: a.connection,
                    kind: a.kind,
                    level: a.level,
                });
            }
            _ => {}
        }
        Ok(())
    }

    fn add_estimate(&mut self, e: &Estimate) {
        if self.names.is_empty() {
            self.names = e.parameters.iter().map(|p| p.name.clone()).collect();
        }
        let nan = |v: Option<f64>| v.map_or(f32::NAN, |v| v as f32);
        let points = e
            .parameters
            .iter()
            .map(|p| Point {
                theta: p.theta as f32,
                level: p.filtered.level as f32,
                lower95: p.filtered.lower95 as f32,
                upper95: p.filtered.upper95 as f32,
                baseline: nan(p.baseline),
                expected: nan(p.normalised.as_ref().map(|n| n.expected)),
            })
            .collect();
        self.samples.push(Sample {
            time_ms: e.time.timestamp_millis(),
            epsilon: e.epsilon as f32,
            epsilon_bound: e.epsilon_bound as f32,
            points,
        });
    }
}

/// A structure's whole history: its log files' histories, oldest first, shared with the
/// cache (nothing is copied per request).
#[derive(Debug, Clone, Default)]
pub struct Logged {
    pub files: Vec<Arc<History>>,
}

impl Logged {
    /// The parameters' names (the first file's that has any).
    pub fn names(&self) -> &[String] {
        self.files
            .iter()
            .find(|f| !f.names.is_empty())
            .map_or(&[], |f| &f.names)
    }

    /// Every estimate, oldest first.
    pub fn samples(&self) -> impl DoubleEndedIterator<Item = &Sample> {
        self.files.iter().flat_map(|f| f.samples.iter())
    }

    /// Every alert, oldest first.
    pub fn marks(&self) -> impl Iterator<Item = &Mark> {
        self.files.iter().flat_map(|f| f.marks.iter())
    }

    /// The estimates at or after `from_ms` (every one for `None`).
    pub fn samples_since(&self, from_ms: Option<i64>) -> Vec<&Sample> {
        let from = from_ms.unwrap_or(i64::MIN);
        self.samples().filter(|s| s.time_ms >= from).collect()
    }
}

/// The history of closed log files, bounded in bytes.
pub struct Cache {
    max_bytes: usize,
    bytes: usize,
    /// File → (its history, when it was last used).
    files: HashMap<PathBuf, (Arc<History>, u64)>,
    clock: u64,
    /// Per structure, the last file being written that was read: its path, length and
    /// time, and its history.
    parts: HashMap<String, PartRead>,
}

/// What was read of a file being written.
struct PartRead {
    path: PathBuf,
    /// Its length and modification time then.
    stamp: (u64, Option<std::time::SystemTime>),
    /// The messages read (of every topic).
    messages: usize,
    history: Arc<History>,
}

impl Cache {
    pub fn new(max_bytes: usize) -> Self {
        Self {
            max_bytes,
            bytes: 0,
            files: HashMap::new(),
            clock: 0,
            parts: HashMap::new(),
        }
    }

    /// The bytes the cache holds now: the closed files' histories (within the bound) and,
    /// per structure, the file being written (bounded by the logs' rotation size).
    pub fn bytes(&self) -> usize {
        self.bytes
            + self
                .parts
                .values()
                .map(|p| p.history.bytes())
                .sum::<usize>()
    }

    /// `structure`'s history from its log files in `dir`, oldest first.
    pub fn history(&mut self, dir: &Path, structure: &str) -> Result<Logged> {
        let mut all = Logged::default();
        for path in log_files(dir, structure)? {
            let h = if path.extension().is_some_and(|e| e == "part") {
                self.part(&path, structure)?
            } else {
                self.closed(&path, structure)?
            };
            all.files.push(h);
        }
        Ok(all)
    }

    /// A closed file's history, from the cache or read and then kept.
    fn closed(&mut self, path: &Path, structure: &str) -> Result<Arc<History>> {
        self.clock += 1;
        if let Some((h, used)) = self.files.get_mut(path) {
            *used = self.clock;
            return Ok(h.clone());
        }
        let mut h = History::default();
        for_each_message(path, |m| h.add(structure, &m))
            .with_context(|| format!("reading {}", path.display()))?;
        // It never grows again: hold what it uses (the bound counts that).
        h.samples.shrink_to_fit();
        h.marks.shrink_to_fit();
        let h = Arc::new(h);
        self.bytes += h.bytes();
        self.files
            .insert(path.to_path_buf(), (h.clone(), self.clock));
        self.evict();
        Ok(h)
    }

    /// The file being written: when its length or time changed since the last read (it
    /// only grows), the messages after those already read are added to what they gave;
    /// else the last read's history.
    fn part(&mut self, path: &Path, structure: &str) -> Result<Arc<History>> {
        let meta =
            std::fs::metadata(path).with_context(|| format!("reading {}", path.display()))?;
        let stamp = (meta.len(), meta.modified().ok());
        let (mut h, seen) = match self.parts.remove(structure) {
            Some(p) if p.path == path && p.stamp == stamp => {
                let h = p.history.clone();
                self.parts.insert(structure.to_string(), p);
                return Ok(h);
            }
            Some(p) if p.path == path => (p.history, p.messages),
            _ => (Arc::new(History::default()), 0),
        };
        let (messages, _) =
            read_tolerant(path).with_context(|| format!("reading {}", path.display()))?;
        if messages.len() < seen {
            // Not the file read before (it only grows): read it afresh.
            h = Arc::new(History::default());
        }
        let from = if messages.len() < seen { 0 } else { seen };
        let grown = Arc::make_mut(&mut h);
        for m in &messages[from..] {
            grown.add(structure, m)?;
        }
        let read = PartRead {
            path: path.to_path_buf(),
            stamp,
            messages: messages.len(),
            history: h.clone(),
        };
        self.parts.insert(structure.to_string(), read);
        Ok(h)
    }

    /// Drops the least recently used files until the cache fits its bound.
    fn evict(&mut self) {
        while self.bytes > self.max_bytes {
            let Some(oldest) = self
                .files
                .iter()
                .min_by_key(|(_, (_, used))| *used)
                .map(|(p, _)| p.clone())
            else {
                break;
            };
            if let Some((h, _)) = self.files.remove(&oldest) {
                self.bytes -= h.bytes();
            }
        }
    }
}

/// `structure`'s log files in `dir` in the order they were written, the one being
/// written (`.mcap.part`) last.
fn log_files(dir: &Path, structure: &str) -> Result<Vec<PathBuf>> {
    let mut files: Vec<((String, u64), bool, PathBuf)> = Vec::new();
    let entries = match std::fs::read_dir(dir) {
        Ok(e) => e,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(e) => return Err(e).with_context(|| format!("listing {}", dir.display())),
    };
    for entry in entries {
        let path = entry?.path();
        let name = path
            .file_name()
            .and_then(|n| n.to_str())
            .unwrap_or_default();
        let closed = name.strip_suffix(".part").unwrap_or(name);
        if let Some(order) = super::log::file_order(structure, closed) {
            files.push((order, name.ends_with(".part"), path));
        }
    }
    files.sort();
    Ok(files.into_iter().map(|(_, _, p)| p).collect())
}
