//! plan.svg: the structure with the planned channels and each connection coloured by
//! what its warning catches.

use std::collections::BTreeMap;

use serde_json::Value;

use crate::core::model::spec::ModelSpec;
use crate::core::plan::Planner;

/// The structure with the planned channels (added ones crossed) and each connection
/// coloured by the loss its warning catches: green when watchable, orange when alerts stay
/// on but the target is missed, red when alerts are off.
pub(super) fn drawing(
    spec: &ModelSpec,
    planner: &Planner,
    doc: &Value,
    planned: &[usize],
    current: &[usize],
) -> Option<String> {
    use crate::draw::{Canvas, Geometry};
    let mut g = Geometry::of(spec)?;
    let names = |cs: &[usize]| -> Vec<String> {
        cs.iter()
            .map(|&c| planner.model().channels()[c].name.clone())
            .collect()
    };
    let (planned, current) = (names(planned), names(current));
    g.channels.retain(|(n, _)| planned.contains(n));
    let rows: BTreeMap<String, Value> = doc["planned"]["connections"]
        .as_array()?
        .iter()
        .filter_map(|r| Some((r["name"].as_str()?.to_string(), r.clone())))
        .collect();
    let title = format!(
        "{}: planned channels (+ added) and what each connection's warning catches",
        planner.model().name
    );
    let mut c = Canvas::new(&g, 760.0, 640.0, &title);
    for (n, p) in &g.channels {
        if !current.contains(n) {
            c.cross(*p, "#d62728", n);
        }
    }
    c.connections(|mark| {
        let params = crate::commands::diagnose::parameters_of(planner.model(), &mark.model_names);
        let worst = params
            .iter()
            .filter_map(|&l| rows.get(&planner.model().parameters()[l].name))
            .max_by(|a, b| detect(a).total_cmp(&detect(b)))?;
        let color = match (worst["alerts_off"] == true, worst["watchable"] == true) {
            (true, _) => "#d62728",
            (false, true) => "#2ca02c",
            (false, false) => "#ff7f0e",
        };
        Some((
            color.to_string(),
            format!(": warning at {:.0} % loss", 100.0 * detect(worst)),
        ))
    });
    c.text(
        10.0,
        38.0,
        "green: watchable at the target loss; orange: alerts on, target missed; red: alerts off",
    );
    Some(c.finish())
}

/// The loss a row's warning catches (infinite when unknown).
fn detect(row: &Value) -> f64 {
    row["detectable_warning"].as_f64().unwrap_or(f64::INFINITY)
}
