//! Screening every candidate effect at every location by the first-order reduction of ε
//! its residual column explains beyond the model's own Jacobian: step 2 of the workflow.

use super::*;

/// Every (effect, location) of `spec`, minus those already named.
pub(super) fn candidates_of<'a>(
    effects: &'a [Box<dyn Effect>],
    spec: &Description,
    named: &[Named],
) -> Vec<(&'a dyn Effect, String)> {
    effects
        .iter()
        .flat_map(|e| e.locations(spec).into_iter().map(move |l| (e.as_ref(), l)))
        .filter(|(e, l)| {
            !named
                .iter()
                .any(|n| n.refit.effect == e.kind() && n.refit.location == *l)
        })
        .collect()
}

/// Screens one candidate (module docs, step 2); `None` when its finite difference changed
/// the mode pairing or the model would not build.
pub(super) fn screen(
    spec: &Description,
    effect: &dyn Effect,
    location: &str,
    data: &MeasuredData,
    base: &Evaluation,
    q: &Mat<f64>,
) -> Option<Candidate> {
    let h = effect.step(spec, location);
    let mut s = spec.clone();
    effect.apply(&mut s, location, h).ok()?;
    let model = s.build().ok()?;
    let mut ev = Evaluator::new(&model).ok()?;
    let e = ev.evaluate(&model, data, &base.theta).ok()?;
    if e.pairing != base.pairing || e.r.len() != base.r.len() {
        return None;
    }
    let mut g: Vec<f64> = e.r.iter().zip(&base.r).map(|(a, b)| (a - b) / h).collect();
    // g⊥ = g − Q Qᵀ g.
    for j in 0..q.ncols() {
        let c: f64 = (0..g.len()).map(|i| q[(i, j)] * g[i]).sum();
        for (i, gi) in g.iter_mut().enumerate() {
            *gi -= c * q[(i, j)];
        }
    }
    let gg: f64 = g.iter().map(|v| v * v).sum();
    let gr: f64 = g.iter().zip(&base.r).map(|(a, b)| a * b).sum();
    if gg.is_nan() || gg <= 0.0 || !gr.is_finite() {
        return None;
    }
    let u_linear = -gr / gg;
    let score = if effect.sign() == Sign::Positive && u_linear <= 0.0 {
        0.0
    } else {
        gr * gr / gg
    };
    Some(Candidate {
        effect: effect.kind(),
        location: location.to_string(),
        score,
        u_linear,
    })
}
