//! The console's charts, drawn server-side as SVG: the filtered level of every connection
//! with its band, baseline and alerts; ε against its bound; an overview's sparkline.
//! A chart line keeps at most [`LINE_POINTS`] samples ([`envelope`]), so a page stays
//! small however long the history.

use std::fmt::Write as _;

use crate::daemon::history::{Logged, Point, Sample};
use crate::plot::{Band, Legend, Panel, Scale, Series, figure_svg_with};

/// At most this many samples per chart line: a panel is a few hundred pixels wide.
pub const LINE_POINTS: usize = 600;

/// The samples a line keeps of `samples`: all when they fit in `max`, else per one of
/// `max / 2` equal runs the one where `value` is lowest and the one where it is highest,
/// in time order, so a drop or a spike shows however long the window.
pub fn envelope(samples: &[&Sample], value: impl Fn(&Sample) -> f32, max: usize) -> Vec<usize> {
    let n = samples.len();
    let bins = (max / 2).max(1);
    if n <= max {
        return (0..n).collect();
    }
    let mut keep = Vec::with_capacity(2 * bins);
    for b in 0..bins {
        let run = (b * n / bins)..((b + 1) * n / bins);
        let at = |i: &usize| value(samples[*i]);
        let lo = run.clone().min_by(|a, b| at(a).total_cmp(&at(b)));
        let hi = run.max_by(|a, b| at(a).total_cmp(&at(b)));
        if let (Some(lo), Some(hi)) = (lo, hi) {
            keep.push(lo.min(hi));
            if hi != lo {
                keep.push(lo.max(hi));
            }
        }
    }
    keep
}

/// Days since the first of `samples` (the chart's time axis).
fn day_axis(samples: &[&Sample]) -> impl Fn(i64) -> f64 {
    let t0 = samples.first().map_or(0, |s| s.time_ms);
    move |t| (t - t0) as f64 / 86_400_000.0
}

/// The filtered level of each parameter in `order` over `samples`, with its 95 % band, the
/// baseline, the level expected under the conditions (when the structure normalises) and
/// the alerts; one panel each, one legend.
pub fn levels(structure: &str, h: &Logged, samples: &[&Sample], order: &[usize]) -> String {
    let days = day_axis(samples);
    let names = h.names();
    let mut panels = Vec::new();
    for &l in order {
        let keep = envelope(samples, |s| s.points[l].level, LINE_POINTS);
        let x: Vec<f64> = keep.iter().map(|&i| days(samples[i].time_ms)).collect();
        let col = |f: fn(&Point) -> f32| -> Vec<f64> {
            keep.iter()
                .map(|&i| f64::from(f(&samples[i].points[l])))
                .collect()
        };
        let mut p = Panel::new(
            &format!("{structure}: {}", names[l]),
            "time, days",
            "θ, stiffness / nominal",
            Scale::Linear,
            Scale::Linear,
        );
        p.bands.push(Band {
            label: "95 % band of the filtered level".into(),
            x: x.clone(),
            lower: col(|p| p.lower95),
            upper: col(|p| p.upper95),
        });
        let expected = col(|p| p.expected);
        if expected.iter().any(|v| v.is_finite()) {
            let e = Series::trace("expected under the conditions", x.clone(), expected);
            p.series.push(e.with_color("#7f7f7f"));
        }
        p.series
            .push(Series::trace("filtered", x, col(|p| p.level)).with_color("#1f77b4"));
        if let Some(b) = samples
            .last()
            .map(|s| s.points[l].baseline)
            .filter(|b| b.is_finite())
        {
            p.hlines.push((f64::from(b), "baseline".into()));
        }
        p.series.extend(marks(h, samples, &names[l], &days, l));
        panels.push(p);
    }
    figure_svg_with(&panels, 3, Legend::Once)
}

/// The alerts of connection `name` as points at the filtered level of the nearest sample.
fn marks(
    h: &Logged,
    samples: &[&Sample],
    name: &str,
    days: &dyn Fn(i64) -> f64,
    l: usize,
) -> Vec<Series> {
    let (Some(first), Some(last)) = (samples.first(), samples.last()) else {
        return Vec::new();
    };
    let (from, to) = (first.time_ms, last.time_ms);
    [
        ("warning", "#ff7f0e"),
        ("alarm", "#d62728"),
        ("cleared", "#2ca02c"),
    ]
    .into_iter()
    .filter_map(|(level, color)| {
        let at: Vec<(f64, f64)> = h
            .marks()
            .filter(|m| m.connection.as_deref() == Some(name) && m.level.as_str() == level)
            .filter(|m| (from..=to).contains(&m.time_ms))
            .map(|m| {
                let i = samples.partition_point(|s| s.time_ms < m.time_ms);
                let s = samples[i.min(samples.len() - 1)];
                (days(m.time_ms), f64::from(s.points[l].level))
            })
            .collect();
        (!at.is_empty()).then(|| {
            let (x, y) = at.into_iter().unzip();
            Series::points(level, x, y).with_color(color)
        })
    })
    .collect()
}

/// ε of each estimate over `samples` against its χ² bound.
pub fn epsilon(structure: &str, samples: &[&Sample]) -> String {
    let days = day_axis(samples);
    let keep = envelope(samples, |s| s.epsilon, LINE_POINTS);
    let x: Vec<f64> = keep.iter().map(|&i| days(samples[i].time_ms)).collect();
    let col = |f: fn(&Sample) -> f32| -> Vec<f64> {
        keep.iter().map(|&i| f64::from(f(samples[i]))).collect()
    };
    let mut p = Panel::new(
        &format!("{structure}: misfit ε against its χ² bound"),
        "time, days",
        "ε (dimensionless)",
        Scale::Linear,
        Scale::Linear,
    );
    p.series
        .push(Series::trace("ε", x.clone(), col(|s| s.epsilon)).with_color("#1f77b4"));
    p.series
        .push(Series::trace("χ² bound", x, col(|s| s.epsilon_bound)).with_color("#d62728"));
    figure_svg_with(&[p], 1, Legend::Once)
}

/// A sparkline of `values` (a polyline `width` × `height` px, NaN skipped), its title the
/// text a reader hovers.
pub fn sparkline(values: &[f32], width: f64, height: f64, title: &str) -> String {
    let finite = || values.iter().copied().filter(|v| v.is_finite());
    let (lo, hi) = finite().fold((f32::INFINITY, f32::NEG_INFINITY), |(a, b), v| {
        (a.min(v), b.max(v))
    });
    let mut svg = format!(
        "<svg class=\"spark\" xmlns=\"http://www.w3.org/2000/svg\" width=\"{width}\" \
         height=\"{height}\" viewBox=\"0 0 {width} {height}\"><title>{}</title>",
        super::pages::escape(title)
    );
    if lo.is_finite() {
        let span = f64::from((hi - lo).max(1e-6));
        let step = width / (values.len().max(2) - 1) as f64;
        let mut points = String::new();
        for (i, v) in values.iter().enumerate().filter(|(_, v)| v.is_finite()) {
            let y = height - 2.0 - (f64::from(*v - lo) / span) * (height - 4.0);
            let _ = write!(points, "{:.1},{y:.1} ", i as f64 * step);
        }
        let _ = write!(
            svg,
            "<polyline fill=\"none\" stroke=\"#1f77b4\" stroke-width=\"1.5\" points=\"{}\"/>",
            points.trim_end()
        );
    }
    svg.push_str("</svg>");
    svg
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample(t: i64, level: f32) -> Sample {
        let p = Point {
            theta: level,
            level,
            lower95: level - 0.1,
            upper95: level + 0.1,
            baseline: 1.0,
            expected: f32::NAN,
        };
        Sample {
            time_ms: t,
            epsilon: 1.0,
            epsilon_bound: 2.0,
            points: vec![p],
        }
    }

    #[test]
    fn the_envelope_keeps_a_short_line_whole_and_a_spike_in_a_long_one() {
        let short: Vec<Sample> = (0..10).map(|t| sample(t, 1.0)).collect();
        let refs: Vec<&Sample> = short.iter().collect();
        assert_eq!(
            envelope(&refs, |s| s.points[0].level, 600),
            (0..10).collect::<Vec<_>>()
        );
        // 10,000 samples at 1 with one drop to 0.2 at 7,777: kept, in time order, ≤ 600.
        let long: Vec<Sample> = (0..10_000)
            .map(|t| sample(t, if t == 7_777 { 0.2 } else { 1.0 }))
            .collect();
        let refs: Vec<&Sample> = long.iter().collect();
        let keep = envelope(&refs, |s| s.points[0].level, 600);
        assert!(keep.len() <= 600, "{}", keep.len());
        assert!(keep.contains(&7_777));
        assert!(keep.windows(2).all(|w| w[0] < w[1]));
        assert_eq!(keep.first(), Some(&0));
    }

    #[test]
    fn the_expected_level_is_drawn_only_when_the_structure_normalises() {
        let history = |expected: f32| {
            let mut samples: Vec<Sample> = (0..5).map(|t| sample(t * 60_000, 1.0)).collect();
            samples
                .iter_mut()
                .for_each(|s| s.points[0].expected = expected);
            Logged {
                files: vec![std::sync::Arc::new(crate::daemon::history::History {
                    names: vec!["C1".into()],
                    samples,
                    marks: Vec::new(),
                })],
            }
        };
        for (expected, drawn) in [(0.98, true), (f32::NAN, false)] {
            let h = history(expected);
            let svg = levels("s", &h, &h.samples_since(None), &[0]);
            assert!(svg.contains("s: C1"));
            assert_eq!(
                svg.contains("expected under the conditions"),
                drawn,
                "{expected}"
            );
        }
    }

    #[test]
    fn a_sparkline_spans_its_box() {
        let svg = sparkline(&[1.0, f32::NAN, 0.5], 100.0, 20.0, "C1 <a>");
        assert!(svg.contains("points=\"0.0,2.0 100.0,18.0\""), "{svg}");
        assert!(svg.contains("<title>C1 &lt;a&gt;</title>"));
    }
}
