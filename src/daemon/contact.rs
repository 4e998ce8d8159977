//! First contact with a sensor's advanced publisher: nothing it published while the
//! daemon was down is lost.
//!
//! zenoh-ext 1.10's advanced subscriber, when it meets a publisher after its own start (a
//! restarted daemon, a sensor that kept publishing), asks that publisher's cache for its
//! history. But a live set that arrives before the reply is delivered at once (the
//! subscriber checks for queries pending on the whole subscriber, not on that publisher),
//! and the older cached sets that follow are then dropped as stale, without a miss report.
//! Under load this lost 62 of 400 sets in a SIGKILL storm.
//!
//! [`Gate`] closes that hole on the daemon's side. Per publisher (the source id the
//! advanced publisher stamps on each set), the first set seen in this run and every set
//! after it are held back while the daemon itself fetches from that publisher's cache
//! everything with a lower sequence number; then all of it goes into the tracking queue in
//! sequence order, and that publisher's sets pass straight through from then on (gaps
//! later are zenoh-ext's recovery). Sets handled in an earlier run come back this way too;
//! the tracker recognises and skips them (counted as duplicates). Sets without a source
//! (a plain publisher) pass straight through.

use std::collections::{BTreeMap, HashMap};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;

use zenoh::Wait;
use zenoh::bytes::ZBytes;
use zenoh::key_expr::KeyExpr;
use zenoh::query::{ConsolidationMode, QueryTarget, ReplyKeyExpr};
use zenoh::sample::Sample;
use zenoh::session::EntityGlobalId;

use super::metrics::Shared;
use super::worker::{Input, WhenFull, enqueue};
use std::sync::mpsc::SyncSender;

/// How long the fetch from a publisher's cache may take.
pub const FETCH_TIMEOUT: Duration = Duration::from_secs(10);

/// Where one publisher stands in this run.
enum Source {
    /// Its earlier sets are being fetched; these arrived meanwhile, by sequence number.
    Held(BTreeMap<u32, ZBytes>),
    /// Everything before its first set was fetched: its sets go straight to the queue.
    Open,
}

/// The gate between one structure's advanced subscriber and its tracking queue.
pub struct Gate {
    session: zenoh::Session,
    key: KeyExpr<'static>,
    tx: SyncSender<Input>,
    shared: Arc<Shared>,
    sources: Mutex<HashMap<EntityGlobalId, Source>>,
}

impl Gate {
    pub fn new(
        session: zenoh::Session,
        key: KeyExpr<'static>,
        tx: SyncSender<Input>,
        shared: Arc<Shared>,
    ) -> Arc<Self> {
        Arc::new(Self {
            session,
            key,
            tx,
            shared,
            sources: Mutex::new(HashMap::new()),
        })
    }

    /// A set from the subscriber (live, or from zenoh-ext's own history and recovery).
    pub fn offer(self: &Arc<Self>, sample: &Sample) {
        let Some(info) = sample.source_info() else {
            enqueue(&self.tx, &self.shared, sample.payload(), WhenFull::Drop);
            return;
        };
        let (id, sn) = (*info.source_id(), info.source_sn());
        let mut sources = self.sources.lock().unwrap_or_else(PoisonError::into_inner);
        match sources.get_mut(&id) {
            Some(Source::Open) => enqueue(&self.tx, &self.shared, sample.payload(), WhenFull::Drop),
            Some(Source::Held(held)) => {
                held.entry(sn).or_insert_with(|| sample.payload().clone());
            }
            None if sn == 0 => {
                sources.insert(id, Source::Open);
                enqueue(&self.tx, &self.shared, sample.payload(), WhenFull::Drop);
            }
            None => {
                sources.insert(
                    id,
                    Source::Held(BTreeMap::from([(sn, sample.payload().clone())])),
                );
                drop(sources);
                let gate = self.clone();
                let spawned = std::thread::Builder::new()
                    .name(format!("contact-{}", self.shared.structure))
                    .spawn(move || gate.fetch_before(id, sn));
                if let Err(e) = spawned {
                    tracing::error!(
                        structure = self.shared.structure,
                        "cannot start the fetch from publisher {}:{}: {e}; its sets pass without it",
                        id.zid(),
                        id.eid()
                    );
                    self.release(id);
                }
            }
        }
    }

    /// Fetches publisher `id`'s cached sets with sequence numbers below `first`, then
    /// releases them with everything held since, in order.
    fn fetch_before(&self, id: EntityGlobalId, first: u32) {
        let selector = format!(
            "{}/@adv/*/{}/{}/**?_sn=..{}",
            self.key,
            id.zid().into_keyexpr(),
            id.eid(),
            first - 1
        );
        let replies = self
            .session
            .get(selector.as_str())
            .consolidation(ConsolidationMode::None)
            .accept_replies(ReplyKeyExpr::Any)
            .target(QueryTarget::All)
            .timeout(FETCH_TIMEOUT)
            .wait();
        let mut fetched = BTreeMap::new();
        match replies {
            Ok(replies) => {
                while let Ok(reply) = replies.recv() {
                    let Ok(sample) = reply.into_result() else {
                        continue;
                    };
                    let Some(info) = sample.source_info() else {
                        continue;
                    };
                    if *info.source_id() == id
                        && info.source_sn() < first
                        && self.key.intersects(sample.key_expr())
                    {
                        fetched.insert(info.source_sn(), sample.payload().clone());
                    }
                }
            }
            Err(e) => tracing::warn!(
                structure = self.shared.structure,
                "cannot ask publisher {}:{} for its cache: {e}",
                id.zid(),
                id.eid()
            ),
        }
        tracing::info!(
            structure = self.shared.structure,
            "first contact with publisher {}:{} at set #{first}: {} earlier set(s) fetched from its cache",
            id.zid(),
            id.eid(),
            fetched.len()
        );
        {
            let mut sources = self.sources.lock().unwrap_or_else(PoisonError::into_inner);
            if let Some(Source::Held(held)) = sources.get_mut(&id) {
                for (sn, payload) in fetched {
                    held.entry(sn).or_insert(payload);
                }
            }
        }
        self.release(id);
    }

    /// Passes publisher `id`'s held sets to the queue in sequence order (waiting for room,
    /// off the lock so live sets keep arriving into the held ones), then opens it.
    fn release(&self, id: EntityGlobalId) {
        loop {
            let next = {
                let mut sources = self.sources.lock().unwrap_or_else(PoisonError::into_inner);
                let Some(source) = sources.get_mut(&id) else {
                    return;
                };
                let Source::Held(held) = source else {
                    return;
                };
                match held.pop_first() {
                    Some((_, payload)) => payload,
                    None => {
                        *source = Source::Open;
                        return;
                    }
                }
            };
            enqueue(&self.tx, &self.shared, &next, WhenFull::Wait);
        }
    }
}
