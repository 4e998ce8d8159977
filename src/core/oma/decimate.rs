//! Decimation of a record whose band of interest lies far below its Nyquist frequency.
//!
//! Each channel is low-pass filtered forward and backward (zero phase, so mode shapes keep
//! their phases across channels) by an order-8 Butterworth filter in second-order sections
//! (`sci-rs`, after SciPy's `butter` and `sosfiltfilt`) cut at 80 % of the new Nyquist
//! frequency, then every `q`-th sample is kept. Forward and backward, the filter attenuates
//! the new Nyquist frequency by 31 dB and everything beyond 1.5 times it by more than 56 dB,
//! so what folds back into the band is that much weaker than it was. The band of interest
//! is kept below 60 % of the new Nyquist ([`factor`]), where the filter's gain is above
//! 0.99: a mode's frequency and damping are those of the record.

use faer::Mat;
use sci_rs::signal::filter::design::{DigitalFilter, FilterBandType, FilterOutputType, butter_dyn};
use sci_rs::signal::filter::sosfiltfilt_dyn;

use super::Record;

/// Order of the anti-alias filter.
const FILTER_ORDER: usize = 8;
/// Cut-off of the filter, as a fraction of the new Nyquist frequency.
const CUTOFF: f64 = 0.8;
/// The band's top lies at most this fraction of the new Nyquist frequency.
pub const BAND_SHARE: f64 = 0.6;

/// The decimation factor that keeps `band_top_hz` below [`BAND_SHARE`] of the new Nyquist
/// frequency: `⌊BAND_SHARE · f_s / (2 f_top)⌋`, at least 1.
pub fn factor(rate_hz: f64, band_top_hz: f64) -> usize {
    let q = (BAND_SHARE * rate_hz / (2.0 * band_top_hz)).floor();
    if q.is_finite() && q >= 2.0 {
        q as usize
    } else {
        1
    }
}

/// `record` decimated by `q` (module docs); the record itself when `q` is 1.
pub fn decimate(record: &Record, q: usize) -> std::borrow::Cow<'_, Record> {
    use rayon::prelude::*;
    if q <= 1 {
        return std::borrow::Cow::Borrowed(record);
    }
    let cutoff = CUTOFF / q as f64;
    let DigitalFilter::Sos(sos) = butter_dyn(
        FILTER_ORDER,
        vec![cutoff],
        Some(FilterBandType::Lowpass),
        Some(false),
        Some(FilterOutputType::Sos),
        None,
    ) else {
        unreachable!("butter_dyn returns the output type asked for")
    };
    let n = record.len().div_ceil(q);
    let columns: Vec<Vec<f64>> = (0..record.channels.len())
        .into_par_iter()
        .map(|j| {
            sosfiltfilt_dyn(record.samples.col(j).iter().copied(), &sos.sos)
                .into_iter()
                .step_by(q)
                .collect()
        })
        .collect();
    let samples = Mat::from_fn(n, columns.len(), |k, j| columns[j][k]);
    std::borrow::Cow::Owned(Record {
        channels: record.channels.clone(),
        rate_hz: record.rate_hz / q as f64,
        samples,
        quantities: record.quantities.clone(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sine_record(rate: f64, n: usize, freqs: &[f64]) -> Record {
        let samples = Mat::from_fn(n, 1, |k, _| {
            freqs
                .iter()
                .map(|f| (2.0 * std::f64::consts::PI * f * k as f64 / rate).sin())
                .sum()
        });
        Record::accelerations(vec!["a".into()], rate, samples)
    }

    fn rms(v: impl Iterator<Item = f64>) -> f64 {
        let (s, n) = v.fold((0.0, 0usize), |(s, n), x| (s + x * x, n + 1));
        (s / n as f64).sqrt()
    }

    /// A sine inside the band comes through with its amplitude (gain above 0.99, module
    /// docs) and its phase; one above the new Nyquist frequency, which would fold into the
    /// band, is gone (below the 56 dB of the filter at 1.5 times the new Nyquist, checked
    /// at 0.3 % of its amplitude).
    #[test]
    fn decimation_keeps_the_band_and_stops_what_would_fold() {
        let (rate, n, q) = (256.0, 8192, 4);
        assert_eq!(factor(rate, 19.2), q);
        let record = sine_record(rate, n, &[10.0]);
        let inside = decimate(&record, q);
        assert_eq!(inside.rate_hz, 64.0);
        assert_eq!(inside.len(), n / q);
        // Away from the ends (the filter's edge transients), sample by sample.
        for k in 200..inside.len() - 200 {
            let t = (k * q) as f64 / rate;
            let want = (2.0 * std::f64::consts::PI * 10.0 * t).sin();
            assert!((inside.samples[(k, 0)] - want).abs() < 0.01, "k {k}");
        }
        // 50 Hz would fold to 14 Hz at 64 Hz.
        let record = sine_record(rate, n, &[50.0]);
        let outside = decimate(&record, q);
        let left = rms(outside.samples.col(0).iter().copied().skip(200).take(1600));
        assert!(left < 0.003 / 2f64.sqrt(), "rms {left}");
        assert_eq!(factor(rate, 100.0), 1);
    }
}
