//! Two-node Euler–Bernoulli space-frame element (issue 25): 12 DOF, `[u, v, w, θx, θy, θz]`
//! at each end, with consistent mass including axial and torsional inertia, in global
//! coordinates. Element-level algebra in `nalgebra` fixed-size matrices (12×12 element
//! matrices, 3×3 rotations); global assembly stays sparse in faer.
//!
//! Local axes: `x` from the first node to the second; `y` the component of a reference
//! vector perpendicular to `x` ([`local_axes`]); `z = x × y`. `I_z` is the second moment for
//! bending in the local x–y plane (transverse displacement `v`, rotation `θz`), `I_y` for
//! bending in the x–z plane (`w`, `θy`), `J` the St-Venant torsion constant, `J_p = I_y +
//! I_z` the polar moment that carries the torsional inertia. The stiffness is the exact
//! cubic-Hermite/linear element, the mass the consistent one of the same shape functions
//! without rotary (ρI) terms (Przemieniecki, *Theory of Matrix Structural Analysis*, 1968,
//! §5.6 and §11.3; the reference structure `space-frame.md` §5 states the same matrices).

use nalgebra::{Matrix3, SMatrix, Vector3};

/// 12×12 element matrix.
pub type Mat12 = SMatrix<f64, 12, 12>;

/// Properties of a space-frame member.
#[allow(non_snake_case)] // the symbols of the formulas
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Section3 {
    /// Young's modulus (Pa).
    pub E: f64,
    /// Shear modulus (Pa).
    pub G: f64,
    /// Density (kg/m³).
    pub rho: f64,
    /// Area (m²).
    pub A: f64,
    /// Second moment for bending in the local x–y plane (about local z), m⁴.
    pub Iz: f64,
    /// Second moment for bending in the local x–z plane (about local y), m⁴.
    pub Iy: f64,
    /// St-Venant torsion constant (m⁴).
    pub J: f64,
    /// Polar moment for the torsional inertia (m⁴), usually `I_y + I_z`.
    pub Jp: f64,
}

/// Local DOF indices of one end (`end` 0 or 1).
const fn dof(end: usize, k: usize) -> usize {
    6 * end + k
}
const U: usize = 0;
const V: usize = 1;
const W: usize = 2;
const RX: usize = 3;
const RY: usize = 4;
const RZ: usize = 5;

/// Adds the 2×2 block `c·[[a, b], [b, a]]` on the DOF `k` of both ends.
fn add_pair(m: &mut Mat12, k: usize, c: f64, a: f64, b: f64) {
    let (i, j) = (dof(0, k), dof(1, k));
    m[(i, i)] += c * a;
    m[(j, j)] += c * a;
    m[(i, j)] += c * b;
    m[(j, i)] += c * b;
}

/// Adds a bending block on `(t1, r1, t2, r2)` (translation and rotation at both ends):
/// `c · b` in the x–y plane, and with the translation–rotation couplings' signs reversed
/// in the x–z plane (`flip`), where a positive `θy` lowers `w`.
fn add_bending(m: &mut Mat12, t: usize, r: usize, c: f64, b: &[[f64; 4]; 4], flip: bool) {
    let idx = [dof(0, t), dof(0, r), dof(1, t), dof(1, r)];
    let is_rot = [false, true, false, true];
    for a in 0..4 {
        for bb in 0..4 {
            let sign = if flip && is_rot[a] != is_rot[bb] {
                -1.0
            } else {
                1.0
            };
            m[(idx[a], idx[bb])] += sign * c * b[a][bb];
        }
    }
}

/// The element stiffness in local axes for length `l`.
pub fn local_stiffness(s: &Section3, l: f64) -> Mat12 {
    let mut k = Mat12::zeros();
    add_pair(&mut k, U, s.E * s.A / l, 1.0, -1.0);
    add_pair(&mut k, RX, s.G * s.J / l, 1.0, -1.0);
    let b = [
        [12.0, 6.0 * l, -12.0, 6.0 * l],
        [6.0 * l, 4.0 * l * l, -6.0 * l, 2.0 * l * l],
        [-12.0, -6.0 * l, 12.0, -6.0 * l],
        [6.0 * l, 2.0 * l * l, -6.0 * l, 4.0 * l * l],
    ];
    let l3 = l * l * l;
    add_bending(&mut k, V, RZ, s.E * s.Iz / l3, &b, false);
    add_bending(&mut k, W, RY, s.E * s.Iy / l3, &b, true);
    k
}

/// The consistent element mass in local axes for length `l`: axial `ρAL/6·[2 1; 1 2]`,
/// torsional `ρJ_pL/6·[2 1; 1 2]`, and the cubic-Hermite bending mass `ρAL/420·[…]` in each
/// plane.
pub fn local_mass(s: &Section3, l: f64) -> Mat12 {
    let mut m = Mat12::zeros();
    add_pair(&mut m, U, s.rho * s.A * l / 6.0, 2.0, 1.0);
    add_pair(&mut m, RX, s.rho * s.Jp * l / 6.0, 2.0, 1.0);
    let b = [
        [156.0, 22.0 * l, 54.0, -13.0 * l],
        [22.0 * l, 4.0 * l * l, 13.0 * l, -3.0 * l * l],
        [54.0, 13.0 * l, 156.0, -22.0 * l],
        [-13.0 * l, -3.0 * l * l, -22.0 * l, 4.0 * l * l],
    ];
    let c = s.rho * s.A * l / 420.0;
    add_bending(&mut m, V, RZ, c, &b, false);
    add_bending(&mut m, W, RY, c, &b, true);
    m
}

/// The geometric stiffness in local axes of an axial force `n` (N, tension positive) for
/// length `l`: the cubic-Hermite `n/(30 l)·[36, 3l, −36, 3l; …]` in each bending plane
/// (Przemieniecki §6.3; the plane frames' [`super::element`] uses the same block). The
/// Wagner torsion term `n J_p/(A l)` is left out, as in the plane frames: it matters only
/// near torsional buckling, far from the forces a monitored frame carries.
pub fn local_geometric(n: f64, l: f64) -> Mat12 {
    let mut k = Mat12::zeros();
    let b = [
        [36.0, 3.0 * l, -36.0, 3.0 * l],
        [3.0 * l, 4.0 * l * l, -3.0 * l, -l * l],
        [-36.0, -3.0 * l, 36.0, -3.0 * l],
        [3.0 * l, -l * l, -3.0 * l, 4.0 * l * l],
    ];
    let c = n / (30.0 * l);
    add_bending(&mut k, V, RZ, c, &b, false);
    add_bending(&mut k, W, RY, c, &b, true);
    k
}

/// Why local axes cannot be formed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum AxesError {
    #[error("the member has zero length")]
    ZeroLength,
    #[error("the reference vector is parallel to the member (or zero)")]
    ParallelReference,
}

/// The rotation from global to local axes (its rows are the local x, y, z in global
/// coordinates) of a member from `a` to `b`: x along the member, y the part of `reference`
/// perpendicular to x, z = x × y.
pub fn local_axes(
    a: Vector3<f64>,
    b: Vector3<f64>,
    reference: Vector3<f64>,
) -> Result<Matrix3<f64>, AxesError> {
    let d = b - a;
    let l = d.norm();
    if l.is_nan() || l <= 0.0 {
        return Err(AxesError::ZeroLength);
    }
    let x = d / l;
    let z = x.cross(&reference);
    let zn = z.norm();
    if zn.is_nan() || zn <= 1e-9 * reference.norm() {
        return Err(AxesError::ParallelReference);
    }
    let z = z / zn;
    let y = z.cross(&x);
    Ok(Matrix3::from_rows(&[
        x.transpose(),
        y.transpose(),
        z.transpose(),
    ]))
}

/// The default reference vector of a member from `a` to `b`: global y (up), or global x
/// for a member along y (a column), whose section orientation then follows x.
pub fn default_reference(a: Vector3<f64>, b: Vector3<f64>) -> Vector3<f64> {
    let d = (b - a).normalize();
    if d.cross(&Vector3::y()).norm() < 1e-6 {
        Vector3::x()
    } else {
        Vector3::y()
    }
}

/// `Tᵀ k T` with `T` the block diagonal of the rotation `r`, four times: an element matrix
/// from local to global axes.
pub fn to_global(local: &Mat12, r: &Matrix3<f64>) -> Mat12 {
    let mut t = Mat12::zeros();
    for blk in 0..4 {
        t.fixed_view_mut::<3, 3>(3 * blk, 3 * blk).copy_from(r);
    }
    t.transpose() * local * t
}

/// Stiffness and consistent mass of a member from `a` to `b` in global axes.
pub fn global_matrices(
    s: &Section3,
    a: Vector3<f64>,
    b: Vector3<f64>,
    reference: Vector3<f64>,
) -> Result<(Mat12, Mat12), AxesError> {
    let r = local_axes(a, b, reference)?;
    let l = (b - a).norm();
    Ok((
        to_global(&local_stiffness(s, l), &r),
        to_global(&local_mass(s, l), &r),
    ))
}

/// The geometric stiffness of an axial force `n` in the member from `a` to `b`, in global
/// axes.
pub fn global_geometric(
    n: f64,
    a: Vector3<f64>,
    b: Vector3<f64>,
    reference: Vector3<f64>,
) -> Result<Mat12, AxesError> {
    let r = local_axes(a, b, reference)?;
    Ok(to_global(&local_geometric(n, (b - a).norm()), &r))
}

#[cfg(test)]
mod tests {
    //! Closed forms: a cantilever along an inclined axis (so the rotation is exercised) under
    //! tip loads (cubic elements are exact for them), and its lowest bending and torsion
    //! frequencies against Euler–Bernoulli and St-Venant under mesh refinement.

    use nalgebra::{DMatrix, DVector};

    use super::*;

    /// The column's section (space-frame.md §4): a ≠ b so the two bending planes differ.
    fn section() -> Section3 {
        let (h, b) = (0.040, 0.020);
        let e = 2.1e11;
        Section3 {
            E: e,
            G: e / 2.6,
            rho: 7850.0,
            A: h * b,
            Iz: b * h * h * h / 12.0,
            Iy: h * b * b * b / 12.0,
            J: 7.328e-8,
            Jp: b * h * h * h / 12.0 + h * b * b * b / 12.0,
        }
    }

    /// A cantilever of `n` elements from the origin along `dir` (length `len`), reference
    /// vector `reference`, clamped at the origin: `(K, M, R)` on the free DOFs (node k's DOF
    /// at `6(k − 1)`), with the rotation R of its elements.
    fn cantilever(
        n: usize,
        len: f64,
        dir: Vector3<f64>,
        reference: Vector3<f64>,
    ) -> (DMatrix<f64>, DMatrix<f64>, Matrix3<f64>) {
        let s = section();
        let d = dir.normalize() * (len / n as f64);
        let size = 6 * n;
        let (mut k, mut m) = (DMatrix::zeros(size, size), DMatrix::zeros(size, size));
        for e in 0..n {
            let a = d * e as f64;
            let (ke, me) = global_matrices(&s, a, a + d, reference).unwrap();
            for i in 0..12 {
                for j in 0..12 {
                    // Node e's DOF first; node 0 is clamped.
                    let gi = (6 * e + i).checked_sub(6);
                    let gj = (6 * e + j).checked_sub(6);
                    if let (Some(gi), Some(gj)) = (gi, gj) {
                        k[(gi, gj)] += ke[(i, j)];
                        m[(gi, gj)] += me[(i, j)];
                    }
                }
            }
        }
        (k, m, local_axes(Vector3::zeros(), d, reference).unwrap())
    }

    /// The tip's displacement (global) under a global load `f` and moment `t` at the tip.
    fn tip_response(
        k: &DMatrix<f64>,
        f: Vector3<f64>,
        t: Vector3<f64>,
    ) -> (Vector3<f64>, Vector3<f64>) {
        let size = k.nrows();
        let mut rhs = DVector::zeros(size);
        for c in 0..3 {
            rhs[size - 6 + c] = f[c];
            rhs[size - 3 + c] = t[c];
        }
        let x = k
            .clone()
            .cholesky()
            .expect("a clamped cantilever")
            .solve(&rhs);
        (
            Vector3::new(x[size - 6], x[size - 5], x[size - 4]),
            Vector3::new(x[size - 3], x[size - 2], x[size - 1]),
        )
    }

    /// Tip deflections in both bending directions, axial and torsional stiffness: the
    /// closed forms `PL³/3EI`, `PL/EA`, `TL/GJ` to 1e-10 (the elements are exact for tip
    /// loads; the rest is rounding), along an inclined axis with a reference vector not perpendicular to it.
    #[test]
    fn cantilever_tip_loads_give_the_closed_forms() {
        let s = section();
        let len: f64 = 1.3;
        let dir = Vector3::new(1.0, 2.0, -0.5);
        let reference = Vector3::new(0.3, 1.0, 0.7);
        let (k, _, r) = cantilever(5, len, dir, reference);
        let (x, y, z) = (
            r.row(0).transpose(),
            r.row(1).transpose(),
            r.row(2).transpose(),
        );
        let p = 1000.0;
        let cases = [
            // (load, moment, displacement or rotation along, expected)
            (
                y * p,
                Vector3::zeros(),
                y,
                p * len.powi(3) / (3.0 * s.E * s.Iz),
            ),
            (
                z * p,
                Vector3::zeros(),
                z,
                p * len.powi(3) / (3.0 * s.E * s.Iy),
            ),
            (x * p, Vector3::zeros(), x, p * len / (s.E * s.A)),
            (Vector3::zeros(), x * p, x, p * len / (s.G * s.J)),
        ];
        for (f, t, along, want) in cases {
            let (u, rot) = tip_response(&k, f, t);
            let got = if t.norm() > 0.0 {
                rot.dot(&along)
            } else {
                u.dot(&along)
            };
            // Exact but for rounding: K's axial and bending stiffnesses differ by ~1e6
            // here, so the solve is good to ~1e-10.
            assert!(
                ((got - want) / want).abs() < 1e-10,
                "load {f:?}, moment {t:?}: {got} against {want}"
            );
        }
        // Bending about local z does not move the tip along z (the planes decouple).
        let (u, _) = tip_response(&k, y * p, Vector3::zeros());
        assert!(u.dot(&z).abs() < 1e-12 * u.norm());
    }

    /// First bending frequency in each plane, `(1.8751²/2π)·√(EI/ρAL⁴)`, and first torsion
    /// frequency, `(1/4L)·√(GJ/ρJ_p)`, of the cantilever: converging from above with the
    /// mesh at the elements' orders (h⁴ bending, h² torsion), within 0.5 % from 2 elements
    /// (bending: 4.8e-4) and from 8 (torsion: 2.6 %, 0.64 %, 0.16 %, 0.04 % at 2–16).
    #[test]
    fn cantilever_frequencies_converge_to_euler_bernoulli_and_st_venant() {
        let s = section();
        let len: f64 = 1.0;
        let beta = 1.875_104_068_711_961_f64;
        let bend = |i: f64| {
            beta * beta / (2.0 * std::f64::consts::PI)
                * (s.E * i / (s.rho * s.A * len.powi(4))).sqrt()
        };
        let torsion = (s.G * s.J / (s.rho * s.Jp)).sqrt() / (4.0 * len);
        let dir = Vector3::new(0.0, 1.0, 1.0);
        let reference = Vector3::new(1.0, 0.0, 0.0);
        let mut last = [f64::INFINITY; 3];
        let mut last_errors: Option<Vec<f64>> = None;
        for n in [2, 4, 8, 16] {
            let (k, m, r) = cantilever(n, len, dir, reference);
            // The modes of each kind: the frequency of the lowest mode dominated by it.
            let l = m.clone().cholesky().unwrap().l();
            let li = l.clone().try_inverse().unwrap();
            let a = &li * &k * li.transpose();
            let a = (&a + a.transpose()) * 0.5;
            let eig = a.symmetric_eigen();
            let mut modes: Vec<(f64, DVector<f64>)> = (0..eig.eigenvalues.len())
                .map(|q| {
                    (
                        eig.eigenvalues[q],
                        li.transpose() * eig.eigenvectors.column(q),
                    )
                })
                .collect();
            modes.sort_by(|a, b| a.0.total_cmp(&b.0));
            let tip = |phi: &DVector<f64>, axis: Vector3<f64>, rot: bool| {
                let o = phi.len() - 6 + if rot { 3 } else { 0 };
                (Vector3::new(phi[o], phi[o + 1], phi[o + 2]))
                    .dot(&axis)
                    .abs()
            };
            let first = |axis: Vector3<f64>, rot: bool| {
                modes
                    .iter()
                    .find(|(_, phi)| {
                        let own = tip(phi, axis, rot);
                        let others = [r.row(0), r.row(1), r.row(2)]
                            .iter()
                            .map(|row| tip(phi, row.transpose(), rot))
                            .fold(0.0, f64::max);
                        own >= others * 0.999 && own > 0.0
                    })
                    .map(|(lam, _)| lam.sqrt() / (2.0 * std::f64::consts::PI))
                    .unwrap()
            };
            let got = [
                first(r.row(1).transpose(), false),
                first(r.row(2).transpose(), false),
                first(r.row(0).transpose(), true),
            ];
            let want = [bend(s.Iz), bend(s.Iy), torsion];
            let errors: Vec<f64> = got.iter().zip(&want).map(|(g, w)| (g - w) / w).collect();
            println!(
                "{n:>2} elements: bending z {:+.2e}, bending y {:+.2e}, torsion {:+.2e}",
                errors[0], errors[1], errors[2]
            );
            for (q, e) in errors.iter().enumerate() {
                assert!(
                    *e > -1e-9,
                    "{n} elements, kind {q}: below the exact value ({e})"
                );
                assert!(
                    got[q] <= last[q] * (1.0 + 1e-12),
                    "{n} elements, kind {q}: not converging"
                );
            }
            // Orders: cubic bending elements O(h⁴) in the frequency, linear torsion O(h²).
            if let Some(prev) = last_errors {
                let rate = |q: usize| prev[q] / errors[q];
                assert!(
                    rate(0) > 12.0 && rate(1) > 12.0,
                    "{n}: bending rate {}",
                    rate(0)
                );
                assert!(rate(2) > 3.5, "{n}: torsion rate {}", rate(2));
            }
            assert!(
                errors[0] < 5e-3 && errors[1] < 5e-3,
                "{n} elements: {errors:?}"
            );
            if n >= 8 {
                assert!(errors[2] < 5e-3, "{n} elements: {errors:?}");
            }
            last_errors = Some(errors);
            last = got;
        }
    }

    /// Default reference vectors: a beam's local y is global y, a column's is global x;
    /// the axes are orthonormal and right-handed.
    #[test]
    fn local_axes_follow_the_reference_vector() {
        let o = Vector3::zeros();
        let bx = local_axes(o, Vector3::x(), default_reference(o, Vector3::x())).unwrap();
        assert_eq!(bx.row(2).transpose(), Vector3::z());
        let bz = local_axes(o, Vector3::z(), default_reference(o, Vector3::z())).unwrap();
        assert_eq!(bz.row(2).transpose(), -Vector3::x());
        let col = local_axes(o, Vector3::y(), default_reference(o, Vector3::y())).unwrap();
        assert_eq!(col.row(1).transpose(), Vector3::x());
        assert!((col * col.transpose() - Matrix3::identity()).norm() < 1e-15);
        assert!((col.determinant() - 1.0).abs() < 1e-15);
        assert_eq!(
            local_axes(o, Vector3::y(), Vector3::y()),
            Err(AxesError::ParallelReference)
        );
        assert_eq!(local_axes(o, o, Vector3::y()), Err(AxesError::ZeroLength));
    }
}
