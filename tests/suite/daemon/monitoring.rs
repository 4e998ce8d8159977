//! The monitoring files of `deploy/`: the Prometheus scrape configuration and alerting
//! rules, checked and unit-tested by `promtool` (Debian package `prometheus`, installed by
//! `.ci/run`), and the Grafana dashboard, whose every query names only metrics the daemon
//! exposes ([`assert_monitoring_names_exposed_metrics`], called with a live scrape).

use std::collections::BTreeSet;
use std::path::Path;
use std::process::Command;

use serde_json::Value;

fn root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

/// `promtool` with `args`, which must succeed.
fn promtool(args: &[&str]) -> String {
    let out = Command::new("promtool")
        .args(args)
        .current_dir(root())
        .output()
        .expect("promtool (Debian package prometheus; .ci/run installs it) checks the rules");
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(out.status.success(), "promtool {args:?}:\n{text}");
    text
}

/// The rules and the configuration are valid, and the rules' unit tests (alerts firing on
/// series shaped like a loosening, a silent structure, a daemon down, dropped sets) pass.
#[test]
fn prometheus_rules_pass_promtool() {
    let rules = promtool(&["check", "rules", "deploy/prometheus/boltwatch-rules.yml"]);
    assert!(rules.contains("SUCCESS: 6 rules found"), "{rules}");
    promtool(&["check", "config", "deploy/prometheus/prometheus.yml"]);
    promtool(&["test", "rules", "tests/data/prometheus/rules-test.yml"]);
}

/// Every PromQL expression and variable query of the dashboard, and every rule's
/// expression.
fn monitoring_queries() -> Vec<String> {
    let dash: Value = serde_json::from_str(
        &std::fs::read_to_string(root().join("deploy/grafana/dashboards/boltwatch.json")).unwrap(),
    )
    .unwrap();
    let mut out = Vec::new();
    collect_queries(&dash, &mut out);
    let rules: serde_yaml::Value = serde_yaml::from_str(
        &std::fs::read_to_string(root().join("deploy/prometheus/boltwatch-rules.yml")).unwrap(),
    )
    .unwrap();
    for group in rules["groups"].as_sequence().unwrap() {
        for rule in group["rules"].as_sequence().unwrap() {
            out.push(rule["expr"].as_str().unwrap().to_string());
        }
    }
    out
}

/// The `expr` and `query` strings anywhere in a dashboard.
fn collect_queries(v: &Value, out: &mut Vec<String>) {
    match v {
        Value::Object(m) => {
            for (k, v) in m {
                match (k.as_str(), v) {
                    ("expr" | "query", Value::String(s)) => out.push(s.clone()),
                    _ => collect_queries(v, out),
                }
            }
        }
        Value::Array(a) => a.iter().for_each(|v| collect_queries(v, out)),
        _ => {}
    }
}

/// The `boltwatch_…` names a query reads.
fn names_in(query: &str) -> BTreeSet<String> {
    let mut names = BTreeSet::new();
    let mut rest = query;
    while let Some(i) = rest.find("boltwatch_") {
        let tail = &rest[i..];
        let end = tail
            .find(|c: char| !(c.is_ascii_alphanumeric() || c == '_'))
            .unwrap_or(tail.len());
        names.insert(tail[..end].to_string());
        rest = &tail[end..];
    }
    names
}

/// The dashboard is well formed (every panel placed, every query with a data source and a
/// reference), and every metric a dashboard query or a rule reads is one the scrape `m`
/// holds.
pub fn assert_monitoring_names_exposed_metrics(m: &str) {
    let exposed: BTreeSet<&str> = m
        .lines()
        .filter(|l| !l.starts_with('#'))
        .filter_map(|l| l.split(['{', ' ']).next())
        .collect();
    let dash: Value = serde_json::from_str(
        &std::fs::read_to_string(root().join("deploy/grafana/dashboards/boltwatch.json")).unwrap(),
    )
    .unwrap();
    for p in dash["panels"].as_array().unwrap() {
        assert!(p["gridPos"]["w"].as_u64().is_some(), "{}", p["title"]);
        for t in p["targets"].as_array().unwrap() {
            assert!(t["refId"].is_string() && t["datasource"].is_object(), "{t}");
        }
    }
    let queries = monitoring_queries();
    assert!(queries.len() > 20, "{queries:?}");
    for q in &queries {
        for name in names_in(q) {
            assert!(
                exposed.contains(name.as_str()),
                "`{q}` reads {name}, which the daemon does not expose"
            );
        }
    }
}
