//! The mode-matching residual and its exact Jacobian.
//!
//! With `W = Σ_M⁻¹` diagonal, the objective (5) is `ε = ‖r‖²` for the whitened residual
//! `r = W^{1/2} e`, where `e` is (6): per measured mode `m` paired with model mode `k_m` by
//! (29), `λ̂_m − λ_{k_m}` and `ψ̂^{(m)} − c_m D φ_{k_m}` with the scale factor (7)
//! `c_m = ψ̂ᵀ D φ / ‖D φ‖²` over the measured entries. The Jacobian `J = ∂r/∂θ = −W^{1/2} S`
//! differentiates the residual that is minimized, including `c_m(θ)`:
//! `∂(c D φ) = c D ∂φ + (∂c) D φ`, `∂c = (ψ̂ − 2c Dφ)ᵀ D ∂φ / ‖Dφ‖²`.

use std::sync::atomic::{AtomicUsize, Ordering};

use faer::Mat;

use super::data::{MeasuredData, TargetMode, TargetShape};
use crate::core::modal::eigen::{STRICT_RESIDUAL, WarmBlock};
use crate::core::modal::{
    EigenPairs, EigenSolver, ModalError, Nelson, SPARSE_FROM_DOF, SharedStiffness, solver_for,
};
use crate::core::model::{Channel, Model};
use pairing::{candidate_readings, gather, pair_mode};

mod pairing;

/// The residual at one θ.
#[derive(Debug, Clone)]
pub struct Evaluation {
    pub theta: Vec<f64>,
    /// Candidate model modes (the lowest few, ascending).
    pub eig: EigenPairs,
    /// Model mode (0-based) paired with each measured mode, (29).
    pub pairing: Vec<usize>,
    /// MAC of each measured shape with its paired model mode (NaN without a shape).
    pub mac: Vec<f64>,
    /// Scale factor (7) per measured mode (NaN without a shape).
    pub scale: Vec<f64>,
    /// Whitened residual `r = W^{1/2} e`.
    pub r: Vec<f64>,
    /// ε (5) = ‖r‖².
    pub epsilon: f64,
}

impl Evaluation {
    /// Model frequency (Hz) paired with measured mode `m`.
    pub fn model_hz(&self, m: usize) -> f64 {
        self.eig.frequency_hz(self.pairing[m])
    }
}

/// How measured modes are paired with model modes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Pairing {
    /// Paper (29): the candidate of highest MAC (the nearest eigenvalue for a mode measured
    /// without a shape). Where two model modes cross or veer, the MAC of a measured shape
    /// with them changes places and ε jumps between the two pairings.
    #[default]
    Mac,
    /// The candidate that contributes least to ε (5): its eigenvalue term plus its shape
    /// term with the optimal scale (7), the same weighted residual the fit minimizes. The
    /// pairing is then part of the minimization (ε is the least of the candidates'
    /// misfits, the lower envelope of functions smooth in θ), so ε is continuous through a
    /// crossing or a veering, where the highest-MAC rule jumps. For a mode without a
    /// shape both rules take the nearest eigenvalue.
    Misfit,
}

/// Workspaces sharing a small model's Nelson solves. On the lab frame (142 DOF, 9 paired
/// modes, ~50 µs each) two cut that part of a warm update from ~460 to ~260 µs; more
/// would spend in hand-offs what they save.
pub const SMALL_MODEL_THREADS: usize = 2;

/// Evaluates residuals and Jacobians for one model, reusing its solvers and buffers.
///
/// It also remembers the eigenpairs and the per-mode sensitivities of the last θ it saw:
/// a tracker's next update starts at the θ where the last one ended, so its first eigen
/// solve and most of its first Jacobian are already done. Both depend on θ alone (the data
/// enter only afterwards), and the solvers are deterministic, so a remembered result is
/// bit for bit the one a fresh evaluator would compute (with warm starts off; with them on,
/// the one the last solve gave, see [`Evaluator::set_warm_start`]).
pub struct Evaluator {
    eigen: Box<dyn EigenSolver + Send>,
    /// Nelson workspaces, one per core (at most [`SMALL_MODEL_THREADS`] for a model the
    /// dense solver takes, four for a larger one), each on its own thread taking the next
    /// paired mode not yet differentiated ([`Evaluator::differentiate`]).
    nelson: Vec<NelsonWorkspace>,
    /// θ, candidate count and eigenpairs of the last solve.
    last_eig: Option<(Vec<f64>, usize, EigenPairs)>,
    /// θ and, per model mode, ∂λ and ∂φ at the channels, of the last Jacobian.
    last_sensitivities: Option<(Vec<f64>, Vec<Option<Sensitivity>>)>,
    /// Eigen solves start from the last solve's block ([`Evaluator::set_warm_start`]).
    warm: bool,
    pairing: Pairing,
}

impl Evaluation {
    /// The residual at θ of eigenpairs solved elsewhere (all of them candidates for
    /// pairing), paired by `rule`: what [`Evaluator::evaluate`] returns for the same pairs.
    pub fn of_pairs(
        model: &Model,
        data: &MeasuredData,
        theta: &[f64],
        eig: EigenPairs,
        rule: Pairing,
    ) -> Self {
        let n_cand = eig.lambda.len();
        residual_at(model, data, theta, eig, n_cand, rule)
    }
}

/// ∂λ_k (per parameter) and ∂φ_k at every channel (channels × parameters).
type Sensitivity = (Vec<f64>, Mat<f64>);

/// One share's sensitivities: each model mode (0-based) with its [`Sensitivity`].
type ModeResult = Result<Sensitivity, ModalError>;

/// Number of model modes searched for pairing partners: twice the measured count, and at
/// least ten more (the paper's Fig. 13 pairs measured mode 9 with model mode 13).
pub fn candidate_count(n_measured: usize, n_dof: usize) -> usize {
    (2 * n_measured).max(n_measured + 10).min(n_dof)
}

impl Evaluator {
    /// The eigen solver [`solver_for`] picks for `model`, and Nelson's method.
    pub fn new(model: &Model) -> Result<Self, ModalError> {
        Self::with_solver(model, solver_for(model)?)
    }

    /// Uses the given eigen solver.
    pub fn with_solver(
        model: &Model,
        eigen: Box<dyn EigenSolver + Send>,
    ) -> Result<Self, ModalError> {
        Ok(Self {
            eigen,
            nelson: {
                let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
                let threads = if model.n_dof() >= SPARSE_FROM_DOF {
                    cores.min(4)
                } else {
                    cores.min(SMALL_MODEL_THREADS)
                };
                let k_theta = SharedStiffness::default();
                (0..threads)
                    .map(|_| NelsonWorkspace::new(model, k_theta.clone()))
                    .collect::<Result<_, _>>()?
            },
            last_eig: None,
            last_sensitivities: None,
            warm: false,
            pairing: Pairing::default(),
        })
    }

    /// The pairing rule of every evaluation from now on.
    pub fn set_pairing(&mut self, pairing: Pairing) {
        self.pairing = pairing;
    }

    pub fn pairing(&self) -> Pairing {
        self.pairing
    }

    /// Warm eigen solves (a tracker's): each solve starts from the Ritz block of the last
    /// one, by subspace iteration, when the solver supports it and θ is near
    /// ([`EigenSolver::solve_warm`]); a paired mode whose residual is above
    /// [`STRICT_RESIDUAL`] is solved again cold. The result then depends on the previous
    /// solve too (within those residuals), so a checkpoint keeps the block
    /// ([`Evaluator::warm_state`]) for a resume to continue bit for bit.
    pub fn set_warm_start(&mut self, on: bool) {
        self.warm = on;
        self.eigen.set_warm(on);
    }

    /// Whether solves start warm ([`Evaluator::set_warm_start`]).
    pub fn warm(&self) -> bool {
        self.warm
    }

    /// The block the next warm solve starts from (that of the last solve).
    pub fn warm_state(&self) -> Option<WarmBlock> {
        self.eigen.warm_block().cloned()
    }

    /// Restores [`Evaluator::warm_state`]: the next solve starts from the block, and an
    /// evaluation at its θ returns its pairs, as in the run that wrote it.
    pub fn restore_warm_state(&mut self, block: WarmBlock) {
        self.last_eig = Some((block.theta.clone(), block.n_modes, block.pairs()));
        self.last_sensitivities = None;
        self.eigen.set_warm_block(Some(block));
    }

    /// The residual at θ with pairing (29) redone.
    pub fn evaluate(
        &mut self,
        model: &Model,
        data: &MeasuredData,
        theta: &[f64],
    ) -> Result<Evaluation, ModalError> {
        let n_cand = candidate_count(data.modes.len(), model.n_dof());
        if let Some((t, n, eig)) = &self.last_eig
            && t == theta
            && *n == n_cand
        {
            return Ok(residual_at(
                model,
                data,
                theta,
                eig.clone(),
                n_cand,
                self.pairing,
            ));
        }
        // Modes that must be exact in a warm or relaxed solve: as many as there are measured modes
        // (they usually pair with the lowest); any other mode that gets paired is checked
        // below.
        let strict = data.modes.len().min(n_cand);
        let warm = if self.warm {
            self.eigen.solve_warm(model, theta, n_cand, strict)?
        } else {
            None
        };
        // Otherwise a relaxed solve, where the solver has one (the sparse solver: the modes
        // beyond the measured ones only to pairing accuracy).
        let quick = match warm {
            Some(w) => Some(w),
            None => self.eigen.solve_relaxed(model, theta, n_cand, strict)?,
        };
        let ev = match quick {
            Some((eig, residual)) => {
                let ev = residual_at(model, data, theta, eig, n_cand, self.pairing);
                if ev.pairing.iter().all(|&k| residual[k] <= STRICT_RESIDUAL) {
                    ev
                } else {
                    let eig = self.eigen.solve(model, theta, n_cand)?;
                    residual_at(model, data, theta, eig, n_cand, self.pairing)
                }
            }
            None => {
                let eig = self.eigen.solve(model, theta, n_cand)?;
                residual_at(model, data, theta, eig, n_cand, self.pairing)
            }
        };
        self.last_eig = Some((theta.to_vec(), n_cand, ev.eig.clone()));
        Ok(ev)
    }

    /// `J = ∂r/∂θ` (N × N_θ) at the evaluation's θ and pairing: `−W^{1/2} S`.
    pub fn jacobian(
        &mut self,
        model: &Model,
        data: &MeasuredData,
        ev: &Evaluation,
    ) -> Result<Mat<f64>, ModalError> {
        let cache = self.sensitivities(model, ev)?;
        Ok(assemble_jacobian(model, data, ev, cache))
    }

    /// ∂λ and ∂φ at every channel of every paired model mode of `ev` (indexed by model
    /// mode), the ones remembered from the last Jacobian at the same θ reused and the others
    /// differentiated; remembered for the next Jacobian.
    fn sensitivities(
        &mut self,
        model: &Model,
        ev: &Evaluation,
    ) -> Result<&[Option<Sensitivity>], ModalError> {
        // Sensitivities per distinct paired model mode: ∂λ (p) and ∂φ at every channel.
        let mut cache: Vec<Option<Sensitivity>> = match self.last_sensitivities.take() {
            Some((t, c)) if t == ev.theta && c.len() == ev.eig.lambda.len() => c,
            _ => vec![None; ev.eig.lambda.len()],
        };
        // The distinct paired modes not yet differentiated, dealt to the workspaces.
        let mut todo: Vec<usize> = ev
            .pairing
            .iter()
            .copied()
            .filter(|&k| cache[k].is_none())
            .collect();
        todo.sort_unstable();
        todo.dedup();
        for (k, sens) in todo.iter().zip(self.differentiate(model, ev, &todo)) {
            cache[*k] = Some(sens?);
        }
        Ok(self
            .last_sensitivities
            .insert((ev.theta.clone(), cache))
            .1
            .as_slice())
    }

    /// Nelson's method (paper (18)–(19)) for the model modes `todo` of `ev`: one result
    /// per mode, in the order of `todo`. The modes are dealt one at a time to whichever
    /// workspace is free: this thread starts at once and the helper threads join when they
    /// wake, so a helper that starts late costs at most the mode it is on (each mode's
    /// result does not depend on the workspace that computes it).
    fn differentiate(&mut self, model: &Model, ev: &Evaluation, todo: &[usize]) -> Vec<ModeResult> {
        let next = AtomicUsize::new(0);
        let deal = |ws: &mut NelsonWorkspace| -> Vec<(usize, ModeResult)> {
            std::iter::from_fn(|| {
                let i = next.fetch_add(1, Ordering::Relaxed);
                todo.get(i).map(|&k| (i, ws.mode(model, ev, k)))
            })
            .collect()
        };
        let workers = self.nelson.len().min(todo.len()).max(1);
        let (first, rest) = self.nelson[..workers]
            .split_first_mut()
            .expect("at least one workspace");
        let mut dealt: Vec<Vec<(usize, ModeResult)>> = (0..workers).map(|_| Vec::new()).collect();
        let (mine, theirs) = dealt.split_first_mut().expect("at least one worker");
        match crate::core::helpers() {
            Some(pool) if workers > 1 => pool.in_place_scope(|scope| {
                for (ws, slot) in rest.iter_mut().zip(theirs.iter_mut()) {
                    let deal = &deal;
                    scope.spawn(move |_| *slot = deal(ws));
                }
                *mine = deal(first);
            }),
            _ => *mine = deal(first),
        }
        let mut results: Vec<(usize, ModeResult)> = dealt.into_iter().flatten().collect();
        results.sort_unstable_by_key(|&(i, _)| i);
        debug_assert_eq!(results.len(), todo.len());
        results.into_iter().map(|(_, r)| r).collect()
    }
}

/// `J = −W^{1/2} S` from the sensitivities of the paired model modes (`cache`, indexed by
/// model mode): per measured mode, its eigenvalue row and then its shape rows.
fn assemble_jacobian(
    model: &Model,
    data: &MeasuredData,
    ev: &Evaluation,
    cache: &[Option<Sensitivity>],
) -> Mat<f64> {
    let p = model.n_params();
    let channels = model.channels();
    let mut jac = Mat::zeros(data.n_data(), p);
    let mut row = 0;
    let mut dp = Vec::new();
    for (m, mode) in data.modes.iter().enumerate() {
        let k = ev.pairing[m];
        let (dl, dch) = cache[k]
            .as_ref()
            .expect("every paired mode was differentiated");
        for l in 0..p {
            jac[(row, l)] = -dl[l] / mode.sigma_lambda;
        }
        row += 1;
        if let Some(s) = &mode.shape {
            read_channels(&ev.eig, k, &s.channels, channels, &mut dp);
            shape_rows(&mut jac, row, s, ev.scale[m], dch, &dp);
            row += s.channels.len();
        }
    }
    jac
}

/// The shape rows of `J` from `row` on for a measured shape `s` with scale factor `c` (7),
/// model readings `dp = Dφ` at its channels and `dch = ∂φ` at every channel: the derivative
/// of `−(ψ̂ − c Dφ)/σ` including `∂c`.
fn shape_rows(jac: &mut Mat<f64>, row: usize, s: &TargetShape, c: f64, dch: &Mat<f64>, dp: &[f64]) {
    let p = jac.ncols();
    let norm2: f64 = dp.iter().map(|v| v * v).sum();
    // ∂c = (ψ̂ − 2c Dφ)ᵀ D∂φ / ‖Dφ‖²
    let weight: Vec<f64> = s
        .values
        .iter()
        .zip(dp)
        .map(|(psi, d)| (psi - 2.0 * c * d) / norm2)
        .collect();
    for l in 0..p {
        let dcol = dch.col(l);
        let dc: f64 = s
            .channels
            .iter()
            .zip(&weight)
            .map(|(&ch, w)| w * dcol[ch])
            .sum();
        let jcol = jac
            .col_mut(l)
            .try_as_col_major_mut()
            .expect("owned matrix columns are contiguous")
            .as_slice_mut();
        for (i, ((&ch, &d), sd)) in s.channels.iter().zip(dp).zip(&s.sigma).enumerate() {
            jcol[row + i] = -(c * dcol[ch] + dc * d) / sd;
        }
    }
}

/// One thread's Nelson workspace and buffers.
struct NelsonWorkspace {
    nelson: Nelson,
    /// The DOFs the channels read (ascending, each once), and per channel its terms as
    /// (position in `rows`, weight), in the channel's order.
    rows: Vec<usize>,
    terms: Vec<Vec<(usize, f64)>>,
    /// ∂φ on `rows`.
    dphi_rows: Mat<f64>,
    dlambda: Vec<f64>,
    phi: Vec<f64>,
}

impl NelsonWorkspace {
    fn new(model: &Model, k_theta: SharedStiffness) -> Result<Self, ModalError> {
        let channels = model.channels();
        let mut rows: Vec<usize> = channels
            .iter()
            .flat_map(|ch| ch.dofs.iter().map(|&(i, _)| i))
            .collect();
        rows.sort_unstable();
        rows.dedup();
        let terms = channels
            .iter()
            .map(|ch| {
                let at = |i: usize| rows.binary_search(&i).expect("every channel DOF is a row");
                ch.dofs.iter().map(|&(i, w)| (at(i), w)).collect()
            })
            .collect();
        Ok(Self {
            nelson: Nelson::sharing(model, k_theta)?,
            dphi_rows: Mat::zeros(rows.len(), model.n_params()),
            rows,
            terms,
            dlambda: vec![0.0; model.n_params()],
            phi: vec![0.0; model.n_dof()],
        })
    }

    /// ∂λ and ∂φ at every channel of the model mode `k` (0-based) of `ev`.
    fn mode(&mut self, model: &Model, ev: &Evaluation, k: usize) -> ModeResult {
        let p = model.n_params();
        for (i, v) in self.phi.iter_mut().enumerate() {
            *v = ev.eig.phi[(i, k)];
        }
        self.nelson.derivatives_on_rows(
            model,
            &ev.theta,
            k + 1,
            ev.eig.lambda[k],
            &self.phi,
            &mut self.dlambda,
            &self.rows,
            self.dphi_rows.as_mut(),
        )?;
        let mut dch = Mat::zeros(self.terms.len(), p);
        for (c, terms) in self.terms.iter().enumerate() {
            for l in 0..p {
                dch[(c, l)] = terms.iter().map(|&(r, w)| w * self.dphi_rows[(r, l)]).sum();
            }
        }
        Ok((self.dlambda.clone(), dch))
    }
}

/// The residual (6) at θ from the eigenpairs there, with each measured mode paired among
/// the first `n_cand` modes by `rule`.
fn residual_at(
    model: &Model,
    data: &MeasuredData,
    theta: &[f64],
    eig: EigenPairs,
    n_cand: usize,
    rule: Pairing,
) -> Evaluation {
    let readings = candidate_readings(model.channels(), &eig, n_cand);
    let mut pairing = Vec::with_capacity(data.modes.len());
    let mut macs = Vec::with_capacity(data.modes.len());
    let mut scales = Vec::with_capacity(data.modes.len());
    let mut r = Vec::with_capacity(data.n_data());
    let mut dphi_k = Vec::new();
    for mode in &data.modes {
        let (k, mac_k) = pair_mode(mode, rule, &eig, &readings, n_cand, &mut dphi_k);
        pairing.push(k);
        macs.push(mac_k);
        r.push((mode.lambda - eig.lambda[k]) / mode.sigma_lambda);
        match &mode.shape {
            Some(s) => {
                gather(&readings, k, &s.channels, &mut dphi_k);
                scales.push(push_shape_residual(s, &dphi_k, &mut r));
            }
            None => scales.push(f64::NAN),
        }
    }
    let epsilon = r.iter().map(|v| v * v).sum();
    Evaluation {
        theta: theta.to_vec(),
        eig,
        pairing,
        mac: macs,
        scale: scales,
        r,
        epsilon,
    }
}

/// The shape part of the residual (6) for measured shape `s` and the paired mode's readings
/// `dphi` at its channels, pushed onto `r`: `(ψ̂ − c Dφ)/σ` with the scale factor `c` (7),
/// which it returns.
fn push_shape_residual(s: &TargetShape, dphi: &[f64], r: &mut Vec<f64>) -> f64 {
    let c = scale_factor(&s.values, dphi);
    for ((psi, dp), sd) in s.values.iter().zip(dphi).zip(&s.sigma) {
        r.push((psi - c * dp) / sd);
    }
    c
}

/// `D φ_k` at the given channels into `out`.
fn read_channels(
    eig: &EigenPairs,
    k: usize,
    idx: &[usize],
    channels: &[Channel],
    out: &mut Vec<f64>,
) {
    out.clear();
    out.extend(idx.iter().map(|&c| {
        channels[c]
            .dofs
            .iter()
            .map(|&(i, w)| w * eig.phi[(i, k)])
            .sum::<f64>()
    }));
}

/// Modal scale factor (7): `c = ψ̂ᵀ Dφ / ‖Dφ‖²` (0 if Dφ vanishes at the channels).
pub fn scale_factor(psi: &[f64], dphi: &[f64]) -> f64 {
    let num: f64 = psi.iter().zip(dphi).map(|(a, b)| a * b).sum();
    let den: f64 = dphi.iter().map(|b| b * b).sum();
    if den == 0.0 { 0.0 } else { num / den }
}
