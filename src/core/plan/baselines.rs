//! What a placement is judged against: effective independence (Kammer 1991) and random
//! placements of the same size.
//!
//! Effective independence keeps the channels that best span the target modes. With `Φ`
//! the target modes' shapes at the channels (one row per channel), the Fisher information
//! of the modal coordinates is `A = ΦᵀΦ`, and channel `i`'s share of it is
//! `E_i = φ_iᵀ A⁻¹ φ_i`, the diagonal of the projector `Φ A⁻¹ Φᵀ` (Kammer 1991, eq. 12;
//! the shares sum to the number of modes). Starting from every candidate, the channel
//! of smallest share is removed, one at a time, until the wanted number is left; the
//! installed channels are kept throughout. Scaling a mode's column (its noise, its
//! normalisation) leaves the projector, so the choice, unchanged.

use anyhow::{Result, bail};
use faer::linalg::solvers::Solve;
use faer::{Mat, Side};
use rand::SeedableRng;
use rand::seq::IndexedRandom;

use super::Planner;

impl Planner {
    /// Effective independence: `n` of `candidates` added to `current` for the modes
    /// `modes` (module docs). Fails when the channels cannot span the modes.
    pub fn effective_independence(
        &self,
        current: &[usize],
        candidates: &[usize],
        modes: &[usize],
        n: usize,
    ) -> Result<Vec<usize>> {
        let mut left: Vec<usize> = candidates
            .iter()
            .copied()
            .filter(|c| !current.contains(c))
            .collect();
        while left.len() > n {
            let rows: Vec<usize> = current.iter().chain(&left).copied().collect();
            let share = self.independence(&rows, modes)?;
            let worst = (current.len()..rows.len())
                .min_by(|&a, &b| share[a].total_cmp(&share[b]))
                .expect("a candidate is left");
            left.remove(worst - current.len());
        }
        Ok(left)
    }

    /// Each channel's share `E_i = φ_iᵀ (ΦᵀΦ)⁻¹ φ_i` of the information on the modes.
    pub fn independence(&self, channels: &[usize], modes: &[usize]) -> Result<Vec<f64>> {
        let phi = Mat::from_fn(channels.len(), modes.len(), |i, j| {
            self.modes[modes[j]].shape[channels[i]]
        });
        let a = phi.transpose() * &phi;
        let Ok(llt) = a.llt(Side::Lower) else {
            bail!(
                "{} channels do not span the {} modes: effective independence needs them to",
                channels.len(),
                modes.len()
            );
        };
        let mut x = phi.transpose().to_owned();
        llt.solve_in_place(x.as_mut());
        Ok((0..channels.len())
            .map(|i| (0..modes.len()).map(|j| phi[(i, j)] * x[(j, i)]).sum())
            .collect())
    }

    /// The worst relative σ of the connections for each of `count` placements of `n`
    /// channels drawn at random from `candidates` (not in `current`), added to `current`;
    /// the draws are the same for the same `seed`.
    pub fn random_placements(
        &mut self,
        current: &[usize],
        candidates: &[usize],
        modes: &[usize],
        n: usize,
        count: usize,
        seed: u64,
    ) -> Result<Vec<f64>> {
        let free: Vec<usize> = candidates
            .iter()
            .copied()
            .filter(|c| !current.contains(c))
            .collect();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        (0..count)
            .map(|_| {
                let mut channels = current.to_vec();
                channels.extend(free.choose_multiple(&mut rng, n));
                let sigma = self.sigma(&channels, modes)?;
                Ok(self.worst(&sigma).0)
            })
            .collect()
    }
}
