//! Settings of an identification derived from the record itself: where its modes lie, how
//! far it can be decimated, how many lags and model orders the stabilization diagram needs.
//! Every rule is stated here; each setting can be fixed by the caller instead.
//!
//! 1. **Where the modes lie.** The peaks of the first singular value of the cross-spectral
//!    matrix ([`super::spectrum`]) inside the band of interest (the caller's, else 0 to 0.45
//!    of the sampling rate).
//! 2. **Sub-bands.** SSI sees a mode through the angle `2π f / f_s` of its discrete pole: a
//!    mode sampled more than [`MAX_SAMPLES_PER_PERIOD`] times a period has its poles crowd
//!    at `z = 1`, where a little noise moves them far in frequency and damping, and needs as
//!    many lags to be seen over a period. When the record's rate (after decimating for the
//!    band's top) oversamples the band's lowest peak that much, the band is split at the
//!    widest gap between its peaks (on a log scale) and each part is identified on its own.
//!    The sub-bands tile the band: nothing between them goes unsearched. Each reaches a
//!    quarter above its highest peak; the band above the highest peak is a last sub-band
//!    of its own, searched at the rate its top needs.
//! 3. **Decimation** ([`super::decimate`]): a sub-band whose top lies below 30 % of the
//!    sampling rate is identified on the record decimated so that the top sits below 60 %
//!    of the new Nyquist frequency.
//! 4. **Lags.** The `2s − 1` lags of the block Hankel matrix span [`LAG_PERIODS`] periods of
//!    the lowest frequency of interest `f_min` (the caller's lower band edge; else the
//!    model's lowest mode in the band; else the band's lowest peak): `s = ⌈LAG_PERIODS ·
//!    f_s / (2 f_min)⌉`. One period is the usual lower limit (Rainieri & Fabbrocino,
//!    "Operational Modal Analysis of Civil Engineering Structures", 2014, §4.4.3); more
//!    separate the close, lightly damped pairs that real frames have. With many channels
//!    the shapes separate them instead: `s · r` stays within [`MAX_HANKEL_ROWS`]. At
//!    least enough block rows for the largest order: `s · r0 ≥ n_max + r0`.
//! 5. **Orders**: up to `max(`[`MIN_ORDER_MAX`]`, 8 · peaks)`: each mode takes two orders,
//!    a peak may hide a close pair, and the noise and the excitation take as many again.
//! 6. **References**: the `min(r, 12)` channels whose responses are the most independent
//!    ([`super::ssi::choose_references`]).

use faer::MatRef;

use super::decimate;
use super::spectrum::{PEAK_PROMINENCE_DB, Peak, Spectrum, spectrum};
use super::ssi::{AUTO_REFERENCES, choose_references};

/// Samples per period of a band's lowest peak above which the band is split (rule 2).
pub const MAX_SAMPLES_PER_PERIOD: f64 = 128.0;
/// Periods of the lowest frequency of interest the lags span (rule 4).
pub const LAG_PERIODS: f64 = 2.0;
/// Rows of the block Hankel matrix (`s · r`) the lags may take (rule 4): many channels
/// separate modes by their shapes, where few need the lags, and the SVD and the
/// uncertainty cost grow with `s³`. 42 channels get 48 block rows: at 1 kHz, 0.96 of a
/// period of a 10-Hz mode (the simulated lab frame's 11 modes are all found with 40).
pub const MAX_HANKEL_ROWS: usize = 2048;
/// Smallest largest model order (rule 5).
pub const MIN_ORDER_MAX: usize = 40;
/// Block rows when a band has nothing to derive them from (no peak, no lower edge).
pub const FALLBACK_BLOCK_ROWS: usize = 40;

/// What the caller fixes; `None` is derived from the record.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Requested {
    /// Band of interest, Hz.
    pub band_hz: Option<(f64, f64)>,
    /// Lowest mode of a model of the structure, Hz.
    pub model_lowest_hz: Option<f64>,
    pub block_rows: Option<usize>,
    pub order_max: Option<usize>,
    /// Decimation factor (1: none).
    pub decimate: Option<usize>,
    pub references: Option<Vec<usize>>,
}

/// How one sub-band is identified.
#[derive(Debug, Clone, PartialEq)]
pub struct BandSettings {
    /// The modes of this sub-band, Hz.
    pub band_hz: (f64, f64),
    /// Decimation factor, and the rate after it.
    pub decimate: usize,
    pub rate_hz: f64,
    /// Lowest frequency of interest the lags are chosen for, and where it came from.
    pub lowest_hz: Option<f64>,
    pub lowest_from: &'static str,
    pub block_rows: usize,
    pub order_max: usize,
    /// Peaks of the spectrum in the sub-band.
    pub peaks: usize,
}

/// The settings of one record.
#[derive(Debug, Clone)]
pub struct Settings {
    pub references: Vec<usize>,
    pub bands: Vec<BandSettings>,
    /// The record's spectrum and its prominent peaks in the band of interest.
    pub spectrum: Spectrum,
    pub peaks: Vec<Peak>,
}

/// Derives the settings of the record `y` at `rate_hz` (module docs).
pub fn derive(y: MatRef<'_, f64>, rate_hz: f64, req: &Requested) -> Settings {
    let references = req
        .references
        .clone()
        .unwrap_or_else(|| choose_references(y, AUTO_REFERENCES));
    let spectrum = spectrum(y, &references, rate_hz);
    let band = req.band_hz.unwrap_or((0.0, 0.45 * rate_hz));
    let peaks = spectrum.peaks(band, PEAK_PROMINENCE_DB);
    let fixed = req.block_rows.is_some() || req.decimate.is_some();
    let (groups, edges) = if fixed {
        (vec![peaks.clone()], vec![band])
    } else {
        let mut groups = split(&peaks, rate_hz, band);
        let edges = edges(&mut groups, band);
        (groups, edges)
    };
    let bands = groups
        .iter()
        .zip(&edges)
        .enumerate()
        .map(|(k, (g, &range))| {
            band_settings(
                g,
                range,
                k == 0,
                rate_hz,
                req,
                (y.ncols(), references.len()),
            )
        })
        .collect();
    Settings {
        references,
        bands,
        spectrum,
        peaks,
    }
}

/// Splits the peaks into groups each of which its own rate does not oversample (rule 2).
fn split(peaks: &[Peak], rate_hz: f64, band: (f64, f64)) -> Vec<Vec<Peak>> {
    let mut done = Vec::new();
    let mut todo = vec![peaks.to_vec()];
    while let Some(g) = todo.pop() {
        let oversampled = match (g.first(), g.last()) {
            (Some(lo), Some(hi)) if g.len() >= 2 => {
                let top = band_top(hi.frequency_hz).min(band.1);
                let rate = rate_hz / decimate::factor(rate_hz, top) as f64;
                rate / lo.frequency_hz > MAX_SAMPLES_PER_PERIOD
            }
            _ => false,
        };
        if !oversampled {
            done.push(g);
            continue;
        }
        let cut = (1..g.len())
            .max_by(|&a, &b| {
                let gap = |i: usize| g[i].frequency_hz / g[i - 1].frequency_hz;
                gap(a).total_cmp(&gap(b))
            })
            .expect("two peaks or more");
        todo.push(g[cut..].to_vec());
        todo.push(g[..cut].to_vec());
    }
    done.sort_by(|a, b| {
        let f = |g: &Vec<Peak>| g.first().map_or(0.0, |p| p.frequency_hz);
        f(a).total_cmp(&f(b))
    });
    done
}

/// The top of a sub-band whose highest peak is at `f`: a quarter above it, so that a mode
/// the peak hides a little higher still belongs to it.
fn band_top(f: f64) -> f64 {
    1.25 * f
}

/// Edges of the sub-bands of `groups`, tiling `band`: each edge a quarter above the lower
/// group's highest peak, or halfway (geometrically) to the next group's lowest when that is
/// nearer. When the last group's edge lies below the band's top, a last sub-band without
/// peaks covers the rest (an empty group is added for it).
fn edges(groups: &mut Vec<Vec<Peak>>, band: (f64, f64)) -> Vec<(f64, f64)> {
    let mut out = Vec::with_capacity(groups.len() + 1);
    let mut lo = band.0;
    for (k, g) in groups.iter().enumerate() {
        let hi = match (g.last(), groups.get(k + 1).and_then(|n| n.first())) {
            (Some(a), Some(b)) => {
                band_top(a.frequency_hz).min((a.frequency_hz * b.frequency_hz).sqrt())
            }
            (Some(a), None) => band_top(a.frequency_hz),
            _ => band.1,
        }
        .min(band.1);
        out.push((lo, hi));
        lo = hi;
    }
    if lo < band.1 {
        groups.push(Vec::new());
        out.push((lo, band.1));
    }
    out
}

/// Settings of one sub-band (rules 3–5).
fn band_settings(
    peaks: &[Peak],
    range: (f64, f64),
    first: bool,
    rate_hz: f64,
    req: &Requested,
    (r, r0): (usize, usize),
) -> BandSettings {
    let decimate = req
        .decimate
        .unwrap_or_else(|| decimate::factor(rate_hz, range.1));
    let rate = rate_hz / decimate as f64;
    let in_band = |f: &f64| *f >= range.0 && *f <= range.1;
    let (lowest_hz, lowest_from) = match req.band_hz {
        Some((lo, _)) if first && lo > 0.0 => (Some(lo), "the band's lower edge"),
        _ => match req.model_lowest_hz.filter(in_band) {
            Some(f) => (Some(f), "the model's lowest mode"),
            None => match peaks.first() {
                Some(p) => (Some(p.frequency_hz), "the lowest peak of the spectrum"),
                None if range.0 > 0.0 => (Some(range.0), "the band's lower edge"),
                None => (None, "nothing (no peak in the band)"),
            },
        },
    };
    let order_max = req
        .order_max
        .unwrap_or_else(|| MIN_ORDER_MAX.max(8 * peaks.len()));
    let block_rows = req.block_rows.unwrap_or_else(|| {
        let lags = lowest_hz.map_or(FALLBACK_BLOCK_ROWS, |f| {
            let rows = (LAG_PERIODS * rate / (2.0 * f)).ceil() as usize;
            rows.min(MAX_HANKEL_ROWS / r.max(1))
        });
        lags.max((order_max + r0).div_ceil(r0.max(1))).max(2)
    });
    BandSettings {
        band_hz: range,
        decimate,
        rate_hz: rate,
        lowest_hz,
        lowest_from,
        block_rows,
        order_max,
        peaks: peaks.len(),
    }
}
