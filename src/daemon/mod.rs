//! `boltwatch run` (issue 5, DESIGN §3.4 and §7): the live daemon.
//!
//! One Zenoh session. Per watched structure: zenoh-ext's advanced subscriber on
//! `boltwatch/<s>/modal` (history and recovery from the sensors' publisher caches) that
//! puts each payload into a bounded queue (a set that does not fit is dropped and counted,
//! and the count is published on `rejected`, logged and shown in status and metrics); a
//! tracking thread ([`worker`]) that runs the sans-I/O [`crate::pipeline::Tracker`] on the
//! queue, publishes `stiffness`, `alerts`, `crosscheck` and `rejected`, and writes inputs and
//! outputs into a rolling MCAP log ([`log`]); a cross-check thread; a queryable on
//! `boltwatch/<s>/status`. A Prometheus endpoint ([`metrics`]) serves every structure.
//!
//! State lives in `[daemon] state_dir` (default `$XDG_STATE_HOME/boltwatch`): `<s>.checkpoint.json` (the tracker, written
//! atomically every `tracker.checkpoint_every_sets` sets, every `checkpoint_every_s` seconds
//! while sets arrive, and at shutdown) and `log/`, which is also the write-ahead log. A
//! restart resumes from the checkpoint and tracks again the sets logged after it
//! ([`worker::Worker::resume`]). systemd: readiness and a watchdog fed while every tracking
//! loop goes round (`sd_notify`).
//!
//! Shutdown (SIGINT, SIGTERM): the subscribers are undeclared first, every set already
//! queued is processed, a running cross-check is awaited, the state is checkpointed and the
//! log file is finished, so nothing received is lost and a restart duplicates nothing.

pub mod contact;
pub mod fleet;
pub mod log;
pub mod metrics;
pub mod worker;

use std::path::Path;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::sync::mpsc::{self, SyncSender};
use std::time::Duration;

use anyhow::{Context, Result, anyhow, bail};
use tokio::task::JoinHandle;
use zenoh::Wait;
use zenoh::query::Queryable;
use zenoh_ext::{AdvancedSubscriber, AdvancedSubscriberBuilderExt, HistoryConfig, RecoveryConfig};

use crate::contract::{Checkpoint, WalPosition, to_wire};
use crate::core::model::Model;
use crate::io::checkpoint;
use crate::io::driver::{CrosscheckLane, MemoryBudget};
use crate::io::mcap::topic;
use crate::io::model::load_structure;
use crate::io::zenoh::{session_config, zerr};
use crate::pipeline::{Tracker, TrackerState};
use crate::settings::{MetricsSettings, Settings, StructureSettings};
use metrics::Shared;
use worker::{Input, LiveSink, Worker};

/// How a tracking thread ended: its structure and its result.
type Done = (String, Result<()>);
/// Where the tracking threads send how they ended, and where the daemon hears it.
type DoneTx = tokio::sync::mpsc::UnboundedSender<Done>;
type DoneRx = tokio::sync::mpsc::UnboundedReceiver<Done>;

/// Runs the daemon until SIGINT or SIGTERM (or a tracking thread fails).
pub async fn run(settings: Settings) -> Result<()> {
    let session = configure(&settings).await?;
    let (done_tx, mut done_rx) = tokio::sync::mpsc::unbounded_channel::<Done>();
    let mut lanes = Lanes::default();
    for s in &settings.structures {
        let recovered = recover(&settings, s, &session)?;
        let lane = lanes.start(&s.name, recovered, settings.daemon.queue, &done_tx)?;
        lanes.watch(&session, &s.name, lane).await?;
    }
    drop(done_tx);
    let served = serve(&settings.metrics, &lanes.shared_all, &mut done_rx).await?;
    drain(session, done_rx, lanes, served).await
}

/// Creates the state directory (`daemon.state_dir`) and opens the Zenoh session.
async fn configure(settings: &Settings) -> Result<zenoh::Session> {
    let d = &settings.daemon;
    if d.state_dir.as_os_str().is_empty() {
        bail!(
            "configuration key daemon.state_dir: not set, and neither XDG_STATE_HOME nor HOME is set to put the default under"
        );
    }
    std::fs::create_dir_all(&d.state_dir).with_context(|| {
        format!(
            "configuration key daemon.state_dir: cannot create {}",
            d.state_dir.display()
        )
    })?;
    let session = zenoh::open(session_config(&settings.zenoh)?)
        .await
        .map_err(zerr("cannot open the Zenoh session"))?;
    tracing::info!(zid = %session.zid(), "Zenoh session open");
    Ok(session)
}

/// One structure as [`recover`] leaves it, before its tracking thread starts.
struct Recovered {
    worker: Worker,
    /// Where the thread handles the logged sets again from (the checkpoint's position).
    resume_from: Option<WalPosition>,
    shared: Arc<Shared>,
}

/// One structure's way in: its tracking queue and its shared status.
struct Lane {
    tx: SyncSender<Input>,
    shared: Arc<Shared>,
}

/// Every structure's part of the running daemon, kept until [`drain`]. The fields drop in
/// the order written (on an early return): the order the daemon has always dropped them in.
#[derive(Default)]
struct Lanes {
    shared_all: Vec<Arc<Shared>>,
    queryables: Vec<Queryable<()>>,
    subscribers: Vec<AdvancedSubscriber<()>>,
    threads: Vec<std::thread::JoinHandle<()>>,
    queues: Vec<SyncSender<Input>>,
}

/// Recovers one structure from its state: the model, the tracker (from the checkpoint, or
/// afresh), the rolling log (which is also the write-ahead log) and the worker over them.
fn recover(
    settings: &Settings,
    s: &StructureSettings,
    session: &zenoh::Session,
) -> Result<Recovered> {
    let d = &settings.daemon;
    let structure_model = Arc::new(load_structure(s)?);
    let model = structure_model.1.clone();
    let ckpt = d.state_dir.join(format!("{}.checkpoint.json", s.name));
    let (mut tracker, resume_from) = restore(settings, s, model, &ckpt)?;
    crate::io::model::adopt_law(&mut tracker)?;
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
    let worker = Worker::new(
        structure_model,
        tracker,
        LiveSink::start(session.clone(), log, shared.clone())?,
        ckpt,
        Duration::from_secs_f64(d.checkpoint_every_s),
        CrosscheckLane {
            cfg: settings.crosscheck.clone(),
            budget: Some(MemoryBudget::from_mib(d.memory_mib)),
        },
        settings.identify.clone(),
    )?;
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

impl Lanes {
    /// Starts the tracking thread of `structure`: it handles again the sets logged after
    /// the checkpoint, then tracks what comes through the returned lane's queue.
    fn start(
        &mut self,
        structure: &str,
        recovered: Recovered,
        queue: usize,
        done: &DoneTx,
    ) -> Result<Lane> {
        let Recovered {
            mut worker,
            resume_from,
            shared,
        } = recovered;
        let (tx, rx) = mpsc::sync_channel::<Input>(queue);
        let done = done.clone();
        let name = structure.to_string();
        self.threads.push(
            std::thread::Builder::new()
                .name(format!("track-{name}"))
                .spawn(move || {
                    crate::core::sequential_numerics();
                    // A panic outside the per-set guards (in the resume, a checkpoint, the
                    // log) must not leave the process up with this structure dark.
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
                    let _ = done.send((name, r));
                })?,
        );
        Ok(Lane { tx, shared })
    }

    /// Declares the subscribers of `structure` (modal sets, raw data, environment
    /// readings, all into `lane`'s queue) and its status queryable, and keeps the lane.
    async fn watch(&mut self, session: &zenoh::Session, structure: &str, lane: Lane) -> Result<()> {
        let modal = subscribe_modal(session, structure, &lane).await?;
        self.subscribers.push(modal);
        let accel = subscribe_accel(session, structure, &lane).await?;
        self.subscribers.push(accel);
        let environment = subscribe_environment(session, structure, &lane).await?;
        self.subscribers.push(environment);
        let status = declare_status(session, structure, &lane.shared).await?;
        self.queryables.push(status);
        self.queues.push(lane.tx);
        self.shared_all.push(lane.shared);
        tracing::info!(
            structure,
            "watching {} (status on {})",
            topic(structure, "modal"),
            topic(structure, "status")
        );
        Ok(())
    }
}

/// The subscriber to the modal sets of `structure`, through a [`contact::Gate`], with a
/// listener that reports the sets lost in transport.
async fn subscribe_modal(
    session: &zenoh::Session,
    structure: &str,
    lane: &Lane,
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
    lane: &Lane,
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
    lane: &Lane,
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

/// The queryable that answers `boltwatch/<structure>/status` from the shared status.
async fn declare_status(
    session: &zenoh::Session,
    structure: &str,
    shared: &Arc<Shared>,
) -> Result<Queryable<()>> {
    let q_shared = shared.clone();
    session
        .declare_queryable(topic(structure, "status"))
        .callback(move |query| {
            let body = to_wire(&q_shared.status_reply());
            if let Err(e) = query.reply(query.key_expr().clone(), body).wait() {
                tracing::warn!("cannot answer a status query: {e}");
            }
        })
        .await
        .map_err(zerr(format!(
            "cannot declare {}",
            topic(structure, "status")
        )))
}

/// How serving ended, and what [`drain`] stops. The fields drop in the order written (on
/// an early return): the order the daemon has always dropped them in.
struct Served {
    /// The first tracking thread that failed, if one did.
    failure: Option<anyhow::Error>,
    watchdog: Option<JoinHandle<()>>,
    /// The SIGTERM stream, no longer polled but held until the daemon stops.
    _sigterm: tokio::signal::unix::Signal,
    metrics_task: Option<JoinHandle<()>>,
}

/// Serves until SIGTERM, SIGINT or the end of a tracking thread: starts the metrics
/// endpoint, tells systemd the daemon is ready and feeds its watchdog.
async fn serve(
    metrics_settings: &MetricsSettings,
    shared_all: &[Arc<Shared>],
    done_rx: &mut DoneRx,
) -> Result<Served> {
    let metrics_task = serve_metrics(metrics_settings, shared_all).await?;
    let mut sigterm = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())
        .context("cannot install the SIGTERM handler")?;
    // systemd (Type=notify): ready once every structure is watched.
    if let Err(e) = sd_notify::notify(&[sd_notify::NotifyState::Ready]) {
        tracing::warn!("cannot notify systemd of readiness: {e}");
    }
    let watchdog = spawn_watchdog(shared_all);
    let mut failure = None;
    tokio::select! {
        _ = sigterm.recv() => tracing::info!("SIGTERM: shutting down"),
        _ = tokio::signal::ctrl_c() => tracing::info!("SIGINT: shutting down"),
        Some((name, r)) = done_rx.recv() => {
            let e = r.err().unwrap_or_else(|| anyhow!("stopped unexpectedly"));
            tracing::error!(structure = name, "tracking thread failed: {e:#}");
            failure = Some(e.context(format!("tracking of {name}")));
        }
    }
    Ok(Served {
        failure,
        watchdog,
        _sigterm: sigterm,
        metrics_task,
    })
}

/// The Prometheus endpoint on `metrics.listen` for every structure, if one is configured.
async fn serve_metrics(
    metrics_settings: &MetricsSettings,
    shared_all: &[Arc<Shared>],
) -> Result<Option<JoinHandle<()>>> {
    if metrics_settings.listen.is_empty() {
        return Ok(None);
    }
    let listener = tokio::net::TcpListener::bind(&metrics_settings.listen)
        .await
        .with_context(|| {
            format!(
                "configuration key metrics.listen: cannot listen on {}",
                metrics_settings.listen
            )
        })?;
    tracing::info!("metrics on http://{}/metrics", metrics_settings.listen);
    Ok(Some(tokio::spawn(metrics::serve(
        listener,
        shared_all.to_vec(),
    ))))
}

/// With systemd's WatchdogSec, a ping every half period, but only while every tracking
/// loop has gone round within that half period, so a hung tracker gets the process
/// restarted.
fn spawn_watchdog(shared_all: &[Arc<Shared>]) -> Option<JoinHandle<()>> {
    sd_notify::watchdog_enabled().map(|period| {
        let shared = shared_all.to_vec();
        tokio::spawn(async move {
            let half = period / 2;
            let mut tick = tokio::time::interval(half);
            loop {
                tick.tick().await;
                match shared.iter().find(|s| s.since_beat() > half) {
                    None => {
                        if let Err(e) = sd_notify::notify(&[sd_notify::NotifyState::Watchdog]) {
                            tracing::warn!("cannot ping the systemd watchdog: {e}");
                        }
                    }
                    Some(s) => tracing::error!(
                        structure = s.structure,
                        "tracking loop silent for {:.1} s: not pinging the watchdog",
                        s.since_beat().as_secs_f64()
                    ),
                }
            }
        })
    })
}

/// Drains: undeclares the subscribers (no new sets from here on), lets every tracking
/// thread process what is queued, checkpoint and close its log, then stops the metrics
/// endpoint and the queryables and closes the session. Fails with the first tracking
/// failure, if there was one.
async fn drain(
    session: zenoh::Session,
    mut done_rx: DoneRx,
    lanes: Lanes,
    served: Served,
) -> Result<()> {
    let mut failure = served.failure;
    let _ = sd_notify::notify(&[sd_notify::NotifyState::Stopping]);
    if let Some(w) = served.watchdog {
        w.abort();
    }
    // No new sets from here on; everything queued is still processed.
    for sub in lanes.subscribers {
        sub.undeclare()
            .await
            .map_err(zerr("cannot undeclare a subscriber"))?;
    }
    let (queues, threads) = (lanes.queues, lanes.threads);
    let joined = tokio::task::spawn_blocking(move || {
        for tx in &queues {
            let _ = tx.send(Input::Shutdown);
        }
        drop(queues);
        for t in threads {
            let _ = t.join();
        }
    });
    joined.await.map_err(|e| anyhow!("shutdown: {e}"))?;
    while let Ok((name, r)) = done_rx.try_recv() {
        if let Err(e) = r {
            tracing::error!(structure = name, "tracking thread failed: {e:#}");
            failure.get_or_insert(e.context(format!("tracking of {name}")));
        }
    }
    if let Some(t) = served.metrics_task {
        t.abort();
    }
    drop(lanes.queryables);
    session
        .close()
        .await
        .map_err(zerr("cannot close the Zenoh session"))?;
    match failure {
        Some(e) => Err(e),
        None => {
            tracing::info!("stopped");
            Ok(())
        }
    }
}
