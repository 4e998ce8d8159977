//! The seasonal scenario's climate and thermal law (`boltwatch scenario seasonal`): two
//! years of a frame in the open, whose bolted connections follow the temperature of the
//! steel.
//!
//! **Temperature** of the structure at time t (days from the start), °C:
//! `T = mean − seasonal · cos(2π (doy − 20) / 365.25) − daily · cos(2π (h − 15) / 24) + w(t)`,
//! coldest on 20 January and at 03:00, warmest on 21 July and at 15:00, with weather `w` an
//! Ornstein–Uhlenbeck process (standard deviation `weather` °C, correlation time 3 days).
//! Defaults: mean 9 °C, seasonal 13 °C, daily 4 °C, weather 3 °C: about −12 … 30 °C.
//!
//! **Connections.** Each connection parameter l follows
//! `ln θ_l(T) = ln θ_l(20 °C) + a_l (20 − T) + b_l · s · ln(1 + exp((T_f − T)/s))`:
//! stiffer as it cools (`a_l`, 0.2–0.5 %/°C: contact and friction), and much stiffer once
//! the joint freezes (`b_l`, 1.0–2.5 %/°C below `T_f` = −1 °C, a transition `s` = 1.5 °C
//! wide). `a_l` and `b_l` are drawn per connection from the seed, so one seed's healthy and
//! loosening records share their law and their weather. Young's modulus follows the steel
//! as in every scenario ([`super::STEEL_ALPHA_E`]).

use chrono::{DateTime, Datelike, Timelike, Utc};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};

/// Climate and law of the seasonal scenario (module docs).
#[derive(Debug, Clone, PartialEq)]
pub struct Seasons {
    pub mean: f64,
    pub seasonal: f64,
    pub daily: f64,
    pub weather: f64,
    /// Freezing point of the joints and the width of the transition, °C.
    pub freeze_c: f64,
    pub freeze_width: f64,
    /// `a_l` and `b_l` per parameter (0 for parameters that are not connections), per °C.
    pub linear: Vec<f64>,
    pub frozen: Vec<f64>,
    /// Weather `w / weather` (unit variance) every [`WEATHER_STEP_DAYS`] from the start.
    weather_series: Vec<f64>,
    start: DateTime<Utc>,
}

/// Grid of the weather process, days.
pub const WEATHER_STEP_DAYS: f64 = 0.25;

/// Correlation time of the weather, days.
pub const WEATHER_DAYS: f64 = 3.0;

impl Seasons {
    /// The law for parameters marked `is_connection`, over `days` from `start`, drawn from
    /// `seed` (a stream of its own: the measurement noise does not change it).
    pub fn new(is_connection: &[bool], days: f64, start: DateTime<Utc>, seed: u64) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x5EA5_0115);
        let mut draw = |lo: f64, hi: f64| lo + (hi - lo) * rng.random::<f64>();
        let (linear, frozen) = is_connection
            .iter()
            .map(|&c| {
                if c {
                    (draw(0.002, 0.005), draw(0.010, 0.025))
                } else {
                    (0.0, 0.0)
                }
            })
            .unzip();
        let n = (days / WEATHER_STEP_DAYS).ceil() as usize + 2;
        let rho = (-WEATHER_STEP_DAYS / WEATHER_DAYS).exp();
        let mut w = Vec::with_capacity(n);
        // Unit variance; scaled by `weather` where it is used.
        let mut x: f64 = rng.sample(StandardNormal);
        for _ in 0..n {
            w.push(x);
            let z: f64 = StandardNormal.sample(&mut rng);
            x = rho * x + (1.0 - rho * rho).sqrt() * z;
        }
        Self {
            mean: 9.0,
            seasonal: 13.0,
            daily: 4.0,
            weather: 3.0,
            freeze_c: -1.0,
            freeze_width: 1.5,
            linear,
            frozen,
            weather_series: w,
            start,
        }
    }

    /// Temperature of the structure at day `t` (module docs).
    pub fn temperature(&self, t: f64) -> f64 {
        use std::f64::consts::TAU;
        let time = self.start + chrono::Duration::milliseconds((t * 86_400_000.0).round() as i64);
        let doy = time.ordinal0() as f64 + time.num_seconds_from_midnight() as f64 / 86_400.0;
        let hour = time.num_seconds_from_midnight() as f64 / 3600.0;
        let k = (t / WEATHER_STEP_DAYS).max(0.0);
        let i = (k.floor() as usize).min(self.weather_series.len() - 2);
        let f = (k - i as f64).clamp(0.0, 1.0);
        let w = self.weather_series[i] * (1.0 - f) + self.weather_series[i + 1] * f;
        self.mean
            - self.seasonal * (TAU * (doy - 20.0) / 365.25).cos()
            - self.daily * (TAU * (hour - 15.0) / 24.0).cos()
            + self.weather * w
    }

    /// `ln θ_l(T) − ln θ_l(20 °C)` of parameter `l` (module docs).
    pub fn log_factor(&self, l: usize, temperature: f64) -> f64 {
        let s = self.freeze_width;
        let x = (self.freeze_c - temperature) / s;
        // ln(1 + eˣ), without overflow.
        let softplus = if x > 30.0 { x } else { x.exp().ln_1p() };
        self.linear[l] * (20.0 - temperature) + self.frozen[l] * s * softplus
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn seasons() -> Seasons {
        let start = DateTime::parse_from_rfc3339("2026-03-01T00:00:00Z")
            .unwrap()
            .with_timezone(&Utc);
        Seasons::new(&[true, true, false], 730.0, start, 4)
    }

    /// Two years span about −12 … 30 °C (weather included), coldest in January.
    #[test]
    fn climate_spans_the_seasons() {
        let s = seasons();
        let temps: Vec<f64> = (0..2920).map(|k| s.temperature(k as f64 * 0.25)).collect();
        let lo = temps.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = temps.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        assert!(
            (-20.0..-8.0).contains(&lo) && (25.0..36.0).contains(&hi),
            "{lo} … {hi}"
        );
        // Day 325 from 1 March is 20 January: colder than day 142 (21 July) by about 2 × 13.
        let jan: f64 = (0..40)
            .map(|k| s.temperature(325.0 + k as f64 * 0.25))
            .sum::<f64>()
            / 40.0;
        let jul: f64 = (0..40)
            .map(|k| s.temperature(142.0 + k as f64 * 0.25))
            .sum::<f64>()
            / 40.0;
        assert!(jul - jan > 15.0, "{jan} vs {jul}");
    }

    /// The law: 0 at 20 °C; a swing of 20–60 % in θ between 30 °C and −12 °C; the freezing
    /// term dominant below T_f; parameters that are not connections unchanged.
    #[test]
    fn connections_stiffen_as_they_cool_and_freeze() {
        let s = seasons();
        for l in 0..2 {
            let at20 = s.log_factor(l, 20.0);
            assert!(at20.abs() < 0.01 * s.frozen[l] * 1.5, "{at20}");
            let swing = s.log_factor(l, -12.0).exp() / s.log_factor(l, 30.0).exp() - 1.0;
            assert!((0.2..0.7).contains(&swing), "{swing}");
            let frozen = s.log_factor(l, -12.0) - s.log_factor(l, -1.0);
            assert!(frozen > 11.0 * s.linear[l], "{frozen}");
        }
        assert_eq!(s.log_factor(2, -12.0), 0.0);
    }
}
