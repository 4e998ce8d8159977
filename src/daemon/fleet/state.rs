//! A structure's state in the fleet's Zenoh storages (`daemon.state = "zenoh"`), under
//! `boltwatch/<structure>/@state/`:
//!
//! - `owner`: the [`OwnerRecord`], who tracks the structure in which epoch; put at each
//!   takeover (a new epoch) and when its owner hands it back;
//! - `checkpoint/<epoch>`: the tracker's checkpoint written by that epoch's owner, with its
//!   [`FleetPosition`] in the write-ahead tail;
//! - `wal/<epoch>/<seq>`: the inputs (modal sets, environment readings) each owner received,
//!   put before it handles them, in the order it handled them; deleted once a checkpoint
//!   covers them.
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
}

/// The key of `structure`'s owner record.
pub fn owner_key(structure: &str) -> String {
    format!("boltwatch/{structure}/@state/owner")
}

/// The key of the checkpoint written in `epoch`.
pub fn checkpoint_key(structure: &str, epoch: u64) -> String {
    format!("boltwatch/{structure}/@state/checkpoint/{epoch}")
}

/// The key of write-ahead entry `seq` of `epoch`.
pub fn wal_key(structure: &str, epoch: u64, seq: u64) -> String {
    format!("boltwatch/{structure}/@state/wal/{epoch}/{seq}")
}

/// One write-ahead entry: the input's topic suffix, its reception time (ns since the epoch)
/// and its bytes.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct WalEntry {
    pub suffix: &'static str,
    pub time_ns: u64,
    pub bytes: Vec<u8>,
}

impl WalEntry {
    /// The stored form: a kind byte (0 modal set, 1 environment reading), the time (8 bytes,
    /// big-endian), the payload.
    pub fn encode(&self) -> Vec<u8> {
        let kind = u8::from(self.suffix == "environment");
        let mut v = Vec::with_capacity(9 + self.bytes.len());
        v.push(kind);
        v.extend_from_slice(&self.time_ns.to_be_bytes());
        v.extend_from_slice(&self.bytes);
        v
    }

    pub fn decode(v: &[u8]) -> Result<Self> {
        if v.len() < 9 {
            bail!("a write-ahead entry of {} bytes is too short", v.len());
        }
        let suffix = match v[0] {
            0 => "modal",
            1 => "environment",
            k => bail!("write-ahead entry of unknown kind {k}"),
        };
        let time_ns = u64::from_be_bytes(v[1..9].try_into().expect("8 bytes"));
        Ok(Self {
            suffix,
            time_ns,
            bytes: v[9..].to_vec(),
        })
    }
}

/// Everything stored for one structure.
#[derive(Default)]
pub struct Fetched {
    pub owner: Option<OwnerRecord>,
    /// Checkpoints by the epoch they were written in.
    pub checkpoints: BTreeMap<u64, Checkpoint<TrackerState>>,
    /// Write-ahead entries by (epoch, seq).
    pub wal: BTreeMap<(u64, u64), WalEntry>,
}

impl Fetched {
    /// The checkpoint to resume from (the latest epoch's) and the entries to handle after
    /// it, in the order they were handled: its epoch's from its position on, then every
    /// later epoch's.
    pub fn tail(&self) -> (Option<&Checkpoint<TrackerState>>, Vec<&WalEntry>) {
        let Some((&epoch, c)) = self.checkpoints.iter().next_back() else {
            return (None, self.wal.values().collect());
        };
        let next = c.fleet.as_ref().map_or(0, |f| f.next);
        let tail = self
            .wal
            .range((epoch, next)..)
            .map(|(_, e)| e)
            .collect::<Vec<_>>();
        (Some(c), tail)
    }

    /// The highest epoch anything stored was written in (0: nothing stored): a takeover
    /// takes the next, even if the record itself was lost or overwritten.
    pub fn latest_epoch(&self) -> u64 {
        let record = self.owner.as_ref().map_or(0, |r| r.epoch);
        let checkpoint = self.checkpoints.keys().next_back().copied().unwrap_or(0);
        let wal = self.wal.keys().next_back().map_or(0, |k| k.0);
        record.max(checkpoint).max(wal)
    }

    /// The keys a checkpoint of a later epoch makes obsolete: every checkpoint and
    /// write-ahead entry fetched.
    pub fn obsolete_keys(&self, structure: &str) -> Vec<String> {
        let c = self
            .checkpoints
            .keys()
            .map(|&e| checkpoint_key(structure, e));
        let w = self.wal.keys().map(|&(e, s)| wal_key(structure, e, s));
        c.chain(w).collect()
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
        let key = sample.key_expr().as_str();
        let rest = key.strip_prefix(&prefix).unwrap_or(key);
        let bytes = sample.payload().to_bytes();
        read_value(&mut f, rest, &bytes).with_context(|| format!("stored state {key}"))?;
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
    let num = |s: &str| {
        s.parse::<u64>()
            .map_err(|_| anyhow!("`{s}` is not a number"))
    };
    match parts.as_slice() {
        ["owner"] => f.owner = Some(serde_json::from_slice(bytes)?),
        ["checkpoint", e] => {
            f.checkpoints
                .insert(num(e)?, serde_json::from_slice(bytes)?);
        }
        ["wal", e, s] => {
            f.wal.insert((num(e)?, num(s)?), WalEntry::decode(bytes)?);
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
            assert_eq!(WalEntry::decode(&entry(t).encode()).unwrap(), entry(t));
        }
        assert!(WalEntry::decode(&[0; 8]).is_err());
        assert!(WalEntry::decode(&[7; 12]).is_err());
    }

    /// The tail after a checkpoint of epoch 2 at position 3: epoch 2's entries from 3 on,
    /// then epoch 3's; epoch 1's and epoch 2's first three are covered.
    #[test]
    fn the_tail_starts_at_the_latest_checkpoints_position() {
        let mut f = Fetched::default();
        for (e, n) in [(1u64, 4u64), (2, 5), (3, 2)] {
            for s in 0..n {
                f.wal.insert((e, s), entry(e * 100 + s));
            }
        }
        assert_eq!(f.tail().1.len(), 11, "no checkpoint: everything");
        let mut c =
            crate::pipeline::Tracker::new(crate::core::model::lab_frame(), Default::default())
                .unwrap()
                .checkpoint();
        c.fleet = Some(crate::contract::FleetPosition {
            epoch: 2,
            owner: "b".into(),
            next: 3,
        });
        f.checkpoints.insert(2, c);
        let times: Vec<u64> = f.tail().1.iter().map(|e| e.time_ns).collect();
        assert_eq!(times, vec![203, 204, 300, 301]);
        assert_eq!(f.obsolete_keys("s").len(), 1 + 11);
    }

    #[test]
    fn records_order_by_epoch_then_owner() {
        let r = OwnerRecord {
            structure: "s".into(),
            epoch: 4,
            owner: "b".into(),
            released: false,
            since: String::new(),
        };
        assert!(r.supersedes(3, "z"));
        assert!(r.supersedes(4, "a"));
        assert!(!r.supersedes(4, "b"));
        assert!(!r.supersedes(5, "a"));
    }
}
