//! The typed wire contracts (issue 22) against the JSON Schemas stored in MCAP files and
//! against their own bytes: every output of a bundled replay, and a rejection, validates
//! against its schema (an independent validator, the `jsonschema` crate), reads back into
//! its type and writes the same bytes again, so the types hold the whole v1 wire form.

use std::path::Path;

use boltwatch::contract::{Alert, AlertDetail, Output, Rejected, Verdict};
use boltwatch::io::mcap::read_all;
use boltwatch::io::schemas::for_topic;
use boltwatch::pipeline::Tracker;
use serde_json::Value;

use super::common::load_model;
use super::tracker::{run_replay, settings, tmp_dir};

/// Validates `bytes` against the schema of topic `suffix`, reads it into its type and
/// checks that it writes the same bytes.
fn check(suffix: &str, bytes: &[u8]) -> Output {
    let (_, text) = for_topic(suffix).unwrap();
    let instance: Value = serde_json::from_slice(bytes).unwrap();
    let errors = super::common::schema_errors(text, &instance);
    assert!(
        errors.is_empty(),
        "{suffix}: {errors:?}\n{}",
        String::from_utf8_lossy(bytes)
    );
    let o = Output::from_wire(suffix, bytes).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(o.topic(), suffix);
    assert!(
        o.to_wire() == bytes,
        "{suffix}: read and written again, the bytes differ:\n{}\n{}",
        String::from_utf8_lossy(bytes),
        String::from_utf8_lossy(&o.to_wire())
    );
    o
}

/// The `mass` recording (an unmodelled mass: model-inadequacy alerts with a diagnosis
/// verdict, loosening warnings flagged inadequate) with a cross-check every 150 sets.
#[test]
fn every_output_of_a_replay_fits_its_schema_and_type() {
    let d = tmp_dir("contract");
    let out = d.join("mass.out.mcap");
    run_replay(
        Path::new("recordings/mass.mcap"),
        &out,
        settings(&[("BOLTWATCH__TRACKER__CROSSCHECK_EVERY_SETS", "150")]),
    );
    let mut seen = std::collections::BTreeMap::<&str, usize>::new();
    let (mut verdicts, mut loosening) = (0, 0);
    for m in read_all(&out).unwrap() {
        let suffix = m.topic.rsplit('/').next().unwrap();
        let o = check(suffix, &m.data);
        *seen.entry(o.topic()).or_default() += 1;
        if let Output::Alert(a) = &o {
            match &a.detail {
                AlertDetail::Inadequacy {
                    diagnosis: Some(Verdict::Found { .. }),
                    ..
                } => verdicts += 1,
                AlertDetail::Loosening { .. } => loosening += 1,
                _ => {}
            }
        }
    }
    assert_eq!(seen.get("stiffness"), Some(&700), "{seen:?}");
    assert!(seen.get("crosscheck") >= Some(&4), "{seen:?}");
    assert!(
        verdicts >= 1 && loosening >= 1,
        "{verdicts} verdicts, {loosening} loosening"
    );
}

/// A rejection (not JSON; and a payload past the echo limit) fits its schema and type, and
/// a reader of another message's bytes is told which schema it got.
#[test]
fn a_rejection_fits_its_schema_and_type() {
    let mut t = Tracker::new(load_model("lab-frame"), settings(&[]).tracker.clone()).unwrap();
    let mut long = b"{\"schema\": \"".to_vec();
    long.extend(std::iter::repeat_n(b'x', 10_000));
    for payload in [&b"{not json"[..], &long] {
        let actions = t.handle(chrono::Utc::now(), payload);
        let [boltwatch::pipeline::Action::Publish(o)] = &actions[..] else {
            panic!("{actions:?}")
        };
        let Output::Rejected(r) = check("rejected", &o.to_wire()) else {
            panic!("not a rejection")
        };
        assert_eq!(r.payload_bytes, payload.len());
        assert_eq!(r.truncated, payload.len() > 4096);
    }
    let alert_bytes = br#"{"schema":"boltwatch.rejected.v1"}"#;
    let e = serde_json::from_slice::<Alert>(alert_bytes).unwrap_err();
    assert!(
        e.to_string()
            .contains("schema is `boltwatch.rejected.v1`, expected `boltwatch.alert.v1`"),
        "{e}"
    );
    let e =
        serde_json::from_slice::<Rejected>(br#"{"schema":"boltwatch.rejected.v2"}"#).unwrap_err();
    assert!(
        e.to_string().contains("expected `boltwatch.rejected.v1`"),
        "{e}"
    );
}

/// A queue report (sets dropped at a full queue) fits the rejection's schema, which
/// describes its `dropped` count: a count that is not a positive integer does not fit.
#[test]
fn a_queue_report_fits_the_rejection_schema() {
    let r = Rejected::dropped(
        "lab-frame",
        chrono::Utc::now(),
        3,
        7,
        "queue full: 3 modal set(s) dropped unprocessed".into(),
    );
    let o = check("rejected", &Output::Rejected(Box::new(r)).to_wire());
    let Output::Rejected(r) = o else {
        panic!("not a rejection")
    };
    assert_eq!(r.dropped, Some(3));
    let (_, text) = for_topic("rejected").unwrap();
    let mut instance: Value = serde_json::from_slice(&Output::Rejected(r).to_wire()).unwrap();
    for bad in [
        serde_json::json!("3"),
        serde_json::json!(0),
        serde_json::json!(1.5),
    ] {
        instance["dropped"] = bad.clone();
        assert!(
            !super::common::schema_errors(text, &instance).is_empty(),
            "dropped = {bad} fits the schema"
        );
    }
}
