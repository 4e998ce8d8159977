//! Raw vibration records from files: CSV with a header `time_s,<channel>,…`, uniformly
//! sampled, and an optional sidecar `FILE.json` next to `FILE.csv`.
//!
//! The sidecar (all keys optional): `rate_hz` (checked against the time column, which it
//! then need not resolve finely), `unit` (one unit for every channel) or `units` (one per
//! column, for channels of mixed quantities; [`crate::core::oma::UNITS`], default `m/s^2`:
//! samples are converted to SI as they are read), `structure`,
//! `channels` (the model's names for the columns, in order: a rename), `start` (RFC 3339
//! time of the first sample). Unknown keys are refused, naming them.

use std::path::Path;

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
    pub channels: Option<Vec<String>>,
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

/// Reads `path` (CSV, module docs) and its sidecar. Every failure names the file, and the
/// line and column where there is one.
pub fn read_csv(path: &Path) -> Result<RecordFile> {
    let name = path.display();
    let text = std::fs::read_to_string(path).with_context(|| format!("cannot read {}", name))?;
    let sidecar_path = path.with_extension("json");
    let sidecar: Sidecar = if sidecar_path.exists() {
        let s = std::fs::read_to_string(&sidecar_path)
            .with_context(|| format!("cannot read {}", sidecar_path.display()))?;
        serde_json::from_str(&s).with_context(|| format!("{}", sidecar_path.display()))?
    } else {
        Sidecar::default()
    };
    let mut lines = text
        .lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty() && !l.starts_with('#'));
    let Some((_, header)) = lines.next() else {
        bail!("{name}: empty file (expected a header `time_s,<channel>,…`)");
    };
    let columns: Vec<&str> = header.split(',').map(str::trim).collect();
    if columns.first() != Some(&"time_s") || columns.len() < 2 {
        bail!("{name}: line 1: the header must be `time_s,<channel>,…`, got `{header}`");
    }
    let mut channels: Vec<String> = columns[1..].iter().map(|c| c.to_string()).collect();
    if let Some(rename) = &sidecar.channels {
        if rename.len() != channels.len() {
            bail!(
                "{}: channels: {} names for the {} columns of {name}",
                sidecar_path.display(),
                rename.len(),
                channels.len()
            );
        }
        channels = rename.clone();
    }
    let mut seen = std::collections::HashSet::new();
    for c in &channels {
        if c.is_empty() || !seen.insert(c.as_str()) {
            bail!("{name}: channel `{c}` is empty or named twice");
        }
    }
    let r = channels.len();
    // The rows parsed in parallel chunks (the text is already in memory); the first
    // error in file order is reported.
    let rows: Vec<(usize, &str)> = lines.collect();
    let parse_rows = |chunk: &[(usize, &str)]| -> Result<(Vec<f64>, Vec<f64>)> {
        let mut times = Vec::with_capacity(chunk.len());
        let mut values = Vec::with_capacity(chunk.len() * r);
        for &(i, line) in chunk {
            let mut n = 0;
            for (j, field) in line.split(',').enumerate() {
                let v: f64 = field.trim().parse().map_err(|_| {
                    anyhow::anyhow!(
                        "{name}: line {}, column {} (`{}`): `{}` is not a number",
                        i + 1,
                        j + 1,
                        columns.get(j).unwrap_or(&"?"),
                        field.trim()
                    )
                })?;
                if !v.is_finite() {
                    bail!(
                        "{name}: line {}, column {} (`{}`): {v} is not finite",
                        i + 1,
                        j + 1,
                        columns.get(j).unwrap_or(&"?")
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
    let n = times.len();
    if n < 3 {
        bail!("{name}: {n} samples: too few to identify anything");
    }
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
    let mut quantities = Vec::with_capacity(r);
    let mut factors = Vec::with_capacity(r);
    for (c, u) in units.iter().enumerate() {
        let (q, f) = crate::core::oma::parse_unit(u).map_err(|e| {
            anyhow::anyhow!("{}: channel `{}`: {e}", sidecar_path.display(), channels[c])
        })?;
        quantities.push(q);
        factors.push(f);
    }
    let samples = Mat::from_fn(n, r, |k, c| values[k * r + c] * factors[c]);
    Ok(RecordFile {
        record: Record {
            channels,
            rate_hz,
            samples,
            quantities,
        },
        sidecar,
        t0_s: times[0],
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
