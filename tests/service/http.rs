//! HTTP details of every answer: security headers and CORS, the API key's spelling, request
//! target and header limits as problem+json, request ids, cache headers of previews and cube maps
//! and SSE ids. Regression tests from tests/edges.rs (issue 25's sharp edges) and
//! tests/service_defects.rs (issue 14's service defects), each written to fail before its fix.

use crate::support::*;
use axum::body::Body;
use axum::http::Request;
use horizon_bake::service::{self, Config, ServeArgs};
use serde_json::Value;
use std::time::Duration;

fn get(path: &str) -> axum::http::Request<axum::body::Body> {
    axum::http::Request::get(path).body(axum::body::Body::empty()).unwrap()
}

/// Every answer carries nosniff and no-referrer; the page a CSP that forbids framing and
/// anything not from this server, and the page has nothing inline for it to block. CORS is off
/// unless `--cors-origin` names an origin.
#[tokio::test]
async fn security_headers_and_cors() {
    let (st, _dir) = idle_state(|_| {});
    let app = horizon_bake::service::app(st);
    for path in ["/", "/healthz", "/v1/bakes", "/v1/bakes/nope", "/no/such/route", "/ui/app.js"] {
        let (_, h, _) = oneshot_with_headers(&app, get(path)).await;
        assert_eq!(h["x-content-type-options"], "nosniff", "{path}");
        assert_eq!(h["referrer-policy"], "no-referrer", "{path}");
        assert!(h.get("access-control-allow-origin").is_none(), "{path}");
    }
    let (s, h, _) = oneshot_with_headers(&app, get("/")).await;
    assert_eq!(s, 200);
    let csp = h["content-security-policy"].to_str().unwrap();
    assert!(csp.contains("default-src 'self'") && csp.contains("frame-ancestors 'none'"), "{csp}");
    assert!(!csp.contains("unsafe-inline") && !csp.contains("unsafe-eval"), "{csp}");

    // Nothing inline: scripts only by src (a JSON data block is not script), no handler or
    // style attributes, no `javascript:` URLs; the modules build no HTML with them either.
    let html = horizon_bake::service::ui::INDEX_HTML;
    let lower = html.to_ascii_lowercase();
    for (i, _) in lower.match_indices("<script") {
        let tag = &lower[i..i + lower[i..].find('>').unwrap()];
        assert!(tag.contains(" src=") || tag.contains("application/json"), "inline script: {tag}");
    }
    let attr = |text: &str, what: &str| {
        let b = text.as_bytes();
        text.match_indices(what).any(|(i, _)| i > 0 && b[i - 1].is_ascii_whitespace())
    };
    for bad in ["style=", "javascript:"] {
        assert!(!lower.contains(bad) || !attr(&lower, bad), "index.html has `{bad}`");
    }
    for ev in ["onclick=", "onload=", "onchange=", "oninput=", "onsubmit=", "onerror="] {
        assert!(!attr(&lower, ev), "index.html has an inline handler `{ev}`");
    }
    for (name, _, js) in horizon_bake::service::ui::ASSETS {
        for bad in
            ["innerHTML", "eval(", "new Function", "setAttribute('style'", "'style':", "style: '"]
        {
            assert!(!js.contains(bad), "{name} uses `{bad}`, which the CSP blocks or invites");
        }
    }

    let (st, _dir) = idle_state(|c| c.cors_origin = Some("https://tools.example".into()));
    let app = horizon_bake::service::app(st);
    let pre = axum::http::Request::builder()
        .method("OPTIONS")
        .uri("/v1/bakes")
        .header("origin", "https://tools.example")
        .header("access-control-request-method", "POST")
        .header("access-control-request-headers", "authorization, content-type")
        .body(axum::body::Body::empty())
        .unwrap();
    let (s, h, _) = oneshot_with_headers(&app, pre).await;
    assert_eq!(s, 204);
    assert_eq!(h["access-control-allow-origin"], "https://tools.example");
    assert!(h["access-control-allow-methods"].to_str().unwrap().contains("POST"));
    assert!(h["access-control-allow-headers"].to_str().unwrap().contains("authorization"));
    let (s, h, _) = oneshot_with_headers(&app, get("/v1/bakes")).await;
    assert_eq!(s, 200);
    assert_eq!(h["access-control-allow-origin"], "https://tools.example");
    assert!(h["access-control-expose-headers"].to_str().unwrap().contains("location"));

    let bad = horizon_bake::service::ServeArgs {
        cors_origin: Some("tools.example/path".into()),
        ..Default::default()
    };
    match horizon_bake::service::Config::from_args(bad) {
        Err(horizon_bake::Error::Param { field, .. }) => assert_eq!(field, "cors_origin"),
        other => panic!("{other:?}"),
    }
}

/// `HORIZON_API_KEY='abc123 '` is the key `abc123`; the `Bearer` scheme is case-insensitive.
#[tokio::test]
async fn api_key_is_trimmed_and_bearer_is_case_insensitive() {
    let args = ServeArgs {
        api_key: Some("abc123 \n".into()),
        data_dir: tempfile::tempdir().unwrap().keep(),
        ..Default::default()
    };
    let config = Config::from_args(args).unwrap();
    assert_eq!(config.api_key.as_deref(), Some("abc123"));
    let (st, _dir) = idle_state(|c| c.api_key = config.api_key.clone());
    let app = service::app(st);
    let get = |auth: &str| {
        Request::get("/v1/bakes").header("authorization", auth).body(Body::empty()).unwrap()
    };
    for ok in ["Bearer abc123", "bearer abc123", "BEARER abc123", "Bearer   abc123"] {
        assert_eq!(oneshot(&app, get(ok)).await.0, 200, "{ok}");
    }
    for bad in ["Bearer abc12", "Basic abc123", "Bearerabc123", "abc123"] {
        assert_eq!(oneshot(&app, get(bad)).await.0, 401, "{bad}");
    }
}

/// A request target over max_uri_bytes is a 414, headers over max_header_bytes a 431, both
/// problem+json (hyper's own bare answers only start far above these limits), over a socket.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn uri_and_header_limits_answer_problem_json() {
    let srv = Server::start(|_| {}).await;
    let c = client();
    let long = format!("/v1/bakes?{}=1", "k".repeat(65_000));
    let (s, p) = problem(c.get(srv.url(&long)).send().await.unwrap()).await;
    assert_eq!((s, p["code"].as_str()), (414, Some("uri_too_long")));
    let big = "v".repeat(100 * 1024);
    let (s, p) =
        problem(c.get(srv.url("/v1/bakes")).header("x-big", big).send().await.unwrap()).await;
    assert_eq!((s, p["code"].as_str()), (431, Some("headers_too_large")));
    let (s, _) = problem(
        c.get(srv.url("/healthz")).header("x-big", "v".repeat(70_000)).send().await.unwrap(),
    )
    .await;
    assert_eq!(s, 431);

    // Above hyper's own limits (a 65,534-byte target, a 1 MiB head) and for heads it cannot
    // parse, hyper answers before any handler; those answers are problem+json too.
    let addr = srv.url("").trim_start_matches("http://").trim_end_matches('/').to_owned();
    let raw = |req: Vec<u8>| {
        let addr = addr.clone();
        async move {
            use tokio::io::{AsyncReadExt, AsyncWriteExt};
            let mut s = tokio::net::TcpStream::connect(&addr).await.unwrap();
            let _ = s.write_all(&req).await; // hyper may close before it has read everything
            let mut out = Vec::new();
            let _ = s.read_to_end(&mut out).await;
            String::from_utf8_lossy(&out).into_owned()
        }
    };
    let long = format!("GET /v1/bakes?{}=1 HTTP/1.1\r\nhost: x\r\n\r\n", "k".repeat(70_000));
    let huge =
        format!("GET /v1/bakes HTTP/1.1\r\nhost: x\r\nx-big: {}\r\n\r\n", "v".repeat(2 << 20));
    for (req, status, code) in [
        (long.into_bytes(), 414, "uri_too_long"),
        (huge.into_bytes(), 431, "headers_too_large"),
        (b"GET /\x01 HTTP/1.1\r\nhost: x\r\n\r\n".to_vec(), 400, "malformed_request"),
    ] {
        let text = raw(req).await;
        let (head, body) = text.split_once("\r\n\r\n").unwrap_or((&text, ""));
        assert!(head.starts_with(&format!("HTTP/1.1 {status} ")), "{head}");
        assert!(head.contains("content-type: application/problem+json"), "{head}");
        let v: Value = serde_json::from_str(body).unwrap_or_else(|e| panic!("{e}: {body:?}"));
        assert_eq!((v["status"].as_u64(), v["code"].as_str()), (Some(status), Some(code)));
    }
    srv.stop().await;
}

/// Operator items: `X-Request-Id` on every answer (the client's, or a fresh one); ETag and
/// Cache-Control on previews and cube maps, whose 304 needs no render; SSE events carry `id:`
/// (and `retry:` first) and end with `done`.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn request_ids_cache_headers_and_sse_ids() {
    let srv = Server::start(|_| {}).await;
    let c = client();
    let res = c.get(srv.url("/v1/bakes")).header("x-request-id", "abc-123").send().await.unwrap();
    assert_eq!(res.headers()["x-request-id"], "abc-123");
    let res = c.get(srv.url("/v1/bakes")).send().await.unwrap();
    assert!(!res.headers()["x-request-id"].is_empty());

    let loc = submit_ok(&c, &srv, &terrain_png16(20, 16, 81), "?radius=3").await;
    let events = c.get(srv.url(&format!("{loc}/events"))).send().await.unwrap();
    let text = tokio::time::timeout(Duration::from_secs(60), events.text()).await.unwrap().unwrap();
    let blocks: Vec<&str> = text.split("\n\n").filter(|b| b.contains("event:")).collect();
    assert!(blocks[0].contains("retry: 2000"), "{text}");
    for (k, b) in blocks.iter().enumerate() {
        assert!(b.lines().any(|l| l == format!("id: {k}")), "event {k} has no id: {text}");
    }
    assert!(blocks.last().unwrap().contains("event: done"), "{text}");

    // How many previews and cube files the server has computed, from /metrics.
    let renders = |kind: &str| {
        let series = format!("horizon_renders_total{{kind=\"{kind}\"}}");
        let (c, srv) = (&c, &srv);
        async move { counter(c, srv, &series).await }
    };
    for (path, kind) in
        [(format!("{loc}/preview?azimuth=30"), "preview"), ("/v1/cubemap/2?size=8".into(), "cube")]
    {
        let before = renders(kind).await;
        let res = c.get(srv.url(&path)).send().await.unwrap();
        assert_eq!(res.status(), 200, "{path}");
        let etag = res.headers()["etag"].to_str().unwrap().to_owned();
        assert!(res.headers()["cache-control"].to_str().unwrap().contains("max-age"), "{path}");
        let body = res.bytes().await.unwrap();
        assert_eq!(renders(kind).await, before + 1, "{path}: a 200 computes once");
        let res = c.get(srv.url(&path)).header("if-none-match", &etag).send().await.unwrap();
        assert_eq!(res.status(), 304, "{path}");
        assert_eq!(res.headers()["etag"].to_str().unwrap(), etag);
        assert_eq!(renders(kind).await, before + 1, "{path}: a 304 must compute nothing");
        // Same request, same bytes, same tag; a different request, a different tag.
        let again = c.get(srv.url(&path)).send().await.unwrap();
        assert_eq!(again.headers()["etag"].to_str().unwrap(), etag);
        assert!(again.bytes().await.unwrap() == body);
    }
    let other = c.get(srv.url(&format!("{loc}/preview?azimuth=31"))).send().await.unwrap();
    let first = c.get(srv.url(&format!("{loc}/preview?azimuth=30"))).send().await.unwrap();
    assert_ne!(other.headers()["etag"], first.headers()["etag"]);
    srv.stop().await;
}
