//! The catalogue of candidate effects (DESIGN §6, issue 6): physically named enrichments of
//! a model file, each with one parameter and its unit, scanned over every location where it
//! can occur.
//!
//! An effect works on the model *file* ([`ModelSpec`](crate::core::model::spec::ModelSpec)):
//! [`Effect::apply`] adds it at a location with a value, and the enriched file is assembled
//! as any other. So an effect needs no support in the assembly, the eigen solvers or the
//! sensitivities, and a new effect type is one more implementation of [`Effect`] in
//! [`catalogue`]: the search does not change.
//!
//! Each effect is applied through an internal coordinate `u` that is 0 for the model as it
//! is ([`Effect::apply`] with `u = 0` changes nothing) and in which the residual is close to
//! linear near 0; [`Effect::value`] turns it into the reported value and unit (support
//! flexibility: `u` is the compliance, the value its stiffness).
//!
//! This module is the catalogue and the public face of the effects: the interface lives in
//! `effect_traits`, the effects that also act on imported models in `matrix_effects`, those
//! that need a model file's geometry in `file_effects`.

pub use super::effect_traits::{Effect, FileEffect, Sign};
pub use super::file_effects::{
    AxialForce, JointInertia, MemberStiffness, Modulus, Splice, SupportFlexibility,
};
pub use super::matrix_effects::{AddedMass, GroundedSpring, StiffnessScale};

/// Every effect type, in the order candidates are listed.
pub fn catalogue() -> Vec<Box<dyn Effect>> {
    vec![
        Box::new(AddedMass),
        Box::new(SupportFlexibility),
        Box::new(MemberStiffness),
        Box::new(Modulus),
        Box::new(JointInertia),
        Box::new(Splice),
        Box::new(AxialForce),
        Box::new(GroundedSpring),
        Box::new(StiffnessScale),
    ]
}

/// The effect of a contract name.
pub fn by_kind(kind: &str) -> Option<Box<dyn Effect>> {
    catalogue().into_iter().find(|e| e.kind() == kind)
}
