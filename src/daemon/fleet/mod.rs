//! The fleet: daemons sharing the structures of one configuration (`[fleet] group`), with
//! no coordinator but Zenoh.
//!
//! - **Membership.** Each daemon declares the liveliness token
//!   `boltwatch/@fleet/<group>/<id>` and follows the group's tokens. A daemon that stops
//!   (or is killed: its Zenoh session closes) loses its token at once; one that is paused
//!   or cut off loses it when its Zenoh lease runs out.
//! - **Ownership.** Each structure belongs to the live member that [`rendezvous`] hashing
//!   names, which every member computes alike. A member takes a structure over only once
//!   the previous owner (in the structure's owner record, [`state`]) is gone from the group
//!   or has handed it back; a member that is no longer the structure's choice hands it back
//!   (its lane drained and its state written first).
//! - **Epochs and fencing.** Each takeover writes a new epoch into the owner record; a
//!   lane's outputs carry its owner and epoch, and a lane whose epoch moved on is fenced
//!   ([`fence`]) and closed without publishing or writing anything more.
//! - **State** in the routers' replicated storages ([`state`]): a new owner resumes from
//!   the latest checkpoint and the write-ahead entries after it, and the sensors'
//!   publisher caches give it the sets published meanwhile.

pub mod fence;
mod ownership;
pub mod rendezvous;
pub mod state;

use std::collections::{BTreeMap, BTreeSet};
use std::sync::Arc;
use std::time::Duration;

use anyhow::{Result, anyhow};
use tokio::sync::oneshot;
use tokio::task::JoinHandle;
use zenoh::sample::{Locality, SampleKind};

use super::lane::Lane;
use super::metrics::Watched;
use super::{DoneTx, unwatch, watch};
use crate::io::zenoh::zerr;
use crate::settings::Settings;
use state::OwnerRecord;

/// How often ownership is looked at again without a membership change (a takeover that
/// waited for a hand-back, a storage that did not answer).
const RECONCILE_EVERY: Duration = Duration::from_millis(500);

/// How often the members are listed again (a token event that a reconnecting link lost).
const MEMBERS_EVERY: Duration = Duration::from_secs(2);

/// How long a member that just joined only listens to the group before it takes anything
/// over: members starting together (a site powering up) then share the structures out
/// once, instead of each taking all and handing most back.
const JOIN_SETTLE: Duration = Duration::from_secs(1);

/// The longest a failed takeover waits before it is tried again (doubling from 1 s).
const BACKOFF_MAX: Duration = Duration::from_secs(30);

/// How long leaving the fleet may take: every lane closed and released, below systemd's
/// stop timeout of the deployed unit.
const STOP_DEADLINE: Duration = Duration::from_secs(90);

/// The key of a member's liveliness token.
pub fn member_key(group: &str, id: &str) -> String {
    format!("boltwatch/@fleet/{group}/{id}")
}

/// The running fleet membership of this daemon: its controller task.
pub struct Fleet {
    stop: oneshot::Sender<()>,
    task: JoinHandle<Result<()>>,
}

impl Fleet {
    /// Joins the group (the token; the members present now) and starts the controller,
    /// which opens and closes this daemon's lanes as ownership moves.
    pub async fn start(
        settings: Arc<Settings>,
        session: zenoh::Session,
        watched: Watched,
        done: DoneTx,
    ) -> Result<Fleet> {
        let f = &settings.fleet;
        let members_ke = format!("boltwatch/@fleet/{}/*", f.group);
        // Both followed through unbounded channels: a callback must never block Zenoh's
        // receiving task, and the controller is busy for seconds at a time (takeovers,
        // hand-backs). Its own records are not echoed back to it.
        let (events, events_rx) = tokio::sync::mpsc::unbounded_channel();
        let to_members = events.clone();
        let members_sub = session
            .liveliness()
            .declare_subscriber(&members_ke)
            .callback(move |s| {
                let _ = to_members.send(Event::Member(s));
            })
            .await
            .map_err(zerr(format!(
                "cannot follow the group's tokens {members_ke}"
            )))?;
        let owners_sub = session
            .declare_subscriber("boltwatch/*/@state/owner")
            .allowed_origin(Locality::Remote)
            .callback(move |s| {
                let _ = events.send(Event::Record(s));
            })
            .await
            .map_err(zerr("cannot follow the owner records"))?;
        let token = session
            .liveliness()
            .declare_token(member_key(&f.group, &f.id))
            .await
            .map_err(zerr("cannot declare this daemon's liveliness token"))?;
        let mut c = Controller {
            me: f.id.clone(),
            members: BTreeSet::from([f.id.clone()]),
            absent: BTreeSet::new(),
            lanes: BTreeMap::new(),
            pending: BTreeMap::new(),
            backoff: BTreeMap::new(),
            members_ke: members_ke.clone(),
            settings: settings.clone(),
            session,
            watched,
            done,
        };
        c.members
            .extend(present_members(&c.session, &members_ke).await?);
        tracing::info!(
            group = f.group,
            id = f.id,
            members = ?c.members,
            "joined the fleet"
        );
        let (stop, stopped) = oneshot::channel();
        let task = tokio::spawn(async move {
            let r = c.control(events_rx, stopped).await;
            drop((members_sub, owners_sub, token));
            r
        });
        Ok(Fleet { stop, task })
    }

    /// Leaves: every lane handed back (drained, state written, record released), then the
    /// token withdrawn.
    pub async fn stop(self) -> Result<()> {
        let _ = self.stop.send(());
        match tokio::time::timeout(STOP_DEADLINE, self.task).await {
            Ok(r) => r.map_err(|e| anyhow!("the fleet controller: {e}"))?,
            Err(_) => Err(anyhow!(
                "leaving the fleet took more than {} s: lanes not handed back are taken over once this daemon's token is gone",
                STOP_DEADLINE.as_secs()
            )),
        }
    }
}

/// The members whose tokens are present now.
async fn present_members(session: &zenoh::Session, ke: &str) -> Result<Vec<String>> {
    let replies = session
        .liveliness()
        .get(ke)
        .timeout(state::FETCH_TIMEOUT)
        .await
        .map_err(zerr("cannot list the group's members"))?;
    let mut out = Vec::new();
    while let Ok(reply) = replies.recv_async().await {
        if let Ok(sample) = reply.result()
            && let Some(id) = sample.key_expr().as_str().rsplit('/').next()
        {
            out.push(id.to_string());
        }
    }
    Ok(out)
}

/// The controller's view: members, this daemon's lanes, and what opening a lane needs.
struct Controller {
    me: String,
    members: BTreeSet<String>,
    /// Members missing from the last listing (removed if missing from the next too).
    absent: BTreeSet<String>,
    lanes: BTreeMap<String, Lane>,
    /// Records of this member to release (structure → epoch), retried until done.
    pending: BTreeMap<String, u64>,
    /// Structures whose takeover failed: not tried again before the instant, and the
    /// next wait.
    backoff: BTreeMap<String, (tokio::time::Instant, Duration)>,
    members_ke: String,
    settings: Arc<Settings>,
    session: zenoh::Session,
    watched: Watched,
    done: DoneTx,
}

/// What the controller hears: a member's token coming or going, an owner record put.
enum Event {
    Member(zenoh::sample::Sample),
    Record(zenoh::sample::Sample),
}

impl Controller {
    /// Follows members and owner records until told to stop, reconciling ownership after
    /// each change and every [`RECONCILE_EVERY`]; then hands every lane back.
    async fn control(
        &mut self,
        mut events: tokio::sync::mpsc::UnboundedReceiver<Event>,
        mut stop: oneshot::Receiver<()>,
    ) -> Result<()> {
        let mut tick = tokio::time::interval(RECONCILE_EVERY);
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        let mut list = tokio::time::interval(MEMBERS_EVERY);
        list.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        let settle = tokio::time::sleep(JOIN_SETTLE);
        tokio::pin!(settle);
        let mut settled = false;
        loop {
            tokio::select! {
                _ = &mut stop => break,
                Some(e) = events.recv() => match e {
                    Event::Member(s) => self.member_changed(&s),
                    Event::Record(s) => self.record_seen(&s).await,
                },
                _ = list.tick() => self.list_members().await,
                _ = tick.tick() => {}
                _ = &mut settle, if !settled => settled = true,
            }
            if settled {
                self.reconcile().await;
            }
        }
        drop(events);
        self.leave().await;
        Ok(())
    }

    /// Hands every lane back at once: all intakes stopped, all queues drained together,
    /// then each record released.
    async fn leave(&mut self) {
        let mut closing = tokio::task::JoinSet::new();
        for (name, lane) in std::mem::take(&mut self.lanes) {
            unwatch(&self.watched, &name);
            if let Some(f) = &lane.fence {
                f.closing();
                if !f.is_fenced() {
                    self.pending.insert(name.clone(), f.epoch);
                }
            }
            closing.spawn(async move { (name, lane.close().await) });
        }
        while let Some(r) = closing.join_next().await {
            match r {
                Ok((name, Err(e))) => tracing::error!(structure = name, "closing: {e:#}"),
                Err(e) => tracing::error!("closing a lane: {e}"),
                Ok(_) => {}
            }
        }
        let names: Vec<String> = self.pending.keys().cloned().collect();
        for name in names {
            self.release_pending(&name).await;
        }
    }

    /// Lists the group's tokens again: a member missed by an event is added; one missing
    /// from two listings in a row is removed (one listing may come while a link is
    /// reconnecting).
    async fn list_members(&mut self) {
        let Ok(listed) = present_members(&self.session, &self.members_ke).await else {
            return;
        };
        let listed: BTreeSet<String> = listed.into_iter().collect();
        let mut changed = false;
        for id in listed
            .difference(&self.members)
            .cloned()
            .collect::<Vec<_>>()
        {
            tracing::warn!(
                member = id,
                "a member's token was found by listing the group"
            );
            changed |= self.members.insert(id);
        }
        let missing: BTreeSet<String> = self
            .members
            .iter()
            .filter(|m| **m != self.me && !listed.contains(*m))
            .cloned()
            .collect();
        for id in missing.intersection(&self.absent) {
            tracing::warn!(
                member = id,
                "a member's token is gone (found by listing the group)"
            );
            changed |= self.members.remove(id);
        }
        self.absent = missing;
        if changed {
            self.expire_fences();
            tracing::info!(members = ?self.members, "fleet membership changed");
        }
    }

    fn expire_fences(&self) {
        for f in self.lanes.values().filter_map(|l| l.fence.as_ref()) {
            f.expire();
        }
    }

    fn member_changed(&mut self, s: &zenoh::sample::Sample) {
        let Some(id) = s.key_expr().as_str().rsplit('/').next() else {
            return;
        };
        if id == self.me {
            return;
        }
        let joined = s.kind() == SampleKind::Put;
        let changed = if joined {
            self.members.insert(id.to_string())
        } else {
            self.members.remove(id)
        };
        if changed {
            // Any change may be this daemon's own link going or coming back: every lane
            // confirms its epoch again before its next output.
            self.expire_fences();
            tracing::info!(
                member = id,
                joined,
                members = ?self.members,
                "fleet membership changed"
            );
        }
    }

    /// An owner record was put: a lane of this daemon whose epoch it passes is fenced and
    /// closed without writing anything more. Another member's record of the lane's own
    /// epoch makes the lane ask the storages which of the two they kept.
    async fn record_seen(&mut self, s: &zenoh::sample::Sample) {
        let Ok(r) = serde_json::from_slice::<OwnerRecord>(&s.payload().to_bytes()) else {
            tracing::warn!("an owner record on {} is not valid", s.key_expr());
            return;
        };
        let Some(f) = self.lanes.get(&r.structure).and_then(|l| l.fence.clone()) else {
            return;
        };
        if r.epoch == f.epoch && r.owner != f.owner {
            f.expire();
        }
        if r.epoch > f.epoch {
            tracing::warn!(
                structure = r.structure,
                owner = r.owner,
                epoch = r.epoch,
                "another member took the structure over: standing down"
            );
            self.abandon(&r.structure).await;
        }
    }

    /// Takes over what rendezvous hashing gives this daemon, hands back what it no longer
    /// does, and closes lanes fenced on the way.
    async fn reconcile(&mut self) {
        let fenced: Vec<String> = self
            .lanes
            .iter()
            .filter(|(_, l)| l.fence.as_ref().is_some_and(|f| f.is_fenced()))
            .map(|(n, _)| n.clone())
            .collect();
        for name in fenced {
            self.abandon(&name).await;
        }
        let pending: Vec<String> = self.pending.keys().cloned().collect();
        for name in pending {
            self.release_pending(&name).await;
        }
        let settings = self.settings.clone();
        for s in &settings.structures {
            let mine = rendezvous::owner(self.members.iter().map(String::as_str), &s.name)
                == Some(self.me.as_str());
            match (mine, self.lanes.contains_key(&s.name)) {
                (true, false) => self.try_take_over(s).await,
                (false, true) => self.hand_back(&s.name).await,
                _ => {}
            }
        }
    }

    /// A takeover, unless a failed one of the structure is still backing off; a failure
    /// doubles the wait (up to [`BACKOFF_MAX`]).
    async fn try_take_over(&mut self, s: &crate::settings::StructureSettings) {
        let now = tokio::time::Instant::now();
        if self
            .backoff
            .get(&s.name)
            .is_some_and(|(until, _)| now < *until)
        {
            return;
        }
        match self.take_over(s).await {
            Ok(()) => {
                self.backoff.remove(&s.name);
            }
            Err(e) => {
                let wait = self
                    .backoff
                    .get(&s.name)
                    .map_or(Duration::from_secs(1), |(_, w)| (*w * 2).min(BACKOFF_MAX));
                tracing::error!(structure = s.name, retry_in_s = wait.as_secs(), "{e:#}");
                self.backoff.insert(s.name.clone(), (now + wait, wait));
            }
        }
    }
}
