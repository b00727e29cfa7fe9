//! Regression tests of the service defects of issue 14, each written to fail before its fix:
//! stalled uploads, retention of deduplicated bakes, API-key spelling, duplicate and unknown
//! parameters, echoed input, cursors, cache busters, oversized multipart bodies, float inputs
//! checked at submission and previews beside a long bake.

use crate::support::*;
use axum::body::Body;
use axum::http::{Request, StatusCode};
use horizon_bake::service::{self, handlers, Config, ServeArgs};
use serde_json::Value;
use std::time::{Duration, Instant};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tower::ServiceExt;

async fn problem(res: reqwest::Response) -> (u16, Value) {
    let status = res.status().as_u16();
    assert_eq!(res.headers()["content-type"], "application/problem+json");
    (status, res.json().await.unwrap())
}

async fn oneshot(app: &axum::Router, req: Request<Body>) -> (StatusCode, Value) {
    let res = app.clone().oneshot(req).await.unwrap();
    let (parts, body) = res.into_parts();
    let bytes = axum::body::to_bytes(body, usize::MAX).await.unwrap();
    (parts.status, serde_json::from_slice(&bytes).unwrap_or(Value::Null))
}

fn raw_submit(png: &[u8], query: &str) -> Request<Body> {
    Request::post(format!("/v1/bakes{query}"))
        .header("content-type", "image/png")
        .body(Body::from(png.to_vec()))
        .unwrap()
}

async fn submit_ok(c: &reqwest::Client, srv: &Server, png: &[u8], query: &str) -> String {
    let res = c
        .post(srv.url(&format!("/v1/bakes{query}")))
        .header("content-type", "image/png")
        .body(png.to_vec())
        .send()
        .await
        .unwrap();
    assert_eq!(res.status(), 202);
    res.headers()["location"].to_str().unwrap().to_owned()
}

/// The value of the counter line `series` (name and labels, as exposed) in the server's
/// /metrics; panics if the server does not expose it.
async fn counter(c: &reqwest::Client, srv: &Server, series: &str) -> u64 {
    let text = c.get(srv.url("/metrics")).send().await.unwrap().text().await.unwrap();
    let key = format!("{series} ");
    let line = text.lines().find(|l| l.starts_with(&key)).unwrap_or_else(|| panic!("{series}"));
    line[key.len()..].parse().unwrap()
}

/// Connections that announce a body and never send it, or never finish their headers, must not
/// keep upload slots (or connections) forever: after the body timeout a real submission works.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn stalled_uploads_do_not_hold_upload_slots() {
    let srv = Server::start(|c| {
        c.max_inflight_uploads = 2;
        c.upload_wait = Duration::from_secs(4);
        c.body_timeout = Duration::from_millis(800);
        c.header_timeout = Duration::from_millis(800);
    })
    .await;
    let addr = srv.base.trim_start_matches("http://").to_owned();
    let mut stalled = Vec::new();
    for _ in 0..2 {
        let mut s = tokio::net::TcpStream::connect(&addr).await.unwrap();
        s.write_all(
            b"POST /v1/bakes HTTP/1.1\r\nhost: x\r\ncontent-type: image/png\r\n\
              content-length: 100000\r\n\r\n\x89PNG",
        )
        .await
        .unwrap();
        stalled.push(s);
    }
    // Headers that never end.
    let mut slow_headers = tokio::net::TcpStream::connect(&addr).await.unwrap();
    slow_headers.write_all(b"POST /v1/bakes HTTP/1.1\r\nhost: x\r\n").await.unwrap();
    tokio::time::sleep(Duration::from_millis(200)).await;

    let c = client();
    let loc = submit_ok(&c, &srv, &terrain_png16(8, 8, 11), "?radius=2").await;
    let v = wait_done(&c, &srv.url(&loc), Duration::from_secs(60)).await;
    assert_eq!(v["status"], "succeeded", "{v}");

    // The stalled uploads were answered 408 (problem+json) and the slow headers were cut off.
    for mut s in stalled {
        let mut buf = Vec::new();
        let _ = tokio::time::timeout(Duration::from_secs(10), s.read_to_end(&mut buf)).await;
        let text = String::from_utf8_lossy(&buf);
        assert!(text.starts_with("HTTP/1.1 408"), "stalled upload got: {text}");
        assert!(text.contains("application/problem+json"), "{text}");
    }
    let mut buf = Vec::new();
    let closed =
        tokio::time::timeout(Duration::from_secs(10), slow_headers.read_to_end(&mut buf)).await;
    assert!(closed.is_ok(), "a connection with unfinished headers was kept open");
    srv.stop().await;
}

/// A deduplicated submission (answered 200) renews the bake's retention, and the resource says
/// when it expires.
#[tokio::test]
async fn dedup_hit_extends_retention_and_shows_expires_at() {
    let (st, repo, _dir) = idle_state_with_repo(|c| c.retention = Duration::from_secs(3600));
    let app = service::app(st.clone());
    let png = terrain_png16(8, 8, 21);
    let (s, v) = oneshot(&app, raw_submit(&png, "")).await;
    assert_eq!(s, 202);
    assert!(v["expires_at"].is_null(), "a queued bake does not expire: {v}");
    let id = v["id"].as_str().unwrap().to_owned();
    // Make it a bake that finished two hours ago: past the retention.
    use horizon_bake::service::store::BakeStore;
    let mut rec = repo.store().get(&id).unwrap().unwrap();
    rec.status = horizon_bake::service::store::Status::Succeeded;
    let two_hours_ago = horizon_bake::service::store::now_ms() - 2 * 3600 * 1000;
    rec.finished_ms = Some(two_hours_ago);
    repo.store().put(&rec).unwrap();
    let (s, v) =
        oneshot(&app, Request::get(format!("/v1/bakes/{id}")).body(Body::empty()).unwrap()).await;
    assert_eq!(s, 200);
    assert_eq!(v["expires_at"], handlers::rfc3339(two_hours_ago + 3600 * 1000));

    let (s, v) = oneshot(&app, raw_submit(&png, "")).await;
    assert_eq!((s, v["id"].as_str().unwrap()), (StatusCode::OK, id.as_str()));
    let renewed = v["expires_at"].as_str().unwrap().to_owned();
    assert!(renewed > handlers::rfc3339(horizon_bake::service::store::now_ms()), "{renewed}");
    let removed = handlers::sweep(&st).await;
    assert_eq!(removed.unwrap(), 0, "the sweep removed a bake that was just asked for again");
    assert!(repo.store().get(&id).unwrap().is_some());
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

/// One rule for a parameter given twice: 422 naming it, whether both are in the query, in two
/// `params` parts, or one in the query and one in the JSON part.
#[tokio::test]
async fn duplicate_parameters_are_a_422_naming_the_key_everywhere() {
    let (st, _dir) = idle_state(|_| {});
    let app = service::app(st);
    let png = terrain_png16(8, 8, 31);
    let (s, p) = oneshot(&app, raw_submit(&png, "?radius=21&radius=22")).await;
    assert_eq!((s.as_u16(), p["field"].as_str()), (422, Some("radius")), "{p}");

    let multipart = |query: &str, parts: &[&str]| {
        let boundary = "XyZ";
        let mut body = Vec::new();
        body.extend_from_slice(
            format!(
                "--{boundary}\r\ncontent-disposition: form-data; name=\"heightmap\"; \
                 filename=\"h.png\"\r\ncontent-type: image/png\r\n\r\n"
            )
            .as_bytes(),
        );
        body.extend_from_slice(&png);
        for part in parts {
            body.extend_from_slice(
                format!(
                    "\r\n--{boundary}\r\ncontent-disposition: form-data; name=\"params\"\r\n\r\n{part}"
                )
                .as_bytes(),
            );
        }
        body.extend_from_slice(format!("\r\n--{boundary}--\r\n").as_bytes());
        Request::post(format!("/v1/bakes{query}"))
            .header("content-type", format!("multipart/form-data; boundary={boundary}"))
            .body(Body::from(body))
            .unwrap()
    };
    let (s, p) = oneshot(&app, multipart("", &[r#"{"radius": 21}"#, r#"{"bins": 32}"#])).await;
    assert_eq!((s.as_u16(), p["field"].as_str()), (422, Some("params")), "{p}");
    let (s, p) = oneshot(&app, multipart("?radius=21", &[r#"{"radius": 21}"#])).await;
    assert_eq!((s.as_u16(), p["field"].as_str()), (422, Some("radius")), "{p}");
    let (s, p) = oneshot(&app, multipart("", &[r#"{"radius": 21, "radius": 22}"#])).await;
    assert_eq!((s.as_u16(), p["field"].as_str()), (422, Some("radius")), "{p}");
    // Different keys from the query and the JSON part are merged.
    let (s, v) = oneshot(&app, multipart("?radius=21", &[r#"{"bins": 48}"#])).await;
    assert_eq!(s, 202, "{v}");
    assert_eq!(
        (&v["params"]["radius"], &v["params"]["bins"]),
        (&Value::from(21), &Value::from(48)),
        "{v}"
    );
}

/// A huge unknown key is named, but not echoed in full: the answer stays small.
#[tokio::test]
async fn echoed_input_in_errors_is_capped() {
    let (st, _dir) = idle_state(|_| {});
    let app = service::app(st);
    // 12,000 characters: under max_uri_bytes (16 KiB), so it reaches the parameter parser.
    let key = "k".repeat(12_000);
    for uri in [
        format!("/v1/bakes?{key}=1"),
        format!("/v1/cubemap/0?size={key}"),
        format!("/v1/bakes?status={key}"),
    ] {
        let res = app.clone().oneshot(Request::get(&uri).body(Body::empty()).unwrap()).await;
        let res = res.unwrap();
        assert_eq!(res.status(), 422);
        let body = axum::body::to_bytes(res.into_body(), usize::MAX).await.unwrap();
        assert!(body.len() < 2048, "{} bytes answered to {}…", body.len(), &uri[..30]);
    }
    let (s, _) = oneshot(&app, raw_submit(&terrain_png16(4, 4, 1), &format!("?{key}=1"))).await;
    assert_eq!(s, 422);
}

/// Every malformed cursor is one answer: 422 naming `cursor`.
#[tokio::test]
async fn invalid_cursors_are_all_422() {
    let (st, _dir) = idle_state(|_| {});
    let app = service::app(st);
    let long = "0".repeat(65);
    for cursor in ["zzz", "", long.as_str(), "0123456789abcdef012", "ZZZZZZZZZZZZZZZZZZZZ"] {
        let (s, p) = oneshot(
            &app,
            Request::get(format!("/v1/bakes?cursor={cursor}")).body(Body::empty()).unwrap(),
        )
        .await;
        assert_eq!((s.as_u16(), p["field"].as_str()), (422, Some("cursor")), "{cursor}: {p}");
    }
    // A well-formed cursor that names no bake is fine: the page after it.
    let (s, v) = oneshot(
        &app,
        Request::get("/v1/bakes?cursor=0123456789abcdef0123").body(Body::empty()).unwrap(),
    )
    .await;
    assert_eq!(s, 200, "{v}");
}

/// Cache busters (`?v=123`) on immutable results are ignored; known keys are still checked.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn unknown_query_keys_on_immutable_results_are_ignored() {
    let srv = Server::start(|_| {}).await;
    let c = client();
    let loc = submit_ok(&c, &srv, &terrain_png16(12, 10, 41), "?radius=3").await;
    let v = wait_done(&c, &srv.url(&loc), Duration::from_secs(60)).await;
    assert_eq!(v["status"], "succeeded", "{v}");
    for path in [
        format!("{loc}/horizon/0?v=123"),
        format!("{loc}/horizon/1?format=png16&_=9"),
        format!("{loc}/horizon.ktx2?v=1"),
        format!("{loc}/horizon.dds?v=1"),
        "/v1/cubemap/0?v=2".to_owned(),
        "/v1/cubemap.ktx2?size=4&v=2".to_owned(),
    ] {
        let res = get_result(&c, &srv.url(&path)).await;
        assert_eq!(res.status(), 200, "{path}");
    }
    let (s, p) =
        problem(c.get(srv.url(&format!("{loc}/horizon/0?format=jpg&v=1"))).send().await.unwrap())
            .await;
    assert_eq!((s, p["field"].as_str()), (422, Some("format")));
    srv.stop().await;
}

/// An oversized multipart upload is answered 413, every time (the server reads and discards a
/// bounded amount so the client sees the answer instead of a reset).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn oversized_multipart_upload_gets_413_every_time() {
    let srv = Server::start(|c| c.max_body_bytes = 64 * 1024).await;
    let c = client();
    // 16 MiB: far more than the socket buffers hold, so a server that answers without reading
    // closes the connection while the client is still sending.
    for round in 0..6 {
        let form = reqwest::multipart::Form::new()
            .part("heightmap", reqwest::multipart::Part::bytes(vec![7u8; 16 << 20]))
            .text("params", "{}");
        let res = c.post(srv.url("/v1/bakes")).multipart(form).send().await;
        let res = res.unwrap_or_else(|e| panic!("round {round}: no answer: {e}"));
        let (s, p) = problem(res).await;
        assert_eq!((s, p["code"].as_str()), (413, Some("payload_too_large")), "round {round}");
    }
    srv.stop().await;
}

fn tiff_of<C: tiff::encoder::colortype::ColorType>(w: u32, h: u32, data: &[C::Inner]) -> Vec<u8>
where
    [C::Inner]: tiff::encoder::TiffValue,
{
    let mut out = std::io::Cursor::new(Vec::new());
    tiff::encoder::TiffEncoder::new(&mut out).unwrap().write_image::<C>(w, h, data).unwrap();
    out.into_inner()
}

fn exr_of(w: usize, h: usize, samples: exr::prelude::FlatSamples) -> Vec<u8> {
    use exr::prelude::*;
    let list: SmallVec<[AnyChannel<FlatSamples>; 4]> =
        std::iter::once(AnyChannel::new("Y", samples)).collect();
    let layer = Layer::new(
        (w, h),
        LayerAttributes::named("height"),
        Encoding::FAST_LOSSLESS,
        AnyChannels::sort(list),
    );
    let mut out = std::io::Cursor::new(Vec::new());
    Image::from_layer(layer).write().to_buffered(&mut out).unwrap();
    out.into_inner()
}

/// A little-endian baseline TIFF of one gray 16-bit float (half) sample per texel, all `v`:
/// written by hand, as the `tiff` crate's encoder has no half-float colour type.
fn half_float_tiff(w: u16, h: u16, v: f32) -> Vec<u8> {
    // f32 → f16 for normal values (v = 0.5 here): sign, rebased exponent, top 10 mantissa bits.
    let b = v.to_bits();
    let half =
        (((b >> 16) & 0x8000) | ((((b >> 23) & 0xff) - 112) << 10) | ((b >> 13) & 0x3ff)) as u16;
    let entries: [(u16, u16, u32); 10] = [
        (256, 3, w as u32),                // ImageWidth
        (257, 3, h as u32),                // ImageLength
        (258, 3, 16),                      // BitsPerSample
        (259, 3, 1),                       // Compression: none
        (262, 3, 1),                       // Photometric: BlackIsZero
        (273, 4, 8 + 2 + 10 * 12 + 4),     // StripOffsets
        (277, 3, 1),                       // SamplesPerPixel
        (278, 3, h as u32),                // RowsPerStrip
        (279, 4, 2 * w as u32 * h as u32), // StripByteCounts
        (339, 3, 3),                       // SampleFormat: IEEE float
    ];
    let mut out = b"II".to_vec();
    out.extend_from_slice(&42u16.to_le_bytes());
    out.extend_from_slice(&8u32.to_le_bytes());
    out.extend_from_slice(&(entries.len() as u16).to_le_bytes());
    for (tag, ty, value) in entries {
        out.extend_from_slice(&tag.to_le_bytes());
        out.extend_from_slice(&ty.to_le_bytes());
        out.extend_from_slice(&1u32.to_le_bytes());
        out.extend_from_slice(&value.to_le_bytes());
    }
    out.extend_from_slice(&0u32.to_le_bytes());
    for _ in 0..w as usize * h as usize {
        out.extend_from_slice(&half.to_le_bytes());
    }
    out
}

/// Float inputs are checked when they are submitted: NaN/Inf and out-of-range heights are a 422
/// (blaming the input), unsupported sample formats a 415; nothing is queued for them.
#[tokio::test]
async fn float_inputs_are_checked_at_submission() {
    use tiff::encoder::colortype::{Gray32, Gray32Float};
    let (st, _dir) = idle_state(|_| {});
    let app = service::app(st);
    let mut nan = vec![0.5f32; 16];
    nan[5] = f32::NAN;
    let mut inf = vec![0.5f32; 16];
    inf[9] = f32::INFINITY;
    let mut huge = vec![0.5f32; 16];
    huge[3] = 3.0e38;
    huge[4] = -3.0e38;
    let cases: Vec<(&str, Vec<u8>, u16, &str)> = vec![
        ("tiff nan", tiff_of::<Gray32Float>(4, 4, &nan), 422, "invalid_input"),
        ("tiff inf", tiff_of::<Gray32Float>(4, 4, &inf), 422, "invalid_input"),
        ("tiff 3e38", tiff_of::<Gray32Float>(4, 4, &huge), 422, "invalid_input"),
        (
            "exr nan",
            exr_of(4, 4, exr::prelude::FlatSamples::F32(nan.clone())),
            422,
            "invalid_input",
        ),
        ("tiff u32", tiff_of::<Gray32>(4, 4, &[7u32; 16]), 415, "unsupported_media_type"),
        ("tiff f16", half_float_tiff(4, 4, 0.5), 415, "unsupported_media_type"),
    ];
    for (what, bytes, status, code) in cases {
        let (s, p) = oneshot(&app, raw_submit(&bytes, "")).await;
        assert_eq!((s.as_u16(), p["code"].as_str()), (status, Some(code)), "{what}: {p}");
        if what == "tiff f16" {
            // Refused for its sample format, not as an unreadable file.
            let detail = p["detail"].as_str().unwrap();
            assert!(detail.contains("16-bit"), "{what}: {detail}");
        }
        if code == "invalid_input" {
            let detail = p["detail"].as_str().unwrap();
            assert!(!detail.contains("height_scale"), "{what} blames height_scale: {detail}");
        }
    }
    let (s, v) = oneshot(&app, Request::get("/v1/bakes").body(Body::empty()).unwrap()).await;
    assert_eq!(s, 200);
    assert_eq!(v["items"].as_array().unwrap().len(), 0, "a rejected input was queued: {v}");
}

/// A preview of a small finished bake answers while a long bake holds every bake slot.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn previews_do_not_queue_behind_a_long_bake() {
    let srv = Server::start(|c| c.bake_threads = 2).await;
    let c = client();
    let small = submit_ok(&c, &srv, &terrain_png16(24, 24, 51), "?radius=4").await;
    let v = wait_done(&c, &srv.url(&small), Duration::from_secs(60)).await;
    assert_eq!(v["status"], "succeeded", "{v}");
    let long = submit_ok(&c, &srv, &noise_png8(4096, 4096, 52), "?radius=64").await;
    let t = Instant::now();
    loop {
        let v: Value = c.get(srv.url(&long)).send().await.unwrap().json().await.unwrap();
        if v["progress"]["stage"] == "bake" {
            break;
        }
        assert!(t.elapsed() < Duration::from_secs(60), "the long bake never started: {v}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let res = c.get(srv.url(&format!("{small}/preview?azimuth=30"))).send().await.unwrap();
    assert_eq!(res.status(), 200);
    let v: Value = c.get(srv.url(&long)).send().await.unwrap().json().await.unwrap();
    assert_eq!(v["status"], "running", "the preview waited for the long bake: {v}");
    let res = c.delete(srv.url(&long)).send().await.unwrap();
    assert_eq!(res.status(), 202);
    srv.stop().await;
}

/// Pay only for what is asked: a bake stores its png8 layers only; another format is encoded on
/// its first request, once however many requests ask at the same time, then kept.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn formats_other_than_png8_are_encoded_once_on_first_request() {
    let srv = Server::start(|_| {}).await;
    let c = client();
    let png = terrain_png16(40, 30, 61);
    let loc = submit_ok(&c, &srv, &png, "?radius=5").await;
    let v = wait_done(&c, &srv.url(&loc), Duration::from_secs(60)).await;
    assert_eq!(v["status"], "succeeded", "{v}");
    assert_eq!(blob_files(srv.dir.path()).len(), 3, "input + two png8 layers");
    let encoded = || counter(&c, &srv, "horizon_results_encoded_total");
    assert_eq!(encoded().await, 0);

    let url = srv.url(&format!("{loc}/horizon/0?format=exr"));
    let gets = (0..4).map(|_| {
        let (c, url) = (c.clone(), url.clone());
        tokio::spawn(async move {
            let res = get_result(&c, &url).await;
            assert_eq!(res.status(), 200);
            res.bytes().await.unwrap()
        })
    });
    let bodies: Vec<_> = futures_util::future::join_all(gets).await;
    let want = library_files(&png, &[("radius", "5")]);
    for b in bodies {
        assert!(b.unwrap()[..] == want["horizon_0.exr"][..], "EXR differs from the library's");
    }
    // Both layers at both EXR precisions, from one re-bake (issue 25).
    assert_eq!(encoded().await, 4, "both EXR layers, float and half, encoded once");
    let res = c.get(srv.url(&format!("{loc}/horizon/1?format=exr"))).send().await.unwrap();
    assert!(res.bytes().await.unwrap()[..] == want["horizon_1.exr"][..]);
    let half = format!("{loc}/horizon/1?format=exr&exr_precision=half");
    assert_eq!(c.get(srv.url(&half)).send().await.unwrap().status(), 200);
    assert_eq!(encoded().await, 4, "layer 1 and half precision were encoded with layer 0");
    assert_eq!(blob_files(srv.dir.path()).len(), 7);
    srv.stop().await;
}

/// DELETE late in a bake (where the encoders used to run for seconds without looking at the
/// cancel flag) stops it within a band, not after every format was encoded.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn delete_late_in_a_bake_does_not_wait_for_the_encoders() {
    let srv = Server::start(|_| {}).await;
    let c = client();
    let loc = submit_ok(&c, &srv, &noise_png8(4096, 4096, 71), "?radius=2").await;
    let t = Instant::now();
    loop {
        let v: Value = c.get(srv.url(&loc)).send().await.unwrap().json().await.unwrap();
        assert_ne!(v["status"], "succeeded", "finished before the DELETE: {v}");
        // Past 0.85 of the overall progress: the end of the kernel, or (before the fix) the
        // encode stage (0.90..0.97).
        if v["progress"]["fraction"].as_f64().unwrap() >= 0.85 {
            break;
        }
        assert!(t.elapsed() < Duration::from_secs(120), "{v}");
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    let asked = Instant::now();
    let res = c.delete(srv.url(&loc)).send().await.unwrap();
    assert_eq!(res.status(), 202, "the bake was no longer running");
    let v = wait_done(&c, &srv.url(&loc), Duration::from_secs(120)).await;
    let took = asked.elapsed();
    assert_eq!(v["status"], "canceled", "{v}");
    assert!(took < Duration::from_secs(2), "cancel took {took:?}");
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

/// `exr_precision=half` serves half-float layers: the library's f32 values rounded to f16.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn half_precision_exr_is_the_f32_layer_in_half() {
    use exr::prelude::*;
    let srv = Server::start(|_| {}).await;
    let c = client();
    let png = terrain_png16(24, 18, 91);
    let loc = submit_ok(&c, &srv, &png, "?radius=4").await;
    let v = wait_done(&c, &srv.url(&loc), Duration::from_secs(60)).await;
    assert_eq!(v["status"], "succeeded", "{v}");
    let res =
        get_result(&c, &srv.url(&format!("{loc}/horizon/1?format=exr&exr_precision=half"))).await;
    assert_eq!(res.status(), 200);
    let bytes = res.bytes().await.unwrap();
    let img = read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .first_valid_layer()
        .all_attributes()
        .from_buffered(std::io::Cursor::new(&bytes[..]))
        .unwrap();
    let list = &img.layer_data.channel_data.list;
    assert!(list.iter().all(|ch| matches!(ch.sample_data, FlatSamples::F16(_))));
    let params = horizon_bake::params::BakeParams::from_pairs([("radius", "4")]).unwrap();
    let (map, _) =
        horizon_bake::heightmap::decode(&png, params.channel, &Default::default()).unwrap();
    let (layers, _) = horizon_bake::bake::bake_horizon(
        &map,
        &params,
        horizon_bake::bake::Precisions::ALL,
        &horizon_bake::progress::Progress::new(),
    )
    .unwrap();
    let want = &layers.f32.as_ref().unwrap()[1];
    let find = |n: &str| list.iter().find(|ch| ch.name == *n).unwrap();
    for (k, name) in ["R", "G", "B", "A"].iter().enumerate() {
        let FlatSamples::F16(got) = &find(name).sample_data else { unreachable!() };
        for (t, g) in got.iter().enumerate() {
            assert_eq!(*g, f16::from_f32(want[t * 4 + k]), "{name} texel {t}");
        }
    }
    // exr_precision without format=exr names itself.
    let (s, p) = problem(
        c.get(srv.url(&format!("{loc}/horizon/0?exr_precision=half"))).send().await.unwrap(),
    )
    .await;
    assert_eq!((s, p["field"].as_str()), (422, Some("exr_precision")));
    srv.stop().await;
}

/// Listing: newest first on request, several statuses in one filter, and the total count.
#[tokio::test]
async fn listing_newest_first_several_statuses_and_total() {
    let (st, _dir) = idle_state(|_| {});
    let app = service::app(st);
    let mut ids = Vec::new();
    for seed in 0..3 {
        let (s, v) = oneshot(&app, raw_submit(&terrain_png16(6, 6, 100 + seed), "")).await;
        assert_eq!(s, 202);
        ids.push(v["id"].as_str().unwrap().to_owned());
        // Ids are time-ordered to the millisecond.
        tokio::time::sleep(Duration::from_millis(3)).await;
    }
    let (s, _) = oneshot(
        &app,
        Request::delete(format!("/v1/bakes/{}", ids[1])).body(Body::empty()).unwrap(),
    )
    .await;
    assert_eq!(s, 200);
    let get = |uri: String| Request::get(uri).body(Body::empty()).unwrap();
    let id_list = |v: &Value| -> Vec<String> {
        v["items"]
            .as_array()
            .unwrap()
            .iter()
            .map(|i| i["id"].as_str().unwrap().to_owned())
            .collect()
    };
    let (s, v) = oneshot(&app, get("/v1/bakes?order=desc&limit=2".into())).await;
    assert_eq!(s, 200, "{v}");
    assert_eq!(id_list(&v), [ids[2].clone(), ids[1].clone()]);
    assert_eq!(v["total"], 3);
    let href = v["next"]["href"].as_str().unwrap().to_owned();
    assert!(href.contains("order=desc"), "{href}");
    let (_, v) = oneshot(&app, get(href)).await;
    assert_eq!(id_list(&v), [ids[0].clone()]);
    assert!(v["next"].is_null());
    let (_, v) = oneshot(&app, get("/v1/bakes?status=canceled".into())).await;
    assert_eq!((id_list(&v), &v["total"]), (vec![ids[1].clone()], &Value::from(1)));
    let (_, v) = oneshot(&app, get("/v1/bakes?status=queued,canceled&limit=1".into())).await;
    assert_eq!((id_list(&v), &v["total"]), (vec![ids[0].clone()], &Value::from(3)));
    let (s, p) = oneshot(&app, get("/v1/bakes?order=sideways".into())).await;
    assert_eq!((s.as_u16(), p["field"].as_str()), (422, Some("order")));
    let (s, p) = oneshot(&app, get("/v1/bakes?status=queued,done".into())).await;
    assert_eq!((s.as_u16(), p["field"].as_str()), (422, Some("status")));
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

/// A submission can name the formats to encode with the bake (`formats`, `exr_precision`: the
/// CLI's `--format` and `--exr-precision`), so a pipeline that wants EXR pays for it once, during
/// the bake, instead of a re-bake on its first download; the resource says what was asked and
/// what is stored, and the downloads are the library's bytes with nothing encoded on request.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn formats_named_at_submission_are_encoded_with_the_bake() {
    let srv = Server::start(|_| {}).await;
    let c = client();
    let png = terrain_png16(36, 28, 63);
    let encoded = || counter(&c, &srv, "horizon_results_encoded_total");
    // Refused at submission, naming the key, with nothing stored.
    for (q, field) in [
        ("?formats=gif", "formats"),
        ("?formats=png8,png16", "formats"),
        ("?formats=exr&formats=png8", "formats"),
        ("?exr_precision=half", "exr_precision"),
        ("?formats=exr&exr_precision=quarter", "exr_precision"),
        ("?outputs=fourier&formats=exr", "formats"),
    ] {
        let res = c
            .post(srv.url(&format!("/v1/bakes{q}")))
            .header("content-type", "image/png")
            .body(png.clone())
            .send()
            .await
            .unwrap();
        let (s, p) = problem(res).await;
        assert_eq!((s, p["field"].as_str()), (422, Some(field)), "{q}: {p}");
    }
    assert!(blob_files(srv.dir.path()).is_empty());

    let loc = submit_ok(&c, &srv, &png, "?radius=4&formats=png16,exr,ktx2").await;
    let v = wait_done(&c, &srv.url(&loc), Duration::from_secs(60)).await;
    assert_eq!(v["status"], "succeeded", "{v}");
    assert_eq!(v["formats"]["requested"], "png16,exr,ktx2", "{v}");
    let stored: Vec<&str> =
        v["formats"]["stored"].as_array().unwrap().iter().map(|s| s.as_str().unwrap()).collect();
    assert_eq!(
        stored,
        ["horizon.ktx2", "horizon_0.exr", "horizon_0.png16", "horizon_1.exr", "horizon_1.png16"]
    );
    assert!(v["links"]["horizon_0"].is_string(), "{v}");
    let want = library_files(&png, &[("radius", "4")]);
    for name in ["horizon_0.png16", "horizon_1.exr", "horizon.ktx2"] {
        let res = c.get(srv.url(&format!("{loc}{}", result_path(name)))).send().await.unwrap();
        assert_eq!(res.status(), 200, "{name}");
        assert!(res.bytes().await.unwrap() == want[name], "{name} differs from the library's");
    }
    assert_eq!(encoded().await, 0, "nothing was encoded on request");
    // A format not asked is still there, encoded on its first request.
    let res = get_result(&c, &srv.url(&format!("{loc}/horizon/1"))).await;
    assert_eq!(res.status(), 200);
    assert!(res.bytes().await.unwrap() == want["horizon_1.png8"]);
    assert_eq!(encoded().await, 2);

    // Formats are not part of the bake's identity: the same input and parameters with other
    // formats is the same bake. In a multipart `params` part they are JSON like the rest.
    let form = reqwest::multipart::Form::new()
        .part("heightmap", reqwest::multipart::Part::bytes(png.clone()))
        .text("params", r#"{"radius": 4, "formats": ["dds"]}"#);
    let res = c.post(srv.url("/v1/bakes")).multipart(form).send().await.unwrap();
    assert_eq!(res.status(), 200);
    let again: Value = res.json().await.unwrap();
    assert_eq!(again["id"], v["id"]);

    // Half-float EXR asked at submission is stored as such.
    let loc = submit_ok(&c, &srv, &png, "?radius=3&formats=png8,exr&exr_precision=half").await;
    let v = wait_done(&c, &srv.url(&loc), Duration::from_secs(60)).await;
    assert_eq!(v["formats"]["requested"], "png8,exr,half", "{v}");
    let stored = v["formats"]["stored"].to_string();
    assert!(stored.contains("horizon_0.half.exr") && !stored.contains("horizon_0.exr\""), "{v}");
    let before = encoded().await;
    let res = c
        .get(srv.url(&format!("{loc}/horizon/0?format=exr&exr_precision=half")))
        .send()
        .await
        .unwrap();
    assert_eq!(res.status(), 200);
    assert_eq!(encoded().await, before);
    srv.stop().await;
}

/// DELETE during the encode stage of a bake that encodes whole-layer formats (asked with
/// `formats`) stops between encoders instead of waiting for all of them: measured against the
/// encode time of the same bake left to finish.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn delete_during_the_encode_stage_stops_between_encoders() {
    let srv = Server::start(|_| {}).await;
    let c = client();
    let q = "?radius=1&bins=16&formats=png16,exr,ktx2,dds";
    let loc = submit_ok(&c, &srv, &terrain_png16(1536, 1536, 71), q).await;
    let v = wait_done(&c, &srv.url(&loc), Duration::from_secs(120)).await;
    assert_eq!(v["status"], "succeeded", "{v}");
    let full_encode = v["timings_ms"]["encode"].as_f64().unwrap();

    let loc = submit_ok(&c, &srv, &terrain_png16(1536, 1536, 72), q).await;
    let t = Instant::now();
    loop {
        let v: Value = c.get(srv.url(&loc)).send().await.unwrap().json().await.unwrap();
        if v["progress"]["stage"] == "encode" {
            break;
        }
        assert!(v["status"] != "succeeded", "the encode stage was never seen: {v}");
        assert!(t.elapsed() < Duration::from_secs(120));
        tokio::time::sleep(Duration::from_millis(2)).await;
    }
    let asked = Instant::now();
    let res = c.delete(srv.url(&loc)).send().await.unwrap();
    assert!(res.status().is_success(), "{}", res.status());
    let v = wait_done(&c, &srv.url(&loc), Duration::from_secs(60)).await;
    let took = asked.elapsed().as_secs_f64() * 1e3;
    assert_eq!(v["status"], "canceled", "{v}");
    eprintln!("cancel during encode: {took:.0} ms; the whole encode: {full_encode:.0} ms");
    assert!(took < 0.8 * full_encode, "cancel took {took:.0} ms of a {full_encode:.0} ms encode");
    srv.stop().await;
}
