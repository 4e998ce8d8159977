//! `boltwatch publish REC.mcap [--rate R]`: publishes a recording's modal sets over Zenoh,
//! in log-time order, as a field simulator for demos and tests, the way a sensor pipeline
//! should: through zenoh-ext's advanced publisher, with a cache of every set it publishes,
//! sequence numbers and heartbeats, so a daemon that restarts part-way recovers the sets it
//! missed. It waits, after the last set, until the daemon has taken them all.

use std::collections::{BTreeMap, BTreeSet};
use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};

use zenoh_ext::{AdvancedPublisher, AdvancedPublisherBuilderExt, CacheConfig, MissDetectionConfig};

use crate::contract::Status;
use crate::io::mcap::{RecordedMessage, read_all};
use crate::io::zenoh::zerr;

#[derive(Debug, clap::Args)]
pub struct PublishArgs {
    /// Recording with `boltwatch/<structure>/modal` messages.
    pub recording: PathBuf,
    /// Modal sets per second (0: as fast as the network takes them; publication blocks
    /// rather than drops when the link is congested).
    #[arg(long, default_value_t = 10.0)]
    pub rate: f64,
    /// Endpoint of the daemon (or of a router) to connect to.
    #[arg(long, default_value = "tcp/127.0.0.1:7447")]
    pub connect: String,
    /// A Zenoh JSON5 configuration (TLS, credentials); replaces --connect.
    #[arg(long)]
    pub zenoh_config: Option<PathBuf>,
    /// Skip this many sets first.
    #[arg(long, default_value_t = 0)]
    pub skip: usize,
    /// Publish at most this many sets.
    #[arg(long)]
    pub count: Option<usize>,
    /// Seconds to wait for a subscriber on each structure's key before publishing (0: do
    /// not wait), and, after the last set, for the daemon to report it has taken them all.
    #[arg(long, default_value_t = 10.0)]
    pub wait: f64,
}

/// Heartbeat period of the advanced publisher: how soon a subscriber learns it missed the
/// last sets.
const HEARTBEAT: Duration = Duration::from_millis(500);

/// Publishes the recording's modal sets (and the readings beside them) and waits until the
/// daemons have taken them.
pub fn run(args: &PublishArgs) -> Result<()> {
    if !(args.rate.is_finite() && args.rate >= 0.0) {
        bail!("--rate {}: must be a finite number >= 0", args.rate);
    }
    let sets = sets_to_publish(args)?;
    let cfg = client_config(args)?;
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .context("cannot start the async runtime")?;
    rt.block_on(publish(args, cfg, sets))
}

/// The recording's modal sets in log-time order, after `--skip` and within `--count`, with
/// the environment readings logged beside them ([`with_readings`]).
fn sets_to_publish(args: &PublishArgs) -> Result<Vec<RecordedMessage>> {
    let mut sets: Vec<_> = read_all(&args.recording)?
        .into_iter()
        .filter(|m| m.topic.starts_with("boltwatch/") && m.topic.ends_with("/modal"))
        .collect();
    sets.sort_by_key(|m| m.log_time);
    if sets.is_empty() {
        bail!(
            "recording {} has no boltwatch/<structure>/modal messages",
            args.recording.display()
        );
    }
    let sets: Vec<_> = sets
        .into_iter()
        .skip(args.skip)
        .take(args.count.unwrap_or(usize::MAX))
        .collect();
    with_readings(&args.recording, sets)
}

/// The Zenoh configuration: `--zenoh-config`, or a peer connecting to `--connect`; either
/// way without multicast scouting, and reconnecting quickly to a restarted daemon.
fn client_config(args: &PublishArgs) -> Result<zenoh::Config> {
    let mut cfg = match &args.zenoh_config {
        Some(f) => {
            zenoh::Config::from_file(f).map_err(zerr(format!("--zenoh-config {}", f.display())))?
        }
        None => {
            let mut c = zenoh::Config::default();
            c.insert_json5("mode", "\"peer\"").map_err(zerr("mode"))?;
            c.insert_json5(
                "connect/endpoints",
                &serde_json::to_string(&[&args.connect])?,
            )
            .map_err(zerr(format!("--connect {}", args.connect)))?;
            c
        }
    };
    cfg.insert_json5("scouting/multicast/enabled", "false")
        .map_err(zerr("scouting"))?;
    // Reconnect to a restarted daemon within 100 to 500 ms (Zenoh's default: 1 to 4 s).
    cfg.insert_json5(
        "connect/retry",
        "{period_init_ms: 100, period_max_ms: 500, period_increase_factor: 2}",
    )
    .map_err(zerr("connect/retry"))?;
    Ok(cfg)
}

/// Opens the session, publishes `sets` on their topics, waits for the daemons to confirm
/// they took them, closes the session and prints what was published.
async fn publish(args: &PublishArgs, cfg: zenoh::Config, sets: Vec<RecordedMessage>) -> Result<()> {
    let session = zenoh::open(cfg)
        .await
        .map_err(zerr("cannot open the Zenoh session"))?;
    let topics: BTreeSet<String> = sets.iter().map(|m| m.topic.clone()).collect();
    let publishers = declare_publishers(&session, &topics, &sets, args).await?;
    let start = Instant::now();
    let k = publish_sets(&publishers, &sets, args.rate, start).await?;
    let secs = start.elapsed().as_secs_f64();
    confirm_taken(&session, &topics, &sets, args.wait).await;
    session
        .close()
        .await
        .map_err(zerr("cannot close the Zenoh session"))?;
    println!(
        "published {} modal sets ({} inputs) of {} on {} ({secs:.1} s, {:.0} sets/s)",
        k,
        sets.len(),
        args.recording.display(),
        topics.into_iter().collect::<Vec<_>>().join(", "),
        k as f64 / secs.max(1e-9)
    );
    Ok(())
}

/// An advanced publisher on each topic, with a cache of all its sets, sequence numbers and
/// heartbeats; with `--wait`, declared once a subscriber matches it.
async fn declare_publishers(
    session: &zenoh::Session,
    topics: &BTreeSet<String>,
    sets: &[RecordedMessage],
    args: &PublishArgs,
) -> Result<BTreeMap<String, AdvancedPublisher<'static>>> {
    let mut publishers = BTreeMap::new();
    for t in topics {
        let cached = sets.iter().filter(|m| &m.topic == t).count();
        let p = session
            .declare_publisher(t.clone())
            .congestion_control(zenoh::qos::CongestionControl::Block)
            .priority(zenoh::qos::Priority::Data)
            .cache(CacheConfig::default().max_samples(cached.max(1)))
            .sample_miss_detection(MissDetectionConfig::default().heartbeat(HEARTBEAT))
            .publisher_detection()
            .await
            .map_err(zerr(format!("cannot declare a publisher on {t}")))?;
        if args.wait > 0.0 {
            wait_for_subscriber(&p, t, args).await?;
        }
        publishers.insert(t.clone(), p);
    }
    Ok(publishers)
}

/// Waits up to `--wait` seconds for a subscriber to match `p`, the publisher on `t`.
async fn wait_for_subscriber(p: &AdvancedPublisher<'_>, t: &str, args: &PublishArgs) -> Result<()> {
    let deadline = Instant::now() + Duration::from_secs_f64(args.wait);
    loop {
        let matched = p
            .matching_status()
            .await
            .map_err(zerr("matching status"))?
            .matching();
        if matched {
            return Ok(());
        }
        if Instant::now() >= deadline {
            let how = match &args.zenoh_config {
                Some(f) => format!("with the Zenoh configuration {}", f.display()),
                None => format!("at {}", args.connect),
            };
            bail!(
                "no subscriber on {t} after {} s (is `boltwatch run` up and reachable {how}, and may this client publish there?)",
                args.wait
            );
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// Puts each message on its topic in order, the modal sets `rate` a second from `start`
/// (0: as fast as the network takes them); returns how many modal sets were put.
async fn publish_sets(
    publishers: &BTreeMap<String, AdvancedPublisher<'_>>,
    sets: &[RecordedMessage],
    rate: f64,
    start: Instant,
) -> Result<usize> {
    let mut k = 0;
    for m in sets {
        let modal = m.topic.ends_with("/modal");
        if rate > 0.0 && modal {
            let due = start + Duration::from_secs_f64(k as f64 / rate);
            tokio::time::sleep_until(due.into()).await;
        }
        k += usize::from(modal);
        publishers[&m.topic]
            .put(m.data.clone())
            .await
            .map_err(zerr(format!("cannot publish on {}", m.topic)))?;
    }
    Ok(k)
}

/// Waits until each structure's daemon reports (status query) the time of its last set as
/// accepted, and warns about those that did not: closing the session drops the cache a
/// restarted daemon would recover from, and what the transport has not sent yet.
async fn confirm_taken(
    session: &zenoh::Session,
    topics: &BTreeSet<String>,
    sets: &[RecordedMessage],
    wait: f64,
) {
    let mut unconfirmed = Vec::new();
    for t in topics.iter().filter(|t| t.ends_with("/modal")) {
        let last = sets
            .iter()
            .filter(|m| &m.topic == t)
            .filter_map(|m| set_time(&m.data))
            .max();
        let status = t.trim_end_matches("/modal").to_string() + "/status";
        if !taken(session, &status, last, wait.max(1.0)).await {
            unconfirmed.push(status);
        }
    }
    if !unconfirmed.is_empty() {
        eprintln!(
            "warning: not confirmed that every set was taken (no daemon reported the last set's time on {} within {} s: not up, or the last set was rejected)",
            unconfirmed.join(", "),
            wait.max(1.0)
        );
    }
}

/// `sets` with the recording's environment readings (`boltwatch/<structure>/environment`)
/// logged from a day before the first of them to the last, in log-time order: a site's
/// thermometer published beside its sets.
fn with_readings(
    path: &std::path::Path,
    sets: Vec<RecordedMessage>,
) -> Result<Vec<RecordedMessage>> {
    let (Some(first), Some(last)) = (sets.first(), sets.last()) else {
        return Ok(sets);
    };
    let (from, to) = (
        first.log_time.saturating_sub(86_400_000_000_000),
        last.log_time,
    );
    let mut all: Vec<_> = read_all(path)?
        .into_iter()
        .filter(|m| {
            m.topic.starts_with("boltwatch/")
                && m.topic.ends_with("/environment")
                && (from..=to).contains(&m.log_time)
        })
        .chain(sets)
        .collect();
    all.sort_by_key(|m| m.log_time);
    Ok(all)
}

/// The `time` of a modal-set payload, to the millisecond (as status replies give it).
fn set_time(payload: &[u8]) -> Option<chrono::DateTime<chrono::Utc>> {
    let v: serde_json::Value = serde_json::from_slice(payload).ok()?;
    let t = chrono::DateTime::parse_from_rfc3339(v.get("time")?.as_str()?).ok()?;
    let ms = t.timestamp_millis();
    chrono::DateTime::from_timestamp_millis(ms)
}

/// Whether, within `timeout_s`, a status reply on `key` gives a last accepted set time at
/// or after `last` (any reply when `last` is unknown).
async fn taken(
    session: &zenoh::Session,
    key: &str,
    last: Option<chrono::DateTime<chrono::Utc>>,
    timeout_s: f64,
) -> bool {
    let deadline = Instant::now() + Duration::from_secs_f64(timeout_s);
    while Instant::now() < deadline {
        let replies = session
            .get(key)
            .priority(zenoh::qos::Priority::Data)
            .congestion_control(zenoh::qos::CongestionControl::Block)
            .timeout(Duration::from_secs(1))
            .await;
        if let Ok(replies) = replies {
            while let Ok(r) = replies.recv_async().await {
                let Ok(sample) = r.result() else { continue };
                let Ok(st) = serde_json::from_slice::<Status>(&sample.payload().to_bytes()) else {
                    continue;
                };
                let at = st
                    .last_set_time
                    .as_deref()
                    .and_then(|t| chrono::DateTime::parse_from_rfc3339(t).ok());
                match (last, at) {
                    (None, _) => return true,
                    (Some(l), Some(a)) if a >= l => return true,
                    _ => {}
                }
            }
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    false
}
