//! `boltwatch scenario NAME -o REC.mcap`: a synthetic monitoring recording
//! ([`crate::scenario`]): the modal sets on `boltwatch/<structure>/modal` and, beside
//! them, the true parameters of every set on `boltwatch/<structure>/truth`. With
//! `--accel SECONDS`, raw accelerations instead: a burst per set on
//! `boltwatch/<structure>/accel`, so `replay` runs the whole chain from accelerations to
//! alerts.

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use indicatif::{ProgressBar, ProgressStyle};
use serde_json::json;

use crate::contract::accel::Accel;
use crate::contract::modal_set::ModalSet;
use crate::contract::{rfc3339, to_wire};
use crate::core::model::Model;
use crate::core::model::spec::ModelSpec;
use crate::core::oma::synth::{SynthOptions, accelerations};
use crate::io::mcap::{ChannelSpec, McapWriter, to_ns};
use crate::io::schemas::TRUTH_SCHEMA;
use crate::scenario::{Event, NAMES, Scenario};

#[derive(Debug, clap::Args)]
pub struct ScenarioArgs {
    /// Scenario: healthy, loosening, sudden or mass.
    pub name: String,
    /// Model the sets are simulated from: a model file or a bundled model (`bundled:NAME`).
    #[arg(long, default_value = "bundled:lab-frame")]
    pub model: PathBuf,
    /// Number of modal sets (default 10,000; seasonal: four a day).
    #[arg(long)]
    pub sets: Option<usize>,
    /// Days the sets span (default 60; seasonal: 730).
    #[arg(long)]
    pub days: Option<f64>,
    /// Random seed (ChaCha8).
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Modes per set (the lowest).
    #[arg(long, default_value_t = 9)]
    pub modes: usize,
    /// Connection parameter that loosens (loosening, sudden; default: the first).
    #[arg(long)]
    pub connection: Option<String>,
    /// Node the added mass is fixed to (mass; default: the second joint).
    #[arg(long)]
    pub at: Option<String>,
    /// Day the event starts (loosening: 40; sudden, mass: 30).
    #[arg(long)]
    pub event_day: Option<f64>,
    /// Seasonal: a connection parameter that loses `--drop` of its stiffness at once on
    /// `--day`.
    #[arg(long, requires = "drop", requires = "day")]
    pub loosen: Option<String>,
    /// Seasonal: the fraction lost by `--loosen`, in (0, 1).
    #[arg(long, requires = "loosen")]
    pub drop: Option<f64>,
    /// Seasonal: the day `--loosen` loses it, from the start.
    #[arg(long, requires = "loosen")]
    pub day: Option<f64>,
    /// The temperature as environment readings (`boltwatch/<structure>/environment`,
    /// one an hour) instead of in each modal set: a site whose thermometer is not in the
    /// box that identifies the modes.
    #[arg(long)]
    pub environment: bool,
    /// Significant digits kept of the shape entries (smaller files; 0: all).
    #[arg(long, default_value_t = 0)]
    pub shape_digits: u32,
    /// Output recording.
    #[arg(short, long)]
    pub out: PathBuf,
    /// Raw accelerations instead of modal sets (`--accel SECONDS`).
    #[command(flatten)]
    pub raw: RawArgs,
}

/// `scenario --accel`: raw accelerations instead of modal sets.
#[derive(Debug, Clone, clap::Args)]
pub struct RawArgs {
    /// Raw accelerations instead of modal sets: for each set, a burst of this many seconds
    /// of every channel (boltwatch.accel.v1 blocks on `boltwatch/<structure>/accel`),
    /// simulated in the time domain under white modal forces ([`crate::core::oma::synth`]).
    #[arg(long)]
    pub accel: Option<f64>,
    /// Sampling rate of the accelerations, Hz (--accel).
    #[arg(long, default_value_t = 1000.0)]
    pub rate: f64,
    /// Modal damping ratio of the simulated accelerations (--accel).
    #[arg(long, default_value_t = 0.01)]
    pub damping: f64,
    /// Sensor noise, relative to each channel's RMS (--accel).
    #[arg(long, default_value_t = 0.02)]
    pub sensor_noise: f64,
    /// Seconds of samples per accel block (--accel).
    #[arg(long, default_value_t = 1.0)]
    pub block: f64,
}

impl Default for RawArgs {
    /// Modal sets, not raw data (the defaults of the options otherwise).
    fn default() -> Self {
        Self {
            accel: None,
            rate: 1000.0,
            damping: 0.01,
            sensor_noise: 0.02,
            block: 1.0,
        }
    }
}

/// Rounds `v` to `digits` significant digits (0: unchanged).
fn significant(v: f64, digits: u32) -> f64 {
    if digits == 0 || v == 0.0 || !v.is_finite() {
        return v;
    }
    let scale = 10f64.powi(digits as i32 - 1 - v.abs().log10().floor() as i32);
    (v * scale).round() / scale
}

/// Writes the synthetic recording `args.out` of the scenario and prints what it holds.
pub fn run(args: &ScenarioArgs) -> Result<()> {
    check_request(args)?;
    let (spec, model) = simulated_model(args)?;
    let sc = build_scenario(args, &model)?;
    check_raw(&args.raw)?;
    write_recording(args, &spec, &model, &sc)?;
    let bytes = std::fs::metadata(&args.out)?.len();
    println!(
        "scenario {}: {} sets over {} days of {} ({}), {:.1} MB -> {}",
        sc.name,
        sc.sets,
        sc.days,
        model.name,
        describe(&sc, &model),
        bytes as f64 / 1e6,
        args.out.display()
    );
    Ok(())
}

/// Rejects an unknown scenario and a `--sets` or `--days` out of range, before the model
/// is read.
fn check_request(args: &ScenarioArgs) -> Result<()> {
    if !NAMES.contains(&args.name.as_str()) {
        bail!(
            "unknown scenario `{}` (known: {})",
            args.name,
            NAMES.join(", ")
        );
    }
    if args.sets == Some(0) {
        bail!("--sets must be at least 1");
    }
    if let Some(d) = args.days
        && !(d.is_finite() && d > 0.0)
    {
        bail!("--days = {d} must be a finite number > 0");
    }
    Ok(())
}

/// The model the sets are simulated from, with its description (which `--accel` and the
/// mass event simulate from), and `--modes` checked against its size.
fn simulated_model(args: &ScenarioArgs) -> Result<(ModelSpec, Model)> {
    let text = crate::io::model::read_model_text(&args.model)?;
    let spec: ModelSpec =
        toml::from_str(&text).with_context(|| format!("model file {}", args.model.display()))?;
    let model = Model::from_spec(&spec)?;
    if args.modes == 0 || args.modes > model.n_dof() {
        bail!(
            "--modes = {} must be between 1 and {}",
            args.modes,
            model.n_dof()
        );
    }
    Ok((spec, model))
}

/// The named scenario on `model`, settled by the options ([`settle`]) and with its event
/// moved to `--event-day`.
fn build_scenario(args: &ScenarioArgs, model: &Model) -> Result<Scenario> {
    let mut sc = Scenario::named(
        &args.name,
        model,
        args.connection.as_deref(),
        args.at.as_deref(),
    )?;
    settle(&mut sc, args, model)?;
    if let Some(d) = args.event_day {
        if !(d.is_finite() && d >= 0.0) {
            bail!("--event-day = {d} must be a finite number ≥ 0");
        }
        match &mut sc.event {
            Event::Loosening { start_day, .. } => *start_day = d,
            Event::Sudden { day, .. } | Event::Mass { day, .. } => *day = d,
            Event::None if sc.seasons.is_some() => bail!(
                "--event-day: the seasonal scenario's event is a loss set by --loosen, --drop and --day"
            ),
            Event::None => bail!("--event-day: the {} scenario has no event", args.name),
        }
    }
    Ok(sc)
}

/// Checks the options of `--accel` when raw accelerations are asked for: a positive burst,
/// rate and block no longer than the burst, a damping ratio in (0, 1), noise ≥ 0.
fn check_raw(raw: &RawArgs) -> Result<()> {
    if let Some(w) = raw.accel {
        let ok = |v: f64| v.is_finite() && v > 0.0;
        if !(ok(w) && ok(raw.rate) && ok(raw.block) && raw.block <= w) {
            bail!(
                "--accel {w}, --rate {}, --block {}: need positive numbers, a block no longer than the burst",
                raw.rate,
                raw.block
            );
        }
        if !(raw.damping > 0.0 && raw.damping < 1.0 && raw.sensor_noise >= 0.0) {
            bail!(
                "--damping {} must be in (0, 1) and --sensor-noise {} ≥ 0",
                raw.damping,
                raw.sensor_noise
            );
        }
    }
    Ok(())
}

/// Writes every set of `sc` to `args.out`, with a progress bar: the modal set (or its
/// accel burst), its truth and, with `--environment`, the readings due by then.
fn write_recording(
    args: &ScenarioArgs,
    spec: &ModelSpec,
    model: &Model,
    sc: &Scenario,
) -> Result<()> {
    let first = if args.raw.accel.is_some() {
        "accel"
    } else {
        "modal"
    };
    let channels = [
        ChannelSpec::for_structure(&model.name, first)?,
        ChannelSpec::for_structure(&model.name, "truth")?,
        ChannelSpec::for_structure(&model.name, "environment")?,
    ];
    let w = McapWriter::create(&args.out, &channels)?;
    let mut out = SetWriter {
        args,
        spec,
        sc,
        structure: &model.name,
        names: model.parameters().iter().map(|p| p.name.as_str()).collect(),
        topics: [
            channels[0].topic.as_str(),
            channels[1].topic.as_str(),
            channels[2].topic.as_str(),
        ],
        w,
        next_reading: 0.0,
    };
    let pb = ProgressBar::new(sc.sets as u64).with_style(
        ProgressStyle::with_template("{msg} {bar:40} {pos}/{len} sets ({eta} left)")
            .expect("template"),
    );
    pb.set_message(format!("scenario {}", sc.name));
    let mut error: Option<anyhow::Error> = None;
    sc.generate(spec, |k, set, theta| {
        let result = out.write_set(k, set, theta);
        pb.inc(1);
        if let Err(e) = result {
            error = Some(e);
            return Err(crate::scenario::ScenarioError::Invalid(
                "write failed".into(),
            ));
        }
        Ok(())
    })
    .map_err(|e| error.take().unwrap_or_else(|| e.into()))?;
    pb.finish_and_clear();
    out.w.finish()?;
    Ok(())
}

/// The recording being written, and what each set written to it needs.
struct SetWriter<'a> {
    args: &'a ScenarioArgs,
    spec: &'a ModelSpec,
    sc: &'a Scenario,
    /// The structure's (the model's) name.
    structure: &'a str,
    /// The model's parameter names, for the truth.
    names: Vec<&'a str>,
    /// Topics of the sets (modal or accel), of the truth and of the environment readings.
    topics: [&'a str; 3],
    w: McapWriter,
    /// Day of the next environment reading due.
    next_reading: f64,
}

impl SetWriter<'_> {
    /// Writes set `k`, simulated at θ = `theta`: the environment readings due by its day
    /// (`--environment`, which also takes its temperature out), the set with its shapes
    /// rounded (or its accel burst), then its truth.
    fn write_set(&mut self, k: usize, mut set: ModalSet, theta: &[f64]) -> Result<()> {
        let (args, sc) = (self.args, self.sc);
        if args.shape_digits > 0 {
            round_shapes(&mut set, args.shape_digits);
        }
        if args.environment {
            set.temperature_c = None;
        }
        let t = to_ns(set.time)?;
        if args.environment {
            self.next_reading = write_readings(
                &mut self.w,
                self.topics[2],
                sc,
                self.structure,
                self.next_reading,
                sc.day(k),
            )?;
        }
        match args.raw.accel {
            None => self
                .w
                .write(self.topics[0], t, &serde_json::to_vec(&set.to_json())?)?,
            Some(burst) => write_burst(
                &mut self.w,
                self.topics[0],
                self.spec,
                added_mass(sc, k),
                theta,
                set.time,
                burst,
                k,
                args,
            )?,
        }
        let added = match added_mass(sc, k) {
            Some((at, mass)) => json!({"at": at, "mass_kg": mass}),
            None => serde_json::Value::Null,
        };
        let truth = json!({
            "schema": TRUTH_SCHEMA,
            "structure": self.structure,
            "time": rfc3339(set.time),
            "scenario": sc.name,
            "set": k,
            "temperature_c": sc.temperature(sc.day(k)),
            "parameters": self.names,
            "theta": theta,
            "added_mass": added,
        });
        self.w
            .write(self.topics[1], t, &serde_json::to_vec(&truth)?)
    }
}

/// Rounds every shape entry of `set` to `digits` significant digits.
fn round_shapes(set: &mut ModalSet, digits: u32) {
    for m in &mut set.modes {
        if let Some(s) = &mut m.shape {
            for v in s.iter_mut().flatten() {
                *v = significant(*v, digits);
            }
        }
    }
}

/// The mass fixed to the structure by set `k` (node, kg), if the event has added it.
fn added_mass(sc: &Scenario, k: usize) -> Option<(&str, f64)> {
    match &sc.event {
        Event::Mass { at, mass, day } if sc.day(k) >= *day => Some((at.as_str(), *mass)),
        _ => None,
    }
}

/// The environment readings due from day `from` up to day `to`, one an hour on the hour;
/// returns the day of the next one.
fn write_readings(
    w: &mut McapWriter,
    topic: &str,
    sc: &Scenario,
    structure: &str,
    from: f64,
    to: f64,
) -> Result<f64> {
    let hour = 1.0 / 24.0;
    let mut day = from;
    while day <= to + 1e-9 {
        let time = sc.start + chrono::Duration::milliseconds((day * 86_400_000.0).round() as i64);
        let reading = crate::contract::environment::EnvironmentReading {
            structure: structure.to_string(),
            time,
            conditions: crate::contract::environment::Conditions {
                temperature_c: Some((sc.temperature(day) * 100.0).round() / 100.0),
                covariates: Default::default(),
            },
        };
        w.write(
            topic,
            to_ns(time)?,
            &serde_json::to_vec(&reading.to_json())?,
        )?;
        day += hour;
    }
    Ok(day)
}

/// The scenario's size, seed and modes from the options, and the seasonal loss: per set
/// four a day when only `--days` is given to the seasonal scenario.
fn settle(sc: &mut Scenario, args: &ScenarioArgs, model: &Model) -> Result<()> {
    let seasonal = sc.seasons.is_some();
    if let Some(d) = args.days {
        if seasonal && args.sets.is_none() {
            sc.sets = (4.0 * d).round().max(1.0) as usize;
        }
        sc.days = d;
    }
    if let Some(n) = args.sets {
        sc.sets = n;
    }
    sc.seed = args.seed;
    sc.modes = args.modes;
    if seasonal {
        sc.reseason(model);
    }
    let Some(name) = &args.loosen else {
        return Ok(());
    };
    if !seasonal {
        bail!("--loosen is an event of the seasonal scenario (the others have --connection)");
    }
    let (drop, day) = (args.drop.unwrap_or(f64::NAN), args.day.unwrap_or(f64::NAN));
    if !(drop > 0.0 && drop < 1.0) {
        bail!("--drop = {drop} must be a fraction in (0, 1)");
    }
    if !(day.is_finite() && day >= 0.0) {
        bail!("--day = {day} must be a finite number ≥ 0");
    }
    let parameter = model
        .parameters()
        .iter()
        .position(|p| {
            &p.name == name && matches!(p.kind, crate::core::model::ParameterKind::Connections(_))
        })
        .with_context(|| {
            format!(
                "--loosen {name}: not a connection parameter of {}",
                model.name
            )
        })?;
    sc.event = Event::Sudden {
        parameter,
        day,
        loss: drop,
    };
    Ok(())
}

/// Writes the accel blocks of one burst of `seconds` at θ, from `time` (`scenario --accel`).
#[allow(clippy::too_many_arguments)]
fn write_burst(
    w: &mut McapWriter,
    topic: &str,
    spec: &ModelSpec,
    mass: Option<(&str, f64)>,
    theta: &[f64],
    time: chrono::DateTime<chrono::Utc>,
    seconds: f64,
    k: usize,
    args: &ScenarioArgs,
) -> Result<()> {
    let model = match mass {
        Some((at, m)) => {
            let mut with = spec.clone();
            with.masses.push(crate::core::model::spec::MassSpec {
                at: at.to_string(),
                mass: m,
                inertia: 0.0,
            });
            Model::from_spec(&with)?
        }
        None => Model::from_spec(spec)?,
    };
    let sim = accelerations(
        &model,
        theta,
        &SynthOptions {
            rate_hz: args.raw.rate,
            duration_s: seconds,
            damping: args.raw.damping,
            max_frequency_hz: None,
            noise_rel: args.raw.sensor_noise,
            seed: args.seed.wrapping_mul(1_000_003).wrapping_add(k as u64),
            quantities: vec![],
        },
    )?;
    let rec = &sim.record;
    let r = rec.channels.len();
    let units = vec!["m/s^2".to_string(); r];
    let per = (args.raw.block * args.raw.rate).round().max(1.0) as usize;
    let mut at = 0;
    while at < rec.len() {
        let n = per.min(rec.len() - at);
        let mut values = Vec::with_capacity(n * r);
        for i in at..at + n {
            values.extend((0..r).map(|c| rec.samples[(i, c)]));
        }
        let start =
            time + chrono::TimeDelta::nanoseconds((at as f64 / args.raw.rate * 1e9).round() as i64);
        let block = Accel::encode(
            &model.name,
            start,
            args.raw.rate,
            &rec.channels,
            &units,
            &values,
        );
        w.write(topic, to_ns(start)?, &to_wire(&block))?;
        at += n;
    }
    Ok(())
}

/// The scenario's event in words, for the summary line.
fn describe(sc: &Scenario, model: &Model) -> String {
    let name = |l: usize| model.parameters()[l].name.clone();
    match &sc.event {
        Event::None => "no event".into(),
        Event::Loosening {
            parameter,
            start_day,
            duration_days,
            loss,
        } => format!(
            "{} loses {:.0} % linearly over {duration_days} days from day {start_day}",
            name(*parameter),
            100.0 * loss
        ),
        Event::Sudden {
            parameter,
            day,
            loss,
        } => format!(
            "{} drops {:.0} % on day {day}",
            name(*parameter),
            100.0 * loss
        ),
        Event::Mass { at, mass, day } => format!("{mass} kg fixed to {at} on day {day}"),
    }
}
