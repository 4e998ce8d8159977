//! `boltwatch fleet status`: the fleet as the network sees it: the members whose liveliness
//! tokens are present, and for every structure with a stored owner record, its owner and
//! epoch, whether the owner is live, and the lag of its lane (sets queued, age of the last
//! set) from the owner's status reply.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::time::Duration;

use anyhow::{Result, bail};
use chrono::{DateTime, Utc};
use serde::Serialize;
use zenoh::query::{ConsolidationMode, QueryTarget};

use crate::contract::Status;
use crate::daemon::fleet::state::OwnerRecord;
use crate::io::zenoh::{session_config, zerr};
use crate::settings::{Settings, ZenohMode};

#[derive(Debug, clap::Subcommand)]
pub enum FleetCommand {
    /// Print the group's members, each structure's owner, epoch and lag.
    Status(StatusArgs),
}

#[derive(Debug, clap::Args)]
pub struct StatusArgs {
    /// The daemons' configuration (its [zenoh] section and fleet.group are used).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Connect to this endpoint (a router) instead of the configuration's.
    #[arg(long)]
    pub connect: Option<String>,
    /// The group (default: the configuration's fleet.group).
    #[arg(long)]
    pub group: Option<String>,
    /// Print JSON instead of tables.
    #[arg(long)]
    pub json: bool,
}

/// One structure's line.
#[derive(Debug, Serialize)]
pub struct StructureLine {
    pub structure: String,
    pub owner: String,
    pub epoch: u64,
    pub released: bool,
    pub owner_live: bool,
    /// Since the record was written (RFC 3339).
    pub since: String,
    /// Sets waiting in the owner's queue (None: the owner did not answer).
    pub queued: Option<u64>,
    /// Seconds since the last accepted set's time.
    pub last_set_age_s: Option<f64>,
}

/// The whole picture.
#[derive(Debug, Serialize)]
pub struct FleetView {
    pub group: String,
    pub members: Vec<String>,
    pub structures: Vec<StructureLine>,
}

pub fn run(cmd: &FleetCommand) -> Result<()> {
    match cmd {
        FleetCommand::Status(a) => status(a),
    }
}

fn status(a: &StatusArgs) -> Result<()> {
    let settings = Settings::load(a.config.as_deref())?;
    let group = a.group.clone().unwrap_or(settings.fleet.group.clone());
    if group.is_empty() {
        bail!("no group: give --group or a configuration with fleet.group");
    }
    let mut z = settings.zenoh.clone();
    z.mode = ZenohMode::Client;
    z.listen = Vec::new();
    if let Some(c) = &a.connect {
        z.connect = vec![c.clone()];
        z.config_file = PathBuf::new();
    }
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()?;
    let view = rt.block_on(async {
        let session = zenoh::open(session_config(&z)?)
            .await
            .map_err(zerr("cannot open the Zenoh session"))?;
        let v = view(&session, &group).await;
        let _ = session.close().await;
        v
    })?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&view)?);
    } else {
        print!("{}", table(&view));
    }
    Ok(())
}

/// Reads members, owner records and status replies.
pub async fn view(session: &zenoh::Session, group: &str) -> Result<FleetView> {
    let wait = Duration::from_secs(3);
    let mut members = Vec::new();
    let replies = session
        .liveliness()
        .get(format!("boltwatch/@fleet/{group}/*"))
        .timeout(wait)
        .await
        .map_err(zerr("cannot list the members"))?;
    while let Ok(r) = replies.recv_async().await {
        if let Ok(s) = r.result()
            && let Some(id) = s.key_expr().as_str().rsplit('/').next()
        {
            members.push(id.to_string());
        }
    }
    members.sort();
    let records: Vec<OwnerRecord> = query_all(session, "boltwatch/*/@state/owner", wait).await?;
    let statuses: BTreeMap<String, Status> =
        query_all::<Status>(session, "boltwatch/*/status", wait)
            .await?
            .into_iter()
            .map(|s| (s.structure.clone(), s))
            .collect();
    let now = Utc::now();
    let structures = records
        .into_iter()
        .map(|r| {
            let st = statuses.get(&r.structure);
            StructureLine {
                owner_live: members.contains(&r.owner),
                queued: st.map(|s| s.queue.depth),
                last_set_age_s: st
                    .and_then(|s| s.last_set_time.as_deref())
                    .and_then(|t| DateTime::parse_from_rfc3339(t).ok())
                    .map(|t| (now - t.with_timezone(&Utc)).num_milliseconds() as f64 * 1e-3),
                structure: r.structure,
                owner: r.owner,
                epoch: r.epoch,
                released: r.released,
                since: r.since,
            }
        })
        .collect();
    Ok(FleetView {
        group: group.to_string(),
        members,
        structures,
    })
}

/// Every reply to a query on `ke`, decoded (a reply that does not decode is skipped).
async fn query_all<T: serde::de::DeserializeOwned>(
    session: &zenoh::Session,
    ke: &str,
    wait: Duration,
) -> Result<Vec<T>> {
    let replies = session
        .get(ke)
        .target(QueryTarget::All)
        .consolidation(ConsolidationMode::Latest)
        .timeout(wait)
        .await
        .map_err(zerr(format!("cannot query {ke}")))?;
    let mut out = Vec::new();
    while let Ok(r) = replies.recv_async().await {
        if let Ok(s) = r.result()
            && let Ok(v) = serde_json::from_slice(&s.payload().to_bytes())
        {
            out.push(v);
        }
    }
    Ok(out)
}

/// The view as text: the members, then a line per structure.
pub fn table(v: &FleetView) -> String {
    let mut s = format!(
        "group {}: {} member(s): {}\n\n",
        v.group,
        v.members.len(),
        v.members.join(", ")
    );
    s += &format!(
        "{:<24} {:<16} {:>6} {:<12} {:>7} {:>12}\n",
        "structure", "owner", "epoch", "state", "queued", "last set (s)"
    );
    for l in &v.structures {
        let state = match (l.released, l.owner_live) {
            (true, _) => "handed back",
            (false, true) => "tracking",
            (false, false) => "owner gone",
        };
        let q = l.queued.map_or("-".into(), |q| q.to_string());
        let age = l.last_set_age_s.map_or("-".into(), |a| format!("{a:.0}"));
        s += &format!(
            "{:<24} {:<16} {:>6} {:<12} {:>7} {:>12}\n",
            l.structure, l.owner, l.epoch, state, q, age
        );
    }
    s
}
