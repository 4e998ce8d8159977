//! `boltwatch.checkpoint.v1`: a tracker's persistent state, and the eigen solver's warm
//! block so that a resume continues bit for bit. The envelope and the block are the
//! contract's; the state type is the tracker's ([`crate::pipeline::TrackerState`]).

use serde::{Deserialize, Serialize};

use super::wire::{Message, Schema};
use crate::core::modal::eigen::WarmBlock;

/// One checkpoint (module docs).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Checkpoint<S> {
    pub schema: Schema<Checkpoint<()>>,
    pub state: S,
    /// `null` before the first eigen solve.
    pub eigen_block: Option<EigenBlock>,
    /// The daemon's write-ahead position: the inputs logged after it were not yet handled
    /// when this state was taken, and a restart replays them (absent in replays).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub wal: Option<WalPosition>,
    /// A fleet daemon's place in the write-ahead tail it keeps in Zenoh (absent otherwise).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fleet: Option<FleetPosition>,
}

/// Where a fleet daemon's checkpoint stands: written in ownership `epoch` by `owner`, with
/// the write-ahead entries of that epoch from `next` on not yet handled (and those of later
/// epochs, written after it, none handled).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct FleetPosition {
    pub epoch: u64,
    pub owner: String,
    pub next: u64,
}

/// A position in the daemon's rolling log: the `modal`-th modal set (from 0) of log file
/// `file` (its name in the log directory), and everything after it in later files.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct WalPosition {
    pub file: String,
    pub modal: u64,
}

impl WalPosition {
    /// The position just after this input: where a resume starts once it is handled.
    pub fn after(&self) -> WalPosition {
        WalPosition {
            file: self.file.clone(),
            modal: self.modal + 1,
        }
    }
}

impl Message for Checkpoint<()> {
    const SCHEMA: &'static str = "boltwatch.checkpoint.v1";
}

/// A [`WarmBlock`] on the wire: θ, the mode count, the Ritz values and the vectors column
/// by column.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EigenBlock {
    pub theta: Vec<f64>,
    pub n_modes: usize,
    pub lambda: Vec<f64>,
    pub x: Vec<Vec<f64>>,
}

impl From<&WarmBlock> for EigenBlock {
    fn from(b: &WarmBlock) -> Self {
        Self {
            theta: b.theta.clone(),
            n_modes: b.n_modes,
            lambda: b.lambda.clone(),
            x: (0..b.x.ncols())
                .map(|j| (0..b.x.nrows()).map(|i| b.x[(i, j)]).collect())
                .collect(),
        }
    }
}

impl EigenBlock {
    /// The block, checked against the model's sizes; the error says what does not fit.
    pub fn into_warm_block(self, n_dof: usize, n_params: usize) -> Result<WarmBlock, String> {
        let q = self.x.len();
        if self.theta.len() != n_params
            || self.lambda.len() != q
            || self.n_modes > q
            || self.x.iter().any(|c| c.len() != n_dof)
        {
            return Err(format!(
                "sizes (θ {}, λ {}, modes {}, vectors {q}) do not fit the model ({n_params} parameters, {n_dof} DOFs)",
                self.theta.len(),
                self.lambda.len(),
                self.n_modes
            ));
        }
        Ok(WarmBlock {
            theta: self.theta,
            n_modes: self.n_modes,
            lambda: self.lambda,
            x: faer::Mat::from_fn(n_dof, q, |i, j| self.x[j][i]),
        })
    }
}
