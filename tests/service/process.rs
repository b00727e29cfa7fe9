//! The real binary: SIGKILL while bakes are queued and running, restart on the same data
//! directory, every bake succeeds once with the library's bytes; SIGTERM returns the running
//! bake to the queue when the grace period is over, exits cleanly, and the next start finishes
//! it; downloads are byte-identical to `horizon-bake bake`.

use crate::support::*;
use serde_json::Value;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

struct Proc {
    child: Child,
    base: String,
}

fn spawn(data: &Path, extra: &[&str]) -> Proc {
    spawn_with(data, extra, Stdio::inherit(), "warn")
}

/// The server with its stderr (the log) going to `stderr`, at log level `level`.
fn spawn_with(data: &Path, extra: &[&str], stderr: Stdio, level: &str) -> Proc {
    let addr_file = data.with_extension("addr");
    let _ = std::fs::remove_file(&addr_file);
    let child = Command::new(env!("CARGO_BIN_EXE_horizon-bake"))
        .arg("serve")
        .args(["--addr", "127.0.0.1:0", "--bake-threads", "2"])
        .arg("--data-dir")
        .arg(data)
        .arg("--addr-file")
        .arg(&addr_file)
        .args(extra)
        .env_remove("HORIZON_API_KEY")
        .env("RUST_LOG", level)
        .stdout(Stdio::null())
        .stderr(stderr)
        .spawn()
        .unwrap();
    // Owned by `Proc` at once, so every path (a failed assert included) kills and reaps it.
    let mut p = Proc { child, base: String::new() };
    let t = Instant::now();
    loop {
        if let Ok(a) = std::fs::read_to_string(&addr_file) {
            p.base = format!("http://{a}");
            return p;
        }
        assert!(t.elapsed() < Duration::from_secs(20), "server did not start");
        std::thread::sleep(Duration::from_millis(20));
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

async fn submit(c: &reqwest::Client, base: &str, png: &[u8], q: &str) -> (u16, Value) {
    let res = c
        .post(format!("{base}/v1/bakes?{q}"))
        .header("content-type", "image/png")
        .body(png.to_vec())
        .send()
        .await
        .unwrap();
    (res.status().as_u16(), res.json().await.unwrap())
}

async fn wait_running(c: &reqwest::Client, base: &str) {
    let t = Instant::now();
    loop {
        let v: Value = c
            .get(format!("{base}/v1/bakes?status=running"))
            .send()
            .await
            .unwrap()
            .json()
            .await
            .unwrap();
        if !v["items"].as_array().unwrap().is_empty() {
            return;
        }
        assert!(t.elapsed() < Duration::from_secs(30), "no bake started running");
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigkill_with_bakes_queued_and_running_loses_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let c = client();
    let inputs: Vec<Vec<u8>> = (0..4).map(|s| terrain_png16(768, 640, 100 + s)).collect();
    let q = "radius=16&height_scale=16";

    let p = spawn(&data, &[]);
    let mut ids = Vec::new();
    for png in &inputs {
        let (s, v) = submit(&c, &p.base, png, q).await;
        assert_eq!(s, 202, "{v}");
        ids.push(v["id"].as_str().unwrap().to_owned());
    }
    wait_running(&c, &p.base).await;
    let mut p = p;
    p.child.kill().unwrap(); // SIGKILL
    p.child.wait().unwrap();
    let before: Vec<Value> = {
        // Nothing was finished, or only some: either way, all are still recorded.
        let p2 = spawn(&data, &[]);
        let mut out = Vec::new();
        for id in &ids {
            let v = wait_done(&c, &format!("{}/v1/bakes/{id}", p2.base), Duration::from_secs(120))
                .await;
            assert_eq!(v["status"], "succeeded", "{v}");
            out.push(v);
        }
        // Results equal the library's, byte for byte.
        for (png, id) in inputs.iter().zip(&ids) {
            let want = library_files(png, &[("radius", "16"), ("height_scale", "16")]);
            for (name, bytes) in &want {
                let url = format!("{}/v1/bakes/{id}{}", p2.base, result_path(name));
                // A format the submission did not name answers 202 until it is encoded.
                let got = get_result(&c, &url).await.bytes().await.unwrap();
                assert!(got[..] == bytes[..], "bake {id} {name} differs");
            }
        }
        // Nothing duplicated: exactly the four records, and a resubmission finds its bake.
        let list: Value =
            c.get(format!("{}/v1/bakes", p2.base)).send().await.unwrap().json().await.unwrap();
        let listed: Vec<&str> =
            list["items"].as_array().unwrap().iter().map(|v| v["id"].as_str().unwrap()).collect();
        assert_eq!(listed, ids.iter().map(String::as_str).collect::<Vec<_>>());
        let (s, v) = submit(&c, &p2.base, &inputs[0], q).await;
        assert_eq!((s, v["id"].as_str().unwrap()), (200, ids[0].as_str()));
        out
    };
    // The one that was running when killed ran again.
    assert!(before.iter().any(|v| v["attempts"].as_u64().unwrap() >= 2), "{before:?}");
    // 10 results each: png8 and png16 layers, KTX2, DDS, and the EXR layers, whose one re-bake
    // stores both precisions (float and half) at once.
    assert_eq!(blob_files(&data).len(), 4 + 4 * 10, "4 inputs + 10 results each");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigterm_drains_then_requeues_and_the_next_start_finishes() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let c = client();
    let big = terrain_png16(2048, 2048, 5);
    // Grace 0: the bake running at SIGTERM goes straight back to the queue. (The 503s while
    // draining are checked in-process by tests/service/api.rs, where the drain can be held open.)
    let p = spawn(&data, &["--shutdown-grace-secs", "0"]);
    let (s, v) = submit(&c, &p.base, &big, "radius=16").await;
    assert_eq!(s, 202);
    let id = v["id"].as_str().unwrap().to_owned();
    let (s, v) = submit(&c, &p.base, &terrain_png16(32, 32, 6), "radius=4").await;
    assert_eq!(s, 202);
    let small = v["id"].as_str().unwrap().to_owned();
    wait_running(&c, &p.base).await;
    // A client watching the running bake: its stream must end with a final `done` event when
    // the server shuts down, not just break off.
    let events = c.get(format!("{}/v1/bakes/{id}/events", p.base)).send().await.unwrap();
    assert_eq!(events.status(), 200);
    let watched = tokio::spawn(async move { events.text().await });
    let pid = p.child.id().to_string();
    assert!(Command::new("kill").args(["-TERM", &pid]).status().unwrap().success());
    let mut p = p;
    let t = Instant::now();
    let status = loop {
        if let Some(st) = p.child.try_wait().unwrap() {
            break st;
        }
        assert!(t.elapsed() < Duration::from_secs(20), "did not exit after SIGTERM");
        std::thread::sleep(Duration::from_millis(20));
    };
    assert!(status.success(), "{status:?}");
    let text = tokio::time::timeout(Duration::from_secs(10), watched)
        .await
        .expect("the event stream did not end with the server")
        .unwrap()
        .unwrap_or_default();
    let last = text.split("\n\n").filter(|b| b.contains("event:")).last().unwrap_or("");
    assert!(last.contains("event: done"), "the stream ended without `done`: {text}");

    let p2 = spawn(&data, &[]);
    let v = wait_done(&c, &format!("{}/v1/bakes/{id}", p2.base), Duration::from_secs(300)).await;
    assert_eq!(v["status"], "succeeded", "{v}");
    assert_eq!(v["attempts"], 2, "the running bake was returned to the queue and re-run: {v}");
    let v = wait_done(&c, &format!("{}/v1/bakes/{small}", p2.base), Duration::from_secs(60)).await;
    assert_eq!((v["status"].as_str(), v["attempts"].as_u64()), (Some("succeeded"), Some(1)));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn downloads_are_byte_identical_to_the_cli() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("in.png");
    let png = terrain_png16(93, 61, 11);
    std::fs::write(&input, &png).unwrap();
    let flags = ["--radius", "12", "--height-scale", "20", "--edge", "none", "--encoding", "sqrt"];
    let cli = |out: &str, format: &str| {
        let st = Command::new(env!("CARGO_BIN_EXE_horizon-bake"))
            .arg("bake")
            .arg(&input)
            .arg("-o")
            .arg(dir.path().join(out))
            .args(flags)
            .args(["--format", format])
            .stdout(Stdio::null())
            .status()
            .unwrap();
        assert!(st.success(), "cli bake {format}");
    };
    cli("a", "exr,ktx2,dds");
    cli("b", "png16");
    cli("c", "png8");
    let p = spawn(&dir.path().join("data"), &[]);
    let c = client();
    let (s, v) =
        submit(&c, &p.base, &png, "radius=12&height_scale=20&edge=none&encoding=sqrt").await;
    assert_eq!(s, 202);
    let url = format!("{}/v1/bakes/{}", p.base, v["id"].as_str().unwrap());
    assert_eq!(wait_done(&c, &url, Duration::from_secs(60)).await["status"], "succeeded");
    let pairs = [
        ("horizon_0.png8", "c/horizon_0.png"),
        ("horizon_1.png8", "c/horizon_1.png"),
        ("horizon_0.exr", "a/horizon_0.exr"),
        ("horizon_1.exr", "a/horizon_1.exr"),
        ("horizon.ktx2", "a/horizon.ktx2"),
        ("horizon.dds", "a/horizon.dds"),
        ("horizon_0.png16", "b/horizon_0.png"),
        ("horizon_1.png16", "b/horizon_1.png"),
    ];
    for (name, file) in pairs {
        let want = std::fs::read(dir.path().join(file)).unwrap();
        let got =
            get_result(&c, &format!("{url}{}", result_path(name))).await.bytes().await.unwrap();
        assert!(got[..] == want[..], "{name} differs from the CLI's {file}");
    }
}

/// `serve` opens its store before it says it is listening: a data directory locked by a running
/// server, or a corrupt `bakes.redb`, exits non-zero naming the file, with no address file and no
/// `listening` line.
#[test]
fn serve_refuses_a_locked_or_corrupt_store_before_listening() {
    let tmp = tempfile::tempdir().unwrap();
    let locked = tmp.path().join("locked");
    let _first = spawn(&locked, &[]);
    let corrupt = tmp.path().join("corrupt");
    std::fs::create_dir_all(&corrupt).unwrap();
    std::fs::write(corrupt.join("bakes.redb"), vec![0x5a; 4096]).unwrap();
    for data in [&locked, &corrupt] {
        let addr_file = tmp.path().join("second.addr");
        let out = Command::new(env!("CARGO_BIN_EXE_horizon-bake"))
            .arg("serve")
            .args(["--addr", "127.0.0.1:0", "--data-dir"])
            .arg(data)
            .arg("--addr-file")
            .arg(&addr_file)
            .env_remove("HORIZON_API_KEY")
            .env("RUST_LOG", "off")
            .output()
            .unwrap();
        let stdout = String::from_utf8_lossy(&out.stdout);
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{}: {stdout} {stderr}", data.display());
        assert!(!stdout.contains("listening"), "{stdout}");
        assert!(!addr_file.exists(), "{}: an address file was written", data.display());
        let path = data.join("bakes.redb");
        assert!(stderr.contains(path.to_str().unwrap()), "{stderr} does not name the store");
    }
}

/// What an operator reads: one log line per request with method, path, status, latency and
/// request id; one line per failed bake naming it; no colour codes when the log is a file.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_log_has_a_line_per_request_and_per_failed_bake_without_colours() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let log_path = dir.path().join("server.log");
    let log = std::fs::File::create(&log_path).unwrap();
    let mut p = spawn_with(&data, &[], Stdio::from(log), "info");
    let c = client();
    let res = c.get(format!("{}/v1/bakes", p.base)).header("x-request-id", "log-a").send();
    assert_eq!(res.await.unwrap().status(), 200);
    let res = c.get(format!("{}/v1/bakes/nope", p.base)).header("x-request-id", "log-b").send();
    assert_eq!(res.await.unwrap().status(), 404);
    // A PNG whose header is sound but whose pixel data is not: accepted (the header check
    // passes), then the bake fails when the worker decodes it.
    let mut png = terrain_png16(64, 64, 3);
    let n = png.len();
    for b in &mut png[n / 2..n / 2 + 64] {
        *b ^= 0x5a;
    }
    let (s, v) = submit(&c, &p.base, &png, "radius=4").await;
    assert_eq!(s, 202, "{v}");
    let id = v["id"].as_str().unwrap().to_owned();
    let v = wait_done(&c, &format!("{}/v1/bakes/{id}", p.base), Duration::from_secs(60)).await;
    assert_eq!(v["status"], "failed", "{v}");
    let _ = Command::new("kill").args(["-TERM", &p.child.id().to_string()]).status();
    let _ = p.child.wait();

    let text = std::fs::read_to_string(&log_path).unwrap();
    assert!(!text.contains('\u{1b}'), "colour codes in a log file:\n{text}");
    let lines_with = |needle: &str| text.lines().filter(|l| l.contains(needle)).collect::<Vec<_>>();
    let a = lines_with("request_id=log-a");
    assert_eq!(a.len(), 1, "one line per request:\n{text}");
    for part in ["method=GET", "path=/v1/bakes ", "status=200", "latency_ms="] {
        assert!(a[0].contains(part), "`{part}` missing from {:?}", a[0]);
    }
    let b = lines_with("request_id=log-b");
    assert_eq!(b.len(), 1, "{text}");
    assert!(b[0].contains("status=404") && b[0].contains("path=/v1/bakes/nope"), "{:?}", b[0]);
    // Requests without an id of their own get one, so every request line has one.
    for l in lines_with(" request ") {
        assert!(l.contains("request_id="), "{l}");
    }
    let failed = lines_with("bake failed");
    assert_eq!(failed.len(), 1, "one line per failed bake:\n{text}");
    assert!(failed[0].contains(&id), "{:?}", failed[0]);
}
