//! The console's pages as HTML: escaped text, tables, the chart as inline SVG.

use std::fmt::Write as _;
use std::sync::atomic::Ordering;

use super::{Console, Window};
use crate::contract::{AlertKind, AlertLevel};
use crate::daemon::history::History;
use crate::daemon::metrics::state::{level_value, loss};
use crate::daemon::metrics::{Shared, Status};
use crate::plot::{Band, Legend, Panel, Scale, Series, figure_svg_with};

/// The console's style sheet (served as `/console.css`: the policy allows no inline style).
pub const CSS: &str = "body{font-family:sans-serif;margin:1.5em;color:#222}\
table{border-collapse:collapse}td,th{padding:.25em .7em;border-bottom:1px solid #ddd;text-align:right}\
td:first-child,th:first-child{text-align:left}tr.alarm td{background:#fbe3e3}\
tr.warning td{background:#fdf0dc}tr.silent td{background:#eee;color:#a00}\
.level{font-weight:bold}nav a{margin-right:1em}svg{max-width:100%;height:auto}\n";

/// Text made safe for HTML.
pub fn escape(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    for c in s.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&#39;"),
            c => out.push(c),
        }
    }
    out
}

fn page(title: &str, body: &str) -> String {
    format!(
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">\
         <title>{} · boltwatch</title><link rel=\"stylesheet\" href=\"/console.css\"></head>\
         <body>{body}</body></html>\n",
        escape(title)
    )
}

/// A page with one message.
pub fn message(title: &str, text: &str) -> String {
    page(
        title,
        &format!("<h1>{}</h1><p>{}</p>", escape(title), escape(text)),
    )
}

/// Seconds since the structure's last set (`None`: none yet).
fn last_set_age(s: &Shared) -> Option<f64> {
    let ms = s.last_received_ms.load(Ordering::Relaxed);
    let now = chrono::Utc::now().timestamp_millis().max(0) as u64;
    (ms > 0).then(|| now.saturating_sub(ms) as f64 / 1e3)
}

fn age_text(age: Option<f64>) -> String {
    match age {
        None => "no set yet".into(),
        Some(a) if a < 120.0 => format!("{a:.0} s ago"),
        Some(a) if a < 7200.0 => format!("{:.0} min ago", a / 60.0),
        Some(a) => format!("{:.1} h ago", a / 3600.0),
    }
}

/// The number of active (not cleared) alerts of `level`.
fn count(st: &Status, level: AlertLevel) -> usize {
    st.alerts.values().filter(|a| a.level == level).count()
}

/// `/`: every structure watched, a row each.
pub fn overview(c: &Console) -> String {
    let all: Vec<_> = c.watched.read().map(|v| v.clone()).unwrap_or_default();
    let mut rows = String::new();
    for s in &all {
        let st = s.status();
        let age = last_set_age(s);
        let silent = age.is_none_or(|a| a > c.silent_after.as_secs_f64());
        let (alarms, warnings) = (
            count(&st, AlertLevel::Alarm),
            count(&st, AlertLevel::Warning),
        );
        let class = match () {
            _ if silent => "silent",
            _ if alarms > 0 => "alarm",
            _ if warnings > 0 => "warning",
            _ => "ok",
        };
        let name = escape(&s.structure);
        let _ = write!(
            rows,
            "<tr class=\"{class}\"><td><a href=\"/structure/{name}\">{name}</a></td><td>{}{}</td>\
             <td>{}</td><td>{alarms}</td><td>{warnings}</td></tr>",
            age_text(age),
            if silent { " (silent)" } else { "" },
            st.accepted
        );
    }
    page(
        "Structures",
        &format!(
            "<h1>Structures</h1><table><thead><tr><th>structure</th><th>last set</th>\
             <th>sets tracked</th><th>alarms</th><th>warnings</th></tr></thead>\
             <tbody>{rows}</tbody></table>"
        ),
    )
}

/// `/structure/<name>`: the structure's state and its chart over `window`.
pub fn structure(c: &Console, s: &Shared, window: Window) -> String {
    let st = s.status();
    let name = escape(&s.structure);
    let mut body = format!(
        "<nav><a href=\"/\">all structures</a><a href=\"?window=24h\">24 h</a>\
         <a href=\"?window=30d\">30 days</a><a href=\"?window=all\">all</a></nav><h1>{name}</h1>"
    );
    let inadequate = st.alerts.get(&(AlertKind::ModelInadequate, None));
    if let Some(e) = &st.last_estimate {
        let _ = write!(
            body,
            "<p>last set {}; misfit ε {:.3} against its bound {:.3}{}</p>",
            age_text(last_set_age(s)),
            e.epsilon,
            e.epsilon_bound,
            match inadequate.map(|a| a.level) {
                Some(l @ (AlertLevel::Warning | AlertLevel::Alarm)) =>
                    format!(": model inadequate ({})", l.as_str()),
                _ => String::new(),
            }
        );
    }
    body.push_str(&connection_table(&st));
    let history = c
        .cache
        .lock()
        .map_err(|_| ())
        .and_then(|mut cache| cache.history(&c.log_dir, &s.structure).map_err(|_| ()));
    match history {
        Ok(h) => body.push_str(&chart(&s.structure, h, window, &st)),
        Err(()) => body.push_str("<p>the history cannot be read from the logs</p>"),
    }
    page(&s.structure, &body)
}

/// The connections' order on a page: in alarm, in warning, then the model's order.
fn by_level(st: &Status, names: &[String]) -> Vec<usize> {
    let level = |n: &String| {
        let a = st.alerts.get(&(AlertKind::Loosening, Some(n.clone())));
        level_value(a.map(|a| a.level))
    };
    let mut order: Vec<usize> = (0..names.len()).collect();
    order.sort_by_key(|&i| (-level(&names[i]), i));
    order
}

/// Per connection of the last estimate: level, θ, σ, filtered level and band, baseline,
/// loss.
fn connection_table(st: &Status) -> String {
    let Some(e) = &st.last_estimate else {
        return "<p>no estimate yet</p>".into();
    };
    let names: Vec<String> = e.parameters.iter().map(|p| p.name.clone()).collect();
    let num = |v: Option<f64>, d: usize| v.map_or("–".into(), |v| format!("{v:.d$}"));
    let mut rows = String::new();
    for i in by_level(st, &names) {
        let p = &e.parameters[i];
        let a = st.alerts.get(&(AlertKind::Loosening, Some(p.name.clone())));
        let level = a.map_or("ok", |a| a.level.as_str());
        let class = if level == "cleared" { "ok" } else { level };
        let _ = write!(
            rows,
            "<tr class=\"{class}\" id=\"c-{n}\"><td>{n}</td><td class=\"level\">{level}</td>\
             <td>{}</td><td>{}</td><td>{}</td><td>{} … {}</td><td>{}</td><td>{}</td></tr>",
            num(Some(p.theta), 3),
            num(p.std, 3),
            num(Some(p.filtered.level), 3),
            num(Some(p.filtered.lower95), 3),
            num(Some(p.filtered.upper95), 3),
            num(p.baseline, 3),
            num(loss(p).map(|l| 100.0 * l), 1),
            n = escape(&p.name),
        );
    }
    format!(
        "<table><thead><tr><th>connection</th><th>alert</th><th>θ</th><th>σ</th>\
         <th>filtered</th><th>95 % band</th><th>baseline</th><th>loss, %</th></tr></thead>\
         <tbody>{rows}</tbody></table>"
    )
}

/// The filtered level of every parameter over `window`, with its band, the baseline and
/// the alerts, connections in alarm first; one legend.
fn chart(structure: &str, h: History, window: Window, st: &Status) -> String {
    let Some(last) = h.samples.last().map(|s| s.time_ms) else {
        return "<p>nothing logged yet</p>".into();
    };
    let h = match window.millis() {
        Some(ms) => h.since(last - ms),
        None => h,
    };
    let day0 = h.samples.first().map_or(last, |s| s.time_ms);
    let days = |t: i64| (t - day0) as f64 / 86_400_000.0;
    let x: Vec<f64> = h.samples.iter().map(|s| days(s.time_ms)).collect();
    let mut panels = Vec::new();
    for l in by_level(st, &h.names) {
        let name = &h.names[l];
        let col = |f: fn(&crate::daemon::history::Point) -> f32| -> Vec<f64> {
            h.samples
                .iter()
                .map(|s| f64::from(f(&s.points[l])))
                .collect()
        };
        let mut p = Panel::new(
            &format!("{structure}: {name}"),
            "time, days",
            "θ, stiffness / nominal",
            Scale::Linear,
            Scale::Linear,
        );
        p.bands.push(Band {
            label: "95 % band of the filtered level".into(),
            x: x.clone(),
            lower: col(|p| p.lower95),
            upper: col(|p| p.upper95),
        });
        p.series
            .push(Series::trace("filtered", x.clone(), col(|p| p.level)).with_color("#1f77b4"));
        if let Some(b) = h
            .samples
            .last()
            .map(|s| s.points[l].baseline)
            .filter(|b| b.is_finite())
        {
            p.hlines.push((f64::from(b), "baseline".into()));
        }
        p.series.extend(marks(&h, name, &days, l));
        panels.push(p);
    }
    figure_svg_with(&panels, 3, Legend::Once)
}

/// The alerts of connection `name` as points at the filtered level of the nearest sample.
fn marks(h: &History, name: &str, days: &dyn Fn(i64) -> f64, l: usize) -> Vec<Series> {
    [
        ("warning", "#ff7f0e"),
        ("alarm", "#d62728"),
        ("cleared", "#2ca02c"),
    ]
    .into_iter()
    .filter_map(|(level, color)| {
        let at: Vec<(f64, f64)> = h
            .marks
            .iter()
            .filter(|m| m.connection.as_deref() == Some(name) && m.level.as_str() == level)
            .filter_map(|m| {
                let i = h.samples.partition_point(|s| s.time_ms < m.time_ms);
                let s = h.samples.get(i.min(h.samples.len().checked_sub(1)?))?;
                Some((days(m.time_ms), f64::from(s.points[l].level)))
            })
            .collect();
        (!at.is_empty()).then(|| {
            let (x, y) = at.into_iter().unzip();
            Series::points(level, x, y).with_color(color)
        })
    })
    .collect()
}

#[cfg(test)]
mod tests {
    use super::escape;

    #[test]
    fn text_is_escaped() {
        assert_eq!(
            escape("<a href=\"x\">'&'</a>"),
            "&lt;a href=&quot;x&quot;&gt;&#39;&amp;&#39;&lt;/a&gt;"
        );
    }
}
