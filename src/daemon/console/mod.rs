//! The operator's console: a read-only web page served by the daemon on `[console] listen`
//! (loopback by default). `/` lists every structure the daemon watches (the age of its last
//! set, sets tracked, alerts by level; a silent one stands out); `/structure/<name>` shows
//! one: ε against its bound, its alerts, and per connection θ, σ, the filtered level with
//! its 95 % band, the baseline, the loss and the alert level, with a chart of the filtered
//! levels over a window (`?window=24h|30d|all`) read back from the daemon's own logs.
//!
//! Pages are plain HTML with the charts drawn server-side as SVG; nothing is fetched from
//! anywhere else, and every response forbids it (Content-Security-Policy).

mod pages;

use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use axum::Router;
use axum::extract::{Path, State};
use axum::http::{HeaderValue, StatusCode, Uri, header};
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

/// Serves the console on `listener` until the task is dropped.
pub async fn serve(listener: tokio::net::TcpListener, console: Arc<Console>) {
    let _ = axum::serve(listener, app(console)).await;
}

/// The console's routes, every response with the security headers.
pub fn app(console: Arc<Console>) -> Router {
    Router::new()
        .route("/", get(overview))
        .route("/structure/{name}", get(structure))
        .route("/console.css", get(css))
        .fallback(|| async { not_found("no such page") })
        .with_state(console)
        .layer(axum::middleware::map_response(secure))
}

/// No resource from anywhere but this page's origin, no framing, no referrer, no caching
/// of a page that changes with every set.
async fn secure(mut r: Response) -> Response {
    let h = r.headers_mut();
    for (name, value) in [
        (
            header::CONTENT_SECURITY_POLICY,
            "default-src 'none'; style-src 'self'; img-src 'self'; base-uri 'none'; form-action 'none'; frame-ancestors 'none'",
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

impl Console {
    /// The structure of that name among those watched now (a name is only ever compared,
    /// never used as a path).
    fn watched_structure(&self, name: &str) -> Option<Arc<super::metrics::Shared>> {
        let all = self.watched.read().ok()?;
        all.iter().find(|s| s.structure == name).cloned()
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
