//! The deployment: a Python client, TLS and access control, a router, SIGKILL recovery,
//! a slow cross-check, the deployment files.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use serde_json::Value;
use zenoh::Wait;

use super::*;
use crate::suite::common::python_venv;
use crate::suite::tracker::{make_scenario, payloads, tmp_dir};
use boltwatch::commands::scenario::{ScenarioArgs, run as scenario};
use boltwatch::io::mcap::{read_all, read_modal_sets, topic};
use boltwatch::settings::Settings;

/// A client written in Python with the `eclipse-zenoh` package publishes modal sets and
/// receives the daemon's estimates, its alerts and a status reply.
#[test]
fn python_zenoh_client_publishes_and_receives() {
    let d = tmp_dir("daemon-python");
    let rec = d.join("rec.mcap");
    boltwatch::core::sequential_numerics();
    scenario(&ScenarioArgs {
        name: "sudden".into(),
        model: "config/models/lab-frame.toml".into(),
        sets: Some(150),
        days: Some(7.5),
        seed: 1,
        modes: 9,
        connection: None,
        at: None,
        event_day: Some(3.0),
        loosen: None,
        drop: None,
        day: None,
        environment: false,
        shape_digits: 0,
        out: rec.clone(),
        raw: Default::default(),
    })
    .unwrap();
    let reference = replayed(&rec, &d.join("ref.mcap"), &[]);
    let want_alerts = payloads(&reference, "alerts");
    assert!(!want_alerts.is_empty(), "the recording raises an alert");
    let (sets, _) = read_modal_sets(&rec, &["lab-frame"]).unwrap();
    let lines: Vec<String> = sets
        .iter()
        .map(|(_, m)| String::from_utf8(m.data.clone()).unwrap())
        .collect();
    std::fs::write(d.join("sets.jsonl"), lines.join("\n") + "\n").unwrap();

    let python = python_venv("py-zenoh-venv", "import zenoh", &["eclipse-zenoh==1.10.2"]);
    let mut daemon = Daemon::start(&d, "", "");
    let s = client(&daemon.endpoint);
    wait_status(&s, Duration::from_secs(30), "the daemon to answer", |_| {
        true
    });
    drop(s);
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/python/zenoh_client.py");
    let o = Command::new(&python)
        .arg(&script)
        .arg(&daemon.endpoint)
        .arg(d.join("sets.jsonl"))
        .arg(want_alerts.len().to_string())
        .output()
        .unwrap();
    assert!(
        o.status.success(),
        "{}\n{}\ndaemon log:\n{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr),
        daemon.log()
    );
    let got: Value = serde_json::from_slice(&o.stdout).unwrap();
    let want_est = payloads(&reference, "stiffness");
    assert_eq!(got["stiffness"].as_array().unwrap(), &want_est);
    assert_eq!(got["alerts"].as_array().unwrap(), &want_alerts);
    assert_eq!(got["status"]["schema"], "boltwatch.status.v1");
    assert_eq!(got["status"]["sets"]["accepted"], 150);
    assert!(daemon.terminate().success());
}

/// A file of `deploy/` with its `/etc/boltwatch/` paths moved to `dir` and the `pairs`
/// replaced (each must occur).
pub(super) fn localize(dir: &Path, file: &str, pairs: &[(&str, &str)]) -> String {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("deploy");
    let mut text = std::fs::read_to_string(root.join(file)).unwrap();
    let dir = format!("{}/", dir.display());
    for (from, to) in [("/etc/boltwatch/", dir.as_str())].iter().chain(pairs) {
        if *from == "/etc/boltwatch/" && !text.contains(from) {
            continue;
        }
        assert!(text.contains(from), "{file} has no `{from}`");
        text = text.replace(from, to);
    }
    text
}

/// A test CA and a server certificate for 127.0.0.1, made with the `openssl` command.
pub(super) fn make_certs(dir: &Path) {
    let tls = dir.join("tls");
    std::fs::create_dir_all(&tls).unwrap();
    std::fs::write(
        tls.join("server.ext"),
        "subjectAltName=IP:127.0.0.1,DNS:localhost\nbasicConstraints=CA:FALSE\n\
         keyUsage=digitalSignature,keyEncipherment\nextendedKeyUsage=serverAuth\n",
    )
    .unwrap();
    let steps: [&[&str]; 3] = [
        &[
            "req",
            "-x509",
            "-newkey",
            "rsa:2048",
            "-nodes",
            "-days",
            "2",
            "-subj",
            "/CN=boltwatch test CA",
            "-addext",
            "basicConstraints=critical,CA:TRUE",
            "-addext",
            "keyUsage=critical,keyCertSign,cRLSign",
            "-keyout",
            "ca-key.pem",
            "-out",
            "ca.pem",
        ],
        &[
            "req",
            "-newkey",
            "rsa:2048",
            "-nodes",
            "-subj",
            "/CN=boltwatch-daemon",
            "-keyout",
            "daemon-key.pem",
            "-out",
            "daemon.csr",
        ],
        &[
            "x509",
            "-req",
            "-in",
            "daemon.csr",
            "-CA",
            "ca.pem",
            "-CAkey",
            "ca-key.pem",
            "-CAcreateserial",
            "-days",
            "2",
            "-extfile",
            "server.ext",
            "-out",
            "daemon.pem",
        ],
    ];
    for args in steps {
        let o = Command::new("openssl")
            .args(args)
            .current_dir(&tls)
            .output()
            .expect("the openssl command (Debian package openssl) makes the test certificates");
        assert!(
            o.status.success(),
            "openssl {args:?}: {}",
            String::from_utf8_lossy(&o.stderr)
        );
    }
}

/// The access-controlled deployment (deploy/zenoh-daemon.json5 and
/// deploy/zenoh-sensor.json5, with this test's paths, port and passwords): a publisher
/// without credentials cannot connect, one with credentials but not the sensor's cannot
/// inject modal data (though it may query the status), and the sensor pipeline can.
#[test]
fn access_control_lets_only_the_sensor_publish_modal_data() {
    let d = tmp_dir("daemon-acl");
    let rec = d.join("rec.mcap");
    make_scenario("healthy", 10, 0.5, &rec);
    make_certs(&d);
    std::fs::write(
        d.join("zenoh-users.txt"),
        "sensor:s3nsor-pass\nviewer:v1ewer-pass\n",
    )
    .unwrap();
    let port = free_port();
    let endpoint = format!("tls/127.0.0.1:{port}");
    let localize = |file: &str, pairs: &[(&str, &str)]| localize(&d, file, pairs);
    let daemon_cfg = localize("zenoh-daemon.json5", &[("tls/0.0.0.0:7447", &endpoint)]);
    std::fs::write(d.join("zenoh-daemon.json5"), daemon_cfg).unwrap();
    let sensor = localize(
        "zenoh-sensor.json5",
        &[
            ("tls/boltwatch-host:7447", &endpoint),
            ("change-me-sensor", "s3nsor-pass"),
        ],
    );
    let viewer = sensor
        .replace("user: \"sensor\"", "user: \"viewer\"")
        .replace("s3nsor-pass", "v1ewer-pass");
    assert_ne!(viewer, sensor);
    let anonymous = viewer
        .lines()
        .filter(|l| !l.contains("usrpwd"))
        .collect::<Vec<_>>()
        .join("\n");
    let wrong_password = viewer.replace("v1ewer-pass", "not-the-password");
    for (name, text) in [
        ("sensor", &sensor),
        ("viewer", &viewer),
        ("anonymous", &anonymous),
        ("wrong-password", &wrong_password),
    ] {
        std::fs::write(d.join(format!("{name}.json5")), text).unwrap();
    }
    let zenoh = format!(
        "config_file = \"{}\"",
        d.join("zenoh-daemon.json5").display()
    );
    let mut daemon = Daemon::start_with(&d, &zenoh, endpoint, "", "");
    let s = client_from(&viewer);
    let st = wait_status(
        &s,
        Duration::from_secs(30),
        "the daemon to answer the viewer",
        |_| true,
    );
    assert_eq!(st["sets"]["received"], 0);
    let publish_as = |who: &str| {
        let mut c = bin();
        c.arg("publish")
            .arg(&rec)
            .arg("--zenoh-config")
            .arg(d.join(format!("{who}.json5")))
            .args(["--rate", "0", "--wait", "5"]);
        c.output().unwrap()
    };
    let received = || status(&s).unwrap()["sets"]["received"].as_u64().unwrap();

    // Without credentials, or with a wrong password: no connection, so no subscriber is
    // ever seen.
    for who in ["anonymous", "wrong-password"] {
        let o = publish_as(who);
        assert!(!o.status.success(), "{who} got through");
        assert!(
            String::from_utf8_lossy(&o.stderr).contains("no subscriber"),
            "{who}: {}",
            String::from_utf8_lossy(&o.stderr)
        );
    }
    // Valid credentials, but not the sensor's: the puts are denied at the daemon.
    let o = publish_as("viewer");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    std::thread::sleep(Duration::from_millis(1500));
    assert_eq!(
        received(),
        0,
        "modal data got in without the sensor's credentials"
    );
    // A dashboard (a Zenoh client of the daemon, which routes for it) subscribes to the
    // outputs; an authenticated user that is not the daemon (the viewer, or even the
    // sensor) publishes a forged alert: it is denied at the daemon and never reaches the
    // dashboard, while the daemon's own outputs do.
    let as_client = |text: &str| text.replacen("mode: \"peer\"", "mode: \"client\"", 1);
    assert_ne!(as_client(&viewer), viewer);
    let dashboard = client_from(&as_client(&viewer));
    let alerts = dashboard
        .declare_subscriber(topic("lab-frame", "alerts"))
        .with(zenoh::handlers::FifoChannel::new(1000))
        .wait()
        .unwrap();
    let estimates = dashboard
        .declare_subscriber(topic("lab-frame", "stiffness"))
        .with(zenoh::handlers::FifoChannel::new(1000))
        .wait()
        .unwrap();
    let forged = br#"{"schema":"boltwatch.alert.v1","structure":"lab-frame","kind":"loosening","level":"alarm","message":"forged"}"#;
    for who in [&viewer, &sensor] {
        let attacker = client_from(&as_client(who));
        std::thread::sleep(Duration::from_millis(500));
        for _ in 0..5 {
            attacker
                .put(topic("lab-frame", "alerts"), forged.to_vec())
                .wait()
                .unwrap();
        }
        std::thread::sleep(Duration::from_millis(500));
        attacker.close().wait().unwrap();
    }
    // The sensor pipeline.
    let o = publish_as("sensor");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let st = wait_status(&s, Duration::from_secs(60), "the sensor's 10 sets", |v| {
        v["sets"]["accepted"] == 10
    });
    assert_eq!(st["sets"]["received"], 10);
    let deadline = Instant::now() + Duration::from_secs(10);
    let mut n_estimates = 0;
    while n_estimates < 10 && Instant::now() < deadline {
        if let Ok(Some(_)) = estimates.try_recv() {
            n_estimates += 1;
        } else {
            std::thread::sleep(Duration::from_millis(20));
        }
    }
    assert_eq!(
        n_estimates, 10,
        "the dashboard receives the daemon's estimates"
    );
    assert!(
        alerts.try_recv().unwrap().is_none(),
        "a forged alert reached the dashboard"
    );
    drop(dashboard);
    drop(s);
    assert!(daemon.terminate().success(), "{}", daemon.log());
}

/// Many structures over one Zenoh network (deploy/zenohd.json5, a router, here in-process,
/// and deploy/zenoh-daemon-client.json5): one daemon watches two structures through the
/// router; the sensor's sets of both are tracked, each by its own tracker, to the
/// estimates a replay gives; a dashboard user receives them and queries both statuses but
/// cannot inject modal data.
#[test]
fn a_router_carries_two_structures_under_access_control() {
    let d = tmp_dir("daemon-router");
    let (lab, cant) = (d.join("lab.mcap"), d.join("cantilever.mcap"));
    make_scenario("healthy", 20, 1.0, &lab);
    boltwatch::core::sequential_numerics();
    scenario(&ScenarioArgs {
        name: "healthy".into(),
        model: "config/models/cantilever-case1.toml".into(),
        sets: Some(20),
        days: Some(1.0),
        seed: 2,
        modes: 4,
        connection: None,
        at: None,
        event_day: None,
        loosen: None,
        drop: None,
        day: None,
        environment: false,
        shape_digits: 0,
        out: cant.clone(),
        raw: Default::default(),
    })
    .unwrap();
    make_certs(&d);
    for f in ["daemon.pem", "daemon-key.pem"] {
        std::fs::copy(
            d.join("tls").join(f),
            d.join("tls").join(f.replace("daemon", "router")),
        )
        .unwrap();
    }
    std::fs::write(
        d.join("users.txt"),
        "sensor:s3nsor-pass\nboltwatch:b0lt-pass\ndashboard:d4sh-pass\n",
    )
    .unwrap();
    let endpoint = format!("tls/127.0.0.1:{}", free_port());
    let zdir = format!("{}/", d.display());
    let router_cfg = localize(
        &d,
        "zenohd.json5",
        &[("/etc/zenoh/", &zdir), ("tls/0.0.0.0:7447", &endpoint)],
    );
    let _router = client_from(&router_cfg);
    let daemon_cfg = localize(
        &d,
        "zenoh-daemon-client.json5",
        &[
            ("tls/zenoh-router:7447", &endpoint),
            ("change-me-boltwatch", "b0lt-pass"),
        ],
    );
    std::fs::write(d.join("zenoh-daemon.json5"), daemon_cfg).unwrap();
    let sensor = localize(
        &d,
        "zenoh-sensor.json5",
        &[
            ("tls/boltwatch-host:7447", &endpoint),
            ("change-me-sensor", "s3nsor-pass"),
        ],
    );
    let dashboard = sensor
        .replace("user: \"sensor\"", "user: \"dashboard\"")
        .replace("s3nsor-pass", "d4sh-pass");
    std::fs::write(d.join("sensor.json5"), &sensor).unwrap();
    std::fs::write(d.join("dashboard.json5"), &dashboard).unwrap();
    let structures = "[[structures]]\nname = \"lab-frame\"\nmodel = \"bundled:lab-frame\"\n\n\
                      [[structures]]\nname = \"cantilever\"\nmodel = \"bundled:cantilever-case1\"\n";
    let zenoh = format!(
        "config_file = \"{}\"",
        d.join("zenoh-daemon.json5").display()
    );
    let mut daemon = Daemon::start_with(&d, &zenoh, endpoint, "", structures);
    let s = client_from(&dashboard);
    for structure in ["lab-frame", "cantilever"] {
        let deadline = Instant::now() + Duration::from_secs(30);
        while status_of(&s, structure).is_none() {
            assert!(
                Instant::now() < deadline,
                "no status of {structure}; log:\n{}",
                daemon.log()
            );
            std::thread::sleep(Duration::from_millis(50));
        }
    }
    let subs: Vec<_> = ["lab-frame", "cantilever"]
        .iter()
        .map(|st| {
            s.declare_subscriber(topic(st, "stiffness"))
                .with(zenoh::handlers::FifoChannel::new(1000))
                .wait()
                .unwrap()
        })
        .collect();
    std::thread::sleep(Duration::from_millis(500));
    let publish_as = |who: &str, rec: &Path| {
        bin()
            .arg("publish")
            .arg(rec)
            .arg("--zenoh-config")
            .arg(d.join(format!("{who}.json5")))
            .args([
                "--rate",
                "0",
                "--wait",
                if who == "sensor" { "10" } else { "3" },
            ])
            .output()
            .unwrap()
    };
    // The router does not even show the dashboard that modal data has subscribers; whether
    // its publish gives up or not, nothing of it may reach the daemon (checked below).
    let o = publish_as("dashboard", &lab);
    println!(
        "dashboard publishing modal data: {}",
        String::from_utf8_lossy(if o.status.success() {
            &o.stdout
        } else {
            &o.stderr
        })
        .trim()
    );
    for rec in [&lab, &cant] {
        let o = publish_as("sensor", rec);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    }
    for (k, (structure, rec, model)) in [
        ("lab-frame", &lab, "config/models/lab-frame.toml"),
        ("cantilever", &cant, "config/models/cantilever-case1.toml"),
    ]
    .into_iter()
    .enumerate()
    {
        let deadline = Instant::now() + Duration::from_secs(60);
        let st = loop {
            let st = status_of(&s, structure).unwrap_or_default();
            if st["sets"]["accepted"] == 20 {
                break st;
            }
            assert!(Instant::now() < deadline, "{structure}: {st:#}");
            std::thread::sleep(Duration::from_millis(50));
        };
        assert_eq!(
            st["sets"]["received"], 20,
            "{structure}: only the sensor's sets get in"
        );
        let settings = {
            let mut s = Settings::load_with_env(None, std::iter::empty()).unwrap();
            s.structures[0].name = structure.to_string();
            s.structures[0].model = model.into();
            s
        };
        let want: Vec<Value> =
            replayed_with(rec, &d.join(format!("{structure}.out.mcap")), settings)
                .iter()
                .filter(|m| m.topic == topic(structure, "stiffness"))
                .map(|m| serde_json::from_slice(&m.data).unwrap())
                .collect();
        let mut got = Vec::new();
        while got.len() < 20 {
            let sample = subs[k]
                .recv_timeout(Duration::from_secs(10))
                .unwrap()
                .unwrap();
            got.push(serde_json::from_slice::<Value>(&sample.payload().to_bytes()).unwrap());
        }
        assert_eq!(got, want, "{structure}");
    }
    drop(subs);
    drop(s);
    assert!(daemon.terminate().success(), "{}", daemon.log());
}

/// SIGKILL (no chance to clean up) while sets arrive, with small log files and a
/// checkpoint every half second: the log rotates into complete files; at the restart the
/// unfinished file is completed (readable to its last synced message) and the tracker
/// resumes from the timed checkpoint, not from scratch.
#[test]
fn sigkill_then_restart_recovers_the_log_and_the_timed_checkpoint() {
    let d = tmp_dir("daemon-sigkill");
    let rec = d.join("rec.mcap");
    make_scenario("healthy", 600, 30.0, &rec);
    let keys = "checkpoint_every_s = 0.5\nlog_rotate_mib = 1";
    let mut daemon = Daemon::start(&d, keys, "");
    let s = client(&daemon.endpoint);
    wait_status(&s, Duration::from_secs(30), "the daemon to answer", |_| {
        true
    });
    run_ok(publish(&rec, &daemon.endpoint, &["--rate", "0"]));
    wait_status(&s, Duration::from_secs(300), "600 sets", |v| {
        v["sets"]["accepted"] == 600
    });
    // A timed checkpoint after the last set (tracker.checkpoint_every_sets is 1000).
    let ckpt = d.join("state/lab-frame.checkpoint.json");
    let accepted = || -> u64 {
        std::fs::read(&ckpt)
            .ok()
            .and_then(|b| serde_json::from_slice::<Value>(&b).ok())
            .and_then(|v| v["state"]["accepted"].as_u64())
            .unwrap_or(0)
    };
    let deadline = Instant::now() + Duration::from_secs(30);
    while accepted() < 600 {
        assert!(
            Instant::now() < deadline,
            "no timed checkpoint: {}",
            accepted()
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    drop(s);
    unsafe {
        libc::kill(daemon.pid(), libc::SIGKILL);
    }
    let _ = daemon.child.wait();
    let files: Vec<PathBuf> = std::fs::read_dir(d.join("state/log"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    let parts = files
        .iter()
        .filter(|p| p.to_string_lossy().ends_with(".mcap.part"))
        .count();
    // Usually one file is being written. The log opens its next file at the next message,
    // so when the last message written filled a file (it was closed and renamed) there is
    // none (seen once in many runs); everything below holds either way.
    assert!(parts <= 1, "at most one file was being written: {files:?}");
    assert!(files.len() >= 3, "1 MiB files rotated: {files:?}");

    let mut daemon = daemon.restart();
    let s = client(&daemon.endpoint);
    let st = wait_status(&s, Duration::from_secs(30), "the restarted daemon", |_| {
        true
    });
    assert_eq!(
        st["sets"]["accepted"], 600,
        "resumed from the timed checkpoint"
    );
    drop(s);
    assert!(daemon.terminate().success());
    let logs = daemon.log_files();
    assert!(
        logs.iter().all(|p| p.extension().unwrap() == "mcap"),
        "the unfinished file was completed: {logs:?}"
    );
    let mut inputs = 0;
    let mut estimates = Vec::new();
    for f in &logs {
        let all = read_all(f).unwrap();
        inputs += payloads(&all, "modal").len();
        estimates.extend(payloads(&all, "stiffness"));
    }
    assert_eq!(
        inputs, 600,
        "every input survived (synced at the checkpoint)"
    );
    let reference = replayed(&rec, &d.join("ref.mcap"), &[]);
    assert!(estimates == payloads(&reference, "stiffness"));
}

/// A cross-check requested on every set cannot keep up; tracking does not wait for it:
/// every set is tracked, and the cross-checks that could not start are counted.
#[test]
fn a_slow_crosscheck_never_holds_up_tracking() {
    let d = tmp_dir("daemon-crosscheck");
    let rec = d.join("rec.mcap");
    make_scenario("healthy", 100, 5.0, &rec);
    let every_set = "[tracker]\ncrosscheck_every_sets = 1\ncrosscheck_every_s = 0.0\n";
    let mut daemon = Daemon::start(&d, "", every_set);
    let s = client(&daemon.endpoint);
    wait_status(&s, Duration::from_secs(30), "the daemon to answer", |_| {
        true
    });
    run_ok(publish(&rec, &daemon.endpoint, &["--rate", "0"]));
    wait_status(&s, Duration::from_secs(300), "100 sets", |v| {
        v["sets"]["accepted"] == 100
    });
    // One request per set (the first set's is the first); each one ran or was skipped.
    let st = wait_status(&s, Duration::from_secs(120), "the last cross-check", |v| {
        v["crosschecks"]["published"].as_u64().unwrap()
            + v["crosschecks"]["skipped"].as_u64().unwrap()
            >= 99
    });
    let (published, skipped) = (
        st["crosschecks"]["published"].as_u64().unwrap(),
        st["crosschecks"]["skipped"].as_u64().unwrap(),
    );
    println!("cross-checks on 100 sets: {published} run, {skipped} skipped");
    assert!(published >= 1 && skipped >= 1, "{st:#}");
    drop(s);
    assert!(daemon.terminate().success());
}

/// The deployment's configuration files load as installed (paths moved into a temporary
/// directory): deploy/boltwatch.toml over the defaults, and every Zenoh file of deploy/.
#[test]
fn deployment_files_load() {
    let d = tmp_dir("daemon-deploy");
    std::fs::create_dir_all(d.join("models")).unwrap();
    std::fs::copy(
        "config/models/lab-frame.toml",
        d.join("models/lab-frame.toml"),
    )
    .unwrap();
    let state = d.join("state");
    let toml = localize(
        &d,
        "boltwatch.toml",
        &[("/var/lib/boltwatch", &state.display().to_string())],
    );
    std::fs::write(d.join("boltwatch.toml"), toml).unwrap();
    std::fs::write(
        d.join("zenoh.json5"),
        localize(&d, "zenoh-daemon.json5", &[]),
    )
    .unwrap();
    let settings = Settings::load_with_env(Some(&d.join("boltwatch.toml")), std::iter::empty())
        .unwrap_or_else(|e| panic!("{e:#}"));
    assert_eq!(settings.daemon.state_dir, state);
    boltwatch::io::zenoh::session_config(&settings.zenoh).unwrap();
    for f in [
        "zenoh-daemon.json5",
        "zenoh-daemon-client.json5",
        "zenoh-sensor.json5",
        "zenohd.json5",
    ] {
        let text = localize(&d, f, &[]);
        zenoh::Config::from_json5(&text).unwrap_or_else(|e| panic!("{f}: {e}"));
    }
}

/// Issue 27: the daemon under the deployment's memory budget (`daemon.memory_mib = 1024`,
/// the unit's `MemoryMax=1G`) tracks the four-bay solid frame (31,458 DOF) and runs its
/// Bayesian cross-check on it: the structure is not reported as unable to cross-check, the
/// cross-check is published with `ok: true`, and the daemon's peak RSS stays below 1 GiB
/// (its MAP used to need 4.5 GB).
#[test]
#[cfg_attr(
    not(feature = "slow-tests"),
    ignore = "slow tier: cargo test --features slow-tests"
)]
fn the_four_bay_frame_is_cross_checked_within_the_memory_budget() {
    let d = tmp_dir("daemon-four-bay");
    let rec = d.join("rec.mcap");
    let out = bin()
        .args([
            "scenario",
            "healthy",
            "--model",
            "config/models/four-bay-solid.toml",
            "--sets",
            "2",
            "--days",
            "1",
            "-o",
        ])
        .arg(&rec)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let structures = "[[structures]]\nname = \"four-bay-solid\"\n\
                      model = \"bundled:four-bay-solid\"\n\n\
                      [tracker]\ncrosscheck_every_sets = 1\ncrosscheck_every_s = 0.0\n";
    let mut daemon = Daemon::start(&d, "memory_mib = 1024", structures);
    let s = client(&daemon.endpoint);
    let sub = s
        .declare_subscriber(topic("four-bay-solid", "crosscheck"))
        .with(zenoh::handlers::FifoChannel::new(100))
        .wait()
        .unwrap();
    let st = wait_status_of(
        &s,
        "four-bay-solid",
        Duration::from_secs(120),
        "the daemon",
        |_| true,
    );
    assert!(
        st["crosschecks"].get("unavailable").is_none(),
        "the cross-check was found not to fit: {st:#}"
    );
    run_ok(publish(&rec, &daemon.endpoint, &["--rate", "0"]));
    let st = wait_status_of(
        &s,
        "four-bay-solid",
        Duration::from_secs(900),
        "two sets and a cross-check",
        |v| {
            v["sets"]["accepted"].as_u64().unwrap() >= 2
                && v["crosschecks"]["published"].as_u64().unwrap() >= 1
        },
    );
    let hwm_kib = vm_hwm_kib(daemon.pid());
    let c: serde_json::Value = serde_json::from_slice(
        &sub.recv_timeout(Duration::from_secs(60))
            .unwrap()
            .unwrap()
            .payload()
            .to_bytes(),
    )
    .unwrap();
    println!(
        "four-bay daemon: {} sets, {} cross-checks ({} skipped), peak RSS {} MiB; cross-check ok {}, {} Newton iterations, max z {}",
        st["sets"]["accepted"],
        st["crosschecks"]["published"],
        st["crosschecks"]["skipped"],
        hwm_kib / 1024,
        c["ok"],
        c["bayesian"]["iterations"],
        c["max_z"]
    );
    assert_eq!(c["ok"], true, "{c:#}");
    assert!(hwm_kib < 1024 * 1024, "peak RSS {hwm_kib} KiB");
    drop(sub);
    drop(s);
    assert!(daemon.terminate().success());
}
