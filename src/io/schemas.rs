//! The JSON Schemas (draft 2020-12) of every message boltwatch reads or writes, stored in
//! MCAP files beside the channels (schema encoding `jsonschema`, DESIGN §3.4), so recordings
//! open in standard MCAP tools.

use crate::contract::{Alert, Crosscheck, Estimate, Message, Rejected};

/// Schema name of the truth channel of synthetic recordings.
pub const TRUTH_SCHEMA: &str = "boltwatch.truth.v1";

/// `(topic suffix, schema name, JSON Schema text)` of every channel, in the order channels
/// are declared in an output file.
pub const CHANNELS: [(&str, &str, &str); 8] = [
    (
        "modal",
        crate::contract::modal_set::MODAL_SET_SCHEMA,
        include_str!("schemas/modal_set.json"),
    ),
    (
        "stiffness",
        Estimate::SCHEMA,
        include_str!("schemas/stiffness.json"),
    ),
    ("alerts", Alert::SCHEMA, include_str!("schemas/alert.json")),
    (
        "crosscheck",
        Crosscheck::SCHEMA,
        include_str!("schemas/crosscheck.json"),
    ),
    (
        "rejected",
        Rejected::SCHEMA,
        include_str!("schemas/rejected.json"),
    ),
    ("truth", TRUTH_SCHEMA, include_str!("schemas/truth.json")),
    (
        "accel",
        crate::contract::accel::Accel::SCHEMA,
        include_str!("schemas/accel.json"),
    ),
    (
        "environment",
        crate::contract::environment::ENVIRONMENT_SCHEMA,
        include_str!("schemas/environment.json"),
    ),
];

/// The schema name and text of a topic suffix (`stiffness`, …).
pub fn for_topic(suffix: &str) -> Option<(&'static str, &'static str)> {
    CHANNELS
        .iter()
        .find(|(t, _, _)| *t == suffix)
        .map(|&(_, name, text)| (name, text))
}

#[cfg(test)]
mod tests {
    /// Every stored schema is valid JSON and names itself in its title.
    #[test]
    fn schemas_parse_and_match_their_names() {
        for (topic, name, text) in super::CHANNELS {
            let v: serde_json::Value =
                serde_json::from_str(text).unwrap_or_else(|e| panic!("{topic}: {e}"));
            assert_eq!(v["title"], name, "{topic}");
        }
    }
}
