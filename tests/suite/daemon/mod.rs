//! `boltwatch run` over real Zenoh on loopback (issue 5): the same estimates and alerts as
//! `replay`, status queries, malformed payloads, a burst larger than the queue, SIGTERM and
//! restart, and a Python client using the `eclipse-zenoh` package.
//!
//! Each test starts the daemon as a user does (the binary, a configuration file, a state
//! directory of its own, free loopback ports) and talks to it from an in-process Zenoh
//! session or from `boltwatch publish`.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::time::{Duration, Instant};

use serde_json::Value;
use zenoh::Wait;

use boltwatch::io::mcap::{read_all, topic};
use boltwatch::settings::Settings;

pub fn bin() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_boltwatch"));
    c.current_dir(env!("CARGO_MANIFEST_DIR"))
        .env("BOLTWATCH__LOG__LEVEL", "warn");
    c
}

/// A loopback TCP port that was free a moment ago.
pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// A running `boltwatch run`; SIGKILLed if dropped while running.
pub struct Daemon {
    child: Child,
    pub dir: PathBuf,
    pub endpoint: String,
    pub metrics: String,
    /// The console's `host:port`.
    pub console: String,
    config: PathBuf,
    env: Vec<(String, String)>,
}

impl Daemon {
    /// Starts the daemon with state in `dir/state` and `extra` TOML appended to its
    /// configuration (no `[zenoh]`/`[daemon]`/`[metrics]` tables in `extra`: use
    /// `daemon_keys` for keys of `[daemon]`).
    pub fn start(dir: &Path, daemon_keys: &str, extra: &str) -> Self {
        Self::start_listening(dir, daemon_keys, extra, &[])
    }

    /// A daemon on fresh loopback ports, returned once it accepts connections. A port
    /// [`free_port`] found free can be taken before the daemon binds it (by another
    /// test's connection): then the daemon exits at start, and it is started again on
    /// other ports.
    fn start_listening(dir: &Path, daemon_keys: &str, extra: &str, env: &[(&str, &str)]) -> Self {
        let env: Vec<(String, String)> = env
            .iter()
            .map(|(k, v)| (k.to_string(), v.to_string()))
            .collect();
        for _ in 0..5 {
            let endpoint = format!("tcp/127.0.0.1:{}", free_port());
            let zenoh = format!("listen = [\"{endpoint}\"]");
            let mut d = Self::start_full(dir, &zenoh, endpoint, daemon_keys, extra, env.clone());
            let port = d.endpoint.rsplit(':').next().unwrap().to_string();
            let deadline = Instant::now() + Duration::from_secs(60);
            loop {
                if std::net::TcpStream::connect(format!("127.0.0.1:{port}")).is_ok() {
                    return d;
                }
                if d.child.try_wait().unwrap().is_some() {
                    let log = d.log();
                    assert!(
                        log.contains("in use") || log.contains("Can not create a new TCP listener"),
                        "the daemon exited at start; its log:\n{log}"
                    );
                    break;
                }
                assert!(
                    Instant::now() < deadline,
                    "the daemon did not listen within 60 s; its log:\n{}",
                    d.log()
                );
                std::thread::sleep(Duration::from_millis(20));
            }
        }
        panic!("no free port for the daemon in 5 tries");
    }

    /// [`Daemon::start`] with the `[zenoh]` table's body given; clients reach it at
    /// `endpoint`.
    pub fn start_with(
        dir: &Path,
        zenoh: &str,
        endpoint: String,
        daemon_keys: &str,
        extra: &str,
    ) -> Self {
        Self::start_full(dir, zenoh, endpoint, daemon_keys, extra, Vec::new())
    }

    /// [`Daemon::start`] with extra environment variables.
    pub fn start_env(dir: &Path, env: &[(&str, &str)]) -> Self {
        Self::start_listening(dir, "", "", env)
    }

    fn start_full(
        dir: &Path,
        zenoh: &str,
        endpoint: String,
        daemon_keys: &str,
        extra: &str,
        env: Vec<(String, String)>,
    ) -> Self {
        let metrics = format!("127.0.0.1:{}", free_port());
        let console = format!("127.0.0.1:{}", free_port());
        let config = dir.join("boltwatch.toml");
        std::fs::write(
            &config,
            format!(
                "[zenoh]\n{zenoh}\n\n[daemon]\nstate_dir = \"{}\"\n{daemon_keys}\n\n[metrics]\nlisten = \"{metrics}\"\n\n[console]\nlisten = \"{console}\"\n\n{extra}\n",
                dir.join("state").display()
            ),
        )
        .unwrap();
        Self::spawn(dir, config, endpoint, (metrics, console), env)
    }

    fn spawn(
        dir: &Path,
        config: PathBuf,
        endpoint: String,
        (metrics, console): (String, String),
        env: Vec<(String, String)>,
    ) -> Self {
        let log = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(dir.join("daemon.log"))
            .unwrap();
        let child = bin()
            .envs(env.iter().map(|(k, v)| (k, v)))
            .arg("run")
            .arg("--config")
            .arg(&config)
            .stdout(Stdio::null())
            .stderr(log)
            .spawn()
            .unwrap();
        Self {
            child,
            dir: dir.to_path_buf(),
            endpoint,
            metrics,
            console,
            config,
            env,
        }
    }

    /// The same daemon (configuration, state, ports) started again.
    pub fn restart(&self) -> Self {
        Self::spawn(
            &self.dir,
            self.config.clone(),
            self.endpoint.clone(),
            (self.metrics.clone(), self.console.clone()),
            self.env.clone(),
        )
    }

    pub fn pid(&self) -> i32 {
        self.child.id() as i32
    }

    /// SIGTERM, then the exit status (within 60 s).
    pub fn terminate(&mut self) -> ExitStatus {
        unsafe {
            libc::kill(self.pid(), libc::SIGTERM);
        }
        let deadline = Instant::now() + Duration::from_secs(60);
        loop {
            if let Some(s) = self.child.try_wait().unwrap() {
                return s;
            }
            assert!(
                Instant::now() < deadline,
                "the daemon did not stop within 60 s of SIGTERM; its log:\n{}",
                self.log()
            );
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    pub fn log(&self) -> String {
        std::fs::read_to_string(self.dir.join("daemon.log")).unwrap_or_default()
    }

    /// Every `.mcap` file of the rolling log, oldest first.
    pub fn log_files(&self) -> Vec<PathBuf> {
        let mut v: Vec<PathBuf> = std::fs::read_dir(self.dir.join("state/log"))
            .unwrap()
            .map(|e| e.unwrap().path())
            .collect();
        v.sort();
        v
    }
}

impl Drop for Daemon {
    fn drop(&mut self) {
        if self.child.try_wait().ok().flatten().is_none() {
            let _ = self.child.kill();
            let _ = self.child.wait();
        }
    }
}

/// An in-process Zenoh session from a JSON5 configuration.
pub fn client_from(json5: &str) -> zenoh::Session {
    zenoh::open(zenoh::Config::from_json5(json5).unwrap())
        .wait()
        .unwrap()
}

/// An in-process Zenoh session connected to `endpoint`.
pub fn client(endpoint: &str) -> zenoh::Session {
    let mut c = zenoh::Config::default();
    c.insert_json5("mode", "\"peer\"").unwrap();
    c.insert_json5("connect/endpoints", &format!("[\"{endpoint}\"]"))
        .unwrap();
    c.insert_json5("listen/endpoints", "[]").unwrap();
    c.insert_json5("scouting/multicast/enabled", "false")
        .unwrap();
    zenoh::open(c).wait().unwrap()
}

/// The daemon's status reply for lab-frame, if it answers within a second.
pub fn status(s: &zenoh::Session) -> Option<Value> {
    status_of(s, "lab-frame")
}

/// The status reply for `structure`, if the daemon answers within a second.
pub fn status_of(s: &zenoh::Session, structure: &str) -> Option<Value> {
    let replies = s
        .get(topic(structure, "status"))
        .timeout(Duration::from_secs(1))
        .wait()
        .ok()?;
    while let Ok(r) = replies.recv() {
        if let Ok(sample) = r.result() {
            return serde_json::from_slice(&sample.payload().to_bytes()).ok();
        }
    }
    None
}

/// Waits until `done(status)` holds (or `limit` passes), returning the last status.
pub fn wait_status(
    s: &zenoh::Session,
    limit: Duration,
    what: &str,
    done: impl Fn(&Value) -> bool,
) -> Value {
    wait_status_of(s, "lab-frame", limit, what, done)
}

/// [`wait_status`] for `structure`.
pub fn wait_status_of(
    s: &zenoh::Session,
    structure: &str,
    limit: Duration,
    what: &str,
    done: impl Fn(&Value) -> bool,
) -> Value {
    let deadline = Instant::now() + limit;
    let mut last = Value::Null;
    while Instant::now() < deadline {
        if let Some(v) = status_of(s, structure) {
            if done(&v) {
                return v;
            }
            last = v;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    panic!("timed out waiting for {what}; last status: {last:#}");
}

/// Every message received on `boltwatch/lab-frame/<suffix>`, by suffix.
pub struct Outputs {
    subs: Vec<(
        String,
        zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>>,
    )>,
}

impl Outputs {
    fn subscribe(s: &zenoh::Session) -> Self {
        let subs = ["stiffness", "alerts", "crosscheck", "rejected"]
            .into_iter()
            .map(|suffix| {
                let sub = s
                    .declare_subscriber(topic("lab-frame", suffix))
                    .with(zenoh::handlers::FifoChannel::new(100_000))
                    .wait()
                    .unwrap();
                (suffix.to_string(), sub)
            })
            .collect();
        Self { subs }
    }

    /// Everything received so far.
    fn drain(&self, into: &mut BTreeMap<String, Vec<Value>>) {
        for (suffix, sub) in &self.subs {
            while let Ok(Some(sample)) = sub.try_recv() {
                into.entry(suffix.clone())
                    .or_default()
                    .push(serde_json::from_slice(&sample.payload().to_bytes()).unwrap());
            }
        }
    }
}

/// `boltwatch publish` of `rec` to `endpoint`.
pub fn publish(rec: &Path, endpoint: &str, extra: &[&str]) -> Command {
    let mut c = bin();
    c.arg("publish")
        .arg(rec)
        .args(["--connect", endpoint])
        .args(extra)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped());
    c
}

pub fn run_ok(mut c: Command) -> String {
    let o = c.output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    String::from_utf8_lossy(&o.stdout).into_owned()
}

/// The outputs of `replay` of `rec` on the default configuration with `env`.
pub fn replayed(
    rec: &Path,
    out: &Path,
    env: &[(&str, &str)],
) -> Vec<boltwatch::io::mcap::RecordedMessage> {
    let settings = Settings::load_with_env(
        None,
        env.iter().map(|(k, v)| (k.to_string(), v.to_string())),
    )
    .unwrap();
    replayed_with(rec, out, settings)
}

/// The outputs of `replay` of `rec` with `settings`.
pub fn replayed_with(
    rec: &Path,
    out: &Path,
    settings: Settings,
) -> Vec<boltwatch::io::mcap::RecordedMessage> {
    super::tracker::run_replay(rec, out, settings);
    read_all(out).unwrap()
}

mod console;
mod deploy;
mod field;
mod fleet;
mod fleet_acl;
mod monitoring;
mod tracking;

/// Peak resident set size of a running process (KiB).
pub fn vm_hwm_kib(pid: i32) -> u64 {
    read_vm_hwm_kib(pid).unwrap()
}

/// Peak resident set size of a process (KiB), `None` once it has exited.
pub fn read_vm_hwm_kib(pid: i32) -> Option<u64> {
    let s = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    s.lines()
        .find_map(|l| l.strip_prefix("VmHWM:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
}
