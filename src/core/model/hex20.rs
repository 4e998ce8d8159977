//! The 20-node serendipity hexahedron (quadratic solid element) for linear isotropic
//! elasticity: stiffness and consistent mass by 3×3×3 Gauss quadrature (Zienkiewicz &
//! Taylor, *The Finite Element Method*, vol. 1, 6th ed., §8.7; Hughes, *The Finite Element
//! Method*, §3.7).
//!
//! Node `a` sits at the natural coordinates [`NATURAL`]`[a]` of the cube `[−1, 1]³`: the
//! eight corners (every coordinate ±1) first, then the twelve edge midpoints (one coordinate
//! 0). Shape functions:
//! - corner `a`: `N = ⅛ (1 + ξξa)(1 + ηηa)(1 + ζζa)(ξξa + ηηa + ζζa − 2)`;
//! - edge midpoint with `ξa = 0`: `N = ¼ (1 − ξ²)(1 + ηηa)(1 + ζζa)`, and alike for `η`, `ζ`.
//!
//! Element DOF `3a + i` is node `a`'s displacement along global axis `i`. The stiffness
//! block of nodes `a`, `b` is `∫ λ ∂ᵢNa ∂ⱼNb + μ ∂ⱼNa ∂ᵢNb + μ δᵢⱼ ∇Na·∇Nb dV`, the
//! `BᵀDB` of isotropic elasticity written out (λ, μ the Lamé constants), and the mass
//! block `ρ ∫ Na Nb dV δᵢⱼ`.

/// Nodes per element and element DOFs.
pub const NODES: usize = 20;
pub const DOFS: usize = 3 * NODES;

/// A dense element matrix.
pub type ElementMatrix = [[f64; DOFS]; DOFS];

/// Natural coordinates of the nodes: 8 corners, then 12 edge midpoints.
pub const NATURAL: [[f64; 3]; NODES] = [
    [-1.0, -1.0, -1.0],
    [1.0, -1.0, -1.0],
    [1.0, 1.0, -1.0],
    [-1.0, 1.0, -1.0],
    [-1.0, -1.0, 1.0],
    [1.0, -1.0, 1.0],
    [1.0, 1.0, 1.0],
    [-1.0, 1.0, 1.0],
    [0.0, -1.0, -1.0],
    [1.0, 0.0, -1.0],
    [0.0, 1.0, -1.0],
    [-1.0, 0.0, -1.0],
    [0.0, -1.0, 1.0],
    [1.0, 0.0, 1.0],
    [0.0, 1.0, 1.0],
    [-1.0, 0.0, 1.0],
    [-1.0, -1.0, 0.0],
    [1.0, -1.0, 0.0],
    [1.0, 1.0, 0.0],
    [-1.0, 1.0, 0.0],
];

/// Isotropic linear elastic material.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Material {
    /// Young's modulus (Pa).
    pub e: f64,
    /// Poisson's ratio.
    pub nu: f64,
    /// Density (kg/m³).
    pub rho: f64,
}

impl Material {
    /// Lamé constants `(λ, μ)`.
    pub fn lame(&self) -> (f64, f64) {
        let mu = self.e / (2.0 * (1.0 + self.nu));
        let lambda = self.e * self.nu / ((1.0 + self.nu) * (1.0 - 2.0 * self.nu));
        (lambda, mu)
    }
}

/// Shape functions and their natural derivatives at `(ξ, η, ζ)`.
pub fn shape(p: [f64; 3]) -> ([f64; NODES], [[f64; 3]; NODES]) {
    let mut n = [0.0; NODES];
    let mut dn = [[0.0; 3]; NODES];
    for (a, na) in NATURAL.iter().enumerate() {
        // Factors (1 + x xa) for the coordinates where xa ≠ 0, (1 − x²) where xa = 0.
        let zero = na.iter().position(|&c| c == 0.0);
        match zero {
            None => {
                let f = [1.0 + p[0] * na[0], 1.0 + p[1] * na[1], 1.0 + p[2] * na[2]];
                let s = p[0] * na[0] + p[1] * na[1] + p[2] * na[2] - 2.0;
                n[a] = 0.125 * f[0] * f[1] * f[2] * s;
                for i in 0..3 {
                    let (j, k) = ((i + 1) % 3, (i + 2) % 3);
                    // ∂/∂xᵢ of ⅛ fᵢ fⱼ fₖ s = ⅛ fⱼ fₖ (xaᵢ s + fᵢ xaᵢ).
                    dn[a][i] = 0.125 * f[j] * f[k] * na[i] * (s + f[i]);
                }
            }
            Some(z) => {
                let (j, k) = ((z + 1) % 3, (z + 2) % 3);
                let g = 1.0 - p[z] * p[z];
                let fj = 1.0 + p[j] * na[j];
                let fk = 1.0 + p[k] * na[k];
                n[a] = 0.25 * g * fj * fk;
                dn[a][z] = -0.5 * p[z] * fj * fk;
                dn[a][j] = 0.25 * g * na[j] * fk;
                dn[a][k] = 0.25 * g * fj * na[k];
            }
        }
    }
    (n, dn)
}

/// 3-point Gauss–Legendre rule on `[−1, 1]`: points and weights (exact to degree 5).
const GAUSS3: [(f64, f64); 3] = [
    (-0.774_596_669_241_483_4, 5.0 / 9.0),
    (0.0, 8.0 / 9.0),
    (0.774_596_669_241_483_4, 5.0 / 9.0),
];

/// Why an element cannot be integrated.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
#[error("element is inverted or degenerate: det J = {det_j:e} at a Gauss point")]
pub struct Degenerate {
    pub det_j: f64,
}

/// Stiffness and consistent mass of one element with node coordinates `x` (in the order of
/// [`NATURAL`]), boxed (each is 28.8 kB).
pub fn element(
    x: &[[f64; 3]; NODES],
    mat: &Material,
) -> Result<(Box<ElementMatrix>, Box<ElementMatrix>), Degenerate> {
    let (lambda, mu) = mat.lame();
    let mut k = Box::new([[0.0; DOFS]; DOFS]);
    let mut m = Box::new([[0.0; DOFS]; DOFS]);
    for &(xi, wx) in &GAUSS3 {
        for &(eta, wy) in &GAUSS3 {
            for &(zeta, wz) in &GAUSS3 {
                let (n, dn) = shape([xi, eta, zeta]);
                // Jacobian J[i][r] = ∂xᵢ/∂ξᵣ.
                let mut j = [[0.0; 3]; 3];
                for a in 0..NODES {
                    for i in 0..3 {
                        for r in 0..3 {
                            j[i][r] += x[a][i] * dn[a][r];
                        }
                    }
                }
                let det = det3(&j);
                if !(det > 0.0 && det.is_finite()) {
                    return Err(Degenerate { det_j: det });
                }
                let inv = inv3(&j, det);
                // Global gradients ∂Na/∂xᵢ = Σ_r ∂Na/∂ξᵣ ∂ξᵣ/∂xᵢ, with ∂ξᵣ/∂xᵢ = J⁻¹[r][i].
                let mut g = [[0.0; 3]; NODES];
                for a in 0..NODES {
                    for i in 0..3 {
                        g[a][i] = (0..3).map(|r| dn[a][r] * inv[r][i]).sum();
                    }
                }
                let w = wx * wy * wz * det;
                for a in 0..NODES {
                    for b in a..NODES {
                        let dot = g[a][0] * g[b][0] + g[a][1] * g[b][1] + g[a][2] * g[b][2];
                        let mab = mat.rho * w * n[a] * n[b];
                        for i in 0..3 {
                            for jj in 0..3 {
                                let mut v = lambda * g[a][i] * g[b][jj] + mu * g[a][jj] * g[b][i];
                                if i == jj {
                                    v += mu * dot;
                                }
                                k[3 * a + i][3 * b + jj] += w * v;
                            }
                            m[3 * a + i][3 * b + i] += mab;
                        }
                    }
                }
            }
        }
    }
    // Fill the lower blocks from the upper ones (both matrices are symmetric).
    for a in 0..NODES {
        for b in a + 1..NODES {
            for i in 0..3 {
                for jj in 0..3 {
                    k[3 * b + jj][3 * a + i] = k[3 * a + i][3 * b + jj];
                    m[3 * b + jj][3 * a + i] = m[3 * a + i][3 * b + jj];
                }
            }
        }
    }
    Ok((k, m))
}

fn det3(j: &[[f64; 3]; 3]) -> f64 {
    j[0][0] * (j[1][1] * j[2][2] - j[1][2] * j[2][1])
        - j[0][1] * (j[1][0] * j[2][2] - j[1][2] * j[2][0])
        + j[0][2] * (j[1][0] * j[2][1] - j[1][1] * j[2][0])
}

fn inv3(j: &[[f64; 3]; 3], det: f64) -> [[f64; 3]; 3] {
    let c =
        |r0: usize, c0: usize, r1: usize, c1: usize| j[r0][c0] * j[r1][c1] - j[r0][c1] * j[r1][c0];
    [
        [
            c(1, 1, 2, 2) / det,
            -c(0, 1, 2, 2) / det,
            c(0, 1, 1, 2) / det,
        ],
        [
            -c(1, 0, 2, 2) / det,
            c(0, 0, 2, 2) / det,
            -c(0, 0, 1, 2) / det,
        ],
        [
            c(1, 0, 2, 1) / det,
            -c(0, 0, 2, 1) / det,
            c(0, 0, 1, 1) / det,
        ],
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Kronecker property and partition of unity (with zero derivative sum) at random points.
    #[test]
    fn shape_functions_interpolate_and_sum_to_one() {
        for (a, na) in NATURAL.iter().enumerate() {
            let (n, _) = shape(*na);
            for (b, &nb) in n.iter().enumerate() {
                let want = if a == b { 1.0 } else { 0.0 };
                assert!((nb - want).abs() < 1e-14, "N{b} at node {a} = {nb}");
            }
        }
        for p in [[0.3, -0.7, 0.1], [-0.9, 0.45, 0.8]] {
            let (n, dn) = shape(p);
            assert!((n.iter().sum::<f64>() - 1.0).abs() < 1e-14);
            for r in 0..3 {
                assert!(dn.iter().map(|d| d[r]).sum::<f64>().abs() < 1e-14);
            }
        }
    }

    /// Natural derivatives against central differences (step 1e-6: error ~1e-10).
    #[test]
    fn shape_derivatives_match_finite_differences() {
        let p = [0.31, -0.62, 0.17];
        let (_, dn) = shape(p);
        let h = 1e-6;
        for r in 0..3 {
            let (mut lo, mut hi) = (p, p);
            lo[r] -= h;
            hi[r] += h;
            let (nl, nh) = (shape(lo).0, shape(hi).0);
            for a in 0..NODES {
                let fd = (nh[a] - nl[a]) / (2.0 * h);
                assert!(
                    (fd - dn[a][r]).abs() < 1e-8,
                    "node {a}, ξ{r}: {fd} vs {}",
                    dn[a][r]
                );
            }
        }
    }

    /// Mass of a unit-density brick sums to its volume per direction; rigid motions
    /// (translations and linearized rotations) cost no strain energy.
    #[test]
    fn brick_mass_and_rigid_modes() {
        let (lx, ly, lz) = (0.3, 0.08, 0.01);
        let x: [[f64; 3]; NODES] = std::array::from_fn(|a| {
            let s = NATURAL[a];
            [
                0.5 * lx * (s[0] + 1.0),
                0.5 * ly * (s[1] + 1.0),
                0.5 * lz * (s[2] + 1.0),
            ]
        });
        let mat = Material {
            e: 2.1e11,
            nu: 0.3,
            rho: 1.0,
        };
        let (k, m) = element(&x, &mat).unwrap();
        let total: f64 = (0..NODES)
            .flat_map(|a| (0..NODES).map(move |b| (a, b)))
            .map(|(a, b)| m[3 * a][3 * b])
            .sum();
        assert!((total - lx * ly * lz).abs() < 1e-15 * 1e3);
        let kmax = k.iter().flatten().fold(0.0_f64, |s, v| s.max(v.abs()));
        let rigid: [fn([f64; 3]) -> [f64; 3]; 6] = [
            |_| [1.0, 0.0, 0.0],
            |_| [0.0, 1.0, 0.0],
            |_| [0.0, 0.0, 1.0],
            |p| [-p[1], p[0], 0.0],
            |p| [0.0, -p[2], p[1]],
            |p| [p[2], 0.0, -p[0]],
        ];
        for u in rigid {
            let q: Vec<f64> = x.iter().flat_map(|p| u(*p)).collect();
            for row in k.iter() {
                let f: f64 = row.iter().zip(&q).map(|(a, b)| a * b).sum();
                assert!(f.abs() < 1e-9 * kmax, "rigid motion loads the element: {f}");
            }
        }
    }
}
