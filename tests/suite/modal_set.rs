//! The `boltwatch.modal_set.v1` contract: one test per rejection rule, round trip, NaN handling.

use boltwatch::contract::modal_set::*;
use chrono::{DateTime, TimeZone, Utc};
use serde_json::{Value, json};

fn model_channels() -> Vec<String> {
    vec!["C1L.1".to_string(), "C1L.2".into(), "C1L.3".into()]
}

const STRUCTURES: &[&str] = &["lab-frame", "bridge-7"];

fn t(s: &str) -> DateTime<Utc> {
    DateTime::parse_from_rfc3339(s).unwrap().with_timezone(&Utc)
}

/// A valid set with every optional field, including an unmeasured shape entry.
fn full() -> Value {
    json!({
        "schema": "boltwatch.modal_set.v1",
        "structure": "lab-frame",
        "time": "2026-11-21T10:00:00Z",
        "channels": ["C1L.1", "C1L.2"],
        "modes": [
            {"frequency_hz": 9.71, "frequency_cov": 0.01, "shape": [0.12, null], "shape_nsd": 0.05},
            {"frequency_hz": 31.4, "frequency_cov": 0.02, "shape": [-0.5, 1.0], "shape_nsd": 0.07},
            {"frequency_hz": 55.0, "frequency_cov": 0.015}
        ],
        "temperature_c": 20.5,
        "source": "ssi-cov run 42"
    })
}

fn parse_with(
    payload: &[u8],
    last: Option<DateTime<Utc>>,
    allow_equal: bool,
) -> Result<ModalSet, Rejection> {
    let channels = model_channels();
    let ctx = ValidationContext {
        structures: STRUCTURES,
        model_channels: &channels,
        last_time: last,
        allow_equal_time: allow_equal,
        max_future: None,
    };
    parse_modal_set(payload, &ctx)
}

fn parse_bytes(payload: &[u8]) -> Result<ModalSet, Rejection> {
    parse_with(payload, None, false)
}

fn parse(v: &Value) -> Result<ModalSet, Rejection> {
    parse_bytes(v.to_string().as_bytes())
}

/// Asserts a rejection on `field` whose reason contains every one of `needles`.
#[track_caller]
fn assert_rejected(result: Result<ModalSet, Rejection>, field: &str, needles: &[&str]) {
    let r = match result {
        Ok(set) => panic!("expected a rejection on {field}, accepted {set:?}"),
        Err(r) => r,
    };
    assert_eq!(r.field, field, "wrong field; reason: {}", r.reason);
    for n in needles {
        assert!(r.reason.contains(n), "reason {:?} lacks {n:?}", r.reason);
    }
}

/// `full()` with `f` applied.
fn with(f: impl FnOnce(&mut Value)) -> Value {
    let mut v = full();
    f(&mut v);
    v
}

#[test]
fn full_set_parses_to_expected_values() {
    let set = parse(&full()).unwrap();
    assert_eq!(set.structure, "lab-frame");
    assert_eq!(
        set.time,
        Utc.with_ymd_and_hms(2026, 11, 21, 10, 0, 0).unwrap()
    );
    assert_eq!(set.channels, vec!["C1L.1".to_string(), "C1L.2".into()]);
    assert_eq!(set.modes.len(), 3);
    assert_eq!(
        set.modes[0],
        MeasuredMode {
            frequency_hz: 9.71,
            frequency_cov: Some(0.01),
            shape: Some(vec![Some(0.12), None]),
            shape_nsd: Some(0.05),
            shape_std: None,
            damping_ratio: None,
            damping_std: None,
            label: None,
        }
    );
    assert_eq!(set.modes[2].shape, None);
    assert_eq!(set.temperature_c, Some(20.5));
    assert_eq!(set.source.as_deref(), Some("ssi-cov run 42"));
}

#[test]
fn valid_full_set_round_trips_through_to_json() {
    let set = parse(&full()).unwrap();
    let json = set.to_json();
    assert_eq!(json, full(), "to_json reproduces the canonical message");
    let back = parse_bytes(&serde_json::to_vec(&json).unwrap()).unwrap();
    assert_eq!(back, set);
}

#[test]
fn round_trip_keeps_sub_seconds_and_awkward_floats() {
    let set = ModalSet {
        structure: "bridge-7".into(),
        time: t("2026-11-21T10:00:00.123456Z"),
        channels: model_channels(),
        modes: vec![
            MeasuredMode {
                frequency_hz: 0.1 + 0.2,
                frequency_cov: None,
                shape: Some(vec![None, Some(1e-300), Some(-123456.789e10)]),
                shape_nsd: None,
                shape_std: None,
                damping_ratio: None,
                damping_std: None,
                label: Some("mode 1".into()),
            },
            MeasuredMode {
                frequency_hz: 1.0 / 3.0,
                frequency_cov: None,
                shape: None,
                shape_nsd: None,
                shape_std: None,
                damping_ratio: None,
                damping_std: None,
                label: None,
            },
        ],
        temperature_c: None,
        source: None,
        missing: vec!["mode 2".into()],
        unexplained_peaks: Vec::new(),
        covariates: Default::default(),
    };
    let json = set.to_json();
    assert_eq!(json["time"], "2026-11-21T10:00:00.123456Z");
    assert!(json.get("temperature_c").is_none() && json.get("source").is_none());
    assert!(json["modes"][0].get("frequency_cov").is_none());
    assert_eq!(parse(&json).unwrap(), set);
}

#[test]
fn to_json_writes_whole_seconds_without_fraction() {
    let set = parse(&full()).unwrap();
    assert_eq!(set.to_json()["time"], "2026-11-21T10:00:00Z");
}

#[test]
fn frequency_only_modes_are_accepted() {
    let v = json!({
        "schema": "boltwatch.modal_set.v1", "structure": "lab-frame",
        "time": "2026-11-21T10:00:00+01:00",
        "modes": [{"frequency_hz": 9.71}, {"frequency_hz": 31}]
    });
    let set = parse(&v).unwrap();
    assert!(set.channels.is_empty());
    assert_eq!(set.modes[1].frequency_hz, 31.0);
    assert!(set.modes.iter().all(|m| m.shape.is_none()));
    assert_eq!(set.time, t("2026-11-21T09:00:00Z"));
    // Empty channels are fine too when no mode has a shape.
    let v2 = with(|v| {
        v["channels"] = json!([]);
        v["modes"] = json!([{"frequency_hz": 9.71}]);
    });
    assert!(parse(&v2).is_ok());
}

// Rule 1: payload.
#[test]
fn rejects_payload_not_utf8() {
    assert_rejected(
        parse_bytes(b"{\"schema\": \"\xff\xfe\"}"),
        "payload",
        &["UTF-8"],
    );
}

#[test]
fn rejects_payload_not_json() {
    assert_rejected(
        parse_bytes(b"{\"schema\": "),
        "payload",
        &["not JSON", "EOF"],
    );
}

#[test]
fn rejects_payload_not_object() {
    assert_rejected(parse_bytes(b"[1, 2]"), "payload", &["object", "array"]);
}

// Rule 2: schema.
#[test]
fn rejects_missing_schema() {
    let v = with(|v| {
        v.as_object_mut().unwrap().remove("schema");
    });
    assert_rejected(parse(&v), "schema", &["missing"]);
}

#[test]
fn rejects_wrong_schema() {
    let v = with(|v| v["schema"] = json!("boltwatch.modal_set.v2"));
    assert_rejected(
        parse(&v),
        "schema",
        &["boltwatch.modal_set.v1", "boltwatch.modal_set.v2"],
    );
}

// Rule 3: non-finite numbers.
#[test]
fn python_nan_in_shape_entry_names_the_entry() {
    let payload = br#"{"schema": "boltwatch.modal_set.v1", "structure": "lab-frame",
        "time": "2026-11-21T10:00:00Z", "channels": ["C1L.1", "C1L.2", "C1L.3"],
        "modes": [{"frequency_hz": 9.71, "shape": [0.1, 0.2, NaN]}]}"#;
    assert_rejected(
        parse_bytes(payload),
        "modes[0].shape[2]",
        &["not a finite number (NaN)"],
    );
}

#[test]
fn python_infinity_names_the_field() {
    let payload = br#"{"schema": "boltwatch.modal_set.v1", "structure": "lab-frame",
        "time": "2026-11-21T10:00:00Z", "channels": ["C1L.1"],
        "modes": [{"frequency_hz": 9.71, "shape": [-Infinity]}, {"frequency_hz": Infinity}]}"#;
    assert_rejected(parse_bytes(payload), "modes[0].shape[0]", &["-Infinity"]);
    let payload = br#"{"schema": "boltwatch.modal_set.v1", "structure": "lab-frame",
        "time": "2026-11-21T10:00:00Z", "modes": [{"frequency_hz":Infinity}]}"#;
    assert_rejected(
        parse_bytes(payload),
        "modes[0].frequency_hz",
        &["not a finite number (Infinity)"],
    );
    let payload = br#"{"schema": "boltwatch.modal_set.v1", "structure": "lab-frame",
        "time": "2026-11-21T10:00:00Z", "modes": [{"frequency_hz": 1}], "temperature_c": NaN}"#;
    assert_rejected(parse_bytes(payload), "temperature_c", &["NaN"]);
}

#[test]
fn overflowing_number_names_the_field() {
    let payload = br#"{"schema": "boltwatch.modal_set.v1", "structure": "lab-frame",
        "time": "2026-11-21T10:00:00Z", "modes": [{"frequency_hz": 1, "frequency_cov": 1e999}]}"#;
    assert_rejected(
        parse_bytes(payload),
        "modes[0].frequency_cov",
        &["1e999", "overflows"],
    );
}

/// Overflow without an exponent (a 400-digit literal), and one at a shape entry: the quick
/// pre-scan must still send both to the full check.
#[test]
fn overflowing_digit_runs_and_shape_entries_name_the_field() {
    let big = format!("1{}", "0".repeat(400));
    let payload = format!(
        r#"{{"schema": "boltwatch.modal_set.v1", "structure": "lab-frame",
        "time": "2026-11-21T10:00:00Z", "modes": [{{"frequency_hz": {big}}}]}}"#
    );
    assert_rejected(
        parse_bytes(payload.as_bytes()),
        "modes[0].frequency_hz",
        &["overflows"],
    );
    let payload = br#"{"schema": "boltwatch.modal_set.v1", "structure": "lab-frame",
        "time": "2026-11-21T10:00:00Z", "channels": ["C1L.1", "C1L.2"],
        "modes": [{"frequency_hz": 1, "shape": [1.0, -2E+308]}]}"#;
    assert_rejected(parse_bytes(payload), "modes[0].shape[1]", &["overflows"]);
}

#[test]
fn nan_inside_a_string_value_is_not_touched() {
    let payload = br#"{"schema": "boltwatch.modal_set.v1", "structure": "lab-frame",
        "time": "2026-11-21T10:00:00Z", "modes": [{"frequency_hz": 1}],
        "source": "NaN run \"Infinity\" \\ -Infinity 1e999"}"#;
    let set = parse_bytes(payload).unwrap();
    assert_eq!(
        set.source.as_deref(),
        Some(r#"NaN run "Infinity" \ -Infinity 1e999"#)
    );
}

#[test]
fn bare_nan_where_a_string_is_expected_is_rejected() {
    let payload = br#"{"schema": "boltwatch.modal_set.v1", "structure": "lab-frame",
        "time": "2026-11-21T10:00:00Z", "modes": [{"frequency_hz": 1}], "source": NaN}"#;
    assert_rejected(
        parse_bytes(payload),
        "source",
        &["expected a string", "NaN"],
    );
}

// Rule 4: wrong JSON types.
#[test]
fn rejects_string_where_a_number_is_expected() {
    let v = with(|v| v["modes"][1]["frequency_hz"] = json!("31.4"));
    assert_rejected(
        parse(&v),
        "modes[1].frequency_hz",
        &["expected a number, got a string"],
    );
    let v = with(|v| v["temperature_c"] = json!(true));
    assert_rejected(
        parse(&v),
        "temperature_c",
        &["expected a number, got a boolean"],
    );
    let v = with(|v| v["modes"][0]["shape"][1] = json!("x"));
    assert_rejected(
        parse(&v),
        "modes[0].shape[1]",
        &["expected a number or null, got a string"],
    );
    let v = with(|v| v["channels"][1] = json!(2));
    assert_rejected(
        parse(&v),
        "channels[1]",
        &["expected a string, got a number"],
    );
}

// Rule 5.
#[test]
fn rejects_non_positive_frequency() {
    let v = with(|v| v["modes"][1]["frequency_hz"] = json!(-3));
    assert_rejected(parse(&v), "modes[1].frequency_hz", &["must be > 0", "-3"]);
    let v = with(|v| v["modes"][0]["frequency_hz"] = json!(0.0));
    assert_rejected(
        parse(&v),
        "modes[0].frequency_hz",
        &["must be > 0", "got 0"],
    );
}

// Rule 6.
#[test]
fn rejects_decreasing_frequencies() {
    let v = with(|v| v["modes"][2]["frequency_hz"] = json!(30.0));
    assert_rejected(parse(&v), "modes[2].frequency_hz", &["30", "31.4"]);
}

#[test]
fn accepts_frequencies_equal_within_tolerance() {
    let f = 31.4 * (1.0 - 0.5 * FREQUENCY_ORDER_TOLERANCE);
    let v = with(|v| v["modes"][2]["frequency_hz"] = json!(f));
    assert!(parse(&v).is_ok());
    let v = with(|v| v["modes"][2]["frequency_hz"] = json!(31.4));
    assert!(parse(&v).is_ok());
    let f = 31.4 * (1.0 - 2.0 * FREQUENCY_ORDER_TOLERANCE);
    let v = with(|v| v["modes"][2]["frequency_hz"] = json!(f));
    assert_rejected(parse(&v), "modes[2].frequency_hz", &["31.4"]);
}

// Rule 7.
#[test]
fn rejects_shape_length_mismatch() {
    let v = with(|v| v["modes"][1]["shape"] = json!([0.1, 0.2, 0.3]));
    assert_rejected(parse(&v), "modes[1].shape", &["3", "2"]);
    // A shape without channels.
    let v = with(|v| {
        v.as_object_mut().unwrap().remove("channels");
    });
    assert_rejected(parse(&v), "modes[0].shape", &["2", "0"]);
}

// Rule 8.
#[test]
fn rejects_unknown_channel() {
    let v = with(|v| v["channels"][1] = json!("C9R.4"));
    assert_rejected(parse(&v), "channels[1]", &["C9R.4"]);
}

#[test]
fn rejects_duplicate_channel() {
    let v = with(|v| v["channels"] = json!(["C1L.2", "C1L.2"]));
    assert_rejected(parse(&v), "channels[1]", &["duplicate", "C1L.2"]);
}

// Rule 9.
#[test]
fn rejects_all_null_shape() {
    let v = with(|v| v["modes"][1]["shape"] = json!([null, null]));
    assert_rejected(parse(&v), "modes[1].shape", &["null"]);
}

#[test]
fn rejects_empty_shape() {
    let v = with(|v| {
        v["channels"] = json!([]);
        v["modes"] = json!([{"frequency_hz": 9.71, "shape": []}]);
    });
    assert_rejected(parse(&v), "modes[0].shape", &["empty"]);
}

// Rule 10.
#[test]
fn rejects_non_positive_frequency_cov() {
    let v = with(|v| v["modes"][2]["frequency_cov"] = json!(0));
    assert_rejected(
        parse(&v),
        "modes[2].frequency_cov",
        &["must be > 0", "got 0"],
    );
}

#[test]
fn rejects_non_positive_shape_nsd() {
    let v = with(|v| v["modes"][1]["shape_nsd"] = json!(-0.07));
    assert_rejected(parse(&v), "modes[1].shape_nsd", &["must be > 0", "-0.07"]);
}

#[test]
fn rejects_shape_nsd_without_shape() {
    let v = with(|v| v["modes"][2]["shape_nsd"] = json!(0.07));
    assert_rejected(parse(&v), "modes[2].shape_nsd", &["without a shape"]);
}

// Rule 11.
#[test]
fn rejects_unwatched_structure() {
    let v = with(|v| v["structure"] = json!("tower-3"));
    assert_rejected(
        parse(&v),
        "structure",
        &["tower-3", "lab-frame", "bridge-7"],
    );
}

// Rule 12.
#[test]
fn rejects_time_before_last_accepted() {
    let last = t("2026-11-21T10:00:01Z");
    let payload = full().to_string();
    assert_rejected(
        parse_with(payload.as_bytes(), Some(last), true),
        "time",
        &["2026-11-21T10:00:00Z", "2026-11-21T10:00:01Z"],
    );
    assert!(parse_with(payload.as_bytes(), Some(t("2026-11-21T09:59:59Z")), false).is_ok());
}

/// The rules that need the receiver's state (the time against the last accepted set) can
/// run after the others, on another thread ([`screen_modal_set`], [`Screened::finish`]),
/// and a payload still gets the verdict of the first rule it breaks in the order of the
/// rules: a stale time before a bad channel, a bad schema before a stale time.
#[test]
fn screening_ahead_keeps_the_order_of_the_rules() {
    let channels = model_channels();
    let ctx = |last: Option<DateTime<Utc>>| ValidationContext {
        structures: STRUCTURES,
        model_channels: &channels,
        last_time: last,
        allow_equal_time: false,
        max_future: None,
    };
    let stateless = ctx(None);
    let last = Some(t("2026-11-21T10:00:01Z"));
    let bad_channel = with(|v| v["channels"] = json!(["C1L.1", "C9X.1"]));
    let bad_schema = with(|v| v["schema"] = json!("boltwatch.modal_set.v0"));
    for (v, last, field) in [
        (full(), last, "time"),
        (bad_channel.clone(), last, "time"),
        (bad_channel, None, "channels[1]"),
        (bad_schema, last, "schema"),
    ] {
        let obj = modal_set_object(v.to_string().as_bytes()).unwrap();
        let ahead = screen_modal_set(&obj, &stateless).finish(&ctx(last));
        assert_eq!(ahead, validate_modal_set(&obj, &ctx(last)));
        assert_rejected(ahead, field, &[]);
    }
    let obj = modal_set_object(full().to_string().as_bytes()).unwrap();
    let ok = screen_modal_set(&obj, &stateless).finish(&ctx(Some(t("2026-11-21T09:00:00Z"))));
    assert_eq!(ok, parse(&full()));
}

#[test]
fn rejects_equal_time_unless_allowed() {
    let last = t("2026-11-21T10:00:00Z");
    let payload = full().to_string();
    assert_rejected(
        parse_with(payload.as_bytes(), Some(last), false),
        "time",
        &["2026-11-21T10:00:00Z"],
    );
}

#[test]
fn accepts_equal_time_when_allowed() {
    let last = t("2026-11-21T10:00:00Z");
    let payload = full().to_string();
    let set = parse_with(payload.as_bytes(), Some(last), true).unwrap();
    assert_eq!(set.time, last);
}

#[test]
fn rejects_unparseable_time() {
    let v = with(|v| v["time"] = json!("21/11/2026 10:00"));
    assert_rejected(parse(&v), "time", &["21/11/2026 10:00", "RFC 3339"]);
    let v = with(|v| {
        v.as_object_mut().unwrap().remove("time");
    });
    assert_rejected(parse(&v), "time", &["missing"]);
}

// Rule 13.
#[test]
fn rejects_mixed_frequency_cov() {
    let v = with(|v| {
        v["modes"][1]
            .as_object_mut()
            .unwrap()
            .remove("frequency_cov");
    });
    assert_rejected(
        parse(&v),
        "modes[1].frequency_cov",
        &["present on some modes but not others"],
    );
}

#[test]
fn rejects_mixed_shape_nsd() {
    let v = with(|v| {
        v["modes"][0].as_object_mut().unwrap().remove("shape_nsd");
    });
    assert_rejected(
        parse(&v),
        "modes[1].shape_nsd",
        &["present on some modes but not others"],
    );
}

// Rule 14.
#[test]
fn rejects_missing_or_empty_modes() {
    let v = with(|v| {
        v.as_object_mut().unwrap().remove("modes");
    });
    assert_rejected(parse(&v), "modes", &["missing"]);
    let v = with(|v| v["modes"] = json!([]));
    assert_rejected(parse(&v), "modes", &["empty"]);
}

#[test]
fn rejects_unknown_top_level_field() {
    let v = with(|v| v["humidity"] = json!(0.4));
    assert_rejected(parse(&v), "humidity", &["unknown field"]);
}

#[test]
fn rejects_unknown_mode_field() {
    let v = with(|v| v["modes"][1]["damping"] = json!(0.02));
    assert_rejected(parse(&v), "modes[1].damping", &["unknown field"]);
}

#[test]
fn rejects_null_for_an_optional_field() {
    let v = with(|v| v["temperature_c"] = Value::Null);
    assert_rejected(parse(&v), "temperature_c", &["got null"]);
}

#[test]
fn has_uncertainties_true_when_all_modes_carry_them() {
    assert!(parse(&full()).unwrap().has_uncertainties());
}

#[test]
fn has_uncertainties_false_when_none_do() {
    let v = with(|v| {
        for m in v["modes"].as_array_mut().unwrap() {
            let m = m.as_object_mut().unwrap();
            m.remove("frequency_cov");
            m.remove("shape_nsd");
        }
    });
    assert!(!parse(&v).unwrap().has_uncertainties());
    // Frequency uncertainties without shape uncertainties are not enough to weight.
    let v = with(|v| {
        for m in v["modes"].as_array_mut().unwrap() {
            m.as_object_mut().unwrap().remove("shape_nsd");
        }
    });
    assert!(!parse(&v).unwrap().has_uncertainties());
}

/// Truncations and byte corruptions of a valid payload: always Ok or Err, never a panic.
#[test]
fn arbitrary_bytes_never_panic() {
    let base = format!(
        "{} NaN -Infinity 1e999 \"\\",
        full().to_string().replace("20.5", "-Infinity")
    )
    .into_bytes();
    for end in 0..=base.len() {
        let _ = parse_bytes(&base[..end]);
    }
    let mut state: u64 = 0x2545_F491_4F6C_DD1D;
    for _ in 0..5000 {
        let mut bytes = base.clone();
        for _ in 0..3 {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            let at = (state % bytes.len() as u64) as usize;
            bytes[at] = (state >> 32) as u8;
        }
        let _ = parse_bytes(&bytes);
    }
}

/// Times outside the common range of every output format (MCAP's unsigned and chrono's
/// signed 64-bit nanoseconds: 1970 to 2262) are rejected by `time`, never reach an output.
#[test]
fn rejects_times_no_output_format_holds() {
    for time in [
        "2300-01-01T00:00:00Z",
        "1969-12-31T23:59:59Z",
        "9999-12-31T23:59:59Z",
    ] {
        let v = with(|v| v["time"] = json!(time));
        assert_rejected(parse(&v), "time", &["outside the range", "2262"]);
    }
    let v = with(|v| v["time"] = json!("2262-04-11T23:47:16Z"));
    assert!(
        parse(&v).is_ok(),
        "the last whole second of the range is accepted"
    );
}

/// Live, a set stamped more than the allowed margin after its reception is rejected by
/// `time` with both times and the configuration key.
#[test]
fn rejects_times_ahead_of_the_receiver_clock() {
    let channels = model_channels();
    let at = |received: &str, ahead_s: i64| {
        let ctx = ValidationContext {
            structures: STRUCTURES,
            model_channels: &channels,
            last_time: None,
            allow_equal_time: false,
            max_future: Some((t(received), chrono::TimeDelta::seconds(ahead_s))),
        };
        parse_modal_set(full().to_string().as_bytes(), &ctx)
    };
    let stamped = full()["time"].as_str().unwrap().to_string();
    let two_days_before = (t(&stamped) - chrono::TimeDelta::days(2)).to_rfc3339();
    assert_rejected(
        at(&two_days_before, 300),
        "time",
        &[
            "ahead of the receiver's clock",
            "172800 s",
            "daemon.max_future_s",
        ],
    );
    let a_minute_before = (t(&stamped) - chrono::TimeDelta::seconds(60)).to_rfc3339();
    assert!(at(&a_minute_before, 300).is_ok(), "within the margin");
}

/// Uncertainties below the floor (a weight 1/σ² that would overflow) and shapes without a
/// direction are rejected by field.
#[test]
fn rejects_degenerate_uncertainties_and_shapes() {
    let v = with(|v| v["modes"][1]["frequency_cov"] = json!(1e-300));
    assert_rejected(parse(&v), "modes[1].frequency_cov", &["below the floor"]);
    let v = with(|v| v["modes"][0]["shape_nsd"] = json!(1e-9));
    assert_rejected(parse(&v), "modes[0].shape_nsd", &["below the floor"]);
    let v = with(|v| {
        let n = v["modes"][0]["shape"].as_array().unwrap().len();
        v["modes"][0]["shape"] = json!(vec![0.0; n]);
    });
    assert_rejected(
        parse(&v),
        "modes[0].shape",
        &["all measured entries are zero"],
    );
    let v = with(|v| {
        let n = v["modes"][0]["shape"].as_array().unwrap().len();
        v["modes"][0]["shape"] = json!(vec![1e-310; n]);
    });
    assert_rejected(parse(&v), "modes[0].shape", &["cannot be normalized"]);
    let v = with(|v| {
        let n = v["modes"][0]["shape"].as_array().unwrap().len();
        v["modes"][0]["shape"] = json!(vec![1e200; n]);
    });
    assert_rejected(parse(&v), "modes[0].shape", &["cannot be normalized"]);
}

/// A reason or a field that would repeat a long attacker string is capped.
#[test]
fn rejection_reasons_and_fields_are_capped() {
    let long = "x".repeat(100_000);
    let v = with(|v| v["structure"] = json!(long));
    let r = parse(&v).unwrap_err();
    assert!(
        r.reason.len() <= boltwatch::contract::modal_set::REASON_LIMIT,
        "{}",
        r.reason.len()
    );
    let v = with(|v| v[long.as_str()] = json!(1));
    let r = parse(&v).unwrap_err();
    assert!(
        r.field.len() <= boltwatch::contract::modal_set::FIELD_LIMIT,
        "{}",
        r.field.len()
    );
    assert!(r.reason.contains("unknown field"), "{}", r.reason);
}

/// A set of more than `MAX_MODES` modes, or one repeating a mode (same frequency, same
/// shape), is rejected: a fuzzed set of 1,534 copies of one mode held the tracker 19 s.
#[test]
fn rejects_too_many_modes_and_repeated_modes() {
    let v = with(|v| {
        let m = v["modes"][0].clone();
        v["modes"] = json!(vec![m; MAX_MODES + 1]);
    });
    assert_rejected(parse(&v), "modes", &["more than the 100"]);
    let v = with(|v| v["modes"][1] = v["modes"][0].clone());
    assert_rejected(parse(&v), "modes[1]", &["repeats modes[0]"]);
}

/// `shape_std` (issue 24): per-entry stds, `null` where the shape is; round trip; each
/// rule named by field.
#[test]
fn shape_std_is_validated_entry_by_entry() {
    let ok = with(|v| {
        v["modes"][0]["shape_std"] = json!([0.004, null]);
        v["modes"][1]["shape_std"] = json!([0.0, 0.03]);
    });
    let set = parse(&ok).unwrap();
    assert_eq!(set.modes[0].shape_std, Some(vec![Some(0.004), None]));
    assert_eq!(set.to_json(), ok, "to_json writes shape_std back");
    // Instead of shape_nsd: a set with shape_std only is a set with uncertainties.
    let only_std = with(|v| {
        v["modes"][0].as_object_mut().unwrap().remove("shape_nsd");
        v["modes"][0]["shape_std"] = json!([0.004, null]);
    });
    assert!(parse(&only_std).unwrap().has_uncertainties());

    let cases: Vec<(Value, &str, &str)> = vec![
        (
            json!([0.004]),
            "modes[0].shape_std",
            "has 1 entries but the shape has 2",
        ),
        (
            json!([0.004, 0.1]),
            "modes[0].shape_std[1]",
            "a number where the shape entry is null",
        ),
        (
            json!([null, null]),
            "modes[0].shape_std[0]",
            "null where the shape entry is a number",
        ),
        (
            json!([-0.1, null]),
            "modes[0].shape_std[0]",
            "-0.1 is negative",
        ),
        (json!([0.0, null]), "modes[0].shape_std", "every entry is 0"),
        (
            json!([1e-9, null]),
            "modes[0].shape_std",
            "below 1e-6 times the shape's RMS",
        ),
        (json!(0.1), "modes[0].shape_std", "expected an array"),
        (
            json!(["x", null]),
            "modes[0].shape_std[0]",
            "expected a number",
        ),
    ];
    for (std, field, needle) in cases {
        let v = with(|v| v["modes"][0]["shape_std"] = std.clone());
        assert_rejected(parse(&v), field, &[needle]);
    }
    let no_shape = with(|v| v["modes"][2]["shape_std"] = json!([0.1]));
    assert_rejected(parse(&no_shape), "modes[2].shape_std", &["without a shape"]);
    // Uncertain on one shaped mode, not on another.
    let mixed = with(|v| {
        v["modes"][0].as_object_mut().unwrap().remove("shape_nsd");
        v["modes"][1].as_object_mut().unwrap().remove("shape_nsd");
        v["modes"][1]["shape_std"] = json!([0.01, 0.03]);
    });
    assert_rejected(
        parse(&mixed),
        "modes[1].shape_std",
        &["present on some modes but not others"],
    );
}

/// The damping fields an identification adds (issue 26): kept and written back; a ratio
/// outside [0, 1) or a std without a ratio is rejected, naming the field.
#[test]
fn damping_fields_are_kept_and_checked() {
    let v = with(|v| {
        v["modes"][0]["damping_ratio"] = json!(0.012);
        v["modes"][0]["damping_std"] = json!(0.002);
    });
    let set = parse(&v).unwrap();
    assert_eq!(set.modes[0].damping_ratio, Some(0.012));
    assert_eq!(set.modes[0].damping_std, Some(0.002));
    assert_eq!(parse(&set.to_json()).unwrap(), set);
    let v = with(|v| v["modes"][1]["damping_ratio"] = json!(1.5));
    assert_rejected(parse(&v), "modes[1].damping_ratio", &["1.5", "fraction"]);
    let v = with(|v| v["modes"][1]["damping_std"] = json!(0.01));
    assert_rejected(
        parse(&v),
        "modes[1].damping_std",
        &["without damping_ratio"],
    );
    let v = with(|v| {
        v["modes"][1]["damping_ratio"] = json!(0.01);
        v["modes"][1]["damping_std"] = json!(0.0);
    });
    assert_rejected(parse(&v), "modes[1].damping_std", &["must be > 0"]);
}

/// Mode labels and the missing list (tracking across windows, issue 26): kept through a
/// round trip; a label twice, an empty or over-long label, a missing label that labels a
/// mode of the set, and a `missing` that is not an array are each rejected by field.
#[test]
fn labels_and_missing_modes_are_kept_and_checked() {
    let v = with(|v| {
        v["modes"][0]["label"] = json!("mode 1");
        v["modes"][1]["label"] = json!("mode 2");
        v["missing"] = json!(["mode 4"]);
    });
    let set = parse(&v).unwrap();
    assert_eq!(set.modes[0].label.as_deref(), Some("mode 1"));
    assert_eq!(set.missing, vec!["mode 4".to_string()]);
    assert_eq!(parse(&set.to_json()).unwrap(), set);
    let v = with(|v| {
        v["modes"][0]["label"] = json!("a");
        v["modes"][2]["label"] = json!("a");
    });
    assert_rejected(parse(&v), "modes[2].label", &["earlier mode"]);
    let v = with(|v| v["modes"][0]["label"] = json!(""));
    assert_rejected(parse(&v), "modes[0].label", &["1 to 64 bytes"]);
    let v = with(|v| v["modes"][0]["label"] = json!("x".repeat(65)));
    assert_rejected(parse(&v), "modes[0].label", &["has 65"]);
    let v = with(|v| {
        v["modes"][0]["label"] = json!("a");
        v["missing"] = json!(["b", "a"]);
    });
    assert_rejected(parse(&v), "missing[1]", &["labels a mode of this set"]);
    let v = with(|v| v["missing"] = json!("a"));
    assert_rejected(parse(&v), "missing", &["expected an array"]);
}

/// `unexplained_peaks` (an identification's cross-check against the spectrum) round-trips,
/// and a malformed one is rejected by its path.
#[test]
fn unexplained_peaks_round_trip_and_are_validated() {
    let v = with(|v| {
        v["unexplained_peaks"] = json!([{"frequency_hz": 21.375, "prominence_db": 8.1}]);
    });
    let set = parse(&v).unwrap();
    assert_eq!(
        set.unexplained_peaks,
        [SpectrumPeak {
            frequency_hz: 21.375,
            prominence_db: 8.1
        }]
    );
    assert_eq!(set.to_json()["unexplained_peaks"], v["unexplained_peaks"]);
    assert_rejected(
        parse(&with(|v| {
            v["unexplained_peaks"] = json!({"frequency_hz": 1.0})
        })),
        "unexplained_peaks",
        &["expected an array"],
    );
    assert_rejected(
        parse(&with(|v| {
            v["unexplained_peaks"] = json!([{"frequency_hz": -2.0, "prominence_db": 8.1}]);
        })),
        "unexplained_peaks[0].frequency_hz",
        &["> 0"],
    );
    assert_rejected(
        parse(&with(|v| {
            v["unexplained_peaks"] = json!([{"frequency_hz": 2.0, "prominence_db": 8.1, "q": 1}]);
        })),
        "unexplained_peaks[0].q",
        &["unknown"],
    );
}
