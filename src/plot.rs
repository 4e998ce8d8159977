//! Minimal SVG line charts: panels of series on linear or log axes, with ticks, labels,
//! legends and vertical markers. Self-contained (no font metrics needed: SVG text is laid
//! out by the viewer).

use std::fmt::Write;

/// Axis scale.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Scale {
    Linear,
    Log,
}

/// One line (and/or markers) on a panel.
#[derive(Debug, Clone)]
pub struct Series {
    pub label: String,
    pub x: Vec<f64>,
    pub y: Vec<f64>,
    /// Draw a marker at every point.
    pub markers: bool,
    /// Draw the connecting line.
    pub line: bool,
    /// Colour (default: the palette's, by position).
    pub color: Option<&'static str>,
    /// Line width.
    pub width: f64,
}

impl Series {
    pub fn line(label: impl Into<String>, x: Vec<f64>, y: Vec<f64>) -> Self {
        Self {
            label: label.into(),
            x,
            y,
            markers: true,
            line: true,
            color: None,
            width: 1.6,
        }
    }

    /// Markers only.
    pub fn points(label: impl Into<String>, x: Vec<f64>, y: Vec<f64>) -> Self {
        Self {
            line: false,
            ..Self::line(label, x, y)
        }
    }

    /// A line without markers (long histories).
    pub fn trace(label: impl Into<String>, x: Vec<f64>, y: Vec<f64>) -> Self {
        Self {
            markers: false,
            ..Self::line(label, x, y)
        }
    }

    pub fn with_color(self, color: &'static str) -> Self {
        Self {
            color: Some(color),
            ..self
        }
    }

    pub fn with_width(self, width: f64) -> Self {
        Self { width, ..self }
    }
}

/// One chart.
#[derive(Debug, Clone)]
pub struct Panel {
    pub title: String,
    pub x_label: String,
    pub y_label: String,
    pub x_scale: Scale,
    pub y_scale: Scale,
    pub series: Vec<Series>,
    /// Vertical reference lines `(x, label)`.
    pub vlines: Vec<(f64, String)>,
    /// Horizontal reference lines `(y, label)`.
    pub hlines: Vec<(f64, String)>,
    /// Shaded bands (e.g. a 95 % interval), drawn under the series.
    pub bands: Vec<Band>,
}

/// A shaded region between `lower` and `upper` over `x`.
#[derive(Debug, Clone)]
pub struct Band {
    pub label: String,
    pub x: Vec<f64>,
    pub lower: Vec<f64>,
    pub upper: Vec<f64>,
}

impl Panel {
    pub fn new(title: &str, x_label: &str, y_label: &str, x_scale: Scale, y_scale: Scale) -> Self {
        Self {
            title: title.into(),
            x_label: x_label.into(),
            y_label: y_label.into(),
            x_scale,
            y_scale,
            series: Vec::new(),
            vlines: Vec::new(),
            hlines: Vec::new(),
            bands: Vec::new(),
        }
    }
}

const PALETTE: [&str; 10] = [
    "#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#17becf",
    "#7f7f7f", "#bcbd22",
];
const W: f64 = 620.0;
const H: f64 = 380.0;
const LEFT: f64 = 80.0;
const RIGHT: f64 = 150.0;
const TOP: f64 = 36.0;
const BOTTOM: f64 = 52.0;

struct Axis {
    scale: Scale,
    lo: f64,
    hi: f64,
}

impl Axis {
    fn fit(values: impl Iterator<Item = f64>, scale: Scale) -> Self {
        let ok = |v: &f64| v.is_finite() && (scale == Scale::Linear || *v > 0.0);
        let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
        for v in values.filter(ok) {
            lo = lo.min(v);
            hi = hi.max(v);
        }
        if !lo.is_finite() {
            (lo, hi) = (1.0, 10.0);
        }
        match scale {
            Scale::Log => {
                if hi <= lo * 1.000001 {
                    (lo, hi) = (lo / 2.0, hi * 2.0);
                }
                Self {
                    scale,
                    lo: 10f64.powf(lo.log10().floor()),
                    hi: 10f64.powf(hi.log10().ceil()),
                }
            }
            Scale::Linear => {
                if hi - lo <= 1e-12 * hi.abs().max(1e-300) {
                    let d = if lo == 0.0 { 1.0 } else { 0.1 * lo.abs() };
                    (lo, hi) = (lo - d, hi + d);
                }
                let pad = 0.05 * (hi - lo);
                Self {
                    scale,
                    lo: lo - pad,
                    hi: hi + pad,
                }
            }
        }
    }

    /// Position of `v` in [0, 1].
    fn frac(&self, v: f64) -> f64 {
        match self.scale {
            Scale::Linear => (v - self.lo) / (self.hi - self.lo),
            Scale::Log => (v.log10() - self.lo.log10()) / (self.hi.log10() - self.lo.log10()),
        }
    }

    fn valid(&self, v: f64) -> bool {
        v.is_finite() && (self.scale == Scale::Linear || v > 0.0)
    }

    fn ticks(&self) -> Vec<f64> {
        match self.scale {
            Scale::Log => {
                let (a, b) = (
                    self.lo.log10().round() as i32,
                    self.hi.log10().round() as i32,
                );
                let step = ((b - a) as f64 / 8.0).ceil().max(1.0) as i32;
                (a..=b)
                    .step_by(step as usize)
                    .map(|k| 10f64.powi(k))
                    .collect()
            }
            Scale::Linear => {
                let raw = (self.hi - self.lo) / 6.0;
                let mag = 10f64.powf(raw.log10().floor());
                let step = [1.0, 2.0, 5.0, 10.0]
                    .iter()
                    .map(|m| m * mag)
                    .find(|s| *s >= raw)
                    .unwrap_or(10.0 * mag);
                let mut t = (self.lo / step).ceil() * step;
                let mut out = Vec::new();
                while t <= self.hi + 1e-9 * step {
                    out.push(if t.abs() < 1e-12 * step { 0.0 } else { t });
                    t += step;
                }
                out
            }
        }
    }
}

fn fmt_tick(v: f64, scale: Scale) -> String {
    match scale {
        Scale::Log => format!("1e{}", v.log10().round() as i32),
        Scale::Linear => {
            let a = v.abs();
            if a == 0.0 {
                "0".into()
            } else if !(1e-3..1e5).contains(&a) {
                format!("{v:.1e}")
            } else {
                let s = format!("{v:.4}");
                s.trim_end_matches('0').trim_end_matches('.').to_string()
            }
        }
    }
}

fn esc(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
}

fn panel_svg(out: &mut String, p: &Panel, ox: f64, oy: f64) {
    let xa = Axis::fit(
        p.series
            .iter()
            .flat_map(|s| s.x.iter().copied())
            .chain(p.vlines.iter().map(|v| v.0)),
        p.x_scale,
    );
    let ya = Axis::fit(
        p.series
            .iter()
            .flat_map(|s| s.y.iter().copied())
            .chain(p.hlines.iter().map(|v| v.0))
            .chain(
                p.bands
                    .iter()
                    .flat_map(|b| b.lower.iter().chain(&b.upper).copied()),
            ),
        p.y_scale,
    );
    let (pw, ph) = (W - LEFT - RIGHT, H - TOP - BOTTOM);
    let px = |v: f64| ox + LEFT + pw * xa.frac(v);
    let py = |v: f64| oy + TOP + ph * (1.0 - ya.frac(v));
    let _ = writeln!(
        out,
        r##"<rect x="{:.1}" y="{:.1}" width="{pw:.1}" height="{ph:.1}" fill="none" stroke="#333"/>"##,
        ox + LEFT,
        oy + TOP
    );
    let _ = writeln!(
        out,
        r#"<text x="{:.1}" y="{:.1}" font-size="14" text-anchor="middle" font-weight="bold">{}</text>"#,
        ox + LEFT + pw / 2.0,
        oy + 22.0,
        esc(&p.title)
    );
    for t in xa.ticks() {
        let x = px(t);
        if !(ox + LEFT - 0.5..=ox + LEFT + pw + 0.5).contains(&x) {
            continue;
        }
        let _ = writeln!(
            out,
            r##"<line x1="{x:.1}" y1="{:.1}" x2="{x:.1}" y2="{:.1}" stroke="#ddd"/><text x="{x:.1}" y="{:.1}" font-size="11" text-anchor="middle">{}</text>"##,
            oy + TOP,
            oy + TOP + ph,
            oy + TOP + ph + 15.0,
            fmt_tick(t, xa.scale)
        );
    }
    for t in ya.ticks() {
        let y = py(t);
        if !(oy + TOP - 0.5..=oy + TOP + ph + 0.5).contains(&y) {
            continue;
        }
        let _ = writeln!(
            out,
            r##"<line x1="{:.1}" y1="{y:.1}" x2="{:.1}" y2="{y:.1}" stroke="#ddd"/><text x="{:.1}" y="{:.1}" font-size="11" text-anchor="end">{}</text>"##,
            ox + LEFT,
            ox + LEFT + pw,
            ox + LEFT - 5.0,
            y + 4.0,
            fmt_tick(t, ya.scale)
        );
    }
    let _ = writeln!(
        out,
        r#"<text x="{:.1}" y="{:.1}" font-size="12" text-anchor="middle">{}</text>"#,
        ox + LEFT + pw / 2.0,
        oy + H - 12.0,
        esc(&p.x_label)
    );
    let _ = writeln!(
        out,
        r#"<text x="{:.1}" y="{:.1}" font-size="12" text-anchor="middle" transform="rotate(-90 {:.1} {:.1})">{}</text>"#,
        ox + 16.0,
        oy + TOP + ph / 2.0,
        ox + 16.0,
        oy + TOP + ph / 2.0,
        esc(&p.y_label)
    );
    for (v, label) in &p.vlines {
        if xa.valid(*v) {
            let x = px(*v);
            let _ = writeln!(
                out,
                r##"<line x1="{x:.1}" y1="{:.1}" x2="{x:.1}" y2="{:.1}" stroke="#000" stroke-dasharray="5,4"/><text x="{:.1}" y="{:.1}" font-size="11">{}</text>"##,
                oy + TOP,
                oy + TOP + ph,
                x + 3.0,
                oy + TOP + 12.0,
                esc(label)
            );
        }
    }
    for (v, label) in &p.hlines {
        if ya.valid(*v) {
            let y = py(*v);
            let _ = writeln!(
                out,
                r##"<line x1="{:.1}" y1="{y:.1}" x2="{:.1}" y2="{y:.1}" stroke="#555" stroke-dasharray="2,3"/><text x="{:.1}" y="{:.1}" font-size="11">{}</text>"##,
                ox + LEFT,
                ox + LEFT + pw,
                ox + LEFT + 4.0,
                y - 3.0,
                esc(label)
            );
        }
    }
    for (k, b) in p.bands.iter().enumerate() {
        let color = PALETTE[k % PALETTE.len()];
        let pts: Vec<(f64, f64, f64)> =
            b.x.iter()
                .zip(b.lower.iter().zip(&b.upper))
                .filter(|(x, (lo, hi))| xa.valid(**x) && ya.valid(**lo) && ya.valid(**hi))
                .map(|(x, (lo, hi))| (px(*x), py(*lo), py(*hi)))
                .collect();
        if pts.len() > 1 {
            let upper = pts.iter().map(|(x, _, hi)| format!("{x:.1},{hi:.1}"));
            let lower = pts.iter().rev().map(|(x, lo, _)| format!("{x:.1},{lo:.1}"));
            let d: Vec<String> = upper.chain(lower).collect();
            let _ = writeln!(
                out,
                r#"<polygon points="{}" fill="{color}" fill-opacity="0.3" stroke="none"><title>{}</title></polygon>"#,
                d.join(" "),
                esc(&b.label)
            );
        }
    }
    let mut legend = 0usize;
    for (k, s) in p.series.iter().enumerate() {
        let color = s.color.unwrap_or(PALETTE[k % PALETTE.len()]);
        let dash = if k >= PALETTE.len() {
            r#" stroke-dasharray="6,3""#
        } else {
            ""
        };
        let pts: Vec<(f64, f64)> =
            s.x.iter()
                .zip(&s.y)
                .filter(|(x, y)| xa.valid(**x) && ya.valid(**y))
                .map(|(x, y)| (px(*x), py(*y)))
                .collect();
        if s.line && pts.len() > 1 {
            let d: Vec<String> = pts.iter().map(|(x, y)| format!("{x:.1},{y:.1}")).collect();
            let _ = writeln!(
                out,
                r#"<polyline points="{}" fill="none" stroke="{color}" stroke-width="{}"{dash}/>"#,
                d.join(" "),
                s.width
            );
        }
        if s.markers {
            for (x, y) in &pts {
                let _ = writeln!(
                    out,
                    r#"<circle cx="{x:.1}" cy="{y:.1}" r="{}" fill="{color}"/>"#,
                    if s.line { 2.4 } else { 4.0 }
                );
            }
        }
        if s.label.is_empty() {
            continue;
        }
        let ly = oy + TOP + 8.0 + 15.0 * legend as f64;
        legend += 1;
        let lx = ox + LEFT + pw + 10.0;
        let _ = writeln!(
            out,
            r#"<line x1="{lx:.1}" y1="{ly:.1}" x2="{:.1}" y2="{ly:.1}" stroke="{color}" stroke-width="2"{dash}/><text x="{:.1}" y="{:.1}" font-size="11">{}</text>"#,
            lx + 18.0,
            lx + 22.0,
            ly + 4.0,
            esc(&s.label)
        );
    }
}

/// An SVG document with `panels` laid out in `columns` columns.
pub fn figure_svg(panels: &[Panel], columns: usize) -> String {
    let columns = columns.max(1);
    let rows = panels.len().div_ceil(columns);
    let (w, h) = (W * columns as f64, H * rows.max(1) as f64);
    let mut out = String::new();
    let _ = writeln!(
        out,
        r#"<svg xmlns="http://www.w3.org/2000/svg" width="{w}" height="{h}" viewBox="0 0 {w} {h}" font-family="sans-serif">"#
    );
    let _ = writeln!(out, r#"<rect width="{w}" height="{h}" fill="white"/>"#);
    for (i, p) in panels.iter().enumerate() {
        panel_svg(
            &mut out,
            p,
            W * (i % columns) as f64,
            H * (i / columns) as f64,
        );
    }
    out.push_str("</svg>\n");
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn log_ticks_are_decades_inside_the_range() {
        let a = Axis::fit([3.0, 4.0e4].into_iter(), Scale::Log);
        assert_eq!((a.lo, a.hi), (1.0, 1e5));
        assert_eq!(a.ticks(), vec![1.0, 10.0, 100.0, 1e3, 1e4, 1e5]);
        assert!((a.frac(100.0) - 0.4).abs() < 1e-12);
    }

    #[test]
    fn linear_ticks_are_round_and_cover_the_data() {
        let a = Axis::fit([0.27, 0.93].into_iter(), Scale::Linear);
        let t = a.ticks();
        assert!(t.first().unwrap() >= &a.lo && t.last().unwrap() <= &a.hi);
        assert!(t.contains(&0.4) && t.contains(&0.8), "{t:?}");
    }

    #[test]
    fn svg_skips_points_a_log_axis_cannot_show() {
        let mut p = Panel::new("t", "x", "y", Scale::Log, Scale::Log);
        p.series.push(Series::line(
            "s",
            vec![1.0, 10.0, 100.0],
            vec![1.0, -1.0, f64::NAN],
        ));
        let svg = figure_svg(&[p], 1);
        assert_eq!(svg.matches("<circle").count(), 1);
        assert!(svg.starts_with("<svg") && svg.ends_with("</svg>\n"));
    }
}
