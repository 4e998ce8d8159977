//! One identification, end to end: settings derived from the record ([`super::settings`]:
//! sub-bands, decimation, lags, orders, references), then for each sub-band the block
//! covariances, SSI-COV at every order, the automatic choice of modes
//! ([`super::stabilize`]) and each chosen mode's first-order standard deviations at the
//! order that represents it; last, the spectrum's peaks that no mode explains.

use super::decimate::decimate;
use super::settings::{BandSettings, Requested, Settings, derive};
use super::spectrum::Peak;
use super::ssi::{PoleSet, SsiOptions};
use super::stabilize::{Criteria, Selection, select};
use super::uncertainty::{Sensitivities, identify_with_sensitivities};
use super::{OmaError, Record};
use rayon::prelude::*;

/// Options of [`identify`].
#[derive(Debug, Clone)]
pub struct IdentifyOptions {
    /// What the caller fixes (band, lags, orders, decimation, references); the rest is
    /// derived from the record.
    pub requested: Requested,
    /// Model orders are `order_step, 2·order_step, …`.
    pub order_step: usize,
    /// Damping and MPC limits of a physical pole (the band is each sub-band's).
    pub criteria: Criteria,
    /// Blocks the record is cut into for the covariance of the Hankel matrix.
    pub blocks: usize,
}

impl Default for IdentifyOptions {
    /// Everything derived from the record, orders in steps of 2, 30 blocks.
    fn default() -> Self {
        Self {
            requested: Requested::default(),
            order_step: 2,
            criteria: Criteria::default(),
            blocks: 30,
        }
    }
}

/// An identification with what it was made of, for a report or a stabilization diagram.
#[derive(Debug, Clone)]
pub struct Identification {
    /// The modes, ascending in frequency.
    pub modes: Vec<IdentifiedMode>,
    pub settings: Settings,
    /// One per sub-band of the settings.
    pub bands: Vec<BandResult>,
    /// Peaks of the spectrum that no mode explains ([`unexplained_peaks`]).
    pub unexplained_peaks: Vec<Peak>,
}

/// The poles of one sub-band and what the selection made of them.
#[derive(Debug, Clone)]
pub struct BandResult {
    pub poles: PoleSet,
    pub selection: Selection,
    /// Per cluster of `selection.modes`, whether the noise rule left it out.
    pub noise: Vec<bool>,
}

/// An identified mode with its standard deviations.
#[derive(Debug, Clone)]
pub struct IdentifiedMode {
    pub frequency_hz: f64,
    pub frequency_std: f64,
    pub damping: f64,
    pub damping_std: f64,
    /// Real shape per channel, unit norm, largest entry positive.
    pub shape: Vec<f64>,
    pub shape_std: Vec<f64>,
    /// Model order of the representative pole, stable poles in its cluster, and its MPC.
    pub order: usize,
    pub members: usize,
    pub mpc: f64,
}

/// A frequency known to no better than this (σ_f/f) is not resolved: a cluster kept only
/// for its share of the orders is then noise (the noise rule). On 30-s windows of the lab
/// frame at 500 Hz such spurious clusters had σ_f/f of 0.96e-2 to 5.8e-2; the true modes
/// below 7e-3.
pub const NOISE_FREQUENCY_COV: f64 = 0.01;

/// The noise rule's measure of a frequency that is not resolved: the cluster's frequencies
/// scatter across model orders by at least this (relative standard deviation). The first-order σ of a lightly damped mode
/// seen by few channels is unreliable: on the measured frame in `tests/data` (0.2 %
/// damping, 5 channels, 240 s) real modes whose poles agree to 1e-4–1.7e-3 across 20–33
/// orders came out with σ_f/f of 1 % to several hundred per cent and σ_ζ above ζ. A
/// cluster that stable is a mode whatever its σ; noise clusters scatter (0.7–24 % there).
pub const NOISE_SPREAD: f64 = 5e-3;

/// Identifies the modes of `record` (module docs), ascending in frequency.
pub fn identify(record: &Record, opts: &IdentifyOptions) -> Result<Vec<IdentifiedMode>, OmaError> {
    Ok(identify_all(record, opts)?.modes)
}

/// [`identify`], with the settings, the poles and the spectrum's check.
pub fn identify_all(record: &Record, opts: &IdentifyOptions) -> Result<Identification, OmaError> {
    if let Some(&bad) = opts
        .requested
        .references
        .iter()
        .flatten()
        .find(|&&j| j >= record.channels.len())
    {
        return Err(OmaError::Input(format!(
            "reference channel {bad} is out of range (the record has {} channels)",
            record.channels.len()
        )));
    }
    let settings = derive(record.samples.as_ref(), record.rate_hz, &opts.requested);
    let mut modes = Vec::new();
    let mut bands = Vec::with_capacity(settings.bands.len());
    for band in &settings.bands {
        let (found, result) = identify_band(record, band, &settings.references, opts)?;
        modes.extend(found);
        bands.push(result);
    }
    modes.sort_by(|a, b| a.frequency_hz.total_cmp(&b.frequency_hz));
    let unexplained_peaks =
        unexplained_peaks(&settings.peaks, &modes, settings.spectrum.resolution_hz());
    Ok(Identification {
        modes,
        settings,
        bands,
        unexplained_peaks,
    })
}

/// The modes of one sub-band: decimation, SSI-COV with sensitivities, selection, σ.
fn identify_band(
    record: &Record,
    band: &BandSettings,
    refs: &[usize],
    opts: &IdentifyOptions,
) -> Result<(Vec<IdentifiedMode>, BandResult), OmaError> {
    let part = decimate(record, band.decimate);
    let ssi = SsiOptions {
        block_rows: band.block_rows,
        order_max: band.order_max,
        order_step: opts.order_step,
        references: refs.to_vec(),
    };
    let (poles, sens) = identify_with_sensitivities(&part, refs, &ssi, opts.blocks)?;
    let criteria = Criteria {
        band_hz: band.band_hz,
        ..opts.criteria.clone()
    };
    let selection = select(&poles, &criteria);
    let solves = order_solves(&selection.modes, &sens)?;
    let found: Vec<IdentifiedMode> = selection
        .modes
        .par_iter()
        .map(|m| with_uncertainty(m, &sens, &solves))
        .collect::<Result<_, _>>()?;
    let mut modes = Vec::with_capacity(selection.modes.len());
    let mut noise = Vec::with_capacity(selection.modes.len());
    for (m, mode) in selection.modes.iter().zip(found) {
        noise.push(is_noise(&mode, m));
        if noise[noise.len() - 1] {
            tracing::debug!(
                f = mode.frequency_hz,
                cov_f = mode.frequency_std / mode.frequency_hz,
                zeta = mode.damping,
                std_zeta = mode.damping_std,
                members = mode.members,
                spread = m.frequency_spread,
                "a mode left out as noise"
            );
        } else {
            modes.push(mode);
        }
    }
    Ok((
        modes,
        BandResult {
            poles,
            selection,
            noise,
        },
    ))
}

/// Which member of a cluster a mode is reported from: the one at this quantile of the
/// members' σ_f (see [`with_uncertainty`]).
pub const SIGMA_QUANTILE: f64 = 0.25;

/// A chosen mode with its standard deviations, estimates and σ all from one member pole:
/// the one at the lower quartile ([`SIGMA_QUANTILE`]) of the members' first-order σ_f.
///
/// Across the orders of a cluster the first-order σ is flat where the model is large
/// enough to hold the mode and small enough not to crowd it, and inflated outside: at
/// high orders a spurious pole lies near the mode's, the state matrix is close to
/// defective there and its left eigenvector large. On the measured frame in `tests/data`
/// (0.2 % damping, 5 channels) half the members of the 2.1-Hz mode, the higher orders,
/// give σ_f of 0.01–45 Hz, the other half 0.5–1.3 mHz; the member nearest the median
/// frequency gave a 13.86-Hz mode σ_f = 80 Hz although three setups agree on it to
/// 0.07 %. The lower quartile takes a pole of the flat part while half the members may be
/// inflated, and is not the single smallest σ of the cluster. The reported shape is that
/// pole's, so its σ belongs to it.
fn with_uncertainty(
    m: &super::stabilize::SelectedMode,
    sens: &Sensitivities,
    solves: &Solves,
) -> Result<IdentifiedMode, OmaError> {
    let mut members = Vec::with_capacity(m.member_poles.len());
    for &(o, fo) in &m.member_poles {
        let solve = solve_at(solves, o)?;
        if let Some((_, sf)) = sens
            .frequency_std_near(solve, fo)
            .filter(|(f, _)| (f / fo - 1.0).abs() <= 1e-6)
        {
            members.push((o, fo, sf));
        }
    }
    members.sort_by(|a, b| a.2.total_cmp(&b.2));
    let pick = ((members.len().max(1) - 1) as f64 * SIGMA_QUANTILE).floor() as usize;
    let not_found = || {
        OmaError::Numerical(format!(
            "no pole of the mode at {:.4} Hz is found again for its uncertainty",
            m.pole.frequency_hz
        ))
    };
    let &(order, fo, _) = members.get(pick).ok_or_else(not_found)?;
    let best = sens
        .mode_near(solve_at(solves, order)?, fo)
        .ok_or_else(not_found)?;
    Ok(IdentifiedMode {
        frequency_hz: best.frequency_hz,
        frequency_std: best.frequency_std,
        damping: best.damping,
        damping_std: best.damping_std,
        shape: best.shape,
        shape_std: best.shape_std,
        order,
        members: m.members,
        mpc: m.mpc,
    })
}

/// The eigen-decomposition of every order a chosen mode has a pole at.
fn order_solves(
    modes: &[super::stabilize::SelectedMode],
    sens: &Sensitivities,
) -> Result<Solves, OmaError> {
    let mut orders: Vec<usize> = modes
        .iter()
        .flat_map(|m| m.member_poles.iter().map(|p| p.0))
        .collect();
    orders.sort_unstable();
    orders.dedup();
    orders
        .into_par_iter()
        .map(|o| Ok((o, sens.order(o)?)))
        .collect()
}

/// Eigen-decompositions by order ([`order_solves`]).
type Solves = std::collections::HashMap<usize, super::uncertainty::OrderSolve>;

/// The decomposition of order `o`, which [`order_solves`] computed.
fn solve_at(solves: &Solves, o: usize) -> Result<&super::uncertainty::OrderSolve, OmaError> {
    solves
        .get(&o)
        .ok_or_else(|| OmaError::Numerical(format!("order {o} was not decomposed")))
}

/// The noise rule. A mode of a well-populated cluster is noise when its damping is not
/// resolved (σ_ζ ≥ ζ) and its poles scatter across orders ([`NOISE_SPREAD`]): the scatter,
/// not the first-order σ_f, judges its frequency (on 20 simulated 30-s windows one
/// spurious cluster of 13 of 20 orders had σ_f/f of 0.95 %, under [`NOISE_FREQUENCY_COV`],
/// and a scatter of 0.7 %). A cluster kept only for its share of the orders
/// ([`super::stabilize::SURE_SHARE`]) must have both resolved: on a simulated 300-s record
/// of the lab frame one such cluster at 223 Hz (MPC 0.88, 13 of 44 orders) had σ_ζ < ζ but
/// σ_f/f of 1.9 %, while the true modes that need the share rule had both well resolved.
fn is_noise(m: &IdentifiedMode, cluster: &super::stabilize::SelectedMode) -> bool {
    let damping_unresolved = m.damping_std >= m.damping;
    let frequency_unresolved = m.frequency_std >= NOISE_FREQUENCY_COV * m.frequency_hz;
    if cluster.well_populated {
        damping_unresolved && cluster.frequency_spread >= NOISE_SPREAD
    } else {
        damping_unresolved || frequency_unresolved
    }
}

/// The peaks of the spectrum that no mode explains: none of the modes lies within its
/// half-power band `f (1 ± ζ)` widened by three of its σ_f and by one line of the
/// spectrum (`resolution_hz`) on either side: a Welch peak lies within half a line of its
/// mode, and two modes closer than the Hann window's main lobe show as one peak between
/// them.
pub fn unexplained_peaks(
    peaks: &[Peak],
    modes: &[IdentifiedMode],
    resolution_hz: f64,
) -> Vec<Peak> {
    peaks
        .iter()
        .filter(|p| {
            !modes.iter().any(|m| {
                let reach = m.damping * m.frequency_hz + 3.0 * m.frequency_std + resolution_hz;
                (m.frequency_hz - p.frequency_hz).abs() <= reach
            })
        })
        .copied()
        .collect()
}
