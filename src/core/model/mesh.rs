//! Structured meshes of 20-node hexahedra on axis-aligned boxes (the solid frame's beams
//! and couplers).

use super::hex20;

/// A structured mesh of 20-node hexahedra on an axis-aligned box. Nodes live on the
/// "half grid" `(2·div + 1)` points per axis, where a point is a node when at most one of
/// its indices is odd (a corner: none; an edge midpoint: one).
#[derive(Debug, Clone)]
pub struct BoxMesh {
    pub origin: [f64; 3],
    pub size: [f64; 3],
    pub div: [usize; 3],
    /// Node number of every half-grid point (`usize::MAX` where there is none).
    grid: Vec<usize>,
    /// Half-grid index of every node.
    pub nodes: Vec<[usize; 3]>,
}

impl BoxMesh {
    pub fn new(origin: [f64; 3], size: [f64; 3], div: [usize; 3]) -> Self {
        let g = div.map(|d| 2 * d + 1);
        let mut grid = vec![usize::MAX; g[0] * g[1] * g[2]];
        let mut nodes = Vec::new();
        for k in 0..g[2] {
            for j in 0..g[1] {
                for i in 0..g[0] {
                    if (i % 2) + (j % 2) + (k % 2) <= 1 {
                        grid[i + g[0] * (j + g[1] * k)] = nodes.len();
                        nodes.push([i, j, k]);
                    }
                }
            }
        }
        Self {
            origin,
            size,
            div,
            grid,
            nodes,
        }
    }

    /// Node number at half-grid index `h`, if that point is a node.
    pub fn node_at(&self, h: [usize; 3]) -> Option<usize> {
        let g = self.div.map(|d| 2 * d + 1);
        if (0..3).any(|r| h[r] >= g[r]) {
            return None;
        }
        let n = self.grid[h[0] + g[0] * (h[1] + g[1] * h[2])];
        (n != usize::MAX).then_some(n)
    }

    /// Coordinates of node `n`.
    pub fn coord(&self, n: usize) -> [f64; 3] {
        let h = self.nodes[n];
        std::array::from_fn(|r| {
            self.origin[r] + self.size[r] * h[r] as f64 / (2 * self.div[r]) as f64
        })
    }

    /// The elements' node numbers, in the order of [`hex20::NATURAL`].
    pub fn elements(&self) -> Vec<[usize; hex20::NODES]> {
        let mut out = Vec::with_capacity(self.div.iter().product());
        for k in 0..self.div[2] {
            for j in 0..self.div[1] {
                for i in 0..self.div[0] {
                    out.push(std::array::from_fn(|a| {
                        let s = hex20::NATURAL[a];
                        let h = [
                            (2 * i as i64 + 1 + s[0] as i64) as usize,
                            (2 * j as i64 + 1 + s[1] as i64) as usize,
                            (2 * k as i64 + 1 + s[2] as i64) as usize,
                        ];
                        self.node_at(h).expect("an element's node is on the grid")
                    }));
                }
            }
        }
        out
    }
}
