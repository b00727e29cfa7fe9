//! The distributed mode (PostgreSQL + S3, API and worker processes) against the embedded mode,
//! in one run, on the real engines of `scripts/engines.sh` (source its `env` file first).
//!
//! - `e2e`: one N² 16-bit bake (N = `DIST_BENCH_SIZE`, default 2048) over HTTP: POST, poll
//!   until `succeeded`, GET both png8 layers, DELETE; best of `DIST_BENCH_RUNS` (3),
//!   interleaved. Embedded: one `serve`; distributed: `serve --role api` + `serve --role worker`.
//!   Target: distributed ≤ 1.2 × embedded.
//! - `claim`: with an idle worker, from a submission's record creation to its claim
//!   (`created_ms` → `started_ms`, both in the record; it includes storing the input), over 40
//!   small bakes. Target p50 ≤ 50 ms (the worker is woken by NOTIFY, not by polling).
//! - `throughput`: 50 small bakes (128²) submitted at once, until all succeeded: one embedded
//!   server against one API + two workers (bake threads split between them).
//!
//! Run: `scripts/engines.sh start /tmp/eng && . /tmp/eng/env && cargo bench --bench distributed`.

mod common;

use common::{start_server as serve, terrain_png16 as terrain};
use std::time::{Duration, Instant};

async fn submit(c: &reqwest::Client, base: &str, png: &[u8], query: &str) -> String {
    let res = c
        .post(format!("{base}/v1/bakes?{query}"))
        .header("content-type", "image/png")
        .body(png.to_vec())
        .send()
        .await
        .expect("submit");
    assert_eq!(res.status(), 202, "submit answered {}", res.status());
    res.headers()["location"].to_str().expect("location").to_owned()
}

async fn wait(c: &reqwest::Client, base: &str, loc: &str) -> serde_json::Value {
    loop {
        let v: serde_json::Value =
            c.get(format!("{base}{loc}")).send().await.expect("poll").json().await.expect("json");
        match v["status"].as_str() {
            Some("succeeded") => return v,
            Some("failed") | Some("canceled") => panic!("bake ended {v}"),
            _ => tokio::time::sleep(Duration::from_millis(5)).await,
        }
    }
}

async fn end_to_end(c: &reqwest::Client, base: &str, png: &[u8]) -> (f64, serde_json::Value) {
    let t = Instant::now();
    let loc = submit(c, base, png, "").await;
    let posted = t.elapsed().as_secs_f64();
    let mut v = wait(c, base, &loc).await;
    v["timings_ms"]["post_s"] = posted.into();
    v["timings_ms"]["done_s"] = t.elapsed().as_secs_f64().into();
    for layer in 0..2 {
        let res = c.get(format!("{base}{loc}/horizon/{layer}")).send().await.expect("get");
        assert_eq!(res.status(), 200);
        res.bytes().await.expect("body");
    }
    let took = t.elapsed().as_secs_f64();
    let res = c.delete(format!("{base}{loc}")).send().await.expect("delete");
    assert_eq!(res.status(), 204);
    (took, v["timings_ms"].clone())
}

fn refs(v: &[String]) -> Vec<&str> {
    v.iter().map(String::as_str).collect()
}

fn percentile(v: &mut [f64], p: f64) -> f64 {
    v.sort_by(f64::total_cmp);
    v[((v.len() - 1) as f64 * p).round() as usize]
}

/// created → started, in ms, of the bake at `loc` (the record's own timestamps).
async fn claim_ms(c: &reqwest::Client, base: &str, loc: &str, db: Option<&sqlx::PgPool>) -> f64 {
    let v = wait(c, base, loc).await;
    let id = v["id"].as_str().expect("id");
    match db {
        Some(db) => {
            let (created, started): (i64, i64) = sqlx::query_as(
                "SELECT (record->>'created_ms')::bigint, (record->>'started_ms')::bigint \
                 FROM bakes WHERE id = $1",
            )
            .bind(id)
            .fetch_one(db)
            .await
            .expect("timestamps");
            (started - created) as f64
        }
        // Embedded: the resource's RFC 3339 times have millisecond precision.
        None => {
            let ms = |s: &str| -> f64 {
                let t = &s[11..23]; // HH:MM:SS.mmm
                let h: f64 = t[0..2].parse().unwrap_or(0.0);
                let m: f64 = t[3..5].parse().unwrap_or(0.0);
                let sec: f64 = t[6..].parse().unwrap_or(0.0);
                ((h * 60.0 + m) * 60.0 + sec) * 1e3
            };
            ms(v["started_at"].as_str().expect("started"))
                - ms(v["created_at"].as_str().expect("created"))
        }
    }
}

#[tokio::main]
async fn main() {
    let var = |k: &str| std::env::var(k).ok().filter(|v| !v.is_empty());
    let (Some(admin), Some(endpoint), Some(bucket)) = (
        var("HORIZON_TEST_DATABASE_URL"),
        var("HORIZON_TEST_S3_ENDPOINT"),
        var("HORIZON_TEST_S3_BUCKET"),
    ) else {
        eprintln!("distributed bench skipped: `scripts/engines.sh start DIR && . DIR/env` first");
        return;
    };
    let n: usize = var("DIST_BENCH_SIZE").and_then(|v| v.parse().ok()).unwrap_or(2048);
    let runs: usize = var("DIST_BENCH_RUNS").and_then(|v| v.parse().ok()).unwrap_or(3);
    let tag = format!("bench_{}", std::process::id());
    let pool = sqlx::PgPool::connect(&admin).await.expect("admin connection");
    sqlx::query(&format!("CREATE DATABASE {tag}")).execute(&pool).await.expect("create db");
    let db_url = format!("{}/{tag}", admin.rsplit_once('/').expect("url").0);
    let tmp = tempfile::tempdir().expect("tmp");
    let shared: Vec<String> = [
        "--database-url",
        db_url.as_str(),
        "--s3-endpoint",
        endpoint.as_str(),
        "--s3-bucket",
        bucket.as_str(),
        "--s3-prefix",
        tag.as_str(),
    ]
    .iter()
    .map(|s| s.to_string())
    .collect();
    let with = |extra: &[&str]| -> Vec<String> {
        let mut v = shared.clone();
        v.extend(extra.iter().map(|s| s.to_string()));
        v
    };
    let c = reqwest::Client::builder().timeout(Duration::from_secs(600)).build().expect("client");

    // --- e2e
    let (_emb, emb) = serve(&tmp.path().join("emb"), &[]);
    let api_args = with(&["--role", "api", "--worker-id", "api"]);
    let (_api, api) = serve(&tmp.path().join("api"), &refs(&api_args));
    let w_args = with(&["--role", "worker", "--worker-id", "w1"]);
    let (_w1, _) = serve(&tmp.path().join("w1"), &refs(&w_args));
    let png = terrain(n, 1);
    let (mut best_e, mut best_d) =
        ((f64::MAX, serde_json::Value::Null), (f64::MAX, serde_json::Value::Null));
    for _ in 0..runs {
        let e = end_to_end(&c, &emb, &png).await;
        if e.0 < best_e.0 {
            best_e = e;
        }
        let d = end_to_end(&c, &api, &png).await;
        if d.0 < best_d.0 {
            best_d = d;
        }
    }
    eprintln!(
        "phases (ms; post_s/done_s: seconds since POST): embedded {}; distributed {}",
        best_e.1, best_d.1
    );
    let (best_e, best_d) = (best_e.0, best_d.0);
    let mtex = (n * n) as f64 / 1e6;
    println!("| case | embedded | distributed | ratio | target |");
    println!("| --- | --- | --- | --- | --- |");
    println!(
        "| {n}² bake over HTTP (POST → 2 × GET png8), best of {runs} | {:.0} ms ({:.2} Mtexel/s) | {:.0} ms ({:.2} Mtexel/s) | {:.2} | ≤ 1.2 |",
        best_e * 1e3,
        mtex / best_e,
        best_d * 1e3,
        mtex / best_d,
        best_d / best_e
    );

    // --- claim latency (idle worker, small bakes)
    let db = sqlx::PgPool::connect(&db_url).await.expect("db");
    let (mut lat_e, mut lat_d) = (Vec::new(), Vec::new());
    for k in 0..40u64 {
        let small = terrain(16, 1000 + k);
        let loc = submit(&c, &emb, &small, "radius=4").await;
        lat_e.push(claim_ms(&c, &emb, &loc, None).await);
        let loc = submit(&c, &api, &small, "radius=4").await;
        lat_d.push(claim_ms(&c, &api, &loc, Some(&db)).await);
    }
    println!(
        "| record created → claimed, idle worker, 40 bakes: p50 / p90 | {:.1} / {:.1} ms | {:.1} / {:.1} ms | {:.2} (p50) | p50 ≤ 50 ms |",
        percentile(&mut lat_e, 0.5),
        percentile(&mut lat_e, 0.9),
        percentile(&mut lat_d, 0.5),
        percentile(&mut lat_d, 0.9),
        percentile(&mut lat_d, 0.5) / percentile(&mut lat_e, 0.5).max(0.1)
    );

    // --- throughput: 50 small bakes, one embedded server vs API + two workers
    let w2_args = with(&["--role", "worker", "--worker-id", "w2"]);
    let (_w2, _) = serve(&tmp.path().join("w2"), &refs(&w2_args));
    let small: Vec<Vec<u8>> = (0..50u64).map(|k| terrain(128, 5000 + k)).collect();
    let mut rates = Vec::new();
    for base in [&emb, &api] {
        let t = Instant::now();
        let mut locs = Vec::new();
        for png in &small {
            locs.push(submit(&c, base, png, "").await);
        }
        for loc in &locs {
            wait(&c, base, loc).await;
        }
        rates.push(50.0 / t.elapsed().as_secs_f64());
    }
    println!(
        "| 50 bakes of 128² submitted at once | {:.1} bakes/s ({:.2} Mtexel/s) | {:.1} bakes/s ({:.2} Mtexel/s), 2 workers | {:.2} (throughput) | — |",
        rates[0],
        rates[0] * 0.016384,
        rates[1],
        rates[1] * 0.016384,
        rates[1] / rates[0]
    );
    drop(db);
    // Stop the nodes before their database goes.
    drop((_emb, _api, _w1, _w2));
    let _ = sqlx::query(&format!("DROP DATABASE {tag} WITH (FORCE)")).execute(&pool).await;
}
