//! `boltwatch router`: a Zenoh router with Zenoh's storage manager linked in, which keeps the
//! fleet's state (`boltwatch/*/@state/**`: each structure's owner record, checkpoints and
//! write-ahead tail) in a memory storage. Two or more such routers replicate each other's
//! storage (the storage manager's replication: digests compared every interval, missing
//! entries fetched), so the state outlives any one box.
//!
//! The router is configured by Zenoh JSON5 files (`--config`, as `zenohd` is; several are
//! merged in order: objects key by key, arrays appended, so a fleet's additions sit in
//! their own file beside the site's router configuration) or by `--listen`/`--connect`. Without a `plugins.storage_manager` section the state storage
//! below ([`STATE_STORAGE`]) is added; with one, that section is used as written. The
//! replication settings must be identical on every router of a fleet (the storage manager
//! pairs replicas by a hash of them).

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use zenoh::internal::plugins::PluginsManager;
use zenoh::internal::runtime::RuntimeBuilder;
use zenoh_plugin_storage_manager::StoragesPlugin;

use crate::io::zenoh::{MAX_MESSAGE_BYTES, zerr};

/// The key expression of the fleet's state. `@state` is a verbatim chunk: no wildcard of a
/// subscriber to the outputs (`boltwatch/**`) matches it.
pub const STATE_KEY_EXPR: &str = "boltwatch/*/@state/**";

/// The storage added when the configuration names none: memory, replicated with the storage
/// manager's defaults made faster (a digest every 2 s, so a router that was away catches
/// up within seconds).
pub const STATE_STORAGE: &str = r#"{
  storages: {
    boltwatch_state: {
      key_expr: "boltwatch/*/@state/**",
      volume: "memory",
      replication: { interval: 2.0, sub_intervals: 5, hot: 6, warm: 30, propagation_delay: 250 },
    },
  },
}"#;

#[derive(Debug, clap::Args)]
pub struct RouterArgs {
    /// A Zenoh JSON5 configuration (mode router is set; listen and connect below are added).
    /// Repeatable: later files are merged into earlier ones (objects key by key, arrays
    /// appended).
    #[arg(long)]
    pub config: Vec<PathBuf>,
    /// Endpoints to listen on, e.g. tcp/127.0.0.1:7450 (repeatable).
    #[arg(long)]
    pub listen: Vec<String>,
    /// Endpoints of other routers to connect to (repeatable).
    #[arg(long)]
    pub connect: Vec<String>,
    /// Log filter (tracing syntax).
    #[arg(long, default_value = "info")]
    pub log_level: String,
}

pub fn run(args: &RouterArgs) -> Result<()> {
    super::init_logging(&crate::settings::LogSettings {
        format: crate::settings::LogFormat::Human,
        level: args.log_level.clone(),
    })?;
    let config = router_config(args)?;
    // The storage manager blocks in place on the runtime: it needs the multi-thread flavour.
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .context("cannot start the async runtime")?;
    rt.block_on(serve(config))
}

/// The router's Zenoh configuration (module docs).
pub fn router_config(args: &RouterArgs) -> Result<zenoh::Config> {
    let mut cfg = match args.config.as_slice() {
        [] => zenoh::Config::default(),
        [f] => zenoh::Config::from_file(f)
            .map_err(zerr(format!("--config: cannot load {}", f.display())))?,
        files => merged_config(files)?,
    };
    let mut set = |key: &str, value: String| {
        cfg.insert_json5(key, &value)
            .map_err(zerr(format!("Zenoh configuration {key} = {value}")))
    };
    set("mode", "\"router\"".into())?;
    set("timestamping/enabled", "true".into())?;
    set(
        "transport/link/rx/max_message_size",
        MAX_MESSAGE_BYTES.to_string(),
    )?;
    if !args.listen.is_empty() {
        set("listen/endpoints", serde_json::to_string(&args.listen)?)?;
    }
    if !args.connect.is_empty() {
        set("connect/endpoints", serde_json::to_string(&args.connect)?)?;
    }
    if args.config.is_empty() {
        set("scouting/multicast/enabled", "false".into())?;
    }
    if cfg.get_json("plugins/storage_manager").is_err() {
        cfg.insert_json5("plugins/storage_manager", STATE_STORAGE)
            .map_err(zerr("the state storage"))?;
    }
    if cfg.get_json("listen/endpoints").map_or(true, |v| v == "[]") {
        bail!("the router listens nowhere: give --listen or listen.endpoints in --config");
    }
    Ok(cfg)
}

/// The Zenoh configuration of several JSON5 files merged in order ([`merge`]).
fn merged_config(files: &[PathBuf]) -> Result<zenoh::Config> {
    let mut all = serde_json::Value::Object(Default::default());
    for f in files {
        let text = std::fs::read_to_string(f)
            .with_context(|| format!("--config: cannot read {}", f.display()))?;
        let v: serde_json::Value = json5::from_str(&text)
            .with_context(|| format!("--config: {} is not valid JSON5", f.display()))?;
        merge(&mut all, v);
    }
    zenoh::Config::from_json5(&all.to_string()).map_err(zerr(format!(
        "--config: the merged configuration of {files:?}"
    )))
}

/// Merges `over` into `base`: objects key by key, arrays appended, anything else replaced.
pub fn merge(base: &mut serde_json::Value, over: serde_json::Value) {
    use serde_json::Value;
    match (base, over) {
        (Value::Object(b), Value::Object(o)) => {
            for (k, v) in o {
                match b.get_mut(&k) {
                    Some(slot) => merge(slot, v),
                    None => {
                        b.insert(k, v);
                    }
                }
            }
        }
        (Value::Array(b), Value::Array(o)) => b.extend(o),
        (b, o) => *b = o,
    }
}

/// Starts the runtime with the storage manager, serves until SIGINT or SIGTERM, closes.
async fn serve(config: zenoh::Config) -> Result<()> {
    let mut plugins = PluginsManager::static_plugins_only();
    plugins.declare_static_plugin::<StoragesPlugin, &str>("storage_manager", true);
    let mut runtime = RuntimeBuilder::new(config)
        .plugins_manager(plugins)
        .build()
        .await
        .map_err(zerr("cannot build the router"))?;
    runtime
        .start()
        .await
        .map_err(zerr("cannot start the router"))?;
    tracing::info!(zid = %runtime.zid(), "router up, storing {STATE_KEY_EXPR}");
    let mut sigterm = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())
        .context("cannot install the SIGTERM handler")?;
    tokio::select! {
        _ = sigterm.recv() => tracing::info!("SIGTERM: stopping"),
        _ = tokio::signal::ctrl_c() => tracing::info!("SIGINT: stopping"),
    }
    runtime
        .close()
        .await
        .map_err(zerr("cannot close the router"))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::merge;
    use serde_json::json;

    #[test]
    fn configurations_merge_objects_by_key_and_append_arrays() {
        let mut base = json!({"mode": "router", "acl": {"enabled": true, "rules": [1, 2]}});
        merge(
            &mut base,
            json!({"mode": "peer", "acl": {"rules": [3]}, "connect": ["a"]}),
        );
        assert_eq!(
            base,
            json!({"mode": "peer", "acl": {"enabled": true, "rules": [1, 2, 3]}, "connect": ["a"]})
        );
    }
}
