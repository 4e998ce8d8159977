//! Line charts drawn with [`plotters`]: panels of series on linear or log axes, with ticks,
//! labels, legends, vertical and horizontal reference lines and shaded bands, laid out in a
//! grid and written as SVG ([`figure_svg`]) or PNG ([`figure_png`]). A figure of many panels
//! that share their series can carry one legend above them all ([`Legend::Once`]).
//!
//! Text is measured (and in PNGs drawn) with DejaVu Sans, bundled by the `dejavu` crate and
//! registered with plotters as `sans-serif`, so no system font is needed. SVG text still names
//! `sans-serif`: a viewer lays it out with its own font.

use std::ops::Range;
use std::path::Path;
use std::sync::Once;

use anyhow::Context;
use plotters::coord::Shift;
use plotters::coord::cartesian::Cartesian2d;
use plotters::coord::ranged1d::{AsRangedCoord, ValueFormatter};
use plotters::prelude::*;
use plotters::style::register_font;
use plotters::style::text_anchor::{HPos, Pos, VPos};

mod legend;
use legend::{Key, draw_legend, figure_legend, legend_height};

/// Where a figure's legends go.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Legend {
    /// Beside each panel, right of its plot.
    PerPanel,
    /// Once, above the panels: every label of every panel, each once.
    Once,
}

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
    /// Colour as `#rrggbb` (default: the palette's, by position).
    pub color: Option<&'static str>,
    /// Line width in pixels (rounded to a whole pixel, at least 1).
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

/// An SVG document with `panels` laid out in `columns` columns, a legend beside each.
pub fn figure_svg(panels: &[Panel], columns: usize) -> String {
    figure_svg_with(panels, columns, Legend::PerPanel)
}

/// An SVG document with `panels` laid out in `columns` columns, legends as `legend` says.
pub fn figure_svg_with(panels: &[Panel], columns: usize, legend: Legend) -> String {
    let mut svg = String::new();
    {
        let size = figure_size(panels, columns, legend);
        let root = SVGBackend::with_string(&mut svg, size);
        draw_figure(&root.into_drawing_area(), panels, columns, legend)
            .expect("drawing into an in-memory SVG with the bundled font does not fail");
    }
    inline_text(&svg)
}

/// A PNG image of `panels` laid out in `columns` columns, written to `path` (which must end
/// in `.png`: the encoder goes by the extension).
pub fn figure_png(
    panels: &[Panel],
    columns: usize,
    legend: Legend,
    path: &Path,
) -> anyhow::Result<()> {
    let root = BitMapBackend::new(path, figure_size(panels, columns, legend));
    draw_figure(&root.into_drawing_area(), panels, columns, legend)
        .with_context(|| format!("cannot write {}", path.display()))
}

const PALETTE: [RGBColor; 10] = [
    RGBColor(0x1f, 0x77, 0xb4),
    RGBColor(0xd6, 0x27, 0x28),
    RGBColor(0x2c, 0xa0, 0x2c),
    RGBColor(0xff, 0x7f, 0x0e),
    RGBColor(0x94, 0x67, 0xbd),
    RGBColor(0x8c, 0x56, 0x4b),
    RGBColor(0xe3, 0x77, 0xc2),
    RGBColor(0x17, 0xbe, 0xcf),
    RGBColor(0x7f, 0x7f, 0x7f),
    RGBColor(0xbc, 0xbd, 0x22),
];
const GRID: RGBColor = RGBColor(0xdd, 0xdd, 0xdd);
const MINOR_GRID: RGBColor = RGBColor(0xee, 0xee, 0xee);
const HLINE: RGBColor = RGBColor(0x55, 0x55, 0x55);
/// Size of one panel in pixels, and the room beside its plot: tick labels and axis titles on
/// the left and bottom, the legend on the right.
const W: u32 = 620;
const H: u32 = 380;
const LEFT: u32 = 72;
const BOTTOM: u32 = 44;
const RIGHT: u32 = 150;
/// The room right of the plot when the legend is above the figure.
const RIGHT_NARROW: u32 = 24;
const FONT: &str = "sans-serif";
/// Font sizes in plotters' units, 1.24 × the CSS pixels they come out as in SVG: 11, 12, 14.
const SMALL: u32 = 14;
const NORMAL: u32 = 15;
const TITLE: u32 = 17;

fn figure_size(panels: &[Panel], columns: usize, legend: Legend) -> (u32, u32) {
    let columns = columns.max(1);
    let rows = panels.len().div_ceil(columns).max(1);
    let width = W * columns as u32;
    let header = match legend {
        Legend::Once => legend_height(panels, width),
        Legend::PerPanel => 0,
    };
    (width, H * rows as u32 + header)
}

fn draw_figure<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    panels: &[Panel],
    columns: usize,
    legend: Legend,
) -> DrawResult<(), DB> {
    register_fonts();
    root.fill(&WHITE)?;
    let columns = columns.max(1);
    let rows = panels.len().div_ceil(columns).max(1);
    let (width, _) = root.dim_in_pixel();
    let header = match legend {
        Legend::Once => legend_height(panels, width),
        Legend::PerPanel => 0,
    };
    let (top, body) = root.split_vertically(header);
    let mut entries: Vec<(&str, Key)> = Vec::new();
    for (area, panel) in body.split_evenly((rows, columns)).iter().zip(panels) {
        let x = fit(panel_xs(panel), panel.x_scale);
        let y = fit(panel_ys(panel), panel.y_scale);
        let drawn = match (panel.x_scale, panel.y_scale) {
            (Scale::Linear, Scale::Linear) => draw_panel(area, panel, x, y, legend),
            (Scale::Linear, Scale::Log) => draw_panel(area, panel, x, y.log_scale(), legend),
            (Scale::Log, Scale::Linear) => draw_panel(area, panel, x.log_scale(), y, legend),
            (Scale::Log, Scale::Log) => {
                draw_panel(area, panel, x.log_scale(), y.log_scale(), legend)
            }
        }?;
        for (label, key) in drawn {
            if !label.is_empty() && entries.iter().all(|(l, _)| *l != label) {
                entries.push((label, key));
            }
        }
    }
    if legend == Legend::Once {
        figure_legend(&top, &entries)?;
    }
    root.present()
}

/// Registers DejaVu Sans as plotters' `sans-serif` (once per process).
pub(crate) fn register_fonts() {
    static FONTS: Once = Once::new();
    FONTS.call_once(|| {
        for (style, bytes) in [
            (FontStyle::Normal, dejavu::sans::regular()),
            (FontStyle::Bold, dejavu::sans::bold()),
        ] {
            assert!(
                register_font(FONT, style, bytes).is_ok(),
                "the bundled DejaVu Sans does not parse"
            );
        }
    });
}

fn panel_xs(p: &Panel) -> impl Iterator<Item = f64> + '_ {
    let series = p.series.iter().flat_map(|s| &s.x);
    let bands = p.bands.iter().flat_map(|b| &b.x);
    series
        .chain(bands)
        .copied()
        .chain(p.vlines.iter().map(|v| v.0))
}

fn panel_ys(p: &Panel) -> impl Iterator<Item = f64> + '_ {
    let series = p.series.iter().flat_map(|s| &s.y);
    let bands = p.bands.iter().flat_map(|b| b.lower.iter().chain(&b.upper));
    series
        .chain(bands)
        .copied()
        .chain(p.hlines.iter().map(|h| h.0))
}

/// Whether `v` can be shown on an axis of `scale`.
fn valid(v: f64, scale: Scale) -> bool {
    v.is_finite() && (scale == Scale::Linear || v > 0.0)
}

/// The axis range that shows `values`: whole decades on a log axis, 5 % margins on a linear
/// one, and a made-up width when all values are equal (or none can be shown).
fn fit(values: impl Iterator<Item = f64>, scale: Scale) -> Range<f64> {
    let (mut lo, mut hi) = values
        .filter(|v| valid(*v, scale))
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
            (lo.min(v), hi.max(v))
        });
    if !lo.is_finite() {
        (lo, hi) = (1.0, 10.0);
    }
    match scale {
        Scale::Log => {
            if hi <= lo * 1.000001 {
                (lo, hi) = (lo / 2.0, hi * 2.0);
            }
            10f64.powf(lo.log10().floor())..10f64.powf(hi.log10().ceil())
        }
        Scale::Linear => {
            if hi - lo <= 1e-12 * hi.abs().max(1e-300) {
                let d = if lo == 0.0 { 1.0 } else { 0.1 * lo.abs() };
                (lo, hi) = (lo - d, hi + d);
            }
            let pad = 0.05 * (hi - lo);
            lo - pad..hi + pad
        }
    }
}

/// A tick label: decades only on a log axis (`1e3`; the grid lines between stay unlabelled),
/// short decimals on a linear one.
fn fmt_tick(v: f64, scale: Scale) -> String {
    let a = v.abs();
    match scale {
        Scale::Log => {
            let k = v.log10().round();
            if (v / 10f64.powf(k) - 1.0).abs() < 1e-9 {
                format!("1e{k}")
            } else {
                String::new()
            }
        }
        Scale::Linear if a < 1e-12 => "0".into(),
        Scale::Linear if !(1e-3..1e5).contains(&a) => format!("{v:.1e}"),
        Scale::Linear => {
            let s = format!("{v:.4}");
            s.trim_end_matches('0').trim_end_matches('.').to_string()
        }
    }
}

/// `#rrggbb` as a colour (black if it is not of that form).
fn rgb(hex: &str) -> RGBColor {
    let digits = hex.strip_prefix('#').filter(|h| h.len() == 6);
    let byte = |i: usize| u8::from_str_radix(digits?.get(i..i + 2)?, 16).ok();
    match (byte(0), byte(2), byte(4)) {
        (Some(r), Some(g), Some(b)) => RGBColor(r, g, b),
        _ => BLACK,
    }
}

type DrawResult<T, DB> = Result<T, DrawingAreaErrorKind<<DB as DrawingBackend>::ErrorType>>;
type Chart<'a, DB, X, Y> = ChartContext<'a, DB, Cartesian2d<X, Y>>;

/// One panel; its legend beside it, or (for [`Legend::Once`]) its entries returned.
fn draw_panel<'p, DB, X, Y>(
    area: &DrawingArea<DB, Shift>,
    p: &'p Panel,
    x: X,
    y: Y,
    legend: Legend,
) -> DrawResult<Vec<(&'p str, Key)>, DB>
where
    DB: DrawingBackend,
    X: AsRangedCoord<Value = f64>,
    Y: AsRangedCoord<Value = f64>,
    X::CoordDescType: ValueFormatter<f64>,
    Y::CoordDescType: ValueFormatter<f64>,
{
    let mut chart = ChartBuilder::on(area)
        .caption(&p.title, (FONT, TITLE, FontStyle::Bold))
        .margin(6)
        .margin_right(match legend {
            Legend::PerPanel => RIGHT,
            Legend::Once => RIGHT_NARROW,
        })
        .x_label_area_size(BOTTOM)
        .y_label_area_size(LEFT)
        .build_cartesian_2d(x, y)?;
    let (xs, ys) = (p.x_scale, p.y_scale);
    // Unlabelled grid lines at 2, 3, … 9 in each decade of a short log axis; none on a linear one.
    let minor = |scale| if scale == Scale::Log { 10 } else { 0 };
    chart
        .configure_mesh()
        .x_desc(&p.x_label)
        .y_desc(&p.y_label)
        .x_labels(7)
        .y_labels(8)
        .x_label_formatter(&|v| fmt_tick(*v, xs))
        .y_label_formatter(&|v| fmt_tick(*v, ys))
        .x_max_light_lines(minor(xs))
        .y_max_light_lines(minor(ys))
        .label_style((FONT, SMALL))
        .axis_desc_style((FONT, NORMAL))
        .bold_line_style(GRID)
        .light_line_style(MINOR_GRID)
        .draw()?;
    draw_reference_lines(&mut chart, p)?;
    let entries = draw_data(&mut chart, p)?;
    if legend == Legend::PerPanel {
        draw_legend(area, chart.plotting_area().get_pixel_range(), &entries)?;
    }
    Ok(entries)
}

/// The panel's vertical and horizontal lines, dashed and labelled.
fn draw_reference_lines<DB, X, Y>(chart: &mut Chart<DB, X, Y>, p: &Panel) -> DrawResult<(), DB>
where
    DB: DrawingBackend,
    X: Ranged<ValueType = f64>,
    Y: Ranged<ValueType = f64>,
{
    let (x_range, y_range) = (chart.x_range(), chart.y_range());
    let text = TextStyle::from((FONT, SMALL).into_font());
    for (v, label) in p.vlines.iter().filter(|(v, _)| valid(*v, p.x_scale)) {
        let line = [(*v, y_range.start), (*v, y_range.end)];
        chart.draw_series(DashedLineSeries::new(line, 5, 4, BLACK.into()))?;
        let at = EmptyElement::at((*v, y_range.end));
        chart.draw_series([at + Text::new(label.clone(), (3, 3), text.clone())])?;
    }
    for (v, label) in p.hlines.iter().filter(|(v, _)| valid(*v, p.y_scale)) {
        let line = [(x_range.start, *v), (x_range.end, *v)];
        chart.draw_series(DashedLineSeries::new(line, 2, 3, HLINE.into()))?;
        // At the right end, above the line: clear of the y axis and its tick labels.
        let right = text.pos(Pos::new(HPos::Right, VPos::Bottom));
        let at = EmptyElement::at((x_range.end, *v));
        chart.draw_series([at + Text::new(label.clone(), (-4, -3), right)])?;
    }
    Ok(())
}

/// The panel's bands, then its series over them, skipping points the axes cannot show;
/// returns the legend's entries.
fn draw_data<'p, DB, X, Y>(
    chart: &mut Chart<DB, X, Y>,
    p: &'p Panel,
) -> DrawResult<Vec<(&'p str, Key)>, DB>
where
    DB: DrawingBackend,
    X: Ranged<ValueType = f64>,
    Y: Ranged<ValueType = f64>,
{
    let (xs, ys) = (p.x_scale, p.y_scale);
    let mut legend = Vec::new();
    for (k, b) in p.bands.iter().enumerate() {
        let points: Vec<_> = (b.x.iter().zip(&b.lower).zip(&b.upper))
            .map(|((&x, &lo), &hi)| (x, lo, hi))
            .filter(|&(x, lo, hi)| valid(x, xs) && valid(lo, ys) && valid(hi, ys))
            .collect();
        if points.len() < 2 {
            continue;
        }
        let upper = points.iter().map(|&(x, _, hi)| (x, hi));
        let lower = points.iter().rev().map(|&(x, lo, _)| (x, lo));
        let fill = PALETTE[k % PALETTE.len()].mix(0.3).filled();
        chart.draw_series([Polygon::new(upper.chain(lower).collect::<Vec<_>>(), fill)])?;
        legend.push((b.label.as_str(), Key::Swatch(fill)));
    }
    for (k, s) in p.series.iter().enumerate() {
        let color = s.color.map_or(PALETTE[k % PALETTE.len()], rgb);
        let style = color.stroke_width(s.width.round().max(1.0) as u32);
        // Past the palette's colours, lines are told apart by a dash.
        let dashed = k >= PALETTE.len();
        let points: Vec<_> = (s.x.iter().zip(&s.y))
            .map(|(&x, &y)| (x, y))
            .filter(|&(x, y)| valid(x, xs) && valid(y, ys))
            .collect();
        if s.line && dashed {
            chart.draw_series(DashedLineSeries::new(points.clone(), 6, 3, style))?;
        } else if s.line {
            chart.draw_series(LineSeries::new(points.clone(), style))?;
        }
        if s.markers {
            let radius = if s.line { 2.4 } else { 4.0 };
            let filled = color.filled();
            chart.draw_series(points.iter().map(|&p| Circle::new(p, radius, filled)))?;
        }
        let key = if s.line {
            Key::Line(style, dashed)
        } else {
            Key::Dot(color)
        };
        legend.push((s.label.as_str(), key));
    }
    Ok(legend)
}

/// plotters-svg writes each text as `<text …>`, the text, `</text>` on three lines; this puts
/// them on one (`<text …>label</text>`), as the hand-written SVG had it.
pub(crate) fn inline_text(svg: &str) -> String {
    let mut out = String::with_capacity(svg.len());
    let mut in_text = false;
    for line in svg.lines() {
        out.push_str(line);
        in_text = (in_text || line.starts_with("<text")) && line != "</text>";
        if !in_text {
            out.push('\n');
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn log_axes_span_whole_decades_and_label_only_them() {
        assert_eq!(fit([3.0, 4.0e4, -1.0].into_iter(), Scale::Log), 1.0..1e5);
        assert_eq!(fmt_tick(1e-3, Scale::Log), "1e-3");
        assert_eq!(fmt_tick(300.0, Scale::Log), "");
    }

    #[test]
    fn linear_axes_pad_the_data_and_label_it_briefly() {
        let r = fit([0.2, 1.2, f64::NAN].into_iter(), Scale::Linear);
        assert!((r.start - 0.15).abs() < 1e-12 && (r.end - 1.25).abs() < 1e-12);
        assert_eq!(fmt_tick(0.25, Scale::Linear), "0.25");
        assert_eq!(fmt_tick(2.0e-5, Scale::Linear), "2.0e-5");
        assert_eq!(rgb("#c0392b"), RGBColor(0xc0, 0x39, 0x2b));
    }

    #[test]
    fn svg_skips_points_a_log_axis_cannot_show() {
        let mut p = Panel::new("t", "x", "y", Scale::Log, Scale::Log);
        let (x, y) = (vec![1.0, 10.0, 100.0], vec![1.0, -1.0, f64::NAN]);
        p.series.push(Series::line("s", x, y));
        let svg = figure_svg(&[p], 1);
        assert_eq!(svg.matches("<circle").count(), 1);
        assert!(svg.starts_with("<svg") && svg.ends_with("</svg>\n"));
        assert!(svg.contains(">s</text>"), "the legend's label on one line");
    }

    #[test]
    fn png_is_written() {
        let mut p = Panel::new("t", "x", "θ", Scale::Linear, Scale::Linear);
        p.series
            .push(Series::points("s", vec![1.0, 2.0], vec![3.0, 4.0]));
        let path = std::env::temp_dir().join(format!("plot-test-{}.png", std::process::id()));
        figure_png(&[p.clone(), p], 2, Legend::Once, &path).unwrap();
        let png = std::fs::read(&path).unwrap();
        std::fs::remove_file(&path).unwrap();
        assert!(png.starts_with(b"\x89PNG"));
    }
}
