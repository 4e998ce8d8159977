//! The console's pages as HTML: escaped text, tables, the chart as inline SVG.

use std::fmt::Write as _;
use std::sync::atomic::Ordering;

use super::{Console, Window, charts};
use crate::contract::stiffness::ParameterEstimate;
use crate::contract::{AlertKind, AlertLevel};
use crate::daemon::history::Logged;
use crate::daemon::metrics::state::loss;
use crate::daemon::metrics::{Shared, Status};

/// The console's style sheet (served as `/console.css`: the policy allows no inline style).
pub const CSS: &str = "body{font-family:sans-serif;margin:1.5em;color:#222}\
table{border-collapse:collapse}td,th{padding:.25em .7em;border-bottom:1px solid #ddd;text-align:right}\
td:first-child,th:first-child{text-align:left}tr.alarm td{background:#fbe3e3}\
tr.warning td{background:#fdf0dc}tr.silent td{background:#eee;color:#a00}\
.level{font-weight:bold}nav a{margin-right:1em}svg{max-width:100%;height:auto}\
svg.spark{vertical-align:middle}h2{margin-top:1.5em}\n";

/// The console's icon: a hexagonal bolt head.
pub const ICON: &str = "<svg xmlns=\"http://www.w3.org/2000/svg\" viewBox=\"0 0 32 32\">\
<polygon points=\"16,2 28,9 28,23 16,30 4,23 4,9\" fill=\"#1f77b4\"/>\
<circle cx=\"16\" cy=\"16\" r=\"6\" fill=\"#fff\"/></svg>\n";

/// The console's only script: live updates. On each event of the page's stream it fetches
/// the page again and swaps in its live part (at most one fetch at a time).
pub const JS: &str = include_str!("console.js");

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

/// A page: its live part in `<main id="live">`, which `/console.js` fetches again when
/// the stream `events` says something changed (without JavaScript the page is complete,
/// only not live).
fn page(title: &str, events: Option<&str>, body: &str) -> String {
    let live = events.map_or(String::new(), |e| format!(" data-events=\"{}\"", escape(e)));
    format!(
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">\
         <title>{} · boltwatch</title><link rel=\"stylesheet\" href=\"/console.css\">\
         <link rel=\"icon\" href=\"/favicon.svg\" type=\"image/svg+xml\">\
         <script src=\"/console.js\" defer></script></head>\
         <body{live}><main id=\"live\">{body}</main></body></html>\n",
        escape(title)
    )
}

/// A page with one message.
pub fn message(title: &str, text: &str) -> String {
    page(
        title,
        None,
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
        let h = logged(c, &s.structure).ok();
        let _ = write!(
            rows,
            "<tr class=\"{class}\" id=\"s-{name}\"><td><a href=\"/structure/{name}\">{name}</a></td>\
             <td>{}{}</td><td>{}</td><td>{}</td><td class=\"alarms\">{alarms}</td>\
             <td>{warnings}</td><td>{}</td></tr>",
            age_text(age),
            if silent { " (silent)" } else { "" },
            st.accepted,
            h.as_ref().map_or("–".into(), |h| per_hour(h).to_string()),
            most_changed(h.as_ref(), &st),
        );
    }
    page(
        "Structures",
        Some("/events"),
        &format!(
            "<h1>Structures</h1><table><thead><tr><th>structure</th><th>last set</th>\
             <th>sets tracked</th><th>sets in the last hour</th><th>alarms</th>\
             <th>warnings</th><th>most changed connection, last 24 h</th></tr></thead>\
             <tbody>{rows}</tbody></table>"
        ),
    )
}

/// The structure's logged history (empty when it cannot be read: the page says so where
/// it draws from it).
fn logged(c: &Console, structure: &str) -> Result<Logged, String> {
    let mut cache = c
        .cache
        .lock()
        .map_err(|_| "the history cache failed".to_string())?;
    cache
        .history(&c.log_dir, structure)
        .map_err(|e| format!("the history cannot be read from the logs: {e:#}"))
}

/// The number of sets logged over the last hour.
fn per_hour(h: &Logged) -> usize {
    let now = chrono::Utc::now().timestamp_millis();
    h.samples()
        .rev()
        .take_while(|x| x.time_ms >= now - 3_600_000)
        .count()
}

/// The connection whose filtered level lost most (or, before a baseline, moved most) in
/// the last estimate, with a sparkline of that level over the last 24 h.
fn most_changed(h: Option<&Logged>, st: &Status) -> String {
    let Some(e) = &st.last_estimate else {
        return "–".into();
    };
    let size = |p: &ParameterEstimate| loss(p).map_or(0.0, f64::abs);
    let Some((l, p)) = e
        .parameters
        .iter()
        .enumerate()
        .max_by(|a, b| size(a.1).total_cmp(&size(b.1)))
    else {
        return "–".into();
    };
    let Some(h) = h else {
        return escape(&p.name);
    };
    let last = h.samples().next_back().map_or(0, |x| x.time_ms);
    let day = h.samples_since(Some(last - 86_400_000));
    let keep = charts::envelope(&day, |x| x.points[l].level, 120);
    let values: Vec<f32> = keep.iter().map(|&i| day[i].points[l].level).collect();
    let title = format!("{}: filtered θ over the last 24 h", p.name);
    format!(
        "{} {} {}",
        escape(&p.name),
        charts::sparkline(&values, 120.0, 24.0, &title),
        loss(p).map_or(String::new(), |x| format!("{:.1} %", 100.0 * x))
    )
}

/// `/structure/<name>`: the structure's state, its connections, its charts over `window`,
/// its drawing, frequencies and last cross-check.
pub fn structure(c: &Console, s: &Shared, window: Window) -> String {
    let st = s.status();
    let name = escape(&s.structure);
    let mut body = format!(
        "<nav><a href=\"/\">all structures</a><a href=\"?window=24h\">24 h</a>\
         <a href=\"?window=30d\">30 days</a><a href=\"?window=all\">all</a></nav><h1>{name}</h1>"
    );
    body.push_str(&summary(s, &st));
    body.push_str(&connection_table(&st));
    body.push_str(&advice(&st));
    let h = logged(c, &s.structure);
    let order = st.last_estimate.as_ref().map_or(Vec::new(), |e| {
        let names: Vec<String> = e.parameters.iter().map(|p| p.name.clone()).collect();
        by_level(&st, &names)
    });
    match &h {
        Ok(h) if h.samples().next().is_some() => {
            let last = h.samples().next_back().map_or(0, |x| x.time_ms);
            let samples = h.samples_since(window.millis().map(|ms| last - ms));
            let order: Vec<usize> = order.into_iter().filter(|&l| l < h.names().len()).collect();
            body.push_str("<h2>Filtered stiffness</h2>");
            body.push_str(&charts::levels(&s.structure, h, &samples, &order));
            body.push_str(&drawing(s, &st));
            body.push_str(&frequencies(&st));
            body.push_str("<h2>Misfit</h2>");
            body.push_str(&charts::epsilon(&s.structure, &samples));
        }
        Ok(_) => body.push_str("<p>nothing logged yet</p>"),
        Err(e) => {
            let _ = write!(body, "<p>{}</p>", escape(e));
        }
    }
    body.push_str(&crosscheck(&st));
    let events = format!("/structure/{}/events", s.structure);
    page(&s.structure, Some(&events), &body)
}

/// The line above the table: last set, sets tracked, ε against its bound, the model's
/// adequacy.
fn summary(s: &Shared, st: &Status) -> String {
    let inadequate = st.alerts.get(&(AlertKind::ModelInadequate, None));
    let mut out = format!(
        "<p>last set {}; <span id=\"sets\">{}</span> sets tracked",
        age_text(last_set_age(s)),
        st.accepted
    );
    if let Some(e) = &st.last_estimate {
        let _ = write!(
            out,
            "; misfit ε {:.3} against its bound {:.3}{}",
            e.epsilon,
            e.epsilon_bound,
            match inadequate.map(|a| a.level) {
                Some(l @ (AlertLevel::Warning | AlertLevel::Alarm)) =>
                    format!(": model inadequate ({})", l.as_str()),
                _ => String::new(),
            }
        );
    }
    out.push_str("</p>");
    out
}

/// The structure drawn with each connection coloured by its change (frame models only).
fn drawing(s: &Shared, st: &Status) -> String {
    let (Some(sm), Some(e)) = (s.model.get(), &st.last_estimate) else {
        return String::new();
    };
    let Some(g) = sm.0.as_ref().and_then(crate::draw::Geometry::of) else {
        return String::new();
    };
    format!(
        "<h2>The structure</h2>{}",
        crate::draw::estimate_svg(&g, &sm.1, e, 720.0, 560.0)
    )
}

/// Measured against model frequencies of the last estimate, with their MAC.
fn frequencies(st: &Status) -> String {
    let Some(e) = &st.last_estimate else {
        return String::new();
    };
    let mut rows = String::new();
    for (k, m) in e.modes.iter().enumerate() {
        let _ = write!(
            rows,
            "<tr><td>{}</td><td>{:.3}</td><td>{:.3}</td><td>{:+.2}</td><td>{}</td><td>{}</td></tr>",
            k + 1,
            m.measured_hz,
            m.model_hz,
            100.0 * (m.model_hz - m.measured_hz) / m.measured_hz,
            m.mac.map_or("–".into(), |v| format!("{v:.3}")),
            m.paired_with,
        );
    }
    format!(
        "<h2>Frequencies</h2><table><thead><tr><th>mode</th><th>measured, Hz</th>\
         <th>model, Hz</th><th>model − measured, %</th><th>MAC</th><th>model mode</th>\
         </tr></thead><tbody>{rows}</tbody></table>"
    )
}

/// What would turn on the alerts commissioning left off ([`crate::daemon::advice`]);
/// nothing when every connection's alerts are on.
fn advice(st: &Status) -> String {
    if let Some(why) = &st.advice_unavailable {
        return format!("<h2>Alerts off</h2><p>no advice: {}</p>", escape(why));
    }
    if st.advice.is_empty() {
        return String::new();
    }
    let mut items = String::new();
    for a in &st.advice {
        let _ = write!(
            items,
            "<li><b>{}</b>: {}</li>",
            escape(&a.connection),
            escape(&a.summary)
        );
    }
    format!("<h2>Alerts off</h2><ul>{items}</ul>")
}

/// The last cross-check of mode matching against the Bayesian MAP.
fn crosscheck(st: &Status) -> String {
    let Some(x) = &st.last_crosscheck else {
        return format!(
            "<h2>Cross-check</h2><p>none yet{}</p>",
            st.crosscheck_unavailable
                .as_ref()
                .map_or(String::new(), |w| format!(" ({})", escape(w)))
        );
    };
    let verdict = match (&x.error, x.disagree.is_empty()) {
        (Some(e), _) => format!("failed: {}", escape(e)),
        (None, true) => "the two methods agree".into(),
        (None, false) => format!("they disagree on {}", escape(&x.disagree.join(", "))),
    };
    format!(
        "<h2>Cross-check</h2><p>{}: mode matching against the Bayesian MAP (σ_c {}): \
         {verdict}; largest z {}</p>",
        x.time.format("%Y-%m-%d %H:%M:%S UTC"),
        x.sigma_c,
        x.max_z.map_or("–".into(), |z| format!("{z:.2}"))
    )
}

/// The connections' order on a page: in alarm, in warning, then the model's order.
fn by_level(st: &Status, names: &[String]) -> Vec<usize> {
    let level = |n: &String| {
        let a = st.alerts.get(&(AlertKind::Loosening, Some(n.clone())));
        AlertLevel::severity(a.map(|a| a.level))
    };
    let mut order: Vec<usize> = (0..names.len()).collect();
    order.sort_by_key(|&i| (std::cmp::Reverse(level(&names[i])), i));
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
