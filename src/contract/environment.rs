//! The conditions of a measurement (temperature and other named covariates) and the
//! `boltwatch.environment.v1` message that carries them for sites whose thermometer is not
//! in the box that identifies the modes: one reading of a structure's environment at one
//! time, on `boltwatch/<structure>/environment`. The tracker joins a modal set without its
//! own conditions to the latest reading at most `tracker.normalisation.max_age_s` older.
//!
//! The rules of the fields are shared with the modal set, which carries the same
//! `temperature_c` and `covariates` fields.

use std::collections::BTreeMap;

use chrono::{DateTime, Utc};
use serde_json::{Map, Value};

use super::fields::{
    json_object, kind, no_unknown_fields, number, reject, required, string, time_field,
};
use super::modal_set::Rejection;
use super::nonfinite::nonfinite_token;

/// The value of the `schema` field of every environment reading.
pub const ENVIRONMENT_SCHEMA: &str = "boltwatch.environment.v1";

/// The temperatures accepted, °C: any structure's, with room for a sensor in the sun; a
/// value outside is a sensor fault, not weather.
pub const TEMPERATURE_RANGE_C: [f64; 2] = [-80.0, 80.0];

/// The most named covariates a message may carry.
pub const MAX_COVARIATES: usize = 16;

/// The name of the temperature among the covariates (its own field on the wire).
pub const TEMPERATURE: &str = "temperature_c";

/// The conditions of a measurement.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Conditions {
    /// Temperature of the structure, °C.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub temperature_c: Option<f64>,
    /// Other covariates by name (humidity, traffic RMS, a second temperature, …), in the
    /// units of their source.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub covariates: BTreeMap<String, f64>,
}

impl Conditions {
    /// The covariate `name` ([`TEMPERATURE`] is the temperature).
    pub fn value(&self, name: &str) -> Option<f64> {
        if name == TEMPERATURE {
            self.temperature_c
        } else {
            self.covariates.get(name).copied()
        }
    }

    /// For a message: `-4.3 °C`, `-4.3 °C, humidity 81`.
    pub fn describe(&self) -> String {
        let mut parts: Vec<String> = self
            .temperature_c
            .iter()
            .map(|t| format!("{t:.1} °C"))
            .collect();
        parts.extend(self.covariates.iter().map(|(k, v)| format!("{k} {v}")));
        parts.join(", ")
    }

    /// Nothing measured.
    pub fn is_empty(&self) -> bool {
        self.temperature_c.is_none() && self.covariates.is_empty()
    }

    /// Parses `temperature_c` and `covariates` of `obj` (both optional).
    pub(crate) fn parse(obj: &Map<String, Value>) -> Result<Self, Rejection> {
        let temperature_c = obj.get(TEMPERATURE).map(temperature).transpose()?;
        let covariates = match obj.get("covariates") {
            None => BTreeMap::new(),
            Some(v) => covariates(v)?,
        };
        Ok(Self {
            temperature_c,
            covariates,
        })
    }

    /// Adds the fields to a JSON object.
    pub(crate) fn write(&self, obj: &mut Map<String, Value>) {
        if let Some(t) = self.temperature_c {
            obj.insert(TEMPERATURE.into(), t.into());
        }
        if !self.covariates.is_empty() {
            let m = self
                .covariates
                .iter()
                .map(|(k, v)| (k.clone(), Value::from(*v)))
                .collect();
            obj.insert("covariates".into(), Value::Object(m));
        }
    }
}

/// `temperature_c`: a finite number of °C within [`TEMPERATURE_RANGE_C`].
fn temperature(v: &Value) -> Result<f64, Rejection> {
    let t = number(v, TEMPERATURE)?;
    let [lo, hi] = TEMPERATURE_RANGE_C;
    if (lo..=hi).contains(&t) {
        Ok(t)
    } else {
        Err(reject(
            TEMPERATURE,
            format!("{t} °C is outside {lo} … {hi} °C: a sensor fault, not a temperature"),
        ))
    }
}

/// `covariates`: an object of at most [`MAX_COVARIATES`] finite numbers named by
/// 1–64 letters, digits and `_` (not `temperature_c`, which has its own field).
fn covariates(v: &Value) -> Result<BTreeMap<String, f64>, Rejection> {
    let Value::Object(items) = v else {
        return Err(reject(
            "covariates",
            format!("expected an object of named numbers, got {}", kind(v)),
        ));
    };
    if items.len() > MAX_COVARIATES {
        return Err(reject(
            "covariates",
            format!(
                "{} covariates, more than the {MAX_COVARIATES} a message may carry",
                items.len()
            ),
        ));
    }
    let mut out = BTreeMap::new();
    for (name, value) in items {
        let path = format!("covariates.{}", name.escape_debug());
        let valid = !name.is_empty()
            && name.len() <= 64
            && name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_');
        if !valid {
            return Err(reject(
                path,
                "a covariate name is 1–64 letters, digits or `_`",
            ));
        }
        if name == TEMPERATURE {
            return Err(reject(
                path,
                "the temperature has its own field, temperature_c",
            ));
        }
        out.insert(name.clone(), number(value, &path)?);
    }
    Ok(out)
}

/// One reading of a structure's environment (module docs).
#[derive(Debug, Clone, PartialEq)]
pub struct EnvironmentReading {
    pub structure: String,
    pub time: DateTime<Utc>,
    pub conditions: Conditions,
}

/// Top-level fields of the environment contract.
const FIELDS: &[&str] = &["schema", "structure", "time", TEMPERATURE, "covariates"];

/// Parses and validates an environment reading for one of `structures`. Never panics.
///
/// Rejections: `payload` (not a JSON object), `schema`, an unknown field, `structure` (not
/// watched), `time`, `temperature_c` (not a number, outside [`TEMPERATURE_RANGE_C`]),
/// `covariates` (see [`Conditions`]); a reading with neither temperature nor covariates.
pub fn parse_environment(
    payload: &[u8],
    structures: &[&str],
) -> Result<EnvironmentReading, Rejection> {
    let obj = json_object(payload)?;
    let schema = required(&obj, "schema", "schema")?;
    if schema.as_str() != Some(ENVIRONMENT_SCHEMA) || nonfinite_token(schema).is_some() {
        return Err(reject(
            "schema",
            format!("expected {ENVIRONMENT_SCHEMA:?}, got {}", kind(schema)),
        ));
    }
    no_unknown_fields(&obj, FIELDS, "")?;
    let structure = string(required(&obj, "structure", "structure")?, "structure")?;
    if !structures.contains(&structure) {
        return Err(reject(
            "structure",
            format!("{structure:?} is not a watched structure (watched: {structures:?})"),
        ));
    }
    let time = time_field(&obj)?;
    let conditions = Conditions::parse(&obj)?;
    if conditions.is_empty() {
        return Err(reject(
            "payload",
            "a reading carries temperature_c, covariates or both",
        ));
    }
    Ok(EnvironmentReading {
        structure: structure.to_string(),
        time,
        conditions,
    })
}

impl EnvironmentReading {
    /// The canonical JSON of the reading.
    pub fn to_json(&self) -> Value {
        let mut obj = Map::new();
        obj.insert("schema".into(), ENVIRONMENT_SCHEMA.into());
        obj.insert("structure".into(), self.structure.clone().into());
        obj.insert("time".into(), super::rfc3339(self.time).into());
        self.conditions.write(&mut obj);
        Value::Object(obj)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &str) -> Result<EnvironmentReading, Rejection> {
        parse_environment(text.as_bytes(), &["lab-frame"])
    }

    #[test]
    fn a_reading_round_trips() {
        let r = parse(
            r#"{"schema":"boltwatch.environment.v1","structure":"lab-frame",
                "time":"2027-01-05T06:00:00Z","temperature_c":-4.5,
                "covariates":{"humidity":81.0,"t_bolt":-6.25}}"#,
        )
        .unwrap();
        assert_eq!(r.conditions.value(TEMPERATURE), Some(-4.5));
        assert_eq!(r.conditions.value("t_bolt"), Some(-6.25));
        let again = parse(&r.to_json().to_string()).unwrap();
        assert_eq!(again, r);
    }

    /// Each bad input is named by its field and says why.
    #[test]
    fn bad_readings_name_the_field() {
        let base = r#""schema":"boltwatch.environment.v1","time":"2027-01-05T06:00:00Z""#;
        let cases = [
            (
                format!(r#"{{{base},"structure":"lab-frame","temperature_c":-120}}"#),
                "temperature_c",
                "outside -80 … 80",
            ),
            (
                format!(r#"{{{base},"structure":"lab-frame","temperature_c":NaN}}"#),
                "temperature_c",
                "NaN",
            ),
            (
                format!(r#"{{{base},"structure":"bridge","temperature_c":5}}"#),
                "structure",
                "not a watched structure",
            ),
            (
                format!(r#"{{{base},"structure":"lab-frame"}}"#),
                "payload",
                "temperature_c, covariates or both",
            ),
            (
                format!(r#"{{{base},"structure":"lab-frame","covariates":{{"rh %":5}}}}"#),
                "covariates.rh %",
                "letters, digits",
            ),
            (
                format!(r#"{{{base},"structure":"lab-frame","covariates":{{"rh":"wet"}}}}"#),
                "covariates.rh",
                "expected a number",
            ),
        ];
        for (text, field, why) in cases {
            let e = parse(&text).unwrap_err();
            assert_eq!(e.field, field, "{text}");
            assert!(e.reason.contains(why), "{text}: {}", e.reason);
        }
    }
}
