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
pub mod log;
pub mod metrics;
pub mod worker;

use std::sync::mpsc;
use std::time::Duration;

use std::sync::atomic::Ordering;

use anyhow::{Context, Result, anyhow, bail};
use zenoh::Wait;
use zenoh_ext::{AdvancedSubscriberBuilderExt, HistoryConfig, RecoveryConfig};

use crate::contract::{Checkpoint, to_wire};
use crate::io::checkpoint;
use crate::io::driver::{CrosscheckLane, MemoryBudget};
use crate::io::mcap::topic;
use crate::io::model::load_structure;
use crate::io::zenoh::{session_config, zerr};
use crate::pipeline::{Tracker, TrackerState};
use crate::settings::Settings;
use metrics::Shared;
use worker::{Input, LiveSink, Worker};

/// Runs the daemon until SIGINT or SIGTERM (or a tracking thread fails).
pub async fn run(settings: Settings) -> Result<()> {
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

    let (done_tx, mut done_rx) = tokio::sync::mpsc::unbounded_channel::<(String, Result<()>)>();
    let mut queues = Vec::new();
    let mut threads = Vec::new();
    let mut subscribers = Vec::new();
    let mut queryables = Vec::new();
    let mut shared_all = Vec::new();
    for s in &settings.structures {
        let structure_model = std::sync::Arc::new(load_structure(s)?);
        let model = structure_model.1.clone();
        let ckpt = d.state_dir.join(format!("{}.checkpoint.json", s.name));
        let mut resume_from = None;
        let mut tracker = match checkpoint::read::<Checkpoint<TrackerState>>(&ckpt)
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
                let t =
                    Tracker::restore(model, settings.tracker.clone(), v).with_context(|| {
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
        let mut worker = Worker::new(
            structure_model,
            tracker,
            LiveSink {
                session: session.clone(),
                log,
                shared: shared.clone(),
            },
            ckpt,
            Duration::from_secs_f64(d.checkpoint_every_s),
            CrosscheckLane {
                cfg: settings.crosscheck.clone(),
                budget: Some(MemoryBudget::from_mib(d.memory_mib)),
            },
            settings.identify.clone(),
        )?;
        let (tx, rx) = mpsc::sync_channel::<Input>(d.queue);
        let done = done_tx.clone();
        let name = s.name.clone();
        threads.push(
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
        let gate = contact::Gate::new(
            session.clone(),
            zenoh::key_expr::KeyExpr::try_from(topic(&s.name, "modal"))
                .map_err(zerr(format!("structure {}: modal key", s.name)))?,
            tx.clone(),
            shared.clone(),
        );
        // zenoh-ext's advanced subscriber: on start it asks every sensor's advanced
        // publisher for its cache (history, and for publishers that appear later), and it
        // detects sets missed in transport by their sequence numbers and fetches them again
        // (recovery, triggered by the publishers' heartbeats). Sets published while the
        // daemon was down are recovered this way; those it had handled are recognised by the
        // tracker and skipped. zenoh-ext can lose the history of a publisher it meets late
        // (see [`contact`]): the gate fetches it again.
        let sub = session
            .declare_subscriber(topic(&s.name, "modal"))
            .history(HistoryConfig::default().detect_late_publishers())
            .recovery(RecoveryConfig::default().heartbeat())
            .subscriber_detection()
            .callback(move |sample| gate.offer(&sample))
            .await
            .map_err(zerr(format!(
                "cannot subscribe to {}",
                topic(&s.name, "modal")
            )))?;
        // Sets a publisher's cache no longer held: lost, so reported (on `rejected`).
        let miss_shared = shared.clone();
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
        subscribers.push(sub);
        // Raw data: blocks in stream order into the same queue, identified by the worker
        // window by window. Recovery fetches blocks missed in transport from the sensor's
        // publisher cache; no history (old blocks would be out of stream order).
        let accel_tx = tx.clone();
        let accel_shared = shared.clone();
        let accel_sub = session
            .declare_subscriber(topic(&s.name, "accel"))
            .recovery(RecoveryConfig::default().heartbeat())
            .callback(move |sample| {
                worker::enqueue_accel(&accel_tx, &accel_shared, sample.payload())
            })
            .await
            .map_err(zerr(format!(
                "cannot subscribe to {}",
                topic(&s.name, "accel")
            )))?;
        subscribers.push(accel_sub);
        // Environment readings, for sites whose thermometer is not in the OMA box: into the
        // same queue (and the write-ahead log), so they are joined in arrival order.
        let env_tx = tx.clone();
        let env_shared = shared.clone();
        let env_sub = session
            .declare_subscriber(topic(&s.name, "environment"))
            .history(HistoryConfig::default().detect_late_publishers())
            .recovery(RecoveryConfig::default().heartbeat())
            .callback(move |sample| {
                worker::enqueue_environment(&env_tx, &env_shared, sample.payload())
            })
            .await
            .map_err(zerr(format!(
                "cannot subscribe to {}",
                topic(&s.name, "environment")
            )))?;
        subscribers.push(env_sub);
        let q_shared = shared.clone();
        queryables.push(
            session
                .declare_queryable(topic(&s.name, "status"))
                .callback(move |query| {
                    let body = to_wire(&q_shared.status_reply());
                    if let Err(e) = query.reply(query.key_expr().clone(), body).wait() {
                        tracing::warn!("cannot answer a status query: {e}");
                    }
                })
                .await
                .map_err(zerr(format!("cannot declare {}", topic(&s.name, "status"))))?,
        );
        queues.push(tx);
        shared_all.push(shared);
        tracing::info!(
            structure = s.name,
            "watching {} (status on {})",
            topic(&s.name, "modal"),
            topic(&s.name, "status")
        );
    }
    drop(done_tx);

    let metrics_task = if settings.metrics.listen.is_empty() {
        None
    } else {
        let listener = tokio::net::TcpListener::bind(&settings.metrics.listen)
            .await
            .with_context(|| {
                format!(
                    "configuration key metrics.listen: cannot listen on {}",
                    settings.metrics.listen
                )
            })?;
        tracing::info!("metrics on http://{}/metrics", settings.metrics.listen);
        Some(tokio::spawn(metrics::serve(listener, shared_all.clone())))
    };

    let mut sigterm = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())
        .context("cannot install the SIGTERM handler")?;
    // systemd (Type=notify): ready once every structure is watched; with WatchdogSec, a
    // ping every half period, but only while every tracking loop has gone round within
    // that half period, so a hung tracker gets the process restarted.
    if let Err(e) = sd_notify::notify(&[sd_notify::NotifyState::Ready]) {
        tracing::warn!("cannot notify systemd of readiness: {e}");
    }
    let watchdog = sd_notify::watchdog_enabled().map(|period| {
        let shared = shared_all.clone();
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
    });
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

    let _ = sd_notify::notify(&[sd_notify::NotifyState::Stopping]);
    if let Some(w) = watchdog {
        w.abort();
    }
    // No new sets from here on; everything queued is still processed.
    for sub in subscribers {
        sub.undeclare()
            .await
            .map_err(zerr("cannot undeclare a subscriber"))?;
    }
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
    if let Some(t) = metrics_task {
        t.abort();
    }
    drop(queryables);
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
