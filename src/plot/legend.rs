//! Legends: beside a panel ([`draw_legend`]), or once above a figure of many panels
//! ([`figure_legend`]), its entries laid out in rows that fit the figure's width.

use std::ops::Range;

use plotters::coord::Shift;
use plotters::element::DashedPathElement;
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};

use super::{FONT, Panel, SMALL};

/// Height of one row of the figure's legend, and its margins (pixels).
const ROW: u32 = 22;
const PAD: u32 = 10;
/// Width of an entry: its key, and per character of its label (DejaVu Sans at the
/// small size averages under 7 px), and the gap after it.
const KEY_W: u32 = 22;
const CHAR_W: u32 = 7;
const GAP: u32 = 22;

/// The legend, right of the plot (`plot`, in pixels of the figure): there, rather than by
/// `configure_series_labels`, which clamps what it draws into the plot.
pub(super) fn draw_legend<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    plot: (Range<i32>, Range<i32>),
    legend: &[(&str, Key)],
) -> DrawResult<(), DB> {
    let (base_x, base_y) = area.get_base_pixel();
    let (x, top) = (plot.0.end - base_x + 10, plot.1.start - base_y + 8);
    let text = TextStyle::from((FONT, SMALL).into_font()).pos(Pos::new(HPos::Left, VPos::Center));
    let labelled = legend.iter().filter(|(label, _)| !label.is_empty());
    for (i, (label, key)) in labelled.enumerate() {
        let y = top + 17 * i as i32;
        draw_entry(area, (x, y), label, *key, &text)?;
    }
    Ok(())
}

/// What a legend entry shows left of its label.
#[derive(Clone, Copy)]
pub(super) enum Key {
    /// A line's style, and whether it is dashed.
    Line(ShapeStyle, bool),
    /// A marker's colour.
    Dot(RGBColor),
    /// A band's fill.
    Swatch(ShapeStyle),
}

/// One entry: its key at (`x`, `y`), its label after it.
fn draw_entry<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    (x, y): (i32, i32),
    label: &str,
    key: Key,
    text: &TextStyle,
) -> Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
    let line = [(x, y), (x + 18, y)];
    match key {
        Key::Line(style, false) => area.draw(&PathElement::new(line, style)),
        Key::Line(style, true) => area.draw(&DashedPathElement::new(line, 6, 3, style)),
        Key::Dot(color) => area.draw(&Circle::new((x + 9, y), 4, color.filled())),
        Key::Swatch(fill) => area.draw(&Rectangle::new([(x, y - 5), (x + 18, y + 5)], fill)),
    }?;
    area.draw(&Text::new(label, (x + KEY_W as i32, y), text))
}

/// Every label the panels show in a legend, each once, in the order they come.
fn labels(panels: &[Panel]) -> Vec<&str> {
    let mut out: Vec<&str> = Vec::new();
    let all = panels.iter().flat_map(|p| {
        let bands = p.bands.iter().map(|b| b.label.as_str());
        bands.chain(p.series.iter().map(|s| s.label.as_str()))
    });
    for l in all.filter(|l| !l.is_empty()) {
        if !out.contains(&l) {
            out.push(l);
        }
    }
    out
}

/// Where each entry of `labels` goes in a figure `width` wide: (x, row).
fn layout(labels: &[&str], width: u32) -> Vec<(u32, u32)> {
    let mut at = Vec::with_capacity(labels.len());
    let (mut x, mut row) = (PAD, 0);
    for l in labels {
        let w = KEY_W + CHAR_W * l.chars().count() as u32;
        if x > PAD && x + w > width.saturating_sub(PAD) {
            (x, row) = (PAD, row + 1);
        }
        at.push((x, row));
        x += w + GAP;
    }
    at
}

/// The height of the legend above a figure of `panels`, `width` wide (0: no entry).
pub(super) fn legend_height(panels: &[Panel], width: u32) -> u32 {
    let labels = labels(panels);
    match layout(&labels, width).last() {
        Some((_, row)) => (row + 1) * ROW + 2 * PAD,
        None => 0,
    }
}

/// The legend above the figure, in `area` (sized by [`legend_height`]).
pub(super) fn figure_legend<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    entries: &[(&str, Key)],
) -> Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
    let (width, _) = area.dim_in_pixel();
    let labels: Vec<&str> = entries.iter().map(|(l, _)| *l).collect();
    let text = TextStyle::from((FONT, SMALL).into_font()).pos(Pos::new(HPos::Left, VPos::Center));
    for ((label, key), (x, row)) in entries.iter().zip(layout(&labels, width)) {
        let y = PAD + row * ROW + ROW / 2;
        draw_entry(area, (x as i32, y as i32), label, *key, &text)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn entries_wrap_to_the_figures_width() {
        let labels = ["filtered", "95 % band of the filtered level", "alarm"];
        let one = layout(&labels, 1860);
        assert!(one.iter().all(|(_, r)| *r == 0), "{one:?}");
        let narrow = layout(&labels, 300);
        assert_eq!(
            narrow.iter().map(|(_, r)| *r).collect::<Vec<_>>(),
            vec![0, 1, 2]
        );
        for ((x, _), l) in narrow.iter().zip(labels) {
            assert!(x + KEY_W + CHAR_W * l.chars().count() as u32 <= 300 - PAD || *x == PAD);
        }
    }
}
