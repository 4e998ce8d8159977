//! Refitting the best candidates with the full nonlinear update (the minimum of the profile
//! ε(u) = min_θ ε(θ, u), found by the joint fit of [`super::joint`] and checked on the
//! profile) and the Laplace uncertainty of the effect's value: step 3.

use std::cell::RefCell;

use super::joint::{Coordinate, Joint, JointMinimum};
use super::*;

/// The full nonlinear refit of one candidate (module docs, step 3): the minimum of the
/// profile found by the joint fit ([`Joint`]) and confirmed on the profile, or by the
/// profile search where the joint fit cannot be used; then the Laplace σ of the value.
pub(super) fn refit(
    spec: &Description,
    effect: &dyn Effect,
    c: &Candidate,
    data: &MeasuredData,
    theta0: &[f64],
) -> Option<Refit> {
    let coord = Coordinate {
        sign: effect.sign(),
        h: effect.step(spec, &c.location),
    };
    let profile = Profile {
        spec,
        effect,
        location: &c.location,
        data,
        theta0,
        nominal: spec.build().ok()?.nominal_theta(),
        best: RefCell::new((f64::INFINITY, theta0.to_vec())),
        from_all: RefCell::new(None),
    };
    let (t0, d) = coord.start(c.u_linear);
    let joint = Joint {
        spec,
        effect,
        location: &c.location,
        data,
        coord,
    };
    let (mut t, mut eps) = match joint.fit(theta0, t0) {
        Some(m) => profile.confirm(m, coord),
        None => None,
    }
    .map_or_else(|| profile.search(t0, d, coord), Some)?;
    // Laplace: σ_u² = 2 / ε''(u), by a three-point difference around the minimum. A
    // neighbour below the minimum means the joint fit stopped short of it: the profile
    // search goes on from there.
    let mut laplace = profile.curvature(coord.u(t), eps, coord);
    if laplace.lower_neighbour {
        (t, eps) = profile.search(t, d, coord)?;
        laplace = profile.curvature(coord.u(t), eps, coord);
    }
    let u = coord.u(t);
    let (_, theta) = profile.at(u, true);
    let std_u = if laplace.curvature > 0.0 {
        (2.0 / laplace.curvature).sqrt()
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

/// The profile `ε(u) = min_θ ε(θ, u)` of one candidate: every point an inner fit of θ.
struct Profile<'a> {
    spec: &'a Description,
    effect: &'a dyn Effect,
    location: &'a str,
    data: &'a MeasuredData,
    /// The fitted θ without the effect.
    theta0: &'a [f64],
    nominal: Vec<f64>,
    /// The lowest point so far: its ε and θ.
    best: RefCell<(f64, Vec<f64>)>,
    /// The last point fitted from every start: its `u`, ε and θ.
    from_all: RefCell<Option<(f64, f64, Vec<f64>)>>,
}

/// The profile's second difference around its minimum.
struct Laplace {
    curvature: f64,
    /// A neighbour lies below the minimum by more than the search resolves.
    lower_neighbour: bool,
}

/// ε differences the profile resolves: its points are fitted to 1e-3 (`fit::mm_options`).
const PROFILE_RESOLUTION: f64 = 1e-2;

impl Profile<'_> {
    /// ε at `u` with θ fitted from the θ of the best point so far (continuation), or, if
    /// `all` or at the first point, also from the fitted θ without the effect and from the
    /// nominal θ (module docs, step 3).
    fn at(&self, u: f64, all: bool) -> (f64, Vec<f64>) {
        if let Some((at, eps, theta)) = &*self.from_all.borrow()
            && all
            && *at == u
        {
            return (*eps, theta.clone());
        }
        let last = self.best.borrow().1.clone();
        let starts: &[&[f64]] = if all || !self.best.borrow().0.is_finite() {
            &[self.theta0, &self.nominal, &last]
        } else {
            &[&last]
        };
        let r = profile_point(self.spec, self.effect, self.location, u, self.data, starts);
        self.remember(&r);
        if all {
            *self.from_all.borrow_mut() = Some((u, r.0, r.1.clone()));
        }
        r
    }

    /// The joint fit's minimum checked on the profile: θ refitted there from every start.
    /// `None` if another start finds a lower ε (the joint path followed a valley that is
    /// not the lowest).
    fn confirm(&self, m: JointMinimum, coord: Coordinate) -> Option<(f64, f64)> {
        *self.best.borrow_mut() = (m.epsilon, m.theta);
        let (eps, _) = self.at(coord.u(m.t), true);
        (eps >= m.epsilon - PROFILE_RESOLUTION).then_some((m.t, eps.min(m.epsilon)))
    }

    /// The profile search: a downhill bracket and Brent's method from `t0` with step `d`,
    /// the inner fits by continuation. Should the minimum's other starts find a lower ε
    /// than the continuation did, the path followed a valley that is not the lowest: the
    /// search is repeated with all three starts everywhere.
    fn search(&self, t0: f64, d: f64, coord: Coordinate) -> Option<(f64, f64)> {
        let (mut t, mut eps) = minimize_1d(|t| self.at(coord.u(t), false).0, t0, d, 2e-3);
        if !eps.is_finite() {
            return None;
        }
        let (eps_all, _) = self.at(coord.u(t), true);
        if eps_all < eps - PROFILE_RESOLUTION {
            (t, eps) = minimize_1d(|t| self.at(coord.u(t), true).0, t, d, 2e-3);
        }
        Some((t, eps))
    }

    /// The second difference of the profile at ±5 % of the value (of the effect's step
    /// near zero).
    fn curvature(&self, u: f64, eps: f64, coord: Coordinate) -> Laplace {
        let du = match coord.sign {
            Sign::Positive => 0.05 * u,
            Sign::Any => 0.05 * u.abs().max(coord.h),
        };
        let (em, ep) = self.neighbours(u - du, u + du);
        Laplace {
            curvature: (ep - 2.0 * eps + em) / (du * du),
            lower_neighbour: em.min(ep) < eps - PROFILE_RESOLUTION,
        }
    }

    /// `self.at(a, false)` then `self.at(b, false)`, the two fits run side by side. Both
    /// start from the best point so far, as they would in turn, unless the first finds a new
    /// best: then the second is fitted again from it, as in turn.
    fn neighbours(&self, a: f64, b: f64) -> (f64, f64) {
        if !self.best.borrow().0.is_finite() {
            return (self.at(a, false).0, self.at(b, false).0);
        }
        let last = self.best.borrow().1.clone();
        let (spec, effect, location, data) = (self.spec, self.effect, self.location, self.data);
        let fit = |u: f64| profile_point(spec, effect, location, u, data, &[&last]);
        let (ra, rb) = rayon::join(|| fit(a), || fit(b));
        if self.remember(&ra) {
            return (ra.0, self.at(b, false).0);
        }
        self.remember(&rb);
        (ra.0, rb.0)
    }

    /// `r` kept as the best point if its ε is the lowest so far; whether it was.
    fn remember(&self, r: &(f64, Vec<f64>)) -> bool {
        let lower = r.0 < self.best.borrow().0;
        if lower {
            *self.best.borrow_mut() = r.clone();
        }
        lower
    }
}

/// `f` over `items` on rayon's pool (results in item order); `progress(done)` on the
/// calling thread as items finish. The items are dealt in order, one at a time, to
/// whichever worker is free, so the first items start first: a shortlist is best first
/// and its costly refits are near its head, where rayon's halving of the range could leave
/// one of them to start last.
pub(super) fn map_with_progress<T: Sync, R: Send>(
    items: &[T],
    f: impl Fn(&T) -> R + Sync,
    mut progress: impl FnMut(usize),
) -> Vec<R> {
    use std::sync::Mutex;
    use std::sync::atomic::{AtomicUsize, Ordering};
    let (tx, rx) = std::sync::mpsc::channel::<()>();
    let slots: Vec<Mutex<Option<R>>> = items.iter().map(|_| Mutex::new(None)).collect();
    let next = AtomicUsize::new(0);
    let workers = rayon::current_num_threads().clamp(1, items.len().max(1));
    let (f, slots, next) = (&f, &slots, &next);
    std::thread::scope(|scope| {
        let work = scope.spawn(move || {
            rayon::scope(|s| {
                for _ in 0..workers {
                    let tx = tx.clone();
                    s.spawn(move |_| {
                        loop {
                            let i = next.fetch_add(1, Ordering::Relaxed);
                            let Some(item) = items.get(i) else { break };
                            let r = f(item);
                            *slots[i].lock().unwrap_or_else(|p| p.into_inner()) = Some(r);
                            let _ = tx.send(());
                        }
                    });
                }
            });
        });
        for (done, ()) in rx.iter().enumerate() {
            progress(done + 1);
        }
        work.join().unwrap_or_else(|p| std::panic::resume_unwind(p))
    });
    slots
        .iter()
        .map(|m| {
            m.lock()
                .unwrap_or_else(|p| p.into_inner())
                .take()
                .expect("every item is mapped")
        })
        .collect()
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
    use crate::core::diagnosis::fixtures::NOISE;
    use crate::core::simulate::simulated_measured_data;

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
        let data = simulated_measured_data(&model, &theta, 9, NOISE, true, 1).unwrap();
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
