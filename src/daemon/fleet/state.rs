//! A structure's state in the fleet's Zenoh storages (`daemon.state = "zenoh"`), under
//! `boltwatch/<structure>/@state/`:
//!
//! - `owner`: the [`OwnerRecord`], who tracks the structure in which epoch; put at each
//!   takeover (a new epoch) and when its owner hands it back;
//! - `checkpoint/<owner>`: the last checkpoint that member wrote, with its
//!   [`FleetPosition`] (epoch, owner, next write-ahead number);
//! - `wal/<owner>/<slot>`: the inputs (modal sets, environment readings) the member
//!   received, each with its epoch and number, put before it handles them, in the order it
//!   handles them, in a ring of [`WAL_SLOTS`] keys per member; deleted once a checkpoint
//!   covers them.
//!
//! The owner is part of every key, so two members that took the same epoch (before they saw
//! each other) never overwrite each other's state; of the two, the epoch's owner is the one
//! the record names ([`Fetched::epoch_owner`]). The ring keeps the number of distinct keys,
//! and so the storages' replication logs of deletions, bounded however long the fleet runs.
//!
//! A new owner fetches all of it at once ([`fetch`]) and resumes from the latest checkpoint
//! and the entries after it ([`Fetched::tail`]), in the order they were handled, so its
//! outputs for them are byte for byte those of the old owner.

use std::collections::BTreeMap;
use std::time::Duration;

use anyhow::{Context, Result, anyhow, bail};
use serde::{Deserialize, Serialize};
use zenoh::Wait;
use zenoh::query::{ConsolidationMode, QueryTarget};

use crate::contract::Checkpoint;
use crate::io::zenoh::zerr;
use crate::pipeline::TrackerState;

/// How long a read of the storages waits for their answers.
pub const FETCH_TIMEOUT: Duration = Duration::from_secs(3);

/// Who tracks a structure, in which ownership epoch (module docs).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct OwnerRecord {
    pub structure: String,
    pub epoch: u64,
    pub owner: String,
    /// The owner handed the structure back (shutdown, or another member's turn).
    pub released: bool,
    /// When the record was written (RFC 3339).
    pub since: String,
}

impl OwnerRecord {
    /// Whether this record wins over `other`: the higher epoch, and of two takeovers of the
    /// same epoch (members that did not yet see each other), the greater owner id.
    pub fn supersedes(&self, epoch: u64, owner: &str) -> bool {
        (self.epoch, self.owner.as_str()) > (epoch, owner)
    }

    /// Whether a lane of `owner` in `epoch` must stand down when this record is the one
    /// stored: a newer epoch, or the same epoch taken by another member (of two members
    /// racing for one epoch, the one whose record the storages kept goes on).
    pub fn fences(&self, epoch: u64, owner: &str) -> bool {
        self.epoch > epoch || (self.epoch == epoch && self.owner != owner)
    }
}

/// The number of write-ahead keys per member and structure: entries go round the ring, and
/// a checkpoint is due before a put would reach an entry not yet covered.
pub const WAL_SLOTS: u64 = 1024;

/// The key of `structure`'s owner record.
pub fn owner_key(structure: &str) -> String {
    format!("boltwatch/{structure}/@state/owner")
}

/// The key of the last checkpoint `owner` wrote.
pub fn checkpoint_key(structure: &str, owner: &str) -> String {
    format!("boltwatch/{structure}/@state/checkpoint/{owner}")
}

/// The key of write-ahead entry `seq` of `owner` (its slot in the ring).
pub fn wal_key(structure: &str, owner: &str, seq: u64) -> String {
    format!(
        "boltwatch/{structure}/@state/wal/{owner}/{}",
        seq % WAL_SLOTS
    )
}

/// One write-ahead entry: the input's topic suffix, its reception time (ns since the epoch)
/// and its bytes.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct WalEntry {
    pub suffix: &'static str,
    pub time_ns: u64,
    pub bytes: Vec<u8>,
}

/// The size of a stored entry's header: kind, epoch, number, time.
const WAL_HEADER: usize = 1 + 3 * 8;

impl WalEntry {
    /// The stored form of entry `seq` of `epoch`: a kind byte (0 modal set, 1 environment
    /// reading), the epoch, the number and the time (8 bytes each, big-endian), the payload.
    pub fn encode(&self, epoch: u64, seq: u64) -> Vec<u8> {
        let kind = u8::from(self.suffix == "environment");
        let mut v = Vec::with_capacity(WAL_HEADER + self.bytes.len());
        v.push(kind);
        for n in [epoch, seq, self.time_ns] {
            v.extend_from_slice(&n.to_be_bytes());
        }
        v.extend_from_slice(&self.bytes);
        v
    }

    /// The entry, its epoch and its number.
    pub fn decode(v: &[u8]) -> Result<(u64, u64, Self)> {
        if v.len() < WAL_HEADER {
            bail!("a write-ahead entry of {} bytes is too short", v.len());
        }
        let suffix = match v[0] {
            0 => "modal",
            1 => "environment",
            k => bail!("write-ahead entry of unknown kind {k}"),
        };
        let n = |i: usize| u64::from_be_bytes(v[1 + 8 * i..9 + 8 * i].try_into().expect("8"));
        let entry = Self {
            suffix,
            time_ns: n(2),
            bytes: v[WAL_HEADER..].to_vec(),
        };
        Ok((n(0), n(1), entry))
    }
}

/// Where stored state was written: (epoch, owner).
pub type Writer = (u64, String);

/// Everything stored for one structure.
#[derive(Default)]
pub struct Fetched {
    pub owner: Option<OwnerRecord>,
    /// Checkpoints by the epoch and owner they were written in.
    pub checkpoints: BTreeMap<Writer, Checkpoint<TrackerState>>,
    /// Write-ahead entries by (epoch, owner, seq).
    pub wal: BTreeMap<(u64, String, u64), WalEntry>,
    /// The keys fetched.
    pub keys: Vec<String>,
}

impl Fetched {
    /// The member whose state counts for `epoch`: the record's owner if the record is of
    /// that epoch, else the greatest id that wrote in it (as [`OwnerRecord::supersedes`]
    /// ranks two takeovers of one epoch). The other's writes, if two members raced for
    /// the epoch, are ignored: both heard the same sensors.
    pub fn epoch_owner(&self, epoch: u64) -> Option<&str> {
        if let Some(r) = self.owner.as_ref().filter(|r| r.epoch == epoch) {
            return Some(&r.owner);
        }
        let wrote = self.checkpoints.keys().map(|(e, o)| (*e, o));
        let wrote = wrote.chain(self.wal.keys().map(|(e, o, _)| (*e, o)));
        wrote
            .filter(|(e, _)| *e == epoch)
            .map(|(_, o)| o.as_str())
            .max()
    }

    /// [`Fetched::epoch_owner`] of every epoch stored, computed once.
    fn epoch_owners(&self) -> BTreeMap<u64, &str> {
        let epochs = self.checkpoints.keys().map(|(e, _)| *e);
        let epochs = epochs.chain(self.wal.keys().map(|(e, _, _)| *e));
        let epochs: std::collections::BTreeSet<u64> = epochs.collect();
        epochs
            .into_iter()
            .filter_map(|e| Some((e, self.epoch_owner(e)?)))
            .collect()
    }

    /// The checkpoint to resume from (the latest epoch's) and the entries to handle after
    /// it, in the order they were handled: its epoch's from its position on, then every
    /// later epoch's. Entries without any checkpoint mean the checkpoint was lost (every
    /// owner writes one before its first entry): an error, not a fresh start.
    pub fn tail(&self) -> Result<(Option<&Checkpoint<TrackerState>>, Vec<&WalEntry>)> {
        let owners = self.epoch_owners();
        let counts = |e: u64, o: &str| owners.get(&e) == Some(&o);
        let checkpoint = self
            .checkpoints
            .iter()
            .rev()
            .find(|((e, o), _)| counts(*e, o));
        let from = match checkpoint {
            Some((_, c)) => {
                let f = c.fleet.as_ref().expect("read_value checks the position");
                (f.epoch, f.next)
            }
            None if self.wal.is_empty() => return Ok((None, Vec::new())),
            None => bail!(
                "{} write-ahead entries are stored but no checkpoint: the state is incomplete",
                self.wal.len()
            ),
        };
        let tail = self
            .wal
            .iter()
            .filter(|((e, o, s), _)| (*e, *s) >= from && counts(*e, o))
            .map(|((e, _, s), entry)| ((*e, *s), entry))
            .collect::<BTreeMap<_, _>>();
        Ok((checkpoint.map(|(_, c)| c), tail.into_values().collect()))
    }

    /// Files the stored value of `key` (a key of `structure`'s state).
    pub fn add(&mut self, structure: &str, key: &str, bytes: &[u8]) -> Result<()> {
        let prefix = format!("boltwatch/{structure}/@state/");
        let rest = key.strip_prefix(&prefix).unwrap_or(key);
        read_value(self, rest, bytes).with_context(|| format!("stored state {key}"))?;
        self.keys.push(key.to_string());
        Ok(())
    }

    /// The highest epoch anything stored was written in (0: nothing stored): a takeover
    /// takes the next, even if the record itself was lost or overwritten.
    pub fn latest_epoch(&self) -> u64 {
        let record = self.owner.as_ref().map_or(0, |r| r.epoch);
        let checkpoint = self.checkpoints.keys().map(|k| k.0).max().unwrap_or(0);
        let wal = self.wal.keys().map(|k| k.0).max().unwrap_or(0);
        record.max(checkpoint).max(wal)
    }

    /// The keys a checkpoint of a later epoch makes obsolete: every checkpoint and
    /// write-ahead entry fetched.
    pub fn obsolete_keys(&self) -> Vec<String> {
        self.keys
            .iter()
            .filter(|k| !k.ends_with("@state/owner"))
            .cloned()
            .collect()
    }
}

/// Reads everything stored for `structure` from the storages (all of them answer; the
/// latest value of each key is kept). A value that cannot be read fails the fetch with its
/// key, and so does finding no storage: a takeover must not resume from a partial state.
pub fn fetch(session: &zenoh::Session, structure: &str) -> Result<Fetched> {
    let prefix = format!("boltwatch/{structure}/@state/");
    let replies = session
        .get(format!("{prefix}**"))
        .target(QueryTarget::All)
        .consolidation(ConsolidationMode::Latest)
        .timeout(FETCH_TIMEOUT)
        .wait()
        .map_err(zerr(format!("cannot query the state of {structure}")))?;
    let mut f = Fetched::default();
    let mut answered = false;
    while let Ok(reply) = replies.recv() {
        answered = true;
        let sample = reply
            .result()
            .map_err(|e| anyhow!("the state storage of {structure} answered an error: {e:?}"))?;
        f.add(
            structure,
            sample.key_expr().as_str(),
            &sample.payload().to_bytes(),
        )?;
    }
    // Nothing stored is a structure never tracked, but only if a storage is there to say
    // so: a session cut off from the routers must not take over from an empty state.
    if !answered && !storage_present(session, structure) {
        bail!("no state storage is reachable for {structure}");
    }
    Ok(f)
}

/// Whether a queryable (a state storage) matches the structure's state now.
pub fn storage_present(session: &zenoh::Session, structure: &str) -> bool {
    session
        .declare_querier(owner_key(structure))
        .wait()
        .and_then(|q| q.matching_status().wait())
        .is_ok_and(|m| m.matching())
}

/// Files one stored value by its key below `@state/`.
fn read_value(f: &mut Fetched, rest: &str, bytes: &[u8]) -> Result<()> {
    let parts: Vec<&str> = rest.split('/').collect();
    match parts.as_slice() {
        ["owner"] => f.owner = Some(serde_json::from_slice(bytes)?),
        ["checkpoint", owner] => {
            let c: Checkpoint<TrackerState> = serde_json::from_slice(bytes)?;
            let Some(p) = c.fleet.as_ref().filter(|p| p.owner == *owner) else {
                bail!("the checkpoint has no fleet position of {owner}");
            };
            f.checkpoints.insert((p.epoch, p.owner.clone()), c);
        }
        ["wal", owner, _slot] => {
            let (epoch, seq, e) = WalEntry::decode(bytes)?;
            f.wal.insert((epoch, owner.to_string(), seq), e);
        }
        _ => bail!("not a key of the fleet's state"),
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn entry(t: u64) -> WalEntry {
        WalEntry {
            suffix: if t.is_multiple_of(2) {
                "modal"
            } else {
                "environment"
            },
            time_ns: t,
            bytes: format!("set {t}").into_bytes(),
        }
    }

    #[test]
    fn wal_entries_round_trip_and_refuse_garbage() {
        for t in [0, 1, u64::MAX] {
            assert_eq!(
                WalEntry::decode(&entry(t).encode(7, t)).unwrap(),
                (7, t, entry(t))
            );
        }
        assert!(WalEntry::decode(&[0; 24]).is_err());
        assert!(WalEntry::decode(&[7; 30]).is_err());
        assert_eq!(
            wal_key("s", "a", WAL_SLOTS + 3),
            "boltwatch/s/@state/wal/a/3"
        );
    }

    fn checkpoint(epoch: u64, owner: &str, next: u64) -> Checkpoint<TrackerState> {
        let mut c =
            crate::pipeline::Tracker::new(crate::core::model::lab_frame(), Default::default())
                .unwrap()
                .checkpoint();
        c.fleet = Some(crate::contract::FleetPosition {
            epoch,
            owner: owner.into(),
            next,
        });
        c
    }

    fn record(epoch: u64, owner: &str) -> OwnerRecord {
        OwnerRecord {
            structure: "s".into(),
            epoch,
            owner: owner.into(),
            released: false,
            since: String::new(),
        }
    }

    /// Entries of epochs 1 (a), 2 (b) and 3 (a); a checkpoint of epoch 2 at position 3:
    /// epoch 2's entries from 3 on, then epoch 3's. Entries alone are refused.
    #[test]
    fn the_tail_starts_at_the_latest_checkpoints_position() {
        let mut f = Fetched::default();
        for (e, o, n) in [(1u64, "a", 4u64), (2, "b", 5), (3, "a", 2)] {
            for s in 0..n {
                f.wal.insert((e, o.into(), s), entry(e * 100 + s));
            }
        }
        assert!(f.tail().is_err(), "entries but no checkpoint");
        f.checkpoints.insert((1, "a".into()), checkpoint(1, "a", 4));
        assert_eq!(f.tail().unwrap().1.len(), 7, "epochs 2 and 3");
        f.checkpoints.insert((2, "b".into()), checkpoint(2, "b", 3));
        let times: Vec<u64> = f.tail().unwrap().1.iter().map(|e| e.time_ns).collect();
        assert_eq!(times, vec![203, 204, 300, 301]);
        assert_eq!(f.latest_epoch(), 3);
    }

    /// Members a and b both took epoch 2: the record's owner's checkpoint and entries
    /// count, the other's are ignored, whichever id is greater.
    #[test]
    fn of_two_takeovers_of_one_epoch_the_records_owner_counts() {
        let mut f = Fetched::default();
        f.checkpoints.insert((1, "c".into()), checkpoint(1, "c", 0));
        for o in ["a", "b"] {
            f.checkpoints.insert((2, o.into()), checkpoint(2, o, 0));
            for s in 0..3 {
                let t = if o == "a" { 10 + s } else { 20 + s };
                f.wal.insert((2, o.into(), s), entry(t));
            }
        }
        let tail =
            |f: &Fetched| -> Vec<u64> { f.tail().unwrap().1.iter().map(|e| e.time_ns).collect() };
        assert_eq!(tail(&f), vec![20, 21, 22], "no record: the greater id");
        f.owner = Some(record(2, "a"));
        assert_eq!(tail(&f), vec![10, 11, 12]);
        let c = f.tail().unwrap().0.unwrap();
        assert_eq!(c.fleet.as_ref().unwrap().owner, "a");
    }

    #[test]
    fn records_order_by_epoch_then_owner_and_fence_another_owner_of_the_epoch() {
        let r = record(4, "b");
        assert!(r.supersedes(3, "z"));
        assert!(r.supersedes(4, "a"));
        assert!(!r.supersedes(4, "b"));
        assert!(!r.supersedes(5, "a"));
        assert!(r.fences(3, "z"));
        assert!(r.fences(4, "a") && r.fences(4, "c"));
        assert!(!r.fences(4, "b"));
        assert!(!r.fences(5, "a"));
    }

    #[test]
    fn a_checkpoint_must_carry_its_writers_position() {
        let mut f = Fetched::default();
        let c = serde_json::to_vec(&checkpoint(3, "a", 1)).unwrap();
        assert!(read_value(&mut f, "checkpoint/a", &c).is_ok());
        assert!(read_value(&mut f, "checkpoint/b", &c).is_err());
        assert!(read_value(&mut f, "checkpoint/a/3", &c).is_err());
        assert_eq!(f.checkpoints.keys().next(), Some(&(3, "a".to_string())));
    }
}
