//! A fleet lane's state in the Zenoh storages (`daemon.state = "zenoh"`, layout in
//! [`crate::daemon::fleet::state`]): each input is put as a write-ahead entry before it is
//! handled, each checkpoint is put with the position after the entries it covers, and then
//! the entries and older checkpoints it makes obsolete are deleted. Every write first asks
//! the lane's [`Fence`]: a daemon whose epoch moved on writes nothing.

use std::sync::Arc;

use anyhow::Result;
use zenoh::Wait;
use zenoh::qos::CongestionControl;

use crate::contract::{Checkpoint, FleetPosition, to_wire};
use crate::daemon::fleet::fence::Fence;
use crate::daemon::fleet::state::{WalEntry, checkpoint_key, wal_key};
use crate::io::zenoh::zerr;
use crate::pipeline::TrackerState;

/// One lane's link to its state in the storages (module docs).
pub struct Remote {
    session: zenoh::Session,
    pub fence: Arc<Fence>,
    /// The next write-ahead entry's number in this epoch.
    next_seq: u64,
    /// Keys the next checkpoint makes obsolete: the state fetched at the takeover, and the
    /// entries put since the last checkpoint.
    obsolete: Vec<String>,
}

impl Remote {
    /// A link for the epoch of `fence`; `obsolete`: the keys of the state taken over.
    pub fn new(session: zenoh::Session, fence: Arc<Fence>, obsolete: Vec<String>) -> Self {
        Self {
            session,
            fence,
            next_seq: 0,
            obsolete,
        }
    }

    /// Puts `entries` in order as the epoch's next write-ahead entries (none once fenced).
    pub fn put_entries(&mut self, entries: &[WalEntry]) -> Result<()> {
        for e in entries {
            if !self.fence.allows() {
                return Ok(());
            }
            let key = wal_key(&self.fence.structure, self.fence.epoch, self.next_seq);
            self.put(&key, e.encode())?;
            self.obsolete.push(key);
            self.next_seq += 1;
        }
        Ok(())
    }

    /// Puts the checkpoint `c` of the state after every entry put so far, then deletes
    /// what it makes obsolete (none of it once fenced).
    pub fn put_checkpoint(&mut self, mut c: Checkpoint<TrackerState>) -> Result<()> {
        if !self.fence.allows() {
            return Ok(());
        }
        let (structure, epoch) = (&self.fence.structure, self.fence.epoch);
        c.fleet = Some(FleetPosition {
            epoch,
            owner: self.fence.owner.clone(),
            next: self.next_seq,
        });
        let key = checkpoint_key(structure, epoch);
        self.put(&key, to_wire(&c))?;
        for k in std::mem::take(&mut self.obsolete) {
            if k != key {
                self.session
                    .delete(&k)
                    .congestion_control(CongestionControl::Block)
                    .wait()
                    .map_err(zerr(format!("cannot delete {k}")))?;
            }
        }
        Ok(())
    }

    fn put(&self, key: &str, bytes: Vec<u8>) -> Result<()> {
        self.session
            .put(key, bytes)
            .congestion_control(CongestionControl::Block)
            .wait()
            .map_err(zerr(format!("cannot put {key}")))
    }
}
