//! TIFF decompression bombs against the decode budgets (issue 43, item 3): a deflated float
//! TIFF of one value, 270 KB on disk and 256 MiB decoded. Over `--max-decode-bytes` it is
//! refused from its header; four at once keep the real server's peak memory under
//! `--decode-memory-bytes` above its idle baseline (before the fix, each decode held twice its
//! decoded size and nothing bounded how many ran).

use crate::support::*;
use serde_json::Value;
use std::io::Cursor;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// 8192×8192 float32, every value `v`, deflated: 256 MiB of heights from ~270 KB.
fn bomb(v: f32) -> Vec<u8> {
    use tiff::encoder::{colortype::Gray32Float, compression::DeflateLevel, Compression};
    let mut out = Cursor::new(Vec::new());
    tiff::encoder::TiffEncoder::new(&mut out)
        .unwrap()
        .with_compression(Compression::Deflate(DeflateLevel::Balanced))
        .write_image::<Gray32Float>(8192, 8192, &vec![v; 8192 * 8192])
        .unwrap();
    out.into_inner()
}

async fn post_tiff(c: &reqwest::Client, base: &str, body: &[u8]) -> reqwest::Response {
    c.post(format!("{base}/v1/bakes?radius=4"))
        .header("content-type", "image/tiff")
        .body(body.to_vec())
        .send()
        .await
        .unwrap()
}

/// Over the per-request budget, the bomb is refused from its header, before any decode: a 422
/// naming the budget and the estimate in MiB.
#[tokio::test]
async fn a_bomb_over_the_per_request_budget_is_refused_from_its_header() {
    let srv = Server::start(|c| {
        c.limits.max_decode_bytes = 100 << 20;
        // Untiled, so the submission would decode it whole.
        c.tiles.tile_above = 1 << 28;
    })
    .await;
    let body = bomb(0.5);
    assert!(body.len() < 1 << 20, "the bomb is {} bytes", body.len());
    let t = Instant::now();
    let (status, p) = problem(post_tiff(&client(), &srv.base, &body).await).await;
    assert_eq!((status, p["code"].as_str().unwrap()), (422, "dimensions_too_large"), "{p}");
    let detail = p["detail"].as_str().unwrap();
    assert!(detail.contains("--max-decode-bytes") && detail.contains("100.0 MiB"), "{detail}");
    // 256 MiB of heights + a strip + slack.
    assert!(detail.contains("about 26"), "{detail}");
    assert!(t.elapsed() < Duration::from_secs(2), "answered after {:?}", t.elapsed());
    srv.stop().await;
}

fn status_kib(pid: u32, key: &str) -> u64 {
    let s = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap();
    let line = s.lines().find(|l| l.starts_with(key)).unwrap();
    line.split_whitespace().nth(1).unwrap().parse().unwrap()
}

struct Proc(Child);

impl Drop for Proc {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Four bombs at once against a 600 MiB process budget (each decode needs about 266 MiB: two
/// fit): the server's peak resident memory stays within the budget of its idle peak, the ones
/// that find the budget taken past the wait get 503 `decode_memory_busy` with Retry-After,
/// none gets a 500, and /healthz answers throughout. The bombs' values are NaN, so a decoded
/// one is refused (422) after its whole decode instead of starting an 8192² bake.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn four_concurrent_bombs_stay_under_the_process_budget() {
    const BUDGET: u64 = 600 << 20;
    let dir = tempfile::tempdir().unwrap();
    let addr_file = dir.path().join("addr");
    let child = Command::new(env!("CARGO_BIN_EXE_horizon-bake"))
        .args(["serve", "--addr", "127.0.0.1:0", "--bake-threads", "1"])
        .arg("--data-dir")
        .arg(dir.path().join("data"))
        .arg("--addr-file")
        .arg(&addr_file)
        .args(["--decode-memory-bytes", &BUDGET.to_string()])
        .args(["--max-decode-bytes", &BUDGET.to_string()])
        .args(["--tile-above", &(1u64 << 28).to_string(), "--upload-wait-ms", "300"])
        .env_remove("HORIZON_API_KEY")
        .env("RUST_LOG", "warn")
        .stdout(Stdio::null())
        .spawn()
        .unwrap();
    let pid = child.id();
    let _proc = Proc(child);
    let t = Instant::now();
    let base = loop {
        if let Ok(a) = std::fs::read_to_string(&addr_file) {
            break format!("http://{a}");
        }
        assert!(t.elapsed() < Duration::from_secs(20), "server did not start");
        tokio::time::sleep(Duration::from_millis(20)).await;
    };
    let c = reqwest::Client::builder().timeout(Duration::from_secs(30)).build().unwrap();
    assert_eq!(c.get(format!("{base}/healthz")).send().await.unwrap().status(), 200);
    let idle = status_kib(pid, "VmHWM:") * 1024;
    let body = bomb(f32::NAN);

    let done = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let health = {
        let (c, base, done) = (c.clone(), base.clone(), done.clone());
        tokio::spawn(async move {
            let mut slowest = Duration::ZERO;
            while !done.load(std::sync::atomic::Ordering::Relaxed) {
                let t = Instant::now();
                let r = c.get(format!("{base}/healthz")).send().await.unwrap();
                assert_eq!(r.status(), 200);
                slowest = slowest.max(t.elapsed());
                tokio::time::sleep(Duration::from_millis(50)).await;
            }
            slowest
        })
    };
    let posts: Vec<_> = (0..4)
        .map(|_| {
            let (c, base, body) = (c.clone(), base.clone(), body.clone());
            tokio::spawn(async move {
                let res = post_tiff(&c, &base, &body).await;
                let retry = res.headers().get("retry-after").is_some();
                let (status, p) = problem(res).await;
                (status, p, retry)
            })
        })
        .collect();
    let mut answers: Vec<(u16, Value, bool)> = Vec::new();
    for p in posts {
        answers.push(p.await.unwrap());
    }
    done.store(true, std::sync::atomic::Ordering::Relaxed);
    let slowest = health.await.unwrap();
    let peak = status_kib(pid, "VmHWM:") * 1024;
    let mib = |b: u64| b as f64 / (1024.0 * 1024.0);
    eprintln!(
        "idle peak {:.1} MiB, peak under load {:.1} MiB (+{:.1}); answers {:?}; slowest healthz {slowest:?}",
        mib(idle),
        mib(peak),
        mib(peak.saturating_sub(idle)),
        answers.iter().map(|a| a.0).collect::<Vec<_>>()
    );
    for (status, p, retry) in &answers {
        match status {
            422 => assert_eq!(p["code"], "invalid_input", "{p}"),
            503 => {
                assert_eq!(p["code"], "decode_memory_busy", "{p}");
                assert!(*retry, "a 503 without Retry-After: {p}");
            }
            other => panic!("answered {other}: {p}"),
        }
    }
    // At least one bomb was decoded whole (else the load measured nothing).
    assert!(answers.iter().any(|a| a.0 == 422), "{answers:?}");
    assert!(slowest < Duration::from_secs(2), "healthz took {slowest:?}");
    assert!(
        peak <= idle + BUDGET,
        "peak {:.1} MiB over the idle {:.1} MiB + the 600 MiB budget",
        mib(peak),
        mib(idle)
    );
}
