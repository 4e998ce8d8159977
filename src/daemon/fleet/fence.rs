//! Fencing: a daemon publishes for a structure, and writes its state, only while its
//! ownership epoch is the current one.
//!
//! The fleet's controller fences a lane at once when it sees a newer owner record. That is
//! not enough for a daemon that was paused (SIGSTOP, a VM frozen) or cut off: it missed the
//! record, and on waking its threads would carry on where they stopped. So every output and
//! every state write first asks [`Fence::allows`]: within [`CONFIRM_WINDOW`] of the last
//! confirmation it is allowed; after it, the owner record is read again from the storages,
//! and a newer epoch, or its own epoch taken by another member, fences the lane for good.
//! A takeover needs the owner's liveliness token gone, which takes a Zenoh lease (seconds)
//! of silence, longer than the window: a daemon that was away long enough to be replaced
//! finds its confirmation stale and reads the record before anything else goes out.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, OnceLock};
use std::time::{Duration, Instant};

use anyhow::{Result, anyhow};
use zenoh::Wait;
use zenoh::query::{ConsolidationMode, QueryTarget};

use super::state::{FETCH_TIMEOUT, OwnerRecord, owner_key};

/// How long a confirmation of the epoch holds.
pub const CONFIRM_WINDOW: Duration = Duration::from_secs(2);

/// How long [`Fence::allows`] waits between two reads of the record that found no storage.
const RETRY: Duration = Duration::from_millis(500);

/// One lane's ownership epoch and whether it still holds (module docs).
pub struct Fence {
    session: zenoh::Session,
    pub structure: String,
    pub owner: String,
    pub epoch: u64,
    state: Mutex<(Instant, bool)>,
    /// The lane is being closed: stop waiting for a storage that does not answer.
    closing: AtomicBool,
    /// Called while waiting for the storages (the lane's heartbeat: a lane that holds its
    /// outputs is alive, and the watchdog must not kill the daemon for it).
    waiting: OnceLock<Box<dyn Fn() + Send + Sync>>,
}

impl Fence {
    /// A fence confirmed now (the epoch was just taken).
    pub fn new(session: zenoh::Session, structure: &str, owner: &str, epoch: u64) -> Arc<Self> {
        Arc::new(Self {
            session,
            structure: structure.to_string(),
            owner: owner.to_string(),
            epoch,
            state: Mutex::new((Instant::now(), false)),
            closing: AtomicBool::new(false),
            waiting: OnceLock::new(),
        })
    }

    /// Sets what to call while [`Fence::allows`] waits for the storages.
    pub fn on_wait(&self, f: impl Fn() + Send + Sync + 'static) {
        let _ = self.waiting.set(Box::new(f));
    }

    pub fn is_fenced(&self) -> bool {
        self.lock().1
    }

    /// Fences the lane for good (a newer owner record was seen).
    pub fn fence(&self) {
        let mut s = self.lock();
        if !s.1 {
            tracing::warn!(
                structure = self.structure,
                epoch = self.epoch,
                "ownership moved on: this daemon publishes nothing more for the structure"
            );
        }
        s.1 = true;
    }

    /// Makes the next [`Fence::allows`] read the owner record again (the membership
    /// changed: this daemon may have been cut off, and records put meanwhile missed).
    pub fn expire(&self) {
        let mut s = self.lock();
        if let Some(t) = Instant::now().checked_sub(CONFIRM_WINDOW) {
            s.0 = s.0.min(t);
        }
    }

    /// The lane is closing: [`Fence::allows`] no longer waits for the storages.
    pub fn closing(&self) {
        self.closing.store(true, Ordering::Relaxed);
    }

    /// Whether an output or a state write may go out now (module docs). Waits while the
    /// storages cannot be read, unless the lane is closing.
    pub fn allows(&self) -> bool {
        let mut warned = false;
        loop {
            {
                let s = self.lock();
                if s.1 {
                    return false;
                }
                if s.0.elapsed() < CONFIRM_WINDOW {
                    return true;
                }
            }
            // The confirmation holds from the moment of asking, not of the answer.
            let asked = Instant::now();
            match read_owner(&self.session, &self.structure) {
                Ok(r) if r.fences(self.epoch, &self.owner) => {
                    self.fence();
                    return false;
                }
                Ok(_) => {
                    self.lock().0 = asked;
                    return true;
                }
                Err(e) => {
                    if self.closing.load(Ordering::Relaxed) {
                        return false;
                    }
                    if !warned {
                        tracing::warn!(
                            structure = self.structure,
                            "cannot confirm the ownership epoch ({e:#}); holding outputs until the state storage answers"
                        );
                        warned = true;
                    }
                    if let Some(beat) = self.waiting.get() {
                        beat();
                    }
                    std::thread::sleep(RETRY);
                }
            }
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, (Instant, bool)> {
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }
}

/// The structure's owner record as the storages hold it. A lane's record exists from its
/// takeover on, so no answer at all (no storage reached, or a session still reconnecting
/// with stale routes) is an error, never "no record": the epoch cannot be confirmed.
pub fn read_owner(session: &zenoh::Session, structure: &str) -> Result<OwnerRecord> {
    let replies = session
        .get(owner_key(structure))
        .target(QueryTarget::All)
        .consolidation(ConsolidationMode::Latest)
        .timeout(FETCH_TIMEOUT)
        .wait()
        .map_err(|e| anyhow!("cannot query the owner of {structure}: {e}"))?;
    let mut record: Option<OwnerRecord> = None;
    while let Ok(reply) = replies.recv() {
        if let Ok(sample) = reply.result() {
            let r: OwnerRecord = serde_json::from_slice(&sample.payload().to_bytes())
                .map_err(|e| anyhow!("the owner record of {structure} is not valid: {e}"))?;
            if record
                .as_ref()
                .is_none_or(|o| r.supersedes(o.epoch, &o.owner))
            {
                record = Some(r);
            }
        }
    }
    record.ok_or_else(|| anyhow!("no state storage answered with the owner record of {structure}"))
}
