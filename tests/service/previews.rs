//! Previews over HTTP beside bakes: a preview of a finished bake answers while a long bake holds
//! every bake slot. (The preview renderings themselves are tested in `api`.) A regression test
//! from tests/service_defects.rs (issue 14's service defects), written to fail before its fix.

use crate::support::*;
use serde_json::Value;
use std::time::{Duration, Instant};

/// A preview of a small finished bake answers while a long bake holds every bake slot.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn previews_do_not_queue_behind_a_long_bake() {
    let srv = Server::start(|c| c.bake_threads = 2).await;
    let c = client();
    let small = submit_ok(&c, &srv, &terrain_png16(24, 24, 51), "?radius=4").await;
    let v = wait_done(&c, &srv.url(&small), Duration::from_secs(60)).await;
    assert_eq!(v["status"], "succeeded", "{v}");
    let long = submit_ok(&c, &srv, &noise_png8(4096, 4096, 52), "?radius=64").await;
    let t = Instant::now();
    loop {
        let v: Value = c.get(srv.url(&long)).send().await.unwrap().json().await.unwrap();
        if v["progress"]["stage"] == "bake" {
            break;
        }
        assert!(t.elapsed() < Duration::from_secs(60), "the long bake never started: {v}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let res = c.get(srv.url(&format!("{small}/preview?azimuth=30"))).send().await.unwrap();
    assert_eq!(res.status(), 200);
    let v: Value = c.get(srv.url(&long)).send().await.unwrap().json().await.unwrap();
    assert_eq!(v["status"], "running", "the preview waited for the long bake: {v}");
    let res = c.delete(srv.url(&long)).send().await.unwrap();
    assert_eq!(res.status(), 202);
    srv.stop().await;
}
