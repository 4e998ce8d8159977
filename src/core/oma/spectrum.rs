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
    let g = cross_spectra(y, refs, &starts, &window);
    // Lines in chunks, each line's power iteration started from its neighbour's vector.
    let all: Vec<usize> = (0..lines).collect();
    let sv1_db = all
        .par_chunks(256)
        .flat_map_iter(|chunk| {
            let mut v = vec![c64::new(1.0, 0.0); r0];
            chunk
                .iter()
                .map(|&l| {
                    let gl = &g[l * r0 * r0..][..r0 * r0];
                    let g = Mat::from_fn(r0, r0, |a, b| gl[a * r0 + b]);
                    10.0 * largest_eigenvalue(&g, &mut v).max(1e-300).log10()
                })
                .collect::<Vec<_>>()
        })
        .collect();
    Spectrum {
        frequency_hz: (0..lines)
            .map(|l| l as f64 * rate_hz / seg as f64)
            .collect(),
        sv1_db,
    }
}

/// The cross-spectral matrices `G(f) = Σ_k X_k(f) X_k(f)ᴴ` of the reference channels
/// over the segments starting at `starts` (each segment's mean removed, each channel
/// scaled to unit variance, then windowed), line by line: `r0 × r0` entries per line,
/// row-major. The segments are shared among the threads, each summing its own matrices.
fn cross_spectra(y: MatRef<'_, f64>, refs: &[usize], starts: &[usize], window: &[f64]) -> Vec<c64> {
    use rayon::prelude::*;
    let (seg, r0) = (window.len(), refs.len());
    let lines = seg / 2 + 1;
    let scale: Vec<f64> = refs
        .iter()
        .map(|&j| 1.0 / column_std(&y.col(j).iter().copied().collect::<Vec<_>>()))
        .collect();
    let per_thread = starts
        .len()
        .div_ceil(rayon::current_num_threads().max(1))
        .max(1);
    starts
        .par_chunks(per_thread)
        .map(|chunk| {
            let fft = RealFftPlanner::<f64>::new().plan_fft_forward(seg);
            let mut buf = fft.make_input_vec();
            let mut spectra = vec![fft.make_output_vec(); r0];
            let mut g = vec![c64::new(0.0, 0.0); lines * r0 * r0];
            for &s in chunk {
                for (a, &j) in refs.iter().enumerate() {
                    let part = y.col(j).subrows(s, seg);
                    let mean = part.iter().sum::<f64>() / seg as f64;
                    for ((b, v), w) in buf.iter_mut().zip(part.iter()).zip(window) {
                        *b = (v - mean) * scale[a] * w;
                    }
                    fft.process(&mut buf, &mut spectra[a])
                        .expect("buffers sized by the plan");
                }
                for (l, gl) in g.chunks_exact_mut(r0 * r0).enumerate() {
                    for a in 0..r0 {
                        let za = spectra[a][l];
                        for b in 0..r0 {
                            let zb = spectra[b][l];
                            gl[a * r0 + b] += c64::new(za.re, za.im) * c64::new(zb.re, -zb.im);
                        }
                    }
                }
            }
            g
        })
        .reduce_with(|mut a, b| {
            a.iter_mut().zip(b).for_each(|(x, y)| *x += y);
            a
        })
        .unwrap_or_else(|| vec![c64::new(0.0, 0.0); lines * r0 * r0])
}

fn column_std(x: &[f64]) -> f64 {
    let n = x.len() as f64;
    let mean = x.iter().sum::<f64>() / n;
    let var = x.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n;
    var.sqrt().max(f64::MIN_POSITIVE)
}

/// Power iterations before [`largest_eigenvalue`] falls back to the full decomposition.
const POWER_ITERATIONS: usize = 200;

/// The largest eigenvalue of the Hermitian matrix `g` (its largest singular value: `g` is
/// a cross-spectral matrix, positive semi-definite), by power iteration from `v`, which is
/// left at its eigenvector. The Rayleigh quotient of a positive semi-definite matrix rises
/// with every iteration; it stops when a step adds less than 1e-10 of it (its error is then
/// that step over `1 − (λ₂/λ₁)²`, far below the 0.01 dB a peak is read to), else after
/// [`POWER_ITERATIONS`] with every eigenvalue computed.
fn largest_eigenvalue(g: &Mat<c64>, v: &mut [c64]) -> f64 {
    let n = v.len();
    let normalise = |v: &mut [c64]| {
        let norm = v.iter().map(|z| z.norm_sqr()).sum::<f64>().sqrt();
        if norm > 0.0 && norm.is_finite() {
            v.iter_mut().for_each(|z| *z /= norm);
            true
        } else {
            false
        }
    };
    if !normalise(v) {
        v.iter_mut().for_each(|z| *z = c64::new(1.0, 0.0));
        normalise(v);
    }
    let mut rho = 0.0;
    for _ in 0..POWER_ITERATIONS {
        let gv: Vec<c64> = (0..n)
            .map(|a| (0..n).fold(c64::new(0.0, 0.0), |acc, b| acc + g[(a, b)] * v[b]))
            .collect();
        let next = v
            .iter()
            .zip(&gv)
            .fold(0.0, |acc, (x, y)| acc + (x.conj() * y).re);
        v.copy_from_slice(&gv);
        if !normalise(v) {
            return 0.0;
        }
        if next - rho <= 1e-10 * next.abs() {
            return next.max(0.0);
        }
        rho = next;
    }
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

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    /// The power iteration against the full decomposition, on cross-spectral matrices
    /// `X Xᴴ` (12 × 12 from 35 segments) of random spectra, and on matrices whose two
    /// largest eigenvalues are 1 and 0.999 (the slowest case: two modes at one line).
    /// 1e-6 relative, 4e-6 dB: far below the 0.01 dB a peak is read to.
    #[test]
    fn power_iteration_gives_the_largest_eigenvalue() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let mut z = || c64::new(rng.random::<f64>() - 0.5, rng.random::<f64>() - 0.5);
        for case in 0..20 {
            let x = Mat::from_fn(12, 35, |_, _| z());
            let mut g = &x * x.adjoint();
            if case % 2 == 1 {
                // Replace the spectrum by 1, 0.999, 0.5 … in the same eigenvectors.
                let eig = g.self_adjoint_eigen(Side::Lower).unwrap();
                let u = eig.U();
                let d = Mat::from_fn(12, 12, |i, j| {
                    let l = match 11 - i {
                        0 => 1.0,
                        1 => 0.999,
                        k => 0.5 / k as f64,
                    };
                    if i == j {
                        c64::new(l, 0.0)
                    } else {
                        c64::new(0.0, 0.0)
                    }
                });
                g = u * &d * u.adjoint();
            }
            let exact = g
                .self_adjoint_eigenvalues(Side::Lower)
                .unwrap()
                .last()
                .copied()
                .unwrap();
            let mut v = vec![c64::new(1.0, 0.0); 12];
            let power = largest_eigenvalue(&g, &mut v);
            assert!(
                (power / exact - 1.0).abs() < 1e-6,
                "case {case}: {power} against {exact}"
            );
        }
    }
}
