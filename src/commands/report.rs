//! `boltwatch report OUT.mcap -o DIR`: plots of a replay's (or the daemon's) outputs, per
//! structure: `DIR/<structure>-stiffness.svg` (each parameter's estimate per set, its
//! filtered level with the 95 % band, the baseline, alert markers),
//! `DIR/<structure>-frequencies.svg` (measured frequencies, their change from the mean
//! of the first 20 sets, model − measured) and `DIR/<structure>-epsilon.svg` (ε against its χ² bound,
//! cold starts, model-inadequacy alerts). With normalisation, also
//! `DIR/<structure>-normalised.svg` (each connection's loss against the stiffness expected
//! under its conditions, with its band and alerts) and `DIR/<structure>-temperature.svg` (θ
//! against temperature with the learned law and its band). Time in days from the first
//! estimate. Each figure also as PNG (`….png`), for mail and documents.

use std::collections::BTreeMap;
use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use chrono::{DateTime, Utc};
use serde_json::Value;

use crate::contract::AlertLevel;
use crate::io::mcap::read_all;
use crate::plot::{Band, Legend, Panel, Scale, Series, figure_png, figure_svg_with};

#[derive(Debug, clap::Args)]
pub struct ReportArgs {
    /// Output recording of `replay` or `run`.
    pub recording: PathBuf,
    /// Directory for the plots (created).
    #[arg(short, long)]
    pub out: PathBuf,
    /// Model file of a structure in the recording (repeatable; matched by the model's
    /// name): its frame is drawn too, each connection coloured by its change from baseline
    /// in the last estimate (`DIR/<structure>-structure.svg`).
    #[arg(long)]
    pub model: Vec<PathBuf>,
}

/// Outputs of one structure, in file order.
#[derive(Default)]
struct Outputs {
    stiffness: Vec<Value>,
    alerts: Vec<Value>,
    crosscheck: Vec<Value>,
    rejected: usize,
}

/// The `time` of an output message.
fn time(v: &Value) -> Option<DateTime<Utc>> {
    DateTime::parse_from_rfc3339(v["time"].as_str()?)
        .ok()
        .map(|t| t.with_timezone(&Utc))
}

/// A JSON number as f64 (NaN when absent or not a number).
fn f(v: &Value) -> f64 {
    v.as_f64().unwrap_or(f64::NAN)
}

/// Writes the figures of each structure in the recording, and the frames of `--model`.
pub fn run(args: &ReportArgs) -> Result<()> {
    let msgs = read_all(&args.recording)?;
    let mut by: BTreeMap<String, Outputs> = BTreeMap::new();
    for m in &msgs {
        let mut parts = m.topic.split('/');
        let (Some("boltwatch"), Some(s), Some(suffix)) = (parts.next(), parts.next(), parts.next())
        else {
            continue;
        };
        let o = by.entry(s.to_string()).or_default();
        let parse = || {
            serde_json::from_slice::<Value>(&m.data)
                .with_context(|| format!("{}: message {} is not JSON", m.topic, m.sequence))
        };
        match suffix {
            "stiffness" => o.stiffness.push(parse()?),
            "alerts" => o.alerts.push(parse()?),
            "crosscheck" => o.crosscheck.push(parse()?),
            "rejected" => o.rejected += 1,
            _ => {}
        }
    }
    by.retain(|_, o| !o.stiffness.is_empty());
    if by.is_empty() {
        bail!(
            "{} has no boltwatch/<structure>/stiffness messages to report",
            args.recording.display()
        );
    }
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("cannot create {}", args.out.display()))?;
    for (structure, o) in &by {
        for (name, panels, columns) in report_structure(structure, o)? {
            let svg = args.out.join(format!("{structure}-{name}.svg"));
            std::fs::write(&svg, figure_svg_with(&panels, columns, Legend::Once))
                .with_context(|| format!("cannot write {}", svg.display()))?;
            let png = svg.with_extension("png");
            figure_png(&panels, columns, Legend::Once, &png)
                .with_context(|| format!("cannot write {}", png.display()))?;
            println!("{}\n{}", svg.display(), png.display());
        }
    }
    for path in &args.model {
        let spec = crate::io::model::load_spec(path)?;
        let Some(o) = by.get(&spec.name) else {
            bail!(
                "{}: structure `{}` has no estimates in {}",
                path.display(),
                spec.name,
                args.recording.display()
            );
        };
        let model = crate::core::model::Model::from_spec(&spec)
            .with_context(|| format!("model file {}", path.display()))?;
        let svg = structure_svg(&spec, &model, o).with_context(|| {
            format!(
                "{}: only frame models (plane or space) are drawn",
                path.display()
            )
        })?;
        let file = args.out.join(format!("{}-structure.svg", spec.name));
        std::fs::write(&file, svg).with_context(|| format!("cannot write {}", file.display()))?;
        println!("{}", file.display());
    }
    Ok(())
}

/// The frame with each connection coloured by its parameter's change in the last estimate.
fn structure_svg(
    spec: &crate::core::model::spec::ModelSpec,
    model: &crate::core::model::Model,
    o: &Outputs,
) -> Option<String> {
    let g = crate::draw::Geometry::of(spec)?;
    let last: crate::contract::Estimate =
        serde_json::from_value(o.stiffness.last()?.clone()).ok()?;
    Some(crate::draw::estimate_svg(&g, model, &last, 720.0, 640.0))
}

/// A figure: its name, panels and columns.
type Figure = (&'static str, Vec<Panel>, usize);

/// The axis of θ: a ratio, so its unit says what 1 is.
const THETA_AXIS: &str = "θ, stiffness / nominal (1 = nominal)";

/// The figures of one structure, time in days from its first estimate: stiffness,
/// frequencies, ε and, with normalisation, the seasonal ones.
fn report_structure(structure: &str, o: &Outputs) -> Result<Vec<Figure>> {
    let t0 = o
        .stiffness
        .iter()
        .find_map(time)
        .context("estimates without a time")?;
    let day = |v: &Value| {
        time(v).map_or(f64::NAN, |t| {
            (t - t0).num_milliseconds() as f64 / 86_400_000.0
        })
    };
    let days: Vec<f64> = o.stiffness.iter().map(day).collect();
    let names: Vec<String> = o.stiffness[0]["parameters"]
        .as_array()
        .into_iter()
        .flatten()
        .map(|p| p["name"].as_str().unwrap_or_default().to_string())
        .collect();
    let mut figures = vec![
        stiffness_figure(structure, o, &names, &days, &day),
        frequencies_figure(structure, o, &days),
        epsilon_figure(structure, o, &days, &day),
    ];
    figures.extend(seasons_figures(structure, o, &names, &days, &day));
    Ok(figures)
}

/// The latest loosening alert level of each connection: 2 alarm, 1 warning, 0 none or
/// cleared.
fn alert_levels(o: &Outputs) -> BTreeMap<&str, u8> {
    let mut levels = BTreeMap::new();
    for a in o.alerts.iter().filter(|a| a["kind"] == "loosening") {
        if let Some(c) = a["connection"].as_str() {
            let level = serde_json::from_value(a["level"].clone()).ok();
            levels.insert(c, AlertLevel::severity(level));
        }
    }
    levels
}

/// `stiffness`: one panel per parameter, with θ per set, its filtered level and that
/// level's 95 % band, the baseline and the alerts; connections in alarm first, then in
/// warning, then the others in the model's order.
fn stiffness_figure(
    structure: &str,
    o: &Outputs,
    names: &[String],
    days: &[f64],
    day: &dyn Fn(&Value) -> f64,
) -> Figure {
    let levels = alert_levels(o);
    let level = |n: &String| levels.get(n.as_str()).copied().unwrap_or(0);
    let mut order: Vec<(usize, &String)> = names.iter().enumerate().collect();
    order.sort_by_key(|(l, n)| (std::cmp::Reverse(level(n)), *l));
    let mut panels = Vec::new();
    for (l, name) in order {
        let title = match level(name) {
            2 => format!("{structure}: {name} (alarm)"),
            1 => format!("{structure}: {name} (warning)"),
            _ => format!("{structure}: {name}"),
        };
        let col = |get: &dyn Fn(&Value) -> f64| -> Vec<f64> {
            o.stiffness
                .iter()
                .map(|e| get(&e["parameters"][l]))
                .collect()
        };
        let mut p = Panel::new(
            &title,
            "time, days",
            THETA_AXIS,
            Scale::Linear,
            Scale::Linear,
        );
        p.bands.push(Band {
            label: "95 % band of the filtered level".into(),
            x: days.to_vec(),
            lower: col(&|v| f(&v["filtered"]["lower95"])),
            upper: col(&|v| f(&v["filtered"]["upper95"])),
        });
        p.series.push(
            Series::trace("θ per set", days.to_vec(), col(&|v| f(&v["theta"])))
                .with_color("#9a9a9a")
                .with_width(0.6),
        );
        p.series.push(
            Series::trace(
                "filtered",
                days.to_vec(),
                col(&|v| f(&v["filtered"]["level"])),
            )
            .with_color("#1f77b4"),
        );
        if let Some(b) = o
            .stiffness
            .iter()
            .rev()
            .find_map(|e| e["parameters"][l]["baseline"].as_f64())
        {
            p.hlines.push((b, "baseline".into()));
        }
        p.series
            .extend(alert_markers(o, name, day, |a| f(&a["theta"])));
        panels.push(p);
    }
    ("stiffness", panels, 3)
}

/// `frequencies`: the measured frequencies, their change from the mean of the first 20
/// sets, and model − measured, a trace per mode in each panel.
fn frequencies_figure(structure: &str, o: &Outputs, days: &[f64]) -> Figure {
    let n_modes = o
        .stiffness
        .iter()
        .map(|e| e["modes"].as_array().map_or(0, Vec::len))
        .max()
        .unwrap_or(0);
    let mut pf = Panel::new(
        &format!("{structure}: measured frequencies"),
        "time, days",
        "frequency, Hz",
        Scale::Linear,
        Scale::Log,
    );
    let mut pc = Panel::new(
        &format!("{structure}: measured frequency change from the first 20 sets' mean"),
        "time, days",
        "change, %",
        Scale::Linear,
        Scale::Linear,
    );
    let mut pe = Panel::new(
        &format!("{structure}: model − measured frequency"),
        "time, days",
        "difference, % of measured",
        Scale::Linear,
        Scale::Linear,
    );
    for m in 0..n_modes {
        let [measured, change, difference] = mode_traces(o, days, m);
        pf.series.push(measured);
        pc.series.push(change);
        pe.series.push(difference);
    }
    ("frequencies", vec![pf, pc, pe], 1)
}

/// Mode `m`'s traces: its measured frequency, that frequency's change in % from the mean
/// of the first 20 sets (the commissioning period), and model − measured in % of measured.
fn mode_traces(o: &Outputs, days: &[f64], m: usize) -> [Series; 3] {
    let get = |k: &str| -> Vec<f64> { o.stiffness.iter().map(|e| f(&e["modes"][m][k])).collect() };
    let (meas, model) = (get("measured_hz"), get("model_hz"));
    let label = format!("mode {}", m + 1);
    // Reference: the mean of the first 20 sets (the commissioning period).
    let early: Vec<f64> = meas
        .iter()
        .copied()
        .filter(|v| v.is_finite())
        .take(20)
        .collect();
    let first = early.iter().sum::<f64>() / early.len() as f64;
    [
        Series::trace(label.clone(), days.to_vec(), meas.clone()).with_width(0.8),
        Series::trace(
            label.clone(),
            days.to_vec(),
            meas.iter().map(|v| 100.0 * (v / first - 1.0)).collect(),
        )
        .with_width(0.6),
        Series::trace(
            label,
            days.to_vec(),
            meas.iter()
                .zip(&model)
                .map(|(a, b)| 100.0 * (b - a) / a)
                .collect(),
        )
        .with_width(0.6),
    ]
}

/// `epsilon`: the misfit ε (5) per set against its χ² bound, with the model-inadequacy
/// alerts and the cold starts.
fn epsilon_figure(
    structure: &str,
    o: &Outputs,
    days: &[f64],
    day: &dyn Fn(&Value) -> f64,
) -> Figure {
    let mut pe = Panel::new(
        &format!("{structure}: misfit ε (5) per set"),
        "time, days",
        "ε (dimensionless)",
        Scale::Linear,
        Scale::Log,
    );
    pe.series.push(
        Series::trace(
            "ε",
            days.to_vec(),
            o.stiffness.iter().map(|e| f(&e["epsilon"])).collect(),
        )
        .with_width(0.8),
    );
    pe.series.push(
        Series::trace(
            "χ² bound",
            days.to_vec(),
            o.stiffness.iter().map(|e| f(&e["epsilon_bound"])).collect(),
        )
        .with_color("#555555"),
    );
    for a in o.alerts.iter().filter(|a| a["kind"] == "model-inadequate") {
        pe.vlines.push((
            day(a),
            format!(
                "model-inadequate {}",
                a["level"].as_str().unwrap_or_default()
            ),
        ));
    }
    let cold: Vec<&Value> = o
        .stiffness
        .iter()
        .filter(|e| e["warm_start"] == false)
        .collect();
    if !cold.is_empty() {
        pe.series.push(
            Series::points(
                "cold start",
                cold.iter().map(|e| day(e)).collect(),
                cold.iter().map(|e| f(&e["epsilon"])).collect(),
            )
            .with_color("#d62728"),
        );
    }
    ("epsilon", vec![pe], 1)
}

/// With normalisation: `normalised` (each connection's loss against the stiffness expected
/// under its conditions over time, with its 95 % band, the thresholds and the alerts) and,
/// when the sets carry a temperature, `temperature` (θ per set against the temperature,
/// with the learned law and its band once the models are frozen).
fn seasons_figures(
    structure: &str,
    o: &Outputs,
    names: &[String],
    days: &[f64],
    day: &dyn Fn(&Value) -> f64,
) -> Vec<Figure> {
    let normalised = |e: &Value, l: usize| e["parameters"][l].get("normalised").cloned();
    let with: Vec<usize> = (0..names.len())
        .filter(|&l| o.stiffness.iter().any(|e| normalised(e, l).is_some()))
        .collect();
    if with.is_empty() {
        return Vec::new();
    }
    let mut loss_panels = Vec::new();
    let mut law_panels = Vec::new();
    for &l in &with {
        let name = &names[l];
        // In %, within the plotted range: the first sets' bands, while the law is mostly
        // its prior, reach far into "stiffer than expected".
        let get = |k: &str| -> Vec<f64> {
            o.stiffness
                .iter()
                .map(|e| {
                    normalised(e, l).map_or(f64::NAN, |n| {
                        (100.0 * f(&n[k])).clamp(LOSS_SHOWN[0], LOSS_SHOWN[1])
                    })
                })
                .collect()
        };
        let mut p = Panel::new(
            &format!("{structure}: {name}"),
            "time, days",
            "loss against expected, % (clipped to -50 … 100)",
            Scale::Linear,
            Scale::Linear,
        );
        p.bands.push(Band {
            label: "95 % band".into(),
            x: days.to_vec(),
            lower: get("loss_lower95"),
            upper: get("loss_upper95"),
        });
        p.series.push(
            Series::trace("normalised loss", days.to_vec(), get("loss")).with_color("#1f77b4"),
        );
        p.hlines.push((0.0, String::new()));
        p.series
            .extend(alert_markers(o, name, day, |a| 100.0 * f(&a["drop"])));
        loss_panels.push(p);
        if let Some(p) = law_panel(structure, name, o, l) {
            law_panels.push(p);
        }
    }
    let mut out = vec![("normalised", loss_panels, 3)];
    if !law_panels.is_empty() {
        out.push(("temperature", law_panels, 3));
    }
    out
}

/// The loosening alerts of connection `name` as markers, one series per level (warning,
/// alarm, cleared), at `value` of each alert.
fn alert_markers(
    o: &Outputs,
    name: &str,
    day: &dyn Fn(&Value) -> f64,
    value: impl Fn(&Value) -> f64,
) -> Vec<Series> {
    [
        ("warning", "#ff7f0e"),
        ("alarm", "#d62728"),
        ("cleared", "#2ca02c"),
    ]
    .into_iter()
    .filter_map(|(level, color)| {
        let hits: Vec<&Value> = o
            .alerts
            .iter()
            .filter(|a| a["connection"].as_str() == Some(name) && a["level"] == level)
            .collect();
        (!hits.is_empty()).then(|| {
            Series::points(
                level,
                hits.iter().map(|a| day(a)).collect(),
                hits.iter().map(|a| value(a)).collect(),
            )
            .with_color(color)
        })
    })
    .collect()
}

/// The range of normalised loss drawn, %.
const LOSS_SHOWN: [f64; 2] = [-50.0, 100.0];

/// θ per set against temperature, and the expectation of the frozen model (sets judged
/// after the training period) as a line with its band, sorted by temperature.
fn law_panel(structure: &str, name: &str, o: &Outputs, l: usize) -> Option<Panel> {
    let points: Vec<(f64, f64)> = o
        .stiffness
        .iter()
        .filter_map(|e| {
            Some((
                e["temperature_c"].as_f64()?,
                f(&e["parameters"][l]["theta"]),
            ))
        })
        .collect();
    if points.is_empty() {
        return None;
    }
    let mut frozen: Vec<(f64, f64, f64, f64)> = o
        .stiffness
        .iter()
        .filter(|e| {
            e["normalisation"]["learning"] == false && e["normalisation"]["source"] == "covariates"
        })
        .filter_map(|e| {
            let n = e["parameters"][l].get("normalised")?;
            Some((
                e["temperature_c"].as_f64()?,
                f(&n["expected"]),
                f(&n["expected_lower95"]),
                f(&n["expected_upper95"]),
            ))
        })
        .collect();
    frozen.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut p = Panel::new(
        &format!("{structure}: {name}"),
        "temperature, °C",
        THETA_AXIS,
        Scale::Linear,
        Scale::Linear,
    );
    let (t, y): (Vec<f64>, Vec<f64>) = points.into_iter().unzip();
    p.series.push(
        Series::points("θ per set", t, y)
            .with_color("#9a9a9a")
            .with_width(0.5),
    );
    if !frozen.is_empty() {
        let t: Vec<f64> = frozen.iter().map(|v| v.0).collect();
        p.bands.push(Band {
            label: "95 % band of a healthy θ".into(),
            x: t.clone(),
            lower: frozen.iter().map(|v| v.2).collect(),
            upper: frozen.iter().map(|v| v.3).collect(),
        });
        p.series.push(
            Series::trace(
                "expected (learned law)",
                t,
                frozen.iter().map(|v| v.1).collect(),
            )
            .with_color("#1f77b4"),
        );
    }
    Some(p)
}
