//! The record's spectrum as frequency-domain decomposition sees it (FDD; Brincker, Zhang &
//! Andersen, "Modal identification of output-only systems using frequency domain
//! decomposition", Smart Mater. Struct. 10, 2001): the first singular value of the output
//! cross-spectral matrix at every frequency line, and its prominent peaks.
//!
//! The cross spectra `G_ij(f)` between every channel `i` and the reference channels `j` are
//! Welch averages (Hann window, half overlap, each segment's mean removed) of the channels
//! scaled to unit variance, so units and gains do not decide. The first singular value of
//! the `r × r0` matrix `G(f)` peaks at every mode a reference sees; two modes close in
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

/// The spectrum of the columns of `y` (samples × channels) at `rate_hz`, against the
/// reference columns `refs`.
pub fn spectrum(y: MatRef<'_, f64>, refs: &[usize], rate_hz: f64) -> Spectrum {
    let (n, r) = (y.nrows(), y.ncols());
    let seg = welch_segment(n).min(n.max(2));
    let lines = seg / 2 + 1;
    let window: Vec<f64> = (0..seg)
        .map(|k| 0.5 - 0.5 * (2.0 * std::f64::consts::PI * k as f64 / seg as f64).cos())
        .collect();
    let scale: Vec<f64> = (0..r).map(|j| 1.0 / column_std(y, j)).collect();
    let fft = RealFftPlanner::<f64>::new().plan_fft_forward(seg);
    let mut g = vec![c64::new(0.0, 0.0); lines * r * refs.len()];
    let mut spectra = vec![vec![c64::new(0.0, 0.0); lines]; r];
    let mut buf = fft.make_input_vec();
    let mut start = 0;
    while start + seg <= n {
        for (j, out) in spectra.iter_mut().enumerate() {
            let seg_y = y.col(j).subrows(start, seg);
            let mean = seg_y.iter().sum::<f64>() / seg as f64;
            for (k, b) in buf.iter_mut().enumerate() {
                *b = (seg_y[k] - mean) * scale[j] * window[k];
            }
            let mut spec: Vec<realfft::num_complex::Complex<f64>> = fft.make_output_vec();
            fft.process(&mut buf, &mut spec)
                .expect("buffers sized by the plan");
            for (o, s) in out.iter_mut().zip(&spec) {
                *o = c64::new(s.re, s.im);
            }
        }
        for l in 0..lines {
            for (b, &jr) in refs.iter().enumerate() {
                let xr = spectra[jr][l].conj();
                for (i, si) in spectra.iter().enumerate() {
                    g[(l * refs.len() + b) * r + i] += si[l] * xr;
                }
            }
        }
        start += seg / 2;
    }
    let sv1_db = (0..lines)
        .map(|l| {
            let gl = &g[l * r * refs.len()..(l + 1) * r * refs.len()];
            10.0 * first_singular_value(gl, r, refs.len()).max(1e-300).log10()
        })
        .collect();
    Spectrum {
        frequency_hz: (0..lines)
            .map(|l| l as f64 * rate_hz / seg as f64)
            .collect(),
        sv1_db,
    }
}

fn column_std(y: MatRef<'_, f64>, j: usize) -> f64 {
    let n = y.nrows() as f64;
    let mean = y.col(j).iter().sum::<f64>() / n;
    let var = y.col(j).iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n;
    var.sqrt().max(f64::MIN_POSITIVE)
}

/// The largest singular value of the `r × r0` matrix `g` (column-major): the square root of
/// the largest eigenvalue of `gᴴg`.
fn first_singular_value(g: &[c64], r: usize, r0: usize) -> f64 {
    let m = Mat::from_fn(r, r0, |i, j| g[j * r + i]);
    let gram = m.adjoint() * &m;
    gram.self_adjoint_eigenvalues(Side::Lower)
        .ok()
        .and_then(|v| v.last().copied())
        .unwrap_or(0.0)
        .max(0.0)
        .sqrt()
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
