//! The distributed mode (SPEC §7) against the real engines: PostgreSQL and an S3 server
//! (SeaweedFS), both on 127.0.0.1, started by `scripts/engines.sh` (which .ci/run calls) and
//! named by the `HORIZON_TEST_*` variables it writes. API and worker nodes are real
//! `horizon-bake serve` processes, so kill -9, SIGSTOP and SIGTERM are the real thing.
//!
//! Without the engines these tests say so and pass, except under `CI=true`, where a missing
//! engine is a failure. Each test gets its own database and bucket prefix; they run one at a
//! time (a global lock), since one of them restarts PostgreSQL.

use crate::cluster::*;
use crate::support::*;
use serde_json::Value;
use std::collections::{BTreeMap, BTreeSet, HashSet};
use std::process::Command;
use std::time::{Duration, Instant};

/// A bake slow enough to observe mid-way (a second or more on a 2-core machine). Its cost is
/// set by the bins, not by the terrain: with 64 bins the exact kernel's span culling baked the
/// smooth test terrain at 160² in 0.1 s, and a DELETE arrived after the bake had finished.
const SLOW: &str = "method=exact&radius=unlimited&bins=256";

/// Polls until the bake is `running` (and returns the resource).
async fn wait_running(c: &reqwest::Client, url: &str) -> Value {
    let t = Instant::now();
    loop {
        let (_, v) = get_json(c, url).await;
        if v["status"] == "running" {
            return v;
        }
        assert!(t.elapsed() < Duration::from_secs(60), "never running: {v}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

/// Every result of a succeeded bake, by result name.
async fn downloads(c: &reqwest::Client, base: &str, id: &str) -> BTreeMap<String, Vec<u8>> {
    let mut out = BTreeMap::new();
    for name in ["horizon_0.png8", "horizon_1.png8", "horizon_0.png16", "horizon.ktx2"] {
        let r = get_result(c, &format!("{base}/v1/bakes/{id}{}", result_path(name))).await;
        assert_eq!(r.status(), 200, "{name}");
        out.insert(name.to_owned(), r.bytes().await.unwrap().to_vec());
    }
    for k in 0..2 {
        let r = c.get(format!("{base}/v1/bakes/{id}/fourier/{k}")).send().await.unwrap();
        assert_eq!(r.status(), 200, "fourier {k}");
        out.insert(format!("fourier_{k}.png"), r.bytes().await.unwrap().to_vec());
    }
    out
}

/// Round trip: every result byte-identical to the embedded mode's and to the CLI's.
#[tokio::test(flavor = "multi_thread")]
async fn results_are_byte_identical_to_the_embedded_mode_and_the_cli() {
    let _serial = SERIAL.lock().await;
    let Some(mut cl) = Cluster::new("roundtrip").await else { return };
    let api = cl.start("api", "api-a", &[]);
    cl.start("worker", "w1", &[]);
    let c = client();
    let png = terrain_png16(48, 40, 7);
    let q = "outputs=horizon,fourier&radius=8";
    let (s, v) = submit(&c, cl.base(api), &png, q).await;
    assert_eq!(s, 202, "{v}");
    let id = v["id"].as_str().unwrap().to_owned();
    let done = wait_done(&c, &cl.url_of(api, &id), Duration::from_secs(60)).await;
    assert_eq!(done["status"], "succeeded", "{done}");
    assert_eq!(done["attempts"], 1);
    let shared = downloads(&c, cl.base(api), &id).await;

    // The embedded mode, in this process.
    let server = Server::start(|_| {}).await;
    let (s, v) = submit(&c, &server.base, &png, q).await;
    assert_eq!(s, 202);
    let eid = v["id"].as_str().unwrap().to_owned();
    let done =
        wait_done(&c, &server.url(&format!("/v1/bakes/{eid}")), Duration::from_secs(60)).await;
    assert_eq!(done["status"], "succeeded");
    let embedded = downloads(&c, &server.base, &eid).await;
    assert_eq!(shared, embedded, "distributed and embedded results differ");

    // The CLI.
    let out = cl.tmp.path().join("cli");
    let input = cl.tmp.path().join("in.png");
    std::fs::write(&input, &png).unwrap();
    let st = Command::new(BIN)
        .args(["bake", input.to_str().unwrap(), "-o", out.to_str().unwrap()])
        .args(["--outputs", "horizon,fourier", "--radius", "8", "--format", "png8"])
        .status()
        .unwrap();
    assert!(st.success());
    for (ours, cli) in [
        ("horizon_0.png8", "horizon_0.png"),
        ("horizon_1.png8", "horizon_1.png"),
        ("fourier_0.png", "fourier_0.png"),
        ("fourier_1.png", "fourier_1.png"),
    ] {
        assert_eq!(shared[ours], std::fs::read(out.join(cli)).unwrap(), "{ours} vs the CLI");
    }
}

/// 20 identical submissions at once, across two API nodes, make one bake.
#[tokio::test(flavor = "multi_thread")]
async fn identical_submissions_to_two_api_nodes_make_one_bake() {
    let _serial = SERIAL.lock().await;
    let Some(mut cl) = Cluster::new("dedup").await else { return };
    let a = cl.start("api", "api-a", &[]);
    let b = cl.start("api", "api-b", &[]);
    let c = client();
    let png = terrain_png16(32, 32, 11);
    let mut tasks = Vec::new();
    for k in 0..20 {
        let (c, base, png) =
            (c.clone(), cl.base(if k % 2 == 0 { a } else { b }).to_owned(), png.clone());
        tasks.push(tokio::spawn(async move { submit(&c, &base, &png, "radius=4").await }));
    }
    let mut ids = HashSet::new();
    let mut created = 0;
    for t in tasks {
        let (s, v) = t.await.unwrap();
        assert!(s == 200 || s == 202, "{s} {v}");
        created += usize::from(s == 202);
        ids.insert(v["id"].as_str().unwrap().to_owned());
    }
    assert_eq!(ids.len(), 1, "several bakes: {ids:?}");
    assert_eq!(created, 1, "more than one submission was answered 202");
    let rows: i64 =
        sqlx::query_scalar("SELECT count(*) FROM bakes").fetch_one(&cl.db().await).await.unwrap();
    assert_eq!(rows, 1);
}

/// 30 bakes across two workers all finish, none twice.
#[tokio::test(flavor = "multi_thread")]
async fn thirty_bakes_across_two_workers_all_finish_none_twice() {
    let _serial = SERIAL.lock().await;
    let Some(mut cl) = Cluster::new("thirty").await else { return };
    let api = cl.start("api", "api-a", &[]);
    cl.start("worker", "w1", &[]);
    cl.start("worker", "w2", &[]);
    let c = client();
    let mut ids = Vec::new();
    for k in 0..30 {
        let png = terrain_png16(24, 24, 100 + k);
        let (s, v) = submit(&c, cl.base(api), &png, "radius=6").await;
        assert_eq!(s, 202, "{v}");
        ids.push(v["id"].as_str().unwrap().to_owned());
    }
    let mut by_worker: BTreeMap<String, usize> = BTreeMap::new();
    for id in &ids {
        let v = wait_done(&c, &cl.url_of(api, id), Duration::from_secs(120)).await;
        assert_eq!(v["status"], "succeeded", "{v}");
        assert_eq!(v["attempts"], 1, "a bake ran twice: {v}");
    }
    let db = cl.db().await;
    let rows: Vec<(String, i32)> =
        sqlx::query_as("SELECT worker, attempt FROM bakes").fetch_all(&db).await.unwrap();
    assert_eq!(rows.len(), 30);
    for (w, attempt) in rows {
        assert_eq!(attempt, 1);
        *by_worker.entry(w).or_default() += 1;
    }
    assert!(
        by_worker.len() == 2,
        "both workers should have baked (claims skip locked rows): {by_worker:?}"
    );
}

/// DELETE on API node A stops a bake running on worker B within 2 s; SSE on node A shows its
/// progress rising, then its final state.
#[tokio::test(flavor = "multi_thread")]
async fn cancel_and_progress_cross_nodes() {
    let _serial = SERIAL.lock().await;
    let Some(mut cl) = Cluster::new("crossnode").await else { return };
    let a = cl.start("api", "api-a", &[]);
    cl.start("worker", "w-b", &[]);
    let c = client();

    // SSE of a bake running on the worker, read on node A.
    // Long enough for several heartbeats (200 ms) of progress to reach node A.
    let png = terrain_png16(256, 256, 3);
    let (s, v) = submit(&c, cl.base(a), &png, SLOW).await;
    assert_eq!(s, 202, "{v}");
    let id = v["id"].as_str().unwrap().to_owned();
    let mut resp = c.get(format!("{}/events", cl.url_of(a, &id))).send().await.unwrap();
    let mut text = String::new();
    while let Some(chunk) = resp.chunk().await.unwrap() {
        text.push_str(&String::from_utf8_lossy(&chunk));
        if text.contains("event: done") {
            break;
        }
    }
    let fractions: Vec<f64> = text
        .lines()
        .filter_map(|l| l.strip_prefix("data: "))
        .filter_map(|d| serde_json::from_str::<Value>(d).ok())
        .filter(|v| v["status"] == "running")
        .filter_map(|v| v["progress"]["fraction"].as_f64())
        .collect();
    let distinct: BTreeSet<u64> = fractions.iter().map(|f| (f * 1e6) as u64).collect();
    assert!(distinct.len() >= 3, "progress did not rise on node A: {fractions:?}\n{text}");
    assert!(fractions.windows(2).all(|w| w[1] >= w[0]), "progress went back: {fractions:?}");
    assert!(text.contains("event: done") && text.contains("\"succeeded\""), "{text}");

    // DELETE on A of a bake running on B.
    let png = terrain_png16(160, 160, 4);
    let (_, v) = submit(&c, cl.base(a), &png, SLOW).await;
    let id = v["id"].as_str().unwrap().to_owned();
    let running = wait_running(&c, &cl.url_of(a, &id)).await;
    assert_eq!(running["attempts"], 1);
    let t = Instant::now();
    let r = c.delete(cl.url_of(a, &id)).send().await.unwrap();
    assert_eq!(r.status(), 202);
    let v = wait_done(&c, &cl.url_of(a, &id), Duration::from_secs(10)).await;
    let took = t.elapsed();
    assert_eq!(v["status"], "canceled", "{v}");
    assert!(took < Duration::from_secs(2), "cancel took {took:?}");
}

/// Kill -9 of a worker mid-bake: another worker takes the bake over after the lease expires;
/// it ends `succeeded` with the same results, one record, attempt 2.
#[tokio::test(flavor = "multi_thread")]
async fn a_killed_worker_s_bake_is_taken_over() {
    let _serial = SERIAL.lock().await;
    let Some(mut cl) = Cluster::new("kill9").await else { return };
    let api = cl.start("api", "api-a", &[]);
    let w1 = cl.start("worker", "w1", &[]);
    let c = client();
    let png = terrain_png16(192, 192, 5);
    let (_, v) = submit(&c, cl.base(api), &png, SLOW).await;
    let id = v["id"].as_str().unwrap().to_owned();
    let running = wait_running(&c, &cl.url_of(api, &id)).await;
    assert_eq!(running["worker"], "w1", "{running}");
    signal(cl.pid(w1), "KILL");
    cl.start("worker", "w2", &[]);
    let v = wait_done(&c, &cl.url_of(api, &id), Duration::from_secs(120)).await;
    assert_eq!(v["status"], "succeeded", "{v}");
    assert_eq!(v["attempts"], 2, "{v}");
    assert_eq!(v["worker"], "w2");
    let rows: i64 =
        sqlx::query_scalar("SELECT count(*) FROM bakes").fetch_one(&cl.db().await).await.unwrap();
    assert_eq!(rows, 1);
    // Same bytes as a bake that was never interrupted.
    let reference =
        library_files(&png, &[("method", "exact"), ("radius", "unlimited"), ("bins", "256")]);
    let r = c.get(format!("{}/horizon/0", cl.url_of(api, &id))).send().await.unwrap();
    assert_eq!(r.bytes().await.unwrap().to_vec(), reference["horizon_0.png8"]);
}

/// A worker stopped (SIGSTOP) past its lease, then resumed, cannot overwrite what the worker
/// that took over wrote.
#[tokio::test(flavor = "multi_thread")]
async fn a_stalled_worker_cannot_overwrite_the_takeover() {
    let _serial = SERIAL.lock().await;
    let Some(mut cl) = Cluster::new("sigstop").await else { return };
    let api = cl.start("api", "api-a", &[]);
    let w1 = cl.start("worker", "w1", &[]);
    let c = client();
    let png = terrain_png16(192, 192, 6);
    let (_, v) = submit(&c, cl.base(api), &png, SLOW).await;
    let id = v["id"].as_str().unwrap().to_owned();
    wait_running(&c, &cl.url_of(api, &id)).await;
    signal(cl.pid(w1), "STOP");
    cl.start("worker", "w2", &[]);
    let v = wait_done(&c, &cl.url_of(api, &id), Duration::from_secs(120)).await;
    assert_eq!((v["status"].as_str(), v["attempts"].as_u64()), (Some("succeeded"), Some(2)));
    let before = v.clone();
    signal(cl.pid(w1), "CONT");
    // w1 wakes up mid-bake: its next heartbeat finds the claim stale and it stops, and any
    // completion it tries is refused. Give it time to try.
    tokio::time::sleep(Duration::from_secs(4)).await;
    let (_, after) = get_json(&c, &cl.url_of(api, &id)).await;
    for k in ["status", "attempts", "worker", "finished_at", "timings_ms"] {
        assert_eq!(after[k], before[k], "{k} changed after the stalled worker resumed");
    }
    let log = cl.log(w1);
    assert!(
        log.contains("lease lost") || log.contains("claim is stale"),
        "the stalled worker did not notice it was fenced off:\n{log}"
    );
    let errors: Vec<&str> = log.lines().filter(|l| l.contains("ERROR")).collect();
    assert!(errors.is_empty(), "the fenced worker logged errors: {errors:#?}");
}

/// SIGTERM of a worker hands its bake back and another finishes it.
#[tokio::test(flavor = "multi_thread")]
async fn sigterm_hands_the_bake_back() {
    let _serial = SERIAL.lock().await;
    let Some(mut cl) = Cluster::new("sigterm").await else { return };
    let api = cl.start("api", "api-a", &[]);
    let w1 = cl.start("worker", "w1", &["--shutdown-grace-secs", "0"]);
    let c = client();
    let png = terrain_png16(192, 192, 8);
    let (_, v) = submit(&c, cl.base(api), &png, SLOW).await;
    let id = v["id"].as_str().unwrap().to_owned();
    wait_running(&c, &cl.url_of(api, &id)).await;
    let t = Instant::now();
    signal(cl.pid(w1), "TERM");
    let st = cl.nodes[w1].child.wait().unwrap();
    assert!(st.success(), "the worker did not exit cleanly: {st}");
    // Handed back at once, not after a lease: queued again right away.
    let (_, v) = get_json(&c, &cl.url_of(api, &id)).await;
    assert_eq!(v["status"], "queued", "{v}");
    assert!(t.elapsed() < Duration::from_secs(2), "{:?}", t.elapsed());
    cl.start("worker", "w2", &[]);
    let v = wait_done(&c, &cl.url_of(api, &id), Duration::from_secs(120)).await;
    assert_eq!(v["status"], "succeeded", "{v}");
    assert_eq!(v["worker"], "w2");
}

/// After retention and sweeping, the bucket holds exactly the blobs that records reference.
#[tokio::test(flavor = "multi_thread")]
async fn after_retention_the_bucket_holds_exactly_the_referenced_blobs() {
    let _serial = SERIAL.lock().await;
    let Some(mut cl) = Cluster::new("retention").await else { return };
    let api = cl.start("all", "n1", &["--retention-secs", "3", "--sweep-interval-secs", "1"]);
    let c = client();
    let mut old = Vec::new();
    for k in 0..3 {
        let (_, v) = submit(&c, cl.base(api), &terrain_png16(16, 16, 200 + k), "radius=4").await;
        old.push(v["id"].as_str().unwrap().to_owned());
    }
    for id in &old {
        let v = wait_done(&c, &cl.url_of(api, id), Duration::from_secs(60)).await;
        assert_eq!(v["status"], "succeeded");
        // An on-request result too, so blobs written after the bake are covered.
        let r = get_result(&c, &format!("{}/horizon/0?format=png16", cl.url_of(api, id))).await;
        assert_eq!(r.status(), 200);
    }
    // Wait past the retention of the first three.
    tokio::time::sleep(Duration::from_secs(5)).await;
    let mut kept = Vec::new();
    for k in 0..2 {
        let (_, v) = submit(
            &c,
            cl.base(api),
            &terrain_png16(16, 16, 300 + k),
            "radius=4&outputs=horizon,fourier",
        )
        .await;
        kept.push(v["id"].as_str().unwrap().to_owned());
    }
    for id in &kept {
        let v = wait_done(&c, &cl.url_of(api, id), Duration::from_secs(60)).await;
        assert_eq!(v["status"], "succeeded");
    }
    for id in &old {
        let (s, _) = get_json(&c, &cl.url_of(api, id)).await;
        assert_eq!(s, 404, "bake {id} outlived its retention");
    }
    let db = cl.db().await;
    let referenced = cl.referenced_blobs().await;
    let from_records: BTreeSet<String> = {
        let recs: Vec<Value> =
            sqlx::query_scalar("SELECT record FROM bakes").fetch_all(&db).await.unwrap();
        recs.iter()
            .flat_map(|r| {
                let mut v = vec![r["input_blob"].as_str().unwrap().to_owned()];
                v.extend(
                    r["results"]
                        .as_object()
                        .unwrap()
                        .values()
                        .map(|h| h.as_str().unwrap().to_owned()),
                );
                v
            })
            .collect()
    };
    assert_eq!(referenced, from_records, "blob_refs disagrees with the records");
    assert_eq!(cl.bucket_blobs().await, referenced, "the bucket holds other blobs than referenced");
    assert!(!referenced.is_empty());
}

/// PostgreSQL restarted mid-run: the API answers 503 meanwhile, then everything recovers.
#[tokio::test(flavor = "multi_thread")]
async fn postgres_restart_gives_503_then_recovers() {
    let _serial = SERIAL.lock().await;
    let Some(mut cl) = Cluster::new("pgrestart").await else { return };
    let api = cl.start("api", "api-a", &[]);
    cl.start("worker", "w1", &[]);
    let c = client();
    let png = terrain_png16(192, 192, 9);
    let (_, v) = submit(&c, cl.base(api), &png, SLOW).await;
    let id = v["id"].as_str().unwrap().to_owned();
    wait_running(&c, &cl.url_of(api, &id)).await;
    let engines = cl.eng.dir.clone();
    let script = concat!(env!("CARGO_MANIFEST_DIR"), "/scripts/engines.sh");
    assert!(Command::new(script)
        .args(["pg-stop", engines.to_str().unwrap()])
        .status()
        .unwrap()
        .success());
    let (s, v) = get_json(&c, &cl.url_of(api, &id)).await;
    let down = (s, v["code"].clone());
    let (ready, _) = get_json(&c, &format!("{}/readyz", cl.base(api))).await;
    let (s_submit, _) = submit(&c, cl.base(api), &terrain_png16(16, 16, 1), "radius=4").await;
    // Down for longer than a lease: the worker cannot heartbeat meanwhile.
    tokio::time::sleep(Duration::from_secs(3)).await;
    assert!(Command::new(script)
        .args(["pg-start", engines.to_str().unwrap()])
        .status()
        .unwrap()
        .success());
    assert_eq!(down, (503, Value::from("store_unavailable")), "GET while the database is down");
    assert_eq!(ready, 503, "readyz while the database is down");
    assert_eq!(s_submit, 503, "a submission while the database is down");
    // Everything recovers: the bake finishes (on the same claim, or after a takeover), and new
    // work is accepted and done.
    let v = wait_done(&c, &cl.url_of(api, &id), Duration::from_secs(120)).await;
    assert_eq!(v["status"], "succeeded", "{v}");
    let (s, v) = submit(&c, cl.base(api), &terrain_png16(16, 16, 2), "radius=4").await;
    assert_eq!(s, 202, "{v}");
    let v =
        wait_done(&c, &cl.url_of(api, v["id"].as_str().unwrap()), Duration::from_secs(60)).await;
    assert_eq!(v["status"], "succeeded", "{v}");
    let (ready, _) = get_json(&c, &format!("{}/readyz", cl.base(api))).await;
    assert_eq!(ready, 200);
}

/// Blobs over a writer's buffer and over one PUT (64 MiB) go up in parts (staged, then copied to
/// their hash) and stream back, from a thread outside the async runtime as on the bake pool
/// (8192² inputs and results are that large).
#[tokio::test(flavor = "multi_thread")]
async fn large_blobs_round_trip_through_s3_from_the_bake_pool() {
    let _serial = SERIAL.lock().await;
    let Some(cl) = Cluster::new("largeblob").await else { return };
    let cfg = horizon_bake::jobs::blob::S3Config {
        endpoint: cl.eng.s3_endpoint.clone(),
        bucket: cl.eng.bucket.clone(),
        region: "us-east-1".into(),
        prefix: cl.prefix.clone(),
        access_key: std::env::var("AWS_ACCESS_KEY_ID").ok(),
        secret_key: std::env::var("AWS_SECRET_ACCESS_KEY").ok(),
    };
    let store = horizon_bake::jobs::blob::S3BlobStore::connect(&cfg, &cl.tmp.path().join("spool"))
        .await
        .unwrap();
    let mut rng = Rng(5);
    let data: Vec<u8> = (0..70 << 20).map(|_| (rng.next_u64() >> 56) as u8).collect();
    let want = blake3::hash(&data).to_hex().to_string();
    let (hash, back, via_put) = std::thread::spawn(move || {
        use horizon_bake::jobs::blob::BlobStore;
        use std::io::{Read, Write};
        let mut w = store.writer().unwrap();
        for chunk in data.chunks(1 << 20) {
            // (Written as a bake writes: in pieces, parts going up meanwhile.)
            w.write_all(chunk).unwrap();
        }
        let hash = w.commit(&|_| Ok(())).unwrap();
        let (len, mut r) = store.open(&hash).unwrap().unwrap();
        let mut back = Vec::new();
        r.read_to_end(&mut back).unwrap();
        assert_eq!(len as usize, back.len());
        let mut other = data.clone();
        other[0] ^= 1;
        let via_put = store.put(&other, &|_| Ok(())).unwrap();
        assert_eq!(store.get(&via_put).unwrap().unwrap(), other);
        (hash, back, via_put)
    })
    .join()
    .unwrap();
    assert_eq!(hash, want);
    assert_eq!(blake3::hash(&back).to_hex().to_string(), want);
    assert_eq!(cl.bucket_blobs().await, [hash, via_put].into_iter().collect());
}

/// A worker serves health and metrics only; flags that cannot work together are refused.
#[tokio::test(flavor = "multi_thread")]
async fn roles_serve_what_spec_7_says() {
    let _serial = SERIAL.lock().await;
    // Without engines: a role other than `all` needs the shared stores.
    let out = Command::new(BIN)
        .args(["serve", "--role", "worker", "--addr", "127.0.0.1:0"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("role"), "{out:?}");
    let out = Command::new(BIN)
        .args(["serve", "--database-url", "postgres://x@127.0.0.1:1/x", "--addr", "127.0.0.1:0"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("s3"), "{out:?}");
    let Some(mut cl) = Cluster::new("roles").await else { return };
    let w = cl.start("worker", "w1", &[]);
    let c = client();
    let (s, v) = get_json(&c, &format!("{}/readyz", cl.base(w))).await;
    assert_eq!((s, v["role"].as_str()), (200, Some("worker")));
    assert_eq!(c.get(format!("{}/metrics", cl.base(w))).send().await.unwrap().status(), 200);
    let (s, v) = get_json(&c, &format!("{}/v1/bakes", cl.base(w))).await;
    assert_eq!(s, 404, "{v}");
    assert_eq!(cl.nodes[w].worker_id, "w1");
}
