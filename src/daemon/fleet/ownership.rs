//! The controller's three moves on one structure: take it over (a new epoch), hand it back
//! (drained, state written, record released), abandon it (fenced: nothing more written).

use anyhow::{Context, Result, anyhow};
use chrono::Utc;
use zenoh::qos::CongestionControl;

use std::sync::Arc;

use super::fence::{Fence, read_owner};
use super::state::{self, OwnerRecord, owner_key};
use super::{Controller, unwatch, watch};
use crate::contract::{Ownership, rfc3339, to_wire};
use crate::daemon::lane::{Lane, LaneState};
use crate::io::zenoh::zerr;
use crate::settings::StructureSettings;

impl Controller {
    /// Takes `s` over, unless its record names a live member that has not handed it back
    /// (then the next reconcile looks again): a new epoch in the owner record, then a lane
    /// resumed from the stored checkpoint and write-ahead tail.
    pub(super) async fn take_over(&mut self, s: &StructureSettings) -> Result<()> {
        let session = self.session.clone();
        let name = s.name.clone();
        let fetched = tokio::task::spawn_blocking(move || state::fetch(&session, &name))
            .await
            .map_err(|e| anyhow!("fetching the state of {}: {e}", s.name))??;
        if let Some(r) = &fetched.owner
            && !r.released
            && r.owner != self.me
            && self.members.contains(&r.owner)
        {
            tracing::debug!(
                structure = s.name,
                owner = r.owner,
                "waiting for the owner to hand the structure back"
            );
            return Ok(());
        }
        let epoch = 1 + fetched.latest_epoch();
        let record = OwnerRecord {
            structure: s.name.clone(),
            epoch,
            owner: self.me.clone(),
            released: false,
            since: rfc3339(Utc::now()),
        };
        put_record(&self.session, &record).await?;
        let fence = Fence::new(self.session.clone(), &s.name, &self.me, epoch);
        let state = LaneState::Remote { fence, fetched };
        let lane = Lane::open(&self.settings, s, &self.session, state, &self.done)
            .await
            .with_context(|| format!("taking {} over at epoch {epoch}", s.name))?;
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

    /// Hands `name` back: its lane closed (every queued set handled, the checkpoint
    /// written), then its record released for the member whose turn it is.
    pub(super) async fn hand_back(&mut self, name: &str) -> Result<()> {
        let Some(lane) = self.lanes.remove(name) else {
            return Ok(());
        };
        unwatch(&self.watched, name);
        let fence = lane.fence.clone();
        if let Some(f) = &fence {
            // With no storage answering, the final checkpoint is given up rather than
            // waited for forever (the record is then not released either).
            f.closing();
        }
        lane.close().await?;
        if let Some(f) = fence
            && !f.is_fenced()
            && still_current(&self.session, &f).await
        {
            let record = OwnerRecord {
                structure: name.to_string(),
                epoch: f.epoch,
                owner: self.me.clone(),
                released: true,
                since: rfc3339(Utc::now()),
            };
            put_record(&self.session, &record).await?;
            tracing::info!(
                structure = name,
                epoch = f.epoch,
                "handed the structure back"
            );
        }
        Ok(())
    }

    /// Closes the lane of `name`, whose epoch moved on, without publishing or writing.
    pub(super) async fn abandon(&mut self, name: &str) {
        let Some(lane) = self.lanes.remove(name) else {
            return;
        };
        unwatch(&self.watched, name);
        if let Some(f) = &lane.fence {
            f.fence();
            f.closing();
        }
        if let Err(e) = lane.close().await {
            tracing::error!(structure = name, "closing the fenced lane: {e:#}");
        }
    }
}

/// Whether the owner record is still the lane's own (read from the storages): a member that
/// was cut off must not release, over a newer owner's record, an epoch that moved on.
async fn still_current(session: &zenoh::Session, f: &Arc<Fence>) -> bool {
    let (session, structure) = (session.clone(), f.structure.clone());
    let read = tokio::task::spawn_blocking(move || read_owner(&session, &structure)).await;
    match read {
        Ok(Ok(r)) => !r.supersedes(f.epoch, &f.owner),
        Ok(Err(e)) => {
            tracing::warn!(structure = f.structure, "not releasing: {e:#}");
            false
        }
        Err(e) => {
            tracing::warn!(structure = f.structure, "not releasing: {e}");
            false
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
