//! A fleet on loopback: two `boltwatch router`s replicating the state storage, three
//! daemons sharing twelve structures, sensors publishing through advanced publishers. A
//! daemon killed -9, brought back, a router killed: no set lost, every set's outputs the
//! bytes a single-daemon replay writes (apart from `owner` and `epoch`). A daemon paused
//! for 30 s: its structure is taken over and, resumed, it publishes nothing more under its
//! old epoch.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::process::{Child, Stdio};
use std::time::{Duration, Instant};

use serde_json::Value;
use zenoh::Wait;

use super::{bin, client, free_port, status_of, wait_status_of};
use crate::suite::tracker::tmp_dir;
use boltwatch::daemon::fleet::rendezvous;
use boltwatch::io::mcap::read_all;

/// No cross-checks (their timing is the wall clock's, live): every output compared is a
/// set's own.
pub(super) const NO_CROSSCHECK: &str =
    "[tracker]\ncrosscheck_every_sets = 100000\ncrosscheck_every_s = 0.0\n";

/// A child process killed when dropped.
pub(super) struct Proc(Child, PathBuf);

impl Proc {
    pub(super) fn spawn(mut c: std::process::Command, log: PathBuf) -> Self {
        let f = std::fs::File::create(&log).unwrap();
        c.stdout(Stdio::null()).stderr(f);
        Proc(c.spawn().unwrap(), log)
    }

    fn pid(&self) -> i32 {
        self.0.id() as i32
    }

    fn signal(&self, sig: i32) {
        // SAFETY: signalling a child this test started and has not reaped.
        unsafe { libc::kill(self.pid(), sig) };
    }

    fn kill9(&mut self) {
        self.signal(libc::SIGKILL);
        let _ = self.0.wait();
    }

    pub(super) fn log(&self) -> String {
        std::fs::read_to_string(&self.1).unwrap_or_default()
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        if self.0.try_wait().ok().flatten().is_none() {
            let _ = self.0.kill();
            let _ = self.0.wait();
        }
    }
}

/// The test's site: structure models and recordings, routers, daemons.
pub(super) struct Site {
    pub(super) dir: PathBuf,
    pub(super) structures: Vec<String>,
    pub(super) routers: Vec<String>,
}

impl Site {
    /// `n` copies of the lab frame named `frame-01`…, each with a healthy recording of
    /// `sets` sets (seed = its number).
    pub(super) fn new(name: &str, n: usize, sets: usize, routers: usize) -> Self {
        let dir = tmp_dir(name);
        let lab = std::fs::read_to_string(
            Path::new(env!("CARGO_MANIFEST_DIR")).join("config/models/lab-frame.toml"),
        )
        .unwrap();
        let structures: Vec<String> = (1..=n).map(|i| format!("frame-{i:02}")).collect();
        for (i, s) in structures.iter().enumerate() {
            let model = lab.replacen("name = \"lab-frame\"", &format!("name = \"{s}\""), 1);
            std::fs::write(dir.join(format!("{s}.toml")), model).unwrap();
            let out = bin()
                .args(["scenario", "healthy", "--model"])
                .arg(dir.join(format!("{s}.toml")))
                .args(["--sets", &sets.to_string(), "--days", "3", "--seed"])
                .arg((i + 1).to_string())
                .arg("-o")
                .arg(dir.join(format!("{s}.mcap")))
                .output()
                .unwrap();
            assert!(out.status.success(), "{out:?}");
        }
        let routers = (0..routers)
            .map(|_| format!("tcp/127.0.0.1:{}", free_port()))
            .collect();
        Self {
            dir,
            structures,
            routers,
        }
    }

    /// Router `i`, connected to the routers before it.
    fn router(&self, i: usize) -> Proc {
        let mut c = bin();
        c.args([
            "router",
            "--log-level",
            "warn",
            "--listen",
            &self.routers[i],
        ]);
        for r in &self.routers[..i] {
            c.args(["--connect", r]);
        }
        Proc::spawn(c, self.dir.join(format!("router-{i}.log")))
    }

    /// Daemon `id` of group `g`, a client of the routers (the first that answers).
    fn daemon(&self, id: &str) -> Proc {
        self.daemon_with_metrics(id, "")
    }

    /// [`Site::daemon`] with its metrics on `metrics` (`host:port`, "": none).
    fn daemon_with_metrics(&self, id: &str, metrics: &str) -> Proc {
        let mut toml = format!(
            "{NO_CROSSCHECK}[zenoh]\nmode = \"client\"\nlisten = []\nconnect = {:?}\n\
             [daemon]\nstate = \"zenoh\"\nstate_dir = \"{}\"\n[fleet]\ngroup = \"g\"\nid = \"{id}\"\n\
             [metrics]\nlisten = \"{metrics}\"\n[console]\nlisten = \"\"\n",
            self.routers,
            self.dir.join(format!("state-{id}")).display()
        );
        for s in &self.structures {
            toml += &format!(
                "[[structures]]\nname = \"{s}\"\nmodel = \"{}\"\n",
                self.dir.join(format!("{s}.toml")).display()
            );
        }
        let cfg = self.dir.join(format!("{id}.toml"));
        std::fs::write(&cfg, toml).unwrap();
        let mut c = bin();
        c.env("BOLTWATCH__LOG__LEVEL", "info,zenoh=warn")
            .args(["run", "--config"])
            .arg(&cfg);
        Proc::spawn(c, self.dir.join(format!("{id}.log")))
    }

    /// A sensor publishing sets `skip..skip + count` of structure `s` through router `r`.
    fn publish(&self, s: &str, r: usize, skip: usize, count: usize, rate: f64) -> Proc {
        let mut c = bin();
        c.arg("publish")
            .arg(self.dir.join(format!("{s}.mcap")))
            .args(["--connect", &self.routers[r], "--rate", &rate.to_string()])
            .args(["--skip", &skip.to_string(), "--count", &count.to_string()])
            .args(["--wait", "20"]);
        Proc::spawn(c, self.dir.join(format!("publish-{s}-{skip}.log")))
    }

    /// Each structure's owner and epoch, from its status (`None`: no answer).
    pub(super) fn owners(&self, z: &zenoh::Session) -> BTreeMap<String, Option<(String, u64)>> {
        self.structures
            .iter()
            .map(|s| {
                let o = status_of(z, s).and_then(|v| {
                    let o = &v["ownership"];
                    Some((o["owner"].as_str()?.to_string(), o["epoch"].as_u64()?))
                });
                (s.clone(), o)
            })
            .collect()
    }

    /// Waits until every structure has an owner satisfying `ok`; the owners.
    fn wait_owners(
        &self,
        z: &zenoh::Session,
        limit: Duration,
        what: &str,
        ok: impl Fn(&str, &str) -> bool,
    ) -> BTreeMap<String, (String, u64)> {
        let deadline = Instant::now() + limit;
        loop {
            let o = self.owners(z);
            if o.iter()
                .all(|(s, v)| v.as_ref().is_some_and(|(d, _)| ok(s, d)))
            {
                return o.into_iter().map(|(k, v)| (k, v.unwrap())).collect();
            }
            assert!(
                Instant::now() < deadline,
                "timed out waiting for {what}: {o:?}"
            );
            std::thread::sleep(Duration::from_millis(100));
        }
    }

    /// The single-daemon replay's outputs of every structure's recording: topic → id →
    /// bytes.
    fn reference(&self, structures: &[String]) -> Outputs {
        let mut all = Outputs::default();
        for s in structures {
            let rec = self.dir.join(format!("{s}.mcap"));
            let out = self.dir.join(format!("{s}-replay.mcap"));
            let cfg = self.dir.join(format!("{s}-replay.toml"));
            let toml = format!(
                "{NO_CROSSCHECK}[[structures]]\nname = \"{s}\"\nmodel = \"{}\"\n",
                self.dir.join(format!("{s}.toml")).display()
            );
            std::fs::write(&cfg, toml).unwrap();
            let status = bin()
                .arg("replay")
                .arg(&rec)
                .arg("--config")
                .arg(&cfg)
                .arg("-o")
                .arg(&out)
                .output()
                .unwrap();
            assert!(status.status.success(), "{status:?}");
            for m in read_all(&out).unwrap() {
                all.add(&m.topic, &m.data);
            }
        }
        all
    }
}

/// Outputs per set: `topic → id → every distinct payload` (owner and epoch taken out).
#[derive(Default, Debug, PartialEq)]
struct Outputs(BTreeMap<String, BTreeMap<String, BTreeSet<Vec<u8>>>>);

impl Outputs {
    fn add(&mut self, topic: &str, bytes: &[u8]) {
        let suffix = topic.rsplit('/').next().unwrap_or_default();
        if !["stiffness", "alerts", "rejected"].contains(&suffix) {
            return;
        }
        let plain = unstamp(bytes);
        let v: Value = serde_json::from_slice(&plain).unwrap();
        let id = v["id"].as_str().unwrap().to_string();
        self.0
            .entry(topic.to_string())
            .or_default()
            .entry(id)
            .or_default()
            .insert(plain);
    }

    fn count(&self, suffix: &str) -> usize {
        self.0
            .iter()
            .filter(|(t, _)| t.ends_with(suffix))
            .map(|(_, ids)| ids.len())
            .sum()
    }
}

/// The payload without the fleet's `"owner"` and `"epoch"` (added last, after a comma).
fn unstamp(bytes: &[u8]) -> Vec<u8> {
    let s = std::str::from_utf8(bytes).unwrap();
    match s.rfind(",\"owner\":") {
        Some(i) if s.ends_with('}') => format!("{}}}", &s[..i]).into_bytes(),
        _ => bytes.to_vec(),
    }
}

/// Every output received on `boltwatch/*/<suffix>`, with its owner, epoch and arrival.
struct Listener {
    subs:
        Vec<zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>>>,
    got: Vec<(Instant, String, Vec<u8>)>,
}

impl Listener {
    fn new(z: &zenoh::Session) -> Self {
        let subs = ["stiffness", "alerts", "rejected"]
            .iter()
            .map(|suffix| {
                z.declare_subscriber(format!("boltwatch/*/{suffix}"))
                    .with(zenoh::handlers::FifoChannel::new(1_000_000))
                    .wait()
                    .unwrap()
            })
            .collect();
        Self {
            subs,
            got: Vec::new(),
        }
    }

    fn drain(&mut self) {
        for sub in &self.subs {
            while let Ok(Some(s)) = sub.try_recv() {
                let key = s.key_expr().as_str().to_string();
                self.got
                    .push((Instant::now(), key, s.payload().to_bytes().to_vec()));
            }
        }
    }

    fn outputs(&self) -> Outputs {
        let mut o = Outputs::default();
        for (_, k, b) in &self.got {
            o.add(k, b);
        }
        o
    }

    /// Waits until `n` estimates have arrived (distinct ids).
    fn wait_estimates(&mut self, n: usize, limit: Duration, what: &str) {
        let deadline = Instant::now() + limit;
        loop {
            self.drain();
            let got = self.outputs().count("stiffness");
            if got >= n {
                return;
            }
            assert!(Instant::now() < deadline, "{what}: {got} of {n} estimates");
            std::thread::sleep(Duration::from_millis(100));
        }
    }
}

/// The member owning the most structures.
fn busiest(owners: &BTreeMap<String, (String, u64)>) -> String {
    let mut n: BTreeMap<&str, usize> = BTreeMap::new();
    for (d, _) in owners.values() {
        *n.entry(d).or_default() += 1;
    }
    n.into_iter().max_by_key(|(_, k)| *k).unwrap().0.to_string()
}

/// Publishes sets `skip..skip + count` of every structure at once through router `r`, and
/// waits for every sensor to finish (each waits until the daemons took all its sets).
fn publish_all(site: &Site, r: usize, skip: usize, count: usize, during: impl FnOnce()) {
    let mut sensors: Vec<Proc> = site
        .structures
        .iter()
        .map(|s| site.publish(s, r, skip, count, 4.0))
        .collect();
    during();
    for p in &mut sensors {
        let st = p.0.wait().unwrap();
        assert!(st.success(), "sensor failed: {}", p.log());
    }
}

/// Each set's outputs, compared with the single-daemon replay's: every id of the replay
/// received (no set lost), none extra, and every copy of an output (re-published by a
/// new owner) the replay's bytes.
fn assert_as_replayed(got: &Outputs, want: &Outputs) {
    for (topic, ids) in &want.0 {
        let g = got.0.get(topic).cloned().unwrap_or_default();
        let missing: Vec<&String> = ids.keys().filter(|id| !g.contains_key(*id)).collect();
        assert!(
            missing.is_empty(),
            "{topic}: {} outputs lost: {missing:?}",
            missing.len()
        );
        for (id, copies) in &g {
            let w = ids
                .get(id)
                .unwrap_or_else(|| panic!("{topic}: {id} not in the replay"));
            assert_eq!(
                copies, w,
                "{topic}: {id} differs from the replay (or between copies)"
            );
        }
    }
    for topic in got.0.keys() {
        assert!(
            want.0.contains_key(topic),
            "{topic}: outputs the replay does not have"
        );
    }
}

/// Waits until `boltwatch fleet status` shows `members` and every structure tracked by a
/// live member, handed back by none, with nothing queued.
fn wait_fleet_settled(site: &Site, members: &[&str]) {
    let settled = |view: &Value| {
        let lines = view["structures"].as_array().cloned().unwrap_or_default();
        view["members"] == serde_json::json!(members)
            && lines.len() == site.structures.len()
            && lines
                .iter()
                .all(|l| l["owner_live"] == true && l["released"] == false && l["queued"] == 0)
    };
    let deadline = Instant::now() + Duration::from_secs(20);
    loop {
        let out = bin()
            .args(["fleet", "status", "--group", "g", "--json", "--connect"])
            .arg(site.routers.last().unwrap())
            .output()
            .unwrap();
        assert!(out.status.success(), "{out:?}");
        let view: Value = serde_json::from_slice(&out.stdout).unwrap();
        if settled(&view) {
            return;
        }
        assert!(Instant::now() < deadline, "fleet status: {view:#}");
        std::thread::sleep(Duration::from_millis(500));
    }
}

/// Batch 1 of [`a_fleet_loses_no_set_when_a_daemon_or_a_router_dies`]: sets 0..20 of every
/// structure, the busiest daemon killed -9 a second in; every structure it owned has a new
/// owner in a new epoch within 10 s. Its id and structures.
fn batch_with_a_kill(
    site: &Site,
    z: &zenoh::Session,
    daemons: &mut BTreeMap<String, Proc>,
) -> (String, Vec<String>) {
    // Settled: each structure with the member rendezvous hashing names among the three.
    let owners = site.wait_owners(z, Duration::from_secs(60), "12 owners", |s, d| {
        rendezvous::owner(daemons.keys().map(String::as_str), s) == Some(d)
    });
    let victim = busiest(&owners);
    let theirs: Vec<String> = owners
        .iter()
        .filter(|(_, (d, _))| *d == victim)
        .map(|(s, _)| s.clone())
        .collect();
    assert!(theirs.len() >= 4, "{owners:?}");
    let mut takeover = Duration::ZERO;
    publish_all(site, 0, 0, 20, || {
        std::thread::sleep(Duration::from_secs(1));
        let killed = Instant::now();
        daemons.get_mut(&victim).unwrap().kill9();
        let after = site.wait_owners(z, Duration::from_secs(10), "the takeover", |_, d| {
            d != victim
        });
        takeover = killed.elapsed();
        for s in &theirs {
            assert!(after[s].1 > owners[s].1, "{s}: no new epoch: {after:?}");
        }
    });
    eprintln!("takeover of {} structures: {takeover:?}", theirs.len());
    assert!(takeover < Duration::from_secs(10));
    (victim, theirs)
}

/// Two routers, three daemons, twelve structures of 60 sets published in three batches of
/// 20: the busiest daemon killed -9 during the first, back for the second, the sensors'
/// router killed before the third.
#[test]
fn a_fleet_loses_no_set_when_a_daemon_or_a_router_dies() {
    let site = Site::new("fleet", 12, 60, 2);
    let want = site.reference(&site.structures);
    assert_eq!(want.count("stiffness"), 12 * 60);
    let mut routers = [site.router(0), site.router(1)];
    std::thread::sleep(Duration::from_millis(500));
    let mut daemons: BTreeMap<String, Proc> = ["d1", "d2", "d3"]
        .iter()
        .map(|id| (id.to_string(), site.daemon(id)))
        .collect();
    let z = client(&site.routers[1]);
    let mut heard = Listener::new(&z);
    let members = ["d1", "d2", "d3"];
    let (victim, theirs) = batch_with_a_kill(&site, &z, &mut daemons);
    heard.wait_estimates(12 * 20, Duration::from_secs(60), "batch 1");

    // Batch 2: the daemon back; its structures return to it first.
    daemons.insert(victim.clone(), site.daemon(&victim));
    let back = site.wait_owners(&z, Duration::from_secs(30), "the hand-back", |s, d| {
        !theirs.contains(&s.to_string()) || d == victim
    });
    for s in &theirs {
        assert_eq!(back[s].0, victim);
    }
    publish_all(&site, 0, 20, 20, || {});
    heard.wait_estimates(12 * 40, Duration::from_secs(60), "batch 2");

    // Batch 3: the first router (the sensors' and some daemons') killed.
    routers[0].kill9();
    site.wait_owners(
        &z,
        Duration::from_secs(30),
        "owners after the router",
        |_, d| members.contains(&d),
    );
    publish_all(&site, 1, 40, 20, || {});
    heard.wait_estimates(12 * 60, Duration::from_secs(60), "batch 3");
    std::thread::sleep(Duration::from_secs(1));
    heard.drain();
    assert_as_replayed(&heard.outputs(), &want);
    wait_fleet_settled(&site, &["d1", "d2", "d3"]);
    for (id, d) in &daemons {
        assert!(!d.log().contains("panicked"), "{id}:\n{}", d.log());
    }
}

/// Nothing of `s` under p1's old `epoch` was heard after `resumed`, and p1's own log has
/// estimates under it that were never published: the fence held them.
fn assert_fenced(site: &Site, heard: &Listener, s: &str, epoch: u64, resumed: Instant) {
    let stale: Vec<String> = heard
        .got
        .iter()
        .filter(|(t, _, _)| *t > resumed)
        .filter_map(|(_, k, b)| {
            let v: Value = serde_json::from_slice(b).ok()?;
            (v["owner"] == "p1" && v["epoch"].as_u64() == Some(epoch)).then(|| k.clone())
        })
        .collect();
    assert!(
        stale.is_empty(),
        "published under the stale epoch after SIGCONT: {stale:?}"
    );
    // The fence had something to hold: sets that reached p1 before its link was dropped,
    // tracked after SIGCONT and written into its own log, but not published.
    let stale_id = |b: &[u8]| {
        let v: Value = serde_json::from_slice(b).ok()?;
        (v["owner"] == "p1" && v["epoch"].as_u64() == Some(epoch))
            .then(|| v["id"].as_str().unwrap().to_string())
    };
    let published: BTreeSet<String> = heard
        .got
        .iter()
        .filter(|(_, k, _)| k.ends_with(&format!("{s}/stiffness")))
        .filter_map(|(_, _, b)| stale_id(b))
        .collect();
    let logged: BTreeSet<String> = std::fs::read_dir(site.dir.join("state-p1/log"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.to_string_lossy().contains(s) && p.extension().is_some_and(|x| x == "mcap"))
        .flat_map(|p| read_all(&p).unwrap())
        .filter(|m| m.topic.ends_with("/stiffness"))
        .filter_map(|m| stale_id(&m.data))
        .collect();
    let held = logged.difference(&published).count();
    eprintln!(
        "p1 under epoch {epoch}: {} estimates logged, {} published, {held} held by the fence",
        logged.len(),
        published.len()
    );
    assert!(
        held > 0,
        "nothing reached p1 during its pause: the fence was not tested"
    );
}

/// A daemon paused (SIGSTOP) for 30 s loses its structures to the others when its Zenoh
/// lease runs out; resumed (SIGCONT), it finds its epoch superseded and publishes nothing
/// more under it, though sets reached it before the pause.
#[test]
fn a_paused_daemon_is_fenced_when_it_resumes() {
    const SETS: usize = 200;
    let site = Site::new("fleet-pause", 4, SETS, 1);
    let _router = site.router(0);
    std::thread::sleep(Duration::from_millis(500));
    let d1 = site.daemon("p1");
    let metrics = format!("127.0.0.1:{}", free_port());
    let _d2 = site.daemon_with_metrics("p2", &metrics);
    let z = client(&site.routers[0]);
    let mut heard = Listener::new(&z);
    let owners = site.wait_owners(&z, Duration::from_secs(60), "4 owners", |_, d| {
        d == "p1" || d == "p2"
    });
    let (s, (_, epoch)) = owners
        .iter()
        .find(|(_, (d, _))| d == "p1")
        .map(|(s, o)| (s.clone(), o.clone()))
        .expect("p1 owns a structure");
    // A burst: p1 is stopped with sets still queued, tracked when it resumes.
    let mut sensor = site.publish(&s, 0, 0, SETS, 0.0);
    let before = wait_status_of(&z, &s, Duration::from_secs(30), "sets to arrive", |v| {
        v["sets"]["received"].as_u64() > Some(0)
    });
    d1.signal(libc::SIGSTOP);
    assert!(
        before["sets"]["accepted"].as_u64() < Some(SETS as u64),
        "p1 tracked the burst before it could be paused: {before:#}"
    );
    std::thread::sleep(Duration::from_secs(30));
    let during = status_of(&z, &s).expect("the structure answers while p1 is paused");
    assert_eq!(during["ownership"]["owner"], "p2", "{during:#}");
    heard.drain();
    // p2's metrics name the structure it took over, with the new epoch.
    let m = super::tracking::http_get(&metrics, "/metrics");
    let line = format!(
        "boltwatch_ownership_epoch{{structure=\"{s}\",owner=\"p2\"}} {}",
        during["ownership"]["epoch"]
    );
    assert!(m.contains(&line), "{line} not in:\n{m}");
    let resumed = Instant::now();
    d1.signal(libc::SIGCONT);
    assert!(sensor.0.wait().unwrap().success(), "{}", sensor.log());
    heard.wait_estimates(SETS, Duration::from_secs(60), "the paused structure's sets");
    std::thread::sleep(Duration::from_secs(3));
    heard.drain();
    assert_fenced(&site, &heard, &s, epoch, resumed);
    assert_as_replayed(&heard.outputs(), &site.reference(std::slice::from_ref(&s)));
    assert!(
        d1.log().contains("ownership moved on") || d1.log().contains("standing down"),
        "{}",
        d1.log()
    );
}
