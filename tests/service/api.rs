//! The HTTP API against real servers on 127.0.0.1:0 (and `app(state)` via `oneshot` where a
//! dispatcher must stay idle): submit → poll → download byte-identical to the library, dedup,
//! ETag/304, SSE, every SPEC §5 rejection leaving nothing behind, 429, auth, retention, metrics,
//! and the openapi.yaml ⇔ router check.

use crate::support::*;
use axum::body::Body;
use axum::http::{Request, StatusCode};
use horizon_bake::service::{self, handlers, ROUTES};
use serde_json::Value;
use std::time::{Duration, Instant};
use tower::ServiceExt;

const PAIRS: &[(&str, &str)] = &[("radius", "8"), ("height_scale", "24"), ("y_axis", "down")];

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn submit_poll_download_is_byte_identical_to_the_library() {
    let srv = Server::start(|_| {}).await;
    let c = client();
    let png = terrain_png16(67, 45, 7);
    let want = library_files(&png, PAIRS);
    assert_eq!(want.len(), 8);

    let res = c
        .post(srv.url("/v1/bakes?radius=8&height_scale=24&y_axis=down"))
        .header("content-type", "image/png")
        .body(png.clone())
        .send()
        .await
        .unwrap();
    assert_eq!(res.status(), 202);
    let loc = res.headers()["location"].to_str().unwrap().to_owned();
    let bake: Value = res.json().await.unwrap();
    assert_eq!(loc, format!("/v1/bakes/{}", bake["id"].as_str().unwrap()));
    assert_eq!(bake["status"], "queued");
    assert_eq!(bake["input"]["width"], 67);
    assert_eq!(bake["input"]["content_hash"], blake3::hash(&png).to_hex().as_str());

    // SSE: progress events, then one `done` carrying the final resource.
    let events = c.get(srv.url(&format!("{loc}/events"))).send().await.unwrap();
    assert_eq!(events.headers()["content-type"], "text/event-stream");
    let text = tokio::time::timeout(Duration::from_secs(60), events.text()).await.unwrap().unwrap();
    let done = text.split("\n\n").find(|e| e.contains("event: done")).expect(&text);
    let data = done.lines().find_map(|l| l.strip_prefix("data: ")).unwrap();
    let final_res: Value = serde_json::from_str(data).unwrap();
    assert_eq!(final_res["status"], "succeeded", "{text}");

    let v = wait_done(&c, &srv.url(&loc), Duration::from_secs(60)).await;
    assert_eq!(v["status"], "succeeded", "{v}");
    assert_eq!(v["progress"]["fraction"], 1.0);
    assert_eq!(v["params"]["resolved_radius"]["texels"], 8);
    assert_eq!(v["input"]["bit_depth"], 16);
    assert!(v["timings_ms"]["bake"].as_f64().unwrap() > 0.0);
    assert_eq!(v["attempts"], 1);

    for (name, bytes) in &want {
        let url = srv.url(&format!("{loc}{}", result_path(name)));
        let res = get_result(&c, &url).await;
        assert_eq!(res.status(), 200, "{url}");
        let etag = res.headers()["etag"].to_str().unwrap().to_owned();
        let body = res.bytes().await.unwrap();
        assert!(body[..] == bytes[..], "{name} differs from the library's");
        assert_eq!(etag, format!("\"{}\"", blake3::hash(&body).to_hex()));
        let res = c.get(&url).header("if-none-match", &etag).send().await.unwrap();
        assert_eq!(res.status(), 304);
        assert_eq!(res.headers()["etag"].to_str().unwrap(), etag);
        assert!(res.bytes().await.unwrap().is_empty());
    }
    // Default format is png8.
    let b =
        c.get(srv.url(&format!("{loc}/horizon/1"))).send().await.unwrap().bytes().await.unwrap();
    assert!(b[..] == want["horizon_1.png8"][..]);
    let res = c.get(srv.url(&format!("{loc}/horizon/0?format=jpeg"))).send().await.unwrap();
    assert_eq!(res.status(), 422);

    // The same input and resolved parameters by multipart: the existing bake, 200.
    let form = reqwest::multipart::Form::new()
        .part("heightmap", reqwest::multipart::Part::bytes(png.clone()).file_name("h.png"))
        .text("params", r#"{"radius": 8, "height_scale": "24", "bins": 32}"#);
    // The query and the JSON part merge (a key in both would be a 422: see service_defects).
    let res = c.post(srv.url("/v1/bakes?y_axis=down")).multipart(form).send().await.unwrap();
    assert_eq!(res.status(), 200);
    let again: Value = res.json().await.unwrap();
    assert_eq!(again["id"], bake["id"]);

    // Different parameters: a new bake.
    let res = c
        .post(srv.url("/v1/bakes?radius=4"))
        .header("content-type", "image/png")
        .body(png.clone())
        .send()
        .await
        .unwrap();
    assert_eq!(res.status(), 202);
    let other: Value = res.json().await.unwrap();
    assert_ne!(other["id"], bake["id"]);
    wait_done(
        &c,
        &srv.url(&format!("/v1/bakes/{}", other["id"].as_str().unwrap())),
        Duration::from_secs(60),
    )
    .await;

    // Listing: two bakes, oldest first, paginated, filtered.
    let page: Value =
        c.get(srv.url("/v1/bakes?limit=1")).send().await.unwrap().json().await.unwrap();
    assert_eq!(page["items"].as_array().unwrap().len(), 1);
    assert_eq!(page["items"][0]["id"], bake["id"]);
    let href = page["next"]["href"].as_str().unwrap();
    let page2: Value = c.get(srv.url(href)).send().await.unwrap().json().await.unwrap();
    assert_eq!(page2["items"][0]["id"], other["id"]);
    assert!(page2["next"].is_null());
    let queued: Value =
        c.get(srv.url("/v1/bakes?status=queued")).send().await.unwrap().json().await.unwrap();
    assert_eq!(queued["items"].as_array().unwrap().len(), 0);

    // Metrics saw it.
    let m = c.get(srv.url("/metrics")).send().await.unwrap().text().await.unwrap();
    assert!(m.contains("horizon_bakes{status=\"succeeded\"} 2\n"), "{m}");
    assert!(m.contains("horizon_bakes_finished_total{status=\"succeeded\"} 2\n"), "{m}");
    assert!(m.contains("horizon_bakes_deduplicated_total 1\n"), "{m}");
    assert!(m.contains("horizon_texels_baked_total 6030\n"), "{m}");
    assert!(
        m.contains("route=\"/v1/bakes/{id}/horizon/{layer}\",method=\"GET\",status=\"304\"} 6"),
        "{m}"
    );

    // Delete a finished bake: 204, then 404, and its results are gone.
    let res = c.delete(srv.url(&loc)).send().await.unwrap();
    assert_eq!(res.status(), 204);
    let res = c.get(srv.url(&loc)).send().await.unwrap();
    assert_eq!(res.status(), 404);
    let dir = srv.stop().await;
    // The input blob is shared with the other bake and stays; the deleted bake's own results go.
    // The other bake's results are its two png8 layers: nothing else was asked of it.
    let files = blob_files(dir.path());
    assert_eq!(files.len(), 1 + 2, "{files:?}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_rejection_is_a_problem_and_leaves_nothing_behind() {
    let srv = Server::start(|c| c.max_body_bytes = 64 * 1024).await;
    let c = client();
    let post = |body: Vec<u8>, q: &str, ct: &str| {
        c.post(srv.url(&format!("/v1/bakes{q}"))).header("content-type", ct).body(body).send()
    };

    // A decompression bomb: the header claims 100000×100000. Rejected from the header alone.
    let bomb = bomb_png(100_000, 100_000);
    let mut best = Duration::MAX;
    for _ in 0..3 {
        let t = Instant::now();
        let (status, p) = problem(post(bomb.clone(), "", "image/png").await.unwrap()).await;
        best = best.min(t.elapsed());
        assert_eq!((status, p["code"].as_str().unwrap()), (422, "dimensions_too_large"));
    }
    assert!(best < Duration::from_millis(100), "bomb took {best:?}");

    let (s, p) = problem(post(vec![7u8; 100 * 1024], "", "image/png").await.unwrap()).await;
    assert_eq!((s, p["code"].as_str().unwrap()), (413, "payload_too_large"));
    // Chunked (no Content-Length) is cut off by the limit too. The server answers 413 and
    // closes without reading the rest, so on a loaded machine the client may still be sending
    // and see the connection reset instead of the answer (a race of the transport, not of the
    // server): every answer that arrives must be the 413, and at least one must arrive.
    let mut answered = 0;
    for _ in 0..5 {
        let chunks =
            futures_util::stream::iter((0..9).map(|_| Ok::<_, std::io::Error>(vec![0u8; 8192])));
        let sent = c
            .post(srv.url("/v1/bakes"))
            .header("content-type", "image/png")
            .body(reqwest::Body::wrap_stream(chunks))
            .send()
            .await;
        match sent {
            Ok(res) => {
                assert_eq!(problem(res).await.0, 413);
                answered += 1;
            }
            Err(e) => assert!(e.is_request(), "not a transport reset: {e}"),
        }
    }
    assert!(answered >= 1, "no chunked upload got its 413");

    let jpeg =
        [0xFF, 0xD8, 0xFF, 0xE0, 0, 16, b'J', b'F', b'I', b'F', 0, 1, 1, 0, 0, 1, 0, 1, 0, 0];
    let (s, p) = problem(post(jpeg.to_vec(), "", "image/png").await.unwrap()).await;
    assert_eq!((s, p["code"].as_str().unwrap()), (415, "unsupported_media_type"));
    let (s, _) = problem(post(jpeg.to_vec(), "", "image/jpeg").await.unwrap()).await;
    assert_eq!(s, 415);
    let (s, _) = problem(post(Vec::new(), "", "image/png").await.unwrap()).await;
    assert_eq!(s, 415);

    let png = terrain_png16(8, 8, 1);
    for (q, field) in [
        ("?bins=24", "bins"),
        ("?radius=0", "radius"),
        ("?edge=clamp", "edge"),
        ("?bogus=1", "bogus"),
        ("?outputs=normals", "outputs"),
    ] {
        let (s, p) = problem(post(png.clone(), q, "image/png").await.unwrap()).await;
        assert_eq!((s, p["field"].as_str().unwrap()), (422, field), "{q}: {p}");
        assert_eq!(p["code"], "invalid_parameter");
    }
    let form = reqwest::multipart::Form::new()
        .part("heightmap", reqwest::multipart::Part::bytes(png.clone()))
        .text("params", r#"{"height_scale": -1}"#);
    let (s, p) = problem(c.post(srv.url("/v1/bakes")).multipart(form).send().await.unwrap()).await;
    assert_eq!((s, p["field"].as_str().unwrap()), (422, "height_scale"));
    let form = reqwest::multipart::Form::new().text("params", "{}");
    let (s, p) = problem(c.post(srv.url("/v1/bakes")).multipart(form).send().await.unwrap()).await;
    assert_eq!((s, p["field"].as_str().unwrap()), (422, "heightmap"));

    let (s, p) =
        problem(c.get(srv.url("/v1/bakes/0123456789abcdef0123")).send().await.unwrap()).await;
    assert_eq!((s, p["code"].as_str().unwrap()), (404, "bake_not_found"));
    let (s, p) = problem(c.get(srv.url("/v1/bakes/nope/horizon/0")).send().await.unwrap()).await;
    assert_eq!((s, p["code"].as_str().unwrap()), (404, "bake_not_found"));
    let (s, p) = problem(c.get(srv.url("/v1/nothing")).send().await.unwrap()).await;
    assert_eq!((s, p["code"].as_str().unwrap()), (404, "route_not_found"));
    let (s, p) = problem(c.put(srv.url("/v1/bakes")).send().await.unwrap()).await;
    assert_eq!((s, p["code"].as_str().unwrap()), (405, "method_not_allowed"));
    let (s, p) = problem(c.get(srv.url("/v1/bakes?limit=0")).send().await.unwrap()).await;
    assert_eq!((s, p["field"].as_str().unwrap()), (422, "limit"));
    let (s, p) = problem(c.get(srv.url("/v1/bakes?status=done")).send().await.unwrap()).await;
    assert_eq!((s, p["field"].as_str().unwrap()), (422, "status"));

    let list: Value = c.get(srv.url("/v1/bakes")).send().await.unwrap().json().await.unwrap();
    assert_eq!(list["items"].as_array().unwrap().len(), 0, "a rejection left a record");
    let dir = srv.stop().await;
    assert!(blob_files(dir.path()).is_empty(), "a rejection left a file");
}

async fn oneshot(
    app: &axum::Router,
    req: Request<Body>,
) -> (StatusCode, axum::http::HeaderMap, Vec<u8>) {
    let res = app.clone().oneshot(req).await.unwrap();
    let (parts, body) = res.into_parts();
    let bytes = axum::body::to_bytes(body, usize::MAX).await.unwrap();
    (parts.status, parts.headers, bytes.to_vec())
}

fn submit_req(png: &[u8]) -> Request<Body> {
    Request::post("/v1/bakes")
        .header("content-type", "image/png")
        .body(Body::from(png.to_vec()))
        .unwrap()
}

#[tokio::test]
async fn not_ready_409_queue_full_429_and_cancel_of_a_queued_bake() {
    // No dispatcher: bakes stay queued.
    let (st, _dir) = idle_state(|c| c.queue_capacity = 2);
    let app = service::app(st);
    let mut ids = Vec::new();
    for seed in 0..2 {
        let (s, h, body) = oneshot(&app, submit_req(&terrain_png16(8, 8, seed))).await;
        assert_eq!(s, 202);
        let v: Value = serde_json::from_slice(&body).unwrap();
        assert_eq!(
            h["location"].to_str().unwrap(),
            format!("/v1/bakes/{}", v["id"].as_str().unwrap())
        );
        ids.push(v["id"].as_str().unwrap().to_owned());
    }
    let (s, h, body) = oneshot(&app, submit_req(&terrain_png16(8, 8, 99))).await;
    assert_eq!(s, 429);
    let retry: u64 = h["retry-after"].to_str().unwrap().parse().unwrap();
    assert!(retry >= 1);
    let p: Value = serde_json::from_slice(&body).unwrap();
    assert_eq!(p["code"], "queue_full");
    // A duplicate of a queued bake is still answered 200 when the queue is full.
    let (s, _, body) = oneshot(&app, submit_req(&terrain_png16(8, 8, 0))).await;
    assert_eq!(s, 200);
    assert_eq!(serde_json::from_slice::<Value>(&body).unwrap()["id"], ids[0].as_str());

    let (s, _, body) = oneshot(
        &app,
        Request::get(format!("/v1/bakes/{}/horizon/0", ids[0])).body(Body::empty()).unwrap(),
    )
    .await;
    assert_eq!(s, 409);
    assert_eq!(serde_json::from_slice::<Value>(&body).unwrap()["code"], "result_not_ready");
    let (s, _, body) = oneshot(
        &app,
        Request::get(format!("/v1/bakes/{}/horizon/2", ids[0])).body(Body::empty()).unwrap(),
    )
    .await;
    assert_eq!(s, 422);
    assert_eq!(serde_json::from_slice::<Value>(&body).unwrap()["field"], "layer");

    // Cancel a queued bake: 200, `canceled`, and the queue has room again.
    let (s, _, body) = oneshot(
        &app,
        Request::delete(format!("/v1/bakes/{}", ids[0])).body(Body::empty()).unwrap(),
    )
    .await;
    assert_eq!(s, 200);
    assert_eq!(serde_json::from_slice::<Value>(&body).unwrap()["status"], "canceled");
    let (s, _, _) = oneshot(&app, submit_req(&terrain_png16(8, 8, 99))).await;
    assert_eq!(s, 202);
    // Resubmitting the canceled bake's input makes a new bake rather than returning the canceled one.
    let (s, _, _) = oneshot(&app, submit_req(&terrain_png16(8, 8, 0))).await;
    assert_eq!(s, 429, "queue is full again (2 waiting)");
}

#[tokio::test]
async fn draining_answers_503_on_readyz_and_submit() {
    let (st, _dir) = idle_state(|_| {});
    let app = service::app(st.clone());
    let (s, _, body) = oneshot(&app, Request::get("/readyz").body(Body::empty()).unwrap()).await;
    assert_eq!(s, 200);
    assert_eq!(serde_json::from_slice::<Value>(&body).unwrap()["status"], "ready");
    st.drain().await;
    let (s, h, body) = oneshot(&app, Request::get("/readyz").body(Body::empty()).unwrap()).await;
    assert_eq!(s, 503);
    assert!(h.contains_key("retry-after"));
    assert_eq!(serde_json::from_slice::<Value>(&body).unwrap()["code"], "shutting_down");
    let (s, _, _) = oneshot(&app, submit_req(&terrain_png16(8, 8, 0))).await;
    assert_eq!(s, 503);
    let (s, _, _) = oneshot(&app, Request::get("/healthz").body(Body::empty()).unwrap()).await;
    assert_eq!(s, 200);
}

#[tokio::test]
async fn api_key_guards_v1_but_not_health() {
    let (st, _dir) = idle_state(|c| c.api_key = Some("s3cret".into()));
    let app = service::app(st);
    let get = |path: &str, auth: Option<&str>| {
        let mut r = Request::get(path);
        if let Some(a) = auth {
            r = r.header("authorization", a);
        }
        r.body(Body::empty()).unwrap()
    };
    let (s, h, body) = oneshot(&app, get("/v1/bakes", None)).await;
    assert_eq!(s, 401);
    assert_eq!(h["www-authenticate"], "Bearer");
    assert_eq!(serde_json::from_slice::<Value>(&body).unwrap()["code"], "unauthorized");
    assert_eq!(oneshot(&app, get("/v1/bakes", Some("Bearer wrong"))).await.0, 401);
    assert_eq!(oneshot(&app, get("/v1/bakes", Some("Bearer s3cret"))).await.0, 200);
    assert_eq!(oneshot(&app, get("/v1/cubemap/0", None)).await.0, 401);
    for open in ["/healthz", "/readyz", "/metrics", "/openapi.yaml"] {
        assert_eq!(oneshot(&app, get(open, None)).await.0, 200, "{open}");
    }
}

#[tokio::test]
async fn cubemap_faces_match_the_library() {
    let (st, _dir) = idle_state(|_| {});
    let app = service::app(st);
    let size = 8;
    let all = horizon_bake::kernels::cubemap::cube_factors(size);
    for face in 0..6 {
        let (s, h, body) = oneshot(
            &app,
            Request::get(format!("/v1/cubemap/{face}?size={size}")).body(Body::empty()).unwrap(),
        )
        .await;
        assert_eq!(s, 200);
        let img = image::load_from_memory(&body).unwrap().to_rgba8();
        let n = size * size * 4;
        let want: Vec<u8> = all[face * n..(face + 1) * n]
            .iter()
            .map(|&f| horizon_bake::kernels::cubemap::unorm8(f))
            .collect();
        assert_eq!(img.as_raw(), &want, "face {face}");
        let etag = h["etag"].to_str().unwrap().to_owned();
        let (s, _, _) = oneshot(
            &app,
            Request::get(format!("/v1/cubemap/{face}?size={size}"))
                .header("if-none-match", etag)
                .body(Body::empty())
                .unwrap(),
        )
        .await;
        assert_eq!(s, 304);
    }
    for (path, file) in
        [("/v1/cubemap.ktx2?size=8", "cubemap.ktx2"), ("/v1/cubemap.dds?size=8", "cubemap.dds")]
    {
        let (s, _, body) = oneshot(&app, Request::get(path).body(Body::empty()).unwrap()).await;
        assert_eq!(s, 200);
        let formats =
            horizon_bake::encode::CubeFormats { ktx2: true, dds: true, ..Default::default() };
        let files = horizon_bake::pipeline::cube_files(8, formats).unwrap();
        let want = files.iter().find(|f| f.name == file).unwrap();
        assert!(body == want.bytes, "{path}");
    }
    let (_, _, body) =
        oneshot(&app, Request::get("/v1/cubemap/0").body(Body::empty()).unwrap()).await;
    assert_eq!(image::load_from_memory(&body).unwrap().width(), 16, "default size");
    for (path, field) in [
        ("/v1/cubemap/6", "face"),
        ("/v1/cubemap/0?size=0", "size"),
        ("/v1/cubemap/0?size=99999", "size"),
    ] {
        let (s, _, body) = oneshot(&app, Request::get(path).body(Body::empty()).unwrap()).await;
        assert_eq!(s, 422, "{path}");
        assert_eq!(serde_json::from_slice::<Value>(&body).unwrap()["field"], field);
    }
    // An unknown key on this immutable result is ignored (a cache buster), not a 422.
    let (s, _, body) =
        oneshot(&app, Request::get("/v1/cubemap/0?sise=4").body(Body::empty()).unwrap()).await;
    assert_eq!(s, 200);
    assert_eq!(image::load_from_memory(&body).unwrap().width(), 16, "`sise` is not `size`");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn finished_bakes_are_removed_after_the_retention() {
    let srv = Server::start(|c| {
        c.retention = Duration::ZERO;
        c.sweep_interval = Duration::from_millis(200);
    })
    .await;
    let c = client();
    let res = c
        .post(srv.url("/v1/bakes?radius=2"))
        .header("content-type", "image/png")
        .body(terrain_png16(16, 16, 3))
        .send()
        .await
        .unwrap();
    let loc = res.headers()["location"].to_str().unwrap().to_owned();
    let t = Instant::now();
    loop {
        let res = c.get(srv.url(&loc)).send().await.unwrap();
        if res.status() == 404 {
            break;
        }
        assert!(t.elapsed() < Duration::from_secs(30), "not removed");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    // The record goes first (a GET must never find a record whose blobs are gone), its blobs
    // a moment later in the same sweep; a stop landing in between waits for the sweep to finish
    // (CI once saw the blobs left behind, before the drain waited for it; the test
    // `a_drain_waits_for_a_retention_sweep_in_flight` makes that case happen every time).
    let dir = srv.stop().await;
    assert!(blob_files(dir.path()).is_empty(), "{:?}", blob_files(dir.path()));
}

/// A blob store whose deletes wait for the test to open a gate (an S3 round trip, a slow disk,
/// held as long as the test needs), so a retention sweep is still removing a bake's blobs when
/// the server drains, however loaded the machine is. A delete gives up waiting after 60 s.
struct SlowDeletes(horizon_bake::jobs::blob::FsBlobStore, std::sync::Arc<Gate>);

#[derive(Default)]
struct Gate {
    open: std::sync::Mutex<bool>,
    opened: std::sync::Condvar,
    /// Set once a delete is waiting at the gate.
    entered: std::sync::atomic::AtomicBool,
}

impl Gate {
    fn open(&self) {
        *self.open.lock().unwrap() = true;
        self.opened.notify_all();
    }
    fn wait(&self) {
        self.entered.store(true, std::sync::atomic::Ordering::SeqCst);
        let g = self.open.lock().unwrap();
        let _g = self.opened.wait_timeout_while(g, Duration::from_secs(60), |open| !*open).unwrap();
    }
}

impl horizon_bake::jobs::blob::BlobStore for SlowDeletes {
    fn writer(&self) -> horizon_bake::error::Result<Box<dyn horizon_bake::jobs::blob::BlobWriter>> {
        self.0.writer()
    }
    fn put(
        &self,
        bytes: &[u8],
        pin: horizon_bake::jobs::blob::PinHook<'_>,
    ) -> horizon_bake::error::Result<String> {
        self.0.put(bytes, pin)
    }
    fn get(&self, hash: &str) -> horizon_bake::error::Result<Option<Vec<u8>>> {
        self.0.get(hash)
    }
    fn contains(&self, hash: &str) -> horizon_bake::error::Result<bool> {
        self.0.contains(hash)
    }
    fn delete(&self, hash: &str) -> horizon_bake::error::Result<()> {
        self.1.wait();
        self.0.delete(hash)
    }
    fn list(&self) -> horizon_bake::error::Result<Vec<(String, u64)>> {
        self.0.list()
    }
    fn open(
        &self,
        hash: &str,
    ) -> horizon_bake::error::Result<Option<(u64, Box<dyn std::io::Read + Send>)>> {
        self.0.open(hash)
    }
}

/// A drain waits for a retention sweep in flight: the bake whose record the sweep removed
/// loses its blobs before the drain returns (the process exits then), rather than keeping
/// them until a later start's orphan sweep. Before the fix the sweeper was a detached task and
/// the drain returned with the blobs still there.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_drain_waits_for_a_retention_sweep_in_flight() {
    use horizon_bake::jobs::{blob::FsBlobStore, repo::EmbeddedRepo};
    use std::sync::Arc;
    let dir = tempfile::tempdir().unwrap();
    let mut config = horizon_bake::service::config::Config::for_dir(dir.path()).unwrap();
    config.bake_threads = 1;
    config.retention = Duration::ZERO;
    config.sweep_interval = Duration::from_millis(100);
    let repo = Arc::new(EmbeddedRepo::open(&dir.path().join("bakes.redb")).unwrap());
    let gate = Arc::new(Gate::default());
    let store = FsBlobStore::open(&dir.path().join("blobs")).unwrap();
    let blobs = Arc::new(SlowDeletes(store, gate.clone()));
    let st = service::AppState::with_stores(config, repo, blobs).unwrap();
    st.start().await.unwrap();
    let app = service::app(st.clone());
    let (s, h, _) = oneshot(&app, submit_req(&terrain_png16(16, 16, 3))).await;
    assert_eq!(s, 202);
    let loc = h["location"].to_str().unwrap().to_owned();
    let t = Instant::now();
    let mut last = String::new();
    loop {
        let (s, _, body) = oneshot(&app, Request::get(&loc).body(Body::empty()).unwrap()).await;
        if s == 404 {
            break;
        }
        last = String::from_utf8_lossy(&body).chars().take(400).collect();
        assert!(t.elapsed() < Duration::from_secs(30), "not removed");
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    // The record is gone and its blobs wait at the gate: the sweep is in flight.
    let left = blob_files(dir.path()).len();
    assert!(
        left > 1,
        "the sweep should still be deleting: {left} blob files left; last seen {last}"
    );
    let drain = tokio::spawn({
        let st = st.clone();
        async move { st.drain().await }
    });
    tokio::time::sleep(Duration::from_millis(300)).await;
    assert!(!drain.is_finished(), "the drain returned with the sweep still deleting");
    gate.open();
    tokio::time::timeout(Duration::from_secs(60), drain).await.unwrap().unwrap();
    assert!(blob_files(dir.path()).is_empty(), "{:?}", blob_files(dir.path()));
}

/// A blob deletion holds the embedded repository's mutex across its store calls (here, at the
/// gate); the calls that need that mutex meanwhile must wait off the runtime. They used to take
/// it on the runtime thread, so on this one-thread runtime nothing else ran, timers included,
/// until the deletion ended (60 s, the gate's timeout). With two runtime threads it took two
/// such calls: the flake of the drain test above, whose 10 ms poll slept through the sweep.
#[tokio::test(flavor = "current_thread")]
async fn a_slow_blob_deletion_does_not_stall_the_runtime() {
    use horizon_bake::jobs::blob::{BlobStore, FsBlobStore};
    use horizon_bake::jobs::repo::{EmbeddedRepo, JobRepo};
    use std::sync::atomic::Ordering;
    use std::sync::Arc;
    let dir = tempfile::tempdir().unwrap();
    let repo = Arc::new(EmbeddedRepo::open(&dir.path().join("bakes.redb")).unwrap());
    let gate = Arc::new(Gate::default());
    let store = FsBlobStore::open(&dir.path().join("blobs")).unwrap();
    let blobs: Arc<dyn BlobStore> = Arc::new(SlowDeletes(store, gate.clone()));
    let (gone, kept) = ("a".repeat(64), "b".repeat(64));
    let deleting = tokio::spawn({
        let (repo, blobs, gone) = (repo.clone(), blobs.clone(), gone.clone());
        async move { repo.delete_blobs_if_unused(vec![gone], blobs).await }
    });
    let t = Instant::now();
    while !gate.entered.load(Ordering::SeqCst) {
        assert!(t.elapsed() < Duration::from_secs(30), "the deletion never reached the store");
        tokio::time::sleep(Duration::from_millis(1)).await;
    }
    // The deletion holds the mutex: pins, tile reads and releases queue behind it.
    let waiting = tokio::spawn({
        let (repo, kept) = (repo.clone(), kept.clone());
        async move {
            repo.pin_blob(&kept, "upload-1").await?;
            let tiles = repo.tiles("no-such-bake").await?;
            let held = repo.release_pins("upload-1").await?;
            Ok::<_, horizon_bake::error::Error>((tiles.len(), held))
        }
    });
    let t = Instant::now();
    tokio::time::sleep(Duration::from_millis(20)).await;
    let slept = t.elapsed();
    let overtook = waiting.is_finished();
    gate.open();
    assert!(slept < Duration::from_secs(10), "a 20 ms sleep took {slept:?}: the runtime stalled");
    assert!(!overtook, "the pin went past a deletion holding the mutex");
    assert_eq!(deleting.await.unwrap().unwrap(), 1);
    assert_eq!(waiting.await.unwrap().unwrap(), (0, vec![kept]));
}

#[test]
fn openapi_matches_the_router() {
    let doc: Value = serde_yaml_ng::from_str(handlers::OPENAPI_YAML).unwrap();
    assert_eq!(doc["openapi"], "3.1.0");
    let paths = doc["paths"].as_object().unwrap();
    let methods = ["get", "post", "put", "patch", "delete", "head", "options"];
    let mut spec: Vec<(String, Vec<String>)> = paths
        .iter()
        .map(|(p, item)| {
            let mut m: Vec<String> = methods
                .iter()
                .filter(|m| item.get(**m).is_some())
                .map(|m| m.to_uppercase())
                .collect();
            m.sort();
            (p.clone(), m)
        })
        .collect();
    spec.sort();
    let mut routes: Vec<(String, Vec<String>)> = ROUTES
        .iter()
        .map(|(p, ms)| {
            let mut m: Vec<String> = ms.iter().map(|s| s.to_string()).collect();
            m.sort();
            (p.to_string(), m)
        })
        .collect();
    routes.sort();
    assert_eq!(spec, routes, "openapi.yaml and service::ROUTES differ");
}

#[tokio::test]
async fn router_serves_exactly_the_declared_routes() {
    // Every ROUTES entry answers its methods (anything but route_not_found / 405) and refuses the
    // others with 405, so ROUTES (checked against openapi.yaml above) is the router's truth.
    let (st, _dir) = idle_state(|_| {});
    let app = service::app(st);
    for (path, methods) in ROUTES {
        let concrete = path
            .replace("{id}", "0123456789abcdef0123")
            .replace("{layer}", "0")
            .replace("{face}", "0")
            .replace("{asset}", "app.js")
            .replace("{file}", "horizon.glsl");
        for m in ["GET", "POST", "PUT", "PATCH", "DELETE"] {
            let req = Request::builder().method(m).uri(&concrete).body(Body::empty()).unwrap();
            let (s, _, body) = oneshot(&app, req).await;
            let code = serde_json::from_slice::<Value>(&body)
                .ok()
                .and_then(|v| v["code"].as_str().map(str::to_owned))
                .unwrap_or_default();
            if methods.contains(&m) {
                assert!(s != 405 && code != "route_not_found", "{m} {path}: {s} {code}");
            } else {
                assert_eq!(s, 405, "{m} {path} should not be routed");
            }
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn fourier_outputs_match_the_cli_function() {
    use horizon_bake::params::BakeParams;
    let srv = Server::start(|_| {}).await;
    let c = client();
    let png = terrain_png16(40, 33, 21);
    let pairs = [("radius", "6"), ("outputs", "fourier"), ("fourier_terms", "7")];
    let params = BakeParams::from_pairs(pairs).unwrap();
    let (map, _) =
        horizon_bake::heightmap::decode(&png, params.channel, &Default::default()).unwrap();
    let (want, _) = horizon_bake::pipeline::fourier_files(
        &map,
        &params,
        &horizon_bake::progress::Progress::new(),
    )
    .unwrap();
    assert_eq!(want.len(), 3);
    let res = c
        .post(srv.url("/v1/bakes?radius=6&outputs=fourier&fourier_terms=7"))
        .header("content-type", "image/png")
        .body(png)
        .send()
        .await
        .unwrap();
    assert_eq!(res.status(), 202);
    let loc = res.headers()["location"].to_str().unwrap().to_owned();
    let v = wait_done(&c, &srv.url(&loc), Duration::from_secs(60)).await;
    assert_eq!(v["status"], "succeeded", "{v}");
    assert_eq!(v["links"]["fourier_2"], format!("{loc}/fourier/2"));
    assert!(v["links"].get("horizon_0").is_none());
    for (k, f) in want.iter().enumerate() {
        let res = c.get(srv.url(&format!("{loc}/fourier/{k}"))).send().await.unwrap();
        assert_eq!(res.status(), 200);
        let body = res.bytes().await.unwrap();
        assert!(body[..] == f.bytes[..], "{} differs", f.name);
    }
    // Not asked for: 409 with a code that says so.
    let res = c.get(srv.url(&format!("{loc}/horizon/0"))).send().await.unwrap();
    assert_eq!(res.status(), 409);
    let p: Value = res.json().await.unwrap();
    assert_eq!(p["code"], "result_not_requested");
    let res = c.get(srv.url(&format!("{loc}/fourier/3"))).send().await.unwrap();
    assert_eq!(res.status(), 422);
    srv.stop().await;
}

/// Decodes a PNG answer to (width, height, RGBA8).
fn rgba_of(png: &[u8]) -> (usize, usize, Vec<u8>) {
    let img = image::load_from_memory_with_format(png, image::ImageFormat::Png).unwrap().to_rgba8();
    (img.width() as usize, img.height() as usize, img.into_raw())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn preview_renders_the_bake_like_the_library() {
    use horizon_bake::params::BakeParams;
    use horizon_bake::preview::{self, PreviewParams};
    use horizon_bake::progress::Progress;
    let srv = Server::start(|_| {}).await;
    let c = client();
    let (s, p) = problem(
        c.get(srv.url("/v1/bakes/0123456789abcdef0123/preview?azimuth=30")).send().await.unwrap(),
    )
    .await;
    assert_eq!((s, p["code"].as_str().unwrap()), (404, "bake_not_found"));

    let (w, h) = (40, 30);
    let png = terrain_png16(w, h, 5);
    let res = c
        .post(srv.url("/v1/bakes?radius=8&height_scale=24&y_axis=down"))
        .header("content-type", "image/png")
        .body(png.clone())
        .send()
        .await
        .unwrap();
    assert_eq!(res.status(), 202);
    let loc = res.headers()["location"].to_str().unwrap().to_owned();
    let v = wait_done(&c, &srv.url(&loc), Duration::from_secs(60)).await;
    assert_eq!(v["status"], "succeeded", "{v}");

    let bake = BakeParams::from_pairs(PAIRS.iter().copied()).unwrap();
    let (map, _) =
        horizon_bake::heightmap::decode(&png, bake.channel, &Default::default()).unwrap();
    let library = |pairs: &[(&str, &str)]| {
        let pp = PreviewParams::from_pairs(pairs.iter().copied()).unwrap();
        preview::render_baking(&map, &bake, &pp, &Progress::new()).unwrap()
    };
    let get = |query: &str| c.get(srv.url(&format!("{loc}/preview?{query}"))).send();

    // Native size, then `size` scaling the longer side; pixels identical to the library's.
    for (query, pairs, dims) in [
        (
            "azimuth=30&elevation=15&shading=horizon",
            &[("azimuth", "30"), ("elevation", "15"), ("shading", "horizon")][..],
            (w, h),
        ),
        (
            "azimuth=200&elevation=25&shading=difference&size=80",
            &[("azimuth", "200"), ("elevation", "25"), ("shading", "difference"), ("size", "80")][..],
            (80, 60),
        ),
    ] {
        let res = get(query).await.unwrap();
        assert_eq!(res.status(), 200, "{query}");
        assert_eq!(res.headers()["content-type"], "image/png");
        let (gw, gh, got) = rgba_of(&res.bytes().await.unwrap());
        assert_eq!((gw, gh), dims, "{query}");
        let want = library(pairs);
        assert_eq!((want.width, want.height), dims);
        assert!(got == want.rgba, "{query}: pixels differ from preview::render_baking");
    }
    // Different light, different picture (the query is really applied).
    let a = rgba_of(&get("azimuth=0").await.unwrap().bytes().await.unwrap()).2;
    let b = rgba_of(&get("azimuth=180").await.unwrap().bytes().await.unwrap()).2;
    assert_ne!(a, b);

    // A contact sheet of 4 tiles of 20×15: 2×2 cells of (tile + 4 px gap) × (tile + label
    // 7 px + 2×4 px + 4 px gap), plus the 4 px outer gap: 52×72.
    let res = get("contact_sheet=4&size=20&elevation=20").await.unwrap();
    assert_eq!(res.status(), 200);
    let (sw, sh, sheet) = rgba_of(&res.bytes().await.unwrap());
    assert_eq!((sw, sh), (4 + 2 * (20 + 4), 4 + 2 * (15 + 7 + 8 + 4)));
    let want = library(&[("contact_sheet", "4"), ("size", "20"), ("elevation", "20")]);
    assert_eq!((want.width, want.height), (sw, sh));
    assert!(sheet == want.rgba, "the contact sheet differs from the library's");

    // Bad parameters: 422 naming the field, unknown keys included.
    for (query, field) in [
        ("azimuth=abc", "azimuth"),
        ("bogus=1", "bogus"),
        ("elevation=95", "elevation"),
        ("contact_sheet=65", "contact_sheet"),
        ("size=4096&contact_sheet=64", "size"),
        ("azimuth=1&azimuth=2", "azimuth"),
    ] {
        let (s, p) = problem(get(query).await.unwrap()).await;
        assert_eq!((s, p["field"].as_str().unwrap()), (422, field), "{query}: {p}");
        assert_eq!(p["code"], "invalid_parameter");
    }
    srv.stop().await;
}

#[tokio::test]
async fn preview_of_an_unfinished_bake_is_409() {
    let (st, _dir) = idle_state(|_| {});
    let app = service::app(st);
    let (s, _, body) = oneshot(&app, submit_req(&terrain_png16(8, 8, 3))).await;
    assert_eq!(s, 202);
    let id = serde_json::from_slice::<Value>(&body).unwrap()["id"].as_str().unwrap().to_owned();
    let (s, h, body) = oneshot(
        &app,
        Request::get(format!("/v1/bakes/{id}/preview?azimuth=30")).body(Body::empty()).unwrap(),
    )
    .await;
    assert_eq!(s, 409);
    assert_eq!(h["content-type"], "application/problem+json");
    assert_eq!(serde_json::from_slice::<Value>(&body).unwrap()["code"], "result_not_ready");
    let (s, _, _) = oneshot(
        &app,
        Request::get("/v1/bakes/0123456789abcdef0123/preview").body(Body::empty()).unwrap(),
    )
    .await;
    assert_eq!(s, 404);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn heights_are_the_scaled_input_for_a_viewer() {
    // What the web page rebuilds its normals from: the decoded input, channel picked,
    // height_scale applied, little-endian f32, row 0 first, in any status.
    let srv = Server::start(|_| {}).await;
    let c = client();
    let png = terrain_png16(37, 23, 11);
    let res = c
        .post(srv.url("/v1/bakes?radius=4&height_scale=24"))
        .header("content-type", "image/png")
        .body(png.clone())
        .send()
        .await
        .unwrap();
    assert_eq!(res.status(), 202);
    let loc = res.headers()["location"].to_str().unwrap().to_owned();
    let (map, _) = horizon_bake::heightmap::decode(
        &png,
        horizon_bake::params::Channel::Luma,
        &Default::default(),
    )
    .unwrap();
    let want: Vec<u8> = map.scaled(24.0).iter().flat_map(|v| v.to_le_bytes()).collect();
    let res = c.get(srv.url(&format!("{loc}/heights"))).send().await.unwrap();
    assert_eq!(res.status(), 200);
    assert_eq!(res.headers()["content-type"], "application/octet-stream");
    assert_eq!(res.headers()["x-width"], "37");
    assert_eq!(res.headers()["x-height"], "23");
    let etag = res.headers()["etag"].to_str().unwrap().to_owned();
    let body = res.bytes().await.unwrap();
    assert_eq!(body.len(), 37 * 23 * 4);
    assert!(body[..] == want[..], "heights differ from the decoded, scaled input");
    // The values really are scaled: the 16-bit terrain spans most of [0, 1].
    let max =
        body.chunks_exact(4).map(|b| f32::from_le_bytes(b.try_into().unwrap())).fold(0.0, f32::max);
    assert!(max > 12.0 && max <= 24.0, "{max}");
    let res = c
        .get(srv.url(&format!("{loc}/heights")))
        .header("if-none-match", &etag)
        .send()
        .await
        .unwrap();
    assert_eq!(res.status(), 304);
    // Another height_scale is another resource with another ETag.
    let res = c
        .post(srv.url("/v1/bakes?radius=4&height_scale=2"))
        .header("content-type", "image/png")
        .body(png)
        .send()
        .await
        .unwrap();
    let loc2 = res.headers()["location"].to_str().unwrap().to_owned();
    let res = c.get(srv.url(&format!("{loc2}/heights"))).send().await.unwrap();
    assert_ne!(res.headers()["etag"].to_str().unwrap(), etag);
    let first = f32::from_le_bytes(res.bytes().await.unwrap()[..4].try_into().unwrap());
    assert_eq!(first, (map.values[0] as f64 * 2.0) as f32);
    let res = c.get(srv.url("/v1/bakes/nosuchbake/heights")).send().await.unwrap();
    assert_eq!(res.status(), 404);
}

#[tokio::test]
async fn web_page_is_built_in_knows_the_limits_and_turns_off() {
    let (st, _dir) = idle_state(|c| {
        c.limits.max_dim = 1234;
        c.api_key = Some("k".into());
    });
    let app = service::app(st);
    let (s, h, body) = oneshot(&app, Request::get("/").body(Body::empty()).unwrap()).await;
    assert_eq!(s, 200);
    assert_eq!(h["content-type"], "text/html; charset=utf-8");
    let html = String::from_utf8(body).unwrap();
    assert!(!html.contains("__HORIZON_CONFIG__"));
    assert!(html.contains("\"max_dim\":1234"), "{html}");
    // The page is open (it asks for the key itself); the API behind it is not.
    assert!(html.contains("\"auth_required\":true"));
    for (name, content_type, builtin) in service::ui::ASSETS {
        let (s, h, body) =
            oneshot(&app, Request::get(format!("/ui/{name}")).body(Body::empty()).unwrap()).await;
        assert_eq!(s, 200, "{name}");
        assert_eq!(h["content-type"], *content_type);
        assert_eq!(body, builtin.as_bytes());
    }
    let (s, _, body) =
        oneshot(&app, Request::get("/ui/nope.js").body(Body::empty()).unwrap()).await;
    assert_eq!(s, 404);
    assert!(String::from_utf8_lossy(&body).contains("ui_asset_not_found"));
    let (s, _, _) = oneshot(&app, Request::get("/v1/bakes").body(Body::empty()).unwrap()).await;
    assert_eq!(s, 401);

    let (st, _dir) = idle_state(|c| c.no_ui = true);
    let app = service::app(st);
    for path in ["/", "/ui/app.js"] {
        let (s, _, body) = oneshot(&app, Request::get(path).body(Body::empty()).unwrap()).await;
        assert_eq!(s, 404, "{path}");
        assert!(String::from_utf8_lossy(&body).contains("ui_disabled"));
    }
    let (s, _, _) = oneshot(&app, Request::get("/healthz").body(Body::empty()).unwrap()).await;
    assert_eq!(s, 200);
}

#[tokio::test]
async fn ui_dir_serves_the_page_from_disk() {
    let ui = tempfile::tempdir().unwrap();
    std::fs::write(ui.path().join("index.html"), "<p>__HORIZON_CONFIG__</p>").unwrap();
    std::fs::write(ui.path().join("app.js"), "export const x = 1;").unwrap();
    let dir = ui.path().to_owned();
    let (st, _dir) = idle_state(move |c| c.ui_dir = Some(dir));
    let app = service::app(st);
    let (s, _, body) = oneshot(&app, Request::get("/").body(Body::empty()).unwrap()).await;
    assert_eq!(s, 200);
    let text = String::from_utf8(body).unwrap();
    assert!(text.starts_with("<p>{\"version\":"), "{text}");
    let (_, _, body) = oneshot(&app, Request::get("/ui/app.js").body(Body::empty()).unwrap()).await;
    assert_eq!(body, b"export const x = 1;");
    // Only the page's own files are served from it, never another path in that directory.
    std::fs::write(ui.path().join("secret.txt"), "no").unwrap();
    let (s, _, _) =
        oneshot(&app, Request::get("/ui/secret.txt").body(Body::empty()).unwrap()).await;
    assert_eq!(s, 404);
    let (s, _, _) =
        oneshot(&app, Request::get("/ui/..%2Fsecret.txt").body(Body::empty()).unwrap()).await;
    assert_eq!(s, 404);
}

/// Issue 44: openness (positive and negative) over HTTP is the library's GeoTIFFs; to the
/// edge of the map (radius unlimited, no max_distance) it is refused naming max_distance.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn openness_over_http() {
    use horizon_bake::params::BakeParams;
    let srv = Server::start(|_| {}).await;
    let c = client();
    let png = terrain_png16(31, 23, 44);
    let q = "method=exact&radius=5&edge=none&outputs=openness&bins=8";
    let params = BakeParams::from_pairs(q.split('&').filter_map(|kv| kv.split_once('='))).unwrap();
    let (map, _) =
        horizon_bake::heightmap::decode(&png, params.channel, &Default::default()).unwrap();
    let progress = horizon_bake::progress::Progress::new();
    let (want, _, _) =
        horizon_bake::pipeline::terrain_files(&map, None, &params, &progress).unwrap();
    assert_eq!(want.len(), 2);
    let loc = submit_ok(&c, &srv, &png, &format!("?{q}")).await;
    let v = wait_done(&c, &srv.url(&loc), Duration::from_secs(60)).await;
    assert_eq!(v["status"], "succeeded", "{v}");
    for name in ["openness_positive", "openness_negative"] {
        assert_eq!(v["links"][name], format!("{loc}/{name}"), "{v}");
        let res = c.get(srv.url(&format!("{loc}/{name}"))).send().await.unwrap();
        assert_eq!(res.status(), 200, "{name}");
        let body = res.bytes().await.unwrap();
        let f = want.iter().find(|f| f.name == format!("{name}.tif")).unwrap();
        assert!(body[..] == f.bytes[..], "{name}.tif differs from the library's");
    }
    let res = c
        .post(srv.url("/v1/bakes?method=exact&radius=unlimited&outputs=openness"))
        .header("content-type", "image/png")
        .body(png)
        .send()
        .await
        .unwrap();
    assert_eq!(res.status(), 422);
    let p: Value = res.json().await.unwrap();
    assert_eq!(p["field"], "max_distance", "{p}");
    srv.stop().await;
}

/// Issue 44: sun hours and insolation over HTTP are the library's GeoTIFFs; a plain image (no
/// projection to place the sun) without latitude/longitude is refused at submission naming
/// latitude, and a sum without a day naming date.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sun_hours_and_insolation_over_http() {
    use horizon_bake::params::BakeParams;
    let srv = Server::start(|_| {}).await;
    let c = client();
    let png = terrain_png16(29, 21, 45);
    let q = "method=exact&radius=8&edge=none&height_scale=20&outputs=sun_hours,insolation\
             &date=2026-03-20&time_step_minutes=30&latitude=46.5&longitude=8.0";
    let params = BakeParams::from_pairs(q.split('&').filter_map(|kv| kv.split_once('='))).unwrap();
    let (map, _) =
        horizon_bake::heightmap::decode(&png, params.channel, &Default::default()).unwrap();
    let progress = horizon_bake::progress::Progress::new();
    let (want, _, _) =
        horizon_bake::pipeline::terrain_files(&map, None, &params, &progress).unwrap();
    assert_eq!(want.len(), 2);
    let loc = submit_ok(&c, &srv, &png, &format!("?{q}")).await;
    let v = wait_done(&c, &srv.url(&loc), Duration::from_secs(60)).await;
    assert_eq!(v["status"], "succeeded", "{v}");
    for name in ["sun_hours", "insolation"] {
        assert_eq!(v["links"][name], format!("{loc}/{name}"), "{v}");
        let res = c.get(srv.url(&format!("{loc}/{name}"))).send().await.unwrap();
        assert_eq!(res.status(), 200, "{name}");
        let body = res.bytes().await.unwrap();
        let f = want.iter().find(|f| f.name == format!("{name}.tif")).unwrap();
        assert!(body[..] == f.bytes[..], "{name}.tif differs from the library's");
    }
    for (query, field) in [
        ("method=exact&outputs=sun_hours&date=2026-03-20", "latitude"),
        ("method=exact&outputs=sun_hours&latitude=46&longitude=8", "date"),
        ("method=exact&outputs=insolation&date=2026-03-20&latitude=46", "longitude"),
        ("method=exact&outputs=sun_hours&date_from=2026-03-20&date_to=2027-06-01&latitude=46&longitude=8", "date_to"),
        ("method=exact&outputs=sun_hours&date=2026-03-20&time_step_minutes=7&latitude=46&longitude=8", "time_step_minutes"),
    ] {
        let res = c
            .post(srv.url(&format!("/v1/bakes?{query}")))
            .header("content-type", "image/png")
            .body(png.clone())
            .send()
            .await
            .unwrap();
        assert_eq!(res.status(), 422, "{query}");
        let p: Value = res.json().await.unwrap();
        assert_eq!(p["field"], field, "{query}: {p}");
    }
    srv.stop().await;
}

/// Issue 24: a bake with `outputs=angles,svf` (and issue 44's `horizon_distance`) serves the
/// same GeoTIFFs as the library writes; shadow and profile are computed on request.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn terrain_products_over_http() {
    use horizon_bake::params::BakeParams;
    let srv = Server::start(|_| {}).await;
    let c = client();
    let png = terrain_png16(37, 29, 24);
    let q = "method=exact&radius=unlimited&edge=none&outputs=angles,svf,horizon_distance&bins=12\
             &svf_model=visual";
    let params = BakeParams::from_pairs(q.split('&').filter_map(|kv| kv.split_once('='))).unwrap();
    let (map, _) =
        horizon_bake::heightmap::decode(&png, params.channel, &Default::default()).unwrap();
    let progress = horizon_bake::progress::Progress::new();
    let (want, _, _) =
        horizon_bake::pipeline::terrain_files(&map, None, &params, &progress).unwrap();
    let res = c
        .post(srv.url(&format!("/v1/bakes?{q}")))
        .header("content-type", "image/png")
        .body(png)
        .send()
        .await
        .unwrap();
    assert_eq!(res.status(), 202);
    let loc = res.headers()["location"].to_str().unwrap().to_owned();
    let v = wait_done(&c, &srv.url(&loc), Duration::from_secs(60)).await;
    assert_eq!(v["status"], "succeeded", "{v}");
    assert_eq!(v["links"]["horizon_distance"], format!("{loc}/horizon_distance"), "{v}");
    for (route, file) in
        [("angles", "angles.tif"), ("svf", "svf.tif"), ("horizon_distance", "horizon_distance.tif")]
    {
        let res = c.get(srv.url(&format!("{loc}/{route}"))).send().await.unwrap();
        assert_eq!(res.status(), 200);
        assert_eq!(res.headers()["content-type"], "image/tiff");
        let body = res.bytes().await.unwrap();
        let f = want.iter().find(|f| f.name == file).unwrap();
        assert!(body[..] == f.bytes[..], "{file} differs from the library's");
    }
    // The shadow: a sun at 90° elevation lights every texel; a 1° sun from the east shadows some.
    let res = c
        .get(srv.url(&format!("{loc}/shadow?sun_azimuth=0&sun_elevation=90")))
        .send()
        .await
        .unwrap();
    assert_eq!(res.status(), 200);
    let etag = res.headers()["etag"].to_str().unwrap().to_owned();
    let body = res.bytes().await.unwrap();
    let mut dec = tiff::decoder::Decoder::new(std::io::Cursor::new(&body[..])).unwrap();
    match dec.read_image().unwrap() {
        tiff::decoder::DecodingResult::U8(v) => assert!(v.iter().all(|&b| b == 1)),
        other => panic!("shadow.tif is not uint8: {other:?}"),
    }
    let res = c
        .get(srv.url(&format!("{loc}/shadow?sun_azimuth=0&sun_elevation=90")))
        .header("if-none-match", etag)
        .send()
        .await
        .unwrap();
    assert_eq!(res.status(), 304);
    let res = c.get(srv.url(&format!("{loc}/shadow?sun_elevation=10"))).send().await.unwrap();
    assert_eq!(res.status(), 422);
    // The profile, JSON and CSV, against the library.
    let want = horizon_bake::bake::horizon_profile(&map, &params, 5, 7, 24).unwrap();
    let res = c.get(srv.url(&format!("{loc}/profile?x=5&y=7&bins=24"))).send().await.unwrap();
    assert_eq!(res.status(), 200);
    let p: Value = res.json().await.unwrap();
    let got: Vec<f64> =
        p["profile"].as_array().unwrap().iter().map(|e| e["elevation"].as_f64().unwrap()).collect();
    assert_eq!(got.len(), 24);
    for (g, w) in got.iter().zip(&want) {
        // JSON numbers round-trip to within an ulp or two.
        assert!((g - w.1).abs() < 1e-9, "{g} vs {}", w.1);
    }
    let res = c
        .get(srv.url(&format!("{loc}/profile?x=5&y=7&bins=24")))
        .header("accept", "text/csv")
        .send()
        .await
        .unwrap();
    assert_eq!(res.headers()["content-type"], "text/csv");
    assert_eq!(res.text().await.unwrap(), horizon_bake::terrain::profile::to_csv(&want));
    let res = c.get(srv.url(&format!("{loc}/profile?x=99&y=7"))).send().await.unwrap();
    assert_eq!(res.status(), 422);
    srv.stop().await;
}

/// A 24×20 float32 GeoTIFF DEM in EPSG:32632 with 30 m cells: a ridge running north-south in
/// metres, nodata -9999, its heights first passed to `edit`.
fn ridge_geotiff(edit: impl FnOnce(&mut [f32])) -> Vec<u8> {
    use horizon_bake::encode::geotiff;
    use horizon_bake::heightmap::georef::Georef;
    let (w, h) = (24usize, 20usize);
    let mut dem: Vec<f32> = (0..w * h)
        .map(|k| {
            let (x, y) = ((k % w) as f32, (k / w) as f32);
            400.0 + 300.0 * (-(x - 12.0).powi(2) / 8.0).exp() + 2.0 * y
        })
        .collect();
    edit(&mut dem);
    let g = Georef {
        pixel_scale: Some(vec![30.0, 30.0, 0.0]),
        tiepoints: Some(vec![0.0, 0.0, 0.0, 500000.0, 5500000.0, 0.0]),
        geo_keys: Some(vec![1, 1, 0, 3, 1024, 0, 1, 1, 3072, 0, 1, 32632, 3076, 0, 1, 9001]),
        ..Georef::default()
    };
    let band = [geotiff::Band { plane: &dem, description: "dem".into() }];
    geotiff::encode(w, h, &band, Some(&g), -9999.0).unwrap()
}

/// SPEC §2: a DEM posted without `method` and `radius` is baked by a line of sight to the edge
/// (`sweep`, curvature on), and `bins` for angles alone may be any count, as for every ray
/// method; a PNG keeps `lengyel` at 16 texels, and its `bins` must then be a multiple of 16
/// (a 422 naming `bins`). Before, the DEM was baked by `lengyel` at 16 texels.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_dem_without_method_bakes_a_line_of_sight() {
    let srv = Server::start(|_| {}).await;
    let c = client();
    let tif = ridge_geotiff(|_| ());
    let post = |q: &'static str, body: Vec<u8>, ty: &'static str| {
        let c = c.clone();
        let url = srv.url(&format!("/v1/bakes?{q}"));
        async move { c.post(url).header("content-type", ty).body(body).send().await.unwrap() }
    };
    let res = post("outputs=angles,svf&bins=36", tif, "image/tiff").await;
    assert_eq!(res.status(), 202);
    let loc = res.headers()["location"].to_str().unwrap().to_owned();
    let v: Value = res.json().await.unwrap();
    let p = &v["params"];
    assert_eq!(
        (&p["method"], &p["radius"]),
        (&serde_json::json!("sweep"), &serde_json::json!("unlimited")),
        "{v}"
    );
    assert_eq!(p["earth_curvature"], "on", "{v}");
    let v = wait_done(&c, &srv.url(&loc), Duration::from_secs(60)).await;
    assert_eq!(v["status"], "succeeded", "{v}");
    assert_eq!(v["params"]["method"], "sweep", "{v}");
    // The resource links what it holds: the terrain products, no horizon layers.
    assert_eq!(v["links"]["angles"], format!("{loc}/angles"), "{v}");
    assert_eq!(v["links"]["svf"], format!("{loc}/svf"), "{v}");
    assert!(v["links"].get("horizon_0").is_none(), "{v}");
    let angles = c.get(srv.url(&format!("{loc}/angles"))).send().await.unwrap();
    assert_eq!(angles.status(), 200);

    // A -9999 border baked as heights (no nodata in effect) is said in the resource (SPEC §2).
    let edged = ridge_geotiff(|dem| dem.chunks_mut(24).for_each(|row| row[0] = -9999.0));
    let res = post("nodata=none&method=exact&radius=4", edged, "image/tiff").await;
    assert_eq!(res.status(), 202);
    let v: Value = res.json().await.unwrap();
    let warnings = v["georeferencing"]["warnings"].as_array().cloned().unwrap_or_default();
    assert!(warnings.iter().any(|w| w.as_str().is_some_and(|w| w.contains("nodata=-9999"))), "{v}");

    let png = terrain_png16(32, 32, 5);
    let res = post("", png.clone(), "image/png").await;
    assert_eq!(res.status(), 202);
    let v: Value = res.json().await.unwrap();
    assert_eq!(
        (&v["params"]["method"], &v["params"]["radius"]),
        (&serde_json::json!("lengyel"), &serde_json::json!(16)),
        "{v}"
    );
    let res = post("outputs=angles&bins=36", png, "image/png").await;
    assert_eq!(res.status(), 422);
    let p: Value = res.json().await.unwrap();
    assert_eq!(p["field"], "bins", "{p}");
}

/// Issue 24, the page's part: a GeoTIFF DEM's resource shows its georeferencing and the DEM
/// defaults from submission on; `format=png` renders the SVF and the shadow as grey + alpha PNGs
/// with the GeoTIFF's values (SVF quantised to 8 bits, shadow 0/255, holes transparent).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn dem_resource_and_png_renderings() {
    let srv = Server::start(|_| {}).await;
    let c = client();
    // A hole in one corner (nodata -9999).
    let (w, h) = (24usize, 20usize);
    let tif = ridge_geotiff(|dem| dem[..2].fill(-9999.0));
    let q = "method=exact&radius=unlimited&outputs=horizon,angles,svf";
    let res = c
        .post(srv.url(&format!("/v1/bakes?{q}")))
        .header("content-type", "image/tiff")
        .body(tif)
        .send()
        .await
        .unwrap();
    assert_eq!(res.status(), 202);
    let loc = res.headers()["location"].to_str().unwrap().to_owned();
    let v: Value = res.json().await.unwrap();
    let geo = &v["georeferencing"];
    assert_eq!(geo["epsg"], 32632, "{v}");
    assert_eq!(geo["cell_size"], 30.0, "{v}");
    assert_eq!(geo["units"], "metre", "{v}");
    assert_eq!(geo["model"], "projected", "{v}");
    assert_eq!(v["params"]["edge"], "none", "{v}");
    assert_eq!(v["params"]["height_scale"].as_f64(), Some(1.0 / 30.0), "{v}");
    let v = wait_done(&c, &srv.url(&loc), Duration::from_secs(60)).await;
    assert_eq!(v["status"], "succeeded", "{v}");
    assert_eq!(v["georeferencing"]["epsg"], 32632);

    // SVF: the PNG against the served GeoTIFF, texel by texel.
    let svf_tif =
        c.get(srv.url(&format!("{loc}/svf"))).send().await.unwrap().bytes().await.unwrap();
    let (svf, _) = horizon_bake::heightmap::decode(
        &svf_tif,
        horizon_bake::params::Channel::Luma,
        &Default::default(),
    )
    .unwrap();
    let res = c.get(srv.url(&format!("{loc}/svf?format=png"))).send().await.unwrap();
    assert_eq!(res.status(), 200);
    assert_eq!(res.headers()["content-type"], "image/png");
    let etag = res.headers()["etag"].to_str().unwrap().to_owned();
    let png = image::load_from_memory(&res.bytes().await.unwrap()).unwrap();
    let la = match png {
        image::DynamicImage::ImageLumaA8(i) => i,
        other => panic!("svf png is not grey + alpha 8-bit: {:?}", other.color()),
    };
    assert_eq!((la.width() as usize, la.height() as usize), (w, h));
    let holes = svf.terrain.holes.clone().unwrap();
    let mut interior = 0;
    for (k, &hole) in holes.iter().enumerate() {
        let p = la.get_pixel((k % w) as u32, (k / w) as u32).0;
        if hole {
            assert_eq!(p[1], 0, "a hole is transparent at {k}");
        } else {
            let want = (svf.values[k] as f64 * 255.0 + 0.5).floor() as u8;
            assert_eq!(p, [want, 255], "svf at {k}: {}", svf.values[k]);
            interior += usize::from(want < 250);
        }
    }
    assert!(holes[0] && holes[1] && !holes[2]);
    assert!(interior > 0, "the ridge occludes some sky");
    let res = c
        .get(srv.url(&format!("{loc}/svf?format=png")))
        .header("if-none-match", etag)
        .send()
        .await
        .unwrap();
    assert_eq!(res.status(), 304);
    let res = c.get(srv.url(&format!("{loc}/svf?format=jpeg"))).send().await.unwrap();
    assert_eq!(res.status(), 422);

    // Shadow at a low western sun: the PNG against the GeoTIFF (1 → 255, 0 → 0, 255 → clear).
    let sun = "sun_azimuth=180&sun_elevation=8";
    let res = c.get(srv.url(&format!("{loc}/shadow?{sun}"))).send().await.unwrap();
    let tif = res.bytes().await.unwrap();
    let mut dec = tiff::decoder::Decoder::new(std::io::Cursor::new(&tif[..])).unwrap();
    let plane = match dec.read_image().unwrap() {
        tiff::decoder::DecodingResult::U8(v) => v,
        other => panic!("shadow.tif is not uint8: {other:?}"),
    };
    let res = c.get(srv.url(&format!("{loc}/shadow?{sun}&format=png"))).send().await.unwrap();
    assert_eq!(res.status(), 200);
    assert_eq!(res.headers()["content-type"], "image/png");
    let la = image::load_from_memory(&res.bytes().await.unwrap()).unwrap().to_luma_alpha8();
    let mut shadowed = 0;
    for (k, &s) in plane.iter().enumerate() {
        let p = la.get_pixel((k % w) as u32, (k / w) as u32).0;
        let want = match s {
            255 => [0, 0],
            0 => [0, 255],
            _ => [255, 255],
        };
        assert_eq!(p, want, "shadow at {k} (tif {s})");
        shadowed += usize::from(s == 0);
    }
    assert_eq!(plane[0], 255, "the hole is nodata");
    assert!(shadowed > 0, "the ridge casts a shadow at 8°");
    srv.stop().await;
}

/// Issue 45: a bake with the surface maps in `outputs` serves `normal.png`, `ao.png` and
/// `bent_normal.png` byte-identical to the CLI's, links them, answers 409 for one it did not
/// compute; the same for their textures, 16-bit PNGs and EXRs; and a tiled map asking for them
/// is a 422 naming `outputs`.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn surface_maps_over_http_are_the_cli_s_files() {
    let srv = Server::start(|c| {
        c.tiles =
            horizon_bake::pipeline::tiled::TileSettings { tile_above: 64 * 64, tile_size: 32 };
    })
    .await;
    let c = client();
    let png = terrain_png16(41, 33, 45);
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("in.png");
    std::fs::write(&input, &png).unwrap();
    let flags = ["--method", "march", "--radius", "12", "--bent-normal-encoding", "rgb_ao"];
    let st = std::process::Command::new(env!("CARGO_BIN_EXE_horizon-bake"))
        .args(["bake", input.to_str().unwrap(), "-o", dir.path().join("out").to_str().unwrap()])
        .args(["--outputs", "horizon,normal,ao,bent_normal"])
        .args(flags)
        .status()
        .unwrap();
    assert!(st.success());
    let q =
        "?method=march&radius=12&bent_normal_encoding=rgb_ao&outputs=horizon,normal,ao,bent_normal";
    let loc = submit_ok(&c, &srv, &png, q).await;
    let v = wait_done(&c, &srv.url(&loc), Duration::from_secs(60)).await;
    assert_eq!(v["status"], "succeeded", "{v}");
    for name in ["normal", "ao", "bent_normal"] {
        assert_eq!(v["links"][name], format!("{loc}/{name}"), "{v}");
        let res = c.get(srv.url(&format!("{loc}/{name}"))).send().await.unwrap();
        assert_eq!(res.status(), 200, "{name}");
        assert_eq!(res.headers()["content-type"], "image/png");
        let body = res.bytes().await.unwrap();
        let cli = std::fs::read(dir.path().join("out").join(format!("{name}.png"))).unwrap();
        assert!(body[..] == cli[..], "{name}.png differs from the CLI's");
    }
    let loc = submit_ok(&c, &srv, &png, "?method=march&radius=12&outputs=horizon,normal").await;
    wait_done(&c, &srv.url(&loc), Duration::from_secs(60)).await;
    let res = c.get(srv.url(&format!("{loc}/ao"))).send().await.unwrap();
    assert_eq!(res.status(), 409);
    let res = c.get(srv.url(&format!("{loc}/normal?format=ktx2"))).send().await.unwrap();
    assert_eq!(res.status(), 409, "no ktx2 in formats");
    let res = c.get(srv.url(&format!("{loc}/normal?format=tga"))).send().await.unwrap();
    assert_eq!(res.status(), 422);
    // As KTX2/DDS textures (BC5 with mips, zstd for the KTX2): the CLI's files.
    let tex = ["--format", "png8,ktx2,dds", "--texture-precision", "bc5", "--mips", "full"];
    let out = dir.path().join("tex");
    let st = std::process::Command::new(env!("CARGO_BIN_EXE_horizon-bake"))
        .args(["bake", input.to_str().unwrap(), "-o", out.to_str().unwrap()])
        .args(["--outputs", "horizon,normal,ao,bent_normal", "--supercompression", "zstd"])
        .args(flags)
        .args(tex)
        .status()
        .unwrap();
    assert!(st.success());
    let q2 =
        format!("{q}&formats=png8,ktx2,dds&texture_precision=bc5&mips=full&supercompression=zstd");
    let loc = submit_ok(&c, &srv, &png, &q2).await;
    let v = wait_done(&c, &srv.url(&loc), Duration::from_secs(60)).await;
    assert_eq!(v["status"], "succeeded", "{v}");
    for name in ["normal", "ao", "bent_normal"] {
        for (ext, ctype) in [("ktx2", "image/ktx2"), ("dds", "image/vnd-ms.dds")] {
            let res = c.get(srv.url(&format!("{loc}/{name}?format={ext}"))).send().await.unwrap();
            assert_eq!(res.status(), 200, "{name} {ext}");
            assert_eq!(res.headers()["content-type"], ctype);
            let body = res.bytes().await.unwrap();
            let cli = std::fs::read(out.join(format!("{name}.{ext}"))).unwrap();
            assert!(body[..] == cli[..], "{name}.{ext} differs from the CLI's");
        }
    }
    // 16-bit PNGs and EXRs, of a bake with no horizon output: the CLI's files, the PNG by
    // default (the 16-bit one, there being no 8-bit one), each format by name; the 8-bit PNG
    // it did not write is a 409.
    let out = dir.path().join("deep");
    let st = std::process::Command::new(env!("CARGO_BIN_EXE_horizon-bake"))
        .args(["bake", input.to_str().unwrap(), "-o", out.to_str().unwrap()])
        .args(["--outputs", "normal,ao,bent_normal", "--format", "png16,exr"])
        .args(flags)
        .status()
        .unwrap();
    assert!(st.success());
    let q3 = "?method=march&radius=12&bent_normal_encoding=rgb_ao&outputs=normal,ao,bent_normal\
              &formats=png16,exr";
    let loc = submit_ok(&c, &srv, &png, q3).await;
    let v = wait_done(&c, &srv.url(&loc), Duration::from_secs(60)).await;
    assert_eq!(v["status"], "succeeded", "{v}");
    for name in ["normal", "ao", "bent_normal"] {
        for (query, file, ctype) in [
            ("", "png", "image/png"),
            ("?format=png16", "png", "image/png"),
            ("?format=png", "png", "image/png"),
            ("?format=exr", "exr", "image/x-exr"),
        ] {
            let res = c.get(srv.url(&format!("{loc}/{name}{query}"))).send().await.unwrap();
            assert_eq!(res.status(), 200, "{name}{query}");
            assert_eq!(res.headers()["content-type"], ctype, "{name}{query}");
            let body = res.bytes().await.unwrap();
            let cli = std::fs::read(out.join(format!("{name}.{file}"))).unwrap();
            assert!(body[..] == cli[..], "{name}{query} differs from the CLI's {name}.{file}");
        }
        let res = c.get(srv.url(&format!("{loc}/{name}?format=png8"))).send().await.unwrap();
        assert_eq!(res.status(), 409, "{name}: no 8-bit PNG was written");
        let p: Value = res.json().await.unwrap();
        assert!(p["detail"].as_str().unwrap().contains("png8"), "{p}");
    }
    // The same bake with 8-bit PNGs is another bake, not this one.
    let q4 = "?method=march&radius=12&bent_normal_encoding=rgb_ao&outputs=normal,ao,bent_normal";
    let loc8 = submit_ok(&c, &srv, &png, q4).await;
    assert_ne!(loc8, loc, "png16,exr and png8 surface maps are different bakes");
    // A 16-bit texture of the maps (SPEC §3.8: as the layers): the CLI's file.
    let out16 = dir.path().join("tex16");
    let st = std::process::Command::new(env!("CARGO_BIN_EXE_horizon-bake"))
        .args(["bake", input.to_str().unwrap(), "-o", out16.to_str().unwrap()])
        .args(["--outputs", "horizon,normal,ao,bent_normal", "--format", "ktx2"])
        .args(["--texture-precision", "unorm16"])
        .args(flags)
        .status()
        .unwrap();
    assert!(st.success());
    let loc =
        submit_ok(&c, &srv, &png, &format!("{q}&formats=ktx2&texture_precision=unorm16")).await;
    let v = wait_done(&c, &srv.url(&loc), Duration::from_secs(60)).await;
    assert_eq!(v["status"], "succeeded", "{v}");
    let res = c.get(srv.url(&format!("{loc}/normal?format=ktx2"))).send().await.unwrap();
    assert_eq!(res.status(), 200);
    let body = res.bytes().await.unwrap();
    assert!(body[..] == std::fs::read(out16.join("normal.ktx2")).unwrap()[..], "normal.ktx2");
    // Above --tile-above (64²): refused before it is queued.
    let res = c
        .post(srv.url("/v1/bakes?method=march&radius=4&outputs=horizon,ao"))
        .header("content-type", "image/png")
        .body(terrain_png16(80, 80, 46))
        .send()
        .await
        .unwrap();
    assert_eq!(res.status(), 422);
    let p: Value = res.json().await.unwrap();
    assert_eq!(p["field"], "outputs", "{p}");
    srv.stop().await;
}
