//! `boltwatch identify`: modal sets with uncertainties from a raw vibration record
//! (operational modal analysis, [`crate::core::oma`]).

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use chrono::{DateTime, Utc};

use super::write_json;
use crate::contract::accel::parse_accel;
use crate::contract::modal_set::ModalSet;
use crate::core::model::Model;
use crate::core::oma::Record;
use crate::core::oma::identify::{Identification, IdentifyOptions, identify_all};
use crate::core::oma::settings::Settings;
use crate::core::oma::track::{Gate, ModeTrack};
use crate::io::record::{RecordFile, read_record};
use crate::pipeline::accel::{
    AccelFront, FrontEvent, IdentifySettings, label, modal_set, spectrum_peaks,
};

#[derive(Debug, clap::Args)]
pub struct IdentifyArgs {
    /// Record: CSV with a header `time_s,<channel>,…`, uniformly sampled, or a NumPy `.npy`
    /// array (samples × channels; its sidecar gives rate_hz), each with an optional sidecar
    /// FILE.json (rate_hz, unit or units, structure, channels, start); or an MCAP recording
    /// of boltwatch.accel.v1 blocks (`.mcap`).
    #[arg(long)]
    pub input: PathBuf,
    /// Output: one boltwatch.modal_set.v1, or a list of them with --window.
    #[arg(short, long)]
    pub out: PathBuf,
    /// Window length, s: the record is cut into consecutive windows, each identified on its
    /// own (the remainder shorter than a window is left out and reported).
    #[arg(long)]
    pub window: Option<f64>,
    /// Largest model order of the stabilization diagram (orders 2, 4, …; default: from
    /// the peaks of the record's spectrum).
    #[arg(long)]
    pub order_max: Option<usize>,
    /// Frequency band of interest, `lo,hi` in Hz (default: 0 to 0.45 of the sampling rate).
    #[arg(long)]
    pub band: Option<String>,
    /// Block rows of the Hankel matrix (lags up to 2s − 1 samples; default: the lags span
    /// two periods of the lowest frequency of interest).
    #[arg(long)]
    pub block_rows: Option<usize>,
    /// Decimation factor (default: from the band's top; 1 turns it off).
    #[arg(long)]
    pub decimate: Option<usize>,
    /// Write the stabilization diagram (PNG and SVG) and its poles (CSV) to this folder.
    #[arg(long)]
    pub plot: Option<PathBuf>,
    /// Blocks the record (or window) is cut into for the uncertainties.
    #[arg(long, default_value_t = 30)]
    pub blocks: usize,
    /// A model: its channels must include the record's, and its name is the structure.
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Time of the first sample (RFC 3339; default: the sidecar's `start`, else the time
    /// column read as seconds after 1970-01-01T00:00:00Z).
    #[arg(long)]
    pub start: Option<String>,
}

/// `boltwatch identify`: the record cut into windows, each identified, labelled and
/// printed, and the modal sets written (an MCAP recording goes to [`run_mcap`]).
pub fn run(args: &IdentifyArgs) -> Result<()> {
    if args.input.extension().is_some_and(|e| e == "mcap") {
        return run_mcap(args);
    }
    let file = read_record(&args.input)?;
    let record = &file.record;
    let mut opts = IdentifyOptions::default();
    let (structure, mut track) = structure_and_track(args, &file, &mut opts)?;
    let start = start_time(args, &file)?;
    request_options(args, &mut opts)?;
    let windows = Windows::cut(args, record, &opts, &structure, start)?;
    let mut sets = Vec::new();
    for w in 0..windows.count {
        sets.push(windows.identify(w, &mut track)?);
    }
    windows.report_left_out();
    let out = if args.window.is_none() {
        sets.pop().expect("one window")
    } else {
        serde_json::Value::Array(sets)
    };
    write_json(&args.out, &out)?;
    println!("written: {}", args.out.display());
    Ok(())
}

/// The structure's name and the track that labels its modes. With `--model`: the model's
/// name and modes (up to the band's top), its channels holding the record's and its name
/// the sidecar's structure, its lowest mode put in `opts`. Without: the sidecar's
/// structure (else the file's stem) and a track of its own.
fn structure_and_track(
    args: &IdentifyArgs,
    file: &RecordFile,
    opts: &mut IdentifyOptions,
) -> Result<(String, ModeTrack)> {
    let record = &file.record;
    let Some(path) = &args.model else {
        let structure = file.sidecar.structure.clone().unwrap_or_else(|| {
            args.input
                .file_stem()
                .map_or("structure".into(), |s| s.to_string_lossy().into_owned())
        });
        return Ok((structure, ModeTrack::new(Gate::default())));
    };
    let (_, model) = super::load_description(path)?;
    check_channels(&args.input, &record.channels, &model)?;
    if let Some(s) = &file.sidecar.structure
        && s != &model.name
    {
        bail!(
            "{}: structure `{s}` of the sidecar is not the model's `{}`",
            args.input.display(),
            model.name
        );
    }
    let hi = match &args.band {
        Some(b) => parse_band(b)?.1,
        None => 0.45 * record.rate_hz,
    };
    let track = ModeTrack::from_model(&model, hi, Gate::default())
        .with_context(|| format!("the modes of model `{}`", model.name))?;
    opts.requested.model_lowest_hz = track.refs.first().map(|r| r.frequency_hz);
    Ok((model.name.clone(), track))
}

/// Fails unless every channel of the record is a channel of `model`.
fn check_channels(input: &Path, channels: &[String], model: &Model) -> Result<()> {
    let known: Vec<&str> = model.channels().iter().map(|c| c.name.as_str()).collect();
    if let Some(c) = channels.iter().find(|c| !known.contains(&c.as_str())) {
        bail!(
            "{}: channel `{c}` is not a channel of model `{}`",
            input.display(),
            model.name
        );
    }
    Ok(())
}

/// Time of the record's first sample: `--start`, else the sidecar's `start`, else the
/// time column's first value as seconds after the epoch.
fn start_time(args: &IdentifyArgs, file: &RecordFile) -> Result<DateTime<Utc>> {
    Ok(match (&args.start, file.sidecar.start) {
        (Some(s), _) => DateTime::parse_from_rfc3339(s)
            .with_context(|| format!("--start `{s}`: not an RFC 3339 time"))?
            .with_timezone(&Utc),
        (None, Some(t)) => t,
        (None, None) => DateTime::from_timestamp_millis((file.t0_s * 1000.0).round() as i64)
            .context("the time column's first value is not a time")?,
    })
}

/// What the command line fixes of the identification: orders, block rows, decimation,
/// band and blocks.
fn request_options(args: &IdentifyArgs, opts: &mut IdentifyOptions) -> Result<()> {
    opts.requested.order_max = args.order_max;
    opts.requested.block_rows = args.block_rows;
    opts.requested.decimate = args.decimate;
    opts.requested.band_hz = args.band.as_deref().map(parse_band).transpose()?;
    opts.blocks = args.blocks;
    Ok(())
}

/// A record cut into consecutive windows, and what each window's modal set is made with.
struct Windows<'a> {
    args: &'a IdentifyArgs,
    record: &'a Record,
    opts: &'a IdentifyOptions,
    structure: &'a str,
    /// Time of the record's first sample.
    start: DateTime<Utc>,
    /// Samples per window.
    len: usize,
    /// Whole windows in the record.
    count: usize,
}

impl<'a> Windows<'a> {
    /// Cuts `record` into windows of `--window` seconds (without it, one window of all of
    /// it); fails when not even one fits.
    fn cut(
        args: &'a IdentifyArgs,
        record: &'a Record,
        opts: &'a IdentifyOptions,
        structure: &'a str,
        start: DateTime<Utc>,
    ) -> Result<Self> {
        let len = match args.window {
            None => record.len(),
            Some(w) if w > 0.0 && w.is_finite() => (w * record.rate_hz).round() as usize,
            Some(w) => bail!("--window {w}: must be a positive number of seconds"),
        };
        let count = record.len() / len.max(1);
        if count == 0 {
            bail!(
                "--window {} s is longer than the record ({:.3} s)",
                args.window.unwrap_or_default(),
                record.duration_s()
            );
        }
        Ok(Self {
            args,
            record,
            opts,
            structure,
            start,
            len,
            count,
        })
    }

    /// Window `w` (from 0) identified: the settings printed (first window only), the
    /// stabilization diagram written (with `--plot`), the modal set labelled by `track`,
    /// printed, and returned as JSON.
    fn identify(&self, w: usize, track: &mut ModeTrack) -> Result<serde_json::Value> {
        let (args, record, window) = (self.args, self.record, self.len);
        let part = Record {
            channels: record.channels.clone(),
            rate_hz: record.rate_hz,
            samples: record.samples.subrows(w * window, window).to_owned(),
            quantities: record.quantities.clone(),
        };
        let what = format!(
            "{}: window {} ({:.3} s from the start)",
            args.input.display(),
            w + 1,
            (w * window) as f64 / record.rate_hz
        );
        let found = identify_all(&part, self.opts).with_context(|| what.clone())?;
        if w == 0 {
            print_settings(&found.settings, &part);
        }
        if let Some(dir) = &args.plot {
            self.write_plot(dir, w, &what, &found)?;
        }
        let time = self.start
            + chrono::TimeDelta::microseconds(
                ((w * window) as f64 / record.rate_hz * 1e6).round() as i64
            );
        let mut set = modal_set(
            self.structure,
            time,
            &record.channels,
            &found.modes,
            format!("boltwatch identify {} (SSI-COV)", args.input.display()),
        );
        set.unexplained_peaks = spectrum_peaks(&found.unexplained_peaks);
        label(&mut set, track);
        print_window(w, time, &found, &set);
        Ok(set.to_json())
    }

    /// Writes window `w`'s stabilization diagram to `dir`: `stabilization`, numbered
    /// `stabilization-<w+1>` when there are several windows.
    fn write_plot(&self, dir: &Path, w: usize, what: &str, found: &Identification) -> Result<()> {
        let name = if self.count == 1 {
            "stabilization".to_string()
        } else {
            format!("stabilization-{}", w + 1)
        };
        super::identify_plot::write(dir, &name, found)
            .with_context(|| format!("{what}: the stabilization diagram"))?;
        Ok(())
    }

    /// Reports the end of the record left out for being shorter than a window (with
    /// `--window` only).
    fn report_left_out(&self) {
        let left = self.record.len() - self.count * self.len;
        if left > 0 && self.args.window.is_some() {
            println!(
                "left out: the last {:.3} s (shorter than a window)",
                left as f64 / self.record.rate_hz
            );
        }
    }
}

/// One window's line: its modes with their uncertainties and labels, the modes missing,
/// then a line per peak of the spectrum that no mode explains.
fn print_window(w: usize, time: DateTime<Utc>, found: &Identification, set: &ModalSet) {
    let modes = &found.modes;
    println!(
        "window {} ({}): {} modes: {}{}",
        w + 1,
        time.to_rfc3339_opts(chrono::SecondsFormat::Millis, true),
        modes.len(),
        modes
            .iter()
            .zip(&set.modes)
            .map(|(m, s)| format!(
                "{}: {:.3} ± {:.3} Hz (ζ {:.2} ± {:.2} %)",
                s.label.as_deref().unwrap_or("?"),
                m.frequency_hz,
                m.frequency_std,
                100.0 * m.damping,
                100.0 * m.damping_std
            ))
            .collect::<Vec<_>>()
            .join(", "),
        missing_note(set)
    );
    for p in &found.unexplained_peaks {
        println!(
            "  a peak of the spectrum at {:.3} Hz ({:.1} dB) is explained by no mode",
            p.frequency_hz, p.prominence_db
        );
    }
}

/// The settings derived from the record, one line per sub-band.
fn print_settings(s: &Settings, record: &Record) {
    let names: Vec<&str> = s
        .references
        .iter()
        .map(|&j| record.channels[j].as_str())
        .collect();
    println!(
        "settings: {} channels at {} Hz, references {}; {} peaks in the spectrum",
        record.channels.len(),
        record.rate_hz,
        names.join(","),
        s.peaks.len()
    );
    for b in &s.bands {
        println!(
            "  {:.2}–{:.2} Hz: decimate {} (to {} Hz), block rows {} (lags span {:.2} s; lowest frequency {} from {}), orders up to {}, {} peaks",
            b.band_hz.0,
            b.band_hz.1,
            b.decimate,
            b.rate_hz,
            b.block_rows,
            (2 * b.block_rows - 1) as f64 / b.rate_hz,
            b.lowest_hz
                .map_or("none".to_string(), |f| format!("{f:.3} Hz")),
            b.lowest_from,
            b.order_max,
            b.peaks
        );
    }
}

/// `; missing: mode 10, …` for a set that lists missing modes, else nothing.
fn missing_note(set: &ModalSet) -> String {
    if set.missing.is_empty() {
        String::new()
    } else {
        format!("; missing: {}", set.missing.join(", "))
    }
}

/// `--band lo,hi` in Hz, with 0 ≤ lo < hi.
fn parse_band(s: &str) -> Result<(f64, f64)> {
    let v: Vec<f64> = s
        .split(',')
        .map(|x| x.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|_| anyhow::anyhow!("--band `{s}`: need `lo,hi` in Hz"))?;
    match v[..] {
        [lo, hi] if lo >= 0.0 && hi > lo && hi.is_finite() => Ok((lo, hi)),
        _ => bail!("--band `{s}`: need 0 ≤ lo < hi"),
    }
}

/// `identify` of an MCAP recording of `boltwatch.accel.v1` blocks: the blocks of its one
/// structure (the model's, with `--model`) through the accel front
/// ([`crate::pipeline::accel`]), windows of `--window` seconds (without it, the whole
/// recording, which must then be one stream without gaps). Blocks refused and samples
/// left over are reported on stderr.
fn run_mcap(args: &IdentifyArgs) -> Result<()> {
    let model = match &args.model {
        Some(path) => Some(super::load_description(path)?.1),
        None => None,
    };
    let blocks = accel_blocks(&args.input)?;
    let structure = pick_structure(args, model.as_ref(), &blocks)?;
    let mine: Vec<&[u8]> = blocks
        .iter()
        .filter(|(s, _)| *s == structure)
        .map(|(_, d)| d.as_slice())
        .collect();
    let (rate, channels, total) = stream_shape(&args.input, &mine)?;
    let settings = front_settings(args, rate, total)?;
    let mut front = match model {
        Some(m) => {
            check_channels(&args.input, &channels, &m)?;
            AccelFront::for_model(std::sync::Arc::new((None, m)), settings)
        }
        None => AccelFront::new(&structure, &channels, settings),
    };
    let mut sets = drive_front(&mut front, &mine);
    if sets.is_empty() {
        bail!(
            "{}: no window identified{}",
            args.input.display(),
            if args.window.is_none() {
                " (without --window the whole recording is one window, and it has gaps: give --window)"
            } else {
                ""
            }
        );
    }
    let out = if args.window.is_none() && sets.len() == 1 {
        sets.pop().expect("one set")
    } else {
        serde_json::Value::Array(sets)
    };
    write_json(&args.out, &out)?;
    println!("written: {}", args.out.display());
    Ok(())
}

/// The recording's accel blocks, in order: the structure of each
/// `boltwatch/<structure>/accel` message, and its payload.
fn accel_blocks(input: &Path) -> Result<Vec<(String, Vec<u8>)>> {
    let mut blocks = Vec::new();
    crate::io::mcap::for_each_message(input, |m| {
        if let Some(s) = m
            .topic
            .strip_prefix("boltwatch/")
            .and_then(|t| t.strip_suffix("/accel"))
        {
            blocks.push((s.to_string(), m.data));
        }
        Ok(())
    })?;
    Ok(blocks)
}

/// The structure whose blocks are identified: the model's (which must have blocks), else
/// the recording's only one.
fn pick_structure(
    args: &IdentifyArgs,
    model: Option<&Model>,
    blocks: &[(String, Vec<u8>)],
) -> Result<String> {
    let mut structures: Vec<&str> = blocks.iter().map(|(s, _)| s.as_str()).collect();
    structures.sort_unstable();
    structures.dedup();
    Ok(match (model, &structures[..]) {
        (_, []) => bail!(
            "{}: no boltwatch/<structure>/accel messages",
            args.input.display()
        ),
        (Some(m), _) if structures.contains(&m.name.as_str()) => m.name.clone(),
        (Some(m), _) => bail!(
            "{}: no accel blocks of model `{}` (structures: {})",
            args.input.display(),
            m.name,
            structures.join(", ")
        ),
        (None, [one]) => one.to_string(),
        (None, many) => bail!(
            "{}: accel blocks of several structures ({}): give --model",
            args.input.display(),
            many.join(", ")
        ),
    })
}

/// The stream's rate and channels (from its first block that reads) and its samples in
/// all blocks that read; blocks that do not are reported on stderr.
fn stream_shape(input: &Path, mine: &[&[u8]]) -> Result<(f64, Vec<String>, usize)> {
    let mut first = None;
    let mut samples = 0usize;
    for (k, d) in mine.iter().enumerate() {
        match parse_accel(d) {
            Ok(b) => {
                samples += b.len();
                first.get_or_insert((b.rate_hz, b.channels));
            }
            Err(r) => eprintln!("block {k}: refused: {}: {}", r.field, r.reason),
        }
    }
    let (rate, channels) =
        first.ok_or_else(|| anyhow::anyhow!("{}: no readable accel block", input.display()))?;
    Ok((rate, channels, samples))
}

/// The accel front's settings from the command line, checked; without `--window`, one
/// window spans the stream's `total` samples at `rate`.
fn front_settings(args: &IdentifyArgs, rate: f64, total: usize) -> Result<IdentifySettings> {
    let window_s = match args.window {
        Some(w) if w > 0.0 && w.is_finite() => w,
        Some(w) => bail!("--window {w}: must be a positive number of seconds"),
        None => total as f64 / rate,
    };
    let settings = IdentifySettings {
        window_s,
        order_max: args.order_max,
        block_rows: args.block_rows,
        decimate: args.decimate,
        blocks: args.blocks,
        band_hz: match &args.band {
            Some(b) => {
                let (lo, hi) = parse_band(b)?;
                vec![lo, hi]
            }
            None => vec![],
        },
    };
    settings.validate()?;
    Ok(settings)
}

/// The blocks through `front`, then its end: the modal sets of the windows, as JSON, each
/// printed; refusals and dropped windows reported on stderr.
fn drive_front(front: &mut AccelFront, mine: &[&[u8]]) -> Vec<serde_json::Value> {
    let mut sets = Vec::new();
    for (k, d) in mine.iter().enumerate() {
        for e in front.handle(d) {
            report(e, Some(k), &mut sets);
        }
    }
    if let Some(e) = front.finish() {
        report(e, None, &mut sets);
    }
    sets
}

/// One event of the front: a modal set printed and kept in `sets`, or a refusal (of
/// block `k`, if a block is to blame) on stderr.
fn report(e: FrontEvent, k: Option<usize>, sets: &mut Vec<serde_json::Value>) {
    match e {
        FrontEvent::Set(set) => {
            println!(
                "window from {}: {} modes: {}{}",
                crate::contract::rfc3339(set.time),
                set.modes.len(),
                set.modes
                    .iter()
                    .map(|m| format!(
                        "{}: {:.3} Hz",
                        m.label.as_deref().unwrap_or("?"),
                        m.frequency_hz
                    ))
                    .collect::<Vec<_>>()
                    .join(", "),
                missing_note(&set)
            );
            sets.push(set.to_json());
        }
        FrontEvent::Refused(r) | FrontEvent::Dropped(r) => eprintln!(
            "{}{}: {}",
            k.map(|k| format!("block {k}: ")).unwrap_or_default(),
            if r.field.is_empty() {
                "window"
            } else {
                &r.field
            },
            r.reason
        ),
    }
}
