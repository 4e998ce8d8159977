//! The basis of one Krylov cycle of [`super::SparseEigen`]: `V` with `M`-orthonormal
//! columns and its products `MV` and `KV`, grown a block at a time (`W = K⁻¹B`, block
//! classical Gram–Schmidt twice against `V`, SVQB within the block), with the block solves
//! and mass products it is built from, split over the worker threads.

use faer::dyn_stack::{MemBuffer, MemStack, StackReq};
use faer::linalg::matmul::matmul;
use faer::sparse::linalg::cholesky::LltRef;
use faer::{Accum, Conj, Mat, MatMut, MatRef, Par, Side};

use crate::core::modal::eigen::symmetrize;
use crate::core::modal::{col_slice, col_slice_mut};
use crate::core::model::Reordered;
use crate::core::model::sparse::{Csc, spmm_symmetric};

/// A direction of a new block whose `M`-norm falls below this fraction of its columns'
/// norms before orthogonalization is dropped: it adds almost nothing new (in a restart,
/// `K⁻¹M` of a converged mode is that mode), and the `K v` carried through the
/// cancellation loses about `ε / fraction` of its relative accuracy, so near-dependent
/// directions would spoil the projected `VᵀKV`.
const DEPENDENT: f64 = 1e-4;

/// Tasks the solver splits its block solves and mass products into (run on rayon's pool,
/// whose threads persist: a thread spawned per block cost a fresh stack each time).
pub(super) fn workers() -> usize {
    rayon::current_num_threads().clamp(1, 8)
}

/// faer's parallelism for the basis's dense products: every core when the solve runs
/// alone, the calling thread when it already runs on one of rayon's workers (a candidate
/// among many, a restart beside another). There the other workers are busy with their own
/// solves, and a parallel product waits at its barrier for threads that do not come.
fn gemm_parallelism() -> Par {
    if rayon::current_thread_index().is_some() {
        Par::Seq
    } else {
        Par::rayon(0)
    }
}

/// One worker's scratch for its share of a block solve: faer's stack, and the share in the
/// reordered numbering.
pub(super) struct SolveScratch {
    stack: MemBuffer,
    permuted: Mat<f64>,
}

impl SolveScratch {
    /// Scratch for shares of up to `cols` columns of `rows` DOFs, faer's stack sized `req`.
    pub(super) fn new(req: StackReq, rows: usize, cols: usize) -> Self {
        Self {
            stack: MemBuffer::new(req),
            permuted: Mat::zeros(rows, cols),
        }
    }
}

/// What a basis is built with: `M`, the factor `K = LLᵀ` and the ordering it is in.
#[derive(Clone, Copy)]
pub(super) struct Operators<'a> {
    pub(super) mass: &'a Csc,
    pub(super) llt: LltRef<'a, usize, f64>,
    pub(super) order: &'a Reordered,
}

/// `X ← K⁻¹ X`, the columns shared among the worker threads (each a sequential
/// supernodal solve: on the four-bay solid frame faer's own parallel solve was half as
/// fast as a sequential one, 4.7 against 2.3 ms per column in blocks of six).
fn solve_split(
    llt: LltRef<'_, usize, f64>,
    order: &Reordered,
    x: MatMut<'_, f64>,
    mem: &mut [SolveScratch],
) {
    let per = x.ncols().div_ceil(mem.len()).max(1);
    rayon::scope(|scope| {
        let mut rest = x;
        for buf in mem.iter_mut() {
            let take = per.min(rest.ncols());
            if take == 0 {
                break;
            }
            let (mut chunk, tail) = rest.split_at_col_mut(take);
            rest = tail;
            scope.spawn(move |_| {
                let mut y = buf.permuted.as_mut().subcols_mut(0, take);
                for c in 0..take {
                    order.permute(col_slice(chunk.as_ref(), c), col_slice_mut(y.as_mut(), c));
                }
                llt.solve_in_place_with_conj(
                    Conj::No,
                    y.as_mut(),
                    Par::Seq,
                    MemStack::new(&mut buf.stack),
                );
                for c in 0..take {
                    order.unpermute(col_slice(y.as_ref(), c), col_slice_mut(chunk.as_mut(), c));
                }
            });
        }
    });
}

/// `Y ← M X`, the rows shared among the worker threads ([`spmm_symmetric`]).
pub(super) fn mass_split(mass: &Csc, x: MatRef<'_, f64>, y: MatMut<'_, f64>) {
    spmm_symmetric(mass, x, y, workers());
}

/// The basis of one cycle: `V` with `M`-orthonormal columns, `MV` and `KV`, stored in the
/// first `len` columns of matrices kept between calls.
pub(super) struct Basis {
    pub(super) v: Mat<f64>,
    pub(super) mv: Mat<f64>,
    pub(super) kv: Mat<f64>,
    pub(super) len: usize,
}

impl Basis {
    /// An empty basis of `n` DOFs with room for `cap` columns.
    pub(super) fn new(n: usize, cap: usize) -> Self {
        Self {
            v: Mat::zeros(n, cap),
            mv: Mat::zeros(n, cap),
            kv: Mat::zeros(n, cap),
            len: 0,
        }
    }

    /// Empties the basis, with room for `cap` columns.
    pub(super) fn reset(&mut self, cap: usize) {
        if self.v.ncols() < cap {
            *self = Self::new(self.v.nrows(), cap);
        }
        self.len = 0;
    }

    /// Appends the part of `W = K⁻¹B` that is new, with `KW = B` carried along: two passes
    /// of block classical Gram–Schmidt against the basis in the `M`-inner product (BCGS2;
    /// `KW` updated once with the summed coefficients), `MW` computed from the result (not
    /// updated: under cancellation an updated `MW` no longer matches `W`), then SVQB within
    /// the block, twice, dropping dependent directions (see `DEPENDENT`). `MW` and `KW`
    /// follow the block's transformations, whose amplification the dropping bounds by
    /// `1 / DEPENDENT`.
    pub(super) fn push_solved(
        &mut self,
        ops: Operators<'_>,
        mem: &mut [SolveScratch],
        b: Mat<f64>,
    ) {
        let (n, r) = (b.nrows(), b.ncols());
        let mut w = b.clone();
        solve_split(ops.llt, ops.order, w.as_mut(), mem);
        let mut kw = b;
        let mut mw = Mat::zeros(n, r);
        // ‖w‖²_M before the pass against the basis: ‖w‖²_M after it plus the squared
        // coefficients taken out (the basis is M-orthonormal).
        let mut taken = vec![0.0; r];
        let len = self.len;
        if len > 0 {
            self.project_out(&mut w, &mut kw, &mut taken);
        }
        mass_split(ops.mass, w.as_ref(), mw.as_mut());
        // Within the block: SVQB (Stathopoulos & Wu, SIAM J. Sci. Comput. 23 (2002)) on the
        // columns scaled by their norms before the pass against the basis, twice.
        let scale = column_scales(&w, &mw, &taken);
        let room = self.v.ncols() - len;
        let Some(t) = svqb(w.as_ref(), mw.as_ref(), &scale, DEPENDENT * DEPENDENT, room) else {
            return;
        };
        let (vb, mvb, kvb) = transformed(&w, &mw, &kw, &t);
        self.append_orthonormalized(&vb, &mvb, &kvb);
    }

    /// BCGS2: `W ← W − V (MV)ᵀW`, twice, against the first `len` columns, and `KW` updated
    /// once with the summed coefficients; `taken[j]`, the squared coefficients taken out of
    /// column `j`.
    fn project_out(&self, w: &mut Mat<f64>, kw: &mut Mat<f64>, taken: &mut [f64]) {
        let (len, r) = (self.len, w.ncols());
        let (v, mv, kv) = (
            self.v.subcols(0, len),
            self.mv.subcols(0, len),
            self.kv.subcols(0, len),
        );
        let par = gemm_parallelism();
        let mut c = Mat::zeros(len, r);
        let mut c_sum = Mat::<f64>::zeros(len, r);
        for _ in 0..2 {
            matmul(
                c.as_mut(),
                Accum::Replace,
                mv.transpose(),
                w.as_ref(),
                1.0,
                par,
            );
            matmul(w.as_mut(), Accum::Add, v, c.as_ref(), -1.0, par);
            c_sum += &c;
        }
        matmul(kw.as_mut(), Accum::Add, kv, c_sum.as_ref(), -1.0, par);
        for (j, t) in taken.iter_mut().enumerate() {
            *t = col_slice(c_sum.as_ref(), j).iter().map(|c| c * c).sum();
        }
    }

    /// The second SVQB, on the block already transformed by the first (unit scales), and its
    /// result appended to `V`, `MV` and `KV`.
    fn append_orthonormalized(&mut self, vb: &Mat<f64>, mvb: &Mat<f64>, kvb: &Mat<f64>) {
        let par = gemm_parallelism();
        let ones = vec![1.0; vb.ncols()];
        if let Some(t2) = svqb(vb.as_ref(), mvb.as_ref(), &ones, 0.5, vb.ncols()) {
            let r2 = t2.ncols();
            let k = self.len;
            for (dst, src) in [(&mut self.v, vb), (&mut self.mv, mvb), (&mut self.kv, kvb)] {
                matmul(
                    dst.as_mut().subcols_mut(k, r2),
                    Accum::Replace,
                    src.as_ref(),
                    t2.as_ref(),
                    1.0,
                    par,
                );
            }
            self.len += r2;
        }
    }
}

/// The SVQB scale of each column of `W`: one over its `M`-norm before the pass against the
/// basis (`‖w‖²_M` after it plus `taken`), zero where that norm is not positive and finite.
fn column_scales(w: &Mat<f64>, mw: &Mat<f64>, taken: &[f64]) -> Vec<f64> {
    let r = w.ncols();
    let norm0: Vec<f64> = (0..r)
        .map(|j| {
            (dot(col_slice(w.as_ref(), j), col_slice(mw.as_ref(), j)).max(0.0) + taken[j]).sqrt()
        })
        .collect();
    norm0
        .iter()
        .map(|&v| {
            if v > 0.0 && v.is_finite() {
                1.0 / v
            } else {
                0.0
            }
        })
        .collect()
}

/// `W T`, `MW T` and `KW T`: the block and its products after the first SVQB.
fn transformed(
    w: &Mat<f64>,
    mw: &Mat<f64>,
    kw: &Mat<f64>,
    t: &Mat<f64>,
) -> (Mat<f64>, Mat<f64>, Mat<f64>) {
    let n = w.nrows();
    let mut vb = Mat::zeros(n, t.ncols());
    let mut mvb = Mat::zeros(n, t.ncols());
    let mut kvb = Mat::zeros(n, t.ncols());
    let par = gemm_parallelism();
    for (dst, src) in [(&mut vb, w), (&mut mvb, mw), (&mut kvb, kw)] {
        matmul(
            dst.as_mut(),
            Accum::Replace,
            src.as_ref(),
            t.as_ref(),
            1.0,
            par,
        );
    }
    (vb, mvb, kvb)
}

/// Scaled blocks whose Gram eigenvalues all exceed this are orthonormalized by Löwdin's
/// transformation (see `svqb`). On an ill-conditioned block it would spread the large
/// entries of `S^{-1/2}`, and the rounding they amplify, over every column (on the lab
/// frame: first-cycle residuals 90× worse, one more cycle).
const NEARLY_ORTHONORMAL: f64 = 0.5;

/// SVQB: the transformation `T` with `(WT)ᵀ M (WT) = I` from the Gram matrix
/// `G = U S Uᵀ` of `W D` (`D = diag(scale)`). When every eigenvalue exceeds
/// `NEARLY_ORTHONORMAL` and there is room for all columns, `T = D U S^{-1/2} Uᵀ`
/// (Löwdin's symmetric orthogonalization: of all orthonormal bases of the span the
/// nearest to `W D`, so nearly orthogonal columns, as in a restart from Ritz vectors, are
/// barely mixed, and a converged mode is not smeared over the block by rounding; with the
/// rotation alone the lab frame's sway mode came out at 1.5× its rounding floor).
/// Otherwise the directions with eigenvalue above `keep`, at most `room`, the largest
/// first: `T = D U_k S_k^{-1/2}`. `None` when none is kept. The scaling makes `keep` a bound on the squared `M`-norm of a
/// kept combination relative to the columns' scale.
fn svqb(
    w: MatRef<'_, f64>,
    mw: MatRef<'_, f64>,
    scale: &[f64],
    keep: f64,
    room: usize,
) -> Option<Mat<f64>> {
    let r = w.ncols();
    let mut g = w.transpose() * mw;
    for i in 0..r {
        for j in 0..r {
            g[(i, j)] *= scale[i] * scale[j];
        }
    }
    symmetrize(&mut g);
    let evd = g.self_adjoint_eigen(Side::Lower).ok()?;
    let s = evd.S().column_vector();
    let u = evd.U();
    let kept: Vec<usize> = (0..r)
        .rev()
        .filter(|&i| s[i] > keep && s[i].is_finite())
        .take(room)
        .collect();
    if kept.is_empty() {
        return None;
    }
    let rotated = Mat::from_fn(r, kept.len(), |i, c| {
        scale[i] * u[(i, kept[c])] / s[kept[c]].sqrt()
    });
    if kept.len() < r || s[0] < NEARLY_ORTHONORMAL {
        return Some(rotated);
    }
    let mut t = Mat::zeros(r, r);
    for c in 0..r {
        for j in 0..r {
            t[(c, j)] = (0..r).map(|k| rotated[(c, k)] * u[(j, kept[k])]).sum();
        }
    }
    Some(t)
}

/// `aᵀb`, summed in order.
pub(super) fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}
