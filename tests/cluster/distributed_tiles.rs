//! Tiled bakes (SPEC §7.1) across real processes on the real engines (PostgreSQL and an S3
//! server started by `scripts/engines.sh`, as tests/cluster/distributed.rs does): one API node and two
//! workers bake the tiles of one map; a killed worker's tiles are taken over; DELETE stops every
//! tile; a stalled worker cannot overwrite a tile another wrote; a stalled coordinator gives the
//! bake back; the results are the CLI's untiled bytes. Without the engines these tests say so
//! and pass, except under `CI=true`.

use crate::cluster::*;
use crate::support;
use crate::support::*;
use serde_json::Value;
use std::collections::{BTreeMap, BTreeSet};
use std::process::Command;
use std::time::{Duration, Instant};

/// Tiling flags for every node: maps above 512² are tiled.
fn tiling(tile: &str) -> Vec<&str> {
    vec!["--tile-above", "262144", "--tile-size", tile]
}

/// The CLI's untiled layers (png8) of `png` with `flags`.
fn cli_layers(dir: &std::path::Path, png: &[u8], flags: &[&str]) -> [Vec<u8>; 2] {
    let input = dir.join(format!("in-{}.png", flags.join("_")));
    let out = dir.join(format!("cli-{}", flags.join("_")));
    std::fs::write(&input, png).unwrap();
    let st = Command::new(BIN)
        .args(["bake", input.to_str().unwrap(), "-o", out.to_str().unwrap(), "--format", "png8"])
        .args(flags)
        .status()
        .unwrap();
    assert!(st.success());
    [
        std::fs::read(out.join("horizon_0.png")).unwrap(),
        std::fs::read(out.join("horizon_1.png")).unwrap(),
    ]
}

async fn layers(c: &reqwest::Client, url: &str) -> [Vec<u8>; 2] {
    let mut out = [Vec::new(), Vec::new()];
    for (k, o) in out.iter_mut().enumerate() {
        let r = c.get(format!("{url}/horizon/{k}")).send().await.unwrap();
        assert_eq!(r.status(), 200, "layer {k}");
        *o = r.bytes().await.unwrap().to_vec();
    }
    out
}

async fn metric(c: &reqwest::Client, base: &str, name: &str) -> f64 {
    let text = c.get(format!("{base}/metrics")).send().await.unwrap().text().await.unwrap();
    text.lines()
        .find(|l| l.starts_with(name))
        .and_then(|l| l.rsplit(' ').next())
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("{name} missing:\n{text}"))
}

/// (index, status, worker, attempt) of every tile of bake `id`.
async fn tile_rows(db: &sqlx::PgPool, id: &str) -> Vec<(i32, String, Option<String>, i32)> {
    sqlx::query_as("SELECT idx, status, worker, attempt FROM tiles WHERE bake_id = $1 ORDER BY idx")
        .bind(id)
        .fetch_all(db)
        .await
        .unwrap()
}

const SUCCEEDED: &str = "horizon_tiles_total{status=\"succeeded\"}";

/// A 2048² map in 512² tiles, R 40, edge wrap and none, one API and two workers: both layers
/// are the CLI's untiled bytes, both workers baked tiles, the resource says 16 of 16, and an
/// unlimited radius on the same map is a 422.
#[tokio::test(flavor = "multi_thread")]
async fn two_workers_bake_the_tiles_of_one_map_with_the_cli_s_bytes() {
    let _serial = SERIAL.lock().await;
    let Some(mut cl) = Cluster::new("tiles2w").await else { return };
    let api = cl.start("api", "api-a", &tiling("512"));
    let w1 = cl.start("worker", "w1", &tiling("512"));
    let w2 = cl.start("worker", "w2", &tiling("512"));
    let c = client();
    let png = terrain_png16(2048, 2048, 31);
    let (s, p) = submit(&c, cl.base(api), &png, "radius=unlimited").await;
    assert_eq!(s, 422, "{p}");
    assert_eq!(p["field"], "radius", "{p}");
    assert!(p["detail"].as_str().unwrap().contains("max_distance"), "{p}");
    for edge in ["wrap", "none"] {
        let (s, v) = submit(&c, cl.base(api), &png, &format!("radius=40&edge={edge}")).await;
        assert_eq!(s, 202, "{v}");
        let id = v["id"].as_str().unwrap().to_owned();
        let done = wait_done(&c, &cl.url_of(api, &id), Duration::from_secs(300)).await;
        assert_eq!(done["status"], "succeeded", "{done}");
        assert_eq!(done["tiles"]["done"], 16, "{done}");
        assert_eq!(done["tiles"]["total"], 16, "{done}");
        let ours = layers(&c, &cl.url_of(api, &id)).await;
        let cli = cli_layers(cl.tmp.path(), &png, &["--radius", "40", "--edge", edge]);
        assert!(ours[0] == cli[0], "edge={edge}: layer 0 differs from the CLI's");
        assert!(ours[1] == cli[1], "edge={edge}: layer 1 differs from the CLI's");
    }
    let (n1, n2) =
        (metric(&c, cl.base(w1), SUCCEEDED).await, metric(&c, cl.base(w2), SUCCEEDED).await);
    assert_eq!(n1 + n2, 32.0, "w1 {n1}, w2 {n2}");
    assert!(n1 > 0.0 && n2 > 0.0, "both workers should bake tiles: w1 {n1}, w2 {n2}");
    // The tiles' intermediate blobs are gone: the bucket holds the input and the results.
    let blobs = cl.bucket_blobs().await;
    assert_eq!(blobs.len(), 1 + 2 * 2, "{blobs:?}");
}

/// kill -9 of a worker running tiles: its tiles are taken over after the lease, the bake
/// succeeds with the CLI's bytes.
#[tokio::test(flavor = "multi_thread")]
async fn a_killed_worker_s_tiles_are_taken_over() {
    let _serial = SERIAL.lock().await;
    let Some(mut cl) = Cluster::new("tileskill").await else { return };
    let api = cl.start("api", "api-a", &tiling("256"));
    let w1 = cl.start("worker", "w1", &tiling("256"));
    cl.start("worker", "w2", &tiling("256"));
    let c = client();
    let png = terrain_png16(1024, 1024, 32);
    let q = "radius=40&method=march";
    let (s, v) = submit(&c, cl.base(api), &png, q).await;
    assert_eq!(s, 202, "{v}");
    let id = v["id"].as_str().unwrap().to_owned();
    let db = cl.db().await;
    // Wait for a tile running on w1, then kill it.
    let t = Instant::now();
    let victim = loop {
        let rows = tile_rows(&db, &id).await;
        if let Some(r) = rows.iter().find(|r| r.1 == "running" && r.2.as_deref() == Some("w1")) {
            break r.0;
        }
        assert!(t.elapsed() < Duration::from_secs(60), "no tile ran on w1: {rows:?}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    };
    signal(cl.pid(w1), "KILL");
    // The victim tile is claimed again (attempt 2) once its lease runs out.
    let t = Instant::now();
    let mut retaken = false;
    loop {
        let rows = tile_rows(&db, &id).await;
        if rows.iter().any(|r| r.0 == victim && r.3 >= 2) {
            retaken = true;
        }
        let (_, v) = get_json(&c, &cl.url_of(api, &id)).await;
        if v["status"] != "running" && v["status"] != "queued" {
            assert_eq!(v["status"], "succeeded", "{v}");
            break;
        }
        assert!(t.elapsed() < Duration::from_secs(180), "not finished: {v}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    assert!(retaken, "tile {victim} was never claimed again");
    let ours = layers(&c, &cl.url_of(api, &id)).await;
    let cli = cli_layers(cl.tmp.path(), &png, &["--radius", "40", "--method", "march"]);
    assert!(ours == cli, "the result after a takeover differs from the CLI's");
}

/// DELETE of a tiled bake stops every tile within 2 s, wherever they run.
#[tokio::test(flavor = "multi_thread")]
async fn delete_stops_every_tile_within_two_seconds() {
    let _serial = SERIAL.lock().await;
    let Some(mut cl) = Cluster::new("tilesdel").await else { return };
    let api = cl.start("api", "api-a", &tiling("256"));
    let w1 = cl.start("worker", "w1", &tiling("256"));
    let w2 = cl.start("worker", "w2", &tiling("256"));
    let c = client();
    let png = terrain_png16(1024, 1024, 33);
    let (s, v) = submit(&c, cl.base(api), &png, "method=exact&bins=128&radius=60").await;
    assert_eq!(s, 202, "{v}");
    let id = v["id"].as_str().unwrap().to_owned();
    let db = cl.db().await;
    let t = Instant::now();
    loop {
        let rows = tile_rows(&db, &id).await;
        let running: BTreeSet<_> =
            rows.iter().filter(|r| r.1 == "running").filter_map(|r| r.2.clone()).collect();
        if running.len() == 2 {
            break;
        }
        assert!(t.elapsed() < Duration::from_secs(60), "tiles never ran on both: {rows:?}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let t = Instant::now();
    let r = c.delete(cl.url_of(api, &id)).send().await.unwrap();
    assert_eq!(r.status(), 202);
    loop {
        let rows = tile_rows(&db, &id).await;
        let busy = metric(&c, cl.base(w1), "horizon_bakes_running").await
            + metric(&c, cl.base(w2), "horizon_bakes_running").await;
        if busy == 0.0 && rows.iter().all(|r| r.1 != "running") {
            break;
        }
        assert!(t.elapsed() < Duration::from_secs(2), "tiles still running after 2 s: {rows:?}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let v = wait_done(&c, &cl.url_of(api, &id), Duration::from_secs(5)).await;
    assert_eq!(v["status"], "canceled", "{v}");
    assert!(t.elapsed() < Duration::from_secs(2), "cancel took {:?}", t.elapsed());
}

/// A worker stopped (SIGSTOP) past its tile's lease, then resumed, cannot overwrite the tile
/// another worker wrote meanwhile: its completion is refused (`lost`), the result is the CLI's.
#[tokio::test(flavor = "multi_thread")]
async fn a_stalled_worker_cannot_overwrite_a_tile_another_wrote() {
    let _serial = SERIAL.lock().await;
    let Some(mut cl) = Cluster::new("tilesstop").await else { return };
    let api = cl.start("api", "api-a", &tiling("256"));
    let w1 = cl.start("worker", "w1", &tiling("256"));
    let w2 = cl.start("worker", "w2", &tiling("256"));
    let c = client();
    let png = terrain_png16(1024, 1024, 34);
    let q = "radius=40&method=march&edge=none";
    let (s, v) = submit(&c, cl.base(api), &png, q).await;
    assert_eq!(s, 202, "{v}");
    let id = v["id"].as_str().unwrap().to_owned();
    let db = cl.db().await;
    let t = Instant::now();
    // The stalled worker must not be the bake's coordinator (the record's `worker`; w1 or w2
    // may win the bake's claim): a stalled coordinator is the next test's case.
    let (victim, stalled) = loop {
        let rows = tile_rows(&db, &id).await;
        let (_, v) = get_json(&c, &cl.url_of(api, &id)).await;
        let coordinator = v["worker"].as_str().map(str::to_owned);
        let pick = |w: &str| {
            (coordinator.as_deref().is_some_and(|c| c != w))
                .then(|| rows.iter().find(|r| r.1 == "running" && r.2.as_deref() == Some(w)))
                .flatten()
                .map(|r| r.0)
        };
        if let Some(r) = pick("w1") {
            break (r, w1);
        }
        if let Some(r) = pick("w2") {
            break (r, w2);
        }
        assert!(t.elapsed() < Duration::from_secs(60), "no tile ran off the coordinator: {rows:?}");
        tokio::time::sleep(Duration::from_millis(10)).await;
    };
    signal(cl.pid(stalled), "STOP");
    // The other worker takes the tile over and finishes it.
    let t = Instant::now();
    let mut seen: BTreeMap<i32, (String, Option<String>, i32)> = BTreeMap::new();
    loop {
        for r in tile_rows(&db, &id).await {
            seen.insert(r.0, (r.1, r.2, r.3));
        }
        let (_, v) = get_json(&c, &cl.url_of(api, &id)).await;
        if v["status"] == "succeeded" {
            break;
        }
        assert!(v["status"] != "failed" && v["status"] != "canceled", "{v}");
        assert!(t.elapsed() < Duration::from_secs(180), "not finished: {v}");
        tokio::time::sleep(Duration::from_millis(30)).await;
    }
    let (_, status_worker_attempt) = seen.get_key_value(&victim).unwrap();
    assert!(status_worker_attempt.2 >= 2, "tile {victim}: {status_worker_attempt:?}");
    let before = get_json(&c, &cl.url_of(api, &id)).await.1;
    signal(cl.pid(stalled), "CONT");
    tokio::time::sleep(Duration::from_secs(3)).await;
    let after = get_json(&c, &cl.url_of(api, &id)).await.1;
    for k in ["status", "attempts", "worker", "finished_at", "formats"] {
        assert_eq!(after[k], before[k], "{k} changed after the stalled worker resumed");
    }
    assert!(
        metric(&c, cl.base(stalled), "horizon_tiles_total{status=\"lost\"}").await >= 1.0,
        "the stalled worker's tile outcome was not refused:\n{}",
        cl.log(stalled)
    );
    // Whatever the stalled worker wrote for the tile it lost went with its refused outcome
    // (before, it stayed in S3, pinned for an hour, then waited for the orphan sweep): the
    // bucket holds the bake's input and results, nothing else.
    let referenced = cl.referenced_blobs().await;
    assert_eq!(cl.bucket_blobs().await, referenced, "blobs besides the referenced ones");
    let other = if stalled == w1 { w2 } else { w1 };
    assert!(metric(&c, cl.base(other), SUCCEEDED).await >= 1.0);
    let ours = layers(&c, &cl.url_of(api, &id)).await;
    let cli =
        cli_layers(cl.tmp.path(), &png, &["--radius", "40", "--method", "march", "--edge", "none"]);
    assert!(ours == cli, "the result differs from the CLI's");
}

/// The embedded mode (one process, its own pool) tiles the same 2048² map with the same bytes
/// as the CLI's untiled bake.
#[tokio::test(flavor = "multi_thread")]
async fn the_embedded_mode_tiles_the_2048_map_with_the_same_bytes() {
    let _serial = SERIAL.lock().await;
    let Some(cl) = Cluster::new("tilesemb").await else { return };
    let server = Server::start(|c| {
        c.tiles =
            horizon_bake::pipeline::tiled::TileSettings { tile_above: 512 * 512, tile_size: 512 };
    })
    .await;
    let c = client();
    let png = terrain_png16(2048, 2048, 31);
    let (s, v) = submit(&c, &server.base, &png, "radius=40&edge=wrap").await;
    assert_eq!(s, 202, "{v}");
    let id = v["id"].as_str().unwrap().to_owned();
    let url = server.url(&format!("/v1/bakes/{id}"));
    let done = wait_done(&c, &url, Duration::from_secs(300)).await;
    assert_eq!(done["status"], "succeeded", "{done}");
    assert_eq!(done["tiles"]["total"], 16, "{done}");
    let ours = layers(&c, &url).await;
    let cli = cli_layers(cl.tmp.path(), &png, &["--radius", "40", "--edge", "wrap"]);
    assert!(ours == cli, "embedded tiled layers differ from the CLI's");
}

/// The database session (`pg_stat_activity.pid`) of a node named `worker` that sits in an open
/// transaction holding what the others need: rows of `bakes` or `tiles` locked or written, or
/// the reaper's advisory lock (`postgres::REAPER_LOCK`, split into its two 32-bit halves).
async fn frozen_holder(db: &sqlx::PgPool, worker: &str) -> Option<i32> {
    sqlx::query_scalar(
        "SELECT a.pid FROM pg_stat_activity a \
         WHERE a.application_name = $1 AND a.state LIKE 'idle in transaction%' \
         AND ((a.backend_xid IS NOT NULL AND EXISTS (SELECT 1 FROM pg_locks l \
                 WHERE l.pid = a.pid AND l.locktype = 'relation' \
                 AND l.relation IN ('bakes'::regclass, 'tiles'::regclass) \
                 AND l.mode IN ('RowShareLock', 'RowExclusiveLock'))) \
              OR EXISTS (SELECT 1 FROM pg_locks l WHERE l.pid = a.pid \
                 AND l.locktype = 'advisory' AND l.classid = 1752134249::oid \
                 AND l.objid = 2054121986::oid)) \
         LIMIT 1",
    )
    .bind(horizon_bake::jobs::repo::postgres::application_name(worker))
    .fetch_optional(db)
    .await
    .unwrap()
}

/// The bake's coordinator (the worker that claimed it and waits for its tiles) stopped
/// (SIGSTOP) past its lease while inside a database transaction that holds a lock the others
/// need (its heartbeat's row lock on the bake, a tile's, the reaper's lock): the server ends
/// that session, the reaper gives the bake back, the other worker coordinates it (reusing the
/// tiles already done) and finishes it with the CLI's bytes; the old coordinator, resumed,
/// changes nothing. Before the sessions had a server-side `idle_in_transaction_session_timeout`
/// the bake stayed `running` at attempt 1 for ever (SPEC §7).
#[tokio::test(flavor = "multi_thread")]
async fn a_stalled_coordinator_gives_the_bake_back() {
    let _serial = SERIAL.lock().await;
    let Some(mut cl) = Cluster::new("tilescoord").await else { return };
    let api = cl.start("api", "api-a", &tiling("256"));
    let w1 = cl.start("worker", "w1", &tiling("256"));
    let w2 = cl.start("worker", "w2", &tiling("256"));
    let c = client();
    let q = "radius=40&method=march&edge=none";
    let db = cl.db().await;
    // A try catches the coordinator inside such a transaction a few percent of the time
    // (heartbeats every 200 ms, the reaper every second); a bake may finish before one does (a
    // fast machine, unlucky tries): then a new map is submitted, within one deadline.
    let deadline = Instant::now() + Duration::from_secs(240);
    let mut seed = 35;
    let (png, id, url, coordinator, session) = 'bakes: loop {
        let png = terrain_png16(2048, 2048, seed);
        seed += 1;
        let (s, v) = submit(&c, cl.base(api), &png, q).await;
        assert_eq!(s, 202, "{v}");
        let id = v["id"].as_str().unwrap().to_owned();
        let url = cl.url_of(api, &id);
        // Wait for the split (the tiles exist) and the first tiles done.
        let t = Instant::now();
        let coordinator = loop {
            let rows = tile_rows(&db, &id).await;
            let (_, v) = get_json(&c, &url).await;
            let done = rows.iter().filter(|r| r.1 == "succeeded").count();
            if let (true, Some(w)) = (done >= 1, v["worker"].as_str()) {
                break w.to_owned();
            }
            assert!(t.elapsed() < Duration::from_secs(60), "no tile done: {v} {rows:?}");
            tokio::time::sleep(Duration::from_millis(10)).await;
        };
        let stalled = if coordinator == "w1" { w1 } else { w2 };
        let mut tries = 0u64;
        loop {
            signal(cl.pid(stalled), "STOP");
            tokio::time::sleep(Duration::from_millis(40)).await;
            if let Some(pid) = frozen_holder(&db, &coordinator).await {
                break 'bakes (png, id, url, coordinator, pid);
            }
            signal(cl.pid(stalled), "CONT");
            tries += 1;
            assert!(
                Instant::now() < deadline,
                "{coordinator} never stopped inside a transaction in {tries} tries"
            );
            if tries.is_multiple_of(16) && get_json(&c, &url).await.1["status"] != "running" {
                continue 'bakes;
            }
            tokio::time::sleep(Duration::from_millis(tries * 7 % 29)).await;
        }
    };
    let (stalled, other) = if coordinator == "w1" { (w1, w2) } else { (w2, w1) };
    let other_id = if coordinator == "w1" { "w2" } else { "w1" };
    let (_, v) = get_json(&c, &url).await;
    assert_eq!(v["status"], "running", "the bake ended before its coordinator stalled: {v}");
    let done_before: BTreeMap<i32, i32> = tile_rows(&db, &id)
        .await
        .into_iter()
        .filter(|r| r.1 == "succeeded")
        .map(|r| (r.0, r.3))
        .collect();
    assert!(!done_before.is_empty());
    // The other worker takes the bake over (attempt 2), reuses the tiles already done, and
    // finishes it while the coordinator is still stopped.
    let t = Instant::now();
    let mut rows_seen: BTreeMap<i32, (String, i32)> = BTreeMap::new();
    let before = loop {
        for r in tile_rows(&db, &id).await {
            rows_seen.insert(r.0, (r.1, r.3));
        }
        let (_, v) = get_json(&c, &url).await;
        if v["status"] == "succeeded" {
            break v;
        }
        assert!(v["status"] != "failed" && v["status"] != "canceled", "{v}");
        if t.elapsed() > Duration::from_secs(120) {
            let sessions: Vec<(i32, Option<String>, String, Option<String>)> = sqlx::query_as(
                "SELECT pid, state, query, backend_xid::text FROM pg_stat_activity \
                 WHERE application_name = $1",
            )
            .bind(horizon_bake::jobs::repo::postgres::application_name(&coordinator))
            .fetch_all(&db)
            .await
            .unwrap();
            panic!(
                "not finished with its coordinator stopped: {v}\ntiles {:?}\n{coordinator}'s \
                 sessions (pid, state, last query, xid): {sessions:?}",
                tile_rows(&db, &id).await
            );
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    };
    assert_eq!(before["worker"], other_id, "{before}");
    assert!(metric(&c, cl.base(other), SUCCEEDED).await >= 1.0, "{}", cl.log(other));
    assert!(before["attempts"].as_u64().unwrap() >= 2, "{before}");
    for (idx, attempt) in &done_before {
        assert_eq!(rows_seen[idx], ("succeeded".to_owned(), *attempt), "tile {idx} was redone");
    }
    let alive: bool =
        sqlx::query_scalar("SELECT EXISTS (SELECT 1 FROM pg_stat_activity WHERE pid = $1)")
            .bind(session)
            .fetch_one(&db)
            .await
            .unwrap();
    assert!(!alive, "the stopped coordinator's session {session} is still open");
    // Resumed, the old coordinator learns it lost the bake and writes nothing.
    let row = |db: sqlx::PgPool, id: String| async move {
        let r: (String, i32, Option<String>, serde_json::Value) =
            sqlx::query_as("SELECT status, attempt, worker, record FROM bakes WHERE id = $1")
                .bind(id)
                .fetch_one(&db)
                .await
                .unwrap();
        r
    };
    let row_before = row(db.clone(), id.clone()).await;
    signal(cl.pid(stalled), "CONT");
    tokio::time::sleep(Duration::from_secs(3)).await;
    let after = get_json(&c, &url).await.1;
    for k in ["status", "attempts", "worker", "finished_at", "formats", "tiles"] {
        assert_eq!(after[k], before[k], "{k} changed after the old coordinator resumed");
    }
    assert_eq!(row(db.clone(), id.clone()).await, row_before);
    // Whichever way it learns (its heartbeat, its outcome, or the tiles gone with the bake the
    // other claim finished), it says so in these words.
    assert!(
        cl.log(stalled).contains("lease lost") || cl.log(stalled).contains("claim is stale"),
        "the old coordinator never learned it lost the bake:\n{}",
        cl.log(stalled)
    );
    // Losing a bake another worker finished is no error of this node's (issue 43: it logged
    // `ERROR … bake failed … internal` for a bake that succeeded).
    let log = cl.log(stalled);
    let errors: Vec<&str> = log.lines().filter(|l| l.contains("ERROR")).collect();
    assert!(errors.is_empty(), "the fenced coordinator logged errors: {errors:#?}");
    let ours = layers(&c, &url).await;
    let cli =
        cli_layers(cl.tmp.path(), &png, &["--radius", "40", "--method", "march", "--edge", "none"]);
    assert!(ours == cli, "the result differs from the CLI's");
}

/// The terrain products of a tiled bake (`outputs=horizon,angles,svf`, `svf_model=tilted`, a
/// nodata hole across a tile seam, edge wrap), on one API and two workers: `angles.tif` and `svf.tif`, assembled tile
/// by tile, are the CLI's untiled files byte for byte (and the layers its PNGs); GDAL
/// (rasterio) reads them with the bands, nodata and holes of the map; the svf's PNG rendering,
/// which would read the whole file, is a 422.
#[tokio::test(flavor = "multi_thread")]
async fn tiled_terrain_geotiffs_are_the_cli_s_bytes() {
    let _serial = SERIAL.lock().await;
    let Some(mut cl) = Cluster::new("tilestif").await else { return };
    let api = cl.start("api", "api-a", &tiling("256"));
    cl.start("worker", "w1", &tiling("256"));
    cl.start("worker", "w2", &tiling("256"));
    let c = client();
    let (w, h) = (1024, 1024);
    let mut heights = terrain16(w, h, 36);
    // A hole (nodata 0) across the seam of four tiles.
    for y in 230..290 {
        heights[y * w + 200..y * w + 300].fill(0);
    }
    let png = horizon_bake::encode::png::encode16(
        w,
        h,
        horizon_bake::encode::png::PngColor::Gray,
        &heights,
    )
    .unwrap();
    // `svf_model=tilted` (issue 44) needs each texel's normal: from the tile's window, the
    // same as the whole map's (the hole across the seam makes some one-sided).
    // Issue 44's ray products too ("same tiling as angles"): each tile walks its own rays
    // within its halo; the sun at a given place (a PNG has no projection to place it).
    let q = "radius=24&method=march&edge=wrap&bins=16&outputs=horizon,angles,svf,\
             openness,sun_hours,insolation&nodata=0&svf_model=tilted\
             &date=2026-06-21&time_step_minutes=120&latitude=46&longitude=8";
    let (s, v) = submit(&c, cl.base(api), &png, q).await;
    assert_eq!(s, 202, "{v}");
    let id = v["id"].as_str().unwrap().to_owned();
    let url = cl.url_of(api, &id);
    let done = wait_done(&c, &url, Duration::from_secs(300)).await;
    assert_eq!(done["status"], "succeeded", "{done}");
    assert_eq!(done["tiles"]["total"], 16, "{done}");
    let get = |what: &'static str| {
        let (c, url) = (c.clone(), url.clone());
        async move {
            let r = c.get(format!("{url}/{what}")).send().await.unwrap();
            assert_eq!(r.status(), 200, "{what}");
            r.bytes().await.unwrap().to_vec()
        }
    };
    let (angles, svf) = (get("angles").await, get("svf").await);
    let ours = layers(&c, &url).await;
    let r = c.get(format!("{url}/svf?format=png")).send().await.unwrap();
    assert_eq!(r.status(), 422);
    let p: Value = r.json().await.unwrap();
    assert_eq!(p["field"], "format", "{p}");

    let input = cl.tmp.path().join("holed.png");
    let out = cl.tmp.path().join("cli-terrain");
    std::fs::write(&input, &png).unwrap();
    let st = Command::new(BIN)
        .args(["bake", input.to_str().unwrap(), "-o", out.to_str().unwrap()])
        .args(["--format", "png8,geotiff", "--bins", "16"])
        .args(["--outputs", "horizon,angles,svf,openness,sun_hours,insolation"])
        .args(["--radius", "24", "--method", "march", "--edge", "wrap", "--nodata", "0"])
        .args(["--svf-model", "tilted", "--date", "2026-06-21", "--time-step-minutes", "120"])
        .args(["--latitude", "46", "--longitude", "8"])
        .status()
        .unwrap();
    assert!(st.success());
    let file = |n: &str| std::fs::read(out.join(n)).unwrap();
    assert!(angles == file("angles.tif"), "angles.tif differs from the CLI's");
    assert!(svf == file("svf.tif"), "svf.tif differs from the CLI's");
    assert!(ours == [file("horizon_0.png"), file("horizon_1.png")], "layers differ");
    for what in ["openness_positive", "openness_negative", "sun_hours", "insolation"] {
        let tiled = get(what).await;
        assert!(tiled == file(&format!("{what}.tif")), "{what}.tif differs from the CLI's");
    }

    if !support::has_rasterio() {
        return;
    }
    let (a, s) = (cl.tmp.path().join("angles.tif"), cl.tmp.path().join("svf.tif"));
    std::fs::write(&a, &angles).unwrap();
    std::fs::write(&s, &svf).unwrap();
    let script = format!(
        "import rasterio, numpy as np\n\
         with rasterio.open({a:?}) as d:\n\
         \x20   x = d.read()\n\
         \x20   assert (d.count, d.width, d.height) == (16, {w}, {h}), (d.count, d.width, d.height)\n\
         \x20   assert d.block_shapes[0] == (512, 512), d.block_shapes\n\
         \x20   assert d.nodata == 0.0, d.nodata\n\
         \x20   assert d.descriptions[4].startswith('horizon degrees at azimuth 90'), d.descriptions\n\
         \x20   hole = x[:, 230:290, 200:300]\n\
         \x20   assert (hole == 0).all()\n\
         \x20   live = np.delete(x, np.s_[230:290], axis=1)\n\
         \x20   assert np.isfinite(live).all() and (live > -90).all() and (live < 90).all()\n\
         with rasterio.open({s:?}) as d:\n\
         \x20   v = d.read(1)\n\
         \x20   assert (d.count, d.width, d.height) == (1, {w}, {h})\n\
         \x20   assert (v[230:290, 200:300] == 0).all()\n\
         \x20   assert ((v[:200] > 0) & (v[:200] <= 1)).mean() > 0.99, v[:200].min()\n\
         print('ok', x.shape, v.shape)\n"
    );
    let out = Command::new("python3").args(["-c", &script]).output().unwrap();
    eprintln!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "rasterio could not read the tiled bake's GeoTIFFs");
}
