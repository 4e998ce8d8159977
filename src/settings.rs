//! The configuration (issue 4 item 9): `config/default.toml` compiled in, an optional file
//! on top, `BOLTWATCH__SECTION__KEY` environment variables on top of both (the `config`
//! crate). [`Settings::load`] checks every value once and names the key of a bad one.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use serde::Deserialize;

use crate::pipeline::TrackerConfig;
use crate::pipeline::accel::IdentifySettings;
use crate::pipeline::crosscheck::CrosscheckConfig;

/// The bundled defaults.
pub const DEFAULT_TOML: &str = include_str!("../config/default.toml");

/// The whole configuration.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Settings {
    pub log: LogSettings,
    pub structures: Vec<StructureSettings>,
    pub tracker: TrackerConfig,
    pub crosscheck: CrosscheckConfig,
    pub zenoh: ZenohSettings,
    pub daemon: DaemonSettings,
    pub metrics: MetricsSettings,
    pub console: ConsoleSettings,
    pub identify: IdentifySettings,
    pub fleet: FleetSettings,
}

/// `[fleet]`: daemons sharing the structures of one configuration.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FleetSettings {
    /// The group's name ("": no fleet, this daemon watches every configured structure).
    pub group: String,
    /// This daemon's id in the group (unique; "": the host name).
    pub id: String,
}

impl FleetSettings {
    /// Whether this daemon belongs to a fleet.
    pub fn enabled(&self) -> bool {
        !self.group.is_empty()
    }
}

/// Where a structure's state (checkpoints, write-ahead tail) lives.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum StateStore {
    /// `daemon.state_dir` on this box.
    Local,
    /// The storages of the fleet's routers (`boltwatch/<structure>/@state/**`).
    Zenoh,
}

/// `[zenoh]`: the session of `boltwatch run`.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ZenohSettings {
    pub mode: ZenohMode,
    pub listen: Vec<String>,
    pub connect: Vec<String>,
    pub multicast_scouting: bool,
    /// A Zenoh JSON5 file that configures the session entirely ("": none).
    pub config_file: PathBuf,
    /// How long a publication may block on a subscriber that does not read before Zenoh
    /// closes its link (s).
    pub block_timeout_s: f64,
}

/// Zenoh session mode.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ZenohMode {
    Peer,
    Client,
}

/// `[daemon]`.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DaemonSettings {
    pub state: StateStore,
    pub state_dir: PathBuf,
    pub queue: usize,
    pub checkpoint_every_s: f64,
    pub log_rotate_mib: u64,
    pub log_rotate_hours: f64,
    /// A set stamped more than this many seconds after its reception is rejected.
    pub max_future_s: f64,
    /// Larger payloads are rejected with their size, never copied whole.
    pub max_payload_bytes: usize,
    /// Bytes of the payloads waiting in one structure's queue, at most (MiB).
    pub queue_mib: usize,
    /// The process's memory budget (MiB), the deployment's `MemoryMax`: a Bayesian
    /// cross-check that would not fit is skipped with the reason.
    pub memory_mib: u64,
}

/// `[metrics]`.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MetricsSettings {
    /// `host:port` of the Prometheus endpoint ("": off).
    pub listen: String,
}

/// `[console]`: the operator's web page.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ConsoleSettings {
    /// `host:port` of the console ("": off).
    pub listen: String,
    /// A structure with no set for this long is shown as silent (s).
    pub silent_after_s: f64,
    /// Bound of the history read back from the logs and kept in memory (MiB).
    pub cache_mib: u64,
    /// PEM certificate chain and private key: both set serves HTTPS ("": plain HTTP).
    pub tls_cert: PathBuf,
    pub tls_key: PathBuf,
    /// A password file of `user:bcrypt-hash` lines (as `htpasswd -B` writes): set, every
    /// request needs HTTP basic authentication by one of its users ("": none).
    pub users_file: PathBuf,
}

/// `[log]`.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LogSettings {
    pub format: LogFormat,
    pub level: String,
}

/// Log line format.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LogFormat {
    Human,
    Json,
}

/// One `[[structures]]` entry.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StructureSettings {
    /// The structure's name, as in its model file and the key expressions.
    pub name: String,
    /// Its model file.
    pub model: PathBuf,
}

impl Settings {
    /// Defaults, then `file` (if given; it must exist), then the environment.
    pub fn load(file: Option<&Path>) -> Result<Self> {
        Self::load_with_env(file, std::env::vars())
    }

    /// [`Settings::load`] with the environment given (tests).
    pub fn load_with_env(
        file: Option<&Path>,
        env: impl IntoIterator<Item = (String, String)>,
    ) -> Result<Self> {
        let mut b = config::Config::builder().add_source(config::File::from_str(
            DEFAULT_TOML,
            config::FileFormat::Toml,
        ));
        if let Some(f) = file {
            if !f.is_file() {
                bail!("configuration file {} does not exist", f.display());
            }
            let text = relative_to_file(f)?;
            b = b.add_source(config::File::from_str(&text, config::FileFormat::Toml));
        }
        let env: config::Map<String, String> = env.into_iter().collect();
        // The base of the default state directory: the given environment first (tests), then
        // the process's.
        let var = |k: &str| {
            env.get(k)
                .cloned()
                .or_else(|| std::env::var(k).ok())
                .filter(|v| !v.is_empty())
        };
        let state_base = var("XDG_STATE_HOME")
            .map(PathBuf::from)
            .or_else(|| var("HOME").map(|h| Path::new(&h).join(".local/state")));
        let env: config::Map<String, String> = env
            .into_iter()
            .filter(|(k, _)| k.starts_with("BOLTWATCH__"))
            .collect();
        b = b.add_source(
            config::Environment::with_prefix("BOLTWATCH")
                .prefix_separator("__")
                .separator("__")
                .try_parsing(true)
                .list_separator(",")
                .with_list_parse_key("zenoh.listen")
                .with_list_parse_key("zenoh.connect")
                .with_list_parse_key("identify.band_hz")
                .source(Some(env)),
        );
        let what = file.map_or("the default configuration".to_string(), |f| {
            format!("configuration {}", f.display())
        });
        let mut s: Settings = b
            .build()
            .and_then(|c| c.try_deserialize())
            .with_context(|| format!("bad {what}"))?;
        if s.daemon.state_dir.as_os_str().is_empty()
            && let Some(base) = state_base
        {
            // XDG base directories: state belongs in $XDG_STATE_HOME (default
            // ~/.local/state), never in the working directory. With neither set it stays
            // empty, and `run` says so.
            s.daemon.state_dir = base.join("boltwatch");
        }
        if s.fleet.enabled() && s.fleet.id.is_empty() {
            s.fleet.id = host_name();
        }
        s.validate().with_context(|| format!("bad {what}"))?;
        Ok(s)
    }

    /// Checks every value once, naming the key of the first bad one. The order of the
    /// checks decides which error a configuration with several faults reports: the
    /// tracker, cross-check and identification sections, the structures, the daemon's
    /// limits and periods, the endpoints, then the log filter.
    fn validate(&self) -> Result<()> {
        self.tracker.validate()?;
        self.crosscheck.validate()?;
        self.identify.validate()?;
        self.validate_structures()?;
        self.validate_daemon()?;
        self.validate_endpoints()?;
        if tracing_subscriber::EnvFilter::try_new(&self.log.level).is_err() {
            bail!(
                "configuration key log.level: `{}` is not a tracing filter",
                self.log.level
            );
        }
        Ok(())
    }

    /// At least one structure, each with a name usable as a key-expression chunk and
    /// watched once.
    fn validate_structures(&self) -> Result<()> {
        if self.structures.is_empty() {
            bail!("configuration key structures: watch at least one structure");
        }
        for (i, s) in self.structures.iter().enumerate() {
            if s.name.is_empty()
                || s.name.starts_with('@')
                || s.name.contains(['/', '*', '$', '?', '#'])
            {
                bail!(
                    "configuration key structures[{i}].name: `{}` is not a usable key-expression chunk",
                    s.name
                );
            }
            if self.structures[..i].iter().any(|o| o.name == s.name) {
                bail!(
                    "configuration key structures[{i}].name: `{}` is watched twice",
                    s.name
                );
            }
        }
        Ok(())
    }

    /// The daemon's queue, payload and memory limits, its periods (with Zenoh's block
    /// timeout: finite and > 0) and its log rotation size.
    fn validate_daemon(&self) -> Result<()> {
        if self.daemon.queue == 0 {
            bail!("configuration key daemon.queue: must be at least 1");
        }
        if self.daemon.max_payload_bytes < 1024 {
            bail!(
                "configuration key daemon.max_payload_bytes: {} is too small for a modal set (at least 1024)",
                self.daemon.max_payload_bytes
            );
        }
        if self.daemon.queue_mib << 20 < self.daemon.max_payload_bytes {
            bail!(
                "configuration key daemon.queue_mib: {} MiB cannot hold one payload of daemon.max_payload_bytes = {}",
                self.daemon.queue_mib,
                self.daemon.max_payload_bytes
            );
        }
        if self.daemon.memory_mib < 64 {
            bail!(
                "configuration key daemon.memory_mib: {} MiB is too small for the daemon (at least 64)",
                self.daemon.memory_mib
            );
        }
        for (key, v) in [
            ("daemon.checkpoint_every_s", self.daemon.checkpoint_every_s),
            ("daemon.log_rotate_hours", self.daemon.log_rotate_hours),
            ("daemon.max_future_s", self.daemon.max_future_s),
            ("zenoh.block_timeout_s", self.zenoh.block_timeout_s),
        ] {
            if !(v.is_finite() && v > 0.0) {
                bail!("configuration key {key}: {v} must be a finite number > 0");
            }
        }
        if self.daemon.log_rotate_mib == 0 {
            bail!("configuration key daemon.log_rotate_mib: must be at least 1");
        }
        self.validate_fleet()
    }

    /// A fleet's group and id are key-expression chunks, and its state is in Zenoh (a
    /// structure taken over must find its state on another box).
    fn validate_fleet(&self) -> Result<()> {
        let f = &self.fleet;
        if !f.enabled() {
            if self.daemon.state == StateStore::Zenoh {
                bail!(
                    "configuration key daemon.state: \"zenoh\" keeps the state in a fleet's storages: set fleet.group (or daemon.state = \"local\")"
                );
            }
            return Ok(());
        }
        for (key, v) in [("fleet.group", &f.group), ("fleet.id", &f.id)] {
            if v.is_empty() || v.starts_with('@') || v.contains(['/', '*', '$', '?', '#']) {
                bail!("configuration key {key}: `{v}` is not a usable key-expression chunk");
            }
        }
        if self.daemon.state != StateStore::Zenoh {
            bail!(
                "configuration key daemon.state: a fleet (fleet.group = `{}`) keeps its state in Zenoh: set daemon.state = \"zenoh\"",
                f.group
            );
        }
        Ok(())
    }

    /// The metrics endpoint (host:port, or off), then Zenoh's endpoints, or its
    /// configuration file when one is named (it must exist).
    fn validate_endpoints(&self) -> Result<()> {
        for (key, listen, example) in [
            ("metrics.listen", &self.metrics.listen, "127.0.0.1:9464"),
            ("console.listen", &self.console.listen, "127.0.0.1:9465"),
        ] {
            if !listen.is_empty() && listen.parse::<std::net::SocketAddr>().is_err() {
                bail!("configuration key {key}: `{listen}` is not host:port (e.g. {example})");
            }
        }
        if self.console.silent_after_s.is_nan() || self.console.silent_after_s <= 0.0 {
            bail!(
                "configuration key console.silent_after_s: {} is not a positive number of seconds",
                self.console.silent_after_s
            );
        }
        let c = &self.console;
        if c.tls_cert.as_os_str().is_empty() != c.tls_key.as_os_str().is_empty() {
            bail!(
                "configuration keys console.tls_cert and console.tls_key: set both (HTTPS) or neither"
            );
        }
        if self.zenoh.config_file.as_os_str().is_empty() {
            for (key, list) in [
                ("zenoh.listen", &self.zenoh.listen),
                ("zenoh.connect", &self.zenoh.connect),
            ] {
                for e in list {
                    if e.parse::<zenoh::config::EndPoint>().is_err() {
                        bail!(
                            "configuration key {key}: `{e}` is not a Zenoh endpoint (e.g. tcp/127.0.0.1:7447)"
                        );
                    }
                }
            }
        } else if !self.zenoh.config_file.is_file() {
            bail!(
                "configuration key zenoh.config_file: {} does not exist",
                self.zenoh.config_file.display()
            );
        }
        Ok(())
    }
}

/// The keys of a configuration file that hold paths: a relative path in a file is relative
/// to that file's folder (so a site's configuration and its models move together).
const PATH_KEYS: &[&[&str]] = &[
    &["zenoh", "config_file"],
    &["daemon", "state_dir"],
    &["tracker", "normalisation", "law"],
];

/// The text of configuration file `f` with its relative paths (the [`PATH_KEYS`] and every
/// `structures[].model` that is not a bundled model) made relative to `f`'s folder.
fn relative_to_file(f: &Path) -> Result<String> {
    let text = std::fs::read_to_string(f)
        .with_context(|| format!("cannot read configuration file {}", f.display()))?;
    let mut doc: toml::Table = toml::from_str(&text)
        .with_context(|| format!("bad configuration {}: not TOML", f.display()))?;
    let dir = f.parent().unwrap_or(Path::new(""));
    let rebase = |v: &mut toml::Value| {
        if let toml::Value::String(p) = v
            && !p.is_empty()
            && !p.starts_with(crate::io::model::BUNDLED)
            && Path::new(p.as_str()).is_relative()
        {
            *p = dir.join(p.as_str()).to_string_lossy().into_owned();
        }
    };
    for key in PATH_KEYS {
        let mut table = Some(&mut doc);
        for k in &key[..key.len() - 1] {
            table = table
                .and_then(|t| t.get_mut(*k))
                .and_then(|v| v.as_table_mut());
        }
        if let Some(v) = table.and_then(|t| t.get_mut(key[key.len() - 1])) {
            rebase(v);
        }
    }
    if let Some(toml::Value::Array(list)) = doc.get_mut("structures") {
        for entry in list.iter_mut().filter_map(|e| e.as_table_mut()) {
            if let Some(v) = entry.get_mut("model") {
                rebase(v);
            }
        }
    }
    Ok(toml::to_string(&doc)?)
}

/// This machine's host name ("" if it has none): a fleet daemon's default id.
fn host_name() -> String {
    let mut buf = [0u8; 256];
    // SAFETY: the buffer is valid for its length; gethostname NUL-terminates within it
    // when the name fits (a longer name is truncated and the last byte zeroed below).
    let rc = unsafe { libc::gethostname(buf.as_mut_ptr().cast(), buf.len() - 1) };
    if rc != 0 {
        return String::new();
    }
    let end = buf.iter().position(|&b| b == 0).unwrap_or(buf.len() - 1);
    String::from_utf8_lossy(&buf[..end]).into_owned()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn env(pairs: &[(&str, &str)]) -> Vec<(String, String)> {
        pairs
            .iter()
            .map(|(k, v)| (k.to_string(), v.to_string()))
            .collect()
    }

    #[test]
    fn defaults_load_and_environment_overrides() {
        let s = Settings::load_with_env(None, env(&[])).unwrap();
        assert_eq!(s.structures[0].name, "lab-frame");
        assert_eq!(s.tracker, TrackerConfig::default());
        let s = Settings::load_with_env(
            None,
            env(&[
                ("BOLTWATCH__TRACKER__ALERTS__ALARM_DROP", "0.3"),
                ("BOLTWATCH__LOG__FORMAT", "json"),
            ]),
        )
        .unwrap();
        assert_eq!(s.tracker.alerts.alarm_drop, 0.3);
        assert_eq!(s.log.format, LogFormat::Json);
    }

    /// A bad value fails with its key named: out of range, wrong type, unknown key.
    #[test]
    fn bad_values_name_their_key() {
        for (pairs, key) in [
            (
                vec![("BOLTWATCH__TRACKER__ALERTS__ALARM_DROP", "1.5")],
                "tracker.alerts.alarm_drop",
            ),
            (
                vec![("BOLTWATCH__TRACKER__BASELINE_SETS", "many")],
                "baseline_sets",
            ),
            (
                vec![("BOLTWATCH__TRACKER__ALARM_LEVEL", "3")],
                "alarm_level",
            ),
            (vec![("BOLTWATCH__LOG__FORMAT", "xml")], "format"),
            (
                vec![("BOLTWATCH__CROSSCHECK__DISAGREE_Z", "-1")],
                "crosscheck.disagree_z",
            ),
        ] {
            let e = Settings::load_with_env(None, env(&pairs)).unwrap_err();
            let msg = format!("{e:#}");
            assert!(msg.contains(key), "{pairs:?}: {msg}");
        }
    }

    /// A relative path in a configuration file is relative to the file's folder; absolute
    /// paths, bundled models and an environment override (relative to the working
    /// directory) are kept as written.
    #[test]
    fn paths_in_a_file_are_relative_to_it() {
        let dir = std::env::temp_dir().join(format!("bw-settings-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let f = dir.join("site.toml");
        // The Zenoh file must exist (it is checked), wherever it is resolved to.
        std::fs::write(dir.join("zenoh.json5"), "{}").unwrap();
        std::fs::write(
            &f,
            "[[structures]]\nname = \"a\"\nmodel = \"models/a.toml\"\n\n\
             [[structures]]\nname = \"b\"\nmodel = \"bundled:lab-frame\"\n\n\
             [[structures]]\nname = \"c\"\nmodel = \"/srv/c.toml\"\n\n\
             [daemon]\nstate_dir = \"state\"\n\n\
             [zenoh]\nconfig_file = \"zenoh.json5\"\n\n\
             [tracker.normalisation]\nlaw = \"law.json\"\n",
        )
        .unwrap();
        let s = Settings::load_with_env(Some(&f), env(&[])).unwrap();
        let models: Vec<_> = s.structures.iter().map(|s| s.model.clone()).collect();
        assert_eq!(
            models,
            [
                dir.join("models/a.toml"),
                PathBuf::from("bundled:lab-frame"),
                PathBuf::from("/srv/c.toml")
            ]
        );
        assert_eq!(s.daemon.state_dir, dir.join("state"));
        assert_eq!(s.zenoh.config_file, dir.join("zenoh.json5"));
        assert_eq!(
            s.tracker.normalisation.law,
            dir.join("law.json").to_string_lossy()
        );
        let s = Settings::load_with_env(Some(&f), env(&[("BOLTWATCH__DAEMON__STATE_DIR", "here")]))
            .unwrap();
        assert_eq!(s.daemon.state_dir, PathBuf::from("here"));
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// The default state directory is under `$XDG_STATE_HOME`, else `~/.local/state`,
    /// never the working directory; a configured one is kept.
    #[test]
    fn state_dir_defaults_to_xdg() {
        let s = Settings::load_with_env(None, env(&[("XDG_STATE_HOME", "/xdg/state")])).unwrap();
        assert_eq!(s.daemon.state_dir, Path::new("/xdg/state/boltwatch"));
        let s = Settings::load_with_env(None, env(&[("XDG_STATE_HOME", ""), ("HOME", "/home/u")]))
            .unwrap();
        // The process's own XDG_STATE_HOME, if it has one, comes before HOME.
        let want = std::env::var("XDG_STATE_HOME")
            .ok()
            .filter(|v| !v.is_empty())
            .map_or(
                Path::new("/home/u/.local/state/boltwatch").to_path_buf(),
                |x| Path::new(&x).join("boltwatch"),
            );
        assert_eq!(s.daemon.state_dir, want);
        let s = Settings::load_with_env(
            None,
            env(&[
                ("XDG_STATE_HOME", "/xdg/state"),
                ("BOLTWATCH__DAEMON__STATE_DIR", "/var/lib/bw"),
            ]),
        )
        .unwrap();
        assert_eq!(s.daemon.state_dir, Path::new("/var/lib/bw"));
    }

    /// A fleet needs its state in Zenoh, and state in Zenoh needs a fleet; ids are single
    /// key-expression chunks. Each error names its key.
    #[test]
    fn fleet_settings_are_checked_together() {
        let load = |pairs: &[(&str, &str)]| Settings::load_with_env(None, env(pairs));
        let group = ("BOLTWATCH__FLEET__GROUP", "g");
        let id = ("BOLTWATCH__FLEET__ID", "a");
        let zenoh = ("BOLTWATCH__DAEMON__STATE", "zenoh");
        assert!(load(&[group, id, zenoh]).is_ok());
        for (pairs, key) in [
            (vec![group, id], "daemon.state"),
            (vec![zenoh], "daemon.state"),
            (
                vec![group, ("BOLTWATCH__FLEET__ID", "a/b"), zenoh],
                "fleet.id",
            ),
            (
                vec![("BOLTWATCH__FLEET__GROUP", "@g"), id, zenoh],
                "fleet.group",
            ),
        ] {
            let e = format!("{:#}", load(&pairs).unwrap_err());
            assert!(e.contains(key), "{pairs:?}: {e}");
        }
    }
}
