//! The fleet under load (not a criterion benchmark: one long run, figures printed): two
//! `boltwatch router`s, three daemons sharing STRUCTURES copies of the lab frame, one
//! sensor process publishing a set per structure per second for SECONDS seconds. Prints
//! the latency from a set's publication to its estimate (p50, p99), each daemon's CPU, the
//! traffic into the state storage, then kills the busiest daemon and prints how long its
//! structures took to be tracked again.
//!
//! `cargo bench --bench fleet` (defaults: 100 structures, 300 s);
//! `BOLTWATCH_BENCH_STRUCTURES=20 BOLTWATCH_BENCH_SECONDS=30 cargo bench --bench fleet`.

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use boltwatch::daemon::fleet::rendezvous;
use boltwatch::io::mcap::{ChannelSpec, McapWriter, read_all};
use serde_json::Value;
use zenoh::Wait;

fn env_or(key: &str, default: usize) -> usize {
    std::env::var(key)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

fn bin() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_boltwatch"));
    c.stdout(Stdio::null());
    c
}

fn port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// Processes killed on drop.
struct Procs(Vec<Child>);

impl Drop for Procs {
    fn drop(&mut self) {
        for c in &mut self.0 {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

/// A process's resident memory (MB).
fn rss_mb(pid: u32) -> f64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap_or_default();
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<f64>().ok())
        .map_or(0.0, |kb| kb / 1e3)
}

/// CPU seconds (user + system) a process has used.
fn cpu_s(pid: u32) -> f64 {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).unwrap_or_default();
    let after = stat.rsplit(')').next().unwrap_or_default();
    let f: Vec<&str> = after.split_whitespace().collect();
    let ticks = |i: usize| f.get(i).and_then(|v| v.parse::<f64>().ok()).unwrap_or(0.0);
    // Fields 14 and 15 (utime, stime) are at 11 and 12 after the command name.
    (ticks(11) + ticks(12)) / 100.0
}

/// `n` lab-frame copies with `sets` healthy sets each, merged into one recording in time
/// order; the model files and the merged recording.
fn site(dir: &Path, n: usize, sets: usize) -> (Vec<(String, PathBuf)>, PathBuf) {
    let lab = std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("config/models/lab-frame.toml"),
    )
    .unwrap();
    let mut models = Vec::new();
    let mut all = Vec::new();
    for i in 0..n {
        let s = format!("load-{i:03}");
        let model = dir.join(format!("{s}.toml"));
        std::fs::write(
            &model,
            lab.replacen("name = \"lab-frame\"", &format!("name = \"{s}\""), 1),
        )
        .unwrap();
        let rec = dir.join(format!("{s}.mcap"));
        let st = bin()
            .args([
                "scenario",
                "healthy",
                "--sets",
                &sets.to_string(),
                "--days",
                "30",
            ])
            .arg("--model")
            .arg(&model)
            .args(["--seed", &(i + 1).to_string(), "-o"])
            .arg(&rec)
            .status()
            .unwrap();
        assert!(st.success());
        all.extend(
            read_all(&rec)
                .unwrap()
                .into_iter()
                .filter(|m| m.topic.ends_with("/modal")),
        );
        models.push((s, model));
    }
    all.sort_by_key(|m| m.log_time);
    let specs: Vec<ChannelSpec> = models
        .iter()
        .map(|(s, _)| ChannelSpec::for_structure(s, "modal").unwrap())
        .collect();
    let merged = dir.join("all.mcap");
    let mut w = McapWriter::create(&merged, &specs).unwrap();
    for m in &all {
        w.copy(m).unwrap();
    }
    w.finish().unwrap();
    (models, merged)
}

fn daemon_config(
    dir: &Path,
    id: &str,
    routers: &[String],
    models: &[(String, PathBuf)],
) -> PathBuf {
    let mut t = format!(
        "[tracker]\ncrosscheck_every_sets = 100000\ncrosscheck_every_s = 0.0\n\
         [log]\nlevel = \"warn\"\n[zenoh]\nmode = \"client\"\nlisten = []\nconnect = {routers:?}\n\
         [daemon]\nstate = \"zenoh\"\nstate_dir = \"{}\"\n[fleet]\ngroup = \"load\"\nid = \"{id}\"\n\
         [metrics]\nlisten = \"\"\n[console]\nlisten = \"\"\n",
        dir.join(format!("state-{id}")).display()
    );
    for (s, m) in models {
        t += &format!(
            "[[structures]]\nname = \"{s}\"\nmodel = \"{}\"\n",
            m.display()
        );
    }
    let p = dir.join(format!("{id}.toml"));
    std::fs::write(&p, t).unwrap();
    p
}

/// What the observer heard: each set's publication and estimate times, the state traffic,
/// and the owner records.
#[derive(Default)]
struct Heard {
    published: HashMap<(String, i64), Instant>,
    estimated: HashMap<(String, i64), Instant>,
    state_puts: u64,
    state_bytes: u64,
    owners: BTreeMap<String, (String, Instant)>,
}

fn structure_of(key: &str) -> String {
    key.split('/').nth(1).unwrap_or_default().to_string()
}

fn observe(
    z: &zenoh::Session,
    heard: std::sync::Arc<std::sync::Mutex<Heard>>,
) -> Vec<zenoh::pubsub::Subscriber<()>> {
    let mut subs = Vec::new();
    for (ke, kind) in [
        ("boltwatch/*/modal", 0),
        ("boltwatch/*/stiffness", 1),
        ("boltwatch/*/@state/**", 2),
    ] {
        let h = heard.clone();
        subs.push(
            z.declare_subscriber(ke)
                .callback(move |s| {
                    let now = Instant::now();
                    let key = s.key_expr().as_str().to_string();
                    let bytes = s.payload().to_bytes();
                    let mut h = h.lock().unwrap();
                    if kind == 2 {
                        h.state_puts += 1;
                        h.state_bytes += bytes.len() as u64;
                        if key.ends_with("/@state/owner")
                            && let Ok(v) = serde_json::from_slice::<Value>(&bytes)
                        {
                            let owner = v["owner"].as_str().unwrap_or_default().to_string();
                            h.owners.insert(structure_of(&key), (owner, now));
                        }
                        return;
                    }
                    let Ok(v) = serde_json::from_slice::<Value>(&bytes) else {
                        return;
                    };
                    // The set's time, as the modal set and its estimate each format it.
                    let t = v["time"]
                        .as_str()
                        .and_then(|t| chrono::DateTime::parse_from_rfc3339(t).ok());
                    let id = (structure_of(&key), t.map_or(0, |t| t.timestamp_millis()));
                    if kind == 0 {
                        h.published.entry(id).or_insert(now);
                    } else {
                        h.estimated.entry(id).or_insert(now);
                    }
                })
                .wait()
                .unwrap(),
        );
    }
    subs
}

/// Each structure's owner, from the records in the storages.
fn stored_owners(z: &zenoh::Session) -> BTreeMap<String, String> {
    let replies = z
        .get("boltwatch/*/@state/owner")
        .target(zenoh::query::QueryTarget::All)
        .timeout(Duration::from_secs(3))
        .wait()
        .unwrap();
    let mut out = BTreeMap::new();
    while let Ok(r) = replies.recv() {
        if let Ok(s) = r.result()
            && let Ok(v) = serde_json::from_slice::<Value>(&s.payload().to_bytes())
            && v["released"] == false
        {
            let owner = v["owner"].as_str().unwrap_or_default().to_string();
            out.insert(structure_of(s.key_expr().as_str()), owner);
        }
    }
    out
}

fn percentile(v: &mut [f64], p: f64) -> f64 {
    v.sort_by(f64::total_cmp);
    v[((v.len() as f64 - 1.0) * p).round() as usize]
}

fn main() {
    let n = env_or("BOLTWATCH_BENCH_STRUCTURES", 100);
    let seconds = env_or("BOLTWATCH_BENCH_SECONDS", 300);
    let dir = std::env::temp_dir().join(format!("bw-bench-fleet-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    eprintln!("fleet load: {n} structures × 1 set/s for {seconds} s, 2 routers, 3 daemons");
    let (models, merged) = site(&dir, n, seconds);
    let routers: Vec<String> = (0..2)
        .map(|_| format!("tcp/127.0.0.1:{}", port()))
        .collect();
    let mut procs = Procs(Vec::new());
    for (i, r) in routers.iter().enumerate() {
        let mut c = bin();
        c.args(["router", "--log-level", "warn", "--listen", r])
            .stderr(Stdio::null());
        if i > 0 {
            c.args(["--connect", &routers[0]]);
        }
        procs.0.push(c.spawn().unwrap());
    }
    std::thread::sleep(Duration::from_millis(500));
    let z = zenoh::open({
        let mut c = zenoh::Config::default();
        c.insert_json5("mode", "\"client\"").unwrap();
        c.insert_json5("connect/endpoints", &format!("[\"{}\"]", routers[1]))
            .unwrap();
        c
    })
    .wait()
    .unwrap();
    let heard = std::sync::Arc::new(std::sync::Mutex::new(Heard::default()));
    let _subs = observe(&z, heard.clone());
    let ids = ["l1", "l2", "l3"];
    let mut daemons = BTreeMap::new();
    for id in ids {
        let cfg = daemon_config(&dir, id, &routers, &models);
        let log = std::fs::File::create(dir.join(format!("{id}.log"))).unwrap();
        let child = bin()
            .args(["run", "--config"])
            .arg(&cfg)
            .stderr(log)
            .spawn()
            .unwrap();
        daemons.insert(id.to_string(), child.id());
        procs.0.push(child);
    }
    // Ownership settles: every structure's record names the member rendezvous hashing
    // gives it among the three.
    let settle = Instant::now();
    let deadline = settle + Duration::from_secs(120);
    loop {
        let owners = stored_owners(&z);
        let settled = owners.len() == n
            && owners
                .iter()
                .all(|(s, o)| rendezvous::owner(ids, s) == Some(o.as_str()));
        if settled {
            let mut split: BTreeMap<&str, usize> = BTreeMap::new();
            for o in owners.values() {
                *split.entry(o).or_default() += 1;
            }
            println!("ownership settled in {:?}: {split:?}", settle.elapsed());
            break;
        }
        assert!(
            Instant::now() < deadline,
            "ownership did not settle: {owners:?}"
        );
        std::thread::sleep(Duration::from_millis(500));
    }
    heard.lock().unwrap().owners = stored_owners(&z)
        .into_iter()
        .map(|(s, o)| (s, (o, Instant::now())))
        .collect();
    std::thread::sleep(Duration::from_secs(3));
    let cpu0: BTreeMap<String, f64> = daemons
        .iter()
        .map(|(id, pid)| (id.clone(), cpu_s(*pid)))
        .collect();
    let (puts0, bytes0) = {
        let h = heard.lock().unwrap();
        (h.state_puts, h.state_bytes)
    };
    let router_pids: Vec<u32> = procs.0[..2].iter().map(Child::id).collect();
    let rss0: Vec<f64> = router_pids.iter().map(|p| rss_mb(*p)).collect();
    let start = Instant::now();
    let st = bin()
        .arg("publish")
        .arg(&merged)
        .args([
            "--connect",
            &routers[0],
            "--rate",
            &n.to_string(),
            "--wait",
            "30",
        ])
        .stderr(Stdio::null())
        .status()
        .unwrap();
    assert!(st.success(), "the sensor failed");
    let wall = start.elapsed().as_secs_f64();
    std::thread::sleep(Duration::from_secs(2));
    report_load(&heard, &daemons, &cpu0, (puts0, bytes0), wall, n * seconds);
    for (i, (pid, before)) in router_pids.iter().zip(rss0).enumerate() {
        println!(
            "router {i}: resident {before:.0} MB before the load, {:.0} MB after",
            rss_mb(*pid)
        );
    }
    report_takeover(&heard, &daemons);
    drop(procs);
}

fn report_load(
    heard: &std::sync::Mutex<Heard>,
    daemons: &BTreeMap<String, u32>,
    cpu0: &BTreeMap<String, f64>,
    (puts0, bytes0): (u64, u64),
    wall: f64,
    sets: usize,
) {
    let h = heard.lock().unwrap();
    let mut lat: Vec<f64> = h
        .estimated
        .iter()
        .filter_map(|(k, t)| Some(t.duration_since(*h.published.get(k)?).as_secs_f64() * 1e3))
        .collect();
    println!(
        "sets published {}, estimated {} of {sets}",
        h.published.len(),
        h.estimated.len()
    );
    println!(
        "latency set → estimate: p50 {:.1} ms, p99 {:.1} ms, max {:.1} ms",
        percentile(&mut lat, 0.5),
        percentile(&mut lat, 0.99),
        percentile(&mut lat, 1.0)
    );
    for (id, pid) in daemons {
        let cpu = cpu_s(*pid) - cpu0[id];
        println!(
            "daemon {id}: {cpu:.1} CPU s over {wall:.0} s ({:.1} % of a core)",
            100.0 * cpu / wall
        );
    }
    let (puts, bytes) = (h.state_puts - puts0, h.state_bytes - bytes0);
    println!(
        "state storage traffic: {puts} puts, {:.1} MB ({:.1} puts/s, {:.1} kB/s)",
        bytes as f64 / 1e6,
        puts as f64 / wall,
        bytes as f64 / wall / 1e3
    );
}

fn report_takeover(heard: &std::sync::Mutex<Heard>, daemons: &BTreeMap<String, u32>) {
    let owners: BTreeMap<String, String> = heard
        .lock()
        .unwrap()
        .owners
        .iter()
        .map(|(s, (o, _))| (s.clone(), o.clone()))
        .collect();
    let mut count: BTreeMap<&str, usize> = BTreeMap::new();
    for o in owners.values() {
        *count.entry(o).or_default() += 1;
    }
    let (victim, k) = count.into_iter().max_by_key(|(_, k)| *k).unwrap();
    let pid = daemons[victim];
    let killed = Instant::now();
    // SAFETY: signalling a child this benchmark started.
    unsafe { libc::kill(pid as i32, libc::SIGKILL) };
    let theirs: Vec<&String> = owners
        .iter()
        .filter(|(_, o)| *o == victim)
        .map(|(s, _)| s)
        .collect();
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let h = heard.lock().unwrap();
        let moved = theirs
            .iter()
            .filter_map(|s| h.owners.get(*s))
            .filter(|(o, t)| o != victim && *t > killed)
            .map(|(_, t)| t.duration_since(killed))
            .collect::<Vec<_>>();
        if moved.len() == theirs.len() {
            let last = moved.iter().max().unwrap();
            println!("takeover of {k} structures after kill -9 of {victim}: the last in {last:?}");
            break;
        }
        assert!(
            Instant::now() < deadline,
            "takeover incomplete: {} of {}",
            moved.len(),
            theirs.len()
        );
        drop(h);
        std::thread::sleep(Duration::from_millis(20));
    }
}
