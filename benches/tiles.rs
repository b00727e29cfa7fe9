//! Tiled bakes (SPEC §7.1) at scale, in one run, on the real engines of `scripts/engines.sh`
//! (source its `env` file first): one N² 16-bit map (N = `TILES_BENCH_SIZE`, default 16384),
//! R 16, png8, over HTTP (POST, poll, GET both layers):
//! - untiled on one embedded node (`--tile-above` N², so it is not tiled);
//! - tiled (`--tile-size` `TILES_BENCH_TILE`, default 2048) on PostgreSQL + S3 with one API and
//!   1, then 2 workers.
//!
//! For each: wall time, every process's peak resident memory (VmHWM from /proc/PID/status),
//! and the bytes each process read and wrote through its sockets and files (rchar/wchar from
//! /proc/PID/io: for the workers and the API that is the S3 and PostgreSQL traffic, plus the
//! HTTP upload and downloads at the API), and the CPU time each process used (user + system,
//! from /proc/PID/stat), the S3 server's included (its pid from the engines' `weed.pid`): on
//! one machine every process shares the same cores, so the sum is what a tiled bake costs
//! beside the untiled one. The tiled layers are checked byte-identical to the untiled ones.
//!
//! `TILES_BENCH_WORKERS=1` runs only the tiled case with one worker (default `1,2`); each
//! run's phases (split, tiles, assembly: the bake's `timings_ms`) go to stderr.
//!
//! Run: `scripts/engines.sh start /tmp/eng && . /tmp/eng/env && cargo test --release --bench tiles`
//! (or `cargo test --bench tiles`, the optimised test profile).

mod common;

use common::{start_server as serve, terrain_png16 as terrain};
use std::time::{Duration, Instant};

/// A /proc/PID/status or /proc/PID/io field, in its unit (kB for VmHWM, bytes for rchar).
fn proc_field(pid: u32, file: &str, key: &str) -> u64 {
    std::fs::read_to_string(format!("/proc/{pid}/{file}"))
        .unwrap_or_default()
        .lines()
        .find_map(|l| l.strip_prefix(key))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
        .unwrap_or(0)
}

/// CPU seconds (user + system, every thread) of process `pid`: fields 14 and 15 of
/// /proc/PID/stat, in clock ticks of 1/100 s (Linux's USER_HZ on every mainstream platform).
fn cpu(pid: u32) -> f64 {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).unwrap_or_default();
    // After the command's closing parenthesis: state is field 3, utime 14, stime 15.
    let rest = stat.rsplit_once(')').map_or("", |(_, r)| r);
    let f: Vec<u64> = rest.split_whitespace().map(|x| x.parse().unwrap_or(0)).collect();
    f.get(11).zip(f.get(12)).map_or(0.0, |(u, s)| (u + s) as f64 / 100.0)
}

/// The S3 server's pid, from the engines' directory (`HORIZON_TEST_ENGINES`), if running.
fn weed_pid() -> Option<u32> {
    let dir = std::env::var("HORIZON_TEST_ENGINES").ok()?;
    std::fs::read_to_string(format!("{dir}/weed.pid")).ok()?.trim().parse().ok()
}

fn io(pid: u32) -> u64 {
    proc_field(pid, "io", "rchar:") + proc_field(pid, "io", "wchar:")
}

/// POST, poll until succeeded, GET both png8 layers: (seconds, layers, the resource).
async fn bake(
    c: &reqwest::Client,
    base: &str,
    png: &[u8],
) -> (f64, [Vec<u8>; 2], serde_json::Value) {
    let t = Instant::now();
    let res = c
        .post(format!("{base}/v1/bakes?radius=16"))
        .header("content-type", "image/png")
        .body(png.to_vec())
        .send()
        .await
        .expect("submit");
    assert_eq!(res.status(), 202, "submit answered {}", res.status());
    let loc = res.headers()["location"].to_str().expect("location").to_owned();
    let v = loop {
        let v: serde_json::Value =
            c.get(format!("{base}{loc}")).send().await.expect("poll").json().await.expect("json");
        match v["status"].as_str() {
            Some("succeeded") => break v,
            Some("failed") | Some("canceled") => panic!("bake ended {v}"),
            _ => tokio::time::sleep(Duration::from_millis(100)).await,
        }
    };
    let mut layers = [Vec::new(), Vec::new()];
    for (k, l) in layers.iter_mut().enumerate() {
        let res = c.get(format!("{base}{loc}/horizon/{k}")).send().await.expect("get");
        assert_eq!(res.status(), 200);
        *l = res.bytes().await.expect("body").to_vec();
    }
    (t.elapsed().as_secs_f64(), layers, v)
}

#[tokio::main]
async fn main() {
    let var = |k: &str| std::env::var(k).ok().filter(|v| !v.is_empty());
    let (Some(admin), Some(endpoint), Some(bucket)) = (
        var("HORIZON_TEST_DATABASE_URL"),
        var("HORIZON_TEST_S3_ENDPOINT"),
        var("HORIZON_TEST_S3_BUCKET"),
    ) else {
        eprintln!("tiles bench skipped: `scripts/engines.sh start DIR && . DIR/env` first");
        return;
    };
    let n: usize = var("TILES_BENCH_SIZE").and_then(|v| v.parse().ok()).unwrap_or(16384);
    let tile = var("TILES_BENCH_TILE").unwrap_or_else(|| "2048".into());
    let c = reqwest::Client::builder().timeout(Duration::from_secs(3600)).build().expect("client");
    let tmp = tempfile::tempdir().expect("tmp");
    let t = Instant::now();
    let png = terrain(n, 7);
    eprintln!(
        "input: {n}² 16-bit PNG, {} MB, made in {:.1} s",
        png.len() / 1_000_000,
        t.elapsed().as_secs_f64()
    );
    let mtex = (n * n) as f64 / 1e6;
    println!("| {n}² R16 png8 | wall | per Mtexel | peak RSS (VmHWM) per process | bytes read + written per process | CPU-s per process (user + sys) |");
    println!("| --- | --- | --- | --- | --- | --- |");
    let weed = weed_pid();

    // Untiled, one embedded node.
    let above = (n * n).to_string();
    let (emb, base) = serve(&tmp.path().join("emb"), &["--tile-above", &above]);
    let pid = emb.0.id();
    let io0 = io(pid);
    let cpu0 = cpu(pid);
    let (secs, reference, v) = bake(&c, &base, &png).await;
    assert!(v.get("tiles").is_none(), "the untiled bake was tiled: {v}");
    let untiled = secs;
    println!(
        "| untiled, 1 node (embedded) | {secs:.1} s | {:.1} ms | {} MB | {} MB | {:.1} |",
        secs * 1e3 / mtex,
        proc_field(pid, "status", "VmHWM:") / 1024,
        (io(pid) - io0) / 1_000_000,
        cpu(pid) - cpu0
    );
    drop(emb);

    eprintln!("untiled timings_ms: {}", v["timings_ms"]);
    let pool = sqlx::PgPool::connect(&admin).await.expect("admin connection");
    // `TILES_BENCH_WORKERS` (default `1,2`): the tiled runs, by number of workers.
    let runs: Vec<usize> = var("TILES_BENCH_WORKERS")
        .unwrap_or_else(|| "1,2".into())
        .split(',')
        .filter_map(|k| k.trim().parse().ok())
        .collect();
    for workers in runs {
        let tag = format!("tbench_{}_{workers}", std::process::id());
        sqlx::query(&format!("CREATE DATABASE {tag}")).execute(&pool).await.expect("create db");
        let db_url = format!("{}/{tag}", admin.rsplit_once('/').expect("url").0);
        let args = |role: &str, id: &str| -> Vec<String> {
            [
                "--role",
                role,
                "--worker-id",
                id,
                "--database-url",
                &db_url,
                "--s3-endpoint",
                &endpoint,
                "--s3-bucket",
                &bucket,
                "--s3-prefix",
                &tag,
                "--tile-size",
                &tile,
            ]
            .iter()
            .map(|s| s.to_string())
            .collect()
        };
        let refs = |v: &[String]| -> Vec<String> { v.to_vec() };
        let dir = tmp.path().join(&tag);
        let a = refs(&args("api", "api"));
        let (api, base) =
            serve(&dir.join("api"), &a.iter().map(String::as_str).collect::<Vec<_>>());
        let mut nodes = vec![("api".to_owned(), api)];
        for k in 0..workers {
            let id = format!("w{}", k + 1);
            let a = args("worker", &id);
            let (w, _) = serve(&dir.join(&id), &a.iter().map(String::as_str).collect::<Vec<_>>());
            nodes.push((id, w));
        }
        let io0: Vec<u64> = nodes.iter().map(|(_, p)| io(p.0.id())).collect();
        let cpu0: Vec<f64> = nodes.iter().map(|(_, p)| cpu(p.0.id())).collect();
        let weed0 = weed.map(cpu);
        let (secs, layers, v) = bake(&c, &base, &png).await;
        assert!(
            layers == reference,
            "{workers} workers: the tiled layers differ from the untiled ones"
        );
        let rss: Vec<String> = nodes
            .iter()
            .map(|(name, p)| {
                format!("{name} {} MB", proc_field(p.0.id(), "status", "VmHWM:") / 1024)
            })
            .collect();
        let moved: Vec<String> = nodes
            .iter()
            .zip(&io0)
            .map(|((name, p), before)| format!("{name} {} MB", (io(p.0.id()) - before) / 1_000_000))
            .collect();
        let mut used: Vec<String> = nodes
            .iter()
            .zip(&cpu0)
            .map(|((name, p), before)| format!("{name} {:.1}", cpu(p.0.id()) - before))
            .collect();
        if let (Some(pid), Some(before)) = (weed, weed0) {
            used.push(format!("S3 server {:.1}", cpu(pid) - before));
        }
        println!(
            "| tiled ({} tiles of {tile}²), API + {workers} worker(s) | {secs:.1} s ({:.2} × untiled) | {:.1} ms | {} | {} | {} |",
            v["tiles"]["total"],
            secs / untiled,
            secs * 1e3 / mtex,
            rss.join(", "),
            moved.join(", "),
            used.join(", ")
        );
        // The phases: split (decode), tiles (bake), assembly (encode).
        eprintln!("{workers} worker(s) timings_ms: {}", v["timings_ms"]);
        drop(nodes);
        let _ = sqlx::query(&format!("DROP DATABASE {tag} WITH (FORCE)")).execute(&pool).await;
    }
    println!("(layers byte-identical to the untiled bake in every tiled run)");
}
