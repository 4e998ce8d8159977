//! The fleet under the deployed access control: two `boltwatch router`s, each given
//! `deploy/zenohd.json5` and `deploy/fleet/router.json5` (TLS, user/password, ACL), two
//! daemons as user `boltwatch` with `deploy/zenoh-daemon-client.json5`, a sensor and a
//! dashboard user. The daemons share the structures and track the sensor's sets through
//! the routers; neither the sensor nor the dashboard can read or write `@state`, or be seen
//! in (or see) the group's membership `@fleet`.

use std::path::Path;
use std::time::{Duration, Instant};

use serde_json::Value;
use zenoh::Wait;

use super::deploy::{localize, make_certs};
use super::fleet::{NO_CROSSCHECK, Proc, Site};
use super::{bin, client_from, free_port};

const USERS: &str =
    "sensor:s3nsor-pass\ndashboard:d4sh-pass\nboltwatch:b0lt-pass\nrouter:r0uter-pass\n";

/// Router `i` of `eps`, from the deployed files; router 1 connects to router 0.
fn router(d: &Path, eps: &[String], i: usize) -> Proc {
    let p = |f: &str| d.join(f).display().to_string();
    let (ca, cert, key, users) = (
        p("tls/ca.pem"),
        p("tls/daemon.pem"),
        p("tls/daemon-key.pem"),
        p("users.txt"),
    );
    let base = localize(
        d,
        "zenohd.json5",
        &[
            ("/etc/zenoh/tls/ca.pem", &ca),
            ("/etc/zenoh/tls/router.pem", &cert),
            ("/etc/zenoh/tls/router-key.pem", &key),
            ("/etc/zenoh/users.txt", &users),
            ("tls/0.0.0.0:7447", &eps[i]),
        ],
    );
    // Both routers carry the test's one certificate (CN boltwatch-daemon).
    let connect = if i == 1 {
        format!("\"{}\"", eps[0])
    } else {
        String::new()
    };
    let fleet = localize(
        d,
        "fleet/router.json5",
        &[
            ("\"tls/router-a:7447\"", &connect),
            ("change-me-router", "r0uter-pass"),
            ("\"router-a\", \"router-b\"", "\"boltwatch-daemon\""),
        ],
    );
    let (b, f) = (
        d.join(format!("zenohd-{i}.json5")),
        d.join(format!("fleet-{i}.json5")),
    );
    std::fs::write(&b, base).unwrap();
    std::fs::write(&f, fleet).unwrap();
    let mut c = bin();
    c.args(["router", "--log-level", "warn", "--config"])
        .arg(&b)
        .arg("--config")
        .arg(&f);
    Proc::spawn(c, d.join(format!("router-{i}.log")))
}

/// A client session of `user` through router `ep` (the sensor's deployed file).
fn user_config(d: &Path, ep: &str, user: &str, password: &str) -> String {
    localize(
        d,
        "zenoh-sensor.json5",
        &[
            ("tls/boltwatch-host:7447", ep),
            ("user: \"sensor\"", &format!("user: \"{user}\"")),
            ("change-me-sensor", password),
            ("mode: \"peer\"", "mode: \"client\""),
        ],
    )
}

/// Daemon `id` as user `boltwatch`, a client of both routers; its configuration file.
fn daemon(site: &Site, id: &str) -> (Proc, std::path::PathBuf) {
    let d = &site.dir;
    let both = format!("{}\", \"{}", site.routers[0], site.routers[1]);
    let z = localize(
        d,
        "zenoh-daemon-client.json5",
        &[
            ("tls/zenoh-router:7447", &both),
            ("change-me-boltwatch", "b0lt-pass"),
        ],
    );
    std::fs::write(d.join("daemon-client.json5"), z).unwrap();
    let mut toml = format!(
        "{NO_CROSSCHECK}[zenoh]\nconfig_file = \"{}\"\n[daemon]\nstate = \"zenoh\"\n\
         state_dir = \"{}\"\n[fleet]\ngroup = \"g\"\nid = \"{id}\"\n[metrics]\nlisten = \"\"\n[console]\nlisten = \"\"\n",
        d.join("daemon-client.json5").display(),
        d.join(format!("state-{id}")).display()
    );
    for s in &site.structures {
        toml += &format!(
            "[[structures]]\nname = \"{s}\"\nmodel = \"{}\"\n",
            d.join(format!("{s}.toml")).display()
        );
    }
    let cfg = d.join(format!("{id}.toml"));
    std::fs::write(&cfg, toml).unwrap();
    let mut c = bin();
    c.env("BOLTWATCH__LOG__LEVEL", "info,zenoh=warn")
        .args(["run", "--config"])
        .arg(&cfg);
    (Proc::spawn(c, d.join(format!("{id}.log"))), cfg)
}

/// `boltwatch fleet status --json` with the daemons' configuration.
fn fleet_status(cfg: &Path) -> Value {
    let out = bin()
        .args(["fleet", "status", "--json", "--config"])
        .arg(cfg)
        .output()
        .unwrap();
    assert!(out.status.success(), "{out:?}");
    serde_json::from_slice(&out.stdout).unwrap()
}

/// The values stored under `structure`'s `@state/` that `z` can read.
fn state_seen(z: &zenoh::Session, structure: &str) -> Vec<String> {
    let replies = z
        .get(format!("boltwatch/{structure}/@state/**"))
        .target(zenoh::query::QueryTarget::All)
        .timeout(Duration::from_secs(2))
        .wait()
        .unwrap();
    let mut keys = Vec::new();
    while let Ok(r) = replies.recv() {
        if let Ok(s) = r.result() {
            keys.push(s.key_expr().to_string());
        }
    }
    keys
}

/// The group's members that `z` can see.
fn members_seen(z: &zenoh::Session) -> Vec<String> {
    let replies = z
        .liveliness()
        .get("boltwatch/@fleet/g/*")
        .timeout(Duration::from_secs(2))
        .wait()
        .unwrap();
    let mut ids = Vec::new();
    while let Ok(r) = replies.recv() {
        if let Ok(s) = r.result() {
            ids.push(s.key_expr().to_string());
        }
    }
    ids
}

#[test]
fn only_daemons_reach_the_fleets_state_and_membership() {
    let mut site = Site::new("fleet-acl", 2, 10, 2);
    let d = site.dir.clone();
    make_certs(&d);
    std::fs::write(d.join("users.txt"), USERS).unwrap();
    site.routers = (0..2)
        .map(|_| format!("tls/127.0.0.1:{}", free_port()))
        .collect();
    let eps = site.routers.clone();
    let _routers = [router(&d, &eps, 0), router(&d, &eps, 1)];
    std::thread::sleep(Duration::from_millis(500));
    let (d1, cfg) = daemon(&site, "d1");
    let (d2, _) = daemon(&site, "d2");

    // The daemons share the two structures, their records stored.
    let deadline = Instant::now() + Duration::from_secs(60);
    let view = loop {
        let v = fleet_status(&cfg);
        let owned = v["structures"]
            .as_array()
            .map_or(0, |l| l.iter().filter(|s| s["owner_live"] == true).count());
        if v["members"] == serde_json::json!(["d1", "d2"]) && owned == 2 {
            break v;
        }
        assert!(
            Instant::now() < deadline,
            "fleet status: {v:#}\n{}\n{}",
            d1.log(),
            d2.log()
        );
        std::thread::sleep(Duration::from_millis(500));
    };
    eprintln!("fleet under ACL: {view}");

    // The sensor's sets (through router 0) are tracked and reach the dashboard (through
    // router 1).
    let sensor_cfg = user_config(&d, &eps[0], "sensor", "s3nsor-pass");
    let dash_cfg = user_config(&d, &eps[1], "dashboard", "d4sh-pass");
    std::fs::write(d.join("sensor.json5"), &sensor_cfg).unwrap();
    let dashboard = client_from(&dash_cfg);
    let estimates = dashboard
        .declare_subscriber("boltwatch/*/stiffness")
        .with(zenoh::handlers::FifoChannel::new(1000))
        .wait()
        .unwrap();
    for s in &site.structures {
        let out = bin()
            .arg("publish")
            .arg(d.join(format!("{s}.mcap")))
            .arg("--zenoh-config")
            .arg(d.join("sensor.json5"))
            .args(["--rate", "0", "--wait", "10"])
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
    }
    let deadline = Instant::now() + Duration::from_secs(30);
    let mut heard = 0;
    while heard < 20 && Instant::now() < deadline {
        match estimates.try_recv() {
            Ok(Some(_)) => heard += 1,
            _ => std::thread::sleep(Duration::from_millis(20)),
        }
    }
    assert_eq!(heard, 20, "estimates heard by the dashboard");

    // A daemon's credentials read the state and see the members; the sensor's and the
    // dashboard's read nothing, forge nothing and join nothing.
    let daemon_z = client_from(&user_config(&d, &eps[1], "boltwatch", "b0lt-pass"));
    let s = &site.structures[0];
    assert!(
        state_seen(&daemon_z, s)
            .iter()
            .any(|k| k.ends_with("@state/owner")),
        "the daemons' user reads the owner record"
    );
    assert_eq!(members_seen(&daemon_z).len(), 2);
    let sensor = client_from(&sensor_cfg);
    for (who, z) in [("sensor", &sensor), ("dashboard", &dashboard)] {
        assert_eq!(state_seen(z, s), Vec::<String>::new(), "{who} read @state");
        assert_eq!(members_seen(z), Vec::<String>::new(), "{who} saw @fleet");
        let forged = format!(
            r#"{{"structure":"{s}","epoch":99,"owner":"{who}","released":false,"since":"2026-12-01T00:00:00Z"}}"#
        );
        z.put(format!("boltwatch/{s}/@state/owner"), forged)
            .wait()
            .unwrap();
        z.delete(format!("boltwatch/{s}/@state/**")).wait().unwrap();
        let _token = z
            .liveliness()
            .declare_token(format!("boltwatch/@fleet/g/{who}"))
            .wait()
            .unwrap();
        std::thread::sleep(Duration::from_secs(3));
        let v = fleet_status(&cfg);
        assert_eq!(
            v["members"],
            serde_json::json!(["d1", "d2"]),
            "{who} joined: {v:#}"
        );
        for line in v["structures"].as_array().unwrap() {
            assert!(
                line["epoch"].as_u64().unwrap() < 99,
                "{who} forged a record: {v:#}"
            );
        }
        let kept = state_seen(&daemon_z, s);
        assert!(
            kept.iter().any(|k| k.contains("@state/checkpoint/")),
            "{who} deleted the state: {kept:?}"
        );
    }
    for (id, p) in [("d1", &d1), ("d2", &d2)] {
        assert!(!p.log().contains("panicked"), "{id}:\n{}", p.log());
    }
}
