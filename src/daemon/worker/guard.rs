//! Tracking one input without letting it stop the thread: a panic in the tracker rejects
//! the set and restores the state from before it; an error or a panic while writing a set's
//! outputs becomes the set's rejection.

use std::panic::AssertUnwindSafe;
use std::time::Instant;

use anyhow::{Context, Result};
use chrono::{DateTime, Utc};

use super::Worker;
use crate::contract::modal_set::Rejection;
use crate::contract::{Checkpoint, Output, Rejected, Schema};
use crate::io::driver::{Pace, dispatch, emit};
use crate::pipeline::{Action, Tracker, TrackerState};

impl Worker {
    /// Tracks one set: a panic in the tracker rejects the set and restores the state from
    /// before it.
    pub(super) fn handle(&mut self, received: DateTime<Utc>, payload: &[u8]) -> Result<()> {
        let before = self.tracker.state().clone();
        let start = Instant::now();
        let tracked =
            std::panic::catch_unwind(AssertUnwindSafe(|| self.tracker.handle(received, payload)));
        self.out.shared.latency.observe(start.elapsed());
        self.dirty = true;
        let actions = match tracked {
            Ok(actions) => actions,
            Err(panic) => {
                let why = panic_message(&*panic);
                tracing::error!(
                    structure = self.structure(),
                    "tracking a set panicked ({why}); the set is rejected and the state restored"
                );
                self.restore(before)?;
                self.out.shared.with_status(|st| st.failed += 1);
                let rej = Rejection {
                    field: "payload".into(),
                    reason: format!(
                        "tracking this set failed (internal error: {why}); the state is as before it"
                    ),
                };
                self.tracker.reject(received, &rej, payload)
            }
        };
        self.publish_guarded(received, payload, actions)
    }

    /// Carries out one set's actions; an error or a panic while writing its outputs
    /// becomes the set's rejection. Only a failure to publish that rejection is fatal.
    pub(super) fn publish_guarded(
        &mut self,
        received: DateTime<Utc>,
        payload: &[u8],
        actions: Vec<Action>,
    ) -> Result<()> {
        let s = self.structure().to_string();
        let done = std::panic::catch_unwind(AssertUnwindSafe(|| {
            dispatch(&s, actions, &mut self.lane, &mut self.out, Pace::Live)
        }));
        let failure = match done {
            Ok(Ok(d)) => {
                if d.checkpoint_due && !self.replaying {
                    self.checkpoint()?;
                }
                return Ok(());
            }
            Ok(Err(e)) => format!("{e:#}"),
            Err(panic) => format!("internal error: {}", panic_message(&*panic)),
        };
        tracing::error!(
            structure = s,
            "writing the outputs of a set failed: {failure}"
        );
        self.out.shared.with_status(|st| st.failed += 1);
        let r = Rejected::payload(
            &s,
            received,
            "payload",
            &format!("writing this set's outputs failed: {failure}"),
            payload,
        );
        emit(&mut self.out, Output::Rejected(Box::new(r)))
            .context("cannot even publish the rejection of a set whose outputs failed")
    }

    /// Rebuilds the tracker from `state` (after a panic mid-update), without the eigen
    /// solver's warm block, which the panic may have left half-written.
    fn restore(&mut self, state: TrackerState) -> Result<()> {
        let model = self.tracker.model().clone();
        let cfg = self.tracker.config().clone();
        let max_future = self.tracker.max_future();
        self.tracker = Tracker::restore(
            model,
            cfg,
            Checkpoint {
                schema: Schema::new(),
                state,
                eigen_block: None,
                wal: None,
                fleet: None,
            },
        )?;
        self.tracker.set_max_future(max_future);
        Ok(())
    }
}

/// What a caught panic said.
pub fn panic_message(panic: &(dyn std::any::Any + Send)) -> String {
    panic
        .downcast_ref::<&str>()
        .map(|s| s.to_string())
        .or_else(|| panic.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "a panic without a message".into())
}
