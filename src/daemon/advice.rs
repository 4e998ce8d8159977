//! The start-up report on connections with alerts off: once a structure has its baseline
//! (at start from its checkpoint, or when commissioning ends during the run), what would
//! turn each such connection's alerts on ([`crate::pipeline::advice`]), computed on a
//! thread of its own, logged as one warning per connection and kept in the status
//! (`advice`, or `advice_unavailable` with the reason). It is started only if it fits the
//! memory budget ([`MemoryBudget::refuses_advice`]).
//!
//! The candidates are the model's places of every kind ([`Places::All`]: translations and
//! rotations at every node); at most [`MAX_ADD`] sensors, or twice the commissioning sets'
//! modes, are tried. The stated noise is the planner's default (`boltwatch plan --noise`):
//! the measured σ rescales it per connection, so only its split between frequencies and
//! shapes matters.

use std::sync::Arc;

use anyhow::Result;

use super::metrics::Shared;
use crate::contract::{Advice, AdviceModes, AdviceSensors};
use crate::core::plan::places::{Places, with_candidates};
use crate::core::simulate::Noise;
use crate::io::driver::{MemoryBudget, StructureModel};
use crate::pipeline::Tracker;
use crate::pipeline::advice::{Limits, Remedy, remedies};
use crate::pipeline::detectability::Detectability;

/// The most sensors the advice adds.
pub const MAX_ADD: usize = 12;

/// The noise the predictions are stated with (rescaled by the measured σ).
const NOISE: Noise = Noise {
    frequency_cov: 0.01,
    shape_nsd: 0.05,
};

/// Sets per day the filter's commissioning σ assumes (the planner's default).
const PER_DAY: f64 = 4.0;

/// Starts the advice for `tracker`'s connections with alerts off, if it has any and it
/// fits `budget`; returns whether it started (`false`: nothing to advise on yet, no
/// connection is off, or the budget refuses it, which the status then says).
pub fn advise(
    model: StructureModel,
    tracker: &Tracker,
    shared: Arc<Shared>,
    budget: Option<MemoryBudget>,
) -> bool {
    let off = tracker.alerts_off_sigma();
    let n_modes = tracker.state().commissioning_modes;
    let channels = tracker.state().commissioning_channels.clone();
    if off.is_empty() || n_modes == 0 {
        return false;
    }
    if let Some(why) = budget.and_then(|b| b.refuses_advice(&model.1, 2 * n_modes)) {
        publish(&shared, Err(anyhow::anyhow!(why)));
        return false;
    }
    let rules = Detectability::of(tracker.config(), PER_DAY);
    let name = shared.structure.clone();
    let work = move || {
        let found = compute(&model, &rules, &off, (&channels, n_modes));
        publish(&shared, found);
    };
    if let Err(e) = std::thread::Builder::new()
        .name(format!("advice-{name}"))
        .spawn(work)
    {
        tracing::warn!(structure = name, "no advice on the alerts off: {e}");
    }
    true
}

/// The advice for the connections `off` of sets that carried `n_modes` modes at the
/// `channels` named (all the model's when none is: a checkpoint of an older version).
pub fn compute(
    model: &StructureModel,
    rules: &Detectability,
    off: &[(usize, f64)],
    (channels, n_modes): (&[String], usize),
) -> Result<Vec<Advice>> {
    let (spec, base) = &**model;
    let with = with_candidates(spec.as_ref(), base, Places::All)?;
    let mut installed: Vec<usize> = channels
        .iter()
        .filter_map(|c| with.model.channel_index(c))
        .collect();
    if installed.is_empty() {
        installed = (0..base.channels().len()).collect();
    }
    installed.sort_unstable();
    let limits = Limits {
        max_add: MAX_ADD,
        max_modes: 2 * n_modes,
    };
    let found = remedies(&with, &installed, n_modes, NOISE, rules, off, limits)?;
    Ok(found
        .into_iter()
        .map(|r| {
            advice(
                &base.parameters()[r.parameter].name,
                r,
                installed.len(),
                n_modes,
            )
        })
        .collect())
}

/// One connection's remedy as the status states it.
fn advice(connection: &str, r: Remedy, channels: usize, modes: usize) -> Advice {
    Advice {
        connection: connection.to_string(),
        measured_std: r.measured,
        predicted_std: r.predicted,
        channels,
        modes,
        summary: r.describe(channels, modes),
        sensors: r.sensors.map(|(add, std)| AdviceSensors { add, std }),
        more_modes: r.modes.map(|(modes, std)| AdviceModes { modes, std }),
    }
}

/// Logs the advice, one warning per connection, and puts it in the status.
fn publish(shared: &Shared, found: Result<Vec<Advice>>) {
    let structure = &shared.structure;
    match found {
        Ok(advice) => {
            for a in &advice {
                let connection = &a.connection;
                tracing::warn!(structure, connection, "alerts off: {}", a.summary);
            }
            shared.with_status(|st| {
                st.advice = advice;
                st.advice_unavailable = None;
            });
        }
        Err(e) => {
            let why = format!("{e:#}");
            tracing::warn!(structure, "no advice on the alerts off: {why}");
            shared.with_status(|st| st.advice_unavailable = Some(why));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::commands::plan::verify::Check;
    use crate::core::model::Model;
    use crate::core::plan::Planner;

    /// A bundled structure measured at `installed` (of its own channels) with its lowest
    /// `modes`, commissioned on simulated sets; the advice on the connections its tracker
    /// turned off; and those still off after commissioning again with the longest list of
    /// sensors advised added.
    struct Trial {
        model: StructureModel,
        tracker: Tracker,
        advice: Vec<Advice>,
        added: Vec<String>,
        still_off: Vec<String>,
    }

    impl Trial {
        fn run(name: &str, every: usize, modes: usize) -> Self {
            let path = format!("bundled:{name}");
            let spec = crate::io::model::load_spec(std::path::Path::new(&path)).unwrap();
            let base = Model::from_spec(&spec).unwrap();
            let with = with_candidates(Some(&spec), &base, Places::All)
                .unwrap()
                .model;
            let installed: Vec<usize> = (0..base.channels().len()).step_by(every).collect();
            let tracker = commissioned(&with, (&installed, &installed), modes);
            let off = tracker.alerts_off_sigma();
            let st = tracker.state();
            assert_eq!(st.commissioning_modes, modes);
            let rules = Detectability::of(tracker.config(), PER_DAY);
            let model: StructureModel = Arc::new((Some(spec), base));
            let measured = (&st.commissioning_channels[..], modes);
            let advice = compute(&model, &rules, &off, measured).unwrap();
            assert_eq!(measured.0.len(), installed.len());
            let mut added: Vec<String> = Vec::new();
            for s in advice.iter().filter_map(|a| a.sensors.as_ref()) {
                if s.add.len() > added.len() {
                    added.clone_from(&s.add);
                }
            }
            let mut planned = installed.clone();
            planned.extend(added.iter().map(|n| with.channel_index(n).unwrap()));
            let again = commissioned(&with, (&installed, &planned), modes);
            let params = model.1.parameters();
            let still_off: Vec<String> = again
                .alerts_off_sigma()
                .iter()
                .map(|&(l, _)| params[l].name.clone())
                .collect();
            Self {
                model,
                tracker,
                advice,
                added,
                still_off,
            }
        }
    }

    /// The tracker of model `with`, commissioned on `baseline_sets` + 2 simulated sets at
    /// `channels` with its lowest `modes` (the planner's draw, the stated noise against
    /// the RMS of each mode over the `installed` channels: a sensor added is as noisy as
    /// those there).
    fn commissioned(
        with: &Model,
        (installed, channels): (&[usize], &[usize]),
        modes: usize,
    ) -> Tracker {
        let settings = crate::settings::Settings::load(None).unwrap();
        let planner = Planner::new(with.clone(), modes, NOISE)
            .unwrap()
            .with_reference(installed);
        let modes: Vec<usize> = (0..modes).collect();
        let check = Check {
            channels,
            modes: &modes,
            sets: settings.tracker.baseline_sets as usize + 2,
            per_day: PER_DAY,
        };
        check.feed(&planner, &settings.tracker, |_| {}).unwrap()
    }

    /// The advice [`advise`] puts in the status, once its thread has finished.
    fn in_status(model: &StructureModel, tracker: &Tracker) -> Vec<Advice> {
        let shared = Shared::new("lab-frame", 8, 1 << 20, 1 << 20);
        let budget = Some(MemoryBudget::from_mib(1024));
        assert!(advise(model.clone(), tracker, shared.clone(), budget));
        for _ in 0..600 {
            let st = shared.status_reply();
            assert_eq!(st.advice_unavailable, None);
            if !st.advice.is_empty() {
                return st.advice;
            }
            std::thread::sleep(std::time::Duration::from_millis(100));
        }
        panic!("no advice in the status after a minute");
    }

    /// The lab frame measured at every fourth channel with 5 modes: the tracker turns
    /// 10 connections' alerts off. The advice names sensors for each; a tracker
    /// commissioned again with them added turns none off. The σ measured is within a
    /// factor of 2.5 of the one predicted (1.1 to 1.9 here): it is the mean of 20
    /// linearisations, each at its own set's estimate, and a connection the data do not
    /// resolve scatters far from nominal (0.3 to 3 times it), which is why the advice
    /// rescales by their ratio.
    #[test]
    fn the_advised_sensors_turn_the_lab_frames_alerts_on() {
        let t = Trial::run("lab-frame", 4, 5);
        assert!(!t.advice.is_empty(), "no connection is off");
        for a in &t.advice {
            let ratio = a.measured_std / a.predicted_std;
            assert!((1.0 / 2.5..=2.5).contains(&ratio), "{a:?}");
            assert!(a.sensors.is_some(), "no sensors: {a:?}");
        }
        assert!(
            t.still_off.is_empty(),
            "{:?} off with {:?}",
            t.still_off,
            t.added
        );
    }

    /// The daemon's route ([`advise`], on a thread of its own) puts the same advice in the
    /// status as the computation itself; under a memory budget it would not fit in, it is
    /// not started and the status says why.
    #[test]
    fn the_advice_is_in_the_status() {
        let t = Trial::run("lab-frame", 4, 5);
        assert_eq!(in_status(&t.model, &t.tracker), t.advice);
        let shared = Shared::new("lab-frame", 8, 1 << 20, 1 << 20);
        let tight = Some(MemoryBudget::from_mib(1));
        assert!(!advise(t.model.clone(), &t.tracker, shared.clone(), tight));
        let st = shared.status_reply();
        assert!(st.advice.is_empty());
        let why = st.advice_unavailable.unwrap();
        assert!(why.contains("daemon.memory_mib = 1;"), "{why}");
    }

    /// The bundled space frame with its 78 channels and 15 modes: its tracker turns 11 of
    /// the 28 connections off. The advice names 11 sensors (rotations) for all but one,
    /// which it gives 25 modes instead; with the 11 added, the tracker turns none off (the
    /// one without sensors too: the ratio it was scaled by shrinks once the data resolve
    /// the connection).
    #[test]
    fn the_advised_sensors_turn_the_space_frames_alerts_on() {
        let t = Trial::run("space-frame", 1, 15);
        assert!(t.advice.len() >= 4, "{:?}", t.advice);
        for a in &t.advice {
            assert!(a.sensors.is_some() || a.more_modes.is_some(), "{a:?}");
        }
        assert!(t.added.len() <= MAX_ADD);
        assert!(
            t.still_off.is_empty(),
            "{:?} off with {:?}",
            t.still_off,
            t.added
        );
    }
}
