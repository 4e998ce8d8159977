//! The controller's three moves on one structure: take it over (a new epoch), hand it back
//! (drained, state written, record released), abandon it (fenced: nothing more written).

use anyhow::{Context, Result, anyhow, bail};
use chrono::Utc;
use zenoh::qos::CongestionControl;

use std::time::Duration;

use super::fence::{Fence, read_owner};
use super::state::{self, OwnerRecord, owner_key};
use super::{Controller, unwatch, watch};
use crate::contract::{Ownership, rfc3339, to_wire};
use crate::daemon::lane::{Lane, LaneState};
use crate::io::zenoh::zerr;
use crate::settings::StructureSettings;

impl Controller {
    /// Takes `s` over, unless its record names a live member that has not handed it back
    /// (then the next reconcile looks again): a new epoch in the owner record, confirmed
    /// from the storages, then a lane resumed from the stored checkpoint and write-ahead
    /// tail.
    pub(super) async fn take_over(&mut self, s: &StructureSettings) -> Result<()> {
        // While a live owner has not handed it back, only its record is read.
        let (session, name) = (self.session.clone(), s.name.clone());
        let record = tokio::task::spawn_blocking(move || read_owner(&session, &name)).await;
        if let Ok(Ok(r)) = &record
            && self.waits_for(r)
        {
            return Ok(());
        }
        let (session, name) = (self.session.clone(), s.name.clone());
        let fetched = tokio::task::spawn_blocking(move || state::fetch(&session, &name))
            .await
            .map_err(|e| anyhow!("fetching the state of {}: {e}", s.name))??;
        if let Some(r) = &fetched.owner
            && self.waits_for(r)
        {
            return Ok(());
        }
        // A state that cannot be resumed is refused before it costs an epoch.
        fetched
            .tail()
            .with_context(|| format!("the stored state of {}", s.name))?;
        let epoch = 1 + fetched.latest_epoch();
        let record = OwnerRecord {
            structure: s.name.clone(),
            epoch,
            owner: self.me.clone(),
            released: false,
            since: rfc3339(Utc::now()),
        };
        put_record(&self.session, &record).await?;
        self.pending.insert(s.name.clone(), epoch);
        confirm(&self.session, &record).await?;
        let fence = Fence::new(self.session.clone(), &s.name, &self.me, epoch);
        let state = LaneState::Remote { fence, fetched };
        let lane = Lane::open(&self.settings, s, &self.session, state, &self.done)
            .await
            .with_context(|| format!("taking {} over at epoch {epoch}", s.name))?;
        self.pending.remove(&s.name);
        lane.shared.with_status(|st| {
            st.ownership = Some(Ownership {
                group: self.settings.fleet.group.clone(),
                owner: self.me.clone(),
                epoch,
                since: record.since.clone(),
                held: 0,
            })
        });
        watch(&self.watched, &lane);
        self.lanes.insert(s.name.clone(), lane);
        tracing::info!(structure = s.name, epoch, "took the structure over");
        Ok(())
    }

    /// Whether `r` names a live member, not this one, that has not handed the structure
    /// back: then a takeover waits.
    fn waits_for(&self, r: &OwnerRecord) -> bool {
        let waits = !r.released && r.owner != self.me && self.members.contains(&r.owner);
        if waits {
            tracing::debug!(
                structure = r.structure,
                owner = r.owner,
                "waiting for the owner to hand the structure back"
            );
        }
        waits
    }

    /// Hands `name` back: its lane closed (every queued set handled, the checkpoint
    /// written), then its record released for the member whose turn it is.
    pub(super) async fn hand_back(&mut self, name: &str) {
        let Some(lane) = self.lanes.remove(name) else {
            return;
        };
        unwatch(&self.watched, name);
        let fence = lane.fence.clone();
        if let Some(f) = &fence {
            // With no storage answering, the final checkpoint is given up rather than
            // waited for forever (the record is then not released either).
            f.closing();
        }
        if let Err(e) = lane.close().await {
            tracing::error!(structure = name, "closing the lane: {e:#}");
        }
        if let Some(f) = fence
            && !f.is_fenced()
        {
            self.pending.insert(name.to_string(), f.epoch);
        }
        self.release_pending(name).await;
    }

    /// Closes the lane of `name`, whose epoch moved on, without publishing or writing. If
    /// the storages still name this member for its epoch (two members took the same
    /// epoch, and both stood down), the record is released so that another can go on.
    pub(super) async fn abandon(&mut self, name: &str) {
        let Some(lane) = self.lanes.remove(name) else {
            return;
        };
        unwatch(&self.watched, name);
        let epoch = lane.fence.as_ref().map(|f| f.epoch);
        if let Some(f) = &lane.fence {
            f.fence();
            f.closing();
        }
        if let Err(e) = lane.close().await {
            tracing::error!(structure = name, "closing the fenced lane: {e:#}");
        }
        if let Some(epoch) = epoch {
            self.pending.insert(name.to_string(), epoch);
            self.release_pending(name).await;
        }
    }

    /// Releases the record of `name` left by this member (a hand-back, a fenced lane, a
    /// takeover that failed after its record was put), if the storages still hold it;
    /// kept for the next reconcile when they cannot be read.
    pub(super) async fn release_pending(&mut self, name: &str) {
        let Some(&epoch) = self.pending.get(name) else {
            return;
        };
        if self.lanes.contains_key(name) {
            self.pending.remove(name);
            return;
        }
        let (session, structure) = (self.session.clone(), name.to_string());
        let read = tokio::task::spawn_blocking(move || read_owner(&session, &structure)).await;
        let r = match read.map_err(anyhow::Error::from).and_then(|r| r) {
            Ok(r) => r,
            Err(e) => {
                tracing::warn!(structure = name, "not released yet: {e:#}");
                return;
            }
        };
        if r.epoch == epoch && r.owner == self.me && !r.released {
            let record = OwnerRecord {
                released: true,
                since: rfc3339(Utc::now()),
                ..r
            };
            if let Err(e) = put_record(&self.session, &record).await {
                tracing::warn!(structure = name, "not released yet: {e:#}");
                return;
            }
            tracing::info!(structure = name, epoch, "handed the structure back");
        }
        self.pending.remove(name);
    }
}

/// How long a takeover waits for the storages to hold its record.
const CONFIRM_TIMEOUT: Duration = Duration::from_secs(3);

/// Waits until the storages hold `record` (the takeover's epoch is this member's), or
/// fails: another member's record of the same or a later epoch, or no confirmation.
async fn confirm(session: &zenoh::Session, record: &OwnerRecord) -> Result<()> {
    let deadline = tokio::time::Instant::now() + CONFIRM_TIMEOUT;
    loop {
        let (session, structure) = (session.clone(), record.structure.clone());
        let read = tokio::task::spawn_blocking(move || read_owner(&session, &structure)).await?;
        match read {
            Ok(r) if r == *record => return Ok(()),
            Ok(r) if r.fences(record.epoch, &record.owner) => bail!(
                "{} was taken at epoch {} by {} meanwhile",
                r.structure,
                r.epoch,
                r.owner
            ),
            _ if tokio::time::Instant::now() >= deadline => bail!(
                "the storages did not confirm epoch {} of {}",
                record.epoch,
                record.structure
            ),
            _ => tokio::time::sleep(Duration::from_millis(50)).await,
        }
    }
}

/// Puts an owner record (blocking on congestion: it must not be dropped).
async fn put_record(session: &zenoh::Session, r: &OwnerRecord) -> Result<()> {
    session
        .put(owner_key(&r.structure), to_wire(r))
        .congestion_control(CongestionControl::Block)
        .await
        .map_err(zerr(format!(
            "cannot put the owner record of {}",
            r.structure
        )))
}
