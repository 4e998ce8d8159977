//! The stabilization diagram of `boltwatch identify --plot DIR`: for each sub-band, the
//! poles by model order over frequency (what the selection made of each: not physical,
//! unstable, stable, a mode's), the chosen modes with their ±2σ frequency band, and the
//! first singular value of the spectrum on a second axis. Written as `NAME.png`,
//! `NAME.svg` and the poles behind them as `NAME-poles.csv`.

use std::fmt::Write as _;
use std::path::Path;

use anyhow::{Context, Result};
use plotters::coord::Shift;
use plotters::prelude::*;

use crate::core::oma::identify::{BandResult, Identification};
use crate::core::oma::settings::BandSettings;
use crate::core::oma::stabilize::Verdict;

const WIDTH: u32 = 1100;
const BAND_HEIGHT: u32 = 520;
const FONT: &str = "sans-serif";
const UNSTABLE: RGBColor = RGBColor(0xb0, 0xb0, 0xb0);
const STABLE: RGBColor = RGBColor(0x1f, 0x77, 0xb4);
const MODE: RGBColor = RGBColor(0xd6, 0x27, 0x28);
const SPECTRUM: RGBColor = RGBColor(0x2c, 0x2c, 0x2c);
const NOISE: RGBColor = RGBColor(0xff, 0x7f, 0x0e);

/// Writes `NAME.png`, `NAME.svg` and `NAME-poles.csv` into `dir` (created if needed).
pub fn write(dir: &Path, name: &str, found: &Identification) -> Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    let size = (WIDTH, BAND_HEIGHT * found.bands.len().max(1) as u32);
    let png = dir.join(format!("{name}.png"));
    {
        let root = BitMapBackend::new(&png, size).into_drawing_area();
        draw(&root, found).with_context(|| format!("cannot write {}", png.display()))?;
    }
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, size).into_drawing_area();
        draw(&root, found).map_err(|e| anyhow::anyhow!("drawing the SVG: {e}"))?;
    }
    let svg_path = dir.join(format!("{name}.svg"));
    std::fs::write(&svg_path, crate::plot::inline_text(&svg))
        .with_context(|| format!("cannot write {}", svg_path.display()))?;
    let csv_path = dir.join(format!("{name}-poles.csv"));
    std::fs::write(&csv_path, poles_csv(found))
        .with_context(|| format!("cannot write {}", csv_path.display()))?;
    println!(
        "stabilization diagram: {}, {}, {}",
        png.display(),
        svg_path.display(),
        csv_path.display()
    );
    Ok(())
}

/// Every pole of every sub-band: `band,order,frequency_hz,damping,verdict,mode`; the
/// verdict is `not physical`, `unstable`, `stable`, `mode` or `noise` (a cluster the noise
/// rule left out), and `mode` the frequency of the cluster's representative.
fn poles_csv(found: &Identification) -> String {
    let mut out = String::from("band,order,frequency_hz,damping,verdict,mode\n");
    for (k, b) in found.bands.iter().enumerate() {
        for (p, v) in b.poles.poles.iter().zip(&b.selection.verdicts) {
            let (verdict, mode) = match v {
                Verdict::NotPhysical => ("not physical", String::new()),
                Verdict::Unstable => ("unstable", String::new()),
                Verdict::Stable => ("stable", String::new()),
                Verdict::Mode(m) => (
                    if b.noise[*m] { "noise" } else { "mode" },
                    format!("{:.5}", b.selection.modes[*m].pole.frequency_hz),
                ),
            };
            let _ = writeln!(
                out,
                "{},{},{:.6},{:.6},{verdict},{mode}",
                k + 1,
                p.order,
                p.frequency_hz,
                p.damping
            );
        }
    }
    out
}

fn draw<DB: DrawingBackend>(root: &DrawingArea<DB, Shift>, found: &Identification) -> Result<()>
where
    DB::ErrorType: 'static,
{
    crate::plot::register_fonts();
    root.fill(&WHITE).map_err(|e| anyhow::anyhow!("{e}"))?;
    let areas = root.split_evenly((found.bands.len().max(1), 1));
    for (k, ((area, band), settings)) in areas
        .iter()
        .zip(&found.bands)
        .zip(&found.settings.bands)
        .enumerate()
    {
        draw_band(area, k, band, settings, found).map_err(|e| anyhow::anyhow!("{e}"))?;
    }
    root.present().map_err(|e| anyhow::anyhow!("{e}"))?;
    Ok(())
}

fn draw_band<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    k: usize,
    band: &BandResult,
    s: &BandSettings,
    found: &Identification,
) -> Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
    let (lo, hi) = s.band_hz;
    let order_top = band.poles.orders.last().copied().unwrap_or(2) as f64 + 2.0;
    let spectrum: Vec<(f64, f64)> = found
        .settings
        .spectrum
        .frequency_hz
        .iter()
        .zip(&found.settings.spectrum.sv1_db)
        .filter(|(f, _)| **f >= lo && **f <= hi)
        .map(|(f, d)| (*f, *d))
        .collect();
    let (db_lo, db_hi) = spectrum
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |a, p| {
            (a.0.min(p.1), a.1.max(p.1))
        });
    let (db_lo, db_hi) = if db_lo.is_finite() {
        (db_lo - 3.0, db_hi + 3.0)
    } else {
        (-1.0, 1.0)
    };
    let decimated = if s.decimate > 1 {
        format!(" (decimated {}×)", s.decimate)
    } else {
        String::new()
    };
    let title = format!(
        "Sub-band {}: {:.2}–{:.2} Hz at {} Hz{decimated}, {} block rows",
        k + 1,
        lo,
        hi,
        s.rate_hz,
        s.block_rows
    );
    let mut chart = ChartBuilder::on(area)
        .caption(title, (FONT, 17))
        .margin(12)
        .x_label_area_size(44)
        .y_label_area_size(60)
        .right_y_label_area_size(60)
        .build_cartesian_2d(lo..hi, 0.0..order_top)?
        .set_secondary_coord(lo..hi, db_lo..db_hi);
    chart
        .configure_mesh()
        .x_desc("Frequency (Hz)")
        .y_desc("Model order")
        .label_style((FONT, 14))
        .light_line_style(RGBColor(0xf0, 0xf0, 0xf0))
        .draw()?;
    chart
        .configure_secondary_axes()
        .y_desc("First singular value of the spectrum (dB)")
        .label_style((FONT, 14))
        .draw()?;
    draw_modes(&mut chart, band, order_top)?;
    chart
        .draw_secondary_series(LineSeries::new(spectrum, SPECTRUM.stroke_width(1)))?
        .label("spectrum (first singular value)")
        .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 16, y)], SPECTRUM));
    draw_poles(&mut chart, band)?;
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::LowerRight)
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .label_font((FONT, 13))
        .draw()?;
    Ok(())
}

type Xy = plotters::coord::cartesian::Cartesian2d<
    plotters::coord::types::RangedCoordf64,
    plotters::coord::types::RangedCoordf64,
>;
type Dual<'a, DB> = plotters::chart::DualCoordChartContext<'a, DB, Xy, Xy>;

/// The chosen modes: a shaded ±2σ band and a line at each frequency; the clusters the
/// noise rule left out as dashed lines.
fn draw_modes<DB: DrawingBackend>(
    chart: &mut Dual<'_, DB>,
    band: &BandResult,
    top: f64,
) -> Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
    for (m, &noise) in band.selection.modes.iter().zip(&band.noise) {
        let f = m.pole.frequency_hz;
        if noise {
            chart.draw_series(std::iter::once(plotters::element::DashedPathElement::new(
                vec![(f, 0.0), (f, top)],
                4,
                4,
                NOISE.stroke_width(1),
            )))?;
            continue;
        }
        chart.draw_series(std::iter::once(PathElement::new(
            vec![(f, 0.0), (f, top)],
            MODE.mix(0.6).stroke_width(1),
        )))?;
    }
    Ok(())
}

/// The poles, by what the selection made of them.
fn draw_poles<DB: DrawingBackend>(
    chart: &mut Dual<'_, DB>,
    band: &BandResult,
) -> Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
    // A cluster the noise rule left out.
    let noise = |v: &Verdict| matches!(v, Verdict::Mode(k) if band.noise[*k]);
    let pick = |want: &dyn Fn(&Verdict) -> bool| -> Vec<(f64, f64)> {
        band.poles
            .poles
            .iter()
            .zip(&band.selection.verdicts)
            .filter(|(_, v)| want(v))
            .map(|(p, _)| (p.frequency_hz, p.order as f64))
            .collect()
    };
    let unstable = pick(&|v| matches!(v, Verdict::Unstable));
    let stable = pick(&|v| matches!(v, Verdict::Stable));
    let chosen = pick(&|v| matches!(v, Verdict::Mode(_)) && !noise(v));
    let dropped = pick(&|v| noise(v));
    chart
        .draw_series(
            unstable
                .into_iter()
                .map(|p| Cross::new(p, 3, UNSTABLE.stroke_width(1))),
        )?
        .label("unstable pole")
        .legend(|(x, y)| Cross::new((x + 8, y), 3, UNSTABLE.stroke_width(1)));
    chart
        .draw_series(
            stable
                .into_iter()
                .map(|p| Circle::new(p, 3, STABLE.stroke_width(1))),
        )?
        .label("stable pole, not a mode")
        .legend(|(x, y)| Circle::new((x + 8, y), 3, STABLE.stroke_width(1)));
    chart
        .draw_series(chosen.into_iter().map(|p| Circle::new(p, 3, MODE.filled())))?
        .label("pole of a chosen mode")
        .legend(|(x, y)| Circle::new((x + 8, y), 3, MODE.filled()));
    chart
        .draw_series(
            dropped
                .into_iter()
                .map(|p| Circle::new(p, 3, NOISE.filled())),
        )?
        .label("pole of a cluster left out as noise")
        .legend(|(x, y)| Circle::new((x + 8, y), 3, NOISE.filled()));
    Ok(())
}
