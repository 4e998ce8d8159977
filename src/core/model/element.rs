//! Two-node Euler–Bernoulli plane frame element (3 DOF per node: u, v, r_z) with consistent
//! mass (axial and bending), in global coordinates.
//!
//! Local DOF order is `[u1, v1, r1, u2, v2, r2]`. The stiffness is the standard exact
//! cubic-Hermite/linear element; the consistent mass uses the same shape functions
//! (Przemieniecki, *Theory of Matrix Structural Analysis*, 1968, §5 and §11).

/// 6×6 element matrix.
pub type Mat6 = [[f64; 6]; 6];

/// Element properties: Young's modulus, density, area, second moment of area.
#[derive(Debug, Clone, Copy)]
pub struct Section {
    pub E: f64,
    pub rho: f64,
    pub A: f64,
    pub I: f64,
}

/// Local stiffness of a frame element of length `l`.
fn local_stiffness(s: &Section, l: f64) -> Mat6 {
    let mut k = [[0.0; 6]; 6];
    let ea = s.E * s.A / l;
    k[0][0] = ea;
    k[3][3] = ea;
    k[0][3] = -ea;
    k[3][0] = -ea;
    let c = s.E * s.I / (l * l * l);
    let b = [
        [12.0, 6.0 * l, -12.0, 6.0 * l],
        [6.0 * l, 4.0 * l * l, -6.0 * l, 2.0 * l * l],
        [-12.0, -6.0 * l, 12.0, -6.0 * l],
        [6.0 * l, 2.0 * l * l, -6.0 * l, 4.0 * l * l],
    ];
    scatter_bending(&mut k, &b, c);
    k
}

/// Local consistent mass of a frame element of length `l`.
fn local_mass(s: &Section, l: f64) -> Mat6 {
    let mut m = [[0.0; 6]; 6];
    let ma = s.rho * s.A * l / 6.0;
    m[0][0] = 2.0 * ma;
    m[3][3] = 2.0 * ma;
    m[0][3] = ma;
    m[3][0] = ma;
    let c = s.rho * s.A * l / 420.0;
    let b = [
        [156.0, 22.0 * l, 54.0, -13.0 * l],
        [22.0 * l, 4.0 * l * l, 13.0 * l, -3.0 * l * l],
        [54.0, 13.0 * l, 156.0, -22.0 * l],
        [-13.0 * l, -3.0 * l * l, -22.0 * l, 4.0 * l * l],
    ];
    scatter_bending(&mut m, &b, c);
    m
}

fn scatter_bending(target: &mut Mat6, b: &[[f64; 4]; 4], scale: f64) {
    const IDX: [usize; 4] = [1, 2, 4, 5];
    for (i, &gi) in IDX.iter().enumerate() {
        for (j, &gj) in IDX.iter().enumerate() {
            target[gi][gj] = scale * b[i][j];
        }
    }
}

/// `Tᵀ a T` with `T = blockdiag(R, R)`, `R = [[c, s, 0], [−s, c, 0], [0, 0, 1]]`
/// (local = T · global).
fn to_global(a: &Mat6, c: f64, s: f64) -> Mat6 {
    let mut t = [[0.0; 6]; 6];
    for blk in [0, 3] {
        t[blk][blk] = c;
        t[blk][blk + 1] = s;
        t[blk + 1][blk] = -s;
        t[blk + 1][blk + 1] = c;
        t[blk + 2][blk + 2] = 1.0;
    }
    let mut at = [[0.0; 6]; 6];
    for i in 0..6 {
        for j in 0..6 {
            at[i][j] = (0..6).map(|k| a[i][k] * t[k][j]).sum();
        }
    }
    let mut g = [[0.0; 6]; 6];
    for i in 0..6 {
        for j in 0..6 {
            g[i][j] = (0..6).map(|k| t[k][i] * at[k][j]).sum();
        }
    }
    g
}

/// Local consistent geometric stiffness of an element of length `l` under axial force `n`
/// (tension positive), from the same cubic shape functions (Przemieniecki §15).
fn local_geometric(n: f64, l: f64) -> Mat6 {
    let mut k = [[0.0; 6]; 6];
    let b = [
        [36.0, 3.0 * l, -36.0, 3.0 * l],
        [3.0 * l, 4.0 * l * l, -3.0 * l, -l * l],
        [-36.0, -3.0 * l, 36.0, -3.0 * l],
        [3.0 * l, -l * l, -3.0 * l, 4.0 * l * l],
    ];
    scatter_bending(&mut k, &b, n / (30.0 * l));
    k
}

/// Global geometric stiffness of the element from `p1` to `p2` under axial force `n`.
pub fn geometric_element(n: f64, p1: [f64; 2], p2: [f64; 2]) -> Mat6 {
    let dx = p2[0] - p1[0];
    let dy = p2[1] - p1[1];
    let l = dx.hypot(dy);
    to_global(&local_geometric(n, l), dx / l, dy / l)
}

/// Global stiffness and consistent mass of the element from `p1` to `p2` (metres).
pub fn frame_element(s: &Section, p1: [f64; 2], p2: [f64; 2]) -> (Mat6, Mat6) {
    let dx = p2[0] - p1[0];
    let dy = p2[1] - p1[1];
    let l = dx.hypot(dy);
    let (c, sn) = (dx / l, dy / l);
    (
        to_global(&local_stiffness(s, l), c, sn),
        to_global(&local_mass(s, l), c, sn),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    const S: Section = Section {
        E: 2.1e11,
        rho: 7840.0,
        A: 5.5e-4,
        I: 5.5458e-9,
    };

    /// A rigid-body translation and a rigid rotation produce no elastic force, in any
    /// orientation. Tolerance: 1e-9 relative to the largest stiffness entry (round-off of
    /// sums of O(10) terms of size EA/L).
    #[test]
    fn rigid_body_modes_are_force_free() {
        for angle in [0.0_f64, 0.3, 1.2, 2.5] {
            let p1 = [0.1, 0.2];
            let p2 = [0.1 + 0.3 * angle.cos(), 0.2 + 0.3 * angle.sin()];
            let (k, _) = frame_element(&S, p1, p2);
            let kmax = k.iter().flatten().fold(0.0_f64, |a, b| a.max(b.abs()));
            // rotation about the origin by a small angle w: u = -w y, v = w x, r = w
            let rot = [-p1[1], p1[0], 1.0, -p2[1], p2[0], 1.0];
            for mode in [
                [1.0, 0.0, 0.0, 1.0, 0.0, 0.0],
                [0.0, 1.0, 0.0, 0.0, 1.0, 0.0],
                rot,
            ] {
                for row in &k {
                    let f: f64 = row.iter().zip(mode.iter()).map(|(a, b)| a * b).sum();
                    assert!(f.abs() < 1e-9 * kmax, "force {f} for angle {angle}");
                }
            }
        }
    }

    /// The consistent mass reproduces the element's total mass for a rigid translation in
    /// any direction: uᵀ M u = ρ A L. Tolerance 1e-12 relative (exact rational weights).
    #[test]
    fn mass_matrix_has_total_mass() {
        let (_, m) = frame_element(&S, [0.0, 0.0], [0.3, 0.4]);
        let total = S.rho * S.A * 0.5;
        for u in [
            [1.0, 0.0, 0.0, 1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0, 0.0, 1.0, 0.0],
        ] {
            let q: f64 = (0..6)
                .flat_map(|i| (0..6).map(move |j| (i, j)))
                .map(|(i, j)| u[i] * m[i][j] * u[j])
                .sum();
            assert!((q - total).abs() < 1e-12 * total, "{q} vs {total}");
        }
    }
}
