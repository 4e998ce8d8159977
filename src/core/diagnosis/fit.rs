//! Fitting a model class to the data (mode matching) and localizing where it misfits:
//! steps 1 and 3 of the workflow (module docs of [`super`]).

use super::*;

/// A fitted model class.
pub(super) struct Fit {
    pub(super) model: Model,
    pub(super) result: ModeMatchingResult,
}

/// Every fit of the diagnosis (mode matching and the joint fit) holds θ within these
/// multiples of its nominal value (and the model's own bounds). A connection far looser
/// than its neighbouring members is a hinge, one far stiffer is rigid: beyond these the
/// modes no longer change (on the space frame a strong-axis connection at 1e-6 of nominal
/// moves no frequency by 1e-7 relative from its value at 1e-30), and a fit left free there
/// walks `ln θ` towards ±∞ in capped steps (50 iterations of a splice's refit, and of the
/// profile points that check it) while its Gauss–Newton model, linear in `ln θ`, keeps
/// promising the decrease the other parameters could give.
pub(super) const THETA_RANGE: (f64, f64) = (1e-6, 1e6);

pub(super) fn mm_options() -> ModeMatchingOptions {
    ModeMatchingOptions {
        step: StepControl::LevenbergMarquardt,
        tol: 1e-6,
        max_iterations: 100,
        final_step: FinalStep::Evaluate,
        sigma_tol: Some(0.01),
        // ε to 1e-3: far below what the tests (Λ against ~24, Δε 6) and the profile's
        // curvature (ε differences ≳ 0.05 over ±5 % of the value) resolve. Without it, fits
        // of a candidate that cannot explain the data creep along a flat valley of ε for
        // 20–50 iterations and stall.
        eps_tol: Some(1e-3),
        error_tol: None,
        bounds: Some(THETA_RANGE),
        // Held, not cut: an insensitive θ on its bound would otherwise shrink every other
        // component's step to its own scale.
        bound_step: BoundStep::Hold,
    }
}

pub(super) fn build(
    spec: &Description,
    what: impl FnOnce() -> String,
) -> Result<Model, DiagnosisError> {
    spec.build().map_err(|source| DiagnosisError::Model {
        what: what(),
        source,
    })
}

/// Fits `spec` to `data` from `theta0` (globalized if `global`).
pub(super) fn fit(
    spec: &Description,
    data: &MeasuredData,
    theta0: &[f64],
    global: bool,
) -> Result<Fit, DiagnosisError> {
    let model = build(spec, || "the effects named so far".into())?;
    let ev = Evaluator::new(&model)?;
    let mut mm = ModeMatching::new(ev);
    let opts = mm_options();
    let result = if global {
        mm.run_global_parallel(&model, data, theta0, &opts)
            .map(|r| r.0)
    } else {
        mm.run(&model, data, theta0, &opts)
    }?;
    Ok(Fit { model, result })
}

/// ε at the profile point `u` of an effect: θ refitted from each of `starts` (the best
/// kept: the fitted θ of the model without the effect can sit in a valley the effect's
/// true value does not share), +∞ when the enriched model cannot be built or fitted.
/// The starts run side by side on rayon's pool, each on its own evaluator (a cold
/// evaluation depends on θ alone, so each fit is the one a shared evaluator gives): the
/// refit that takes longest then uses the cores the others have left.
pub(super) fn profile_point(
    spec: &Description,
    effect: &dyn Effect,
    location: &str,
    u: f64,
    data: &MeasuredData,
    starts: &[&[f64]],
) -> (f64, Vec<f64>) {
    use rayon::prelude::*;
    let mut best = (f64::INFINITY, starts[0].to_vec());
    let Some(model) = model_with(spec, effect, location, u) else {
        return best;
    };
    let fits: Vec<Option<(f64, Vec<f64>)>> = starts
        .par_iter()
        .map(|t| {
            let mut mm = ModeMatching::new(Evaluator::new(&model).ok()?);
            let r = mm.run(&model, data, t, &mm_options()).ok()?;
            Some((r.epsilon(), r.theta))
        })
        .collect();
    for (eps, theta) in fits.into_iter().flatten() {
        if eps < best.0 {
            best = (eps, theta);
        }
    }
    best
}

/// The model class with `effect` at `location` of value `u`, and an evaluator for it;
/// `None` when the effect does not apply there or the model does not build.
pub(super) fn with_effect(
    spec: &Description,
    effect: &dyn Effect,
    location: &str,
    u: f64,
) -> Option<(Model, Evaluator)> {
    let model = model_with(spec, effect, location, u)?;
    let evaluator = Evaluator::new(&model).ok()?;
    Some((model, evaluator))
}

/// The model class with `effect` at `location` of value `u`; `None` when the effect does
/// not apply there or the model does not build.
pub(super) fn model_with(
    spec: &Description,
    effect: &dyn Effect,
    location: &str,
    u: f64,
) -> Option<Model> {
    let mut s = spec.clone();
    effect.apply(&mut s, location, u).ok()?;
    s.build().ok()
}

/// The misfit of a fitted model, per mode and per channel.
pub(super) fn localize(model: &Model, data: &MeasuredData, ev: &Evaluation) -> Localization {
    let channels = model.channels();
    let mut per_channel: Vec<(String, f64, usize)> =
        channels.iter().map(|c| (c.name.clone(), 0.0, 0)).collect();
    let mut modes = Vec::new();
    let mut at = 0;
    for (m, mode) in data.modes.iter().enumerate() {
        let k = ev.pairing[m];
        modes.push(ModeMisfit {
            measured_hz: mode.lambda.sqrt() / (2.0 * std::f64::consts::PI),
            model_hz: ev.eig.frequency_hz(k),
            error_sigma: ev.r[at],
            mac: ev.mac[m],
            paired_with: k + 1,
        });
        at += 1;
        if let Some(s) = &mode.shape {
            for &c in &s.channels {
                per_channel[c].1 += ev.r[at] * ev.r[at];
                per_channel[c].2 += 1;
                at += 1;
            }
        }
    }
    Localization {
        epsilon: ev.epsilon,
        theta: ev.theta.clone(),
        modes,
        channels: per_channel,
    }
}
