//! A fleet lane's state in the Zenoh storages (`daemon.state = "zenoh"`, layout in
//! [`crate::daemon::fleet::state`]): each input is put as a write-ahead entry before it is
//! handled, each checkpoint is put with the position after the last entry handled, and then
//! the entries and older state it makes obsolete are deleted. Every write first asks the
//! lane's [`Fence`]: a daemon whose epoch moved on writes nothing.
//!
//! The entries go round a ring of [`WAL_SLOTS`] keys; a checkpoint is due
//! ([`Remote::needs_checkpoint`]) once half the ring is handled and not yet covered, so a
//! put never reaches an entry a checkpoint does not cover (a batch is at most a quarter of
//! the ring).

use std::collections::VecDeque;
use std::sync::Arc;

use anyhow::{Result, bail};
use zenoh::Wait;
use zenoh::qos::CongestionControl;

use crate::contract::{Checkpoint, FleetPosition, to_wire};
use crate::daemon::fleet::fence::Fence;
use crate::daemon::fleet::state::{WAL_SLOTS, WalEntry, checkpoint_key, wal_key};
use crate::io::zenoh::zerr;
use crate::pipeline::TrackerState;

/// One lane's link to its state in the storages (module docs).
pub struct Remote {
    session: zenoh::Session,
    pub fence: Arc<Fence>,
    /// The next write-ahead entry's number in this epoch.
    next_seq: u64,
    /// The first entry of this epoch not yet handled (what a checkpoint records).
    handled_next: u64,
    /// Entries of this epoch put and not yet deleted, oldest first.
    own: VecDeque<u64>,
    /// The state fetched at the takeover: obsolete once the tail it held has been handled
    /// again and a checkpoint of this epoch covers it.
    fetched: Vec<String>,
    /// The tail has been handled again ([`Remote::resumed`]).
    resumed: bool,
}

impl Remote {
    /// A link for the epoch of `fence`; `fetched`: the keys of the state taken over.
    pub fn new(session: zenoh::Session, fence: Arc<Fence>, fetched: Vec<String>) -> Self {
        Self {
            session,
            fence,
            next_seq: 0,
            handled_next: 0,
            own: VecDeque::new(),
            fetched,
            resumed: false,
        }
    }

    /// Puts `entries` in order as the epoch's next write-ahead entries; the number of each
    /// (`None` once fenced: not stored).
    pub fn put_entries(&mut self, entries: &[WalEntry]) -> Result<Vec<Option<u64>>> {
        let mut seqs = Vec::with_capacity(entries.len());
        for e in entries {
            if !self.fence.allows() {
                seqs.push(None);
                continue;
            }
            let seq = self.next_seq;
            if self.own.len() as u64 >= WAL_SLOTS {
                bail!(
                    "the write-ahead ring of {} is full ({WAL_SLOTS} entries not covered by a checkpoint)",
                    self.fence.structure
                );
            }
            let f = &self.fence;
            self.put(
                &wal_key(&f.structure, &f.owner, seq),
                e.encode(f.epoch, seq),
            )?;
            self.own.push_back(seq);
            self.next_seq += 1;
            seqs.push(Some(seq));
        }
        Ok(seqs)
    }

    /// Entry `seq` has been handled: a checkpoint from now on covers it.
    pub fn handled(&mut self, seq: u64) {
        self.handled_next = self.handled_next.max(seq + 1);
    }

    /// Whether half the ring is handled and not yet covered by a checkpoint.
    pub fn needs_checkpoint(&self) -> bool {
        let covered = self.own.front().copied().unwrap_or(self.handled_next);
        self.handled_next.saturating_sub(covered) >= WAL_SLOTS / 2
    }

    /// The tail fetched at the takeover has been handled again: the next checkpoint covers
    /// it, and deletes it.
    pub fn resumed(&mut self) {
        self.resumed = true;
    }

    /// Puts the checkpoint `c`, taken after the entries handled so far, then deletes what
    /// it makes obsolete (none of it once fenced).
    pub fn put_checkpoint(&mut self, mut c: Checkpoint<TrackerState>) -> Result<()> {
        if !self.fence.allows() {
            return Ok(());
        }
        let f = self.fence.clone();
        c.fleet = Some(FleetPosition {
            epoch: f.epoch,
            owner: f.owner.clone(),
            next: self.handled_next,
        });
        let key = checkpoint_key(&f.structure, &f.owner);
        self.put(&key, to_wire(&c))?;
        let mut obsolete = Vec::new();
        if self.resumed {
            // Not this member's own keys reused in this epoch since the takeover.
            let mine: std::collections::HashSet<String> = (0..self.next_seq.min(WAL_SLOTS))
                .map(|s| wal_key(&f.structure, &f.owner, s))
                .chain([key])
                .collect();
            let fetched = std::mem::take(&mut self.fetched);
            obsolete.extend(fetched.into_iter().filter(|k| !mine.contains(k)));
        }
        while let Some(&seq) = self.own.front()
            && seq < self.handled_next
        {
            obsolete.push(wal_key(&f.structure, &f.owner, seq));
            self.own.pop_front();
        }
        for k in obsolete {
            self.session
                .delete(&k)
                .congestion_control(CongestionControl::Block)
                .wait()
                .map_err(zerr(format!("cannot delete {k}")))?;
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
