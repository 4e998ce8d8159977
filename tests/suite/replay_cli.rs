//! `boltwatch replay`, `report` and `scenario` as a user runs them: SIGKILL and resume,
//! the official Python `mcap` reader on the output, configuration errors.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::Instant;

use rand::{Rng, SeedableRng};

use super::common::python_venv;
use super::tracker::{make_scenario, payloads, tmp_dir};
use boltwatch::io::mcap::{ChannelSpec, McapWriter, read_all, topic};

fn bin() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_boltwatch"));
    c.current_dir(env!("CARGO_MANIFEST_DIR"))
        .env("BOLTWATCH__LOG__LEVEL", "warn");
    c
}

/// Checkpoints every 5 sets, cross-checks every 50.
const ENV: [(&str, &str); 3] = [
    ("BOLTWATCH__TRACKER__CHECKPOINT_EVERY_SETS", "5"),
    ("BOLTWATCH__TRACKER__CROSSCHECK_EVERY_SETS", "50"),
    ("BOLTWATCH__TRACKER__CROSSCHECK_EVERY_S", "0"),
];

fn replay_cmd(rec: &Path, out: &Path, resume: bool) -> Command {
    let mut c = bin();
    c.arg("replay").arg(rec).arg("-o").arg(out);
    if resume {
        c.arg("--resume");
    }
    c.envs(ENV).stdout(Stdio::piped()).stderr(Stdio::piped());
    c
}

/// SIGKILL the replay at 10 random points and resume each time: the final output file is
/// byte-identical to an uninterrupted run's, so no estimate is lost or written twice.
#[test]
fn killed_replay_resumes_to_the_same_bytes() {
    let d = tmp_dir("kill");
    let rec = d.join("rec.mcap");
    make_scenario("loosening", 300, 60.0, &rec);
    let reference = d.join("ref.mcap");
    let t0 = Instant::now();
    let o = replay_cmd(&rec, &reference, false).output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let full = t0.elapsed();
    let out = d.join("out.mcap");
    let ckpt = d.join("out.mcap.checkpoint.json");
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
    // Ten kill points spread over the run: wait until the checkpoint has passed a random
    // set, then a random further delay of up to 50 sets' time (by the full run's pace, at
    // most 250 ms), so kills fall anywhere: mid-set, mid-chunk, mid-checkpoint, and always
    // before the last set (a checkpoint is written every 5 sets here).
    let max_delay_ms = (full.as_millis() as u64 * 50 / 300).clamp(1, 250);
    let mut targets: Vec<u64> = (0..10).map(|_| rng.random_range(0..240)).collect();
    targets.sort_unstable();
    let next_input = || {
        std::fs::read(&ckpt)
            .ok()
            .and_then(|b| serde_json::from_slice::<serde_json::Value>(&b).ok())
            .and_then(|c| c["next_input"].as_u64())
    };
    let mut resumed_at = Vec::new();
    for (k, target) in targets.iter().enumerate() {
        let mut child = replay_cmd(&rec, &out, k > 0).spawn().unwrap();
        while next_input().unwrap_or(0) < *target && child.try_wait().unwrap().is_none() {
            std::thread::sleep(std::time::Duration::from_millis(5));
        }
        std::thread::sleep(std::time::Duration::from_millis(
            rng.random_range(0..max_delay_ms),
        ));
        assert!(
            child.try_wait().unwrap().is_none(),
            "kill {k}: the replay ended before it (full run {full:?})"
        );
        child.kill().unwrap(); // SIGKILL
        child.wait().unwrap();
        resumed_at.push(next_input());
    }
    println!("full run {full:?}; checkpoint after each kill: {resumed_at:?}");
    assert!(
        resumed_at.iter().flatten().any(|&n| n > 0),
        "no checkpoint was ever written"
    );
    // Without the unfinished output the checkpoint cannot be resumed: a clear error, and
    // nothing is overwritten.
    let part = d.join("out.mcap.part");
    let saved = d.join("saved.part");
    std::fs::rename(&part, &saved).unwrap();
    let o = replay_cmd(&rec, &out, true).output().unwrap();
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("is missing"));
    std::fs::rename(&saved, &part).unwrap();
    let o = replay_cmd(&rec, &out, true).output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(stdout.contains("resumed at set"), "{stdout}");
    let (a, b) = (
        std::fs::read(&reference).unwrap(),
        std::fs::read(&out).unwrap(),
    );
    assert!(
        a == b,
        "resumed output differs ({} vs {} bytes)",
        a.len(),
        b.len()
    );
    let est = payloads(&read_all(&out).unwrap(), "stiffness");
    assert_eq!(est.len(), 300);
    assert!(
        est.windows(2)
            .all(|w| w[0]["time"].as_str() < w[1]["time"].as_str())
    );
    // A resume of a complete run changes nothing and says so.
    let o = replay_cmd(&rec, &out, true).output().unwrap();
    assert!(String::from_utf8_lossy(&o.stdout).contains("already replayed"));
    assert!(std::fs::read(&out).unwrap() == a);
}

/// A virtual environment with the official Python `mcap` reader.
fn python_with_mcap() -> PathBuf {
    python_venv(
        "py-mcap-venv",
        "import mcap, zstandard",
        &["mcap==1.6.0", "zstandard==0.25.0"],
    )
}

/// The official Python `mcap` package reads the output: every channel and schema (JSON
/// Schema text that parses), every message (JSON that parses and names its schema), with
/// the same counts as our reader.
#[test]
fn python_mcap_reads_every_channel_and_schema() {
    let d = tmp_dir("python");
    let rec = d.join("rec.mcap");
    make_scenario("sudden", 120, 60.0, &rec);
    // One bad set, so that every output channel has messages.
    let mixed = d.join("mixed.mcap");
    {
        let all = read_all(&rec).unwrap();
        let modal = topic("lab-frame", "modal");
        let mut w = McapWriter::create(
            &mixed,
            &[ChannelSpec::for_structure("lab-frame", "modal").unwrap()],
        )
        .unwrap();
        for m in all.iter().filter(|m| m.topic == modal) {
            w.write(&modal, m.log_time, &m.data).unwrap();
        }
        w.write(
            &modal,
            u64::MAX / 2,
            br#"{"schema": "boltwatch.modal_set.v1"}"#,
        )
        .unwrap();
        w.finish().unwrap();
    }
    let out = d.join("out.mcap");
    let o = bin()
        .arg("replay")
        .arg(&mixed)
        .arg("-o")
        .arg(&out)
        .env("BOLTWATCH__TRACKER__CROSSCHECK_EVERY_SETS", "50")
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let script = r#"
import json, sys
from mcap.reader import make_reader
with open(sys.argv[1], "rb") as f:
    reader = make_reader(f)
    summary = reader.get_summary()
    schemas = {i: s for i, s in summary.schemas.items()}
    for s in schemas.values():
        assert s.encoding == "jsonschema", s.encoding
        assert json.loads(s.data)["title"] == s.name, s.name
    counts = {c.topic: 0 for c in summary.channels.values()}
    for schema, channel, message in reader.iter_messages():
        assert channel.message_encoding == "json"
        body = json.loads(message.data)
        assert body["schema"] == schema.name, (body["schema"], schema.name)
        assert body["structure"] == "lab-frame"
        counts[channel.topic] += 1
    print(json.dumps({"counts": counts, "schemas": sorted(s.name for s in schemas.values()),
                      "stats": summary.statistics.message_count}))
"#;
    let o = Command::new(python_with_mcap())
        .arg("-c")
        .arg(script)
        .arg(&out)
        .output()
        .unwrap();
    assert!(
        o.status.success(),
        "python: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    println!("{v}");
    let ours = read_all(&out).unwrap();
    for suffix in ["stiffness", "alerts", "crosscheck", "rejected"] {
        let t = topic("lab-frame", suffix);
        let n = ours.iter().filter(|m| m.topic == t).count();
        assert!(n > 0, "no {suffix} messages to read");
        assert_eq!(v["counts"][&t], n, "{t}");
    }
    assert_eq!(v["stats"], ours.len());
    assert_eq!(v["schemas"].as_array().unwrap().len(), 4);
}

/// `report` writes the three plots, each an SVG with one panel per parameter / mode.
#[test]
fn report_draws_stiffness_frequency_and_epsilon() {
    let d = tmp_dir("report");
    let rec = d.join("rec.mcap");
    make_scenario("sudden", 80, 60.0, &rec);
    let out = d.join("out.mcap");
    let o = bin()
        .arg("replay")
        .arg(&rec)
        .arg("-o")
        .arg(&out)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(
        stdout.contains("C1L@J1L") && stdout.contains("loosening alarm"),
        "{stdout}"
    );
    let o = bin()
        .arg("report")
        .arg(&out)
        .arg("-o")
        .arg(d.join("plots"))
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    for name in ["stiffness", "frequencies", "epsilon"] {
        let svg = std::fs::read_to_string(d.join(format!("plots/lab-frame-{name}.svg"))).unwrap();
        assert!(
            svg.starts_with("<svg") || svg.starts_with("<?xml"),
            "{name}"
        );
        assert!(svg.contains("</svg>"));
    }
    let svg = std::fs::read_to_string(d.join("plots/lab-frame-stiffness.svg")).unwrap();
    assert_eq!(
        svg.matches("<polygon").count(),
        17,
        "a 95 % band per parameter"
    );
    assert!(svg.contains(">alarm<"), "alarm marker in the legend");
    assert_reads_at_a_glance(&svg);
}

/// The stiffness figure reads at a glance: one legend for the figure, the connection in
/// alarm first, every axis with its unit, and no text running past the figure's edges
/// (a start-anchored text at most 7 px a character; the same estimate lays the legend).
fn assert_reads_at_a_glance(svg: &str) {
    assert_eq!(svg.matches(">95 % band of the filtered level<").count(), 1);
    assert_eq!(svg.matches(">alarm<").count(), 1, "one legend entry");
    let attr = |t: &str, name: &str| -> Option<f64> {
        let rest = t.split(&format!(" {name}=\"")).nth(1)?;
        rest.split('"').next()?.parse().ok()
    };
    let width = attr(svg.lines().next().unwrap(), "width").unwrap();
    let texts: Vec<(&str, &str)> = svg
        .lines()
        .filter(|l| l.starts_with("<text"))
        .filter_map(|l| {
            let (tag, rest) = l.split_once('>')?;
            Some((tag, rest.strip_suffix("</text>")?))
        })
        .collect();
    let titles: Vec<&str> = texts
        .iter()
        .filter(|(t, _)| t.contains("font-weight=\"bold\""))
        .map(|(_, s)| *s)
        .collect();
    assert_eq!(titles[0], "lab-frame: C1L@J1L (alarm)", "{titles:?}");
    assert_eq!(titles.len(), 17);
    let axes = texts
        .iter()
        .filter(|(_, s)| s.starts_with("θ, stiffness / nominal"));
    assert_eq!(axes.count(), 17, "θ's unit on every panel");
    for (tag, text) in &texts {
        let x = attr(tag, "x").unwrap();
        let w = 7.0 * text.chars().count() as f64;
        let (from, to) = if tag.contains("text-anchor=\"end\"") {
            (x - w, x)
        } else if tag.contains("text-anchor=\"middle\"") || tag.contains("rotate(") {
            (x - w / 2.0, x + w / 2.0)
        } else {
            (x, x + w)
        };
        if !tag.contains("rotate(") {
            assert!(
                from >= 0.0 && to <= width,
                "`{text}` at {x} runs past 0..{width}"
            );
        }
    }
}

/// Bad configuration fails at start, exit code 2, naming the key; a rejected input is not
/// a configuration error.
#[test]
fn bad_configuration_fails_naming_the_key() {
    let d = tmp_dir("config");
    let rec = d.join("rec.mcap");
    make_scenario("healthy", 3, 1.0, &rec);
    for (text, key) in [
        (
            "[tracker.alerts]\nalarm_drop = 2.0\n",
            "tracker.alerts.alarm_drop",
        ),
        ("[tracker]\nbaseline_set = 5\n", "baseline_set"),
        (
            "[tracker.drift]\nlevel_per_day = \"fast\"\n",
            "level_per_day",
        ),
        (
            "[[structures]]\nname = \"lab/frame\"\nmodel = \"x.toml\"\n",
            "structures[0].name",
        ),
    ] {
        let c = d.join("bad.toml");
        std::fs::write(&c, text).unwrap();
        let o = bin()
            .arg("replay")
            .arg(&rec)
            .arg("--config")
            .arg(&c)
            .arg("-o")
            .arg(d.join("o.mcap"))
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{text}: {err}");
        assert!(err.contains(key), "{text}: {err}");
    }
    let o = bin()
        .arg("replay")
        .arg(&rec)
        .arg("-o")
        .arg(d.join("o.mcap"))
        .env("BOLTWATCH__TRACKER__ALERTS__PERSISTENCE", "0")
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("tracker.alerts.persistence"));
}

/// The binary works from any folder: the default configuration's model is compiled in
/// (`bundled:lab-frame`), and a relative path in a configuration file is relative to that
/// file, not to the working directory. Run from an empty folder elsewhere, a replay of a
/// bundled recording with the defaults and one with a configuration file beside a copied
/// model (`model = "models/frame.toml"`) give the same bytes; a bundled model that does
/// not exist is named, with the ones that do.
#[test]
fn replay_works_from_any_folder_with_paths_relative_to_the_configuration() {
    let d = tmp_dir("anywhere");
    let cwd = d.join("elsewhere");
    let site = d.join("site");
    std::fs::create_dir_all(&cwd).unwrap();
    std::fs::create_dir_all(site.join("models")).unwrap();
    let rec = d.join("rec.mcap");
    make_scenario("healthy", 30, 1.0, &rec);
    let repo = Path::new(env!("CARGO_MANIFEST_DIR"));
    std::fs::copy(
        repo.join("config/models/lab-frame.toml"),
        site.join("models/frame.toml"),
    )
    .unwrap();
    let config = site.join("boltwatch.toml");
    std::fs::write(
        &config,
        "[[structures]]\nname = \"lab-frame\"\nmodel = \"models/frame.toml\"\n",
    )
    .unwrap();
    let replay = |config: Option<&Path>, out: &str| {
        let mut c = bin();
        c.current_dir(&cwd)
            .arg("replay")
            .arg(&rec)
            .arg("-o")
            .arg(out);
        if let Some(f) = config {
            c.arg("--config").arg(f);
        }
        let o = c.envs(ENV).output().unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        std::fs::read(cwd.join(out)).unwrap()
    };
    let bundled = replay(None, "bundled.mcap");
    let beside = replay(Some(&config), "beside.mcap");
    assert!(!bundled.is_empty());
    assert!(bundled == beside, "the bundled and the copied model differ");
    std::fs::write(
        &config,
        "[[structures]]\nname = \"lab-frame\"\nmodel = \"bundled:lab-fram\"\n",
    )
    .unwrap();
    let o = bin()
        .current_dir(&cwd)
        .arg("replay")
        .arg(&rec)
        .arg("--config")
        .arg(&config)
        .arg("-o")
        .arg("x.mcap")
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(
        err.contains("no bundled model `lab-fram`") && err.contains("bundled:lab-frame"),
        "{err}"
    );
}
