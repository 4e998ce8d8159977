//! The structure's state as Prometheus metrics, not only the daemon's: per parameter the
//! latest θ and its σ, the drift filter's level and 95 % band, the baseline, the loss and
//! the loosening alert level; per structure the misfit ε against its bound, the
//! model-inadequacy alert level and the age of the last set received. The label sets are
//! bounded by the configuration: a structure, and a parameter of its model.

use std::sync::atomic::Ordering;

use prometheus_client::encoding::{DescriptorEncoder, EncodeMetric};
use prometheus_client::metrics::MetricType;
use prometheus_client::metrics::gauge::ConstGauge;

use super::{Shared, Status};
use crate::contract::stiffness::ParameterEstimate;
use crate::contract::{AlertKind, AlertLevel};

/// The loss of a parameter's filtered level, as a fraction: against the expectation under
/// the set's conditions when the structure is normalised, else against the baseline.
pub fn loss(p: &ParameterEstimate) -> Option<f64> {
    match &p.normalised {
        Some(n) => Some(n.loss),
        None => p.filtered.change.map(|c| -c),
    }
}

/// How a per-parameter gauge is read (`None`: not exported for that parameter).
type ParamGetter = fn(&ParameterEstimate, &Status) -> Option<f64>;

fn parameter_gauges() -> [(&'static str, &'static str, ParamGetter); 7] {
    [
        (
            "boltwatch_theta_std",
            "Standard deviation of this set's θ.",
            |p, _| p.std,
        ),
        (
            "boltwatch_theta_filtered",
            "The drift filter's level of θ.",
            |p, _| Some(p.filtered.level),
        ),
        (
            "boltwatch_theta_filtered_lower95",
            "Lower bound of the 95 % band of the filtered level.",
            |p, _| Some(p.filtered.lower95),
        ),
        (
            "boltwatch_theta_filtered_upper95",
            "Upper bound of the 95 % band of the filtered level.",
            |p, _| Some(p.filtered.upper95),
        ),
        (
            "boltwatch_theta_baseline",
            "θ at commissioning (once the baseline sets are in).",
            |p, _| p.baseline,
        ),
        (
            "boltwatch_loss",
            "Loss of the filtered level (fraction): against the expectation under the set's conditions when normalised, else against the baseline.",
            |p, _| loss(p),
        ),
        (
            "boltwatch_alert_level",
            "Loosening alert level of the parameter: 0 none or cleared, 1 warning, 2 alarm.",
            |p, st| {
                let a = st.alerts.get(&(AlertKind::Loosening, Some(p.name.clone())));
                Some(f64::from(AlertLevel::severity(a.map(|a| a.level))))
            },
        ),
    ]
}

/// Every per-parameter gauge of [`parameter_gauges`], then the per-structure ones.
pub fn encode(enc: &mut DescriptorEncoder, all: &[(&Shared, Status)]) -> std::fmt::Result {
    for (name, help, get) in parameter_gauges() {
        let mut family = enc.encode_descriptor(name, help, None, MetricType::Gauge)?;
        for (s, st) in all {
            for p in st.last_estimate.iter().flat_map(|e| &e.parameters) {
                if let Some(v) = get(p, st).filter(|v| v.is_finite()) {
                    let labels = [("structure", s.structure.as_str()), ("parameter", &p.name)];
                    ConstGauge::new(v).encode(family.encode_family(&labels)?)?;
                }
            }
        }
    }
    encode_structure(enc, all)
}

/// How a per-structure gauge is read.
type StructureGetter = fn(&Shared, &Status) -> Option<f64>;

fn structure_gauges() -> [(&'static str, &'static str, StructureGetter); 4] {
    [
        (
            "boltwatch_epsilon",
            "Misfit ε of the latest estimate.",
            |_, st| st.last_estimate.as_ref().map(|e| e.epsilon),
        ),
        (
            "boltwatch_epsilon_bound",
            "The χ² bound of ε above which the model is inadequate.",
            |_, st| st.last_estimate.as_ref().map(|e| e.epsilon_bound),
        ),
        (
            "boltwatch_model_inadequate_level",
            "Model-inadequacy alert level: 0 none or cleared, 1 warning, 2 alarm.",
            |_, st| {
                let a = st.alerts.get(&(AlertKind::ModelInadequate, None));
                Some(f64::from(AlertLevel::severity(a.map(|a| a.level))))
            },
        ),
        (
            "boltwatch_last_set_age_seconds",
            "Seconds since the last modal set was received (absent before the first).",
            |s, _| {
                let ms = s.last_received_ms.load(Ordering::Relaxed);
                let now = chrono::Utc::now().timestamp_millis() as u64;
                (ms > 0).then(|| now.saturating_sub(ms) as f64 / 1e3)
            },
        ),
    ]
}

fn encode_structure(enc: &mut DescriptorEncoder, all: &[(&Shared, Status)]) -> std::fmt::Result {
    for (name, help, get) in structure_gauges() {
        let mut family = enc.encode_descriptor(name, help, None, MetricType::Gauge)?;
        for (s, st) in all {
            if let Some(v) = get(s, st).filter(|v| v.is_finite()) {
                let labels = [("structure", s.structure.as_str())];
                ConstGauge::new(v).encode(family.encode_family(&labels)?)?;
            }
        }
    }
    Ok(())
}
