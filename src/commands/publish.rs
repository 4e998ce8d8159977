//! `boltwatch publish REC.mcap [--rate R]`: publishes a recording's modal sets over Zenoh,
//! in log-time order, as a field simulator for demos and tests.

use std::collections::BTreeSet;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};

use crate::io::mcap::read_all;
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
    /// not wait).
    #[arg(long, default_value_t = 10.0)]
    pub wait: f64,
}

pub fn run(args: &PublishArgs) -> Result<()> {
    if !(args.rate.is_finite() && args.rate >= 0.0) {
        bail!("--rate {}: must be a finite number >= 0", args.rate);
    }
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
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .context("cannot start the async runtime")?;
    rt.block_on(async move {
        let session = zenoh::open(cfg)
            .await
            .map_err(zerr("cannot open the Zenoh session"))?;
        let topics: BTreeSet<String> = sets.iter().map(|m| m.topic.clone()).collect();
        let mut publishers = std::collections::BTreeMap::new();
        for t in &topics {
            let p = session
                .declare_publisher(t.clone())
                .congestion_control(zenoh::qos::CongestionControl::Block)
                .priority(zenoh::qos::Priority::Data)
                .await
                .map_err(zerr(format!("cannot declare a publisher on {t}")))?;
            if args.wait > 0.0 {
                let deadline = Instant::now() + Duration::from_secs_f64(args.wait);
                loop {
                    let matched = p
                        .matching_status()
                        .await
                        .map_err(zerr("matching status"))?
                        .matching();
                    if matched {
                        break;
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
            publishers.insert(t.clone(), p);
        }
        let start = Instant::now();
        for (k, m) in sets.iter().enumerate() {
            if args.rate > 0.0 {
                let due = start + Duration::from_secs_f64(k as f64 / args.rate);
                tokio::time::sleep_until(due.into()).await;
            }
            publishers[&m.topic]
                .put(m.data.clone())
                .await
                .map_err(zerr(format!("cannot publish on {}", m.topic)))?;
        }
        let secs = start.elapsed().as_secs_f64();
        // Closing the session discards what its transport has not sent yet (a CI run
        // through a TLS router on a loaded machine saw 4 of 20 sets arrive after a 200 ms
        // pause, 1 s later). So wait for delivery: a query to each structure's status,
        // behind the sets on the same links and at the same priority (Data, FIFO per link
        // and per router hop), is answered by the daemon only after it has received them.
        let mut unconfirmed = Vec::new();
        for t in &topics {
            let status = t.trim_end_matches("/modal").to_string() + "/status";
            if !delivered(&session, &status, args.wait.max(1.0)).await {
                unconfirmed.push(status);
            }
        }
        if !unconfirmed.is_empty() {
            // No daemon answers for these (another kind of subscriber): give the transport
            // time to drain instead.
            eprintln!(
                "warning: delivery not confirmed (no answer on {}); waiting 2 s before closing",
                unconfirmed.join(", ")
            );
            tokio::time::sleep(Duration::from_secs(2)).await;
        }
        session.close().await.map_err(zerr("cannot close the Zenoh session"))?;
        println!(
            "published {} modal sets of {} on {} ({secs:.1} s, {:.0} sets/s)",
            sets.len(),
            args.recording.display(),
            topics.into_iter().collect::<Vec<_>>().join(", "),
            sets.len() as f64 / secs.max(1e-9)
        );
        Ok(())
    })
}

/// Whether a status query on `key`, sent after the sets, is answered within `timeout_s`
/// seconds (see the delivery barrier in [`run`]).
async fn delivered(session: &zenoh::Session, key: &str, timeout_s: f64) -> bool {
    let Ok(replies) = session
        .get(key)
        .priority(zenoh::qos::Priority::Data)
        .congestion_control(zenoh::qos::CongestionControl::Block)
        .timeout(Duration::from_secs_f64(timeout_s))
        .await
    else {
        return false;
    };
    while let Ok(r) = replies.recv_async().await {
        if r.result().is_ok() {
            return true;
        }
    }
    false
}
