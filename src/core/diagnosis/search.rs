//! One-dimensional minimization for the profile of an effect: a downhill bracket, then
//! Brent's method (golden sections with parabolic steps).

/// Minimizes `f` over `t` from `t0` with initial step `d`: a downhill bracket, then a
/// Brent search to `tol`. Returns the minimizer and the minimum.
pub(super) fn minimize_1d(mut f: impl FnMut(f64) -> f64, t0: f64, d: f64, tol: f64) -> (f64, f64) {
    const GOLD: f64 = 1.618_033_988_749_895;
    let f0 = f(t0);
    let (mut a, mut fa) = (t0, f0);
    let (mut b, mut fb) = (t0 + d, f(t0 + d));
    if fb > fa {
        let (c, fc) = (t0 - d, f(t0 - d));
        if fc >= fa {
            return brent(&mut f, t0 - d, t0 + d, (t0, f0), tol);
        }
        (b, fb) = (c, fc);
    }
    // Downhill from a through b: expand until the function rises.
    for _ in 0..12 {
        let c = b + GOLD * (b - a);
        let fc = f(c);
        if fc >= fb {
            let (lo, hi) = if a < c { (a, c) } else { (c, a) };
            return brent(&mut f, lo, hi, (b, fb), tol);
        }
        (a, fa) = (b, fb);
        (b, fb) = (c, fc);
    }
    let _ = fa;
    (b, fb)
}

/// Brent's minimization on [lo, hi] from a known interior point (golden sections with
/// parabolic steps; R. P. Brent, *Algorithms for Minimization without Derivatives*, 1973,
/// ch. 5): a smooth minimum in about 10 evaluations instead of golden section's 25.
pub(super) fn brent(
    f: &mut impl FnMut(f64) -> f64,
    mut lo: f64,
    mut hi: f64,
    best: (f64, f64),
    tol: f64,
) -> (f64, f64) {
    const R: f64 = 0.381_966_011_250_105;
    let (mut x, mut fx) = best;
    let (mut w, mut fw, mut v, mut fv) = (x, fx, x, fx);
    let (mut d, mut e): (f64, f64) = (0.0, 0.0);
    for _ in 0..60 {
        let m = 0.5 * (lo + hi);
        let tol1 = tol * 0.5 + 1e-12 * x.abs();
        if (x - m).abs() <= 2.0 * tol1 - 0.5 * (hi - lo) {
            break;
        }
        let mut golden_step = true;
        if e.abs() > tol1 {
            // Parabola through x, w, v.
            let r = (x - w) * (fx - fv);
            let mut q = (x - v) * (fx - fw);
            let mut p = (x - v) * q - (x - w) * r;
            q = 2.0 * (q - r);
            if q > 0.0 {
                p = -p;
            }
            q = q.abs();
            if p.abs() < (0.5 * q * e).abs() && p > q * (lo - x) && p < q * (hi - x) {
                e = d;
                d = p / q;
                let u = x + d;
                if u - lo < 2.0 * tol1 || hi - u < 2.0 * tol1 {
                    d = if m > x { tol1 } else { -tol1 };
                }
                golden_step = false;
            }
        }
        if golden_step {
            e = if x >= m { lo - x } else { hi - x };
            d = R * e;
        }
        let u = if d.abs() >= tol1 {
            x + d
        } else {
            x + tol1.copysign(d)
        };
        let fu = f(u);
        if fu <= fx {
            if u >= x {
                lo = x;
            } else {
                hi = x;
            }
            (v, fv, w, fw, x, fx) = (w, fw, x, fx, u, fu);
        } else {
            if u < x {
                lo = u;
            } else {
                hi = u;
            }
            if fu <= fw || w == x {
                (v, fv, w, fw) = (w, fw, u, fu);
            } else if fu <= fv || v == x || v == w {
                (v, fv) = (u, fu);
            }
        }
    }
    (x, fx)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The 1-D search finds the minimum of a parabola from either side and of a function
    /// whose minimum is at the start.
    #[test]
    fn minimize_1d_finds_minima() {
        for (t0, d) in [(0.0, 1.0), (10.0, 1.0), (3.0, 0.1), (-5.0, 2.0)] {
            let (t, v) = minimize_1d(|t| (t - 3.0) * (t - 3.0) + 1.0, t0, d, 1e-6);
            assert!((t - 3.0).abs() < 1e-5, "from {t0}: {t}");
            assert!((v - 1.0).abs() < 1e-9);
        }
    }
}
