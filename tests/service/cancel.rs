//! DELETE of a running bake stops it soon, wherever it is: late in the kernel, or in the encode
//! stage between encoders. Regression tests from tests/service_defects.rs (issue 14's service
//! defects), each written to fail before its fix.

use crate::support::*;
use serde_json::Value;
use std::time::{Duration, Instant};

/// DELETE late in a bake (where the encoders used to run for seconds without looking at the
/// cancel flag) stops it within a band, not after every format was encoded.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn delete_late_in_a_bake_does_not_wait_for_the_encoders() {
    let srv = Server::start(|_| {}).await;
    let c = client();
    let loc = submit_ok(&c, &srv, &noise_png8(4096, 4096, 71), "?radius=2").await;
    let t = Instant::now();
    loop {
        let v: Value = c.get(srv.url(&loc)).send().await.unwrap().json().await.unwrap();
        assert_ne!(v["status"], "succeeded", "finished before the DELETE: {v}");
        // Past 0.85 of the overall progress: the end of the kernel, or (before the fix) the
        // encode stage (0.90..0.97).
        if v["progress"]["fraction"].as_f64().unwrap() >= 0.85 {
            break;
        }
        assert!(t.elapsed() < Duration::from_secs(120), "{v}");
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    let asked = Instant::now();
    let res = c.delete(srv.url(&loc)).send().await.unwrap();
    assert_eq!(res.status(), 202, "the bake was no longer running");
    let v = wait_done(&c, &srv.url(&loc), Duration::from_secs(120)).await;
    let took = asked.elapsed();
    assert_eq!(v["status"], "canceled", "{v}");
    assert!(took < Duration::from_secs(2), "cancel took {took:?}");
    srv.stop().await;
}

/// DELETE during the encode stage of a bake that encodes whole-layer formats (asked with
/// `formats`) stops between encoders instead of waiting for all of them: measured against the
/// encode time of the same bake left to finish.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn delete_during_the_encode_stage_stops_between_encoders() {
    let srv = Server::start(|_| {}).await;
    let c = client();
    let q = "?radius=1&bins=16&formats=png16,exr,ktx2,dds";
    let loc = submit_ok(&c, &srv, &terrain_png16(1536, 1536, 71), q).await;
    let v = wait_done(&c, &srv.url(&loc), Duration::from_secs(120)).await;
    assert_eq!(v["status"], "succeeded", "{v}");
    let full_encode = v["timings_ms"]["encode"].as_f64().unwrap();

    let loc = submit_ok(&c, &srv, &terrain_png16(1536, 1536, 72), q).await;
    let t = Instant::now();
    loop {
        let v: Value = c.get(srv.url(&loc)).send().await.unwrap().json().await.unwrap();
        if v["progress"]["stage"] == "encode" {
            break;
        }
        assert!(v["status"] != "succeeded", "the encode stage was never seen: {v}");
        assert!(t.elapsed() < Duration::from_secs(120));
        tokio::time::sleep(Duration::from_millis(2)).await;
    }
    let asked = Instant::now();
    let res = c.delete(srv.url(&loc)).send().await.unwrap();
    assert!(res.status().is_success(), "{}", res.status());
    // Polled every 2 ms, not wait_done's 50: the whole encode is ~160 ms here, and a 50 ms
    // poll alone made the cancel look as long as it (CI failed on 164 ms against 163 ms).
    let v = loop {
        let v: Value = c.get(srv.url(&loc)).send().await.unwrap().json().await.unwrap();
        if v["status"] != "running" {
            break v;
        }
        assert!(asked.elapsed() < Duration::from_secs(60), "{v}");
        tokio::time::sleep(Duration::from_millis(2)).await;
    };
    let took = asked.elapsed().as_secs_f64() * 1e3;
    assert_eq!(v["status"], "canceled", "{v}");
    eprintln!("cancel during encode: {took:.0} ms; the whole encode: {full_encode:.0} ms");
    assert!(took < 0.8 * full_encode, "cancel took {took:.0} ms of a {full_encode:.0} ms encode");
    srv.stop().await;
}

/// A bake canceled after it stored some of its files (the Fourier PNGs, written before the
/// streamed horizon layers) leaves no blob its record does not reference: before, they stayed
/// pinned for an hour and then waited for the orphan sweep (issue 43: refused or abandoned
/// results stay in the store).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_canceled_bake_leaves_no_blob_behind() {
    let srv = Server::start(|_| {}).await;
    let c = client();
    let q = "?radius=24&outputs=horizon,fourier";
    let loc = submit_ok(&c, &srv, &noise_png8(2048, 2048, 73), q).await;
    let t = Instant::now();
    // The input and at least one Fourier file are in the store; the horizon is still baking.
    while blob_files(srv.dir.path()).len() < 2 {
        let v: Value = c.get(srv.url(&loc)).send().await.unwrap().json().await.unwrap();
        assert_ne!(v["status"], "succeeded", "finished before the DELETE: {v}");
        assert!(t.elapsed() < Duration::from_secs(120), "{v}");
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    let res = c.delete(srv.url(&loc)).send().await.unwrap();
    assert_eq!(res.status(), 202, "the bake was no longer running");
    let v = wait_done(&c, &srv.url(&loc), Duration::from_secs(120)).await;
    assert_eq!(v["status"], "canceled", "{v}");
    let t = Instant::now();
    while blob_files(srv.dir.path()).len() > 1 && t.elapsed() < Duration::from_secs(10) {
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    assert_eq!(blob_files(srv.dir.path()).len(), 1, "only the input should be left");
    srv.stop().await;
}
