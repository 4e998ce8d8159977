//! The operator's console: a read-only web page served by the daemon on `[console] listen`
//! (loopback by default). `/` lists every structure the daemon watches (the age of its last
//! set, sets tracked, alerts by level; a silent one stands out); `/structure/<name>` shows
//! one: ε against its bound, its alerts, and per connection θ, σ, the filtered level with
//! its 95 % band, the baseline, the loss and the alert level, with a chart of the filtered
//! levels over a window (`?window=24h|30d|all`) read back from the daemon's own logs.
//!
//! Pages are plain HTML with the charts drawn server-side as SVG; nothing is fetched from
//! anywhere else, and every response forbids it (Content-Security-Policy). The one script,
//! `/console.js`, keeps a page live: it listens to the page's server-sent events
//! (`/events`, `/structure/<name>/events`) and fetches the page again when they say
//! something changed.

mod access;
mod charts;
mod pages;

use std::convert::Infallible;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use axum::Router;
use axum::extract::{Path, State};
use axum::http::{HeaderValue, StatusCode, Uri, header};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{Html, IntoResponse, Response};
use axum::routing::get;

use super::history::Cache;
use super::metrics::Watched;
use crate::settings::ConsoleSettings;

/// What the pages read: the structures watched now, their logs, the history cache.
pub struct Console {
    watched: Watched,
    log_dir: PathBuf,
    silent_after: Duration,
    cache: Mutex<Cache>,
}

impl Console {
    pub fn new(settings: &ConsoleSettings, watched: Watched, log_dir: PathBuf) -> Arc<Self> {
        Arc::new(Self {
            watched,
            log_dir,
            silent_after: Duration::from_secs_f64(settings.silent_after_s),
            cache: Mutex::new(Cache::new((settings.cache_mib as usize) << 20)),
        })
    }
}

/// The time window of a structure page's chart.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Window {
    Day,
    Month,
    All,
}

impl Window {
    /// The window a query string asks for: none, or exactly `window=24h|30d|all`.
    pub fn from_query(query: Option<&str>) -> Option<Self> {
        match query {
            None | Some("") | Some("window=30d") => Some(Self::Month),
            Some("window=24h") => Some(Self::Day),
            Some("window=all") => Some(Self::All),
            Some(_) => None,
        }
    }

    /// Its length in ms (`None`: everything).
    pub fn millis(self) -> Option<i64> {
        match self {
            Self::Day => Some(86_400_000),
            Self::Month => Some(30 * 86_400_000),
            Self::All => None,
        }
    }
}

/// How the console is reached: over TLS or not, by the users of a password file or anyone.
pub struct Access {
    tls: Option<axum_server::tls_rustls::RustlsConfig>,
    users: Option<Arc<access::Users>>,
}

impl Access {
    /// From `[console]`: the certificate and key must load, and the password file.
    pub fn of(settings: &ConsoleSettings) -> anyhow::Result<Self> {
        let tls = if settings.tls_cert.as_os_str().is_empty() {
            None
        } else {
            Some(access::tls_config(&settings.tls_cert, &settings.tls_key)?)
        };
        let users = if settings.users_file.as_os_str().is_empty() {
            None
        } else {
            Some(Arc::new(access::Users::load(&settings.users_file)?))
        };
        Ok(Self { tls, users })
    }

    /// "https" or "http".
    pub fn scheme(&self) -> &'static str {
        if self.tls.is_some() { "https" } else { "http" }
    }
}

/// Serves the console on `listener` until the task is dropped.
pub async fn serve(listener: tokio::net::TcpListener, console: Arc<Console>, access: Access) {
    let app = app(console, access.users);
    let Some(tls) = access.tls else {
        let _ = axum::serve(listener, app).await;
        return;
    };
    let served = listener
        .into_std()
        .and_then(|l| axum_server::tls_rustls::from_tcp_rustls(l, tls));
    match served {
        Ok(server) => {
            let _ = server.serve(app.into_make_service()).await;
        }
        Err(e) => tracing::error!("console: cannot serve HTTPS: {e}"),
    }
}

/// The console's routes, every response with the security headers, every request
/// authenticated when `users` is set.
pub fn app(console: Arc<Console>, users: Option<Arc<access::Users>>) -> Router {
    Router::new()
        .route("/", get(overview))
        .route("/structure/{name}", get(structure))
        .route("/events", get(overview_events))
        .route("/structure/{name}/events", get(structure_events))
        .route("/console.css", get(css))
        .route("/console.js", get(js))
        .route("/favicon.svg", get(icon))
        .fallback(|| async { not_found("no such page") })
        .with_state(console)
        .layer(axum::middleware::from_fn_with_state(users, access::require))
        .layer(axum::middleware::map_response(secure))
}

/// No resource from anywhere but this page's origin, no framing, no referrer, no caching
/// of a page that changes with every set.
async fn secure(mut r: Response) -> Response {
    let h = r.headers_mut();
    for (name, value) in [
        (
            header::CONTENT_SECURITY_POLICY,
            "default-src 'none'; style-src 'self'; script-src 'self'; connect-src 'self'; img-src 'self'; base-uri 'none'; form-action 'none'; frame-ancestors 'none'",
        ),
        (header::X_CONTENT_TYPE_OPTIONS, "nosniff"),
        (header::REFERRER_POLICY, "no-referrer"),
        (header::X_FRAME_OPTIONS, "DENY"),
        (header::CACHE_CONTROL, "no-store"),
        (header::CONNECTION, "close"),
    ] {
        h.insert(name, HeaderValue::from_static(value));
    }
    r
}

fn not_found(what: &str) -> Response {
    (
        StatusCode::NOT_FOUND,
        Html(pages::message("Not found", what)),
    )
        .into_response()
}

async fn overview(State(c): State<Arc<Console>>) -> Response {
    Html(pages::overview(&c)).into_response()
}

async fn structure(State(c): State<Arc<Console>>, Path(name): Path<String>, uri: Uri) -> Response {
    let Some(window) = Window::from_query(uri.query()) else {
        return (
            StatusCode::BAD_REQUEST,
            Html(pages::message(
                "Bad request",
                "the only query is window=24h, window=30d or window=all",
            )),
        )
            .into_response();
    };
    let Some(shared) = c.watched_structure(&name) else {
        return not_found("this daemon does not watch that structure");
    };
    let page = tokio::task::spawn_blocking(move || pages::structure(&c, &shared, window)).await;
    match page {
        Ok(html) => Html(html).into_response(),
        Err(e) => (
            StatusCode::INTERNAL_SERVER_ERROR,
            Html(pages::message(
                "Error",
                &format!("drawing the page failed: {e}"),
            )),
        )
            .into_response(),
    }
}

async fn css() -> Response {
    (
        [(header::CONTENT_TYPE, "text/css; charset=utf-8")],
        pages::CSS,
    )
        .into_response()
}

async fn icon() -> Response {
    ([(header::CONTENT_TYPE, "image/svg+xml")], pages::ICON).into_response()
}

async fn js() -> Response {
    (
        [(header::CONTENT_TYPE, "text/javascript; charset=utf-8")],
        pages::JS,
    )
        .into_response()
}

/// The least time between two events of one stream: a page is fetched again on each.
const EVENT_GAP: Duration = Duration::from_secs(1);

/// `/structure/<name>/events`: an event (the number of outputs so far) whenever the
/// structure published something, at most one per [`EVENT_GAP`]; the stream ends when
/// the daemon stops watching the structure.
async fn structure_events(State(c): State<Arc<Console>>, Path(name): Path<String>) -> Response {
    let Some(shared) = c.watched_structure(&name) else {
        return not_found("this daemon does not watch that structure");
    };
    let rx = shared.changed.subscribe();
    drop(shared);
    let stream = futures_util::stream::unfold((rx, false), |(mut rx, waited)| async move {
        if waited {
            tokio::time::sleep(EVENT_GAP).await;
        }
        rx.changed().await.ok()?;
        let n = *rx.borrow_and_update();
        Some((
            Ok::<_, Infallible>(Event::default().data(n.to_string())),
            (rx, true),
        ))
    });
    Sse::new(stream)
        .keep_alive(KeepAlive::default())
        .into_response()
}

/// `/events`: an event whenever any structure published something or the structures
/// watched changed, looked at every [`EVENT_GAP`].
async fn overview_events(State(c): State<Arc<Console>>) -> Response {
    let first = c.outputs_so_far();
    let stream = futures_util::stream::unfold((c, first), |(c, mut seen)| async move {
        loop {
            tokio::time::sleep(EVENT_GAP).await;
            let now = c.outputs_so_far();
            if now != seen {
                seen = now;
                let n: u64 = seen.iter().map(|(_, n)| n).sum();
                let event = Event::default().data(n.to_string());
                return Some((Ok::<_, Infallible>(event), (c, seen)));
            }
        }
    });
    Sse::new(stream)
        .keep_alive(KeepAlive::default())
        .into_response()
}

impl Console {
    /// The structure of that name among those watched now (a name is only ever compared,
    /// never used as a path).
    fn watched_structure(&self, name: &str) -> Option<Arc<super::metrics::Shared>> {
        let all = self.watched.read().ok()?;
        all.iter().find(|s| s.structure == name).cloned()
    }

    /// The page of structure `name` over `window` (`None`: not watched), as
    /// `/structure/<name>` serves it.
    pub fn structure_page(&self, name: &str, window: Window) -> Option<String> {
        let shared = self.watched_structure(name)?;
        Some(pages::structure(self, &shared, window))
    }

    /// The bytes the history cache holds now.
    pub fn cache_bytes(&self) -> usize {
        self.cache.lock().map_or(0, |c| c.bytes())
    }

    /// Each structure watched with the number of outputs it has published.
    fn outputs_so_far(&self) -> Vec<(String, u64)> {
        let all = self.watched.read().map(|v| v.clone()).unwrap_or_default();
        all.iter()
            .map(|s| (s.structure.clone(), *s.changed.borrow()))
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::Window;

    #[test]
    fn only_the_three_windows_are_accepted() {
        assert_eq!(Window::from_query(None), Some(Window::Month));
        assert_eq!(Window::from_query(Some("window=24h")), Some(Window::Day));
        assert_eq!(Window::from_query(Some("window=all")), Some(Window::All));
        for bad in ["window=1y", "window=24h&x=1", "x", "window=24h%00"] {
            assert_eq!(Window::from_query(Some(bad)), None, "{bad}");
        }
    }
}
