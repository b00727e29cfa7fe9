//! A large upload is streamed to the blob store, not held (issue 23): a raw body of a 384 MiB
//! 16-bit PNG sent in 64 KiB pieces to the service's router is accepted (202) with the input's
//! size and hash, stored whole, and the process's peak resident memory grows by far less than
//! the body. Plus a multipart upload of the same kind, and a small upload still in memory.
//! And uploads that misbehave (from tests/service_defects.rs, issue 14): stalled bodies and
//! unfinished headers do not hold upload slots, an oversized multipart body gets its 413.
//!
//! The memory test is ignored by default (it moves 384 MiB twice): run it alone, so that the
//! peak is the process's, with `cargo test --test service -- --ignored --exact --nocapture
//! uploads::a_large_upload_does_not_raise_memory_by_its_size`.

use crate::support::*;
use axum::body::Body;
use axum::http::Request;
use horizon_bake::service;
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tower::ServiceExt;

#[path = "../../benches/common/proc_status.rs"]
mod proc_status;
use proc_status::status;

/// A valid PNG signature and IHDR of a `w × h` 16-bit grey image, then `len` bytes in all
/// (the rest zeros: only the header is read at submission).
fn png_head(w: u32, h: u32) -> Vec<u8> {
    let mut b = b"\x89PNG\r\n\x1a\n".to_vec();
    let mut ihdr = Vec::new();
    ihdr.extend_from_slice(&w.to_be_bytes());
    ihdr.extend_from_slice(&h.to_be_bytes());
    ihdr.extend_from_slice(&[16, 0, 0, 0, 0]);
    b.extend_from_slice(&13u32.to_be_bytes());
    b.extend_from_slice(b"IHDR");
    b.extend_from_slice(&ihdr);
    let mut crc = crc32fast::Hasher::new();
    crc.update(b"IHDR");
    crc.update(&ihdr);
    b.extend_from_slice(&crc.finalize().to_be_bytes());
    b
}

/// The body: `head`, then zeros up to `len`, in 64 KiB pieces; and its BLAKE3.
fn body(head: &[u8], len: usize) -> (Body, String) {
    let piece = 64 << 10;
    let mut h = blake3::Hasher::new();
    h.update(head);
    let zeros = vec![0u8; piece];
    let mut left = len - head.len();
    while left > 0 {
        let n = left.min(piece);
        h.update(&zeros[..n]);
        left -= n;
    }
    let head = bytes::Bytes::copy_from_slice(head);
    let rest = len - head.len();
    let chunks = std::iter::once(head).chain(
        (0..rest.div_ceil(piece))
            .map(move |k| bytes::Bytes::from(vec![0u8; piece.min(rest - k * piece)])),
    );
    let stream = futures_util::stream::iter(chunks.map(Ok::<_, std::io::Error>));
    (Body::from_stream(stream), h.finalize().to_hex().to_string())
}

async fn post(app: &axum::Router, req: Request<Body>) -> (u16, serde_json::Value) {
    let res = app.clone().oneshot(req).await.unwrap();
    let s = res.status().as_u16();
    let b = axum::body::to_bytes(res.into_body(), usize::MAX).await.unwrap();
    (s, serde_json::from_slice(&b).unwrap_or_default())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore = "moves 384 MiB twice; run with --ignored"]
async fn a_large_upload_does_not_raise_memory_by_its_size() {
    let len: usize = 384 << 20;
    let (st, dir) = idle_state(|c| {
        c.max_body_bytes = 1 << 30;
        c.limits.max_bytes = 1 << 30;
    });
    let app = service::app(st);
    // 1. A raw body announced by Content-Length: spooled from its first byte.
    let before = status("VmHWM:");
    let (b, hash) = body(&png_head(8192, 8192), len);
    let req = Request::post("/v1/bakes")
        .header("content-type", "image/png")
        .header("content-length", len.to_string())
        .body(b)
        .unwrap();
    let (s, v) = post(&app, req).await;
    assert_eq!(s, 202, "{v}");
    assert_eq!(v["input"]["content_hash"], hash, "{v}");
    let grew = status("VmHWM:").saturating_sub(before) as f64 / 1024.0;
    println!("raw upload of {} MiB with Content-Length: peak +{grew:.1} MiB", len >> 20);
    assert!(grew < 64.0, "the upload raised the peak by {grew:.1} MiB");
    let path = dir.path().join("blobs").join(&hash[..2]).join(&hash);
    assert_eq!(std::fs::metadata(&path).unwrap().len(), len as u64);

    // 2. Multipart with Content-Length: the heightmap part streams the same way.
    let before = status("VmHWM:");
    let boundary = "XyZbOuNdArY";
    let head = format!(
        "--{boundary}\r\nContent-Disposition: form-data; name=\"heightmap\"; \
         filename=\"m.png\"\r\nContent-Type: image/png\r\n\r\n"
    );
    let tail = format!("\r\n--{boundary}--\r\n");
    let mut first = head.into_bytes();
    first.extend_from_slice(&png_head(8192, 4096));
    let (inner, _) = body(&first, len);
    let stream = futures_util::StreamExt::chain(
        inner.into_data_stream(),
        futures_util::stream::iter([Ok(bytes::Bytes::from(tail.clone()))]),
    );
    let req = Request::post("/v1/bakes")
        .header("content-type", format!("multipart/form-data; boundary={boundary}"))
        .header("content-length", (len + tail.len()).to_string())
        .body(Body::from_stream(stream))
        .unwrap();
    let (s, v) = post(&app, req).await;
    assert_eq!(s, 202, "{v}");
    let grew = status("VmHWM:").saturating_sub(before) as f64 / 1024.0;
    println!("multipart upload of {} MiB: peak +{grew:.1} MiB", len >> 20);
    assert!(grew < 64.0, "the multipart upload raised the peak by {grew:.1} MiB");

    // 3. A raw body of unknown length: the first 64 MiB in memory, then spooled.
    let before = status("VmHWM:");
    let (b, _) = body(&png_head(4096, 8192), len);
    let req = Request::post("/v1/bakes").header("content-type", "image/png").body(b).unwrap();
    let (s, v) = post(&app, req).await;
    assert_eq!(s, 202, "{v}");
    let grew = status("VmHWM:").saturating_sub(before) as f64 / 1024.0;
    println!("raw upload of {} MiB, no Content-Length: peak +{grew:.1} MiB", len >> 20);
    assert!(grew < 160.0, "the upload raised the peak by {grew:.1} MiB");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_spooled_upload_is_probed_from_the_store() {
    // Over the threshold, with dimensions over the limit: spooled, then refused from its header.
    let (st, _dir) = idle_state(|c| c.max_body_bytes = 1 << 30);
    let app = service::app(st);
    let len = horizon_bake::service::upload::STREAM_UPLOAD_ABOVE + (1 << 20);
    let (b, _) = body(&png_head(100_000, 8), len);
    let req = Request::post("/v1/bakes").header("content-type", "image/png").body(b).unwrap();
    let (s, v) = post(&app, req).await;
    assert_eq!(s, 422, "{v}");
    assert!(v["detail"].as_str().unwrap_or("").contains("100000"), "{v}");
    // Accepted with the size and hash of what was sent.
    let (b, hash) = body(&png_head(512, 256), len);
    let req = Request::post("/v1/bakes").header("content-type", "image/png").body(b).unwrap();
    let (s, v) = post(&app, req).await;
    assert_eq!(s, 202, "{v}");
    assert_eq!(v["input"]["content_hash"], hash, "{v}");
    assert_eq!(v["input"]["width"], 512, "{v}");
    assert_eq!(v["input"]["height"], 256, "{v}");
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
