//! Load and cancellation against a real server: 200 concurrent submissions on a small queue get
//! only 202/200/429 (no 5xx), memory stays bounded and every accepted bake finishes; a running
//! 4096² bake stops within a second of DELETE and reads `canceled`.
//!
//! A binary of its own: the load test reads this process's peak resident memory (VmHWM) before
//! and after, which only means "memory stays bounded" when no other test of the process is
//! baking big maps meanwhile (the service binary's 1536² and 4096² bakes would raise the same
//! peak, or hide a rise behind an earlier one).

#[path = "../support/mod.rs"]
mod support;

use serde_json::Value;
use std::time::{Duration, Instant};
use support::*;

fn peak_rss_kib() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmHWM:"))
                .and_then(|l| l.split_whitespace().nth(1).and_then(|v| v.parse().ok()))
        })
        .unwrap_or(0)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn two_hundred_concurrent_submissions_on_a_small_queue() {
    let srv = Server::start(|c| {
        c.queue_capacity = 8;
        c.max_concurrent_bakes = 2;
        c.max_inflight_uploads = 32;
    })
    .await;
    let c = client();
    // 150 distinct inputs and 50 repeats of earlier ones (dedup under load). Each bake must
    // take long enough (64², R = 32: tens of ms) for the queue to fill: a bake encodes only its
    // png8 layers now, so a 24², R = 4 one finished before the next upload arrived.
    let inputs: Vec<Vec<u8>> = (0..150).map(|s| terrain_png16(64, 64, 1000 + s)).collect();
    let rss_before = peak_rss_kib();
    let mut tasks = Vec::new();
    for k in 0..200usize {
        let body = inputs[k % 150].clone();
        let c = c.clone();
        let url = srv.url("/v1/bakes?radius=32");
        tasks.push(tokio::spawn(async move {
            let res =
                c.post(url).header("content-type", "image/png").body(body).send().await.unwrap();
            let status = res.status().as_u16();
            let retry = res.headers().get("retry-after").is_some();
            let v: Value = res.json().await.unwrap();
            (status, retry, v)
        }));
    }
    let mut accepted = std::collections::BTreeSet::new();
    let mut counts = std::collections::BTreeMap::new();
    for t in tasks {
        let (status, retry, v) = t.await.unwrap();
        *counts.entry(status).or_insert(0) += 1;
        match status {
            202 | 200 => {
                accepted.insert(v["id"].as_str().unwrap().to_owned());
            }
            429 => assert!(retry, "429 without Retry-After"),
            other => panic!("unexpected {other}: {v}"),
        }
    }
    assert!(counts.get(&429).copied().unwrap_or(0) > 0, "the small queue never filled: {counts:?}");
    assert!(counts.get(&202).copied().unwrap_or(0) >= 8, "{counts:?}");
    for id in &accepted {
        let v = wait_done(&c, &srv.url(&format!("/v1/bakes/{id}")), Duration::from_secs(120)).await;
        assert_eq!(v["status"], "succeeded", "{v}");
    }
    let grown_mib = peak_rss_kib().saturating_sub(rss_before) / 1024;
    assert!(grown_mib < 512, "peak RSS grew by {grown_mib} MiB");
    let list: Value =
        c.get(srv.url("/v1/bakes?limit=1000")).send().await.unwrap().json().await.unwrap();
    assert_eq!(list["items"].as_array().unwrap().len(), accepted.len(), "records ≠ accepted bakes");
    srv.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn canceling_a_running_4096_bake_stops_within_a_second() {
    let srv = Server::start(|_| {}).await;
    let c = client();
    let png = noise_png8(4096, 4096, 3);
    let res = c
        .post(srv.url("/v1/bakes?radius=32"))
        .header("content-type", "image/png")
        .body(png)
        .send()
        .await
        .unwrap();
    assert_eq!(res.status(), 202);
    let loc = res.headers()["location"].to_str().unwrap().to_owned();
    let url = srv.url(&loc);
    // Wait until the kernel itself is running and has made progress.
    let t = Instant::now();
    loop {
        let v: Value = c.get(&url).send().await.unwrap().json().await.unwrap();
        if v["progress"]["stage"] == "bake" && v["progress"]["fraction"].as_f64().unwrap() > 0.05 {
            break;
        }
        assert!(v["status"] != "succeeded", "finished before it could be canceled: {v}");
        assert!(t.elapsed() < Duration::from_secs(120), "never reached the bake stage: {v}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let t = Instant::now();
    let res = c.delete(&url).send().await.unwrap();
    assert_eq!(res.status(), 202);
    let v = wait_done(&c, &url, Duration::from_secs(10)).await;
    let took = t.elapsed();
    assert_eq!(v["status"], "canceled", "{v}");
    assert!(took < Duration::from_secs(1), "cancel took {took:?}");
    assert!(v["finished_at"].is_string());
    // A canceled bake has no results.
    let res = c.get(srv.url(&format!("{loc}/horizon/0"))).send().await.unwrap();
    assert_eq!(res.status(), 409);
    srv.stop().await;
}
