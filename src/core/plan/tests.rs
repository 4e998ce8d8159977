use super::*;
use crate::core::model::Channel;
use crate::core::model::spec::ModelSpec;
use crate::core::simulate::simulated_measured_data;
use crate::core::updating::{ModeMatching, ModeMatchingOptions};

fn lab_frame() -> Model {
    let spec = crate::io::model::load_spec(std::path::Path::new("bundled:lab-frame")).unwrap();
    Model::from_spec(&spec).unwrap()
}

const NOISE: Noise = Noise {
    frequency_cov: 0.01,
    shape_nsd: 0.05,
};

/// With every channel and 9 modes the prediction is the σ the tracker's fit reports on
/// noise-free data stated with the same σ (it converges at the nominal parameters).
#[test]
fn the_prediction_is_the_fits_covariance_at_the_nominal_parameters() {
    let model = lab_frame();
    let all: Vec<usize> = (0..model.channels().len()).collect();
    let mut planner = Planner::new(model.clone(), 9, NOISE).unwrap();
    let predicted = planner.sigma(&all, &(0..9).collect::<Vec<_>>()).unwrap();
    let theta0 = model.nominal_theta();
    let data = simulated_measured_data(&model, &theta0, 9, NOISE, false, 1).unwrap();
    let mut evaluator = Evaluator::new(&model).unwrap();
    evaluator.set_pairing(Pairing::Misfit);
    let mut mm = ModeMatching::new(evaluator);
    let fit = mm
        .run(&model, &data, &theta0, &ModeMatchingOptions::default())
        .unwrap();
    for (l, (p, f)) in predicted.iter().zip(fit.std()).enumerate() {
        // Same formula at the same θ: equal to rounding.
        assert!(
            (p - f).abs() <= 1e-9 * f.abs().max(1e-12),
            "{l}: {p} against {f}"
        );
    }
}

/// Taking channels away raises σ, and the greedy choice puts back what matters: from
/// a third of the channels, each added channel lowers the worst relative σ.
#[test]
fn greedy_additions_lower_the_worst_sigma_step_by_step() {
    let model = lab_frame();
    let n = model.channels().len();
    let modes: Vec<usize> = (0..9).collect();
    let mut planner = Planner::new(model, 9, NOISE).unwrap();
    let few: Vec<usize> = (0..n).step_by(3).collect();
    let all: Vec<usize> = (0..n).collect();
    let sigma_few = planner.sigma(&few, &modes).unwrap();
    let (worst_few, _) = planner.worst(&sigma_few);
    let sigma_all = planner.sigma(&all, &modes).unwrap();
    let (worst_all, _) = planner.worst(&sigma_all);
    assert!(worst_all < worst_few, "{worst_all} against {worst_few}");
    let steps = planner
        .greedy(&few, &all, &modes, 4, Criterion { needed: 0.0 })
        .unwrap();
    let mut last = worst_few;
    for s in &steps {
        assert!(s.worst < last, "{} after {last}", s.worst);
        assert!(!few.contains(&s.channel));
        last = s.worst;
    }
    let e = planner
        .greedy(&few, &all, &modes, n, Criterion { needed: 0.0 })
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("only"), "{e}");
}

/// Monte Carlo: 200 noisy sets (every channel, 9 modes, the stated noise drawn), each
/// fitted from the nominal parameters; the sample σ of every parameter is within 20 %
/// of the prediction. With 200 sets a sample σ's own relative standard error is
/// 1/√400 = 5 %: 20 % is four of them, leaving room for the estimate's nonlinearity.
#[test]
fn the_prediction_matches_the_scatter_of_fits_to_noisy_sets() {
    let model = lab_frame();
    let all: Vec<usize> = (0..model.channels().len()).collect();
    let mut planner = Planner::new(model.clone(), 9, NOISE).unwrap();
    let predicted = planner.sigma(&all, &(0..9).collect::<Vec<_>>()).unwrap();
    let theta0 = model.nominal_theta();
    let mut mm = ModeMatching::new(Evaluator::new(&model).unwrap());
    let fits: Vec<Vec<f64>> = (0..200)
        .map(|seed| {
            let data = simulated_measured_data(&model, &theta0, 9, NOISE, true, seed).unwrap();
            let opts = ModeMatchingOptions::default();
            mm.run(&model, &data, &theta0, &opts).unwrap().theta
        })
        .collect();
    for (l, p) in predicted.iter().enumerate() {
        let x: Vec<f64> = fits.iter().map(|t| t[l]).collect();
        let sample = crate::core::stats::sample_std(&x);
        assert!(
            (sample / p - 1.0).abs() < 0.2,
            "{l}: sample {sample} against {p}"
        );
    }
}

/// Against the installed channels' noise, a channel added only adds information: no σ
/// rises (to rounding), whichever channel it is. (Stated against the RMS of whatever is
/// measured, a loud channel would make every other one noisier.)
#[test]
fn with_a_reference_an_added_channel_never_raises_a_sigma() {
    let model = lab_frame();
    let n = model.channels().len();
    let modes: Vec<usize> = (0..9).collect();
    let installed: Vec<usize> = (0..n).step_by(2).collect();
    let mut planner = Planner::new(model, 9, NOISE)
        .unwrap()
        .with_reference(&installed);
    let before = planner.sigma(&installed, &modes).unwrap();
    for extra in (1..n).step_by(2) {
        let mut more = installed.clone();
        more.push(extra);
        let after = planner.sigma(&more, &modes).unwrap();
        for (l, (a, b)) in after.iter().zip(&before).enumerate() {
            assert!(
                *a <= b * (1.0 + 1e-9),
                "channel {extra}, parameter {l}: {b} → {a}"
            );
        }
    }
}

#[test]
fn zero_modes_are_refused() {
    let e = Planner::new(lab_frame(), 0, NOISE)
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("--modes"), "{e}");
}

/// Kammer's shares: each channel's is in [0, 1] and they sum to the number of modes (the
/// trace of a rank-m projector); effective independence removes the channel of least
/// share first, and never an installed one.
#[test]
fn effective_independence_removes_the_least_independent_channel() {
    let model = lab_frame();
    let n = model.channels().len();
    let modes: Vec<usize> = (0..9).collect();
    let planner = Planner::new(model, 9, NOISE).unwrap();
    let all: Vec<usize> = (0..n).collect();
    let share = planner.independence(&all, &modes).unwrap();
    let sum: f64 = share.iter().sum();
    assert!((sum - 9.0).abs() < 1e-9, "{sum}");
    assert!(share.iter().all(|&e| (-1e-12..=1.0 + 1e-12).contains(&e)));
    let least = (0..n)
        .min_by(|&a, &b| share[a].total_cmp(&share[b]))
        .unwrap();
    let kept = planner
        .effective_independence(&[], &all, &modes, n - 1)
        .unwrap();
    assert!(!kept.contains(&least) && kept.len() == n - 1);
    // With the least one installed it stays, and another goes.
    let kept = planner
        .effective_independence(&[least], &all, &modes, n - 2)
        .unwrap();
    assert_eq!(kept.len(), n - 2);
    assert!(!kept.contains(&least));
    // Fewer channels than modes cannot span them.
    let e = planner
        .effective_independence(&[], &all[..4], &modes, 2)
        .unwrap_err()
        .to_string();
    assert!(e.contains("span"), "{e}");
}

/// The score: undetermined connections first, then the shortfall from what is needed,
/// then the worst σ.
#[test]
fn the_criterion_counts_the_undetermined_then_the_shortfall_then_the_worst() {
    let c = Criterion { needed: 0.2 };
    assert!(c.score(&[0.1, f64::INFINITY]) > c.score(&[0.9, 0.9]));
    assert_eq!(c.score(&[0.1, 0.4])[1], 1.0);
    // Both meet the need: the worst decides.
    assert!(c.score(&[0.1, 0.15]) < c.score(&[0.05, 0.19]));
    // One far short against two a little short: the smaller total shortfall wins.
    assert!(c.score(&[0.25, 0.25]) < c.score(&[0.1, 0.5]));
}

/// A drawn set: frequencies ascending, one σ per mode, and over many draws the scatter
/// of a shape entry is that σ (2000 draws: the sample σ within 10 %, six of its 1.6 %
/// standard errors).
#[test]
fn a_drawn_set_has_the_planned_scatter() {
    let model = lab_frame();
    let channels: Vec<usize> = (0..model.channels().len()).step_by(2).collect();
    let modes: Vec<usize> = (0..9).collect();
    let planner = Planner::new(model, 9, NOISE)
        .unwrap()
        .with_reference(&channels);
    let mut rng = <rand_chacha::ChaCha8Rng as rand::SeedableRng>::seed_from_u64(3);
    let exact = planner.draw(&channels, &modes, &mut rng);
    assert!(
        exact
            .windows(2)
            .all(|w| w[0].0.frequency_hz <= w[1].0.frequency_hz)
    );
    let sigma = planner.shape_sigma(0, &channels);
    let x: Vec<f64> = (0..2000)
        .map(|_| {
            let set = planner.draw(&channels, &[0], &mut rng);
            set[0].0.shape[0]
        })
        .collect();
    let sd = crate::core::stats::sample_std(&x);
    assert!((sd / sigma - 1.0).abs() < 0.1, "{sd} against {sigma}");
}

/// A two-bay solid frame of six elements along each beam: its five beams' own channels at
/// 1/3 and 2/3 of their length are element corners 2 and 4 of 6.
fn small_solid() -> ModelSpec {
    toml::from_str(include_str!("../../../tests/data/two-bay-solid.toml")).unwrap()
}

/// A solid's candidates are points on its beams' axes at every sixth of their length, less
/// the two its own channels read: three places of three translations on each of 5 beams;
/// each reads DOFs no own channel reads, and the planner takes them as channels.
#[test]
fn a_solids_candidates_are_its_beams_axis_points_not_read_already() {
    use places::{Places, with_candidates};
    let spec = small_solid();
    let base = Model::from_spec(&spec).unwrap();
    let w = with_candidates(Some(&spec), &base, Places::Nodes).unwrap();
    let own = base.channels().len();
    assert_eq!(own, 30);
    assert_eq!(w.model.channels().len(), own + 45);
    let added = &w.model.channels()[own..];
    assert_eq!(added[0].name, "B1@0.167.x");
    for c in added {
        assert!(
            base.channels().iter().all(|o| o.dofs != c.dofs),
            "{} reads what an own channel reads",
            c.name
        );
    }
    let names: Vec<&str> = added.iter().map(|c| c.name.as_str()).collect();
    assert!(
        !names
            .iter()
            .any(|n| n.contains("@0.333") || n.contains("@0.667"))
    );
    // A planner over them: adding the candidates lowers no σ below what every channel gives.
    let mut planner = Planner::new(w.model.clone(), 6, NOISE).unwrap();
    let modes: Vec<usize> = (0..6).collect();
    let own_idx: Vec<usize> = (0..own).collect();
    let every: Vec<usize> = (0..own + 45).collect();
    let (before, after) = (
        planner.sigma(&own_idx, &modes).unwrap(),
        planner.sigma(&every, &modes).unwrap(),
    );
    for (b, a) in before.iter().zip(&after) {
        assert!(a.is_finite() && *a <= b * (1.0 + 1e-9), "{b} → {a}");
    }
}

/// An imported model's candidates are its DOFs by label, less those a channel reads on its
/// own: the 18-storey shear frame's 18 floors less its 6 measured; with no named
/// locations, `nodes` is refused, naming why; and a name used twice is refused.
#[test]
fn an_imported_models_candidates_are_its_dofs_by_label() {
    use places::{Places, with_candidates};
    let json =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/smu-shear-18/model.json");
    let base = crate::io::model::load_model(&json).unwrap();
    let w = with_candidates(None, &base, Places::Dofs).unwrap();
    assert_eq!(w.model.channels().len(), 18);
    assert_eq!(w.candidates.len(), 18);
    let added: Vec<&str> = w.model.channels()[6..]
        .iter()
        .map(|c| c.name.as_str())
        .collect();
    assert_eq!(&added[..3], ["floor1", "floor2", "floor4"]);
    let Err(err) = with_candidates(None, &base, Places::Nodes) else {
        panic!("nodes of a model with no locations");
    };
    assert!(format!("{err:#}").contains("names no locations"), "{err:#}");
    let twice = Channel {
        name: "floor3".into(),
        dofs: vec![(0, 1.0)],
    };
    let err = base.with_channels(vec![twice]).unwrap_err();
    assert!(err.to_string().contains("floor3"), "{err}");
    // The model has no connection parameters: every parameter is watched.
    let planner = Planner::new(w.model, 6, NOISE).unwrap();
    assert_eq!(planner.watched().len(), 18);
}
