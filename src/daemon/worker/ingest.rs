//! What the worker does with a batch from the queue: write-ahead (every set logged, one
//! fsync for the batch), then each input handled in order; raw blocks through the accel
//! front, whose windows' modal sets are logged and tracked like received ones.

use std::collections::HashSet;
use std::panic::AssertUnwindSafe;
use std::time::Instant;

use anyhow::Result;
use chrono::{DateTime, Utc};

use super::{Input, Worker, panic_message};
use crate::contract::modal_set::Rejection;
use crate::contract::rejected::REJECTED_PAYLOAD_LIMIT;
use crate::contract::{Output, WalPosition, digest};
use crate::daemon::fleet::state::WalEntry as RemoteEntry;
use crate::daemon::metrics::Shared;
use crate::io::driver::emit;
use crate::io::mcap::to_ns;
use crate::pipeline::Action;
use crate::pipeline::accel::FrontEvent;

/// An input's write-ahead entry: its topic suffix, its log time and its bytes.
type WalEntry = (&'static str, u64, Vec<u8>);

impl Worker {
    /// Write-ahead: logs every set of `batch` that is not a re-delivery, makes them
    /// durable with one fsync, then handles them in order (a re-delivery is handled too,
    /// so the tracker counts it, and publishes nothing).
    pub(super) fn commit_and_handle(&mut self, batch: Vec<Input>) -> Result<()> {
        let shared = self.out.shared.clone();
        let mut logged = HashSet::new();
        let entries = batch
            .iter()
            .map(|input| self.wal_entry(&shared, input, &mut logged))
            .collect::<Result<Vec<_>>>()?;
        let positions = self.write_ahead(&shared, entries)?;
        for (input, (pos, seq)) in batch.into_iter().zip(positions) {
            self.handle_input(&shared, input, pos)?;
            self.remote_handled(seq)?;
            shared.beat();
        }
        self.update_status()
    }

    /// Write-ahead entry `seq` (if it was put) has been handled; a checkpoint when the
    /// ring of entries needs one.
    fn remote_handled(&mut self, seq: Option<u64>) -> Result<()> {
        let Some(r) = self.remote.as_mut() else {
            return Ok(());
        };
        if let Some(seq) = seq {
            r.handled(seq);
        }
        if r.needs_checkpoint() {
            self.checkpoint()?;
        }
        Ok(())
    }

    /// Takes one input off the queue's counts and, a set or an environment reading, gives
    /// its write-ahead entry. A set whose bytes the tracker has handled, or that `logged`
    /// holds (an earlier set of the batch), is not logged again.
    fn wal_entry(
        &self,
        shared: &Shared,
        input: &Input,
        logged: &mut HashSet<u128>,
    ) -> Result<Option<WalEntry>> {
        shared.dequeued(input);
        Ok(match input {
            Input::Set { received, payload } => {
                let d = digest(payload);
                if self.tracker.has_seen(d) || !logged.insert(d) {
                    shared.with_status(|st| st.wal.redeliveries += 1);
                    return Ok(None);
                }
                Some(("modal", to_ns(*received)?, payload.clone()))
            }
            // Raw blocks are not logged (a day of 42 channels at 1 kHz is 19 GB); the
            // modal set of each window is, as an input, when it is identified.
            Input::Oversize { .. } | Input::Accel { .. } | Input::Shutdown => None,
            Input::Environment { received, payload } => {
                Some(("environment", to_ns(*received)?, payload.clone()))
            }
        })
    }

    /// The group commit: the entries written into the log and made durable with one fsync
    /// (none when there is nothing to log), counted in the write-ahead log's status; the
    /// position of each.
    fn write_ahead(
        &mut self,
        shared: &Shared,
        entries: Vec<Option<WalEntry>>,
    ) -> Result<Vec<(Option<WalPosition>, Option<u64>)>> {
        let logged = entries.iter().flatten().count() as u64;
        if logged == 0 {
            return Ok(vec![(None, None); entries.len()]);
        }
        let logged_at: Vec<bool> = entries.iter().map(Option::is_some).collect();
        let remote_entries: Vec<RemoteEntry> = match self.remote {
            Some(_) => entries
                .iter()
                .flatten()
                .map(|(suffix, time_ns, bytes)| RemoteEntry {
                    suffix,
                    time_ns: *time_ns,
                    bytes: bytes.clone(),
                })
                .collect(),
            None => Vec::new(),
        };
        let (positions, ms) = self.out.log(move |log| {
            let positions = entries
                .into_iter()
                .map(|e| {
                    e.map(|(suffix, time, bytes)| log.write_input(suffix, time, &bytes))
                        .transpose()
                })
                .collect::<Result<Vec<_>>>()?;
            let t = Instant::now();
            log.sync()?;
            Ok((positions, t.elapsed().as_secs_f64() * 1e3))
        })?;
        let mut seqs = match self.remote.as_mut() {
            Some(remote) => remote.put_entries(&remote_entries)?.into_iter(),
            None => Vec::new().into_iter(),
        };
        // Each logged input's number among the remote entries, in order.
        let seqs: Vec<Option<u64>> = logged_at
            .iter()
            .map(|&l| if l { seqs.next().flatten() } else { None })
            .collect();
        shared.with_status(|st| {
            st.wal.syncs += 1;
            st.wal.sets += logged;
            st.wal.sync_ms += ms;
        });
        Ok(positions.into_iter().zip(seqs).collect())
    }

    /// Handles one input of a committed batch; `pos` is where it was logged, if it was.
    fn handle_input(
        &mut self,
        shared: &Shared,
        input: Input,
        pos: Option<WalPosition>,
    ) -> Result<()> {
        match input {
            Input::Set { received, payload } => {
                self.handle(received, &payload)?;
                if let Some(p) = pos {
                    self.handled_upto = Some(p.after());
                }
            }
            Input::Oversize {
                received,
                size,
                head,
                digest,
            } => {
                let rej = Rejection {
                    field: "payload".into(),
                    reason: format!(
                        "{size} bytes exceeds the limit of {} bytes (daemon.max_payload_bytes)",
                        shared.max_payload
                    ),
                };
                let o = self.tracker.refuse(received, &rej, &head, size, digest);
                self.publish_guarded(received, &head, vec![Action::Publish(o)])?;
            }
            Input::Accel { received, payload } => self.handle_accel(received, &payload)?,
            Input::Environment { received, payload } => {
                let actions = self.tracker.handle_environment(received, &payload);
                self.dirty = true;
                self.publish_guarded(received, &payload, actions)?;
                if let Some(p) = pos {
                    self.handled_upto = Some(p.after());
                }
            }
            Input::Shutdown => {}
        }
        Ok(())
    }

    /// Feeds one raw block to the accel front; a panic there rejects the block.
    fn handle_accel(&mut self, received: DateTime<Utc>, payload: &[u8]) -> Result<()> {
        let events = std::panic::catch_unwind(AssertUnwindSafe(|| self.front.handle(payload)))
            .unwrap_or_else(|panic| {
                vec![FrontEvent::Refused(Rejection {
                    field: "payload".into(),
                    reason: format!(
                        "identifying this block's window failed (internal error: {})",
                        panic_message(&*panic)
                    ),
                })]
            });
        for e in events {
            self.front_event(received, payload, e)?;
        }
        Ok(())
    }

    /// A window's modal set is logged as an input (write-ahead), published for others
    /// and tracked like a received set; a refused block or a dropped window is published
    /// on `rejected`.
    pub(super) fn front_event(
        &mut self,
        received: DateTime<Utc>,
        payload: &[u8],
        e: FrontEvent,
    ) -> Result<()> {
        match e {
            FrontEvent::Set(set) => {
                let bytes = serde_json::to_vec(&set.to_json())?;
                let (time, entry) = (to_ns(received)?, bytes.clone());
                let pos = self.out.log(move |log| {
                    let pos = log.write_input("modal", time, &entry)?;
                    log.sync()?;
                    Ok(pos)
                })?;
                let seq = match self.remote.as_mut() {
                    Some(remote) => remote.put_entries(&[RemoteEntry {
                        suffix: "modal",
                        time_ns: time,
                        bytes: bytes.clone(),
                    }])?[0],
                    None => None,
                };
                emit(&mut self.out, Output::Modal(set))?;
                self.handle(received, &bytes)?;
                self.handled_upto = Some(pos.after());
                self.remote_handled(seq)?;
            }
            FrontEvent::Refused(rej) => {
                let head = &payload[..payload.len().min(REJECTED_PAYLOAD_LIMIT)];
                let o = self
                    .tracker
                    .refuse(received, &rej, head, payload.len(), digest(payload));
                self.publish_guarded(received, head, vec![Action::Publish(o)])?;
            }
            FrontEvent::Dropped(rej) => {
                let o = self.tracker.refuse(received, &rej, &[], 0, digest(&[]));
                self.publish_guarded(received, &[], vec![Action::Publish(o)])?;
            }
        }
        Ok(())
    }
}
