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

pub mod advice;
pub mod console;
pub mod contact;
pub mod fleet;
pub mod history;
pub mod lane;
pub mod log;
pub mod metrics;
pub mod worker;

use std::sync::Arc;

use anyhow::{Context, Result, anyhow, bail};
use tokio::task::JoinHandle;

use crate::io::zenoh::{session_config, zerr};
use crate::settings::{MetricsSettings, Settings};
use lane::{Lane, LaneState};
use metrics::Watched;

/// How a tracking thread ended: its structure and its result.
type Done = (String, Result<()>);
/// Where the tracking threads send how they ended, and where the daemon hears it.
pub type DoneTx = tokio::sync::mpsc::UnboundedSender<Done>;
type DoneRx = tokio::sync::mpsc::UnboundedReceiver<Done>;

/// Runs the daemon until SIGINT or SIGTERM (or a tracking thread fails).
pub async fn run(settings: Settings) -> Result<()> {
    let session = configure(&settings).await?;
    let (done_tx, mut done_rx) = tokio::sync::mpsc::unbounded_channel::<Done>();
    let watched = Watched::default();
    if settings.fleet.enabled() {
        let fleet = fleet::Fleet::start(
            Arc::new(settings.clone()),
            session.clone(),
            watched.clone(),
            done_tx,
        )
        .await?;
        let served = serve(&settings, &watched, &mut done_rx).await?;
        let closed = fleet.stop().await;
        return drain(session, done_rx, closed, served).await;
    }
    let mut lanes = Vec::new();
    for s in &settings.structures {
        let lane = Lane::open(&settings, s, &session, LaneState::Local, &done_tx).await?;
        watch(&watched, &lane);
        lanes.push(lane);
    }
    drop(done_tx);
    let served = serve(&settings, &watched, &mut done_rx).await?;
    let closed = close_all(lanes).await;
    drain(session, done_rx, closed, served).await
}

/// Adds a lane's status to what the metrics and the watchdog see.
pub fn watch(watched: &Watched, lane: &Lane) {
    if let Ok(mut v) = watched.write() {
        v.push(lane.shared.clone());
    }
}

/// Removes a lane's status from what the metrics and the watchdog see.
pub fn unwatch(watched: &Watched, structure: &str) {
    if let Ok(mut v) = watched.write() {
        v.retain(|s| s.structure != structure);
    }
}

/// Closes every lane: first no new sets anywhere, then every queue handled, every state
/// written and every log closed.
pub async fn close_all(mut lanes: Vec<Lane>) -> Result<()> {
    for lane in &mut lanes {
        lane.stop_intake().await?;
    }
    for lane in &lanes {
        lane.signal_shutdown().await;
    }
    // Every lane joined, whatever an earlier one returned; the first failure reported.
    let mut first = Ok(());
    for lane in lanes {
        let r = lane.join().await;
        if first.is_ok() {
            first = r;
        }
    }
    first
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
    let mut config = session_config(&settings.zenoh)?;
    if settings.daemon.state == crate::settings::StateStore::Zenoh {
        // The storages order a structure's state by the writer's timestamps (deletes
        // included: a router stamps puts only).
        config
            .insert_json5("timestamping/enabled", "true")
            .map_err(zerr("Zenoh configuration timestamping"))?;
    }
    let session = zenoh::open(config)
        .await
        .map_err(zerr("cannot open the Zenoh session"))?;
    tracing::info!(zid = %session.zid(), "Zenoh session open");
    Ok(session)
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
    console_task: Option<JoinHandle<()>>,
}

/// Serves until SIGTERM, SIGINT or the end of a tracking thread: starts the metrics
/// endpoint, tells systemd the daemon is ready and feeds its watchdog.
async fn serve(settings: &Settings, watched: &Watched, done_rx: &mut DoneRx) -> Result<Served> {
    let metrics_task = serve_metrics(&settings.metrics, watched).await?;
    let console_task = serve_console(settings, watched).await?;
    let mut sigterm = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())
        .context("cannot install the SIGTERM handler")?;
    // systemd (Type=notify): ready once every structure is watched.
    if let Err(e) = sd_notify::notify(&[sd_notify::NotifyState::Ready]) {
        tracing::warn!("cannot notify systemd of readiness: {e}");
    }
    let watchdog = spawn_watchdog(watched);
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
        console_task,
    })
}

/// The operator's console on `console.listen`, if one is configured.
async fn serve_console(settings: &Settings, watched: &Watched) -> Result<Option<JoinHandle<()>>> {
    let c = &settings.console;
    let Some(listener) = bind_listener("console.listen", &c.listen).await? else {
        return Ok(None);
    };
    let access = console::Access::of(c)?;
    tracing::info!("console on {}://{}/", access.scheme(), c.listen);
    let loopback = listener.local_addr().is_ok_and(|a| a.ip().is_loopback());
    if !loopback && c.users_file.as_os_str().is_empty() {
        tracing::warn!(
            "the console on {} is open to anyone who reaches it: set console.users_file, or \
             put it behind a reverse proxy with authentication",
            c.listen
        );
    }
    let log_dir = settings.daemon.state_dir.join("log");
    let console = console::Console::new(c, watched.clone(), log_dir);
    Ok(Some(tokio::spawn(console::serve(
        listener, console, access,
    ))))
}

/// The Prometheus endpoint on `metrics.listen` for every structure, if one is configured.
async fn serve_metrics(
    metrics_settings: &MetricsSettings,
    watched: &Watched,
) -> Result<Option<JoinHandle<()>>> {
    let Some(listener) = bind_listener("metrics.listen", &metrics_settings.listen).await? else {
        return Ok(None);
    };
    tracing::info!("metrics on http://{}/metrics", metrics_settings.listen);
    Ok(Some(tokio::spawn(metrics::serve(
        listener,
        watched.clone(),
    ))))
}

/// A listener on the address of configuration key `key` (`None` when it is empty: off).
async fn bind_listener(key: &str, listen: &str) -> Result<Option<tokio::net::TcpListener>> {
    if listen.is_empty() {
        return Ok(None);
    }
    let listener = tokio::net::TcpListener::bind(listen)
        .await
        .with_context(|| format!("configuration key {key}: cannot listen on {listen}"))?;
    Ok(Some(listener))
}

/// With systemd's WatchdogSec, a ping every half period, but only while every tracking
/// loop has gone round within that half period, so a hung tracker gets the process
/// restarted.
fn spawn_watchdog(watched: &Watched) -> Option<JoinHandle<()>> {
    sd_notify::watchdog_enabled().map(|period| {
        let watched = watched.clone();
        tokio::spawn(async move {
            let half = period / 2;
            let mut tick = tokio::time::interval(half);
            loop {
                tick.tick().await;
                let shared = watched.read().map(|v| v.clone()).unwrap_or_default();
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

/// Drains once the lanes are closed (`closed`: how that went): stops the metrics endpoint
/// and the watchdog, closes the session. Fails with the first tracking failure, if there
/// was one.
async fn drain(
    session: zenoh::Session,
    mut done_rx: DoneRx,
    closed: Result<()>,
    served: Served,
) -> Result<()> {
    let mut failure = served.failure;
    let _ = sd_notify::notify(&[sd_notify::NotifyState::Stopping]);
    if let Some(w) = served.watchdog {
        w.abort();
    }
    closed?;
    while let Ok((name, r)) = done_rx.try_recv() {
        if let Err(e) = r {
            tracing::error!(structure = name, "tracking thread failed: {e:#}");
            failure.get_or_insert(e.context(format!("tracking of {name}")));
        }
    }
    for t in [served.metrics_task, served.console_task]
        .into_iter()
        .flatten()
    {
        t.abort();
    }
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
