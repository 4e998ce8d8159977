//! One structure's lane in the running daemon: its tracking thread ([`Worker`]) and the
//! Zenoh declarations feeding it (subscribers to modal sets, raw data and environment
//! readings; the status queryable). A lane opens from the structure's state, local or in
//! the fleet's storages ([`LaneState`]), and closes in steps (intake stopped, queue
//! drained, state written), so the daemon can open and close lanes while it runs: all at
//! start and stop alone, or one by one as a fleet's ownership moves.

use std::path::Path;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::sync::mpsc::{self, SyncSender};
use std::time::Duration;

use anyhow::{Context, Result, anyhow};
use zenoh::Wait;
use zenoh::query::Queryable;
use zenoh_ext::{AdvancedSubscriber, AdvancedSubscriberBuilderExt, HistoryConfig, RecoveryConfig};

use super::fleet::fence::Fence;
use super::fleet::state::{Fetched, WalEntry};
use super::metrics::Shared;
use super::worker::{self, Input, LiveSink, Remote, Resume, Worker};
use super::{DoneTx, contact, log};
use crate::contract::{Checkpoint, WalPosition, to_wire};
use crate::core::model::Model;
use crate::io::checkpoint;
use crate::io::driver::{CrosscheckLane, MemoryBudget};
use crate::io::mcap::topic;
use crate::io::model::load_structure;
use crate::io::zenoh::zerr;
use crate::pipeline::{Tracker, TrackerState};
use crate::settings::{Settings, StructureSettings};

/// Where a lane's state is.
pub enum LaneState {
    /// `daemon.state_dir`: the checkpoint file and the rolling log.
    Local,
    /// The fleet's storages: what was fetched at the takeover, and the epoch's fence.
    Remote { fence: Arc<Fence>, fetched: Fetched },
}

/// What the subscribers of a lane feed: its queue and its shared status.
struct Intake {
    tx: SyncSender<Input>,
    shared: Arc<Shared>,
}

/// One structure's running lane (module docs). The fields drop in the order written.
pub struct Lane {
    pub name: String,
    pub shared: Arc<Shared>,
    pub fence: Option<Arc<Fence>>,
    queryable: Option<Queryable<()>>,
    subscribers: Vec<AdvancedSubscriber<()>>,
    thread: Option<std::thread::JoinHandle<()>>,
    tx: SyncSender<Input>,
}

impl Lane {
    /// Recovers the structure from `state`, starts its tracking thread (which first handles
    /// again what the state says was not yet handled) and declares its subscribers and
    /// status queryable.
    pub async fn open(
        settings: &Settings,
        s: &StructureSettings,
        session: &zenoh::Session,
        state: LaneState,
        done: &DoneTx,
    ) -> Result<Lane> {
        let fence = match &state {
            LaneState::Remote { fence, .. } => Some(fence.clone()),
            LaneState::Local => None,
        };
        let recovered = recover(settings, s, session, state)?;
        let shared = recovered.shared.clone();
        if let Some(f) = &fence {
            let beat = shared.clone();
            f.on_wait(move || beat.beat());
        }
        let (tx, thread) = start(&s.name, recovered, settings.daemon.queue, done)?;
        let intake = Intake {
            tx: tx.clone(),
            shared: shared.clone(),
        };
        let mut lane = Lane {
            name: s.name.clone(),
            shared,
            fence,
            queryable: None,
            subscribers: Vec::new(),
            thread: Some(thread),
            tx,
        };
        if let Err(e) = lane.declare(session, &s.name, &intake).await {
            // The thread has resumed and may write: stand it down before failing.
            if let Some(f) = &lane.fence {
                f.fence();
                f.closing();
            }
            if let Err(c) = lane.close().await {
                tracing::error!(structure = s.name, "closing the lane that failed: {c:#}");
            }
            return Err(e);
        }
        tracing::info!(
            structure = s.name,
            "watching {} (status on {})",
            topic(&s.name, "modal"),
            topic(&s.name, "status")
        );
        Ok(lane)
    }

    /// Declares the lane's subscribers and its status queryable.
    async fn declare(
        &mut self,
        session: &zenoh::Session,
        name: &str,
        intake: &Intake,
    ) -> Result<()> {
        self.subscribers
            .push(subscribe_modal(session, name, intake).await?);
        self.subscribers
            .push(subscribe_accel(session, name, intake).await?);
        self.subscribers
            .push(subscribe_environment(session, name, intake).await?);
        self.queryable = Some(declare_status(session, name, &self.shared).await?);
        Ok(())
    }

    /// Stops the intake: no new input from here on (what is queued is still handled).
    pub async fn stop_intake(&mut self) -> Result<()> {
        for sub in self.subscribers.drain(..) {
            sub.undeclare()
                .await
                .map_err(zerr("cannot undeclare a subscriber"))?;
        }
        Ok(())
    }

    /// Tells the tracking thread to finish once the queue is handled (waiting, off the
    /// async runtime, while the queue is full).
    pub async fn signal_shutdown(&self) {
        let tx = self.tx.clone();
        let _ = tokio::task::spawn_blocking(move || tx.send(Input::Shutdown)).await;
    }

    /// Waits for the tracking thread (it checkpoints and closes its log) and withdraws the
    /// status queryable.
    pub async fn join(mut self) -> Result<()> {
        if let Some(t) = self.thread.take() {
            tokio::task::spawn_blocking(move || t.join())
                .await
                .map_err(|e| anyhow!("shutdown of {}: {e}", self.name))?
                .map_err(|_| anyhow!("the tracking thread of {} panicked", self.name))?;
        }
        Ok(())
    }

    /// Closes the lane: intake stopped, queue handled, state written, log closed.
    pub async fn close(mut self) -> Result<()> {
        self.stop_intake().await?;
        self.signal_shutdown().await;
        self.join().await
    }
}

/// Starts the tracking thread of `structure`: it handles again what the recovery found,
/// then tracks what comes through the returned queue.
fn start(
    structure: &str,
    recovered: Recovered,
    queue: usize,
    done: &DoneTx,
) -> Result<(SyncSender<Input>, std::thread::JoinHandle<()>)> {
    let Recovered {
        mut worker,
        resume_from,
        ..
    } = recovered;
    let (tx, rx) = mpsc::sync_channel::<Input>(queue);
    let done = done.clone();
    let name = structure.to_string();
    let thread = std::thread::Builder::new()
        .name(format!("track-{name}"))
        .spawn(move || {
            crate::core::sequential_numerics();
            // A panic outside the per-set guards (in the resume, a checkpoint, the log)
            // must not leave the process up with this structure dark.
            let r = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                worker.resume(resume_from)?;
                worker.run(rx)
            }))
            .unwrap_or_else(|p| {
                Err(anyhow!(
                    "the tracking thread panicked: {}",
                    worker::panic_message(&*p)
                ))
            });
            // A lane closed on purpose ends well and says nothing: the daemon hears of
            // failures only.
            if r.is_err() {
                let _ = done.send((name, r));
            }
        })?;
    Ok((tx, thread))
}

/// One structure as [`recover`] leaves it, before its tracking thread starts.
struct Recovered {
    worker: Worker,
    /// What the thread handles again before it takes new inputs.
    resume_from: Resume,
    shared: Arc<Shared>,
}

/// Recovers one structure from its state: the model, the tracker (from the checkpoint, or
/// afresh), the rolling log (which is also the write-ahead log) and the worker over them.
fn recover(
    settings: &Settings,
    s: &StructureSettings,
    session: &zenoh::Session,
    state: LaneState,
) -> Result<Recovered> {
    let d = &settings.daemon;
    let structure_model = Arc::new(load_structure(s)?);
    let model = structure_model.1.clone();
    let ckpt = d.state_dir.join(format!("{}.checkpoint.json", s.name));
    let (mut tracker, resume_from, remote) = match state {
        LaneState::Local => {
            let (t, from) = restore(settings, s, model, &ckpt)?;
            (t, Resume::Log(from), None)
        }
        LaneState::Remote { fence, fetched } => {
            let (t, tail) = restore_remote(settings, s, model, &fetched)?;
            let obsolete = fetched.obsolete_keys();
            let remote = Remote::new(session.clone(), fence, obsolete);
            (t, Resume::Remote(tail), Some(remote))
        }
    };
    crate::io::model::adopt_law(&mut tracker)?;
    for (connection, why) in tracker.alerts_off() {
        tracing::warn!(structure = s.name, connection, "alerts off: {why}");
    }
    tracker.set_max_future(Some(chrono::TimeDelta::milliseconds(
        (d.max_future_s * 1e3).round() as i64,
    )));
    let log = log::RollingLog::open(
        &d.state_dir.join("log"),
        &s.name,
        d.log_rotate_mib << 20,
        Duration::from_secs_f64(d.log_rotate_hours * 3600.0),
    )?;
    let shared = Shared::new(
        &s.name,
        d.queue,
        (d.queue_mib as u64) << 20,
        d.max_payload_bytes,
    );
    let _ = shared.model.set(structure_model.clone());
    let fence = remote.as_ref().map(|r| r.fence.clone());
    let mut worker = Worker::new(
        structure_model,
        tracker,
        LiveSink::start(session.clone(), log, shared.clone(), fence)?,
        ckpt,
        Duration::from_secs_f64(d.checkpoint_every_s),
        CrosscheckLane {
            cfg: settings.crosscheck.clone(),
            budget: Some(MemoryBudget::from_mib(d.memory_mib)),
        },
        settings.identify.clone(),
    )?;
    if let Some(r) = remote {
        worker = worker.with_remote(r);
    }
    Ok(Recovered {
        worker,
        resume_from,
        shared,
    })
}

/// The structure's tracker, restored from the checkpoint `ckpt` with the write-ahead
/// position it recorded, or a fresh one (and no position) when there is no checkpoint.
fn restore(
    settings: &Settings,
    s: &StructureSettings,
    model: Model,
    ckpt: &Path,
) -> Result<(Tracker, Option<WalPosition>)> {
    let mut resume_from = None;
    let tracker = match checkpoint::read::<Checkpoint<TrackerState>>(ckpt)
        .with_context(|| format!("{} (move it away to start afresh)", ckpt.display()))?
    {
        Some(v) => {
            resume_from = v.wal.clone();
            if resume_from.is_none() {
                tracing::warn!(
                    structure = s.name,
                    "checkpoint {} has no write-ahead position (written before there was one): sets logged after it are not handled again",
                    ckpt.display()
                );
            }
            let t = Tracker::restore(model, settings.tracker.clone(), v).with_context(|| {
                format!(
                    "checkpoint {} (move it away to start afresh)",
                    ckpt.display()
                )
            })?;
            tracing::info!(
                structure = s.name,
                accepted = t.state().accepted,
                "resumed from checkpoint {}",
                ckpt.display()
            );
            t
        }
        None => Tracker::new(model, settings.tracker.clone())?,
    };
    Ok((tracker, resume_from))
}

/// The structure's tracker from the latest checkpoint the storages hold (or afresh), and
/// the write-ahead entries to handle again after it.
fn restore_remote(
    settings: &Settings,
    s: &StructureSettings,
    model: Model,
    fetched: &Fetched,
) -> Result<(Tracker, Vec<WalEntry>)> {
    let (c, tail) = fetched
        .tail()
        .with_context(|| format!("the stored state of {}", s.name))?;
    let tail: Vec<WalEntry> = tail.into_iter().cloned().collect();
    let tracker = match c {
        Some(c) => {
            let t = Tracker::restore(model, settings.tracker.clone(), c.clone())
                .with_context(|| format!("the stored checkpoint of {}", s.name))?;
            tracing::info!(
                structure = s.name,
                accepted = t.state().accepted,
                to_handle_again = tail.len(),
                "resumed from the fleet's stored checkpoint"
            );
            t
        }
        None => Tracker::new(model, settings.tracker.clone())?,
    };
    Ok((tracker, tail))
}

/// The subscriber to the modal sets of `structure`, through a [`contact::Gate`], with a
/// listener that reports the sets lost in transport.
async fn subscribe_modal(
    session: &zenoh::Session,
    structure: &str,
    lane: &Intake,
) -> Result<AdvancedSubscriber<()>> {
    let gate = contact::Gate::new(
        session.clone(),
        zenoh::key_expr::KeyExpr::try_from(topic(structure, "modal"))
            .map_err(zerr(format!("structure {structure}: modal key")))?,
        lane.tx.clone(),
        lane.shared.clone(),
    );
    // zenoh-ext's advanced subscriber: on start it asks every sensor's advanced
    // publisher for its cache (history, and for publishers that appear later), and it
    // detects sets missed in transport by their sequence numbers and fetches them again
    // (recovery, triggered by the publishers' heartbeats). Sets published while the
    // daemon was down are recovered this way; those it had handled are recognised by the
    // tracker and skipped. zenoh-ext can lose the history of a publisher it meets late
    // (see [`contact`]): the gate fetches it again.
    let sub = session
        .declare_subscriber(topic(structure, "modal"))
        .history(HistoryConfig::default().detect_late_publishers())
        .recovery(RecoveryConfig::default().heartbeat())
        .subscriber_detection()
        .callback(move |sample| gate.offer(&sample))
        .await
        .map_err(zerr(format!(
            "cannot subscribe to {}",
            topic(structure, "modal")
        )))?;
    // Sets a publisher's cache no longer held: lost, so reported (on `rejected`).
    let miss_shared = lane.shared.clone();
    sub.sample_miss_listener()
        .callback(move |miss| {
            tracing::warn!(
                structure = miss_shared.structure,
                "{} modal set(s) from publisher {}:{} were lost in transport and are no longer in its cache",
                miss.nb(),
                miss.source().zid(),
                miss.source().eid()
            );
            miss_shared
                .missed
                .fetch_add(u64::from(miss.nb()), Ordering::Relaxed);
        })
        .background()
        .await
        .map_err(zerr("cannot declare the sample-miss listener"))?;
    Ok(sub)
}

/// The subscriber to the raw data of `structure`: blocks in stream order into the same
/// queue, identified by the worker window by window. Recovery fetches blocks missed in
/// transport from the sensor's publisher cache; no history (old blocks would be out of
/// stream order).
async fn subscribe_accel(
    session: &zenoh::Session,
    structure: &str,
    lane: &Intake,
) -> Result<AdvancedSubscriber<()>> {
    let accel_tx = lane.tx.clone();
    let accel_shared = lane.shared.clone();
    session
        .declare_subscriber(topic(structure, "accel"))
        .recovery(RecoveryConfig::default().heartbeat())
        .callback(move |sample| worker::enqueue_accel(&accel_tx, &accel_shared, sample.payload()))
        .await
        .map_err(zerr(format!(
            "cannot subscribe to {}",
            topic(structure, "accel")
        )))
}

/// The subscriber to the environment readings of `structure`, for sites whose thermometer
/// is not in the OMA box: into the same queue (and the write-ahead log), so they are
/// joined in arrival order.
async fn subscribe_environment(
    session: &zenoh::Session,
    structure: &str,
    lane: &Intake,
) -> Result<AdvancedSubscriber<()>> {
    let env_tx = lane.tx.clone();
    let env_shared = lane.shared.clone();
    session
        .declare_subscriber(topic(structure, "environment"))
        .history(HistoryConfig::default().detect_late_publishers())
        .recovery(RecoveryConfig::default().heartbeat())
        .callback(move |sample| worker::enqueue_environment(&env_tx, &env_shared, sample.payload()))
        .await
        .map_err(zerr(format!(
            "cannot subscribe to {}",
            topic(structure, "environment")
        )))
}

/// The queryable that answers `boltwatch/<structure>/status` (and wildcard queries
/// matching it) from the shared status.
async fn declare_status(
    session: &zenoh::Session,
    structure: &str,
    shared: &Arc<Shared>,
) -> Result<Queryable<()>> {
    let q_shared = shared.clone();
    let key = topic(structure, "status");
    session
        .declare_queryable(key.clone())
        .callback(move |query| {
            let body = to_wire(&q_shared.status_reply());
            // On its own key, so a query on `boltwatch/*/status` has every structure answer.
            if let Err(e) = query.reply(&key, body).wait() {
                tracing::warn!("cannot answer a status query: {e}");
            }
        })
        .await
        .map_err(zerr(format!(
            "cannot declare {}",
            topic(structure, "status")
        )))
}
