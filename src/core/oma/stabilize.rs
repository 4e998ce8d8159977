//! The automatic choice of modes from the poles of many model orders, with thresholds the
//! data decide: the three-stage clustering of Reynders, Houbrechts & De Roeck, "Fully
//! automated (operational) modal analysis", MSSP 29 (2012) 228–250, §3.
//!
//! 0. **Physical poles only**: damping ratio in `(0, max_damping]`, frequency inside the
//!    band, modal phase collinearity at least `min_mpc`.
//! 1. **Possibly physical or certainly mathematical** (their stage 1): every pole is
//!    compared with its nearest pole of the next lower order (distance
//!    [`pole_distance`]) by five criteria: the relative differences of its eigenvalue,
//!    frequency and damping, `1 − MAC` and the difference of MPC. Two-means clustering of
//!    these vectors (each criterion scaled by its range, centres started at the smallest
//!    and the largest values) splits the poles in two; the group of the smaller centre is
//!    the *stable* poles of the diagram. No fixed 1 % / 30 % / MAC 0.95: a record whose
//!    modes are lightly damped (damping scattering far more than 30 % between orders) and
//!    seen by few channels (MAC noisy) draws its own line.
//! 2. **Hierarchical clustering** of the stable poles (their stage 2): average linkage on
//!    [`pole_distance`] (eigenvalue difference plus `1 − MAC`), cut at the mean plus twice
//!    the standard deviation of the stable poles' distances to their lower-order
//!    neighbours: poles of one mode lie that close to each other, whatever the order.
//!    Within a cluster one pole per order is kept, the nearest the cluster's median
//!    frequency.
//! 3. **Physical clusters** (their stage 3): two-means on the cluster sizes; the clusters of
//!    the larger centre are the modes. A mode appears at most orders above the one that
//!    first resolves it; a spurious pole at few. A cluster holding fewer than
//!    [`MIN_MEMBERS`] orders is never a mode; one holding [`SURE_SHARE`] of the orders
//!    is a candidate, kept when its uncertainties are resolved.
//! 4. Each mode is represented by the member pole closest to the cluster's median
//!    frequency (its order is reported; uncertainties are computed at that order).

use faer::c64;

use super::ssi::{Pole, PoleSet, mac_complex, real_shape};

/// Fewest orders a cluster needs to be a mode (step 3).
pub const MIN_MEMBERS: usize = 3;

/// Share of the orders from which a cluster is a candidate mode whatever the two-means on
/// the sizes says (step 3). The two-means alone splits the modes themselves when a few
/// stand out: on one simulated 120-s record of the lab frame it left seven true modes out.
/// Such a cluster must then have resolved uncertainties to be kept
/// ([`super::identify::NOISE_FREQUENCY_COV`]): on a 30-s window two spurious clusters of 5
/// and 9 of 20 orders came this far, with σ_ζ above ζ and σ_f/f of 1.7 and 6 %.
pub const SURE_SHARE: f64 = 0.25;

/// Criteria of the automatic selection (module docs).
#[derive(Debug, Clone)]
pub struct Criteria {
    pub band_hz: (f64, f64),
    pub max_damping: f64,
    pub min_mpc: f64,
}

impl Default for Criteria {
    fn default() -> Self {
        Self {
            band_hz: (0.0, f64::INFINITY),
            max_damping: 0.2,
            min_mpc: 0.5,
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
    /// Stable poles in the cluster (one per order), and the spread of their frequencies
    /// (relative std).
    pub members: usize,
    pub frequency_spread: f64,
    /// Every pole of the cluster: (model order, frequency in Hz).
    pub member_poles: Vec<(usize, f64)>,
    /// In the group of the larger centre of the two-means on the cluster sizes (step 3);
    /// false for a cluster kept because it holds [`SURE_SHARE`] of the orders.
    pub well_populated: bool,
}

/// What the selection made of one pole (for the stabilization diagram).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Verdict {
    /// Outside the band, negatively or heavily damped, or complex in shape (step 0).
    NotPhysical,
    /// Certainly mathematical (step 1).
    Unstable,
    /// Possibly physical, in a cluster that is not a mode.
    Stable,
    /// A member of the cluster of mode `k` (index into [`Selection::modes`]).
    Mode(usize),
}

/// The selection of one pole set.
#[derive(Debug, Clone)]
pub struct Selection {
    pub modes: Vec<SelectedMode>,
    /// One per pole of the set, in its order.
    pub verdicts: Vec<Verdict>,
    /// The cut of the hierarchical clustering (step 2).
    pub cut: f64,
}

/// Selects the modes of a pole set (module docs), ascending in frequency.
pub fn select_modes(set: &PoleSet, c: &Criteria) -> Vec<SelectedMode> {
    select(set, c).modes
}

/// [`select_modes`] with the verdict on every pole.
pub fn select(set: &PoleSet, c: &Criteria) -> Selection {
    let mut verdicts = vec![Verdict::NotPhysical; set.poles.len()];
    let mpc: Vec<f64> = set.poles.iter().map(|p| real_shape(&p.shape).1).collect();
    let physical: Vec<usize> = (0..set.poles.len())
        .filter(|&i| {
            let p = &set.poles[i];
            p.damping > 0.0
                && p.damping <= c.max_damping
                && p.frequency_hz >= c.band_hz.0
                && p.frequency_hz <= c.band_hz.1
                && mpc[i] >= c.min_mpc
        })
        .collect();
    let (stable, neighbour_distances) = stable_poles(set, &physical, &mpc);
    for &i in &physical {
        verdicts[i] = Verdict::Unstable;
    }
    for &i in &stable {
        verdicts[i] = Verdict::Stable;
    }
    let cut = mean_plus_two_std(&neighbour_distances);
    let clusters = cluster(set, &stable, cut);
    let modes = physical_clusters(set, clusters);
    let modes: Vec<(SelectedMode, Vec<usize>)> = modes
        .into_iter()
        .map(|(members, well_populated)| {
            let mut mode = summarize(set, &members);
            mode.well_populated = well_populated;
            (mode, members)
        })
        .collect();
    let mut modes = modes;
    modes.sort_by(|a, b| a.0.pole.frequency_hz.total_cmp(&b.0.pole.frequency_hz));
    for (k, (_, members)) in modes.iter().enumerate() {
        for &i in members {
            verdicts[i] = Verdict::Mode(k);
        }
    }
    Selection {
        modes: modes.into_iter().map(|(m, _)| m).collect(),
        verdicts,
        cut,
    }
}

/// The distance of two poles: `|μ_a − μ_b| / max(|μ_a|, |μ_b|) + 1 − MAC`, μ the continuous
/// eigenvalues (Reynders et al. 2012, eq. (10)).
pub fn pole_distance(a: &Pole, b: &Pole) -> f64 {
    let (ma, mb) = (eigenvalue(a), eigenvalue(b));
    (ma - mb).norm() / ma.norm().max(mb.norm()) + 1.0 - mac_complex(&a.shape, &b.shape)
}

/// The continuous eigenvalue `μ = −ζω + iω√(1 − ζ²)` of a pole.
fn eigenvalue(p: &Pole) -> c64 {
    let w = 2.0 * std::f64::consts::PI * p.frequency_hz;
    c64::new(
        -p.damping * w,
        w * (1.0 - p.damping * p.damping).max(0.0).sqrt(),
    )
}

/// Step 1: the possibly physical poles (indices into `set.poles`) and their distances to
/// their nearest pole of the next lower order.
fn stable_poles(set: &PoleSet, physical: &[usize], mpc: &[f64]) -> (Vec<usize>, Vec<f64>) {
    let mut candidates = Vec::new();
    let mut features: Vec<[f64; 5]> = Vec::new();
    let mut distances = Vec::new();
    for w in set.orders.windows(2) {
        let (lower, order) = (w[0], w[1]);
        let below: Vec<usize> = physical
            .iter()
            .copied()
            .filter(|&j| set.poles[j].order == lower)
            .collect();
        for &i in physical.iter().filter(|&&i| set.poles[i].order == order) {
            let p = &set.poles[i];
            let Some((j, d)) = below
                .iter()
                .map(|&j| (j, pole_distance(p, &set.poles[j])))
                .min_by(|a, b| a.1.total_cmp(&b.1))
            else {
                continue;
            };
            let q = &set.poles[j];
            let (mp, mq) = (eigenvalue(p), eigenvalue(q));
            features.push([
                (mp - mq).norm() / mp.norm().max(mq.norm()),
                (p.frequency_hz / q.frequency_hz - 1.0).abs(),
                ((p.damping - q.damping) / p.damping.max(q.damping)).abs(),
                1.0 - mac_complex(&p.shape, &q.shape),
                (mpc[i] - mpc[j]).abs(),
            ]);
            candidates.push(i);
            distances.push(d);
        }
    }
    let near = two_means_low(&features);
    let stable: Vec<usize> = near.iter().map(|&k| candidates[k]).collect();
    let d: Vec<f64> = near.iter().map(|&k| distances[k]).collect();
    (stable, d)
}

/// Indices of the vectors in the group of the smaller centre of a two-means clustering
/// (Lloyd's iterations; every coordinate scaled by its range; centres started at the
/// smallest and the largest values).
fn two_means_low<const D: usize>(x: &[[f64; D]]) -> Vec<usize> {
    if x.len() < 2 {
        return (0..x.len()).collect();
    }
    let mut lo = [f64::INFINITY; D];
    let mut hi = [f64::NEG_INFINITY; D];
    for v in x {
        for d in 0..D {
            lo[d] = lo[d].min(v[d]);
            hi[d] = hi[d].max(v[d]);
        }
    }
    let scaled: Vec<[f64; D]> = x
        .iter()
        .map(|v| std::array::from_fn(|d| (v[d] - lo[d]) / (hi[d] - lo[d]).max(1e-300)))
        .collect();
    let mut centres = [[0.0; D], [1.0; D]];
    let mut group = vec![false; x.len()];
    for _ in 0..100 {
        let dist = |v: &[f64; D], c: &[f64; D]| -> f64 {
            v.iter().zip(c).map(|(a, b)| (a - b) * (a - b)).sum()
        };
        let next: Vec<bool> = scaled
            .iter()
            .map(|v| dist(v, &centres[1]) < dist(v, &centres[0]))
            .collect();
        let changed = next != group;
        group = next;
        for (g, centre) in centres.iter_mut().enumerate() {
            let members: Vec<&[f64; D]> = scaled
                .iter()
                .zip(&group)
                .filter(|(_, gr)| **gr == (g == 1))
                .map(|(v, _)| v)
                .collect();
            if !members.is_empty() {
                *centre = std::array::from_fn(|d| {
                    members.iter().map(|v| v[d]).sum::<f64>() / members.len() as f64
                });
            }
        }
        if !changed {
            break;
        }
    }
    (0..x.len()).filter(|&k| !group[k]).collect()
}

fn mean_plus_two_std(v: &[f64]) -> f64 {
    if v.is_empty() {
        return 0.0;
    }
    let n = v.len() as f64;
    let mean = v.iter().sum::<f64>() / n;
    let var = v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n;
    mean + 2.0 * var.sqrt()
}

/// Step 2: average-linkage clusters of the poles `stable` cut at `cut`, one pole per order
/// in each (the nearest the cluster's median frequency).
fn cluster(set: &PoleSet, stable: &[usize], cut: f64) -> Vec<Vec<usize>> {
    let n = stable.len();
    if n == 0 {
        return Vec::new();
    }
    let mut condensed = Vec::with_capacity(n * (n - 1) / 2);
    for a in 0..n {
        for b in a + 1..n {
            condensed.push(pole_distance(&set.poles[stable[a]], &set.poles[stable[b]]));
        }
    }
    let dendrogram = kodama::linkage(&mut condensed, n, kodama::Method::Average);
    // Average linkage is monotone: the clusters below the cut are the unions of the merges
    // at or below it.
    let mut parent: Vec<usize> = (0..2 * n).collect();
    fn root(parent: &mut [usize], mut i: usize) -> usize {
        while parent[i] != i {
            parent[i] = parent[parent[i]];
            i = parent[i];
        }
        i
    }
    for (k, step) in dendrogram.steps().iter().enumerate() {
        if step.dissimilarity <= cut {
            let (a, b) = (
                root(&mut parent, step.cluster1),
                root(&mut parent, step.cluster2),
            );
            parent[a] = n + k;
            parent[b] = n + k;
        }
    }
    let mut groups: std::collections::BTreeMap<usize, Vec<usize>> = Default::default();
    for (a, &i) in stable.iter().enumerate() {
        groups.entry(root(&mut parent, a)).or_default().push(i);
    }
    groups
        .into_values()
        .map(|members| one_per_order(set, members))
        .collect()
}

/// The members of a cluster, one per order: the nearest the cluster's median frequency.
fn one_per_order(set: &PoleSet, members: Vec<usize>) -> Vec<usize> {
    let f = median(members.iter().map(|&i| set.poles[i].frequency_hz).collect());
    let mut best: std::collections::BTreeMap<usize, usize> = Default::default();
    for i in members {
        let p = &set.poles[i];
        best.entry(p.order)
            .and_modify(|j| {
                if (p.frequency_hz - f).abs() < (set.poles[*j].frequency_hz - f).abs() {
                    *j = i;
                }
            })
            .or_insert(i);
    }
    best.into_values().collect()
}

/// Step 3: the clusters of the larger centre of a two-means on their sizes (marked
/// `true`), and those holding poles from at least [`SURE_SHARE`] of the orders.
fn physical_clusters(set: &PoleSet, clusters: Vec<Vec<usize>>) -> Vec<(Vec<usize>, bool)> {
    let sure = (SURE_SHARE * set.orders.len() as f64).ceil() as usize;
    let big: Vec<Vec<usize>> = clusters
        .into_iter()
        .filter(|c| c.len() >= MIN_MEMBERS)
        .collect();
    let sizes: Vec<[f64; 1]> = big.iter().map(|c| [c.len() as f64]).collect();
    let small: std::collections::HashSet<usize> = if sizes.len() >= 2 {
        let low = two_means_low(&sizes);
        if low.len() == sizes.len() {
            Default::default()
        } else {
            low.into_iter().collect()
        }
    } else {
        Default::default()
    };
    big.into_iter()
        .enumerate()
        .filter(|(k, c)| !small.contains(k) || c.len() >= sure.max(MIN_MEMBERS))
        .map(|(k, c)| (c, !small.contains(&k)))
        .collect()
}

/// The mode a cluster stands for (step 4).
fn summarize(set: &PoleSet, members: &[usize]) -> SelectedMode {
    let freqs: Vec<f64> = members.iter().map(|&i| set.poles[i].frequency_hz).collect();
    let f = median(freqs.clone());
    let mean = freqs.iter().sum::<f64>() / freqs.len() as f64;
    let spread =
        (freqs.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / freqs.len() as f64).sqrt() / mean;
    let rep = members
        .iter()
        .map(|&i| &set.poles[i])
        .min_by(|a, b| {
            (a.frequency_hz - f)
                .abs()
                .total_cmp(&(b.frequency_hz - f).abs())
        })
        .expect("clusters are not empty");
    let (shape, mpc) = real_shape(&rep.shape);
    SelectedMode {
        pole: rep.clone(),
        shape,
        mpc,
        members: members.len(),
        frequency_spread: spread,
        member_poles: members
            .iter()
            .map(|&i| (set.poles[i].order, set.poles[i].frequency_hz))
            .collect(),
        well_populated: true,
    }
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
