//! What a bake costs through the HTTP service against the CLI, in one run, and what EXR costs
//! against the bake.
//!
//! For an N² 16-bit height map at the default parameters (N = `HTTP_BENCH_SIZE`, default 2048),
//! best of `HTTP_BENCH_RUNS` (default 3), interleaved so machine load affects both alike:
//! - `cli`: the real binary, `horizon-bake bake IN -o DIR --format png8` (or the
//!   `HTTP_BENCH_FORMAT`), wall time and peak
//!   resident memory (VmHWM sampled from /proc every 5 ms);
//! - `http`: the real binary as a server (`horizon-bake serve`, a child process): POST the PNG,
//!   wait on its event stream until the bake ends, GET `horizon/0` and `horizon/1` (png8), DELETE. Its peak resident
//!   memory (VmHWM of the server process) is read at the end.
//!
//! Prints both times, the HTTP/CLI ratio (target ≤ 1.3) and both peaks (target for the server at
//! 8192²: ≤ 1.5 GiB). Then, for N ≤ 4096, the EXR/bake ratio: encoding both f32 layers as EXR
//! (float and half) against `bake_horizon` of those layers, in this process (target ≤ 1), and
//! the first `?format=exr` download of both layers over HTTP (re-bake included) against the
//! service's own `timings_ms.bake`, and a bake that names `formats=png8,exr` at submission
//! (EXR encoded with the bake; its downloads are file reads).
//! `HTTP_BENCH_SERVE_ARGS` adds `serve` flags (`--tile-above 67108864`: 8192² untiled).
//! `HTTP_BENCH_FORMAT=png16` bakes 16-bit layers instead, named at submission
//! (`?formats=png16`) and downloaded as `?format=png16`, against the CLI's `--format png16`.
//! Run: `cargo bench --bench http` (or `HTTP_BENCH_SIZE=8192 HTTP_BENCH_RUNS=1 …`).

mod common;

use common::{start_server, terrain_png16};
use horizon_bake::bake::{self, Precisions};
use horizon_bake::encode::exr::{encode_rgba_as, ExrPrecision};
use horizon_bake::heightmap::{self, Limits};
use horizon_bake::params::BakeParams;
use horizon_bake::progress::Progress;
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// VmHWM of process `pid` in MiB.
fn peak_mib(pid: u32) -> Option<f64> {
    let s = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let line = s.lines().find(|l| l.starts_with("VmHWM:"))?;
    Some(line.split_whitespace().nth(1)?.parse::<f64>().ok()? / 1024.0)
}

/// The CLI's png8 bake of `input` into `out`: (wall seconds, peak MiB).
fn cli(input: &Path, out: &Path, format: &str) -> (f64, f64) {
    let t = Instant::now();
    let mut child = Command::new(env!("CARGO_BIN_EXE_horizon-bake"))
        .arg("bake")
        .arg(input)
        .arg("-o")
        .arg(out)
        .args(["--format", format])
        .stderr(Stdio::null())
        .spawn()
        .expect("cli");
    let mut peak = 0.0f64;
    loop {
        peak = peak.max(peak_mib(child.id()).unwrap_or(0.0));
        match child.try_wait().expect("wait") {
            Some(st) => {
                assert!(st.success(), "cli bake failed: {st}");
                return (t.elapsed().as_secs_f64(), peak);
            }
            None => std::thread::sleep(Duration::from_millis(5)),
        }
    }
}

async fn submit_and_wait(
    c: &reqwest::Client,
    base: &str,
    png: &[u8],
) -> (String, serde_json::Value) {
    submit_and_wait_q(c, base, png, "").await
}

async fn submit_and_wait_q(
    c: &reqwest::Client,
    base: &str,
    png: &[u8],
    query: &str,
) -> (String, serde_json::Value) {
    let t_post = Instant::now();
    let res = c
        .post(format!("{base}/v1/bakes{query}"))
        .header("content-type", "image/png")
        .body(png.to_vec())
        .send()
        .await
        .expect("submit");
    assert_eq!(res.status(), 202, "submit answered {}", res.status());
    eprintln!("  POST answered 202 after {:.1} ms", t_post.elapsed().as_secs_f64() * 1e3);
    let loc = res.headers()["location"].to_str().expect("location").to_owned();
    // Wait as a pipeline should: on the bake's event stream, which ends when the bake does
    // (polling every few ms would cost the server CPU the CLI does not spend).
    let events = c.get(format!("{base}{loc}/events")).send().await.expect("events");
    assert_eq!(events.status(), 200);
    let _ = events.bytes().await;
    let v: serde_json::Value =
        c.get(format!("{base}{loc}")).send().await.expect("get").json().await.expect("json");
    match v["status"].as_str() {
        Some("succeeded") => (loc, v),
        _ => panic!("bake ended {v}"),
    }
}

async fn get_all(c: &reqwest::Client, base: &str, loc: &str, query: &str) -> usize {
    let mut bytes = 0;
    for layer in 0..2 {
        let url = format!("{base}{loc}/horizon/{layer}{query}");
        // A format the bake did not encode answers 202 while it is encoded in the background.
        let res = loop {
            let res = c.get(&url).send().await.expect("get");
            if res.status() != 202 {
                break res;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        };
        assert_eq!(res.status(), 200);
        // Counted as it arrives, as a pipeline writing the file would take it: collecting a
        // 534 MB layer into one growing buffer cost this client seconds the server never spent
        // (curl reads the same file at over 1 GB/s).
        let mut res = res;
        while let Some(chunk) = res.chunk().await.expect("body") {
            bytes += chunk.len();
        }
    }
    bytes
}

async fn over_http(
    c: &reqwest::Client,
    base: &str,
    png: &[u8],
    format: &str,
) -> (usize, serde_json::Value) {
    // png8 is the default format: named neither at submission nor at download, as a pipeline
    // asking for the defaults would; any other is named at both.
    let (submit_q, get_q) = if format == "png8" {
        (String::new(), String::new())
    } else {
        (format!("?formats={format}"), format!("?format={format}"))
    };
    let (loc, v) = submit_and_wait_q(c, base, png, &submit_q).await;
    let t = Instant::now();
    let bytes = get_all(c, base, &loc, &get_q).await;
    eprintln!(
        "  GET of both layers: {:.1} ms, {:.1} MB",
        t.elapsed().as_secs_f64() * 1e3,
        bytes as f64 / 1e6
    );
    // Remove it so the next run is a fresh bake rather than a deduplicated answer.
    let res = c.delete(format!("{base}{loc}")).send().await.expect("delete");
    assert_eq!(res.status(), 204);
    (bytes, v["timings_ms"].clone())
}

/// Encoding both f32 layers as EXR against baking them, in this process: (bake s, [(float s,
/// bytes), (half s, bytes)]).
fn exr_against_bake(png: &[u8]) -> (f64, Vec<(ExrPrecision, f64, usize)>) {
    let params = BakeParams::default();
    let (map, _) = heightmap::decode(png, params.channel, &Limits::default()).expect("decode");
    let t = Instant::now();
    let only_f32 = Precisions { u8: false, u16: false, f32: true };
    let (layers, _) = bake::bake_horizon(&map, &params, only_f32, &Progress::new()).expect("bake");
    let bake_s = t.elapsed().as_secs_f64();
    let l = layers.f32.as_ref().expect("f32 layers");
    let (w, h) = (layers.width, layers.height);
    let mut out = Vec::new();
    for p in [ExrPrecision::Float, ExrPrecision::Half] {
        let t = Instant::now();
        // As encode::horizon_files does: the two layers side by side.
        let (a, b) =
            rayon::join(|| encode_rgba_as(w, h, &l[0], p), || encode_rgba_as(w, h, &l[1], p));
        let bytes = a.expect("exr").len() + b.expect("exr").len();
        out.push((p, t.elapsed().as_secs_f64(), bytes));
    }
    (bake_s, out)
}

fn main() {
    let n: usize =
        std::env::var("HTTP_BENCH_SIZE").ok().and_then(|v| v.parse().ok()).unwrap_or(2048);
    let runs: usize =
        std::env::var("HTTP_BENCH_RUNS").ok().and_then(|v| v.parse().ok()).unwrap_or(3);
    let format = std::env::var("HTTP_BENCH_FORMAT").unwrap_or_else(|_| "png8".into());
    assert!(format == "png8" || format == "png16", "HTTP_BENCH_FORMAT is png8 or png16");
    let png = terrain_png16(n, 0);
    let dir = tempfile::tempdir().expect("tempdir");
    let input = dir.path().join("in.png");
    std::fs::write(&input, &png).expect("input");
    // `HTTP_BENCH_SERVE_ARGS`: more `serve` flags, e.g. `--tile-above 67108864` to bake an
    // 8192² map untiled (the default tiles maps above 4096², SPEC §7.1).
    let serve_args = std::env::var("HTTP_BENCH_SERVE_ARGS").unwrap_or_default();
    let serve_args: Vec<&str> = serve_args.split_whitespace().collect();
    let (server, base) = start_server(dir.path(), &serve_args);
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .expect("runtime");
    let c = reqwest::Client::new();
    let (mut best_cli, mut best_http, mut cli_peak) = (f64::MAX, f64::MAX, 0.0f64);
    let mut timings = serde_json::Value::Null;
    for run in 0..runs {
        let (t, peak) = cli(&input, &dir.path().join(format!("cli{run}")), &format);
        best_cli = best_cli.min(t);
        cli_peak = cli_peak.max(peak);
        let t = Instant::now();
        let (bytes, tm) = rt.block_on(over_http(&c, &base, &png, &format));
        let took = t.elapsed().as_secs_f64();
        if took < best_http {
            best_http = took;
            timings = tm;
        }
        assert!(bytes > 0);
    }
    let server_peak = peak_mib(server.0.id()).unwrap_or(f64::NAN);
    let texels = (n * n) as f64;
    println!("{n}×{n} 16-bit input, default parameters, {format} layers, best of {runs}");
    println!("{:<6} {:>10} {:>10} {:>9} {:>10}", "path", "ms", "Mtexel/s", "ratio", "peak MiB");
    for (name, t, peak) in [("cli", best_cli, cli_peak), ("http", best_http, server_peak)] {
        println!(
            "{name:<6} {:>10.1} {:>10.2} {:>9.3} {:>10.0}",
            t * 1e3,
            texels / t / 1e6,
            t / best_cli,
            peak
        );
    }
    println!("service timings_ms of the best run: {timings}");
    let cli_json = std::fs::read(dir.path().join("cli0").join("bake.json")).expect("bake.json");
    let cli_json: serde_json::Value = serde_json::from_slice(&cli_json).expect("bake.json");
    println!("cli timings_ms of the first run: {}", cli_json["timings_ms"]);
    println!(
        "HTTP/CLI ratio: {:.3} (target ≤ 1.3); server peak {:.0} MiB (target ≤ 1536 at 8192²)",
        best_http / best_cli,
        server_peak
    );

    if n <= 4096 {
        let (bake_s, exr) = exr_against_bake(&png);
        println!("\nEXR of both layers against the bake of those layers (this process):");
        println!("bake (f32 layers) {:.1} ms", bake_s * 1e3);
        for (p, s, bytes) in exr {
            println!(
                "exr {:<6} {:>8.1} ms  {:>7.1} MB  EXR/bake ratio {:.3} (target ≤ 1)",
                p.as_str(),
                s * 1e3,
                bytes as f64 / 1e6,
                s / bake_s
            );
        }
        // Over HTTP: the first EXR request of a finished bake starts a re-bake that encodes
        // float and half (answered 202 until stored; the half request after it is a file
        // read); named at submission (`formats=png8,exr`), EXR is encoded with the bake and downloads are
        // file reads.
        rt.block_on(async {
            let (loc, v) = submit_and_wait(&c, &base, &png).await;
            let bake_ms = v["timings_ms"]["bake"].as_f64().unwrap_or(f64::NAN);
            for q in ["?format=exr", "?format=exr&exr_precision=half"] {
                let t = Instant::now();
                let bytes = get_all(&c, &base, &loc, q).await;
                let ms = t.elapsed().as_secs_f64() * 1e3;
                println!(
                    "first GET of both layers {q}: {ms:.1} ms, {:.1} MB, over the service's \
                     bake {bake_ms:.1} ms: {:.3}",
                    bytes as f64 / 1e6,
                    ms / bake_ms
                );
            }
            let res = c.delete(format!("{base}{loc}")).send().await.expect("delete");
            assert_eq!(res.status(), 204);
            let t = Instant::now();
            let (loc, v) = submit_and_wait_q(&c, &base, &png, "?formats=png8,exr").await;
            let submit_ms = t.elapsed().as_secs_f64() * 1e3;
            let t = Instant::now();
            let bytes = get_all(&c, &base, &loc, "?format=exr").await;
            let get_ms = t.elapsed().as_secs_f64() * 1e3;
            let tm = &v["timings_ms"];
            println!(
                "formats=png8,exr at submission: bake {:.1} ms + encode {:.1} ms (encode/bake \
                 {:.3}), submit-to-done {submit_ms:.1} ms; GET of both EXR layers {get_ms:.1} ms, \
                 {:.1} MB",
                tm["bake"].as_f64().unwrap_or(f64::NAN),
                tm["encode"].as_f64().unwrap_or(f64::NAN),
                tm["encode"].as_f64().unwrap_or(f64::NAN) / tm["bake"].as_f64().unwrap_or(f64::NAN),
                bytes as f64 / 1e6
            );
            let res = c.delete(format!("{base}{loc}")).send().await.expect("delete");
            assert_eq!(res.status(), 204);
        });
    }
    drop(server);
}
