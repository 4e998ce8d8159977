//! Structure description → FE assembly → `K(θ) = K0 + Σ θ_l K_l` (paper (1)) and `M`.
//!
//! The model owns the sparse matrices (CSC, both triangles stored), the DOF labels, the
//! parameters, the bolted connections and the sensor channels (rows of the selection
//! matrix `D` of (7), here allowed to be non-Boolean). Assembly follows the primal
//! formulation (3)–(4): every mesh node's three DOFs are linear combinations of the unique
//! DOFs (a non-Boolean `L` where a member end is offset from a rigid joint's centre), and each
//! element contributes `Lᵀ k_e L`.

mod assemble;
mod assemble_check;
pub mod element;
mod finish;
pub mod frame3d;
pub mod hex20;
pub mod import;
mod matrix_market;
pub mod mesh;
pub mod solid;
mod solid_element;
pub mod space;
mod space_check;
pub mod sparse;
pub mod spec;

use faer::reborrow::ReborrowMut;
use faer::{Mat, MatMut};
pub use sparse::{Csc, Reordered, UnionPattern, ValueLayout};
pub use spec::ModelSpec;

/// What an updating parameter scales.
#[derive(Debug, Clone, PartialEq)]
pub enum ParameterKind {
    /// Rotational stiffness of bolted connections (indices into [`Model::connections`]).
    Connections(Vec<usize>),
    /// Young's modulus of a set of members (names).
    Modulus(Vec<String>),
    /// Discrete springs (names).
    Springs(Vec<String>),
    /// A stiffness matrix read from a file (an imported model, [`import`]).
    Matrix(String),
}

/// One updating parameter θ_l.
#[derive(Debug, Clone)]
pub struct Parameter {
    pub name: String,
    pub nominal: f64,
    /// Bounds of θ_l that mode matching keeps it within (an imported model's `lower` and
    /// `upper`), besides `--bounds`.
    pub lower: Option<f64>,
    pub upper: Option<f64>,
    pub kind: ParameterKind,
}

/// A bolted connection: member end ↔ node, nominal rotational stiffness `k` (N·m/rad).
#[derive(Debug, Clone)]
pub struct Connection {
    pub name: String,
    pub member: String,
    pub node: String,
    pub k: f64,
    /// The parameter that scales it, if any.
    pub parameter: Option<usize>,
}

/// A named place of an imported model: DOFs an effect of `diagnose` or `simulate --inject`
/// can act on (added mass on each, a grounded spring on each).
#[derive(Debug, Clone, PartialEq)]
pub struct Location {
    pub name: String,
    pub dofs: Vec<usize>,
}

/// A named sensor channel: `y = Σ c_i q_i` over the model DOFs.
#[derive(Debug, Clone)]
pub struct Channel {
    pub name: String,
    pub dofs: Vec<(usize, f64)>,
}

impl Channel {
    /// The channel's reading of a DOF vector.
    pub fn read(&self, q: &[f64]) -> f64 {
        self.dofs.iter().map(|&(i, c)| c * q[i]).sum()
    }
}

/// Errors in a model file, each naming the offending entry.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ModelError {
    #[error("model file is not valid TOML for a model: {0}")]
    Parse(String),
    #[error("{what} `{name}` is defined twice")]
    Duplicate { what: &'static str, name: String },
    #[error("{field}: unknown {what} `{name}`")]
    Unknown {
        field: String,
        what: &'static str,
        name: String,
    },
    #[error("{field}: {reason}")]
    Invalid { field: String, reason: String },
    #[error("M, DOF `{dof}`: {reason}")]
    Mass { dof: String, reason: String },
    #[error(
        "DOF `{dof}` has no mass and K(θ0) is singular on it (no stiffness at nominal θ): fix \
         the DOF, or give it stiffness or mass"
    )]
    MasslessSingular { dof: String },
}

/// The shipped lab-frame model, for unit tests.
#[cfg(test)]
pub(crate) fn lab_frame() -> Model {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/config/models/lab-frame.toml");
    Model::from_toml(&std::fs::read_to_string(path).expect("shipped model exists"))
        .expect("shipped model assembles")
}

/// An assembled FE model of class C (paper §2.1): `M` and `K(θ) = K0 + Σ θ_l K_l`.
#[derive(Debug, Clone)]
pub struct Model {
    pub name: String,
    dof_labels: Vec<String>,
    // The matrices are shared between copies of a model (a tracker's, a cross-check's, the
    // daemon's): on the four-bay solid frame each copy was ~0.3 GB. `K0` is the union
    // pattern's own matrix ([`UnionPattern::pattern`]).
    k_params: std::sync::Arc<Vec<Csc>>,
    m: std::sync::Arc<Csc>,
    parameters: Vec<Parameter>,
    connections: Vec<Connection>,
    channels: Vec<Channel>,
    /// Union of the patterns of K0, every K_l and M (positions 0, 1..=p, p+1 in `maps`),
    /// carrying K0's values.
    union: std::sync::Arc<UnionPattern>,
    /// DOFs without mass, ascending (see `finish::massless_dofs`).
    massless: Vec<usize>,
    /// Named places (imported models).
    locations: Vec<Location>,
    /// The union reordered for factorization, computed on first use ([`Model::reordered`]).
    reordered: std::sync::OnceLock<std::sync::Arc<Reordered>>,
    /// The model file's defaults for the Bayesian MAP.
    pub bayesian: spec::BayesSpec,
}

impl Model {
    /// Parses a model file's text and assembles it.
    pub fn from_toml(text: &str) -> Result<Self, ModelError> {
        let spec: ModelSpec = toml::from_str(text).map_err(|e| ModelError::Parse(e.to_string()))?;
        Self::from_spec(&spec)
    }

    /// Checks a parsed model file and assembles it.
    pub fn from_spec(spec: &ModelSpec) -> Result<Self, ModelError> {
        if let Some(space) = &spec.space_frame {
            spec.check_no_frame_entries()?;
            return space::assemble(&spec.name, space, &spec.bayesian);
        }
        match &spec.solid_frame {
            Some(solid) => {
                spec.check_no_frame_entries()?;
                solid::assemble(&spec.name, solid, &spec.bayesian)
            }
            None => assemble::assemble(spec),
        }
    }

    pub fn n_dof(&self) -> usize {
        self.dof_labels.len()
    }
    /// DOFs that carry no mass, ascending: `M` is singular on them and the model has
    /// [`Model::n_finite_modes`] modes.
    pub fn massless_dofs(&self) -> &[usize] {
        &self.massless
    }
    /// Modes of finite frequency: one per DOF that carries mass.
    pub fn n_finite_modes(&self) -> usize {
        self.n_dof() - self.massless.len()
    }
    /// Named places (an imported model's `locations`; none for the TOML models, whose
    /// effects name joints and members).
    pub fn locations(&self) -> &[Location] {
        &self.locations
    }
    pub fn n_params(&self) -> usize {
        self.parameters.len()
    }
    pub fn dof_labels(&self) -> &[String] {
        &self.dof_labels
    }
    pub fn parameters(&self) -> &[Parameter] {
        &self.parameters
    }
    pub fn connections(&self) -> &[Connection] {
        &self.connections
    }
    pub fn channels(&self) -> &[Channel] {
        &self.channels
    }
    pub fn channel_index(&self, name: &str) -> Option<usize> {
        self.channels.iter().position(|c| c.name == name)
    }
    /// This model with `extra` channels after its own (places a sensor could go: the
    /// matrices are shared, not copied). A name already used, or a DOF out of range, is an
    /// error naming it.
    pub fn with_channels(&self, extra: Vec<Channel>) -> Result<Model, ModelError> {
        let mut model = self.clone();
        for c in extra {
            let invalid = |reason: String| ModelError::Invalid {
                field: format!("channels.{}", c.name),
                reason,
            };
            if model.channel_index(&c.name).is_some() {
                return Err(invalid("is defined twice".into()));
            }
            if let Some(&(i, _)) = c.dofs.iter().find(|(i, _)| *i >= self.n_dof()) {
                return Err(invalid(format!("DOF {i} is out of range")));
            }
            model.channels.push(c);
        }
        Ok(model)
    }
    /// The nominal rotational stiffness (N·m/rad) of the connections parameter `l` scales,
    /// when it scales connections that share one (what θ_l multiplies in an estimate).
    pub fn connection_stiffness(&self, l: usize) -> Option<f64> {
        let ParameterKind::Connections(c) = &self.parameters[l].kind else {
            return None;
        };
        let k = self.connections[*c.first()?].k;
        (k.is_finite() && c.iter().all(|&i| self.connections[i].k == k)).then_some(k)
    }
    /// The nominal parameter vector θ0.
    pub fn nominal_theta(&self) -> Vec<f64> {
        self.parameters.iter().map(|p| p.nominal).collect()
    }
    /// What parameter `l` scales, as `(kind, name)` pairs: connection, member (modulus) or
    /// spring names.
    pub fn parameter_elements(&self, l: usize) -> Vec<(&'static str, String)> {
        match &self.parameters[l].kind {
            ParameterKind::Connections(idx) => idx
                .iter()
                .map(|&i| ("connection", self.connections[i].name.clone()))
                .collect(),
            ParameterKind::Modulus(m) => m.iter().map(|n| ("member", n.clone())).collect(),
            ParameterKind::Springs(s) => s.iter().map(|n| ("spring", n.clone())).collect(),
            ParameterKind::Matrix(f) => vec![("matrix", f.clone())],
        }
    }

    /// A starting θ for this (finer) model from `coarse_theta` of a coarser
    /// parameterization of the same structure (paper §4.2, stage I → stage II): each
    /// parameter takes the value of the coarse parameter that scales everything it scales,
    /// and its nominal value when no coarse parameter does (a parameter new at this stage).
    /// Returns, per parameter, the value and the coarse parameter's index if any.
    pub fn refine_theta(
        &self,
        coarse: &Model,
        coarse_theta: &[f64],
    ) -> Result<Vec<(f64, Option<usize>)>, ModelError> {
        let coarse_sets: Vec<_> = (0..coarse.n_params())
            .map(|c| coarse.parameter_elements(c))
            .collect();
        (0..self.n_params())
            .map(|l| {
                let mine = self.parameter_elements(l);
                let covering: Vec<usize> = (0..coarse_sets.len())
                    .filter(|&c| mine.iter().all(|e| coarse_sets[c].contains(e)))
                    .collect();
                match covering.as_slice() {
                    [] => Ok((self.parameters[l].nominal, None)),
                    [c] => Ok((coarse_theta[*c], Some(*c))),
                    _ => Err(ModelError::Invalid {
                        field: format!("parameters.{}", self.parameters[l].name),
                        reason: format!(
                            "covered by several parameters of the coarse model {} ({})",
                            coarse.name,
                            covering
                                .iter()
                                .map(|&c| coarse.parameters[c].name.as_str())
                                .collect::<Vec<_>>()
                                .join(", ")
                        ),
                    }),
                }
            })
            .collect()
    }

    /// `K0`, the part of the stiffness no parameter scales, on the union pattern (an
    /// explicit zero where only a `K_l`, `M` or the diagonal has an entry).
    pub fn k0(&self) -> &Csc {
        &self.union.pattern
    }
    /// `K_l = ∂K/∂θ_l`, paper (1)–(2).
    pub fn k_param(&self, l: usize) -> &Csc {
        &self.k_params[l]
    }
    pub fn mass(&self) -> &Csc {
        &self.m
    }
    pub fn union_pattern(&self) -> &UnionPattern {
        &self.union
    }

    /// The union pattern reordered (AMD) and analysed for sparse factorizations, shared by
    /// every solver of this model (computed once, on first use).
    pub fn reordered(&self) -> Result<&Reordered, faer::sparse::FaerError> {
        if let Some(r) = self.reordered.get() {
            return Ok(r);
        }
        let r = std::sync::Arc::new(Reordered::new(&self.union)?);
        // The ordering's and analysis' scratch (~0.1 GB on the four-bay frame, about the
        // matrices' size) back to the system when it is large, not kept for allocations
        // of other sizes.
        crate::release_scratch(self.matrix_bytes());
        Ok(self.reordered.get_or_init(|| r))
    }

    /// Bytes held by the matrices (values and indices of every `K_l`, `M`, and their
    /// union pattern, which carries `K0`, with its maps); copies of a model share them, and
    /// the reordered analysis.
    pub fn matrix_bytes(&self) -> u64 {
        let csc = |a: &Csc| (a.val().len() * 16 + (a.ncols() + 1) * 8) as u64;
        self.k_params.iter().map(csc).sum::<u64>()
            + csc(&self.m)
            + csc(&self.union.pattern)
            + self
                .union
                .maps
                .iter()
                .map(|m| m.len() as u64 * 4)
                .sum::<u64>()
    }

    /// `K(θ) − σ M` on the value array of [`Model::reordered`]'s lower triangle, paper (1).
    pub fn shifted_stiffness_reordered(
        &self,
        reordered: &Reordered,
        theta: &[f64],
        sigma: f64,
        out: &mut [f64],
    ) {
        self.shifted_into(reordered, theta, sigma, out);
    }

    /// `out −= σ M` on the value array of [`Model::reordered`]'s lower triangle.
    pub fn subtract_mass_reordered(&self, reordered: &Reordered, sigma: f64, out: &mut [f64]) {
        self.subtract_mass_into(reordered, sigma, out);
    }

    /// `K(θ) − σ M` on the union pattern's value array, paper (1).
    pub fn shifted_stiffness_values(&self, theta: &[f64], sigma: f64, out: &mut [f64]) {
        self.shifted_into(&*self.union, theta, sigma, out);
    }

    /// `out −= σ M` on the union pattern's value array (after
    /// [`Model::shifted_stiffness_values`] with σ = 0).
    pub fn subtract_mass_values(&self, sigma: f64, out: &mut [f64]) {
        self.subtract_mass_into(&*self.union, sigma, out);
    }

    /// `K(θ) − σ M` on a value array laid out by `layout` (source matrices 0 = K0,
    /// 1..=p = K_l, p + 1 = M, as in the union).
    fn shifted_into(&self, layout: &impl ValueLayout, theta: &[f64], sigma: f64, out: &mut [f64]) {
        out.iter_mut().for_each(|v| *v = 0.0);
        layout.add_into(0, self.k0(), 1.0, out);
        for (l, kl) in self.k_params.iter().enumerate() {
            layout.add_into(l + 1, kl, theta[l], out);
        }
        self.subtract_mass_into(layout, sigma, out);
    }

    fn subtract_mass_into(&self, layout: &impl ValueLayout, sigma: f64, out: &mut [f64]) {
        if sigma != 0.0 {
            layout.add_into(self.k_params.len() + 1, &self.m, -sigma, out);
        }
    }

    /// Dense `K(θ)` into `out` (n × n), paper (1).
    pub fn stiffness_dense_into(&self, theta: &[f64], mut out: MatMut<'_, f64>) {
        out.fill(0.0);
        scatter_dense(self.k0(), 1.0, out.rb_mut());
        for (l, kl) in self.k_params.iter().enumerate() {
            scatter_dense(kl, theta[l], out.rb_mut());
        }
    }

    /// This model with additions that need no geometry (the effects a diagnosis can put
    /// into an imported model): `K0` scaled by `1 + k0_scale`, `springs` (DOF, N/m or
    /// N·m/rad) added to `K0`'s diagonal and `masses` (DOF, kg or kg·m²) to `M`'s. The
    /// result goes through the checks of every assembly (massless DOFs, symmetry).
    pub fn edited(
        &self,
        masses: &[(usize, f64)],
        springs: &[(usize, f64)],
        k0_scale: f64,
    ) -> Result<Model, ModelError> {
        let n = self.n_dof();
        let with_diagonal = |a: &Csc, scale: f64, add: &[(usize, f64)]| {
            let s = a.symbolic();
            let entries: Vec<(usize, usize, f64)> = (0..n)
                .flat_map(|j| {
                    s.row_idx_of_col_raw(j)
                        .iter()
                        .zip(a.val_of_col(j))
                        .map(move |(&i, &v)| (i, j, scale * v))
                })
                .chain(add.iter().map(|&(i, v)| (i, i, v)))
                .collect();
            sparse::csc_from_triplets(n, entries.into_iter())
        };
        let mut mats = Vec::with_capacity(self.n_params() + 2);
        mats.push(with_diagonal(self.k0(), 1.0 + k0_scale, springs));
        mats.extend(self.k_params.iter().cloned());
        mats.push(with_diagonal(&self.m, 1.0, masses));
        let mut model = finish::finish(
            &self.name,
            self.dof_labels.clone(),
            mats,
            self.parameters.clone(),
            self.connections.clone(),
            self.channels.clone(),
            self.bayesian.clone(),
        )?;
        model.locations = self.locations.clone();
        Ok(model)
    }

    /// The DOFs of a place of this model: a named location, or one DOF by its label.
    pub fn location_dofs(&self, name: &str) -> Option<Vec<usize>> {
        self.locations
            .iter()
            .find(|l| l.name == name)
            .map(|l| l.dofs.clone())
            .or_else(|| {
                self.dof_labels
                    .iter()
                    .position(|l| l == name)
                    .map(|i| vec![i])
            })
    }

    /// Dense `M`.
    pub fn mass_dense(&self) -> Mat<f64> {
        let mut out = Mat::zeros(self.n_dof(), self.n_dof());
        scatter_dense(&self.m, 1.0, out.as_mut());
        out
    }
}

fn scatter_dense(a: &Csc, alpha: f64, mut out: MatMut<'_, f64>) {
    let s = a.symbolic();
    for j in 0..a.ncols() {
        for (&i, &v) in s.row_idx_of_col_raw(j).iter().zip(a.val_of_col(j)) {
            out[(i, j)] += alpha * v;
        }
    }
}
