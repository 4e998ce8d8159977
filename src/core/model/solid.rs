//! The multi-bay solid frame (paper §5, DESIGN §4.3): flat steel beams and couplers in the
//! x–z plane meshed with 20-node hexahedra ([`super::hex20`]), joined at rigid interfaces.
//!
//! Layout (x along the chords, z up, y out of the plane): a bottom chord at `z = 0` and
//! a top chord at `z = H`, each `bays` beams long (support → coupler → … → support); the
//! `bays − 1` bottom couplers are joined to the top ones by vertical beams, so
//! `H = beam length + coupler size`. The four chord ends are clamped (their end faces' nodes
//! are fixed).
//!
//! **Rigid interfaces.** Every beam end at a coupler, and the part of the coupler face it
//! meets (the beam's cross-section), is a rigid interface: its nodes follow a 6-DOF master at the
//! face centre `c` by the linearized rigid-body motion `u = u_m + ω × (x − c)`, entered in
//! the primal assembly as non-Boolean rows of `L` (paper (3)–(4)), as the lab frame's member
//! ends follow its joints. The two masters of a connection share the three translations and
//! the rotation about the beam axis; the two bending rotations of each side are their own
//! DOFs, tied by rotational springs `θ_j k_IP` (in-plane: about y) and `θ4 k_OP`
//! (out-of-plane), `k = factor · 4EI/L` of the beam about that axis (the moment that turns
//! a beam end clamped at the other end by a unit angle), `factor` = 50 in the paper.
//!
//! **Parameters**, in this order: `ip-left`, `ip-right`, `ip-vertical` (the in-plane
//! springs of every coupler's left, right and vertical connection) and `op` (every
//! out-of-plane spring).
//!
//! **Orientation.** DESIGN §4.3 puts the beams' 80 mm in the frame plane; here the 8 mm is
//! (`in_plane = 0.008`, `out_of_plane = 0.08` in `four-bay-solid.toml`). The frame is
//! symmetric about its mid-plane, so in-plane and out-of-plane modes decouple exactly and
//! the in-plane springs θ1–θ3 act on in-plane modes only. With 80 mm in the plane, the 11
//! lowest modes are all out-of-plane: the six modes would carry no information on
//! θ1–θ3 (measured: mode matching drifts them to 1e9 with a singular Hessian). The paper
//! identifies θ1–θ3 from six modes and shares θ4 because the out-of-plane connections
//! "would require high-frequency modes": its in-plane direction is the flexible one, as in
//! the lab frame (flat bars 50 × 11 mm, 11 mm in the plane).
//!
//! **Channels.** At the mesh node nearest to 1/3 and 2/3 of each beam's length on the beam's
//! axis (the middle of its width, paper §5), three translations: `<beam>.<1|2>.<x|y|z>`.
//! Beams are `B1…` (bottom chord, left to right), `T1…` (top chord) and `V1…` (verticals);
//! couplers `KB1…` and `KT1…`.

use super::hex20::{self, Material};
use faer::sparse::SymbolicSparseColMat;
use rayon::prelude::*;

use super::mesh::BoxMesh;
use super::sparse::{Accumulator, Csc};
use super::spec::{PARAMETERS, SolidFrameSpec};
use super::{Channel, Connection, Model, ModelError, Parameter, ParameterKind};

/// One part (beam or coupler) of the frame.
struct Part {
    name: String,
    mesh: BoxMesh,
    /// First global node number of the part.
    first: usize,
}

/// Where a mesh node's translations go: a linear combination of unique DOFs per direction
/// (empty: fixed).
type Combos = [Vec<(usize, f64)>; 3];

fn invalid(field: &str, reason: impl Into<String>) -> ModelError {
    ModelError::Invalid {
        field: field.to_string(),
        reason: reason.into(),
    }
}

/// The axis (0 = x, 2 = z) along which a beam runs.
fn beam_axis(name: &str) -> usize {
    if name.starts_with('V') { 2 } else { 0 }
}

/// Checks a `[solid_frame]` and assembles it.
pub(super) fn assemble(
    name: &str,
    sf: &SolidFrameSpec,
    bayesian: &super::spec::BayesSpec,
) -> Result<Model, ModelError> {
    if sf.bays < 2 {
        return Err(invalid(
            "solid_frame.bays",
            format!("must be at least 2, got {}", sf.bays),
        ));
    }
    let b = &sf.beam;
    for (f, v) in [
        ("solid_frame.beam.length", b.length),
        ("solid_frame.beam.in_plane", b.in_plane),
        ("solid_frame.beam.out_of_plane", b.out_of_plane),
        ("solid_frame.coupler.size", sf.coupler.size),
        ("solid_frame.material.E", sf.material.E),
        ("solid_frame.material.rho", sf.material.rho),
        ("solid_frame.spring_factor", sf.spring_factor),
    ] {
        super::finish::check_positive(f.to_string(), v)?;
    }
    if !(sf.material.nu > -1.0 && sf.material.nu < 0.5) {
        return Err(invalid(
            "solid_frame.material.nu",
            format!("must lie in (−1, 0.5), got {}", sf.material.nu),
        ));
    }
    if b.divisions.contains(&0) || sf.coupler.divisions == 0 {
        return Err(invalid(
            "solid_frame",
            "every `divisions` entry must be ≥ 1",
        ));
    }
    if sf.coupler.size < b.in_plane {
        return Err(invalid(
            "solid_frame.coupler.size",
            format!("must be at least the beam width {} m", b.in_plane),
        ));
    }
    // The interface on a coupler face is the beam's width about the face centre; it must
    // be made of whole mesh lines so that it matches nodes.
    let step = sf.coupler.size / (2 * sf.coupler.divisions) as f64;
    let margin = 0.5 * (sf.coupler.size - b.in_plane) / step;
    if (margin - margin.round()).abs() > 1e-9 {
        return Err(invalid(
            "solid_frame.coupler.divisions",
            "the beam width must start and end on the coupler's mesh lines (its half-element \
             grid)",
        ));
    }

    let (l, w, t, c) = (b.length, b.in_plane, b.out_of_plane, sf.coupler.size);
    let height = l + c;
    let pitch = l + c;
    let n_couplers = sf.bays - 1;

    // Parts, in a fixed order: bottom chord, top chord, verticals, then couplers.
    let mut parts: Vec<Part> = Vec::new();
    let mut push = |name: String, origin: [f64; 3], size: [f64; 3], div: [usize; 3]| {
        let first = parts
            .last()
            .map_or(0, |p: &Part| p.first + p.mesh.nodes.len());
        parts.push(Part {
            name,
            mesh: BoxMesh::new(origin, size, div),
            first,
        });
    };
    let chord_div = [b.divisions[0], b.divisions[2], b.divisions[1]];
    let vert_div = [b.divisions[1], b.divisions[2], b.divisions[0]];
    for (prefix, z0) in [("B", 0.0), ("T", height)] {
        for i in 0..sf.bays {
            push(
                format!("{prefix}{}", i + 1),
                [i as f64 * pitch, -0.5 * t, z0 - 0.5 * w],
                [l, t, w],
                chord_div,
            );
        }
    }
    for i in 0..n_couplers {
        let xc = (i + 1) as f64 * pitch - 0.5 * c;
        push(
            format!("V{}", i + 1),
            [xc - 0.5 * w, -0.5 * t, 0.5 * c],
            [w, t, l],
            vert_div,
        );
    }
    let cd = sf.coupler.divisions;
    for (prefix, z0) in [("KB", 0.0), ("KT", height)] {
        for i in 0..n_couplers {
            let xc = (i + 1) as f64 * pitch - 0.5 * c;
            push(
                format!("{prefix}{}", i + 1),
                [xc - 0.5 * c, -0.5 * t, z0 - 0.5 * c],
                [c, t, c],
                [cd, b.divisions[2], cd],
            );
        }
    }
    let n_nodes = parts.last().map_or(0, |p| p.first + p.mesh.nodes.len());
    let part_index = |name: &str| {
        parts
            .iter()
            .position(|p| p.name == name)
            .expect("part exists")
    };

    // The interfaces: (beam, its end 0 or 1, coupler or None for a clamped end).
    let mut interfaces: Vec<(usize, usize, Option<usize>)> = Vec::new();
    for prefix in ["B", "T"] {
        let kp = if prefix == "B" { "KB" } else { "KT" };
        for i in 0..sf.bays {
            let beam = part_index(&format!("{prefix}{}", i + 1));
            let left = (i > 0).then(|| part_index(&format!("{kp}{i}")));
            let right = (i + 1 < sf.bays).then(|| part_index(&format!("{kp}{}", i + 1)));
            interfaces.push((beam, 0, left));
            interfaces.push((beam, 1, right));
        }
    }
    for i in 0..n_couplers {
        let beam = part_index(&format!("V{}", i + 1));
        interfaces.push((beam, 0, Some(part_index(&format!("KB{}", i + 1)))));
        interfaces.push((beam, 1, Some(part_index(&format!("KT{}", i + 1)))));
    }

    let mut labels: Vec<String> = Vec::new();
    let mut new_dof = |label: String| {
        labels.push(label);
        labels.len() - 1
    };
    // Owner of every node: None = own DOFs (assigned below), Some(combos) = fixed or slave.
    let mut combos: Vec<Option<Combos>> = vec![None; n_nodes];
    let mat = Material {
        e: sf.material.E,
        nu: sf.material.nu,
        rho: sf.material.rho,
    };
    // Spring constants: 4EI/L about the in-plane bending axis (y: I = t w³/12) and the
    // out-of-plane one (I = w t³/12).
    let k_ip = sf.spring_factor * 4.0 * mat.e * t * w.powi(3) / 12.0 / l;
    let k_op = sf.spring_factor * 4.0 * mat.e * w * t.powi(3) / 12.0 / l;
    let mut springs: Vec<(usize, usize, usize, f64)> = Vec::new(); // (dof a, dof b, param, k)
    let mut connections: Vec<Connection> = Vec::new();
    let mut conn_of_param: [Vec<usize>; 4] = Default::default();

    let tol = 1e-9 * (l + c);
    for &(beam, end, coupler) in &interfaces {
        let bp = &parts[beam];
        let axis = beam_axis(&bp.name);
        let bm = &bp.mesh;
        let along = if end == 0 { 0 } else { 2 * bm.div[axis] };
        let beam_face: Vec<usize> = (0..bm.nodes.len())
            .filter(|&n| bm.nodes[n][axis] == along)
            .collect();
        let centre: [f64; 3] = std::array::from_fn(|r| {
            let at = match (r == axis, end) {
                (true, 0) => 0.0,
                (true, _) => 1.0,
                (false, _) => 0.5,
            };
            bm.origin[r] + at * bm.size[r]
        });
        let Some(coupler) = coupler else {
            for &n in &beam_face {
                combos[bp.first + n] = Some(Default::default());
            }
            continue;
        };
        let cp = &parts[coupler];
        let cm = &cp.mesh;
        let cname = format!("{}@{}", bp.name, cp.name);
        // The coupler face the beam end meets, restricted to the beam's width.
        let across = 2 - axis; // the other in-plane axis (x ↔ z)
        let coupler_face: Vec<usize> = (0..cm.nodes.len())
            .filter(|&n| {
                let x = cm.coord(n);
                (x[axis] - centre[axis]).abs() < tol
                    && (x[across] - centre[across]).abs() <= 0.5 * w + tol
            })
            .collect();
        // Shared: translations and the rotation about the beam axis; own: the bending
        // rotations about y (in plane) and about `across` (out of plane).
        let shared: [usize; 4] = [
            new_dof(format!("{cname}.ux")),
            new_dof(format!("{cname}.uy")),
            new_dof(format!("{cname}.uz")),
            new_dof(format!("{cname}.r{}", ["x", "y", "z"][axis])),
        ];
        let op_axis = across;
        let mut masters = Vec::new();
        for side in [&bp.name, &cp.name] {
            let ry = new_dof(format!("{cname}.{side}.ry"));
            let rop = new_dof(format!("{cname}.{side}.r{}", ["x", "y", "z"][op_axis]));
            let mut rot = [0; 3];
            rot[axis] = shared[3];
            rot[1] = ry;
            rot[op_axis] = rop;
            masters.push((rot, ry, rop));
        }
        for (side, (part, face)) in [(bp, &beam_face), (cp, &coupler_face)]
            .into_iter()
            .enumerate()
        {
            let (rot, _, _) = masters[side];
            for &n in face {
                let x = part.mesh.coord(n);
                let r = [x[0] - centre[0], x[1] - centre[1], x[2] - centre[2]];
                // u = u_m + ω × r: (ω_y r_z − ω_z r_y, ω_z r_x − ω_x r_z, ω_x r_y − ω_y r_x).
                let comb: Combos = [
                    vec![(shared[0], 1.0), (rot[1], r[2]), (rot[2], -r[1])],
                    vec![(shared[1], 1.0), (rot[2], r[0]), (rot[0], -r[2])],
                    vec![(shared[2], 1.0), (rot[0], r[1]), (rot[1], -r[0])],
                ];
                let slot = &mut combos[part.first + n];
                if slot.is_some() {
                    return Err(invalid(
                        "solid_frame",
                        format!("a node of {} belongs to two interfaces", part.name),
                    ));
                }
                *slot = Some(comb.map(|v| v.into_iter().filter(|&(_, c)| c != 0.0).collect()));
            }
        }
        // θ1 the coupler's left connection (a chord beam ending at it), θ2 its right one
        // (a chord beam starting at it), θ3 its vertical one.
        let ip_param = match (axis, end) {
            (2, _) => 2,
            (_, 1) => 0,
            _ => 1,
        };
        for (dofs, param, k) in [
            ((masters[0].1, masters[1].1), ip_param, k_ip),
            ((masters[0].2, masters[1].2), 3, k_op),
        ] {
            springs.push((dofs.0, dofs.1, param, k));
            let suffix = if param == 3 { "op" } else { "ip" };
            conn_of_param[param].push(connections.len());
            connections.push(Connection {
                name: format!("{cname}.{suffix}"),
                member: bp.name.clone(),
                node: cp.name.clone(),
                k,
                parameter: Some(param),
            });
        }
    }
    // Every other node gets its own three translations.
    for p in &parts {
        for n in 0..p.mesh.nodes.len() {
            let slot = &mut combos[p.first + n];
            if slot.is_none() {
                *slot = Some(std::array::from_fn(|r| {
                    vec![(
                        new_dof(format!("{}.n{n}.{}", p.name, ["x", "y", "z"][r])),
                        1.0,
                    )]
                }));
            }
        }
    }
    let combos: Vec<Combos> = combos
        .into_iter()
        .map(|c| c.expect("every node placed"))
        .collect();
    let n_dof = labels.len();

    let couplings: Vec<(usize, usize)> = springs.iter().map(|&(a, b, _, _)| (a, b)).collect();
    let (k0, mass) = element_matrices(&parts, &combos, &mat, n_dof, &couplings)?;
    let mut k_params: Vec<Accumulator> = vec![Accumulator::default(); PARAMETERS.len()];
    for &(a, b2, param, k) in &springs {
        k_params[param].add_mapped(&[[k, -k], [-k, k]], &[&[(a, 1.0)], &[(b2, 1.0)]]);
    }

    // Channels: the mesh node nearest to 1/3 and 2/3 of each beam's length on its axis (the
    // middle of its width and of its thickness); ties go to the lower node number.
    let mut channels = Vec::new();
    for p in parts.iter().filter(|p| !p.name.starts_with('K')) {
        let axis = beam_axis(&p.name);
        let m = &p.mesh;
        for (k, frac) in [(1, 1.0 / 3.0), (2, 2.0 / 3.0)] {
            let target: [f64; 3] = std::array::from_fn(|r| {
                m.origin[r] + if r == axis { frac } else { 0.5 } * m.size[r]
            });
            let dist = |n: usize| {
                let x = m.coord(n);
                (0..3).map(|r| (x[r] - target[r]).powi(2)).sum::<f64>()
            };
            let n = (0..m.nodes.len())
                .min_by(|&a, &b| dist(a).total_cmp(&dist(b)))
                .expect("a mesh has nodes");
            for (r, d) in ["x", "y", "z"].iter().enumerate() {
                let dofs = combos[p.first + n][r].clone();
                if dofs.is_empty() {
                    return Err(invalid(
                        "solid_frame",
                        format!("sensor {}.{k} is fixed", p.name),
                    ));
                }
                channels.push(Channel {
                    name: format!("{}.{k}.{d}", p.name),
                    dofs,
                });
            }
        }
    }

    let parameters = PARAMETERS
        .iter()
        .enumerate()
        .map(|(l, name)| Parameter {
            name: (*name).to_string(),
            nominal: 1.0,
            lower: None,
            upper: None,
            kind: ParameterKind::Connections(conn_of_param[l].clone()),
        })
        .collect();
    // K0 and M are mirrored by `element_matrices`; the springs' few entries here.
    let mut mats = vec![k0];
    mats.extend(
        k_params
            .iter()
            .map(|a| super::finish::symmetric_from_lower(a.build(n_dof))),
    );
    mats.push(mass);
    super::finish::finish_symmetric(
        name,
        labels,
        mats,
        parameters,
        connections,
        channels,
        bayesian.clone(),
    )
    .inspect(|m| debug_assert_eq!(m.n_dof(), n_dof))
}

/// `K` and `M` of every part's elements through `L` (each node's translations → `combos`),
/// assembled straight into their common sparse pattern (no triplet lists: on the four-bay
/// frame those were ~450 MB, most of an update's peak memory, and filling fresh pages
/// dominated the assembly time). The elements of a box mesh are one box translated, so
/// each part's element matrices are computed once, from its first element.
///
/// The pattern also holds each pair of `couplings` (the springs' DOFs) as explicit zeros,
/// so that it is the union of the model's patterns and `K0` serves as the union itself
/// (`UnionPattern::with_first`: no merge and no copy).
fn element_matrices(
    parts: &[Part],
    combos: &[Combos],
    mat: &Material,
    n: usize,
    couplings: &[(usize, usize)],
) -> Result<(Csc, Csc), ModelError> {
    // Every element's global DOFs, sorted, and the DOF → element incidence.
    let elements: Vec<(usize, [usize; hex20::NODES])> = parts
        .iter()
        .enumerate()
        .flat_map(|(ip, p)| p.mesh.elements().into_iter().map(move |e| (ip, e)))
        .collect();
    let terms = |ip: usize, nodes: &[usize; hex20::NODES], d: usize| {
        combos[parts[ip].first + nodes[d / 3]][d % 3].as_slice()
    };
    let element_dofs: Vec<Vec<usize>> = elements
        .iter()
        .map(|(ip, nodes)| {
            let mut dofs: Vec<usize> = (0..hex20::DOFS)
                .flat_map(|d| terms(*ip, nodes, d).iter().map(|&(g, _)| g))
                .collect();
            dofs.sort_unstable();
            dofs.dedup();
            dofs
        })
        .collect();
    let mut start = vec![0usize; n + 1];
    for dofs in &element_dofs {
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
    // Column j's rows: every DOF of every element at j. A node's DOFs are numbered in a
    // row and lie in the same elements: a column with the same elements as the one before
    // has its rows (two columns in three on a solid mesh, which saves sorting them).
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
            && incident[start[j - 1]..start[j]] == incident[start[j]..start[j + 1]]
        {
            row_idx.extend_from_within(col_ptr[j - 1]..first);
            col_ptr.push(row_idx.len());
            continue;
        }
        for &e in &incident[start[j]..start[j + 1]] {
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
    drop((mark, coupled));

    let per_part: Vec<(Box<hex20::ElementMatrix>, Box<hex20::ElementMatrix>)> = parts
        .iter()
        .enumerate()
        .map(|(ip, p)| {
            let Some(&(_, nodes)) = elements.iter().find(|(i, _)| *i == ip) else {
                return Ok((
                    Box::new([[0.0; hex20::DOFS]; hex20::DOFS]),
                    Box::new([[0.0; hex20::DOFS]; hex20::DOFS]),
                ));
            };
            let x = nodes.map(|nd| p.mesh.coord(nd));
            hex20::element(&x, mat)
                .map_err(|err| invalid("solid_frame", format!("{} element 0: {err}", p.name)))
        })
        .collect::<Result<_, _>>()?;
    // The lower triangles of K and M together, column by column (the columns split among
    // the worker threads), then mirrored. For column j and each element at j, in element
    // order, the positions of the element's DOFs i ≥ j in the column are found by one merge
    // of two sorted lists; each entry sums its terms in the order of the elements, whatever
    // the split, as the scatter of both triangles did before. On the four-bay frame: 20 ms,
    // where a binary search per entry, one thread for K and one for M, took 70–110 ms.
    let nnz = row_idx.len();
    // Zeros written here, on one thread, rather than left to the allocator's fresh pages:
    // the threads' concurrent first writes to those pages cost more than the scatter
    // itself (48 against 20 ms on the four-bay frame).
    let zeros = |len: usize| {
        let mut v = Vec::with_capacity(len);
        v.resize(len, 0.0);
        v
    };
    let (mut k_val, mut m_val): (Vec<f64>, Vec<f64>) = (zeros(nnz), zeros(nnz));
    let blocks = super::sparse::column_blocks(n);
    let mut k_rest = k_val.as_mut_slice();
    let mut m_rest = m_val.as_mut_slice();
    let mut shares = Vec::with_capacity(blocks.len() - 1);
    for w in blocks.windows(2) {
        let len = col_ptr[w[1]] - col_ptr[w[0]];
        let (k_share, k_tail) = k_rest.split_at_mut(len);
        let (m_share, m_tail) = m_rest.split_at_mut(len);
        shares.push((w[0]..w[1], k_share, m_share));
        (k_rest, m_rest) = (k_tail, m_tail);
    }
    // Each element's terms by local DOF, as (index in its sorted global DOFs, coefficient):
    // flat, so the scatter's inner loop follows no pointers.
    let local_terms: Vec<LocalTerms> = elements
        .par_iter()
        .zip(&element_dofs)
        .map(|((ip, nodes), dofs)| {
            let mut start = Vec::with_capacity(hex20::DOFS + 1);
            let mut list = Vec::new();
            start.push(0);
            for d in 0..hex20::DOFS {
                for &(g, c) in terms(*ip, nodes, d) {
                    let a = dofs.binary_search(&g).expect("an element's DOF");
                    list.push((a as u32, c));
                }
                start.push(u16::try_from(list.len()).expect("an element's terms fit"));
            }
            (start, list)
        })
        .collect();
    shares.into_par_iter().for_each(|(cols, k_share, m_share)| {
        let base = col_ptr[cols.start];
        let mut pos = Vec::new();
        for j in cols {
            let rows = &row_idx[col_ptr[j]..col_ptr[j + 1]];
            let at = col_ptr[j] - base;
            let diag = rows.partition_point(|&i| i < j);
            for &e in &incident[start[j]..start[j + 1]] {
                let dofs = &element_dofs[e];
                let aj = dofs.partition_point(|&i| i < j);
                pos.resize(dofs.len(), 0);
                let mut r = diag;
                for (a, &d) in dofs.iter().enumerate().skip(aj) {
                    while rows[r] != d {
                        r += 1; // the column holds every DOF of its elements
                    }
                    pos[a] = at + r;
                }
                let (ka, ma) = &per_part[elements[e].0];
                let (tstart, tlist) = &local_terms[e];
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
    });
    drop(local_terms);
    drop((incident, start, element_dofs));
    let mirrored = super::finish::mirror_lower(&col_ptr, &row_idx, &mut [&mut k_val, &mut m_val]);
    debug_assert!(mirrored, "an assembled pattern is structurally symmetric");
    // Exact zeros are dropped from M: the consistent mass couples no two directions, so two
    // thirds of the shared pattern is zero in M, and every mass product would read them. K
    // keeps the pattern's arrays (not a copy: 54 MB on the four-bay frame) with its few
    // zeros (5,002 of 3.36 million entries there, where roundoff cancels).
    let m = without_zeros(n, &col_ptr, &row_idx, &m_val);
    drop(m_val);
    let k = Csc::new(
        SymbolicSparseColMat::new_checked(n, n, col_ptr, None, row_idx),
        k_val,
    );
    Ok((k, m))
}

/// An element's terms: for each local DOF `d`, `list[start[d]..start[d + 1]]` holds
/// `(index in the element's sorted global DOFs, coefficient)`.
type LocalTerms = (Vec<u16>, Vec<(u32, f64)>);

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
        .ok_or_else(|| {
            invalid(
                "solid cantilever",
                "needs an even number of elements across",
            )
        })?;
    let channels = [("tip.y", 1), ("tip.z", 2)]
        .map(|(name, r)| Channel {
            name: name.to_string(),
            dofs: combos[tip][r].clone(),
        })
        .to_vec();
    super::finish::finish_symmetric(
        "solid-cantilever",
        labels,
        vec![k, m],
        Vec::new(),
        Vec::new(),
        channels,
        Default::default(),
    )
}
