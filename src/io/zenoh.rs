//! The Zenoh side of the I/O adapters (DESIGN §3.4): the session configuration from
//! `[zenoh]`, and the error mapping (`zenoh::Error` is a boxed `dyn Error`, not `anyhow`).

use anyhow::{Result, anyhow};

use crate::settings::{ZenohMode, ZenohSettings};

/// The largest message the Zenoh transport takes in (instead of its 1 GiB default): a bound
/// on the memory one message can take. The daemon itself rejects, with their size, payloads
/// over `daemon.max_payload_bytes` (1 MiB); larger ones up to this bound reach it to be
/// rejected and reported, larger still are dropped by Zenoh. The deploy configurations set
/// the same value.
pub const MAX_MESSAGE_BYTES: usize = 32 << 20;

/// A Zenoh error as an `anyhow` error, with what was being done.
pub fn zerr(what: impl std::fmt::Display) -> impl FnOnce(zenoh::Error) -> anyhow::Error {
    move |e| anyhow!("{what}: {e}")
}

/// The session configuration: the file `config_file` if one is set (TLS, authentication and
/// access control live there), else mode, listen and connect endpoints and multicast
/// scouting from the keys.
pub fn session_config(z: &ZenohSettings) -> Result<zenoh::Config> {
    if !z.config_file.as_os_str().is_empty() {
        return zenoh::Config::from_file(&z.config_file).map_err(zerr(format!(
            "configuration key zenoh.config_file: cannot load {}",
            z.config_file.display()
        )));
    }
    let mut cfg = zenoh::Config::default();
    let mode = match z.mode {
        ZenohMode::Peer => "peer",
        ZenohMode::Client => "client",
    };
    let set = |cfg: &mut zenoh::Config, key: &str, value: String| {
        cfg.insert_json5(key, &value)
            .map_err(zerr(format!("Zenoh configuration {key} = {value}")))
    };
    set(&mut cfg, "mode", format!("\"{mode}\""))?;
    set(
        &mut cfg,
        "listen/endpoints",
        serde_json::to_string(&z.listen)?,
    )?;
    set(
        &mut cfg,
        "connect/endpoints",
        serde_json::to_string(&z.connect)?,
    )?;
    set(
        &mut cfg,
        "scouting/multicast/enabled",
        z.multicast_scouting.to_string(),
    )?;
    set(
        &mut cfg,
        "transport/link/rx/max_message_size",
        MAX_MESSAGE_BYTES.to_string(),
    )?;
    set(
        &mut cfg,
        "transport/link/tx/queue/congestion_control/block/wait_before_close",
        ((z.block_timeout_s * 1e6).round() as u64).to_string(),
    )?;
    Ok(cfg)
}
