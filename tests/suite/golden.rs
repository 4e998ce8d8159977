//! The wire bytes do not move: every bundled recording replayed, and the JSON of
//! `simulate`, `modes`, `update` (mode matching, Bayesian, two-stage), `sweep-sigma` and
//! `diagnose`, each reduced to a SHA-256 digest and compared with `tests/golden/digests.txt`.
//!
//! What is digested: for an MCAP output, every message in file order (topic, sequence, log
//! and publish time, payload bytes), not the file (its chunking and compression are not the
//! contract); for a JSON file, its bytes with every `"seconds"` value (wall-clock time) set
//! to `null`. A change of the wire form is a new schema version: regenerate the digests
//! with `BOLTWATCH_BLESS=1 cargo test golden` and say so in the commit.
//!
//! Slow tier (`cargo test --features slow-tests`).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;

use boltwatch::io::mcap::read_all;
use serde_json::Value;
use sha2::{Digest, Sha256};

use super::common::model_path;

const DIGESTS: &str = "tests/golden/digests.txt";

fn boltwatch(args: &[&str]) {
    let out = Command::new(env!("CARGO_BIN_EXE_boltwatch"))
        .args(args)
        .env("BOLTWATCH__LOG__LEVEL", "warn")
        .output()
        .expect("binary runs");
    assert!(
        out.status.success(),
        "boltwatch {}: {}",
        args.join(" "),
        String::from_utf8_lossy(&out.stderr)
    );
}

fn hex(d: impl AsRef<[u8]>) -> String {
    d.as_ref().iter().map(|b| format!("{b:02x}")).collect()
}

/// Digest of an MCAP file's messages (module docs).
fn mcap_digest(path: &Path) -> String {
    let mut h = Sha256::new();
    for m in read_all(path).unwrap() {
        h.update(m.topic.as_bytes());
        h.update([0]);
        h.update(m.sequence.to_le_bytes());
        h.update(m.log_time.to_le_bytes());
        h.update(m.publish_time.to_le_bytes());
        h.update((m.data.len() as u64).to_le_bytes());
        h.update(&m.data);
    }
    hex(h.finalize())
}

/// Every `"seconds"` value set to `null`, recursively.
fn without_seconds(v: &mut Value) {
    match v {
        Value::Object(map) => {
            for (k, x) in map.iter_mut() {
                if k == "seconds" {
                    *x = Value::Null;
                } else {
                    without_seconds(x);
                }
            }
        }
        Value::Array(a) => a.iter_mut().for_each(without_seconds),
        _ => {}
    }
}

/// Digest of a JSON file (module docs): its bytes with only the `"seconds"` numbers
/// replaced. The file must read back to its own bytes through serde_json (checked), so the
/// digest covers key order and number formatting as written.
fn json_digest(path: &Path) -> String {
    let text = std::fs::read_to_string(path).unwrap();
    let mut v: Value = serde_json::from_str(&text).unwrap();
    let write = |v: &Value| {
        if text.trim_end().contains('\n') {
            serde_json::to_string_pretty(v).unwrap()
        } else {
            serde_json::to_string(v).unwrap()
        }
    };
    assert_eq!(
        write(&v),
        text.trim_end(),
        "{} does not read back to its own bytes",
        path.display()
    );
    without_seconds(&mut v);
    hex(Sha256::digest(write(&v).as_bytes()))
}

fn dir() -> PathBuf {
    let d = std::env::temp_dir().join(format!("bw-golden-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn p(path: &Path) -> &str {
    path.to_str().unwrap()
}

/// Every output's digest, by name.
fn digests() -> BTreeMap<String, String> {
    let d = dir();
    let mut out = BTreeMap::new();
    for rec in ["healthy", "loosening", "sudden", "mass", "seasonal"] {
        let o = d.join(format!("{rec}.out.mcap"));
        boltwatch(&[
            "replay",
            &format!("recordings/{rec}.mcap"),
            "-o",
            p(&o),
            "--checkpoint",
            p(&d.join(format!("{rec}.ckpt.json"))),
        ]);
        out.insert(format!("replay/{rec}"), mcap_digest(&o));
    }
    let lab = model_path("lab-frame");
    let simplified = model_path("lab-frame-simplified");
    let data = "recordings/lab-frame-modal-set.json";
    let json = |name: &str, args: &[&str], file: &Path, out: &mut BTreeMap<String, String>| {
        boltwatch(args);
        out.insert(name.to_string(), json_digest(file));
    };
    let sim = d.join("simulated.json");
    json(
        "simulate",
        &[
            "simulate",
            "--model",
            &lab,
            "--modes",
            "9",
            "--seed",
            "5",
            "-o",
            p(&sim),
        ],
        &sim,
        &mut out,
    );
    let modes = d.join("modes.json");
    json(
        "modes",
        &["modes", "--model", &lab, "-n", "9", "-o", p(&modes)],
        &modes,
        &mut out,
    );
    let mm = d.join("update-mm.json");
    json(
        "update/mode-matching",
        &["update", "--model", &lab, "--data", data, "-o", p(&mm)],
        &mm,
        &mut out,
    );
    let bayes = d.join("update-bayes.json");
    json(
        "update/bayesian",
        &[
            "update",
            "--method",
            "bayesian",
            "--model",
            &lab,
            "--data",
            data,
            "-o",
            p(&bayes),
        ],
        &bayes,
        &mut out,
    );
    let two = d.join("update-two-stage.json");
    json(
        "update/two-stage",
        &[
            "update",
            "--method",
            "bayesian",
            "--model",
            &lab,
            "--data",
            data,
            "--stage1-model",
            &simplified,
            "--stage1-sigma-c",
            "1e3",
            "--sigma-c",
            "1e3",
            "-o",
            p(&two),
        ],
        &two,
        &mut out,
    );
    let sweep = d.join("sweep");
    boltwatch(&[
        "sweep-sigma",
        "--model",
        &lab,
        "--data",
        data,
        "--from",
        "10",
        "--to",
        "1e5",
        "--points",
        "4",
        "-o",
        p(&sweep),
    ]);
    out.insert("sweep-sigma".into(), json_digest(&sweep.join("sweep.json")));
    let injected = d.join("injected.json");
    boltwatch(&[
        "simulate",
        "--model",
        &lab,
        "--modes",
        "9",
        "--seed",
        "3",
        "--inject",
        "added-mass@J2L=0.8",
        "-o",
        p(&injected),
    ]);
    let diag = d.join("diagnosis");
    boltwatch(&[
        "diagnose",
        "--model",
        &lab,
        "--data",
        p(&injected),
        "-o",
        p(&diag),
    ]);
    out.insert("diagnose".into(), json_digest(&diag.join("diagnosis.json")));
    let _ = std::fs::remove_dir_all(&d);
    out
}

#[test]
#[cfg_attr(
    not(feature = "slow-tests"),
    ignore = "slow tier: cargo test --features slow-tests"
)]
fn outputs_match_the_stored_digests() {
    let now = digests();
    let text: String = now.iter().map(|(k, v)| format!("{k} {v}\n")).collect();
    if std::env::var_os("BOLTWATCH_BLESS").is_some() {
        std::fs::create_dir_all("tests/golden").unwrap();
        std::fs::write(DIGESTS, &text).unwrap();
        return;
    }
    let stored: BTreeMap<String, String> = std::fs::read_to_string(DIGESTS)
        .unwrap_or_else(|e| panic!("{DIGESTS}: {e}"))
        .lines()
        .filter_map(|l| {
            let (k, v) = l.split_once(' ')?;
            Some((k.to_string(), v.to_string()))
        })
        .collect();
    let differ: std::collections::BTreeSet<&String> = now
        .keys()
        .chain(stored.keys())
        .filter(|k| now.get(*k) != stored.get(*k))
        .collect();
    assert!(
        differ.is_empty(),
        "outputs changed: {differ:?}\nnow:\n{text}(a new schema version? BOLTWATCH_BLESS=1)"
    );
}
