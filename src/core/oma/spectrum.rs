//! The record's spectrum as frequency-domain decomposition sees it (FDD; Brincker, Zhang &
//! Andersen, "Modal identification of output-only systems using frequency domain
//! decomposition", Smart Mater. Struct. 10, 2001): the first singular value of the output
//! cross-spectral matrix at every frequency line, and its prominent peaks.
//!
//! The cross spectra `G_ij(f)` between the reference channels are Welch averages (Hann
//! window, half overlap, each segment's mean removed) of the channels scaled to unit
//! variance, so units and gains do not decide. The first singular value of the `r0 × r0`
//! matrix `G(f)` peaks at every mode a reference sees; two modes close in
//! frequency show as one peak of the first and one of the second singular value, so peaks
//! of the first are a lower bound on the modes of a band. It serves twice: it tells where
//! the record's modes lie before any setting is chosen ([`super::settings`]), and it checks
//! the identified modes afterwards (a prominent peak that no mode explains is reported).

use faer::{Mat, MatRef, Side, c64};
use realfft::RealFftPlanner;

/// Prominence (dB) a peak of the first singular value needs to be listed. A Welch estimate
/// from `K` segments scatters by about `10·log10(1 + 1/√K)` dB around its mean: below 1 dB
/// for the 30 and more segments [`welch_segment`] gives; 6 dB (a four-fold power ratio
/// against the valleys on both sides) leaves out the scatter and the side-lobes of the
/// Hann window and keeps every mode of the measured frames in `tests/data`, whose weakest
/// stands 7.5 dB above its valleys.
pub const PEAK_PROMINENCE_DB: f64 = 6.0;

/// The first singular value of the cross-spectral matrix over frequency.
#[derive(Debug, Clone)]
pub struct Spectrum {
    /// Frequency lines, Hz.
    pub frequency_hz: Vec<f64>,
    /// First singular value at each line, dB (relative: the channels are unit-variance).
    pub sv1_db: Vec<f64>,
}

/// Damping above which a peak is not taken for a mode's: its half-power width (−3 dB) is
/// more than `2 ζ f` plus two lines of the spectrum. 5 % is beyond the damping of bolted
/// steel and concrete frames; a wider hump is the excitation's or the instrument's (the
/// measured frame in `tests/data` shows two, 20 Hz wide, at 61 and 95 Hz).
pub const MAX_PEAK_DAMPING: f64 = 0.05;

/// A peak of [`Spectrum::sv1_db`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Peak {
    pub frequency_hz: f64,
    /// Height above the higher of the valleys on its two sides, dB.
    pub prominence_db: f64,
    /// Width where the peak is 3 dB below its top, Hz.
    pub width_hz: f64,
}

/// Welch segment length for a record of `n` samples: the largest power of two that leaves
/// at least 30 half-overlapping segments (about 16 when the record is short), at least 64.
pub fn welch_segment(n: usize) -> usize {
    let mut len = 64usize;
    while len * 2 <= n / 16 {
        len *= 2;
    }
    len
}

/// The spectrum of the reference columns `refs` of `y` (samples × channels) at `rate_hz`:
/// the first singular value of their `r0 × r0` cross-spectral matrix. The references are
/// the channels whose responses are the most independent ([`super::ssi::choose_references`]),
/// so every mode the identification can see shows here, at `r0²` rather than `r²` the cost.
pub fn spectrum(y: MatRef<'_, f64>, refs: &[usize], rate_hz: f64) -> Spectrum {
    use rayon::prelude::*;
    let n = y.nrows();
    let r0 = refs.len();
    let seg = welch_segment(n).min(n.max(2));
    let lines = seg / 2 + 1;
    let window: Vec<f64> = (0..seg)
        .map(|k| 0.5 - 0.5 * (2.0 * std::f64::consts::PI * k as f64 / seg as f64).cos())
        .collect();
    let starts: Vec<usize> = (0..)
        .map(|k| k * (seg / 2))
        .take_while(|s| s + seg <= n)
        .collect();
    // Per reference channel, the spectra of every segment (segments × lines).
    let spectra: Vec<Vec<Vec<c64>>> = refs
        .par_iter()
        .map(|&j| segment_spectra(y.col(j).iter().copied().collect(), &starts, &window))
        .collect();
    let sv1_db = (0..lines)
        .into_par_iter()
        .map(|l| {
            let g = Mat::from_fn(r0, r0, |a, b| {
                (0..starts.len())
                    .map(|k| spectra[a][k][l] * spectra[b][k][l].conj())
                    .fold(c64::new(0.0, 0.0), |acc, x| acc + x)
            });
            10.0 * largest_eigenvalue(&g).max(1e-300).log10()
        })
        .collect();
    Spectrum {
        frequency_hz: (0..lines)
            .map(|l| l as f64 * rate_hz / seg as f64)
            .collect(),
        sv1_db,
    }
}

/// The windowed spectra of one channel's segments (each segment's mean removed; the
/// channel scaled to unit variance).
fn segment_spectra(x: Vec<f64>, starts: &[usize], window: &[f64]) -> Vec<Vec<c64>> {
    let seg = window.len();
    let scale = 1.0 / column_std(&x);
    let fft = RealFftPlanner::<f64>::new().plan_fft_forward(seg);
    let mut buf = fft.make_input_vec();
    let mut out = fft.make_output_vec();
    starts
        .iter()
        .map(|&s| {
            let part = &x[s..s + seg];
            let mean = part.iter().sum::<f64>() / seg as f64;
            for ((b, v), w) in buf.iter_mut().zip(part).zip(window) {
                *b = (v - mean) * scale * w;
            }
            fft.process(&mut buf, &mut out)
                .expect("buffers sized by the plan");
            out.iter().map(|z| c64::new(z.re, z.im)).collect()
        })
        .collect()
}

fn column_std(x: &[f64]) -> f64 {
    let n = x.len() as f64;
    let mean = x.iter().sum::<f64>() / n;
    let var = x.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n;
    var.sqrt().max(f64::MIN_POSITIVE)
}

/// The largest eigenvalue of the Hermitian matrix `g` (its largest singular value: `g` is
/// a cross-spectral matrix, positive semi-definite).
fn largest_eigenvalue(g: &Mat<c64>) -> f64 {
    g.self_adjoint_eigenvalues(Side::Lower)
        .ok()
        .and_then(|v| v.last().copied())
        .unwrap_or(0.0)
        .max(0.0)
}

impl Spectrum {
    /// Peaks of at least `min_prominence_db` inside `band` (Hz) and no wider than a mode's
    /// ([`MAX_PEAK_DAMPING`]), ascending in frequency. The zero-frequency line and the top
    /// line are not peaks.
    pub fn peaks(&self, band: (f64, f64), min_prominence_db: f64) -> Vec<Peak> {
        let mut finder = find_peaks::PeakFinder::new(&self.sv1_db);
        finder.with_min_prominence(min_prominence_db);
        let mut peaks: Vec<Peak> = finder
            .find_peaks()
            .into_iter()
            .filter_map(|p| {
                let i = p.middle_position();
                let f = self.frequency_hz[i];
                let width_hz = self.half_power_width(i);
                let modal = width_hz <= 2.0 * MAX_PEAK_DAMPING * f + 4.0 * self.resolution_hz();
                (i > 0 && i + 1 < self.frequency_hz.len() && f >= band.0 && f <= band.1 && modal)
                    .then(|| Peak {
                        frequency_hz: f,
                        prominence_db: p.prominence.unwrap_or(0.0),
                        width_hz,
                    })
            })
            .collect();
        peaks.sort_by(|a, b| a.frequency_hz.total_cmp(&b.frequency_hz));
        peaks
    }

    /// Width of the peak at line `i` where it is 3 dB below its top, Hz.
    fn half_power_width(&self, i: usize) -> f64 {
        let floor = self.sv1_db[i] - 3.0;
        let n = self.sv1_db.len();
        let lo = (0..i).rev().find(|&k| self.sv1_db[k] < floor).unwrap_or(0);
        let hi = (i + 1..n)
            .find(|&k| self.sv1_db[k] < floor)
            .unwrap_or(n - 1);
        self.frequency_hz[hi] - self.frequency_hz[lo]
    }

    /// Width of one frequency line, Hz.
    pub fn resolution_hz(&self) -> f64 {
        self.frequency_hz.get(1).copied().unwrap_or(f64::INFINITY)
    }
}
