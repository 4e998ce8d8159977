//! Modal assurance criterion (26) and MAC pairing (29).

/// MAC(a, b) = (aᵀb)² / (‖a‖² ‖b‖²), paper (26). Zero if either vector is zero.
pub fn mac(a: &[f64], b: &[f64]) -> f64 {
    let (mut ab, mut aa, mut bb) = (0.0, 0.0, 0.0);
    for (x, y) in a.iter().zip(b) {
        ab += x * y;
        aa += x * x;
        bb += y * y;
    }
    if aa == 0.0 || bb == 0.0 {
        0.0
    } else {
        ab * ab / (aa * bb)
    }
}

/// Pairing (29): for each measured shape, the index of the candidate with the largest MAC
/// (first one on ties) and that MAC. Several measured modes may pair with the same candidate,
/// as in the paper's Fig. 13.
pub fn pair_modes(measured: &[&[f64]], candidates: &[Vec<f64>]) -> Vec<(usize, f64)> {
    measured
        .iter()
        .map(|psi| {
            let mut best = (0, f64::NEG_INFINITY);
            for (k, c) in candidates.iter().enumerate() {
                let v = mac(psi, c);
                if v > best.1 {
                    best = (k, v);
                }
            }
            best
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mac_is_scale_and_sign_invariant() {
        let a = [1.0, 2.0, -0.5];
        let b = [-3.0, -6.0, 1.5];
        // exact arithmetic up to a few roundings
        assert!((mac(&a, &b) - 1.0).abs() < 1e-15);
        assert_eq!(mac(&a, &[0.0, 0.0, 0.0]), 0.0);
        assert!(mac(&[1.0, 0.0], &[0.0, 1.0]).abs() < 1e-300);
    }

    #[test]
    fn pairing_picks_largest_mac() {
        let cands = vec![
            vec![1.0, 0.0, 0.0],
            vec![0.0, 1.0, 0.1],
            vec![0.0, 0.0, 1.0],
        ];
        let m1 = [0.1, 1.0, 0.0];
        let m2 = [0.0, 0.2, -1.0];
        let p = pair_modes(&[&m1, &m2], &cands);
        assert_eq!(p[0].0, 1);
        assert_eq!(p[1].0, 2);
    }
}
