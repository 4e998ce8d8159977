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
}

/// One estimate: its set's time (ms since the Unix epoch) and its parameters, in the
/// model's order.
#[derive(Debug, Clone)]
pub struct Sample {
    pub time_ms: i64,
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
            })
            .collect();
        self.samples.push(Sample {
            time_ms: e.time.timestamp_millis(),
            points,
        });
    }

    /// Appends `other` (a later file's history).
    fn extend(&mut self, other: &History) {
        if self.names.is_empty() {
            self.names = other.names.clone();
        }
        self.samples.extend(other.samples.iter().cloned());
        self.marks.extend(other.marks.iter().cloned());
    }

    /// Only what happened at or after `from_ms`.
    pub fn since(mut self, from_ms: i64) -> Self {
        self.samples.retain(|s| s.time_ms >= from_ms);
        self.marks.retain(|m| m.time_ms >= from_ms);
        self
    }
}

/// The history of closed log files, bounded in bytes.
pub struct Cache {
    max_bytes: usize,
    bytes: usize,
    /// File → (its history, when it was last used).
    files: HashMap<PathBuf, (Arc<History>, u64)>,
    clock: u64,
}

impl Cache {
    pub fn new(max_bytes: usize) -> Self {
        Self {
            max_bytes,
            bytes: 0,
            files: HashMap::new(),
            clock: 0,
        }
    }

    /// The bytes the cache holds now.
    pub fn bytes(&self) -> usize {
        self.bytes
    }

    /// `structure`'s history from its log files in `dir`, oldest first.
    pub fn history(&mut self, dir: &Path, structure: &str) -> Result<History> {
        let mut all = History::default();
        for path in log_files(dir, structure)? {
            if path.extension().is_some_and(|e| e == "part") {
                all.extend(&read_part(&path, structure)?);
            } else {
                let h = self.closed(&path, structure)?;
                all.extend(&h);
            }
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
        let h = Arc::new(h);
        self.bytes += h.bytes();
        self.files
            .insert(path.to_path_buf(), (h.clone(), self.clock));
        self.evict();
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

/// The file being written, up to its last complete chunk.
fn read_part(path: &Path, structure: &str) -> Result<History> {
    let (messages, _) =
        read_tolerant(path).with_context(|| format!("reading {}", path.display()))?;
    let mut h = History::default();
    for m in &messages {
        h.add(structure, m)?;
    }
    Ok(h)
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
