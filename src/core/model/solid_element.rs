//! The solid frame's element assembly: the parts' 20-node hexahedra ([`super::hex20`])
//! entered through the primal `L` (paper (3)–(4)), each mesh node's translations a linear
//! combination of unique DOFs, into `K0` and `M` on one sparse pattern.
//!
//! This module owns the parts (a box mesh and its first global node number), the node → DOF
//! combinations, and the steps of the assembly: each element's DOFs and the DOF → element
//! incidence, the pattern, each part's element matrices, and the parallel scatter of the
//! lower triangles of `Lᵀ k_e L` and `Lᵀ m_e L`, mirrored at the end; and the one-box solid
//! cantilever that gives the element its known answers ([`solid_cantilever`], re-exported
//! by [`super::solid`]). The frame's layout, its rigid interfaces and springs are
//! [`super::solid`]'s.

use std::ops::Range;

use faer::sparse::SymbolicSparseColMat;
use rayon::prelude::*;

use super::finish::{finish_symmetric, mirror_lower};
use super::hex20::{self, ElementMatrix, Material};
use super::mesh::BoxMesh;
use super::sparse::{Csc, column_blocks};
use super::{Channel, Model, ModelError};

/// One part (beam or coupler) of the frame.
pub(super) struct Part {
    pub(super) name: String,
    pub(super) mesh: BoxMesh,
    /// First global node number of the part.
    pub(super) first: usize,
}

/// Where a mesh node's translations go: a linear combination of unique DOFs per direction
/// (empty: fixed).
pub(super) type Combos = [Vec<(usize, f64)>; 3];

/// An element's stiffness and consistent mass.
type ElementPair = (Box<ElementMatrix>, Box<ElementMatrix>);

/// An element's terms: for each local DOF `d`, `list[start[d]..start[d + 1]]` holds
/// `(index in the element's sorted global DOFs, coefficient)`.
type LocalTerms = (Vec<u16>, Vec<(u32, f64)>);

/// A worker thread's columns and its shares of the value arrays of `K` and `M`.
type Share<'a> = (Range<usize>, &'a mut [f64], &'a mut [f64]);

/// `K` and `M` of every part's elements through `L` (each node's translations → `combos`),
/// assembled straight into their common sparse pattern (no triplet lists: on the four-bay
/// frame those were ~450 MB, most of an update's peak memory, and filling fresh pages
/// dominated the assembly time). The elements of a box mesh are one box translated, so
/// each part's element matrices are computed once, from its first element.
///
/// The pattern also holds each pair of `couplings` (the springs' DOFs) as explicit zeros,
/// so that it is the union of the model's patterns and `K0` serves as the union itself
/// (`UnionPattern::with_first`: no merge and no copy).
pub(super) fn element_matrices(
    parts: &[Part],
    combos: &[Combos],
    mat: &Material,
    n: usize,
    couplings: &[(usize, usize)],
) -> Result<(Csc, Csc), ModelError> {
    let node_map = NodeMap { parts, combos };
    let elements = Elements::new(node_map);
    let incidence = Incidence::new(&elements.dofs, n);
    let (col_ptr, row_idx) = pattern(n, &incidence, &elements.dofs, couplings);
    let per_part = part_matrices(parts, &elements, mat)?;
    let nnz = row_idx.len();
    let (mut k_val, mut m_val): (Vec<f64>, Vec<f64>) = (zeros(nnz), zeros(nnz));
    let shares = split_shares(&col_ptr, n, &mut k_val, &mut m_val);
    let local_terms = local_terms(node_map, &elements);
    let scatter = Scatter {
        col_ptr: &col_ptr,
        row_idx: &row_idx,
        incidence: &incidence,
        elements: &elements,
        per_part: &per_part,
        local_terms: &local_terms,
    };
    shares
        .into_par_iter()
        .for_each(|share| scatter.add_share(share));
    drop(local_terms);
    drop((incidence, elements));
    Ok(mirrored(n, col_ptr, row_idx, k_val, m_val))
}

/// The parts and `L`: where every mesh node's translations go.
#[derive(Clone, Copy)]
struct NodeMap<'a> {
    parts: &'a [Part],
    combos: &'a [Combos],
}

impl<'a> NodeMap<'a> {
    /// Row `d` of the `L` of element `nodes` of part `ip`: `(unique DOF, coefficient)`.
    fn terms(&self, ip: usize, nodes: &[usize; hex20::NODES], d: usize) -> &'a [(usize, f64)] {
        self.combos[self.parts[ip].first + nodes[d / 3]][d % 3].as_slice()
    }
}

/// Every part's elements, in part order: `(part index, node numbers)`, and each element's
/// global DOFs, sorted.
struct Elements {
    nodes: Vec<(usize, [usize; hex20::NODES])>,
    dofs: Vec<Vec<usize>>,
}

impl Elements {
    /// The elements of `node_map`'s parts and their DOFs.
    fn new(node_map: NodeMap<'_>) -> Self {
        let nodes: Vec<(usize, [usize; hex20::NODES])> = node_map
            .parts
            .iter()
            .enumerate()
            .flat_map(|(ip, p)| p.mesh.elements().into_iter().map(move |e| (ip, e)))
            .collect();
        let dofs = nodes
            .iter()
            .map(|(ip, el)| {
                let mut dofs: Vec<usize> = (0..hex20::DOFS)
                    .flat_map(|d| node_map.terms(*ip, el, d).iter().map(|&(g, _)| g))
                    .collect();
                dofs.sort_unstable();
                dofs.dedup();
                dofs
            })
            .collect();
        Self { nodes, dofs }
    }
}

/// The DOF → element incidence: the elements at DOF `g`, ascending, are
/// `incident[start[g]..start[g + 1]]`.
struct Incidence {
    start: Vec<usize>,
    incident: Vec<usize>,
}

impl Incidence {
    /// The incidence of `element_dofs` (each element's DOFs, of `n`).
    fn new(element_dofs: &[Vec<usize>], n: usize) -> Self {
        let mut start = vec![0usize; n + 1];
        for dofs in element_dofs {
            for &g in dofs {
                start[g + 1] += 1;
            }
        }
        for j in 0..n {
            start[j + 1] += start[j];
        }
        let mut incident = vec![0usize; start[n]];
        let mut next = start.clone();
        for (e, dofs) in element_dofs.iter().enumerate() {
            for &g in dofs {
                incident[next[g]] = e;
                next[g] += 1;
            }
        }
        Self { start, incident }
    }

    /// The elements at DOF `g`, ascending.
    fn at(&self, g: usize) -> &[usize] {
        &self.incident[self.start[g]..self.start[g + 1]]
    }
}

/// The common pattern of `K0` and `M`, both triangles, as `(col_ptr, row_idx)`: column `j`'s
/// rows are every DOF of every element at `j` and the DOFs `couplings` pair with `j`,
/// ascending. A node's DOFs are numbered in a row and lie in the same elements: a column
/// with the same elements as the one before has its rows (two columns in three on a solid
/// mesh, which saves sorting them).
fn pattern(
    n: usize,
    incidence: &Incidence,
    element_dofs: &[Vec<usize>],
    couplings: &[(usize, usize)],
) -> (Vec<usize>, Vec<usize>) {
    let mut coupled: Vec<Vec<usize>> = vec![Vec::new(); n];
    for &(a, b) in couplings {
        coupled[a].push(b);
        coupled[b].push(a);
    }
    let mut col_ptr = Vec::with_capacity(n + 1);
    let mut row_idx = Vec::new();
    let mut mark = vec![usize::MAX; n];
    col_ptr.push(0);
    for j in 0..n {
        let first = row_idx.len();
        if j > 0
            && coupled[j - 1].is_empty()
            && coupled[j].is_empty()
            && incidence.at(j - 1) == incidence.at(j)
        {
            row_idx.extend_from_within(col_ptr[j - 1]..first);
            col_ptr.push(row_idx.len());
            continue;
        }
        for &e in incidence.at(j) {
            for &i in &element_dofs[e] {
                if mark[i] != j {
                    mark[i] = j;
                    row_idx.push(i);
                }
            }
        }
        for &i in &coupled[j] {
            if mark[i] != j {
                mark[i] = j;
                row_idx.push(i);
            }
        }
        row_idx[first..].sort_unstable();
        col_ptr.push(row_idx.len());
    }
    (col_ptr, row_idx)
}

/// Each part's element stiffness and consistent mass ([`hex20::element`]), from its first
/// element (zeros for a part without elements).
fn part_matrices(
    parts: &[Part],
    elements: &Elements,
    mat: &Material,
) -> Result<Vec<ElementPair>, ModelError> {
    parts
        .iter()
        .enumerate()
        .map(|(ip, p)| {
            let Some(&(_, nodes)) = elements.nodes.iter().find(|(i, _)| *i == ip) else {
                return Ok((
                    Box::new([[0.0; hex20::DOFS]; hex20::DOFS]),
                    Box::new([[0.0; hex20::DOFS]; hex20::DOFS]),
                ));
            };
            let x = nodes.map(|nd| p.mesh.coord(nd));
            hex20::element(&x, mat).map_err(|err| ModelError::Invalid {
                field: "solid_frame".to_string(),
                reason: format!("{} element 0: {err}", p.name),
            })
        })
        .collect()
}

/// `len` zeros, written here, on one thread, rather than left to the allocator's fresh
/// pages: the threads' concurrent first writes to those pages cost more than the scatter
/// itself (48 against 20 ms on the four-bay frame).
fn zeros(len: usize) -> Vec<f64> {
    let mut v = Vec::with_capacity(len);
    v.resize(len, 0.0);
    v
}

/// The value arrays `k_val` and `m_val` (on the pattern `col_ptr`) cut into the worker
/// threads' shares, one per column block ([`column_blocks`]).
fn split_shares<'a>(
    col_ptr: &[usize],
    n: usize,
    k_val: &'a mut [f64],
    m_val: &'a mut [f64],
) -> Vec<Share<'a>> {
    let blocks = column_blocks(n);
    let mut k_rest = k_val;
    let mut m_rest = m_val;
    let mut shares = Vec::with_capacity(blocks.len() - 1);
    for w in blocks.windows(2) {
        let len = col_ptr[w[1]] - col_ptr[w[0]];
        let (k_share, k_tail) = k_rest.split_at_mut(len);
        let (m_share, m_tail) = m_rest.split_at_mut(len);
        shares.push((w[0]..w[1], k_share, m_share));
        (k_rest, m_rest) = (k_tail, m_tail);
    }
    shares
}

/// Each element's terms by local DOF, as (index in its sorted global DOFs, coefficient):
/// flat, so the scatter's inner loop follows no pointers.
fn local_terms(node_map: NodeMap<'_>, elements: &Elements) -> Vec<LocalTerms> {
    elements
        .nodes
        .par_iter()
        .zip(&elements.dofs)
        .map(|((ip, nodes), dofs)| {
            let mut start = Vec::with_capacity(hex20::DOFS + 1);
            let mut list = Vec::new();
            start.push(0);
            for d in 0..hex20::DOFS {
                for &(g, c) in node_map.terms(*ip, nodes, d) {
                    let a = dofs.binary_search(&g).expect("an element's DOF");
                    list.push((a as u32, c));
                }
                start.push(u16::try_from(list.len()).expect("an element's terms fit"));
            }
            (start, list)
        })
        .collect()
}

/// The lower triangles of `K` and `M` together, column by column (the columns split among
/// the worker threads). For column j and each element at j, in element order, the positions
/// of the element's DOFs i ≥ j in the column are found by one merge of two sorted lists;
/// each entry sums its terms in the order of the elements, whatever the split, as the
/// scatter of both triangles did before. On the four-bay frame: 20 ms, where a binary
/// search per entry, one thread for K and one for M, took 70–110 ms.
struct Scatter<'a> {
    col_ptr: &'a [usize],
    row_idx: &'a [usize],
    incidence: &'a Incidence,
    elements: &'a Elements,
    per_part: &'a [ElementPair],
    local_terms: &'a [LocalTerms],
}

impl Scatter<'_> {
    /// Scatters every element at the share's columns into its values.
    fn add_share(&self, share: Share<'_>) {
        let (cols, k_share, m_share) = share;
        let base = self.col_ptr[cols.start];
        let mut pos = Vec::new();
        for j in cols {
            let rows = &self.row_idx[self.col_ptr[j]..self.col_ptr[j + 1]];
            let at = self.col_ptr[j] - base;
            let diag = rows.partition_point(|&i| i < j);
            for &e in self.incidence.at(j) {
                let dofs = &self.elements.dofs[e];
                let aj = dofs.partition_point(|&i| i < j);
                pos.resize(dofs.len(), 0);
                let mut r = diag;
                for (a, &d) in dofs.iter().enumerate().skip(aj) {
                    while rows[r] != d {
                        r += 1; // the column holds every DOF of its elements
                    }
                    pos[a] = at + r;
                }
                self.add_element_column(e, aj, &pos, k_share, m_share);
            }
        }
    }

    /// Element `e`'s part of column `j` (its sorted DOF `aj`) of the lower triangles of
    /// `Lᵀ k_e L` and `Lᵀ m_e L`, paper (3)–(4): entry `a ≥ aj` goes to `pos[a]`.
    fn add_element_column(
        &self,
        e: usize,
        aj: usize,
        pos: &[usize],
        k_share: &mut [f64],
        m_share: &mut [f64],
    ) {
        let (ka, ma) = &self.per_part[self.elements.nodes[e].0];
        let (tstart, tlist) = &self.local_terms[e];
        let of = |d: usize| &tlist[tstart[d] as usize..tstart[d + 1] as usize];
        for q in 0..hex20::DOFS {
            for &(b, cj) in of(q) {
                if b as usize != aj {
                    continue;
                }
                for p in 0..hex20::DOFS {
                    let (kv, mv) = (ka[p][q] * cj, ma[p][q] * cj);
                    if kv == 0.0 && mv == 0.0 {
                        continue;
                    }
                    for &(a, ci) in of(p) {
                        if a as usize >= aj {
                            k_share[pos[a as usize]] += ci * kv;
                            m_share[pos[a as usize]] += ci * mv;
                        }
                    }
                }
            }
        }
    }
}

/// `K` and `M` from their lower triangles' values on the pattern, mirrored. Exact zeros are
/// dropped from M: the consistent mass couples no two directions, so two thirds of the
/// shared pattern is zero in M, and every mass product would read them. K keeps the
/// pattern's arrays (not a copy: 54 MB on the four-bay frame) with its few zeros (5,002 of
/// 3.36 million entries there, where roundoff cancels).
fn mirrored(
    n: usize,
    col_ptr: Vec<usize>,
    row_idx: Vec<usize>,
    mut k_val: Vec<f64>,
    mut m_val: Vec<f64>,
) -> (Csc, Csc) {
    let symmetric = mirror_lower(&col_ptr, &row_idx, &mut [&mut k_val, &mut m_val]);
    debug_assert!(symmetric, "an assembled pattern is structurally symmetric");
    let m = without_zeros(n, &col_ptr, &row_idx, &m_val);
    drop(m_val);
    let k = Csc::new(
        SymbolicSparseColMat::new_checked(n, n, col_ptr, None, row_idx),
        k_val,
    );
    (k, m)
}

/// The `n × n` CSC matrix with the given pattern and values, exact zeros left out.
fn without_zeros(n: usize, col_ptr: &[usize], row_idx: &[usize], val: &[f64]) -> Csc {
    let mut ptr = Vec::with_capacity(n + 1);
    let mut rows = Vec::new();
    let mut vals = Vec::new();
    ptr.push(0);
    for j in 0..n {
        for p in col_ptr[j]..col_ptr[j + 1] {
            if val[p] != 0.0 {
                rows.push(row_idx[p]);
                vals.push(val[p]);
            }
        }
        ptr.push(rows.len());
    }
    Csc::new(
        SymbolicSparseColMat::new_checked(n, n, ptr, None, rows),
        vals,
    )
}

/// A solid cantilever: one box `[0, length] × [−width/2, width/2] × [−height/2, height/2]`
/// meshed with `div` hexahedra, its face `x = 0` clamped, no parameters, and channels
/// `tip.y`, `tip.z` at the centre of the free end's edge `y = 0`, `z = +height/2`. A known
/// answer for the element (Euler–Bernoulli, mesh convergence) and a small model on which
/// the dense and sparse eigen solvers can both run.
pub fn solid_cantilever(
    length: f64,
    width: f64,
    height: f64,
    div: [usize; 3],
    mat: Material,
) -> Result<Model, ModelError> {
    let part = Part {
        name: "bar".to_string(),
        mesh: BoxMesh::new(
            [0.0, -0.5 * width, -0.5 * height],
            [length, width, height],
            div,
        ),
        first: 0,
    };
    let mut labels = Vec::new();
    let combos: Vec<Combos> = (0..part.mesh.nodes.len())
        .map(|n| {
            if part.mesh.nodes[n][0] == 0 {
                Default::default()
            } else {
                std::array::from_fn(|r| {
                    labels.push(format!("bar.n{n}.{}", ["x", "y", "z"][r]));
                    vec![(labels.len() - 1, 1.0)]
                })
            }
        })
        .collect();
    let (k, m) = element_matrices(
        std::slice::from_ref(&part),
        &combos,
        &mat,
        labels.len(),
        &[],
    )?;
    let tip = part
        .mesh
        .node_at([2 * div[0], div[1], 2 * div[2]])
        .ok_or_else(|| ModelError::Invalid {
            field: "solid cantilever".to_string(),
            reason: "needs an even number of elements across".into(),
        })?;
    let channels = [("tip.y", 1), ("tip.z", 2)]
        .map(|(name, r)| Channel {
            name: name.to_string(),
            dofs: combos[tip][r].clone(),
        })
        .to_vec();
    finish_symmetric(
        "solid-cantilever",
        labels,
        vec![k, m],
        Vec::new(),
        Vec::new(),
        channels,
        Default::default(),
    )
}
