//! Operations and middleware: health, readiness, metrics, the openapi document, the fallback,
//! request-head limits, authentication and request logging.

#![allow(clippy::result_large_err)]

use super::*;

/// `GET /healthz`: the process is alive.
pub async fn healthz() -> Response {
    (StatusCode::OK, Json(Health { status: "ok" })).into_response()
}

/// `GET /readyz`: 200 while accepting work, 503 while draining.
pub async fn readyz(State(st): State<AppState>) -> Answer {
    if st.is_draining() {
        return Err(Problem::shutting_down());
    }
    // Ready means the stores answer too: with PostgreSQL away this is 503, so a load
    // balancer stops sending work here until it is back.
    let c = st.0.jobs.counts().await.map_err(store_err)?;
    // And that the blob store can write: on a full disk this is 507 until space is freed.
    let blobs = st.0.jobs.blob_store().clone();
    blocking(move || blobs.check_writable()).await?;
    let ready = Readiness {
        status: "ready",
        role: match st.0.config.role {
            crate::service::config::Role::All => "all",
            crate::service::config::Role::Api => "api",
            crate::service::config::Role::Worker => "worker",
        },
        queue_depth: c.queued,
        queue_capacity: st.0.config.queue_capacity,
        running: c.running,
        running_here: st.0.jobs.running_here(),
    };
    Ok((StatusCode::OK, Json(ready)).into_response())
}

#[derive(serde::Serialize)]
struct Health {
    status: &'static str,
}

/// `GET /readyz`'s answer.
#[derive(serde::Serialize)]
struct Readiness {
    status: &'static str,
    /// `all`, `api` or `worker` (SPEC §7).
    role: &'static str,
    /// Bakes queued, on every node.
    queue_depth: u64,
    queue_capacity: usize,
    /// Bakes running, on every node.
    running: u64,
    /// Bakes running in this process.
    running_here: usize,
}

/// `GET /metrics`: Prometheus text.
pub async fn metrics(State(st): State<AppState>) -> Answer {
    let c = st.0.jobs.counts().await.map_err(store_err)?;
    let stored: Vec<(Status, u64)> = Status::ALL.iter().map(|s| (*s, c.of(*s))).collect();
    let (waiting, running) = (c.queued as usize, c.running as usize);
    let text = st.0.metrics.render(&stored, waiting, running);
    Ok(([(header::CONTENT_TYPE, "text/plain; version=0.0.4; charset=utf-8")], text).into_response())
}

/// `GET /openapi.yaml`.
pub async fn openapi() -> Response {
    ([(header::CONTENT_TYPE, "application/yaml")], OPENAPI_YAML).into_response()
}

/// Unknown routes.
pub async fn fallback() -> Problem {
    Problem::new(StatusCode::NOT_FOUND, "route_not_found", "no such route; see /openapi.yaml")
}

// ---------------------------------------------------------------------------------------------
// Middleware

pub(super) fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

/// 414 for a request target over `max_uri_bytes`, 431 for headers over `max_header_bytes`,
/// both problem+json, before routing (so before any extractor echoes a part of them).
pub async fn head_limits(State(st): State<AppState>, req: Request, next: Next) -> Response {
    let target = req.uri().path_and_query().map_or(0, |pq| pq.as_str().len());
    if target > st.0.config.max_uri_bytes {
        return Problem::new(
            StatusCode::URI_TOO_LONG,
            "uri_too_long",
            format!(
                "the request target is {target} bytes; at most {} are accepted (max_uri_bytes)",
                st.0.config.max_uri_bytes
            ),
        )
        .into_response();
    }
    let headers: usize = req.headers().iter().map(|(k, v)| k.as_str().len() + v.len() + 4).sum();
    if headers > st.0.config.max_header_bytes {
        return Problem::new(
            StatusCode::REQUEST_HEADER_FIELDS_TOO_LARGE,
            "headers_too_large",
            format!(
                "the request headers are {headers} bytes; at most {} are accepted \
                 (max_header_bytes)",
                st.0.config.max_header_bytes
            ),
        )
        .into_response();
    }
    next.run(req).await
}

/// Bearer-token check on /v1 routes when an API key is configured.
pub async fn auth(State(st): State<AppState>, req: Request, next: Next) -> Response {
    if let Some(key) = &st.0.config.api_key {
        // RFC 9110 §11.1: the auth scheme is case-insensitive (`bearer`, `BEARER`), and the
        // credentials follow after one or more spaces.
        let ok = req
            .headers()
            .get(header::AUTHORIZATION)
            .and_then(|v| v.to_str().ok())
            .and_then(|v| v.split_once(' '))
            .filter(|(scheme, _)| scheme.eq_ignore_ascii_case("bearer"))
            .is_some_and(|(_, t)| constant_time_eq(t.trim().as_bytes(), key.as_bytes()));
        if !ok {
            return Problem::new(
                StatusCode::UNAUTHORIZED,
                "unauthorized",
                "this route needs `Authorization: Bearer <api key>`",
            )
            .into_response();
        }
    }
    next.run(req).await
}

/// The request id: the client's `X-Request-Id` when it is a short token, else a fresh one.
pub(super) fn request_id(headers: &HeaderMap) -> String {
    use std::sync::atomic::{AtomicU64, Ordering};
    static NEXT: AtomicU64 = AtomicU64::new(1);
    let given = headers.get("x-request-id").and_then(|v| v.to_str().ok()).filter(|v| {
        !v.is_empty()
            && v.len() <= 64
            && v.bytes().all(|b| b.is_ascii_alphanumeric() || b"-_.:".contains(&b))
    });
    match given {
        Some(v) => v.to_owned(),
        None => format!("{:08x}-{}", std::process::id(), NEXT.fetch_add(1, Ordering::Relaxed)),
    }
}

/// One log line per request (method, path, status, latency, request id; the path without its
/// query and capped, so a huge or secret-bearing query string never reaches the log), the
/// `X-Request-Id` answer header, and the request counters by matched route.
pub async fn track(State(st): State<AppState>, req: Request, next: Next) -> Response {
    let started = std::time::Instant::now();
    let route = req
        .extensions()
        .get::<MatchedPath>()
        .map(|m| m.as_str().to_owned())
        .unwrap_or_else(|| "unmatched".into());
    let method = req.method().clone();
    let path = crate::service::problem::cap(req.uri().path(), 200);
    let rid = request_id(req.headers());
    let mut res = next.run(req).await;
    let status = res.status().as_u16();
    tracing::info!(
        method = %method,
        path = %path,
        status,
        latency_ms = (started.elapsed().as_secs_f64() * 1e3 * 10.0).round() / 10.0,
        request_id = %rid,
        "request"
    );
    if let Ok(v) = HeaderValue::from_str(&rid) {
        res.headers_mut().insert("x-request-id", v);
    }
    let method = if [Method::GET, Method::POST, Method::DELETE, Method::HEAD].contains(&method) {
        method.as_str().to_owned()
    } else {
        "OTHER".into()
    };
    st.0.metrics.http(&route, &method, status);
    res
}
