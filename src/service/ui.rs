//! The web page at `/` (SPEC §5): upload, parameters, progress, downloads and a WebGL2 viewer
//! that decodes the baked layers as a game shader does.
//!
//! The page is plain HTML, ES modules and CSS, built into the binary with `include_str!` (as
//! `openapi.yaml` is), so the service still needs nothing beside itself and no build step
//! downloads anything. `--ui-dir DIR` serves the same files from disk instead, re-read on every
//! request, so the page can be worked on without rebuilding the server. `--no-ui` turns it off.
//!
//! The page learns the server's limits and whether it needs an API key from a JSON object put
//! into `index.html` when it is served (no extra route, nothing to fetch before the first paint).

// `Problem` is the error answer itself, built at most once per request (as in `handlers`).
#![allow(clippy::result_large_err)]

use crate::service::problem::Problem;
use crate::service::AppState;
use axum::extract::{Path, State};
use axum::http::{header, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};

/// The page's files: name under `/ui/`, content type, built-in contents.
pub const ASSETS: &[(&str, &str, &str)] = &[
    ("app.js", "text/javascript; charset=utf-8", include_str!("ui/app.js")),
    ("viewer.js", "text/javascript; charset=utf-8", include_str!("ui/viewer.js")),
    ("api.js", "text/javascript; charset=utf-8", include_str!("ui/api.js")),
    ("probe.js", "text/javascript; charset=utf-8", include_str!("ui/probe.js")),
    ("style.css", "text/css; charset=utf-8", include_str!("ui/style.css")),
];

/// The page itself; `__HORIZON_CONFIG__` is replaced by [`page_config`].
pub const INDEX_HTML: &str = include_str!("ui/index.html");

/// What the page needs to know about this server before its first request.
#[derive(Debug, serde::Serialize)]
pub struct PageConfig {
    pub version: &'static str,
    pub auth_required: bool,
    pub max_body_bytes: u64,
    pub max_dim: u32,
    pub max_texels: u64,
    /// The `method` values this build accepts (the form offers these).
    pub methods: Vec<&'static str>,
}

/// The configuration object `index.html` receives.
pub fn page_config(st: &AppState) -> PageConfig {
    let c = &st.0.config;
    PageConfig {
        version: env!("CARGO_PKG_VERSION"),
        auth_required: c.api_key.is_some(),
        max_body_bytes: c.max_body_bytes,
        max_dim: c.limits.max_dim,
        max_texels: c.limits.max_texels,
        methods: crate::params::METHODS.iter().map(|(name, _)| *name).collect(),
    }
}

fn disabled() -> Problem {
    Problem::new(StatusCode::NOT_FOUND, "ui_disabled", "the web page is turned off (--no-ui)")
}

/// Reads one of the page's files from `--ui-dir`, or the built-in copy.
fn contents(st: &AppState, name: &str, builtin: &'static str) -> Result<String, Problem> {
    match &st.0.config.ui_dir {
        Some(dir) => std::fs::read_to_string(dir.join(name)).map_err(|e| {
            Problem::new(
                StatusCode::NOT_FOUND,
                "ui_asset_not_found",
                format!("cannot read `{name}` from --ui-dir: {e}"),
            )
        }),
        None => Ok(builtin.to_owned()),
    }
}

fn answer(content_type: &'static str, body: String) -> Response {
    let mut r = body.into_response();
    r.headers_mut().insert(header::CONTENT_TYPE, HeaderValue::from_static(content_type));
    // The page changes with the binary (or the --ui-dir files): revalidate rather than cache.
    r.headers_mut().insert(header::CACHE_CONTROL, HeaderValue::from_static("no-cache"));
    r
}

/// `GET /`: the page, with this server's configuration in it.
pub async fn index(State(st): State<AppState>) -> Result<Response, Problem> {
    if st.0.config.no_ui {
        return Err(disabled());
    }
    let html = contents(&st, "index.html", INDEX_HTML)?;
    let config = serde_json::to_string(&page_config(&st))
        .map_err(|e| Problem::internal(&format!("page configuration: {e}")))?;
    // `</` cannot occur in this JSON (numbers, booleans and fixed names), so it cannot end the
    // <script> element it is placed in.
    Ok(answer("text/html; charset=utf-8", html.replace("__HORIZON_CONFIG__", &config)))
}

/// `GET /ui/{asset}`: a module or stylesheet of the page.
pub async fn asset(
    State(st): State<AppState>,
    Path(name): Path<String>,
) -> Result<Response, Problem> {
    if st.0.config.no_ui {
        return Err(disabled());
    }
    let Some(&(name, content_type, builtin)) = ASSETS.iter().find(|(n, _, _)| *n == name) else {
        return Err(Problem::new(
            StatusCode::NOT_FOUND,
            "ui_asset_not_found",
            "no such file of the web page",
        ));
    };
    Ok(answer(content_type, contents(&st, name, builtin)?))
}
