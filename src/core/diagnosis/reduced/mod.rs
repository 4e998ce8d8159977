//! A candidate solved on a reduced basis (step 2 of the workflow, [`super::screen`]): an
//! effect that changes only values of `K` and `M`, at a few DOFs, solved by Rayleigh–Ritz
//! on the fitted model's lowest modes and correction vectors of the DOFs it touches.
//!
//! With `K, M` the fitted model at θ̂, `Φ` its lowest `p` modes (`KΦ = MΦΛ`, `ΦᵀMΦ = I`)
//! and `T` the DOFs where the candidate's `K′ = K + ΔK`, `M′ = M + ΔM` differ from them,
//! the basis is `V = [Φ, C]`. `C` is a block Krylov space of `K⁻¹M` started from
//! `S = K⁻¹E_T − ΦΛ⁻¹Φ_Tᵀ`, the static response to unit loads at `T` less its part along
//! `Φ` (the residual flexibility, the correction vector of modal truncation augmentation):
//! `C = [S, K⁻¹MS, (K⁻¹M)²S, …]` ([`CORRECTION_BLOCKS`] blocks), each block deflated off
//! `Φ`, then made `K`-orthonormal. The projected pencil
//!
//! ```text
//! VᵀK′V = VᵀKV + V_TᵀΔK_TT V_T,    VᵀM′V = VᵀMV + V_TᵀΔM_TT V_T,
//! ```
//!
//! of order `p + |C|` (about 70 for a mass at a node of the space frame, `p` = 60) needs
//! no sparse factorization and no Krylov space of the whole model; its lowest pairs are
//! found as the dense solver finds them. At `ΔK = ΔM = 0` they are the fitted model's
//! modes; a change excites the truncated modes, which the static correction covers in
//! their static part and each further block to a higher order in `λ`. The residual
//! `‖K′φ − λM′φ‖ / ‖K′φ‖` of every pair is measured on the candidate's own matrices. A
//! candidate whose paired modes miss [`STRICT_RESIDUAL`] (the target of the evaluator's
//! own relaxed solves) or any mode [`LOOSE_RESIDUAL`] (enough for pairing) is solved in
//! full, as is one that touches more than [`changes::REDUCED_MAX_TOUCHED`] DOFs.
//!
//! A candidate may renumber the DOFs and add a few: a splice moves a member's mesh nodes
//! to its two parts and adds the hinge's DOF, a support flexibility frees a restrained one.
//! Its DOFs are matched to the fitted model's by label (through the effect's renaming,
//! [`changes`]), and its `s` new DOFs are appended, where the fitted model has no stiffness
//! or mass. Their whole rows are then the change, and the basis is `V = [Φ, C, E_N]` with
//! `E_N` the unit vectors of the new DOFs; the correction `C` covers the fitted model's
//! DOFs that the change couples to them. A new DOF must be coupled to those DOFs (a
//! splice's hinge is), or `K′` would be singular.

mod changes;

use changes::{Changes, mass_values};

use faer::linalg::solvers::DenseSolveCore;
use faer::{Mat, MatRef, Side};

use crate::core::modal::eigen::{
    EigenPairs, LOOSE_RESIDUAL, STRICT_RESIDUAL, sign_convention, symmetrize,
};
use crate::core::modal::solver_for;
use crate::core::model::Model;
use crate::core::updating::residual::candidate_count;
use crate::core::updating::{Evaluation, MeasuredData, Pairing};

/// Largest model the basis is built for: it keeps `K⁻¹` dense (32 MB at 2,000 DOF).
const REDUCED_MAX_DOF: usize = 2000;

/// Blocks of the correction `[S, K⁻¹MS, (K⁻¹M)²S, …]`. Each divides the residuals of the
/// reduced pairs by about 30–100. Measured over both screening rounds of the space frame
/// (the diagnosis of `docs/design/diagnosis.md`, 872 reduced solves), the paired modes'
/// median residual was 1.6e-4 with one block, 1.9e-6 with two, 6e-8 with three; with
/// four, all were below 2.4e-7 and 837 below [`STRICT_RESIDUAL`].
const CORRECTION_BLOCKS: usize = 4;

/// Relative size below which a direction of the correction block is dependent: 1e-12 of
/// the largest eigenvalue of its Gram matrix `CᵀKC`, well above the Gram product's
/// rounding (about 1e-16 of its largest entry).
const DEPENDENT: f64 = 1e-12;

/// Fitted modes in the basis per candidate mode searched for pairing.
const BASE_MODES_PER_CANDIDATE: usize = 2;

/// The fitted model at θ̂ as the reduced solves need it.
pub(super) struct ReducedBasis<'a> {
    model: &'a Model,
    theta: Vec<f64>,
    /// `K(θ̂)` and `M` on the model's union pattern.
    k: Vec<f64>,
    m: Vec<f64>,
    /// The lowest `p` modes (n × p, mass-normalized) and their eigenvalues.
    phi: Mat<f64>,
    lambda: Vec<f64>,
    /// `KΦ` and `MΦ`, formed once: a Ritz vector's `K′φ` and `M′φ` are these and the
    /// correction's products combined by its coefficients, plus the change at its DOFs.
    k_phi: Mat<f64>,
    m_phi: Mat<f64>,
    /// `K(θ̂)⁻¹`, dense.
    flex: Mat<f64>,
    n_cand: usize,
}

/// The correction block `C` (K-orthonormal) and its products `KC`, `MC` with the fitted
/// model's matrices.
struct Correction {
    c: Mat<f64>,
    kc: Mat<f64>,
    mc: Mat<f64>,
}

impl<'a> ReducedBasis<'a> {
    /// The basis of `model` at `theta` for `data`'s candidate count; `None` for a model too
    /// large to keep `K⁻¹` dense, or one whose modes or factor fail.
    pub(super) fn new(model: &'a Model, data: &MeasuredData, theta: &[f64]) -> Option<Self> {
        let n = model.n_dof();
        if n > REDUCED_MAX_DOF {
            return None;
        }
        let n_cand = candidate_count(data.modes.len(), n);
        let p = (BASE_MODES_PER_CANDIDATE * n_cand).min(model.n_finite_modes());
        let eig = solver_for(model).ok()?.solve(model, theta, p).ok()?;
        let mut kd = Mat::zeros(n, n);
        model.stiffness_dense_into(theta, kd.as_mut());
        let flex = kd.llt(Side::Lower).ok()?.inverse();
        let mut k = vec![0.0; model.k0().val().len()];
        model.shifted_stiffness_values(theta, 0.0, &mut k);
        let m = mass_values(model);
        let k_phi = pattern_times(model, &k, eig.phi.as_ref());
        let m_phi = pattern_times(model, &m, eig.phi.as_ref());
        Some(Self {
            model,
            theta: theta.to_vec(),
            k,
            m,
            k_phi,
            m_phi,
            phi: eig.phi,
            lambda: eig.lambda,
            flex,
            n_cand,
        })
    }

    /// The evaluation of `candidate` at θ̂ from a reduced solve, as the fitted model's
    /// evaluator would give it; `None` when the candidate must be solved in full.
    /// `relabel` gives a DOF label of the fitted model as the candidate labels it.
    pub(super) fn evaluate(
        &self,
        candidate: &Model,
        data: &MeasuredData,
        relabel: &dyn Fn(&str) -> String,
    ) -> Option<Evaluation> {
        let map = self.dof_map(candidate, relabel)?;
        let ch = self.changes(candidate, &map)?;
        let c = self.k_orthonormal(self.corrections(ch.t_old()))?;
        let (a, b) = self.projected(&ch, &c);
        let (lambda, y) = lowest_pairs(a, b, self.n_cand)?;
        let (phi, products) = self.ritz_vectors(&c, &y, map.new);
        // (The residuals do not depend on the signs the convention then sets.)
        let residual = residuals(products, &ch, phi.as_ref(), &lambda);
        let mut phi = if map.is_identity() {
            phi
        } else {
            Mat::from_fn(candidate.n_dof(), phi.ncols(), |j, k| phi[(map.ext[j], k)])
        };
        sign_convention(&mut phi);
        let pairs = EigenPairs { lambda, phi };
        let ev = Evaluation::of_pairs(candidate, data, &self.theta, pairs, Pairing::default());
        let exact = ev.pairing.iter().all(|&k| residual[k] <= STRICT_RESIDUAL)
            && residual.iter().all(|&r| r <= LOOSE_RESIDUAL);
        exact.then_some(ev)
    }

    /// The Ritz vectors `V y` of the reduced pairs (the fitted model's DOFs, then the `new`
    /// ones), with their products `(KV y, MV y)` with the fitted model's matrices (nothing
    /// at the new DOFs).
    fn ritz_vectors(
        &self,
        cor: &Correction,
        y: &Mat<f64>,
        new: usize,
    ) -> (Mat<f64>, (Mat<f64>, Mat<f64>)) {
        let (n, p, q) = (self.phi.nrows(), self.lambda.len(), cor.c.ncols());
        let (yp, yc) = (y.subrows(0, p), y.subrows(p, q));
        let extend = |top: Mat<f64>, tail: Option<MatRef<'_, f64>>| {
            Mat::from_fn(n + new, y.ncols(), |i, k| match (i < n, tail) {
                (true, _) => top[(i, k)],
                (false, Some(t)) => t[(i - n, k)],
                (false, None) => 0.0,
            })
        };
        let phi = self.phi.as_ref() * yp + cor.c.as_ref() * yc;
        let kphi = &self.k_phi * yp + &cor.kc * yc;
        let mphi = &self.m_phi * yp + &cor.mc * yc;
        if new == 0 {
            return (phi, (kphi, mphi));
        }
        let tail = y.subrows(p + q, new);
        let products = (extend(kphi, None), extend(mphi, None));
        (extend(phi, Some(tail)), products)
    }

    /// `S = K⁻¹E_T − ΦΛ⁻¹Φ_Tᵀ`: the static response to unit loads at `t` less its part
    /// along `Φ` (module docs).
    fn static_correction(&self, t: &[usize]) -> Mat<f64> {
        let n = self.phi.nrows();
        let p = self.lambda.len();
        let g = Mat::from_fn(p, t.len(), |k, a| self.phi[(t[a], k)] / self.lambda[k]);
        let mut s = Mat::from_fn(n, t.len(), |i, a| self.flex[(i, t[a])]);
        s -= self.phi.as_ref() * g.as_ref();
        s
    }

    /// The correction block `[S, K⁻¹MS, (K⁻¹M)²S, …]` ([`CORRECTION_BLOCKS`] blocks), each
    /// block deflated off `Φ` (`X − ΦΦᵀMX`; `S` is already) and its columns scaled to unit
    /// length.
    fn corrections(&self, t: &[usize]) -> Mat<f64> {
        let (n, r) = (self.phi.nrows(), t.len());
        let mut c = Mat::zeros(n, CORRECTION_BLOCKS * r);
        let mut block = self.static_correction(t);
        for d in 0..CORRECTION_BLOCKS {
            for a in 0..r {
                let norm = block.col(a).norm_l2();
                if norm > 0.0 {
                    c.col_mut(d * r + a)
                        .iter_mut()
                        .zip(block.col(a).iter())
                        .for_each(|(ci, &bi)| *ci = bi / norm);
                }
            }
            if d + 1 < CORRECTION_BLOCKS {
                let mx = pattern_times(self.model, &self.m, c.subcols(d * r, r));
                block = self.flex.as_ref() * mx;
                let mb = pattern_times(self.model, &self.m, block.as_ref());
                block -= self.phi.as_ref() * (self.phi.transpose() * mb);
            }
        }
        c
    }

    /// `C` made `K`-orthonormal (the fitted model's `K`), directions of `CᵀKC` below
    /// [`DEPENDENT`] of its largest dropped: the later blocks converge towards the same
    /// truncated modes and become nearly dependent. With it, `KC` and `MC`.
    fn k_orthonormal(&self, c: Mat<f64>) -> Option<Correction> {
        let kc = pattern_times(self.model, &self.k, c.as_ref());
        let mut g = c.transpose() * &kc;
        symmetrize(&mut g);
        let evd = g.self_adjoint_eigen(Side::Lower).ok()?;
        let sv = evd.S().column_vector();
        let top = (0..sv.nrows()).map(|i| sv[i]).fold(0.0, f64::max);
        let keep: Vec<usize> = (0..sv.nrows())
            .filter(|&i| sv[i] > DEPENDENT * top)
            .collect();
        if keep.is_empty() {
            return None;
        }
        let u = Mat::from_fn(sv.nrows(), keep.len(), |i, j| {
            evd.U()[(i, keep[j])] / sv[keep[j]].sqrt()
        });
        let c = c * &u;
        let mc = pattern_times(self.model, &self.m, c.as_ref());
        Some(Correction { kc: kc * u, c, mc })
    }

    /// The projected pencil `(VᵀK′V, VᵀM′V)`, `V = [Φ, C, E_N]` (module docs).
    fn projected(&self, ch: &Changes, cor: &Correction) -> (Mat<f64>, Mat<f64>) {
        let c = &cor.c;
        let (p, r, q) = (self.lambda.len(), ch.t.len(), c.ncols());
        let (n, new) = (self.phi.nrows(), ch.t.len() - ch.old);
        let w = Mat::from_fn(r, p + q + new, |a, col| {
            let i = ch.t[a];
            match (i < n, col < p, col < p + q) {
                (true, true, _) => self.phi[(i, col)],
                (true, false, true) => c[(i, col - p)],
                (false, _, _) if col == p + q + (i - n) => 1.0,
                _ => 0.0,
            }
        });
        let mut a = w.transpose() * ch.dk.as_ref() * w.as_ref();
        let mut b = w.transpose() * ch.dm.as_ref() * w.as_ref();
        let ckc = c.transpose() * &cor.kc;
        let cmc = c.transpose() * &cor.mc;
        let pkc = self.phi.transpose() * &cor.kc;
        let pmc = self.phi.transpose() * &cor.mc;
        for k in 0..p {
            a[(k, k)] += self.lambda[k];
            b[(k, k)] += 1.0;
            for j in 0..q {
                a[(k, p + j)] += pkc[(k, j)];
                a[(p + j, k)] += pkc[(k, j)];
                b[(k, p + j)] += pmc[(k, j)];
                b[(p + j, k)] += pmc[(k, j)];
            }
        }
        for i in 0..q {
            for j in 0..q {
                a[(p + i, p + j)] += ckc[(i, j)];
                b[(p + i, p + j)] += cmc[(i, j)];
            }
        }
        symmetrize(&mut a);
        symmetrize(&mut b);
        (a, b)
    }
}

/// `A X` for the values `a` of a matrix on the model's union pattern (stored in full).
fn pattern_times(model: &Model, a: &[f64], x: MatRef<'_, f64>) -> Mat<f64> {
    let pattern = model.k0().symbolic();
    let (col_ptr, row_idx) = (pattern.col_ptr(), pattern.row_idx());
    let mut y = Mat::zeros(x.nrows(), x.ncols());
    for c in 0..x.ncols() {
        for j in 0..x.nrows() {
            let xj = x[(j, c)];
            if xj == 0.0 {
                continue;
            }
            for e in col_ptr[j]..col_ptr[j + 1] {
                y[(row_idx[e], c)] += a[e] * xj;
            }
        }
    }
    y
}

/// The lowest `want` pairs of the pencil `(a, b)`, `a` definite, `yᵀby = 1`: in the inverse
/// form of the dense solver, the largest `μ = 1/λ` of `L⁻¹bL⁻ᵀ` with `a = LLᵀ`;
/// `None` when `a` is not definite or a wanted `μ` is not positive.
fn lowest_pairs(a: Mat<f64>, b: Mat<f64>, want: usize) -> Option<(Vec<f64>, Mat<f64>)> {
    let order = a.nrows();
    if want > order {
        return None;
    }
    let llt = a.llt(Side::Lower).ok()?;
    let l = llt.L();
    let mut c = b;
    l.solve_lower_triangular_in_place(c.as_mut());
    let mut c = c.transpose().to_owned();
    l.solve_lower_triangular_in_place(c.as_mut());
    symmetrize(&mut c);
    let evd = c.self_adjoint_eigen(Side::Lower).ok()?;
    let (mu, u) = (evd.S().column_vector(), evd.U());
    let mut lambda = Vec::with_capacity(want);
    let mut y = Mat::zeros(order, want);
    for j in 0..want {
        let col = order - 1 - j;
        let m = mu[col];
        if m.is_nan() || m <= 0.0 {
            return None;
        }
        lambda.push(m.recip());
        let scale = m.sqrt().recip();
        for i in 0..order {
            y[(i, j)] = u[(i, col)] * scale;
        }
    }
    l.transpose().solve_upper_triangular_in_place(y.as_mut());
    Some((lambda, y))
}

/// `‖K′φ − λM′φ‖ / ‖K′φ‖` of each pair on the candidate's own matrices (condensed onto the
/// fitted model's DOFs), from `(Kφ, Mφ)` with the fitted model's matrices plus the changes.
fn residuals(
    (mut kphi, mut mphi): (Mat<f64>, Mat<f64>),
    ch: &Changes,
    phi: MatRef<'_, f64>,
    lambda: &[f64],
) -> Vec<f64> {
    let phi_t = Mat::from_fn(ch.t.len(), phi.ncols(), |a, c| phi[(ch.t[a], c)]);
    let (dkphi, dmphi) = (
        ch.dk.as_ref() * phi_t.as_ref(),
        ch.dm.as_ref() * phi_t.as_ref(),
    );
    for (a, &i) in ch.t.iter().enumerate() {
        for c in 0..phi.ncols() {
            kphi[(i, c)] += dkphi[(a, c)];
            mphi[(i, c)] += dmphi[(a, c)];
        }
    }
    (0..phi.ncols())
        .map(|c| {
            let (mut num, mut den) = (0.0, 0.0);
            for i in 0..phi.nrows() {
                let kp = kphi[(i, c)];
                num += (kp - lambda[c] * mphi[(i, c)]).powi(2);
                den += kp * kp;
            }
            (num / den).sqrt()
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::diagnosis::fixtures::{NOISE, lab, space_frame, spread_theta};
    use crate::core::diagnosis::{Description, effects};
    use crate::core::simulate::simulated_measured_data;
    use crate::core::updating::Evaluator;

    /// The lab frame with `kind@location = u`.
    fn with(spec: &Description, kind: &str, location: &str, u: f64) -> Model {
        let mut s = spec.clone();
        effects::by_kind(kind)
            .unwrap()
            .apply(&mut s, location, u)
            .unwrap();
        s.build().unwrap()
    }

    /// The reduced evaluation of `candidate` against its full one: the same pairing, the
    /// paired eigenvalues to 1e-9 and the residual to 1e-5 σ. A reduced pair is accepted at
    /// a relative residual of 1e-7, which puts its eigenvalue within ~1e-14 and its shape
    /// within ~1e-7 of the exact ones; the full solve's own residuals are of the same order,
    /// and a shape error of 1e-7 is 2e-6 of the 5 % shape σ.
    fn assert_agrees(reduced: &Evaluation, candidate: &Model, data: &MeasuredData, what: &str) {
        let full = Evaluator::new(candidate)
            .unwrap()
            .evaluate(candidate, data, &reduced.theta)
            .unwrap();
        assert_eq!(reduced.pairing, full.pairing, "{what}");
        for &k in &full.pairing {
            let (a, b) = (reduced.eig.lambda[k], full.eig.lambda[k]);
            assert!((a / b - 1.0).abs() < 1e-9, "{what}: λ{k}");
        }
        for (a, b) in reduced.r.iter().zip(&full.r) {
            assert!((a - b).abs() < 1e-5, "{what}: r {a} vs {b}");
        }
    }

    /// The DOF labels as `kind@location` renames them.
    fn relabel<'a>(
        spec: &'a Description,
        kind: &str,
        location: &'a str,
    ) -> impl Fn(&str) -> String + 'a {
        let effect = effects::by_kind(kind).unwrap();
        move |label: &str| effect.dof_label_after(spec, location, label)
    }

    /// Each reduced solve gives the evaluation a full solve gives ([`assert_agrees`]), for
    /// changes at the fitted model's DOFs and for a support flexibility, which adds one. The
    /// changes are a finite-difference step, which must be reduced, and 30 steps, as the
    /// screening's probes make, which may be solved in full instead (a member 60 % stiffer
    /// is).
    #[test]
    fn reduced_solves_agree_with_full_solves() {
        let spec = lab();
        let model = spec.build().unwrap();
        let theta = spread_theta(&model);
        let data = simulated_measured_data(&model, &theta, 9, NOISE, true, 4).unwrap();
        let basis = ReducedBasis::new(&model, &data, &theta).expect("the lab frame is small");
        let cases = [
            ("added-mass", "B2.3"),
            ("member-stiffness", "C1L"),
            ("axial-force", "C1L"),
            ("joint-inertia", "J1L"),
            // Frees the restrained rotation: a DOF the fitted model does not have.
            ("support-flexibility", "BL.rz"),
        ];
        let mut reduced_count = 0;
        for (kind, location) in cases {
            let h = effects::by_kind(kind).unwrap().step(&spec, location);
            for u in [h, 30.0 * h] {
                let candidate = with(&spec, kind, location, u);
                if kind == "support-flexibility" {
                    assert_eq!(candidate.n_dof(), model.n_dof() + 1, "BL.rz is restrained");
                }
                let same = relabel(&spec, kind, location);
                let Some(reduced) = basis.evaluate(&candidate, &data, &same) else {
                    // A large change may miss the residual target: then it is solved in
                    // full. A step's change must not.
                    assert!(u != h, "{kind}@{location}={u}: no reduced solve");
                    continue;
                };
                reduced_count += 1;
                assert_agrees(
                    &reduced,
                    &candidate,
                    &data,
                    &format!("{kind}@{location}={u}"),
                );
            }
        }
        assert!(reduced_count >= 8, "{reduced_count} of 10 changes reduced");
    }

    /// A splice renumbers the DOFs (the member's mesh nodes move to its parts) and adds the
    /// hinge's: matched by the effect's renaming, it is solved on the reduced basis and
    /// agrees with the full solve, on a beam of the plane lab frame and on the space frame;
    /// without the renaming the DOFs do not match and it is solved in full. (On the lab
    /// frame's columns the lowest mode's residual stays at 1–2e-7 however stiff the
    /// splice, just above [`STRICT_RESIDUAL`]: those are solved in full.)
    #[test]
    fn a_splice_is_matched_by_its_renaming_and_reduced() {
        for (spec, location) in [(lab(), "B2.3"), (space_frame(), "BX21a.3.weak")] {
            let model = spec.build().unwrap();
            let theta = model.nominal_theta();
            let data = simulated_measured_data(&model, &theta, 9, NOISE, false, 1).unwrap();
            let basis = ReducedBasis::new(&model, &data, &theta).unwrap();
            let h = effects::by_kind("splice").unwrap().step(&spec, location);
            let candidate = with(&spec, "splice", location, h);
            let renamed = relabel(&spec, "splice", location);
            let map = basis
                .dof_map(&candidate, &renamed)
                .expect("every DOF matched");
            assert_eq!(
                (map.new, candidate.n_dof()),
                (1, model.n_dof() + 1),
                "{location}"
            );
            let reduced = basis
                .evaluate(&candidate, &data, &renamed)
                .expect("reduced");
            assert_agrees(&reduced, &candidate, &data, location);
            let unchanged = |label: &str| label.to_string();
            assert!(basis.evaluate(&candidate, &data, &unchanged).is_none());
        }
    }
}
