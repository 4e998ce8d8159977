//! Statistics the numerics and the tracker share: the standard normal distribution (Φ,
//! Φ⁻¹, the 95 % quantile), the χ² bounds of a misfit and the sample standard deviation.

/// Two-sided 95 % normal quantile.
pub const Z95: f64 = 1.959_963_984_540_054;

/// Standard normal CDF (Abramowitz–Stegun 7.1.26 on erfc, |error| < 1.5e-7).
pub fn normal_cdf(z: f64) -> f64 {
    let x = z.abs() / std::f64::consts::SQRT_2;
    let t = 1.0 / (1.0 + 0.327_591_1 * x);
    let poly = t
        * (0.254_829_592
            + t * (-0.284_496_736
                + t * (1.421_413_741 + t * (-1.453_152_027 + t * 1.061_405_429))));
    let erfc = poly * (-x * x).exp();
    if z >= 0.0 {
        1.0 - 0.5 * erfc
    } else {
        0.5 * erfc
    }
}

/// χ²₁ quantile at upper-tail probability `p`: `z²` with `z = Φ⁻¹(1 − p/2)`.
pub fn chi2_1_upper_quantile(p: f64) -> f64 {
    let z = inverse_normal_cdf(1.0 - p / 2.0);
    z * z
}

/// Φ⁻¹ by P. J. Acklam's rational approximation (relative error < 1.2e-9 on (0, 1)).
pub fn inverse_normal_cdf(p: f64) -> f64 {
    const A: [f64; 6] = [
        -3.969_683_028_665_376e1,
        2.209_460_984_245_205e2,
        -2.759_285_104_469_687e2,
        1.383_577_518_672_69e2,
        -3.066_479_806_614_716e1,
        2.506_628_277_459_239,
    ];
    const B: [f64; 5] = [
        -5.447_609_879_822_406e1,
        1.615_858_368_580_409e2,
        -1.556_989_798_598_866e2,
        6.680_131_188_771_972e1,
        -1.328_068_155_288_572e1,
    ];
    const C: [f64; 6] = [
        -7.784_894_002_430_293e-3,
        -3.223_964_580_411_365e-1,
        -2.400_758_277_161_838,
        -2.549_732_539_343_734,
        4.374_664_141_464_968,
        2.938_163_982_698_783,
    ];
    const D: [f64; 4] = [
        7.784_695_709_041_462e-3,
        3.224_671_290_700_398e-1,
        2.445_134_137_142_996,
        3.754_408_661_907_416,
    ];
    const LOW: f64 = 0.02425;
    if p <= 0.0 {
        return f64::NEG_INFINITY;
    }
    if p >= 1.0 {
        return f64::INFINITY;
    }
    let tail = |q: f64| {
        (((((C[0] * q + C[1]) * q + C[2]) * q + C[3]) * q + C[4]) * q + C[5])
            / ((((D[0] * q + D[1]) * q + D[2]) * q + D[3]) * q + 1.0)
    };
    if p < LOW {
        tail((-2.0 * p.ln()).sqrt())
    } else if p > 1.0 - LOW {
        -tail((-2.0 * (1.0 - p).ln()).sqrt())
    } else {
        let q = p - 0.5;
        let r = q * q;
        (((((A[0] * r + A[1]) * r + A[2]) * r + A[3]) * r + A[4]) * r + A[5]) * q
            / (((((B[0] * r + B[1]) * r + B[2]) * r + B[3]) * r + B[4]) * r + 1.0)
    }
}

/// The χ² degrees of freedom of ε: `ν = N − N_θ` (at least 1).
pub fn chi2_dof(n_data: usize, n_params: usize) -> f64 {
    n_data.saturating_sub(n_params).max(1) as f64
}

/// The χ² acceptance bound of a χ²_ν quantity: `ν + 4√(2ν)` (4 standard deviations above
/// the mean).
pub fn chi2_bound_of_dof(nu: f64) -> f64 {
    nu + 4.0 * (2.0 * nu).sqrt()
}

/// The χ² acceptance bound of ε: `ν + 4√(2ν)` with `ν = N − N_θ` (ε ~ χ²_ν when the model
/// class is right and Σ_M is true; 4 standard deviations above the mean).
pub fn chi2_bound(n_data: usize, n_params: usize) -> f64 {
    chi2_bound_of_dof(chi2_dof(n_data, n_params))
}

/// The sample standard deviation (with n − 1), NaN for fewer than two values.
pub fn sample_std(x: &[f64]) -> f64 {
    let n = x.len() as f64;
    let mean = x.iter().sum::<f64>() / n;
    (x.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1.0)).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Eight values of mean 5 whose squared deviations sum to 32: σ = √(32/7).
    #[test]
    fn sample_std_divides_by_n_minus_one() {
        let x = [2.0, 4.0, 4.0, 4.0, 5.0, 5.0, 7.0, 9.0];
        assert!((sample_std(&x) - (32.0_f64 / 7.0).sqrt()).abs() < 1e-15);
        assert!(sample_std(&[1.0]).is_nan());
    }

    #[test]
    fn normal_cdf_known_values() {
        for (z, p) in [
            (0.0, 0.5),
            (1.0, 0.841_344_746),
            (-1.959_963_985, 0.025),
            (1.644_853_627, 0.95),
            (3.0, 0.998_650_102),
        ] {
            assert!(
                (normal_cdf(z) - p).abs() < 2e-7,
                "Φ({z}) = {}",
                normal_cdf(z)
            );
        }
    }

    /// Φ⁻¹ inverts Φ (A&S erfc, |error| < 1.5e-7) and matches known quantiles.
    #[test]
    fn inverse_normal_cdf_inverts_the_cdf() {
        assert!((inverse_normal_cdf(0.975) - 1.959_963_985).abs() < 1e-8);
        assert!((inverse_normal_cdf(0.5)).abs() < 1e-12);
        assert!((inverse_normal_cdf(1e-6) + 4.753_424_309).abs() < 1e-7);
        assert!((inverse_normal_cdf(0.975) - Z95).abs() < 1e-8);
        for p in [1e-9, 1e-4, 0.01, 0.3, 0.7, 0.99, 0.999_99] {
            let z = inverse_normal_cdf(p);
            let back = normal_cdf(z);
            assert!((back - p).abs() < 2e-7, "p {p}: Φ(Φ⁻¹(p)) = {back}");
        }
        // χ²₁ at 5 %: 3.841.
        assert!((chi2_1_upper_quantile(0.05) - 3.841_458_821).abs() < 1e-7);
    }
}
