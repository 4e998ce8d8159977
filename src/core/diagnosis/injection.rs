//! An effect put into a model file by name: `kind@location=value` (`simulate --inject`,
//! and the tests that hide an effect from the model class).

use super::DiagnosisError;
use super::description::Description;
use super::effects::{Effect, Sign, by_kind, catalogue};

/// An effect added to a model file: `kind@location=value` (`added-mass@J2R=0.5`), the
/// value in the effect's unit.
pub struct Injection {
    pub effect: Box<dyn Effect>,
    pub location: String,
    pub value: f64,
}

impl Injection {
    /// Parses `kind@location=value`.
    pub fn parse(s: &str) -> Result<Self, DiagnosisError> {
        let bad = |why: &str| {
            DiagnosisError::Location(format!(
                "`{s}`: {why} (expected kind@location=value, e.g. added-mass@J2R=0.5)"
            ))
        };
        let (kind, rest) = s.split_once('@').ok_or_else(|| bad("no `@`"))?;
        let (location, value) = rest.split_once('=').ok_or_else(|| bad("no `=`"))?;
        let effect = by_kind(kind).ok_or_else(|| {
            bad(&format!(
                "unknown effect; known: {}",
                catalogue()
                    .iter()
                    .map(|e| e.kind())
                    .collect::<Vec<_>>()
                    .join(", ")
            ))
        })?;
        let value: f64 = value
            .trim()
            .parse()
            .map_err(|_| bad("the value is not a number"))?;
        if !value.is_finite() {
            return Err(bad("the value is not finite"));
        }
        Ok(Self {
            effect,
            location: location.to_string(),
            value,
        })
    }

    /// Adds the effect to the model.
    pub fn apply(&self, spec: &mut Description) -> Result<(), DiagnosisError> {
        if self.effect.sign() == Sign::Positive && self.value <= 0.0 {
            return Err(DiagnosisError::Location(format!(
                "{}@{} = {}: must be > 0",
                self.effect.kind(),
                self.location,
                self.value
            )));
        }
        if !self.effect.accepts(spec, &self.location) {
            let known = self.effect.locations(spec);
            if known.is_empty() {
                // Not an effect of this kind of model: its own error says why.
                return self
                    .effect
                    .apply(spec, &self.location, self.effect.coordinate(self.value));
            }
            return Err(DiagnosisError::Location(format!(
                "{}@{}: not a location of this effect in the model (e.g. {})",
                self.effect.kind(),
                self.location,
                known.iter().take(6).cloned().collect::<Vec<_>>().join(", ")
            )));
        }
        self.effect
            .apply(spec, &self.location, self.effect.coordinate(self.value))
    }
}
