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

#[cfg(test)]
mod tests {
    use std::collections::BTreeMap;
    use std::sync::{Arc, Mutex};

    use super::*;
    use crate::daemon::fleet::state::Fetched;
    use zenoh::sample::SampleKind;

    /// A session on its own, with a "storage" of its own puts and deletes (what the
    /// routers' storages would hold).
    /// What the storages would hold: key → value.
    type Store = Arc<Mutex<BTreeMap<String, Vec<u8>>>>;

    fn session_with_store() -> (zenoh::Session, Store) {
        let mut c = zenoh::Config::default();
        c.insert_json5("mode", "\"peer\"").unwrap();
        c.insert_json5("listen/endpoints", "[]").unwrap();
        c.insert_json5("scouting/multicast/enabled", "false")
            .unwrap();
        let z = zenoh::open(c).wait().unwrap();
        let store = Arc::new(Mutex::new(BTreeMap::new()));
        let s = store.clone();
        z.declare_subscriber("boltwatch/s/@state/**")
            .callback(move |x| {
                let k = x.key_expr().to_string();
                let mut s = s.lock().unwrap();
                match x.kind() {
                    SampleKind::Put => s.insert(k, x.payload().to_bytes().to_vec()),
                    SampleKind::Delete => s.remove(&k),
                };
            })
            .background()
            .wait()
            .unwrap();
        (z, store)
    }

    fn stored(store: &Mutex<BTreeMap<String, Vec<u8>>>) -> Fetched {
        let mut f = Fetched::default();
        for (k, v) in store.lock().unwrap().iter() {
            f.add("s", k, v).unwrap();
        }
        f
    }

    fn entry(i: u64) -> WalEntry {
        WalEntry {
            suffix: "modal",
            time_ns: i,
            bytes: vec![i as u8],
        }
    }

    /// A batch of 3 is put, and a checkpoint falls due after its first set: the
    /// checkpoint covers that set only, and the two others stay the tail a new owner
    /// handles.
    #[test]
    fn a_checkpoint_inside_a_batch_covers_only_what_was_handled() {
        let (z, store) = session_with_store();
        let fence = Fence::new(z.clone(), "s", "a", 4);
        let mut r = Remote::new(z, fence, Vec::new());
        r.resumed();
        let seqs = r.put_entries(&[entry(0), entry(1), entry(2)]).unwrap();
        assert_eq!(seqs, vec![Some(0), Some(1), Some(2)]);
        r.handled(0);
        let c = crate::pipeline::Tracker::new(crate::core::model::lab_frame(), Default::default())
            .unwrap()
            .checkpoint();
        r.put_checkpoint(c).unwrap();
        let f = stored(&store);
        let (c, tail) = f.tail().unwrap();
        assert_eq!(c.unwrap().fleet.as_ref().unwrap().next, 1);
        let times: Vec<u64> = tail.iter().map(|e| e.time_ns).collect();
        assert_eq!(times, vec![1, 2]);
        assert_eq!(f.wal.len(), 2, "the covered entry is deleted");
    }

    /// Half the ring handled and uncovered asks for a checkpoint; after it, the ring
    /// goes round without a put reaching an uncovered entry.
    #[test]
    fn the_ring_asks_for_a_checkpoint_at_half_full() {
        let (z, store) = session_with_store();
        let mut r = Remote::new(z.clone(), Fence::new(z, "s", "a", 1), Vec::new());
        let c = || {
            crate::pipeline::Tracker::new(crate::core::model::lab_frame(), Default::default())
                .unwrap()
                .checkpoint()
        };
        let mut checkpoints = 0;
        for i in 0..3 * WAL_SLOTS {
            let seq = r.put_entries(&[entry(i)]).unwrap()[0].unwrap();
            r.handled(seq);
            assert!(r.own.len() as u64 <= WAL_SLOTS / 2);
            if r.needs_checkpoint() {
                r.put_checkpoint(c()).unwrap();
                checkpoints += 1;
            }
        }
        assert_eq!(checkpoints, 6);
        let f = stored(&store);
        assert!(f.tail().unwrap().1.is_empty());
        assert!(store.lock().unwrap().len() as u64 <= 1 + WAL_SLOTS);
    }
}
