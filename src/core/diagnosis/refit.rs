//! Refitting the best candidates with the full nonlinear update (the profile ε(u) with θ
//! refitted at every u) and the Laplace uncertainty of the effect's value: step 3.

use super::*;

/// The full nonlinear refit of one candidate (module docs, step 3).
pub(super) fn refit(
    spec: &Description,
    effect: &dyn Effect,
    c: &Candidate,
    data: &MeasuredData,
    theta0: &[f64],
) -> Option<Refit> {
    let h = effect.step(spec, &c.location);
    // The search coordinate: ln u for effects of one sign, u / h otherwise.
    let (t0, d, to_u): (f64, f64, Box<dyn Fn(f64) -> f64>) = match effect.sign() {
        Sign::Positive => (c.u_linear.max(h * 1e-3).ln(), 0.7, Box::new(f64::exp)),
        Sign::Any => (
            c.u_linear / h,
            (c.u_linear.abs() / h / 2.0).max(1.0),
            Box::new(move |t| t * h),
        ),
    };
    // Starts of the inner fits: the fitted θ without the effect, the nominal θ, and the θ of
    // the best profile point so far (continuation). All three at the first point and at the
    // minimum found; in between the continuation alone (its fits are short, u moves little).
    // Should the minimum's other starts find a lower ε than the continuation did, the path
    // followed a valley that is not the lowest: the search is repeated with all three
    // everywhere.
    let nominal = spec.build().ok()?.nominal_theta();
    let best = std::cell::RefCell::new((f64::INFINITY, theta0.to_vec()));
    let eps_at = |u: f64, all: bool| {
        let last = best.borrow().1.clone();
        let starts: &[&[f64]] = if all || !best.borrow().0.is_finite() {
            &[theta0, &nominal, &last]
        } else {
            &[&last]
        };
        let r = profile_point(spec, effect, &c.location, u, data, starts);
        if r.0 < best.borrow().0 {
            *best.borrow_mut() = r.clone();
        }
        r
    };
    let (mut t, mut eps) = minimize_1d(|t| eps_at(to_u(t), false).0, t0, d, 2e-3);
    if !eps.is_finite() {
        return None;
    }
    let (eps_all, _) = eps_at(to_u(t), true);
    if eps_all < eps - 1e-2 {
        (t, eps) = minimize_1d(|t| eps_at(to_u(t), true).0, t, d, 2e-3);
    }
    let u = to_u(t);
    let (_, theta) = eps_at(u, true);
    // Laplace: σ_u² = 2 / ε''(u), by a three-point difference around the minimum.
    let du = match effect.sign() {
        Sign::Positive => 0.05 * u,
        Sign::Any => 0.05 * u.abs().max(h),
    };
    let (em, ep) = (eps_at(u - du, false).0, eps_at(u + du, false).0);
    let curvature = (ep - 2.0 * eps + em) / (du * du);
    let std_u = if curvature > 0.0 {
        (2.0 / curvature).sqrt()
    } else {
        f64::NAN
    };
    Some(Refit {
        effect: effect.kind(),
        unit: effect.unit(&c.location),
        location: c.location.clone(),
        u,
        std_u,
        value: effect.value(u),
        std: effect.value_std(u, std_u),
        epsilon: eps,
        theta,
    })
}

/// `f` over `items` on rayon's pool (results in item order); `progress(done)` on the
/// calling thread as items finish.
pub(super) fn map_with_progress<T: Sync, R: Send>(
    items: &[T],
    f: impl Fn(&T) -> R + Sync,
    mut progress: impl FnMut(usize),
) -> Vec<R> {
    use rayon::prelude::*;
    let (tx, rx) = std::sync::mpsc::channel::<()>();
    let f = &f;
    std::thread::scope(|scope| {
        let work = scope.spawn(move || {
            items
                .par_iter()
                .map_with(tx, |tx, item| {
                    let r = f(item);
                    let _ = tx.send(());
                    r
                })
                .collect::<Vec<R>>()
        });
        for (done, ()) in rx.iter().enumerate() {
            progress(done + 1);
        }
        work.join().unwrap_or_else(|p| std::panic::resume_unwind(p))
    })
}

/// `spec` with `named` added at their values.
pub(super) fn with_effects(
    spec: &Description,
    effects: &[Box<dyn Effect>],
    named: &[&Refit],
) -> Result<Description, DiagnosisError> {
    let mut s = spec.clone();
    for r in named {
        effect_of(effects, r.effect).apply(&mut s, &r.location, r.u)?;
    }
    Ok(s)
}

/// One pass of coordinate descent over the values of `set`: each effect's value refitted
/// (profile) with the others at theirs. Returns ε of `spec` with the set at its new values.
/// An effect another one of the set depends on (a splice whose new node carries a named
/// mass) keeps its value: the model without it cannot be built.
pub(super) fn reprofile(
    spec: &Description,
    effects: &[Box<dyn Effect>],
    set: &mut [Refit],
    data: &MeasuredData,
    theta: &[f64],
) -> Result<(f64, Vec<f64>), DiagnosisError> {
    let mut theta = theta.to_vec();
    for i in 0..set.len() {
        let others: Vec<&Refit> = set
            .iter()
            .enumerate()
            .filter(|&(k, _)| k != i)
            .map(|(_, r)| r)
            .collect();
        let without = match with_effects(spec, effects, &others) {
            Ok(s) => s,
            Err(DiagnosisError::Location(_)) => continue,
            Err(e) => return Err(e),
        };
        let c = Candidate {
            effect: set[i].effect,
            location: set[i].location.clone(),
            score: 0.0,
            u_linear: set[i].u,
        };
        if let Some(better) = refit(&without, effect_of(effects, c.effect), &c, data, &theta) {
            theta = better.theta.clone();
            set[i] = better;
        }
    }
    let refs: Vec<&Refit> = set.iter().collect();
    let f = fit(&with_effects(spec, effects, &refs)?, data, &theta, false)?;
    Ok((f.result.epsilon(), f.result.theta))
}

pub(super) fn effect_of<'a>(effects: &'a [Box<dyn Effect>], kind: &str) -> &'a dyn Effect {
    effects
        .iter()
        .find(|e| e.kind() == kind)
        .expect("an effect of the catalogue")
        .as_ref()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::simulate::{Noise, simulated_measured_data};

    fn named(effect: &'static str, location: &str, u: f64) -> Refit {
        Refit {
            effect,
            unit: "",
            location: location.into(),
            u,
            std_u: f64::NAN,
            value: u,
            std: f64::NAN,
            epsilon: f64::NAN,
            theta: Vec::new(),
        }
    }

    /// A splice of B2 at its second mesh node and a mass on the node its first part then
    /// has (`B2~a.1`, which exists only with the splice): the mass is refitted, the splice
    /// keeps its value (the model without it cannot carry the mass), and the pass does not
    /// fail. Before, the whole diagnosis failed with "`B2~a.1` is not a free node".
    #[test]
    fn an_effect_another_depends_on_keeps_its_value() {
        let text = std::fs::read_to_string(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/config/models/lab-frame.toml"
        ))
        .unwrap();
        let spec = Description::File(toml::from_str(&text).unwrap());
        let effects = effects::catalogue();
        let mut set = vec![
            named("splice", "B2.2", 2e4),
            named("added-mass", "B2~a.1", 0.2),
        ];
        let with = with_effects(&spec, &effects, &set.iter().collect::<Vec<_>>()).unwrap();
        let model = with.build().unwrap();
        let theta = model.nominal_theta();
        let noise = Noise {
            frequency_cov: 0.01,
            shape_nsd: 0.05,
        };
        let data = simulated_measured_data(&model, &theta, 9, noise, true, 1).unwrap();
        let (eps, _) = reprofile(&spec, &effects, &mut set, &data, &theta).unwrap();
        assert!(eps.is_finite());
        assert_eq!(set[0].u, 2e4, "the splice keeps its value");
        assert!(
            set[1].std.is_finite(),
            "the mass was refitted: {:?}",
            set[1]
        );
    }
}
