//! The automatic choice of modes from the poles of many model orders: no hand-picking.
//!
//! 1. **Physical poles only**: damping ratio in `(0, max_damping]`, frequency inside the
//!    band, modal phase collinearity at least `min_mpc` (a structural mode with
//!    proportional-like damping is nearly real; noise poles are not).
//! 2. **Stability across orders**: a pole is *stable* when the next lower order has a pole
//!    within `df` in frequency (relative), `dxi` in damping (relative) and with MAC at
//!    least `mac` (the usual stabilization-diagram criteria; Peeters & De Roeck 2001,
//!    Reynders et al. 2012 for their automated use).
//! 3. **Clustering**: stable poles are grouped by frequency distance and MAC (a pole joins
//!    the cluster whose median frequency is within `cluster_df` and whose representative
//!    shape it matches at `mac`); a cluster is a mode when it holds stable poles from at
//!    least `min_share` of the orders. Spurious poles appear at few orders and scatter,
//!    so they form small clusters and are dropped. The mode count is the number of
//!    clusters that remain: decided by the data.
//! 4. Each mode is represented by the member pole closest to the cluster's median
//!    frequency (its order is reported; uncertainties are computed at that order).

use super::ssi::{Pole, PoleSet, mac_complex, real_shape};

/// Criteria of the automatic selection (module docs).
#[derive(Debug, Clone)]
pub struct Criteria {
    pub band_hz: (f64, f64),
    pub max_damping: f64,
    pub min_mpc: f64,
    pub df: f64,
    pub dxi: f64,
    pub mac: f64,
    pub cluster_df: f64,
    pub min_share: f64,
}

impl Default for Criteria {
    fn default() -> Self {
        Self {
            band_hz: (0.0, f64::INFINITY),
            max_damping: 0.2,
            min_mpc: 0.5,
            df: 0.01,
            dxi: 0.3,
            mac: 0.95,
            cluster_df: 0.02,
            min_share: 0.4,
        }
    }
}

/// A mode chosen from the stabilization diagram.
#[derive(Debug, Clone)]
pub struct SelectedMode {
    /// The representative pole.
    pub pole: Pole,
    /// Real mode shape (unit norm, largest entry positive) and its MPC.
    pub shape: Vec<f64>,
    pub mpc: f64,
    /// Stable poles in the cluster, and the spread of their frequencies (relative std).
    pub members: usize,
    pub frequency_spread: f64,
    /// Every stable pole of the cluster: (model order, frequency in Hz).
    pub member_poles: Vec<(usize, f64)>,
}

/// Selects the modes of a pole set (module docs), ascending in frequency.
pub fn select_modes(set: &PoleSet, c: &Criteria) -> Vec<SelectedMode> {
    let physical: Vec<&Pole> = set
        .poles
        .iter()
        .filter(|p| {
            p.damping > 0.0
                && p.damping <= c.max_damping
                && p.frequency_hz >= c.band_hz.0
                && p.frequency_hz <= c.band_hz.1
                && real_shape(&p.shape).1 >= c.min_mpc
        })
        .collect();
    // Stable: a matching pole at the next lower order.
    let stable: Vec<&Pole> = set
        .orders
        .windows(2)
        .flat_map(|w| {
            let (lower, order) = (w[0], w[1]);
            let below: Vec<&Pole> = physical
                .iter()
                .copied()
                .filter(|p| p.order == lower)
                .collect();
            physical
                .iter()
                .copied()
                .filter(move |p| p.order == order)
                .filter(move |p| {
                    below.iter().any(|q| {
                        (p.frequency_hz / q.frequency_hz - 1.0).abs() <= c.df
                            && (p.damping / q.damping - 1.0).abs() <= c.dxi
                            && mac_complex(&p.shape, &q.shape) >= c.mac
                    })
                })
        })
        .collect();
    // Clusters, in order of frequency.
    let mut sorted = stable;
    sorted.sort_by(|a, b| a.frequency_hz.total_cmp(&b.frequency_hz));
    let mut clusters: Vec<Vec<&Pole>> = Vec::new();
    for p in sorted {
        let home = clusters.iter_mut().find(|cl| {
            let f = median(cl.iter().map(|q| q.frequency_hz).collect());
            (p.frequency_hz / f - 1.0).abs() <= c.cluster_df
                && mac_complex(&p.shape, &cl[0].shape) >= c.mac
        });
        match home {
            Some(cl) => cl.push(p),
            None => clusters.push(vec![p]),
        }
    }
    let n_orders = set.orders.len().saturating_sub(1).max(1) as f64;
    let mut modes: Vec<SelectedMode> = clusters
        .into_iter()
        .filter(|cl| {
            let mut orders: Vec<usize> = cl.iter().map(|p| p.order).collect();
            orders.sort_unstable();
            orders.dedup();
            orders.len() as f64 >= c.min_share * n_orders
        })
        .map(|cl| {
            let freqs: Vec<f64> = cl.iter().map(|p| p.frequency_hz).collect();
            let f = median(freqs.clone());
            let mean = freqs.iter().sum::<f64>() / freqs.len() as f64;
            let spread =
                (freqs.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / freqs.len() as f64).sqrt()
                    / mean;
            let rep = cl
                .iter()
                .min_by(|a, b| {
                    (a.frequency_hz - f)
                        .abs()
                        .total_cmp(&(b.frequency_hz - f).abs())
                })
                .expect("clusters are not empty");
            let (shape, mpc) = real_shape(&rep.shape);
            SelectedMode {
                pole: (*rep).clone(),
                shape,
                mpc,
                members: cl.len(),
                frequency_spread: spread,
                member_poles: cl.iter().map(|p| (p.order, p.frequency_hz)).collect(),
            }
        })
        .collect();
    modes.sort_by(|a, b| a.pole.frequency_hz.total_cmp(&b.pole.frequency_hz));
    modes
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}
