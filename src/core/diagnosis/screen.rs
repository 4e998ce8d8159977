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

/// Multiples of the finite-difference step at which a candidate whose step changed the mode
/// pairing is probed (both signs for an effect of either sign): 3 to 100 steps (an added
/// mass from 3 % to the lightest joint's whole mass). Such a candidate moves a measured mode
/// across a close neighbour (the space frame's identical beams have clusters of local modes
/// within 0.1 %), so its first-order column says nothing, and it is often the effect sought:
/// a mass on one beam splits its cluster.
const PROBE_STEPS: [f64; 4] = [3.0, 10.0, 30.0, 100.0];

/// Screens one candidate (module docs, step 2); `None` when the model would not build or
/// evaluate. A candidate whose finite difference changes the mode pairing is scored by
/// [`probe`] instead.
pub(super) fn screen(
    spec: &Description,
    effect: &dyn Effect,
    location: &str,
    data: &MeasuredData,
    base: &Evaluation,
    q: &Mat<f64>,
    reduced: Option<&ReducedBasis>,
) -> Option<Candidate> {
    let h = effect.step(spec, location);
    let e = evaluate_with(spec, effect, location, h, data, base, reduced)?;
    if e.pairing != base.pairing || e.r.len() != base.r.len() {
        return probe(spec, effect, location, data, base, q, reduced);
    }
    let mut g: Vec<f64> = e.r.iter().zip(&base.r).map(|(a, b)| (a - b) / h).collect();
    project_off(&mut g, q);
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

/// The evaluation at the base θ with the effect applied at value `u`: by a reduced solve
/// where one holds ([`ReducedBasis`]), else in full.
fn evaluate_with(
    spec: &Description,
    effect: &dyn Effect,
    location: &str,
    u: f64,
    data: &MeasuredData,
    base: &Evaluation,
    reduced: Option<&ReducedBasis>,
) -> Option<Evaluation> {
    let model = model_with(spec, effect, location, u)?;
    let relabel = |label: &str| effect.dof_label_after(spec, location, label);
    if let Some(ev) = reduced.and_then(|b| b.evaluate(&model, data, &relabel)) {
        return Some(ev);
    }
    let mut ev = Evaluator::new(&model).ok()?;
    ev.evaluate(&model, data, &base.theta).ok()
}

/// `v − Q Qᵀ v`: `v` projected off the span of the model's own Jacobian.
fn project_off(v: &mut [f64], q: &Mat<f64>) {
    for j in 0..q.ncols() {
        let c: f64 = (0..v.len()).map(|i| q[(i, j)] * v[i]).sum();
        for (i, vi) in v.iter_mut().enumerate() {
            *vi -= c * q[(i, j)];
        }
    }
}

/// The score of a candidate whose first-order column is undefined (its step changed the
/// mode pairing): the ε reduction at finite values `u` ([`PROBE_STEPS`]) with θ corrected to
/// first order, `‖(I − QQᵀ) r(θ̂)‖² − ‖(I − QQᵀ) r(θ̂, u)‖²`, the largest over the values; the
/// value giving it starts the refit. The same measure as the linear score, without the
/// linearization in `u`.
fn probe(
    spec: &Description,
    effect: &dyn Effect,
    location: &str,
    data: &MeasuredData,
    base: &Evaluation,
    q: &Mat<f64>,
    reduced: Option<&ReducedBasis>,
) -> Option<Candidate> {
    let h = effect.step(spec, location);
    let signs: &[f64] = match effect.sign() {
        Sign::Positive => &[1.0],
        Sign::Any => &[1.0, -1.0],
    };
    let residual_off = |r: &[f64]| {
        let mut v = r.to_vec();
        project_off(&mut v, q);
        v.iter().map(|x| x * x).sum::<f64>()
    };
    let at_base = residual_off(&base.r);
    let mut best = (0.0, h);
    for &sign in signs {
        for k in PROBE_STEPS {
            let u = sign * k * h;
            let Some(e) = evaluate_with(spec, effect, location, u, data, base, reduced) else {
                continue;
            };
            if e.r.len() != base.r.len() {
                continue;
            }
            let reduction = at_base - residual_off(&e.r);
            if reduction.is_finite() && reduction > best.0 {
                best = (reduction, u);
            }
        }
    }
    Some(Candidate {
        effect: effect.kind(),
        location: location.to_string(),
        score: best.0,
        u_linear: best.1,
    })
}
