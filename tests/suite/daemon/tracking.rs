//! The daemon tracks what replay tracks, rejects what it must, and loses nothing on
//! SIGTERM or at a full queue.

use std::collections::BTreeMap;
use std::process::Command;
use std::time::{Duration, Instant};

use serde_json::Value;
use zenoh::Wait;

use super::console::{Browser, assert_browser_shows_the_alarm, connection_rows};
use super::*;
use crate::suite::common::python_venv;
use crate::suite::tracker::{make_scenario, make_scenario_with, payloads, tmp_dir};
use boltwatch::io::mcap::{ChannelSpec, McapWriter, read_all, read_modal_sets, topic};

/// Cross-checks every 400 sets (and not by time).
const CROSSCHECK_400: &str = "[tracker]\ncrosscheck_every_sets = 400\ncrosscheck_every_s = 0.0\n";
const CROSSCHECK_400_ENV: [(&str, &str); 2] = [
    ("BOLTWATCH__TRACKER__CROSSCHECK_EVERY_SETS", "400"),
    ("BOLTWATCH__TRACKER__CROSSCHECK_EVERY_S", "0"),
];

/// A loosening recording published over Zenoh gives the estimates, alerts and cross-checks
/// a replay of it gives, payload for payload; the status query reports the run; the
/// daemon's log replays to the same estimates; SIGTERM stops it cleanly.
#[test]
fn daemon_over_zenoh_gives_what_replay_gives() {
    let d = tmp_dir("daemon-replay");
    let rec = d.join("rec.mcap");
    make_scenario("loosening", 1200, 60.0, &rec);
    let mut daemon = Daemon::start(&d, "queue = 2000", CROSSCHECK_400);
    let s = client(&daemon.endpoint);
    let outputs = Outputs::subscribe(&s);
    wait_status(&s, Duration::from_secs(30), "the daemon to answer", |_| {
        true
    });
    // All but the last set; the console in a browser; then the last set, live.
    let said = run_ok(publish(
        &rec,
        &daemon.endpoint,
        &["--rate", "0", "--count", "1199"],
    ));
    assert!(said.contains("published 1199 modal sets"), "{said}");
    wait_status(&s, Duration::from_secs(300), "1199 sets tracked", |v| {
        v["sets"]["accepted"].as_u64().unwrap() >= 1199
    });
    let shot = d.join("console.png");
    let mut browser = Browser::open(&daemon.console, "/structure/lab-frame?window=all", &shot);
    eprintln!("the console's screenshot: {}", shot.display());
    assert_browser_shows_the_alarm(&browser);
    let said = run_ok(publish(
        &rec,
        &daemon.endpoint,
        &["--rate", "0", "--skip", "1199"],
    ));
    assert!(said.contains("published 1 modal sets"), "{said}");
    let live = browser.wait_text("sets", "1200");
    assert_eq!(
        live["ok"], true,
        "the page did not update: {}",
        live["text"]
    );
    assert_eq!(connection_rows(live["dom"].as_str().unwrap()).len(), 17);
    browser.assert_same_origin_and_clean(&live);
    drop(browser);
    let st = wait_status(&s, Duration::from_secs(300), "1200 sets tracked", |v| {
        v["sets"]["accepted"].as_u64().unwrap() + v["sets"]["rejected"].as_u64().unwrap() >= 1200
    });
    assert_eq!(st["sets"]["received"], 1200);
    assert_eq!(st["sets"]["accepted"], 1200);
    assert_eq!(st["sets"]["dropped"], 0);
    assert_eq!(st["schema"], "boltwatch.status.v1");

    let reference = replayed(&rec, &d.join("ref.mcap"), &CROSSCHECK_400_ENV);
    let want = |suffix| payloads(&reference, suffix);
    let mut got = BTreeMap::new();
    let deadline = Instant::now() + Duration::from_secs(120);
    loop {
        outputs.drain(&mut got);
        let n = |k: &str| got.get(k).map_or(0, Vec::len);
        if n("stiffness") == 1200 && n("crosscheck") == want("crosscheck").len() {
            break;
        }
        assert!(
            Instant::now() < deadline,
            "outputs missing: {:?}",
            got.iter().map(|(k, v)| (k, v.len())).collect::<Vec<_>>()
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    assert_eq!(
        got["stiffness"],
        want("stiffness"),
        "estimates differ from replay"
    );
    assert!(!want("alerts").is_empty(), "the recording raises alerts");
    assert_eq!(got["alerts"], want("alerts"), "alerts differ from replay");
    let mut cc = got["crosscheck"].clone();
    cc.sort_by_key(|v| v["time"].as_str().unwrap().to_string());
    assert_eq!(cc, want("crosscheck"), "cross-checks differ from replay");
    assert!(!got.contains_key("rejected"));
    // The status shows the last estimate and the alerts raised.
    assert_eq!(st["last_estimate"], *want("stiffness").last().unwrap());
    assert!(
        st["alerts"]
            .as_array()
            .unwrap()
            .iter()
            .any(|a| a["level"] == "alarm" && a["connection"] == "C1L@J1L"),
        "{:#}",
        st["alerts"]
    );
    // Metrics.
    let m = http_get(&daemon.metrics, "/metrics");
    assert!(
        m.contains("boltwatch_sets_processed_total{structure=\"lab-frame\"} 1200"),
        "{m}"
    );
    assert!(m.contains("boltwatch_update_seconds_count{structure=\"lab-frame\"} 1200"));
    assert!(m.contains("boltwatch_theta{structure=\"lab-frame\",parameter=\"C1L@J1L\"}"));
    assert_structure_metrics(&m, &st);
    super::monitoring::assert_monitoring_names_exposed_metrics(&m);
    assert_console_shows_the_alarm(&daemon.console);
    drop(outputs);
    drop(s);

    let exit = daemon.terminate();
    assert!(exit.success(), "{exit:?}; log:\n{}", daemon.log());
    let logs = daemon.log_files();
    assert_eq!(logs.len(), 1, "{logs:?}");
    assert_history_reads_the_log(&d.join("state/log"), &want("stiffness"), &want("alerts"));
    let again = replayed(&logs[0], &d.join("again.mcap"), &CROSSCHECK_400_ENV);
    assert_eq!(payloads(&again, "stiffness"), want("stiffness"));
    assert_eq!(
        payloads(&read_all(&logs[0]).unwrap(), "stiffness"),
        want("stiffness")
    );
}

/// The history read back from the daemon's log holds every estimate and alert, the last
/// estimate's values exactly (as f32), and comes from the cache the second time; a cache
/// bounded below one file's history keeps nothing.
fn assert_history_reads_the_log(dir: &std::path::Path, estimates: &[Value], alerts: &[Value]) {
    use boltwatch::daemon::history::Cache;
    let mut cache = Cache::new(64 << 20);
    let h = cache.history(dir, "lab-frame").unwrap();
    assert_eq!(h.samples().count(), estimates.len());
    assert_eq!(h.marks().count(), alerts.len());
    let last = estimates.last().unwrap();
    let l = h.names().iter().position(|n| n == "C1L@J1L").unwrap();
    let p = h.samples().last().unwrap().points[l];
    let c1 = &last["parameters"][l];
    assert_eq!(p.theta, c1["theta"].as_f64().unwrap() as f32);
    assert_eq!(
        p.upper95,
        c1["filtered"]["upper95"].as_f64().unwrap() as f32
    );
    let bytes = cache.bytes();
    assert!(bytes > 0);
    // Compared as printed: a baseline not yet set is NaN, which equals nothing.
    let same = |a: &boltwatch::daemon::history::Logged| format!("{a:?}") == format!("{h:?}");
    assert!(same(&cache.history(dir, "lab-frame").unwrap()));
    assert_eq!(cache.bytes(), bytes, "read from the cache");
    let mut tiny = Cache::new(bytes - 1);
    assert!(same(&tiny.history(dir, "lab-frame").unwrap()));
    assert_eq!(tiny.bytes(), 0, "evicted");
    let since = h.samples().nth_back(9).unwrap().time_ms;
    assert_eq!(h.samples_since(Some(since)).len(), 10);
}

/// The value of the metric line `name{labels}`.
fn metric(m: &str, name_labels: &str) -> Option<f64> {
    m.lines()
        .find_map(|l| l.strip_prefix(name_labels)?.strip_prefix(' '))
        .and_then(|v| v.trim().parse().ok())
}

/// The structure's state in the metrics equals the status's last estimate and alerts:
/// C1L@J1L in alarm at its filtered level and loss, a healthy connection at level 0.
fn assert_structure_metrics(m: &str, st: &Value) {
    let p = |name: &str| {
        st["last_estimate"]["parameters"]
            .as_array()
            .unwrap()
            .iter()
            .find(|p| p["name"] == name)
            .unwrap()
            .clone()
    };
    let labels = |c: &str| format!("{{structure=\"lab-frame\",parameter=\"{c}\"}}");
    let c1 = p("C1L@J1L");
    let get = |name: &str, c: &str| {
        metric(m, &format!("{name}{}", labels(c))).unwrap_or_else(|| panic!("{name} {c}: {m}"))
    };
    assert_eq!(get("boltwatch_alert_level", "C1L@J1L"), 2.0);
    assert_eq!(get("boltwatch_alert_level", "C2L@J2L"), 0.0);
    let close = |a: f64, b: &Value| (a - b.as_f64().unwrap()).abs() <= 1e-12 * a.abs().max(1.0);
    assert!(close(
        get("boltwatch_theta_filtered", "C1L@J1L"),
        &c1["filtered"]["level"]
    ));
    assert!(close(get("boltwatch_theta_std", "C1L@J1L"), &c1["std"]));
    let loss = get("boltwatch_loss", "C1L@J1L");
    // Against the expectation under the set's temperature (the default normalises).
    assert!(close(loss, &c1["normalised"]["loss"]), "{loss} {c1:#}");
    assert!(loss > 0.25, "an alarm is a loss over 25 %: {loss}");
    let eps = metric(m, "boltwatch_epsilon{structure=\"lab-frame\"}").unwrap();
    assert!(close(eps, &st["last_estimate"]["epsilon"]));
    let age = metric(m, "boltwatch_last_set_age_seconds{structure=\"lab-frame\"}").unwrap();
    assert!((0.0..600.0).contains(&age), "{age}");
}

/// A site whose thermometer is not in the box that identifies the modes: thirty days of
/// the seasonal scenario (120 sets) with the temperature as 715 hourly environment readings,
/// published over Zenoh. The daemon joins each set to its reading as replay does, estimate
/// for estimate, judging every set under a temperature; its log replays to the same.
#[test]
fn environment_readings_over_zenoh_are_joined_as_replay_joins_them() {
    let d = tmp_dir("daemon-environment");
    let rec = d.join("rec.mcap");
    make_scenario_with("seasonal", None, 30.0, true, &rec);
    let mut daemon = Daemon::start(&d, "queue = 2000", CROSSCHECK_400);
    let s = client(&daemon.endpoint);
    let outputs = Outputs::subscribe(&s);
    wait_status(&s, Duration::from_secs(30), "the daemon to answer", |_| {
        true
    });
    let said = run_ok(publish(&rec, &daemon.endpoint, &["--rate", "0"]));
    assert!(
        said.contains("published 120 modal sets (835 inputs)"),
        "{said}"
    );
    let reference = replayed(&rec, &d.join("ref.mcap"), &CROSSCHECK_400_ENV);
    let want = payloads(&reference, "stiffness");
    assert_eq!(want.len(), 120);
    let mut got = BTreeMap::new();
    let deadline = Instant::now() + Duration::from_secs(120);
    while got.get("stiffness").map_or(0, Vec::len) < 120 {
        assert!(Instant::now() < deadline, "estimates missing");
        outputs.drain(&mut got);
        std::thread::sleep(Duration::from_millis(50));
    }
    assert_eq!(got["stiffness"], want, "estimates differ from replay");
    assert!(!got.contains_key("rejected"), "{:?}", got.get("rejected"));
    for e in &want {
        let t = e["temperature_c"].as_f64();
        assert!(t.is_some_and(|t| (-40.0..50.0).contains(&t)), "{e:#}");
    }
    drop(outputs);
    drop(s);
    let exit = daemon.terminate();
    assert!(exit.success(), "{exit:?}; log:\n{}", daemon.log());
    let logs = daemon.log_files();
    let again = replayed(&logs[0], &d.join("again.mcap"), &CROSSCHECK_400_ENV);
    assert_eq!(
        payloads(&again, "stiffness"),
        want,
        "the log replays otherwise"
    );
}

/// A minimal HTTP GET on loopback: the whole response, whatever its status.
pub fn http_response(addr: &str, path: &str) -> String {
    use std::io::{Read, Write};
    let mut c = std::net::TcpStream::connect(addr).unwrap();
    write!(c, "GET {path} HTTP/1.1\r\nHost: {addr}\r\n\r\n").unwrap();
    let mut s = String::new();
    c.read_to_string(&mut s).unwrap();
    s
}

/// The console of a daemon fed the loosening recording: the overview lists the structure
/// with its alarm; its page has every connection's row, C1L@J1L first and in alarm, and
/// the chart; every response forbids other origins; an unknown structure, a path out of
/// the console, a query that is not a window and a 6,000-byte query are refused.
fn assert_console_shows_the_alarm(console: &str) {
    let home = http_get(console, "/");
    assert!(
        home.contains("content-security-policy: default-src 'none'"),
        "{home}"
    );
    assert!(
        home.contains(
            "<tr class=\"alarm\" id=\"s-lab-frame\"><td><a href=\"/structure/lab-frame\">"
        ),
        "{home}"
    );
    let page = http_get(console, "/structure/lab-frame?window=all");
    let rows: Vec<&str> = page.split("<tr class=").skip(1).collect();
    assert_eq!(rows.len(), 17, "a row per parameter");
    assert!(
        rows[0].starts_with("\"alarm\" id=\"c-C1L@J1L\""),
        "{}",
        rows[0]
    );
    assert!(page.contains("<svg") && page.contains(">lab-frame: C1L@J1L<"));
    for other in ["href=\"http", "src=\"http", "href=\"//", "src=\"//", "url("] {
        assert!(
            !page.contains(other),
            "a request to another origin: {other}"
        );
    }
    let long_query = format!("/structure/lab-frame?window={}", "9".repeat(6000));
    for (path, status) in [
        ("/structure/other", "404"),
        ("/structure/..%2F..%2Fetc%2Fpasswd", "404"),
        ("/../../etc/passwd", "404"),
        ("/structure/lab-frame?window=1y", "400"),
        ("/structure/lab-frame?window=24h&x=y", "400"),
        (long_query.as_str(), "400"),
    ] {
        let r = http_response(console, path);
        assert!(r.starts_with(&format!("HTTP/1.1 {status}")), "{path}: {r}");
    }
}

/// A minimal HTTP GET on loopback.
pub fn http_get(addr: &str, path: &str) -> String {
    use std::io::{Read, Write};
    let mut c = std::net::TcpStream::connect(addr).unwrap();
    write!(c, "GET {path} HTTP/1.1\r\nHost: {addr}\r\n\r\n").unwrap();
    let mut s = String::new();
    c.read_to_string(&mut s).unwrap();
    assert!(s.starts_with("HTTP/1.1 200"), "{s}");
    s
}

/// Garbage bytes, a wrong schema, a NaN frequency and a set of another structure sent over
/// Zenoh are each answered on `rejected` with the reason and field; the daemon keeps
/// tracking.
#[test]
fn malformed_payloads_over_zenoh_are_rejected_and_the_daemon_goes_on() {
    let d = tmp_dir("daemon-malformed");
    let rec = d.join("rec.mcap");
    make_scenario("healthy", 30, 1.5, &rec);
    let (sets, _) = read_modal_sets(&rec, &["lab-frame"]).unwrap();
    let mut daemon = Daemon::start(&d, "", "");
    let s = client(&daemon.endpoint);
    let outputs = Outputs::subscribe(&s);
    wait_status(&s, Duration::from_secs(30), "the daemon to answer", |_| {
        true
    });
    // A publisher that blocks rather than drops, once the daemon's subscriber is known.
    let publisher = s
        .declare_publisher(topic("lab-frame", "modal"))
        .congestion_control(zenoh::qos::CongestionControl::Block)
        .wait()
        .unwrap();
    let deadline = Instant::now() + Duration::from_secs(30);
    while !publisher.matching_status().wait().unwrap().matching() {
        assert!(
            Instant::now() < deadline,
            "the daemon's subscriber never matched"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    let put = |bytes: Vec<u8>| publisher.put(bytes).wait().unwrap();
    for (_, m) in &sets[..20] {
        put(m.data.clone());
    }
    // Re-deliveries (the same bytes again): one of a set handled long before, two of the
    // last one, likely in the same batch as it. None is logged or tracked again.
    for i in [5, 19, 19] {
        put(sets[i].1.data.clone());
    }
    let text = String::from_utf8(sets[20].1.data.clone()).unwrap();
    let mut nan: Value = serde_json::from_str(&text).unwrap();
    let f = nan["modes"][0]["frequency_hz"].as_f64().unwrap();
    let nan_text = text.replacen(&format!("{f}"), "NaN", 1);
    assert_ne!(nan_text, text);
    nan["structure"] = "other-frame".into();
    let bad: [(&str, Vec<u8>); 4] = [
        ("garbage", vec![0xff, 0xfe, 0x00, 0x13, 0x37]),
        (
            "schema",
            br#"{"schema": "boltwatch.modal_set.v0"}"#.to_vec(),
        ),
        ("NaN", nan_text.into_bytes()),
        ("structure", serde_json::to_vec(&nan).unwrap()),
    ];
    for (_, b) in &bad {
        put(b.clone());
    }
    for (_, m) in &sets[20..] {
        put(m.data.clone());
    }
    let st = wait_status(&s, Duration::from_secs(120), "34 sets handled", |v| {
        v["sets"]["accepted"].as_u64().unwrap() + v["sets"]["rejected"].as_u64().unwrap() >= 34
    });
    assert_eq!(st["sets"]["accepted"], 30);
    assert_eq!(st["sets"]["rejected"], 4);
    assert_eq!(st["sets"]["duplicates"], 3, "{st:#}");
    assert_eq!(st["wal"]["redeliveries"], 3, "{st:#}");
    assert_eq!(st["wal"]["sets"], 34, "{st:#}");
    let mut got = BTreeMap::new();
    let deadline = Instant::now() + Duration::from_secs(30);
    while got.get("rejected").map_or(0, Vec::len) < 4
        || got.get("stiffness").map_or(0, Vec::len) < 30
    {
        assert!(Instant::now() < deadline);
        std::thread::sleep(Duration::from_millis(20));
        outputs.drain(&mut got);
    }
    let rejected = &got["rejected"];
    assert_eq!(rejected.len(), 4);
    for (r, (what, _)) in rejected.iter().zip(&bad) {
        let reason = r["reason"].as_str().unwrap();
        assert!(!reason.is_empty(), "{what}: {r:#}");
        assert_eq!(r["schema"], "boltwatch.rejected.v1");
        println!("{what}: field {} — {reason}", r["field"]);
    }
    assert!(
        rejected[1]["field"].as_str().unwrap().contains("schema"),
        "{:#}",
        rejected[1]
    );
    assert!(
        rejected[2]["field"].as_str().unwrap().contains("frequency"),
        "{:#}",
        rejected[2]
    );
    assert!(
        rejected[3]["field"].as_str().unwrap().contains("structure"),
        "{:#}",
        rejected[3]
    );
    // Tracking went on across the rejections: the estimates equal a replay of the 30 good sets.
    let reference = replayed(&rec, &d.join("ref.mcap"), &[]);
    assert_eq!(got["stiffness"], payloads(&reference, "stiffness"));
    assert!(daemon.terminate().success());
    let logged: usize = daemon
        .log_files()
        .iter()
        .filter(|f| f.extension().is_some_and(|e| e == "mcap"))
        .map(|f| {
            let all = read_all(f).unwrap();
            all.iter()
                .filter(|m| m.topic == topic("lab-frame", "modal"))
                .count()
        })
        .sum();
    assert_eq!(logged, 34, "each set and each rejected input logged once");
}

/// SIGTERM while a publisher is mid-stream, then a restart: both runs exit cleanly, every
/// log file is complete and opens in the Python `mcap` reader, every set the daemon
/// received has exactly one estimate, no estimate appears twice, and the restarted
/// tracker goes on from the first run's state.
#[test]
fn sigterm_mid_stream_then_restart_loses_and_duplicates_nothing() {
    let d = tmp_dir("daemon-sigterm");
    let rec = d.join("rec.mcap");
    make_scenario("healthy", 600, 30.0, &rec);
    let mut daemon = Daemon::start(&d, "", "");
    let s = client(&daemon.endpoint);
    wait_status(&s, Duration::from_secs(30), "the daemon to answer", |_| {
        true
    });
    drop(s);
    let mut publisher = publish(&rec, &daemon.endpoint, &["--rate", "200", "--count", "400"])
        .spawn()
        .unwrap();
    std::thread::sleep(Duration::from_millis(1000));
    let exit = daemon.terminate();
    assert!(exit.success(), "{exit:?}; log:\n{}", daemon.log());
    let _ = publisher.wait();
    let first_logs = daemon.log_files();
    assert_eq!(first_logs.len(), 1, "{first_logs:?}");
    let ckpt: Value =
        serde_json::from_slice(&std::fs::read(d.join("state/lab-frame.checkpoint.json")).unwrap())
            .unwrap();
    let accepted_first = ckpt["state"]["accepted"].as_u64().unwrap();
    assert!(
        (50..400).contains(&accepted_first),
        "SIGTERM came mid-stream: {accepted_first} sets tracked"
    );

    let mut daemon = daemon.restart();
    let s = client(&daemon.endpoint);
    wait_status(&s, Duration::from_secs(30), "the restarted daemon", |_| {
        true
    });
    run_ok(publish(
        &rec,
        &daemon.endpoint,
        &["--rate", "0", "--skip", "400"],
    ));
    let st = wait_status(&s, Duration::from_secs(120), "200 more sets", |v| {
        v["sets"]["accepted"].as_u64().unwrap() >= accepted_first + 200
    });
    assert_eq!(
        st["sets"]["accepted"].as_u64().unwrap(),
        accepted_first + 200,
        "resumed count"
    );
    drop(s);
    assert!(daemon.terminate().success());

    let logs = daemon.log_files();
    assert_eq!(logs.len(), 2, "{logs:?}");
    assert!(
        logs.iter().all(|p| p.extension().unwrap() == "mcap"),
        "{logs:?}"
    );
    let mut inputs = Vec::new();
    let mut estimates = Vec::new();
    for f in &logs {
        let all = read_all(f).unwrap();
        let time = |v: &Value| {
            chrono::DateTime::parse_from_rfc3339(v["time"].as_str().unwrap())
                .unwrap()
                .to_utc()
        };
        inputs.extend(payloads(&all, "modal").iter().map(time));
        estimates.extend(payloads(&all, "stiffness").iter().map(time));
        assert!(payloads(&all, "rejected").is_empty());
    }
    assert_eq!(
        estimates.len(),
        inputs.len(),
        "one estimate per set received"
    );
    assert!(
        estimates == inputs,
        "one estimate per set received, in order"
    );
    assert_eq!(estimates.len() as u64, accepted_first + 200);
    let mut unique = estimates.clone();
    unique.dedup();
    assert_eq!(unique.len(), estimates.len(), "an estimate appears twice");
    // The Python reader opens both files, every message.
    let python = python_venv(
        "py-mcap-venv",
        "import mcap, zstandard",
        &["mcap==1.6.0", "zstandard==0.25.0"],
    );
    for f in &logs {
        let o = Command::new(&python)
            .args([
                "-c",
                "import sys; from mcap.reader import make_reader\n\
                 r = make_reader(open(sys.argv[1], 'rb'))\n\
                 print(sum(1 for _ in r.iter_messages()))",
            ])
            .arg(f)
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let n: usize = String::from_utf8_lossy(&o.stdout).trim().parse().unwrap();
        assert_eq!(n, read_all(f).unwrap().len(), "{}", f.display());
    }
}

/// 10,000 sets published as fast as the link takes them into a queue of 1,024: every set
/// is either tracked or counted as dropped (status, metrics, one `rejected` report per
/// batch), and the daemon's peak memory stays bounded.
#[test]
#[cfg_attr(
    not(feature = "slow-tests"),
    ignore = "slow tier: cargo test --features slow-tests"
)]
fn a_burst_larger_than_the_queue_is_tracked_or_counted() {
    let d = tmp_dir("daemon-burst");
    let small = d.join("small.mcap");
    make_scenario("healthy", 200, 10.0, &small);
    // 10,000 sets: the 200 restamped one minute apart.
    let (sets, _) = read_modal_sets(&small, &["lab-frame"]).unwrap();
    let rec = d.join("burst.mcap");
    {
        let mut w = McapWriter::create(
            &rec,
            &[ChannelSpec::for_structure("lab-frame", "modal").unwrap()],
        )
        .unwrap();
        let t0 = chrono::DateTime::parse_from_rfc3339("2026-01-01T00:00:00Z")
            .unwrap()
            .to_utc();
        for k in 0..10_000 {
            let mut v: Value = serde_json::from_slice(&sets[k % sets.len()].1.data).unwrap();
            let t = t0 + chrono::Duration::minutes(k as i64);
            v["time"] = boltwatch::contract::rfc3339(t).into();
            let ns = t.timestamp_nanos_opt().unwrap() as u64;
            w.write(
                &topic("lab-frame", "modal"),
                ns,
                &serde_json::to_vec(&v).unwrap(),
            )
            .unwrap();
        }
        w.finish().unwrap();
    }
    let mut daemon = Daemon::start(&d, "queue = 1024", "");
    let s = client(&daemon.endpoint);
    let outputs = Outputs::subscribe(&s);
    wait_status(&s, Duration::from_secs(30), "the daemon to answer", |_| {
        true
    });
    let said = run_ok(publish(&rec, &daemon.endpoint, &["--rate", "0"]));
    println!("{said}");
    let st = wait_status(&s, Duration::from_secs(300), "the burst handled", |v| {
        let n = |k: &str| v["sets"][k].as_u64().unwrap();
        n("received") == 10_000
            && v["queue"]["depth"] == 0
            && n("accepted") + n("rejected") + n("dropped") == 10_000
    });
    let dropped = st["sets"]["dropped"].as_u64().unwrap();
    let hwm_kib = vm_hwm_kib(daemon.pid());
    println!(
        "burst of 10,000: {} tracked, {dropped} dropped; daemon peak RSS {:.1} MiB",
        st["sets"]["accepted"],
        hwm_kib as f64 / 1024.0
    );
    // Reported: the rejected reports add up to the dropped count.
    let mut got = BTreeMap::new();
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        outputs.drain(&mut got);
        let reported: u64 = got.get("rejected").map_or(0, |r| {
            r.iter().map(|x| x["dropped"].as_u64().unwrap_or(0)).sum()
        });
        if reported == dropped {
            break;
        }
        assert!(
            Instant::now() < deadline,
            "dropped {dropped}, reported {reported}"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    let m = http_get(&daemon.metrics, "/metrics");
    assert!(
        m.contains(&format!(
            "boltwatch_sets_dropped_total{{structure=\"lab-frame\"}} {dropped}"
        )),
        "{m}"
    );
    // Bounded: the queue holds at most 1,024 payloads of ~8 KB; the model, solver and
    // Zenoh buffers need a few tens of MiB. 512 MiB would mean something grows with the
    // burst.
    assert!(hwm_kib < 512 * 1024, "peak RSS {hwm_kib} KiB");
    drop(outputs);
    drop(s);
    assert!(daemon.terminate().success());
}

/// Raw data live: 3 bursts of 30 s of simulated accelerations (42 channels at 500 Hz, in
/// one-second `boltwatch.accel.v1` blocks) published on `boltwatch/lab-frame/accel` are
/// windowed and identified by the daemon, which publishes each window's modal set on
/// `…/modal` and tracks it: the modal sets and estimates are those a replay of the same
/// recording gives, payload for payload. A block sent twice is rejected (field `start`)
/// and the window goes on; the daemon's log holds the identified sets as its inputs.
#[test]
fn raw_accelerations_over_zenoh_are_identified_and_tracked() {
    let d = tmp_dir("daemon-accel");
    let rec = d.join("accel.mcap");
    let run = bin()
        .args(["scenario", "healthy", "--accel", "30", "--rate", "500"])
        .args(["--sets", "3", "--days", "1", "-o"])
        .arg(&rec)
        .output()
        .unwrap();
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let identify = "[identify]\nwindow_s = 30.0\n";
    let mut daemon = Daemon::start(&d, "", identify);
    let s = client(&daemon.endpoint);
    let outputs = Outputs::subscribe(&s);
    let modal = s
        .declare_subscriber(topic("lab-frame", "modal"))
        .with(zenoh::handlers::FifoChannel::new(1000))
        .wait()
        .unwrap();
    wait_status(&s, Duration::from_secs(30), "the daemon to answer", |_| {
        true
    });
    let blocks: Vec<_> = read_all(&rec)
        .unwrap()
        .into_iter()
        .filter(|m| m.topic == topic("lab-frame", "accel"))
        .collect();
    assert_eq!(blocks.len(), 90);
    let publisher = s
        .declare_publisher(topic("lab-frame", "accel"))
        .congestion_control(zenoh::qos::CongestionControl::Block)
        .wait()
        .unwrap();
    for (k, b) in blocks.iter().enumerate() {
        publisher.put(b.data.clone()).wait().unwrap();
        if k == 10 {
            publisher.put(b.data.clone()).wait().unwrap();
        }
    }
    let mut got = BTreeMap::new();
    let mut sets: Vec<Value> = Vec::new();
    let deadline = Instant::now() + Duration::from_secs(180);
    loop {
        outputs.drain(&mut got);
        while let Ok(Some(sample)) = modal.try_recv() {
            sets.push(serde_json::from_slice(&sample.payload().to_bytes()).unwrap());
        }
        let n = |k: &str| got.get(k).map_or(0, Vec::len);
        if n("stiffness") == 3 && sets.len() == 3 && n("rejected") == 1 {
            break;
        }
        assert!(
            Instant::now() < deadline,
            "outputs missing: {} modal sets, {:?}; log:\n{}",
            sets.len(),
            got.iter().map(|(k, v)| (k, v.len())).collect::<Vec<_>>(),
            daemon.log()
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    assert_eq!(
        got["rejected"][0]["field"], "start",
        "{:#}",
        got["rejected"][0]
    );
    let settings = boltwatch::settings::Settings::load_with_env(
        None,
        [(
            "BOLTWATCH__IDENTIFY__WINDOW_S".to_string(),
            "30".to_string(),
        )],
    )
    .unwrap();
    // As the replay command and the daemon run their numerics: sequentially (faer's
    // parallel SVD rounds differently).
    boltwatch::core::sequential_numerics();
    let reference = replayed_with(&rec, &d.join("ref.mcap"), settings);
    let brief = |v: &[Value]| -> Vec<String> {
        v.iter()
            .map(|s| format!("{} {}", s["time"], s["modes"][0]["frequency_hz"]))
            .collect()
    };
    let want = payloads(&reference, "modal");
    assert_eq!(brief(&sets), brief(&want));
    assert!(sets == want, "modal sets differ from replay");
    assert_eq!(
        got["stiffness"],
        payloads(&reference, "stiffness"),
        "estimates differ from replay"
    );
    drop(publisher);
    drop(modal);
    drop(outputs);
    drop(s);
    let exit = daemon.terminate();
    assert!(exit.success(), "{exit:?}; log:\n{}", daemon.log());
    let logs = daemon.log_files();
    let inputs: usize = logs
        .iter()
        .map(|f| payloads(&read_all(f).unwrap(), "modal").len())
        .sum();
    assert_eq!(inputs, 3, "the identified sets are the log's inputs");
}
