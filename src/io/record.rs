//! Raw vibration records from files, with an optional sidecar `FILE.json` beside `FILE.csv`
//! or `FILE.npy`:
//!
//! - CSV with a header `time_s,<channel>,…`, uniformly sampled;
//! - a NumPy `.npy` array of samples (rows) by channels (columns), float64, either byte
//!   order, C or Fortran order (as pyOMA and most Python OMA tools keep their records). It
//!   has no time column: its sidecar must give `rate_hz`, and its columns are `ch1`, `ch2`,
//!   … unless the sidecar names them.
//!
//! The sidecar (all keys optional): `rate_hz` (checked against a CSV's time column, which
//! it then need not resolve finely), `unit` (one unit for every channel) or `units` (one per
//! column, for channels of mixed quantities; [`crate::core::oma::UNITS`], default `m/s^2`:
//! samples are converted to SI as they are read), `structure`, `channels` (the model's names
//! for the columns, in order: a rename; `null` leaves a column out, e.g. a sensor that was
//! not working), `start` (RFC 3339 time of the first sample). Unknown keys are refused,
//! naming them.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use chrono::{DateTime, Utc};
use faer::Mat;
use serde::Deserialize;

use crate::core::oma::Record;

/// The sidecar of a record file (module docs).
#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Sidecar {
    pub rate_hz: Option<f64>,
    pub unit: Option<String>,
    pub units: Option<Vec<String>>,
    pub structure: Option<String>,
    pub channels: Option<Vec<Option<String>>>,
    pub start: Option<DateTime<Utc>>,
}

/// Sampling intervals may differ from their median by this fraction (a time column
/// written with 6 significant digits at 1 kHz resolves 1e-3 s steps to ~1e-6 relative).
const UNIFORM_TOLERANCE: f64 = 1e-3;

/// A record read from a CSV file, with its sidecar, and the time of its first sample in
/// the file's time column (s).
#[derive(Debug, Clone)]
pub struct RecordFile {
    pub record: Record,
    pub sidecar: Sidecar,
    pub t0_s: f64,
}

/// Reads a record file (module docs) by its extension: `.npy` or CSV.
pub fn read_record(path: &Path) -> Result<RecordFile> {
    match path.extension().and_then(|e| e.to_str()) {
        Some("npy") => read_npy(path),
        _ => read_csv(path),
    }
}

/// The sidecar of `path` (`FILE.json`; empty when there is none) and its path.
fn read_sidecar(path: &Path) -> Result<(Sidecar, PathBuf)> {
    let sidecar_path = path.with_extension("json");
    if !sidecar_path.exists() {
        return Ok((Sidecar::default(), sidecar_path));
    }
    let s = std::fs::read_to_string(&sidecar_path)
        .with_context(|| format!("cannot read {}", sidecar_path.display()))?;
    let sidecar =
        serde_json::from_str(&s).with_context(|| format!("{}", sidecar_path.display()))?;
    Ok((sidecar, sidecar_path))
}

/// Reads `path` (CSV, module docs) and its sidecar. Every failure names the file, and the
/// line and column where there is one.
pub fn read_csv(path: &Path) -> Result<RecordFile> {
    let name = path.display();
    let text = std::fs::read_to_string(path).with_context(|| format!("cannot read {}", name))?;
    let (sidecar, sidecar_path) = read_sidecar(path)?;
    let mut lines = numbered_lines(&text).into_iter();
    let Some((_, header)) = lines.next() else {
        bail!("{name}: empty file (expected a header `time_s,<channel>,…`)");
    };
    let columns: Vec<&str> = header.split(',').map(str::trim).collect();
    if columns.first() != Some(&"time_s") || columns.len() < 2 {
        bail!("{name}: line 1: the header must be `time_s,<channel>,…`, got `{header}`");
    }
    let rows: Vec<(usize, &str)> = lines.collect();
    let (times, values) = parse_csv_rows(path, &columns, &rows)?;
    let n = times.len();
    if n < 3 {
        bail!("{name}: {n} samples: too few to identify anything");
    }
    let dt = uniform_step(path, &times, &rows)?;
    let rate_hz = match sidecar.rate_hz {
        Some(f) if f > 0.0 && f.is_finite() => {
            if (f * dt - 1.0).abs() > UNIFORM_TOLERANCE {
                bail!(
                    "{}: rate_hz = {f} disagrees with the time column of {name} (median step {dt:e} s)",
                    sidecar_path.display()
                );
            }
            f
        }
        Some(f) => bail!("{}: rate_hz = {f} must be > 0", sidecar_path.display()),
        None => 1.0 / dt,
    };
    let r = columns.len() - 1;
    let columns = Columns {
        names: columns[1..].iter().map(|c| c.to_string()).collect(),
        n,
        value: |k: usize, c: usize| values[k * r + c],
    };
    finish(path, &sidecar_path, sidecar, columns, rate_hz, times[0])
}

/// The lines of `text` that hold something (not blank, not a `#` comment), each with its
/// index in the file; split in parallel over pieces that end at a line break.
fn numbered_lines(text: &str) -> Vec<(usize, &str)> {
    use rayon::prelude::*;
    const PIECE: usize = 1 << 20;
    let mut pieces = Vec::new();
    let mut start = 0;
    while start < text.len() {
        let end = text[(start + PIECE).min(text.len())..]
            .find('\n')
            .map_or(text.len(), |i| (start + PIECE).min(text.len()) + i + 1);
        pieces.push(&text[start..end]);
        start = end;
    }
    let split: Vec<(usize, Vec<(usize, &str)>)> = pieces
        .par_iter()
        .map(|piece| {
            let mut count = 0;
            let kept = piece
                .lines()
                .inspect(|_| count += 1)
                .enumerate()
                .filter(|(_, l)| !l.trim().is_empty() && !l.starts_with('#'))
                .collect();
            (count, kept)
        })
        .collect();
    let mut offset = 0;
    let mut out = Vec::with_capacity(split.iter().map(|p| p.1.len()).sum());
    for (count, kept) in split {
        out.extend(kept.into_iter().map(|(i, l)| (i + offset, l)));
        offset += count;
    }
    out
}

/// The samples and time column of the CSV rows, parsed in parallel chunks (the text is
/// already in memory); the first error in file order is reported.
fn parse_csv_rows(
    path: &Path,
    columns: &[&str],
    rows: &[(usize, &str)],
) -> Result<(Vec<f64>, Vec<f64>)> {
    let name = path.display();
    let r = columns.len() - 1;
    let parse_rows = |chunk: &[(usize, &str)]| -> Result<(Vec<f64>, Vec<f64>)> {
        let mut times = Vec::with_capacity(chunk.len());
        let mut values = Vec::with_capacity(chunk.len() * r);
        for &(i, line) in chunk {
            let mut n = 0;
            for (j, field) in line.split(',').enumerate() {
                let column = columns.get(j).unwrap_or(&"?");
                let v: f64 = field.trim().parse().map_err(|_| {
                    anyhow::anyhow!(
                        "{name}: line {}, column {} (`{column}`): `{}` is not a number",
                        i + 1,
                        j + 1,
                        field.trim()
                    )
                })?;
                if !v.is_finite() {
                    bail!(
                        "{name}: line {}, column {} (`{column}`): {v} is not finite",
                        i + 1,
                        j + 1,
                    );
                }
                if j == 0 {
                    times.push(v);
                } else if j <= r {
                    values.push(v);
                }
                n += 1;
            }
            if n != r + 1 {
                bail!(
                    "{name}: line {}: {n} fields, the header has {}",
                    i + 1,
                    r + 1
                );
            }
        }
        Ok((times, values))
    };
    let parsed: Vec<Result<(Vec<f64>, Vec<f64>)>> = {
        use rayon::prelude::*;
        rows.par_chunks(4096).map(parse_rows).collect()
    };
    let mut times = Vec::with_capacity(rows.len());
    let mut values: Vec<f64> = Vec::with_capacity(rows.len() * r);
    for p in parsed {
        let (t, v) = p?;
        times.extend(t);
        values.extend(v);
    }
    Ok((times, values))
}

/// The median step of the time column, once every step is within [`UNIFORM_TOLERANCE`] of
/// it.
fn uniform_step(path: &Path, times: &[f64], rows: &[(usize, &str)]) -> Result<f64> {
    let name = path.display();
    let mut steps: Vec<f64> = times.windows(2).map(|w| w[1] - w[0]).collect();
    steps.sort_by(f64::total_cmp);
    let dt = steps[steps.len() / 2];
    if dt <= 0.0 {
        bail!("{name}: the time column does not increase");
    }
    if let Some((k, w)) = times
        .windows(2)
        .enumerate()
        .find(|(_, w)| ((w[1] - w[0]) / dt - 1.0).abs() > UNIFORM_TOLERANCE)
    {
        bail!(
            "{name}: not uniformly sampled: line {} steps {:.6e} s after a median step of {dt:.6e} s (a gap or a repeated time?)",
            rows[k + 1].0 + 1,
            w[1] - w[0]
        );
    }
    Ok(dt)
}

/// Reads `path` (`.npy`, module docs) and its sidecar, which must give `rate_hz`.
pub fn read_npy(path: &Path) -> Result<RecordFile> {
    let name = path.display();
    let bytes = std::fs::read(path).with_context(|| format!("cannot read {name}"))?;
    let (sidecar, sidecar_path) = read_sidecar(path)?;
    let npy =
        npyz::NpyFile::new(&bytes[..]).with_context(|| format!("{name}: not a NumPy .npy file"))?;
    let (n, r) = match npy.shape()[..] {
        [n, r] => (n as usize, r as usize),
        ref other => bail!("{name}: an array of shape {other:?}: need (samples, channels)"),
    };
    let fortran = npy.order() == npyz::Order::Fortran;
    let dtype = npy.dtype();
    let values: Vec<f64> = npy
        .into_vec()
        .map_err(|e| anyhow::anyhow!("{name}: elements of type {dtype:?}: need float64 ({e})"))?;
    if n < 3 || r == 0 {
        bail!("{name}: {n} samples of {r} channels: too few to identify anything");
    }
    let index = |k: usize, c: usize| if fortran { c * n + k } else { k * r + c };
    if let Some(i) = (0..n * r).find(|&i| !values[i].is_finite()) {
        let (k, c) = if fortran {
            (i % n, i / n)
        } else {
            (i / r, i % r)
        };
        bail!(
            "{name}: sample {k}, column {c}: {} is not finite",
            values[i]
        );
    }
    let rate_hz = match sidecar.rate_hz {
        Some(f) if f > 0.0 && f.is_finite() => f,
        Some(f) => bail!("{}: rate_hz = {f} must be > 0", sidecar_path.display()),
        None => bail!(
            "{name} has no time column: its sidecar {} must give rate_hz",
            sidecar_path.display()
        ),
    };
    let columns = Columns {
        names: (1..=r).map(|c| format!("ch{c}")).collect(),
        n,
        value: |k: usize, c: usize| values[index(k, c)],
    };
    finish(path, &sidecar_path, sidecar, columns, rate_hz, 0.0)
}

/// The columns of a record file as read: their names in the file (or by default), the
/// number of samples, and sample k of column c.
struct Columns<F: Fn(usize, usize) -> f64> {
    names: Vec<String>,
    n: usize,
    value: F,
}

/// The record of `columns` under its sidecar: columns renamed or left out (`channels`),
/// converted to SI (`unit`/`units`).
fn finish<F: Fn(usize, usize) -> f64>(
    path: &Path,
    sidecar_path: &Path,
    sidecar: Sidecar,
    columns: Columns<F>,
    rate_hz: f64,
    t0_s: f64,
) -> Result<RecordFile> {
    let name = path.display();
    let r = columns.names.len();
    let names: Vec<Option<String>> = match &sidecar.channels {
        Some(rename) if rename.len() != r => bail!(
            "{}: channels: {} names for the {r} columns of {name}",
            sidecar_path.display(),
            rename.len(),
        ),
        Some(rename) => rename.clone(),
        None => columns.names.iter().cloned().map(Some).collect(),
    };
    let mut seen = std::collections::HashSet::new();
    for c in names.iter().flatten() {
        if c.is_empty() || !seen.insert(c.as_str()) {
            bail!("{name}: channel `{c}` is empty or named twice");
        }
    }
    let kept: Vec<usize> = (0..r).filter(|&c| names[c].is_some()).collect();
    if kept.is_empty() {
        bail!(
            "{}: channels: every column is left out",
            sidecar_path.display()
        );
    }
    let units: Vec<String> = match (&sidecar.unit, &sidecar.units) {
        (Some(_), Some(_)) => bail!(
            "{}: give `unit` (every channel) or `units` (one per column), not both",
            sidecar_path.display()
        ),
        (Some(u), None) => vec![u.clone(); r],
        (None, Some(us)) if us.len() == r => us.clone(),
        (None, Some(us)) => bail!(
            "{}: units: {} units for the {r} columns of {name}",
            sidecar_path.display(),
            us.len()
        ),
        (None, None) => vec!["m/s^2".to_string(); r],
    };
    let mut channels = Vec::with_capacity(kept.len());
    let mut quantities = Vec::with_capacity(kept.len());
    let mut factors = Vec::with_capacity(kept.len());
    for &c in &kept {
        let channel = names[c].clone().expect("kept columns are named");
        let (q, f) = crate::core::oma::parse_unit(&units[c])
            .map_err(|e| anyhow::anyhow!("{}: channel `{channel}`: {e}", sidecar_path.display()))?;
        channels.push(channel);
        quantities.push(q);
        factors.push(f);
    }
    let samples = Mat::from_fn(columns.n, kept.len(), |k, j| {
        (columns.value)(k, kept[j]) * factors[j]
    });
    Ok(RecordFile {
        record: Record {
            channels,
            rate_hz,
            samples,
            quantities,
        },
        sidecar,
        t0_s,
    })
}

/// Writes `record` as CSV (module docs), times from `t0_s`, each number in the shortest
/// form that reads back to the same value.
pub fn write_csv(path: &Path, record: &Record, t0_s: f64) -> Result<()> {
    use std::io::Write;
    let file =
        std::fs::File::create(path).with_context(|| format!("cannot write {}", path.display()))?;
    let mut w = std::io::BufWriter::new(file);
    writeln!(w, "time_s,{}", record.channels.join(","))?;
    for k in 0..record.len() {
        write!(w, "{}", t0_s + k as f64 / record.rate_hz)?;
        for c in 0..record.channels.len() {
            write!(w, ",{}", record.samples[(k, c)])?;
        }
        writeln!(w)?;
    }
    w.flush()?;
    Ok(())
}
