//! End-to-end cost of the HTTP service against the library call it wraps, in one run.
//!
//! For a 2048² 16-bit height map at the default parameters, times (best of `HTTP_BENCH_RUNS`,
//! default 3):
//! - `library`: decode → `bake_horizon` (every precision) → `encode::horizon_files` for the same
//!   eight files the service stores (png8, png16, exr, ktx2, dds);
//! - `http`: POST the PNG to a server on 127.0.0.1:0, poll until `succeeded`, download both png8
//!   layers — queueing, hashing, durable blob writes and the record commit included.
//!
//! Prints ms, Mtexel/s and the HTTP/library ratio; the target is a ratio ≤ 1.20.
//! Run: `cargo bench --bench http` (set `HTTP_BENCH_SIZE` for another size).

use horizon_bake::bake::{self, Precisions};
use horizon_bake::encode::png::{encode16, PngColor};
use horizon_bake::encode::{self, Formats, TexturePrecision};
use horizon_bake::heightmap::{self, Limits};
use horizon_bake::params::BakeParams;
use horizon_bake::progress::Progress;
use horizon_bake::service::{self, Config};
use std::f64::consts::TAU;
use std::time::{Duration, Instant};

fn terrain(n: usize) -> Vec<u8> {
    let mut data = Vec::with_capacity(n * n);
    let mut seed = 0x1234_5678_9abc_def0u64;
    for y in 0..n {
        for x in 0..n {
            seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            let (u, v) = (x as f64 / n as f64, y as f64 / n as f64);
            let s =
                (u * TAU * 3.0).sin() * (v * TAU * 2.0).cos() + 0.5 * ((u + v) * TAU * 5.0).sin();
            let noise = ((seed >> 40) as f64 / (1u64 << 24) as f64 - 0.5) * 0.1;
            data.push((((s / 1.5 + 1.0) * 0.45 + noise).clamp(0.0, 1.0) * 65535.0) as u16);
        }
    }
    encode16(n, n, PngColor::Gray, &data).expect("encode input")
}

fn library(png: &[u8]) -> usize {
    let params = BakeParams::default();
    let (map, _) = heightmap::decode(png, params.channel, &Limits::default()).expect("decode");
    let (layers, _) =
        bake::bake_horizon(&map, &params, Precisions::ALL, &Progress::new()).expect("bake");
    let all = Formats::parse("png8,exr,ktx2,dds", TexturePrecision::Unorm8).expect("formats");
    let wide = Formats::parse("png16", TexturePrecision::Unorm8).expect("formats");
    let mut bytes = 0;
    for f in [all, wide] {
        bytes += encode::horizon_files(&layers, &f)
            .expect("encode")
            .iter()
            .map(|f| f.bytes.len())
            .sum::<usize>();
    }
    bytes
}

async fn over_http(c: &reqwest::Client, base: &str, png: &[u8]) -> usize {
    let res = c
        .post(format!("{base}/v1/bakes"))
        .header("content-type", "image/png")
        .body(png.to_vec())
        .send()
        .await
        .expect("submit");
    assert_eq!(res.status(), 202, "submit answered {}", res.status());
    let loc = res.headers()["location"].to_str().expect("location").to_owned();
    loop {
        let v: serde_json::Value =
            c.get(format!("{base}{loc}")).send().await.expect("poll").json().await.expect("json");
        match v["status"].as_str() {
            Some("succeeded") => break,
            Some("failed") | Some("canceled") => panic!("bake ended {v}"),
            _ => tokio::time::sleep(Duration::from_millis(5)).await,
        }
    }
    let mut bytes = 0;
    for layer in 0..2 {
        bytes += c
            .get(format!("{base}{loc}/horizon/{layer}"))
            .send()
            .await
            .expect("download")
            .bytes()
            .await
            .expect("body")
            .len();
    }
    // Remove it so the next run is a fresh bake rather than a deduplicated answer.
    let res = c.delete(format!("{base}{loc}")).send().await.expect("delete");
    assert_eq!(res.status(), 204);
    bytes
}

fn main() {
    let n: usize =
        std::env::var("HTTP_BENCH_SIZE").ok().and_then(|v| v.parse().ok()).unwrap_or(2048);
    let runs: usize =
        std::env::var("HTTP_BENCH_RUNS").ok().and_then(|v| v.parse().ok()).unwrap_or(3);
    let png = terrain(n);
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .expect("runtime");
    let dir = tempfile::tempdir().expect("tempdir");
    let mut config = Config::for_dir(dir.path()).expect("config");
    config.max_body_bytes = 1 << 30;
    let (base, stop) = rt.block_on(async {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.expect("bind");
        let base = format!("http://{}", listener.local_addr().expect("addr"));
        let (tx, rx) = tokio::sync::oneshot::channel::<()>();
        tokio::spawn(service::run(config, listener, async move {
            let _ = rx.await;
        }));
        (base, tx)
    });
    let c = reqwest::Client::new();
    // Interleave the two so machine load affects both alike; keep the best of each.
    let (mut best_lib, mut best_http) = (f64::MAX, f64::MAX);
    for _ in 0..runs {
        let t = Instant::now();
        let lib_bytes = std::hint::black_box(library(&png));
        best_lib = best_lib.min(t.elapsed().as_secs_f64());
        let t = Instant::now();
        let http_bytes = rt.block_on(over_http(&c, &base, &png));
        best_http = best_http.min(t.elapsed().as_secs_f64());
        assert!(lib_bytes > 0 && http_bytes > 0);
    }
    let _ = stop.send(());
    let texels = (n * n) as f64;
    println!("end-to-end {n}×{n} bake, default parameters, best of {runs}");
    println!("{:<10} {:>10} {:>12} {:>8}", "path", "ms", "Mtexel/s", "ratio");
    for (name, t) in [("library", best_lib), ("http", best_http)] {
        println!("{name:<10} {:>10.1} {:>12.2} {:>8.3}", t * 1e3, texels / t / 1e6, t / best_lib);
    }
    let overhead = best_http / best_lib - 1.0;
    println!("HTTP overhead: {:.1}% (target ≤ 20%)", overhead * 100.0);
}
