//! The daemon in the field (issue 23): hostile inputs over real Zenoh, and SIGKILL at
//! random points of a publish with an immediate restart, from `boltwatch publish` and from
//! a Python sensor with zenoh-ext's advanced publisher.

use std::collections::BTreeMap;
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use rand::{Rng, SeedableRng};
use serde_json::{Value, json};
use zenoh::Wait;

use super::*;
use crate::suite::common::python_venv;
use crate::suite::tracker::{make_scenario, tmp_dir};
use boltwatch::io::mcap::{read_all, read_modal_sets};

/// The modal-set payloads of a recording, in order.
fn modal_payloads(rec: &Path) -> Vec<Vec<u8>> {
    read_modal_sets(rec, &["lab-frame"])
        .unwrap()
        .0
        .into_iter()
        .map(|(_, m)| m.data)
        .collect()
}

/// Each hostile input of the issue (a set stamped in 2300, one two days ahead of the
/// daemon's clock, a 16 MiB payload, a frequency CoV of 1e-300, an all-zero shape) is
/// rejected on `rejected` with its field named; the daemon stays up and tracks the later
/// sets; the checkpoint holds nothing non-finite; a restart on the same state goes on.
#[test]
fn hostile_inputs_are_rejected_by_field_and_the_daemon_goes_on() {
    let d = tmp_dir("daemon-hostile");
    let rec = d.join("rec.mcap");
    make_scenario("healthy", 30, 1.0, &rec);
    let sets = modal_payloads(&rec);
    let mut daemon = Daemon::start(&d, "", "");
    let s = client(&daemon.endpoint);
    wait_status(&s, Duration::from_secs(30), "the daemon to answer", |_| {
        true
    });
    let outputs = Outputs::subscribe(&s);
    // Blocking, as a sensor publishes: with Zenoh's default (drop), the client itself may
    // drop the 16 MiB message's fragments, and the sets after it, on a loaded machine.
    let publisher = s
        .declare_publisher(topic("lab-frame", "modal"))
        .congestion_control(zenoh::qos::CongestionControl::Block)
        .wait()
        .unwrap();
    let put = |bytes: Vec<u8>| publisher.put(bytes).wait().unwrap();
    for p in &sets[..10] {
        put(p.clone());
    }
    wait_status(&s, Duration::from_secs(60), "10 sets", |v| {
        v["sets"]["accepted"] == 10
    });

    let set = |k: usize| -> Value { serde_json::from_slice(&sets[k]).unwrap() };
    let mut hostile = Vec::new();
    let mut v = set(10);
    v["time"] = json!("2300-01-01T00:00:00Z");
    hostile.push((serde_json::to_vec(&v).unwrap(), "time", "outside the range"));
    let mut v = set(10);
    v["time"] = json!((chrono::Utc::now() + chrono::TimeDelta::days(2)).to_rfc3339());
    hostile.push((
        serde_json::to_vec(&v).unwrap(),
        "time",
        "ahead of the receiver's clock",
    ));
    let mut v = set(10);
    v["source"] = json!("x".repeat(16 << 20));
    hostile.push((
        serde_json::to_vec(&v).unwrap(),
        "payload",
        "exceeds the limit",
    ));
    let mut v = set(10);
    v["modes"][0]["frequency_cov"] = json!(1e-300);
    hostile.push((
        serde_json::to_vec(&v).unwrap(),
        "modes[0].frequency_cov",
        "below the floor",
    ));
    let mut v = set(10);
    let n = v["modes"][0]["shape"].as_array().unwrap().len();
    v["modes"][0]["shape"] = json!(vec![0.0; n]);
    hostile.push((
        serde_json::to_vec(&v).unwrap(),
        "modes[0].shape",
        "all measured entries are zero",
    ));
    for (payload, _, _) in &hostile {
        put(payload.clone());
    }
    for p in &sets[10..] {
        put(p.clone());
    }
    let st = wait_status(&s, Duration::from_secs(60), "30 sets", |v| {
        v["sets"]["accepted"] == 30 && v["sets"]["rejected"] == 5
    });
    let ms = |t: &Value| {
        chrono::DateTime::parse_from_rfc3339(t.as_str().unwrap())
            .unwrap()
            .timestamp_millis()
    };
    assert_eq!(
        ms(&st["last_set_time"]),
        ms(&set(29)["time"]),
        "neither the 2300 nor the two-days-ahead set became the last accepted time"
    );
    std::thread::sleep(Duration::from_millis(300));
    let mut got = BTreeMap::new();
    outputs.drain(&mut got);
    let rejected = got.remove("rejected").unwrap_or_default();
    assert_eq!(rejected.len(), 5, "{rejected:#?}");
    for ((_, field, needle), r) in hostile.iter().zip(&rejected) {
        assert_eq!(r["field"], *field, "{r:#}");
        assert!(r["reason"].as_str().unwrap().contains(needle), "{r:#}");
        assert!(r["reason"].as_str().unwrap().len() <= 512);
        assert!(r["payload"].as_str().unwrap().len() <= 4096);
        assert!(r["id"].as_str().unwrap().starts_with("lab-frame/"), "{r:#}");
    }
    assert_eq!(
        rejected[2]["payload_bytes"].as_u64().unwrap() as usize,
        hostile[2].0.len()
    );
    assert_eq!(got["stiffness"].len(), 30);

    assert!(daemon.terminate().success(), "{}", daemon.log());
    let ckpt = std::fs::read_to_string(d.join("state/lab-frame.checkpoint.json")).unwrap();
    let v: Value = serde_json::from_str(&ckpt).unwrap();
    assert!(v["state"]["epsilon"].as_f64().is_some_and(f64::is_finite));
    let mut daemon = daemon.restart();
    let s = client(&daemon.endpoint);
    let st = wait_status(&s, Duration::from_secs(30), "the restarted daemon", |_| {
        true
    });
    assert_eq!(st["sets"]["accepted"], 30, "resumed from the checkpoint");
    drop(s);
    assert!(daemon.terminate().success(), "{}", daemon.log());
}

/// SIGKILL at 20 random points of a 400-set publish at 200 sets/s, each followed by an
/// immediate restart on the same state. `start` launches the sensor side (given the
/// daemon's endpoint, the recording and the test directory), which must exit 0 once the
/// daemon reports the last set taken. In the union of the daemon's logs every set has an
/// estimate, and a set estimated more than once has byte-identical estimates (hence the
/// same id).
fn sigkill_storm(name: &str, start: impl FnOnce(&str, &Path, &Path) -> Command) {
    let d = tmp_dir(name);
    let rec = d.join("rec.mcap");
    make_scenario("healthy", 400, 4.0, &rec);
    let mut daemon = Daemon::start(&d, "", "");
    let s = client(&daemon.endpoint);
    wait_status(&s, Duration::from_secs(30), "the daemon to answer", |_| {
        true
    });
    let mut sensor = start(&daemon.endpoint, &rec, &d)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    wait_status(&s, Duration::from_secs(60), "the first set", |v| {
        v["sets"]["received"].as_u64() > Some(0)
    });
    drop(s);
    let t0 = Instant::now();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(23);
    let mut kills: Vec<f64> = (0..20).map(|_| rng.random_range(0.0..2.0)).collect();
    kills.sort_by(f64::total_cmp);
    for at in kills {
        std::thread::sleep(
            (t0 + Duration::from_secs_f64(at)).saturating_duration_since(Instant::now()),
        );
        daemon.child.kill().unwrap();
        daemon.child.wait().unwrap();
        daemon = daemon.restart();
    }
    let deadline = Instant::now() + Duration::from_secs(180);
    while sensor.try_wait().unwrap().is_none() {
        assert!(
            Instant::now() < deadline,
            "the sensor side did not finish; daemon log:\n{}",
            daemon.log()
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    let out = sensor.wait_with_output().unwrap();
    assert!(
        out.status.success(),
        "sensor side: {}\n{}\ndaemon log:\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr),
        daemon.log()
    );
    let s = client(&daemon.endpoint);
    let st = wait_status(&s, Duration::from_secs(60), "400 sets", |v| {
        v["sets"]["accepted"] == 400
    });
    drop(s);
    assert!(daemon.terminate().success(), "{}", daemon.log());

    let mut estimates: BTreeMap<i64, Vec<Vec<u8>>> = BTreeMap::new();
    let mut inputs = 0;
    for f in daemon.log_files() {
        if f.extension().is_none_or(|e| e != "mcap") {
            continue;
        }
        for m in read_all(&f).unwrap() {
            if m.topic == topic("lab-frame", "modal") {
                inputs += 1;
            }
            if m.topic == topic("lab-frame", "stiffness") {
                let v: Value = serde_json::from_slice(&m.data).unwrap();
                let t = chrono::DateTime::parse_from_rfc3339(v["time"].as_str().unwrap()).unwrap();
                estimates
                    .entry(t.timestamp_millis())
                    .or_default()
                    .push(m.data);
            }
        }
    }
    let mut twice = 0;
    for p in modal_payloads(&rec) {
        let v: Value = serde_json::from_slice(&p).unwrap();
        let t = chrono::DateTime::parse_from_rfc3339(v["time"].as_str().unwrap()).unwrap();
        let e = estimates
            .get(&t.timestamp_millis())
            .unwrap_or_else(|| panic!("set {} has no estimate in the logs", v["time"]));
        assert!(
            e.iter().all(|x| x == &e[0]),
            "set {}: estimates differ",
            v["time"]
        );
        twice += usize::from(e.len() > 1);
    }
    let files = daemon.log_files().len();
    eprintln!(
        "{name}: 400 sets, 20 SIGKILLs: {files} log files, {} inputs logged, {} sets estimated more than once (identical); last daemon: {} duplicates skipped, {} replayed",
        inputs, twice, st["sets"]["duplicates"], st["sets"]["replayed"]
    );
}

#[test]
#[cfg_attr(
    not(feature = "slow-tests"),
    ignore = "slow tier: cargo test --features slow-tests"
)]
fn sigkill_storm_with_boltwatch_publish_loses_nothing() {
    sigkill_storm("daemon-storm-publish", |endpoint, rec, _| {
        let mut c = bin();
        c.arg("publish")
            .arg(rec)
            .args(["--connect", endpoint, "--rate", "200", "--wait", "120"]);
        c
    });
}

#[test]
#[cfg_attr(
    not(feature = "slow-tests"),
    ignore = "slow tier: cargo test --features slow-tests"
)]
fn sigkill_storm_with_a_python_advanced_publisher_loses_nothing() {
    let python = python_venv(
        "py-zenoh-venv",
        "import zenoh.ext",
        &["eclipse-zenoh==1.10.2"],
    );
    sigkill_storm("daemon-storm-python", |endpoint, rec, d| {
        let lines: Vec<String> = modal_payloads(rec)
            .into_iter()
            .map(|p| String::from_utf8(p).unwrap())
            .collect();
        let jsonl = d.join("sets.jsonl");
        std::fs::write(&jsonl, lines.join("\n") + "\n").unwrap();
        let script =
            Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/python/advanced_publisher.py");
        let mut c = Command::new(&python);
        c.arg(script).arg(endpoint).arg(&jsonl).args(["200", "120"]);
        c
    });
}

/// systemd's protocol (Type=notify, WatchdogSec): the daemon sends READY=1 once it
/// watches its structures and WATCHDOG=1 every half period while its tracking loops go
/// round, and STOPPING=1 at SIGTERM.
#[test]
fn the_daemon_notifies_systemd_and_feeds_its_watchdog() {
    use std::os::unix::net::UnixDatagram;
    let d = tmp_dir("daemon-sdnotify");
    let path = d.join("notify.sock");
    let sock = UnixDatagram::bind(&path).unwrap();
    sock.set_read_timeout(Some(Duration::from_secs(30)))
        .unwrap();
    let socket = path.display().to_string();
    let mut daemon = Daemon::start_env(
        &d,
        &[
            ("NOTIFY_SOCKET", socket.as_str()),
            ("WATCHDOG_USEC", "400000"),
        ],
    );
    let mut got = Vec::new();
    let mut buf = [0u8; 256];
    let start = Instant::now();
    while got
        .iter()
        .filter(|m: &&String| m.contains("WATCHDOG=1"))
        .count()
        < 3
    {
        let n = sock.recv(&mut buf).expect("a notification within 30 s");
        got.push(String::from_utf8_lossy(&buf[..n]).into_owned());
    }
    assert!(got[0].contains("READY=1"), "{got:?}");
    // Three pings, 0.2 s apart, within about a second of readiness.
    assert!(start.elapsed() < Duration::from_secs(20), "{got:?}");
    assert!(daemon.terminate().success(), "{}", daemon.log());
    let mut rest = Vec::new();
    sock.set_read_timeout(Some(Duration::from_millis(500)))
        .unwrap();
    while let Ok(n) = sock.recv(&mut buf) {
        rest.push(String::from_utf8_lossy(&buf[..n]).into_owned());
    }
    assert!(rest.iter().any(|m| m.contains("STOPPING=1")), "{rest:?}");
}

/// A subscriber that stops reading (a Python client, SIGSTOPped) holds up the daemon's
/// publications at most `zenoh.block_timeout_s` (here 1 s): then Zenoh closes its link and
/// tracking goes on; the MCAP log still gets every output.
#[test]
#[cfg_attr(
    not(feature = "slow-tests"),
    ignore = "slow tier: cargo test --features slow-tests"
)]
fn a_subscriber_that_stops_reading_cannot_stall_tracking() {
    let d = tmp_dir("daemon-stalled-subscriber");
    let port = free_port();
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let zenoh = format!("listen = [\"{endpoint}\"]\nblock_timeout_s = 1.0");
    let mut daemon = Daemon::start_with(&d, &zenoh, endpoint.clone(), "", "");
    let s = client(&daemon.endpoint);
    wait_status(&s, Duration::from_secs(30), "the daemon to answer", |_| {
        true
    });
    let python = python_venv("py-zenoh-venv", "import zenoh", &["eclipse-zenoh==1.10.2"]);
    let script = format!(
        r#"
import json, sys, time, zenoh
c = zenoh.Config()
c.insert_json5("mode", '"peer"')
c.insert_json5("connect/endpoints", json.dumps(["{endpoint}"]))
c.insert_json5("listen/endpoints", "[]")
c.insert_json5("scouting/multicast/enabled", "false")
s = zenoh.open(c)
sub = s.declare_subscriber("boltwatch/lab-frame/rejected", lambda sample: None)
print("ready", flush=True)
time.sleep(600)
"#
    );
    let mut slow = Command::new(&python)
        .args(["-c", &script])
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let mut line = String::new();
    std::io::BufRead::read_line(
        &mut std::io::BufReader::new(slow.stdout.as_mut().unwrap()),
        &mut line,
    )
    .unwrap();
    assert_eq!(line.trim(), "ready");
    std::thread::sleep(Duration::from_millis(500));
    unsafe {
        libc::kill(slow.id() as i32, libc::SIGSTOP);
    }
    // 20,000 rejected payloads of 8 KiB, in chunks of 500 (the queue holds 1,024): each is
    // answered on `rejected` with a 4 KiB echo, 80 MiB in all, far more than the stopped
    // subscriber's socket buffers hold. The longest wait for a chunk to be handled is the
    // stall.
    let n = 20_000u64;
    let publisher = s
        .declare_publisher(topic("lab-frame", "modal"))
        .congestion_control(zenoh::qos::CongestionControl::Block)
        .wait()
        .unwrap();
    let t0 = Instant::now();
    let mut longest = Duration::ZERO;
    let mut st = Value::Null;
    for chunk in 0..n / 500 {
        let c0 = Instant::now();
        for k in chunk * 500..(chunk + 1) * 500 {
            let payload = format!(
                "{{\"schema\":\"not-a-modal-set\",\"k\":{k},\"pad\":\"{}\"}}",
                "p".repeat(8192)
            );
            publisher.put(payload).wait().unwrap();
        }
        let want = (chunk + 1) * 500;
        st = wait_status(&s, Duration::from_secs(60), "a chunk handled", |v| {
            v["sets"]["rejected"].as_u64().unwrap_or(0) + v["sets"]["dropped"].as_u64().unwrap_or(0)
                >= want
        });
        longest = longest.max(c0.elapsed());
    }
    let took = t0.elapsed();
    unsafe {
        libc::kill(slow.id() as i32, libc::SIGKILL);
    }
    let _ = slow.wait();
    drop(s);
    assert!(daemon.terminate().success(), "{}", daemon.log());
    let (mut logged, mut reported_dropped) = (0, 0);
    for f in daemon.log_files() {
        if f.extension().is_some_and(|e| e == "mcap") {
            for m in read_all(&f).unwrap() {
                if m.topic == topic("lab-frame", "rejected") {
                    let v: Value = serde_json::from_slice(&m.data).unwrap();
                    match v["dropped"].as_u64() {
                        Some(k) => reported_dropped += k,
                        None => logged += 1,
                    }
                }
            }
        }
    }
    eprintln!(
        "stalled subscriber: {n} rejections in {:.1} s, longest chunk of 500 {:.2} s; dropped {}, publish errors {}",
        took.as_secs_f64(),
        longest.as_secs_f64(),
        st["sets"]["dropped"],
        st["publish_errors"]
    );
    assert_eq!(
        logged,
        st["sets"]["rejected"].as_u64().unwrap(),
        "the log has every output"
    );
    assert_eq!(
        reported_dropped,
        st["sets"]["dropped"].as_u64().unwrap(),
        "every drop reported"
    );
    assert_eq!(
        st["sets"]["dropped"], 0,
        "nothing dropped: the stall is bounded"
    );
    assert!(
        longest < Duration::from_secs(4),
        "tracking stalled {longest:?} on a subscriber that stopped reading (bound: 1 s)"
    );
}
