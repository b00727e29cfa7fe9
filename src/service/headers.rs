//! Headers every answer carries, whatever produced it (a handler, a problem, axum's own 404):
//! the security headers of a page that keeps an API key in local storage, and CORS for browser
//! clients of another origin when `--cors-origin` allows one.
//!
//! - `X-Content-Type-Options: nosniff` and `Referrer-Policy: no-referrer` on every response.
//! - `Content-Security-Policy` on every response: `default-src 'self'` (the page loads only its
//!   own modules and stylesheet, and calls only this server), `img-src 'self' blob: data:` (the
//!   viewer shows authenticated downloads through `blob:` URLs), `frame-ancestors 'none'` (no
//!   other site can frame the page to click on it). The page has no inline script, handler or
//!   style attribute for it to block. On API answers it costs nothing and covers a JSON or
//!   problem body a browser is tricked into rendering.
//! - CORS (off by default): with `--cors-origin`, answers carry `Access-Control-Allow-Origin`
//!   for that origin and preflight `OPTIONS` requests are answered here, before routing and
//!   before the API-key check (a preflight never carries credentials).

use crate::service::AppState;
use axum::extract::{Request, State};
use axum::http::{header, HeaderValue, Method, StatusCode};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};

/// The page's Content-Security-Policy.
pub const CSP: &str = "default-src 'self'; img-src 'self' blob: data:; object-src 'none'; \
                       base-uri 'none'; form-action 'self'; frame-ancestors 'none'";

/// Methods a cross-origin browser client may use.
const CORS_METHODS: &str = "GET, POST, DELETE, OPTIONS";
/// Request headers a cross-origin client may send.
const CORS_HEADERS: &str =
    "authorization, content-type, range, if-none-match, if-range, x-request-id, last-event-id";
/// Response headers a cross-origin client may read.
const CORS_EXPOSE: &str = "location, etag, retry-after, content-range, content-disposition, \
                           accept-ranges, x-request-id, x-width, x-height";

/// Middleware: security headers on every answer, CORS when configured.
pub async fn security(State(st): State<AppState>, req: Request, next: Next) -> Response {
    let cors = st.0.config.cors_origin.as_deref();
    let preflight = req.method() == Method::OPTIONS
        && req.headers().contains_key(header::ORIGIN)
        && req.headers().contains_key(header::ACCESS_CONTROL_REQUEST_METHOD);
    let mut res = match cors {
        Some(_) if preflight => {
            let mut r = StatusCode::NO_CONTENT.into_response();
            let h = r.headers_mut();
            h.insert(header::ACCESS_CONTROL_ALLOW_METHODS, HeaderValue::from_static(CORS_METHODS));
            h.insert(header::ACCESS_CONTROL_ALLOW_HEADERS, HeaderValue::from_static(CORS_HEADERS));
            h.insert(header::ACCESS_CONTROL_MAX_AGE, HeaderValue::from_static("600"));
            r
        }
        _ => next.run(req).await,
    };
    let h = res.headers_mut();
    h.insert(header::X_CONTENT_TYPE_OPTIONS, HeaderValue::from_static("nosniff"));
    h.insert(header::REFERRER_POLICY, HeaderValue::from_static("no-referrer"));
    h.insert(header::CONTENT_SECURITY_POLICY, HeaderValue::from_static(CSP));
    h.insert(header::X_FRAME_OPTIONS, HeaderValue::from_static("DENY"));
    if let Some(origin) = cors.and_then(|o| HeaderValue::from_str(o).ok()) {
        h.insert(header::ACCESS_CONTROL_ALLOW_ORIGIN, origin);
        h.insert(header::ACCESS_CONTROL_EXPOSE_HEADERS, HeaderValue::from_static(CORS_EXPOSE));
        h.append(header::VARY, HeaderValue::from_static("origin"));
    }
    res
}
