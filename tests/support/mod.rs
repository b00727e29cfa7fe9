//! Helpers shared by every integration-test binary (`tests/<binary>/main.rs` includes this file
//! as `mod support`): the golden files, a deterministic RNG, kernel oracles, synthetic height
//! maps, a server on 127.0.0.1:0, polling. Not every binary uses every helper, hence the
//! `dead_code` allowance. The real-engines cluster harness is `support/cluster.rs`, included only
//! by the cluster binary.
#![allow(dead_code)]

use horizon_bake::bake::{self, Precisions};
use horizon_bake::encode::png::{encode16, encode8, PngColor};
use horizon_bake::encode::{self, Formats, TexturePrecision};
use horizon_bake::heightmap::{self, Limits};
use horizon_bake::kernels::{Grid, HorizonRows};
use horizon_bake::params::BakeParams;
use horizon_bake::params::Edge;
use horizon_bake::progress::Progress;
use horizon_bake::service::{self, AppState, Config};
use serde_json::Value;
use std::collections::BTreeMap;
use std::path::PathBuf;
use std::time::{Duration, Instant};

/// The golden files, kept in the repository (tests/golden: a copy of the shared acceptance set), so
/// a lone clone passes its tests; `HORIZON_GOLDEN_DIR` points at another copy instead.
pub fn golden_dir() -> PathBuf {
    if let Ok(d) = std::env::var("HORIZON_GOLDEN_DIR") {
        return PathBuf::from(d);
    }
    let d = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/golden");
    assert!(
        d.join("cases.json").exists(),
        "golden files not found at {} (set HORIZON_GOLDEN_DIR)",
        d.display()
    );
    d
}

/// Whether python3 with rasterio and numpy (GDAL, for reading our GeoTIFFs back) is here; when
/// it is not, says so (the caller skips its read-back), except under `CI=true`, where that is
/// a failure.
pub fn has_rasterio() -> bool {
    let ci = std::env::var("CI").is_ok_and(|v| v == "true");
    let has = std::process::Command::new("python3")
        .args(["-c", "import rasterio, numpy"])
        .status()
        .is_ok_and(|s| s.success());
    if !has {
        assert!(!ci, "CI=true: python3 with rasterio and numpy is required (pip install rasterio)");
        eprintln!("skipped the GDAL read-back: python3 with rasterio is missing");
    }
    has
}

/// Little-endian f32 file.
pub fn read_f32(path: &std::path::Path) -> Vec<f32> {
    let b = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    b.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect()
}

/// A tiny deterministic RNG (SplitMix64) so property tests need no extra crates to reproduce.
/// The one RNG of every binary: the service tests had a copy of `next_u64`, the same algorithm
/// (checked to give the same sequences), so no test's random input changed when they merged.
pub struct Rng(pub u64);
impl Rng {
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    pub fn f32(&mut self) -> f32 {
        (self.next_u64() >> 40) as f32 / (1u64 << 24) as f32
    }
    pub fn range(&mut self, lo: usize, hi: usize) -> usize {
        lo + (self.next_u64() % (hi - lo + 1) as u64) as usize
    }
}

/// The bilinear surface at image point (X, Y): wrapped, or on [0, W−1]×[0, H−1] for edge=none.
pub fn surface(g: &Grid<'_>, x: f64, y: f64) -> f64 {
    let (w, h) = (g.width as i64, g.height as i64);
    let cell = |p: f64, n: i64| -> (i64, f64) {
        let mut c = p.floor() as i64;
        if g.edge == Edge::None {
            c = c.clamp(0, (n - 2).max(0));
        }
        (c, p - c as f64)
    };
    let (cx, fx) = cell(x, w);
    let (cy, fy) = cell(y, h);
    let at = |c: i64, r: i64| -> f64 {
        let (c, r) = match g.edge {
            Edge::Wrap => (c.rem_euclid(w), r.rem_euclid(h)),
            Edge::None => (c.clamp(0, w - 1), r.clamp(0, h - 1)),
        };
        g.heights[(r * w + c) as usize] as f64
    };
    let top = at(cx, cy) * (1.0 - fx) + at(cx + 1, cy) * fx;
    let bot = at(cx, cy + 1) * (1.0 - fx) + at(cx + 1, cy + 1) * fx;
    top * (1.0 - fy) + bot * fy
}

/// Three smooth waves of whole periods over the map (so `edge=wrap` has no seam): frequencies
/// 0..=`max_freq` per axis, amplitudes up to `amp` texels, random phases.
pub fn waves(rng: &mut Rng, w: usize, h: usize, max_freq: usize, amp: f32) -> Vec<f32> {
    let mut v = vec![0.0f32; w * h];
    for _ in 0..3 {
        let (fx, fy) = (rng.range(0, max_freq) as f32, rng.range(0, max_freq) as f32);
        let (a, p) = (amp * rng.f32(), std::f32::consts::TAU * rng.f32());
        for r in 0..h {
            for c in 0..w {
                let t = std::f32::consts::TAU
                    * (fx * c as f32 / w as f32 + fy * r as f32 / h as f32)
                    + p;
                v[r * w + c] += a * t.sin();
            }
        }
    }
    v
}

/// Per-bin sin α of every texel of `k` (`bins_out`), computed in bands of `band` rows so band
/// seams are exercised.
pub fn per_bin(k: &dyn HorizonRows, band: usize) -> Vec<f32> {
    let (w, h, nb) = (k.width(), k.height(), k.bins());
    let mut out = vec![0.0f32; w * h * nb];
    let mut ch = vec![0.0f32; w * band * 8];
    for y0 in (0..h).step_by(band) {
        let rows = band.min(h - y0);
        k.rows(y0, &mut ch[..rows * w * 8], Some(&mut out[y0 * w * nb..(y0 + rows) * w * nb]));
    }
    out
}

/// Mean and 99th percentile of `d`.
pub fn mean_p99(mut d: Vec<f64>) -> (f64, f64) {
    let mean = d.iter().sum::<f64>() / d.len() as f64;
    d.sort_by(f64::total_cmp);
    (mean, d[((d.len() as f64 * 0.99) as usize).min(d.len() - 1)])
}

// ---------------------------------------------------------------------------------------------
// Service tests: synthetic height maps, a server on 127.0.0.1:0, polling.

/// A 16-bit gray PNG of smooth random terrain (a few summed waves plus noise).
pub fn terrain_png16(w: usize, h: usize, seed: u64) -> Vec<u8> {
    encode16(w, h, PngColor::Gray, &terrain16(w, h, seed)).unwrap()
}

/// The samples of [`terrain_png16`], row-major.
pub fn terrain16(w: usize, h: usize, seed: u64) -> Vec<u16> {
    let mut rng = Rng(seed);
    let waves: Vec<(f64, f64, f64)> = (0..4)
        .map(|_| {
            let a = (rng.next_u64() % 1000) as f64 / 1000.0 * std::f64::consts::TAU;
            let f = 1.0 + (rng.next_u64() % 6) as f64;
            let p = (rng.next_u64() % 1000) as f64 / 1000.0 * std::f64::consts::TAU;
            (a, f, p)
        })
        .collect();
    let mut data = Vec::with_capacity(w * h);
    for y in 0..h {
        for x in 0..w {
            let (u, v) = (x as f64 / w as f64, y as f64 / h as f64);
            let mut s = 0.0;
            for &(a, f, p) in &waves {
                s += (std::f64::consts::TAU * f * (u * a.cos() + v * a.sin()) + p).sin();
            }
            let noise = (rng.next_u64() % 1000) as f64 / 1000.0 - 0.5;
            let val = ((s / 4.0 + 1.0) * 0.5 * 0.95 + noise * 0.05).clamp(0.0, 1.0);
            data.push((val * 65535.0) as u16);
        }
    }
    data
}

/// An 8-bit gray PNG of white noise (cheap to make at 4096²).
pub fn noise_png8(w: usize, h: usize, seed: u64) -> Vec<u8> {
    let mut rng = Rng(seed);
    let data: Vec<u8> = (0..w * h).map(|_| (rng.next_u64() >> 56) as u8).collect();
    encode8(w, h, PngColor::Gray, &data).unwrap()
}

/// What the library produces for `png` and `pairs`, by the service's result name:
/// `horizon_{0,1}.png8`, `horizon_{0,1}.png16` (streamed, as `bake --format png8|png16` writes
/// them), `horizon_{0,1}.exr`, `horizon.ktx2`, `horizon.dds`.
pub fn library_files(png: &[u8], pairs: &[(&str, &str)]) -> BTreeMap<String, Vec<u8>> {
    let params = BakeParams::from_pairs(pairs.iter().copied()).unwrap();
    let (map, _) = heightmap::decode(png, params.channel, &Limits::default()).unwrap();
    let mut out = BTreeMap::new();
    let (p8, _) = horizon_bake::pipeline::stream_horizon_pngs::<u8, _>(
        map.clone(),
        &params,
        &Progress::new(),
        [Vec::new(), Vec::new()],
    )
    .unwrap();
    let (p16, _) = horizon_bake::pipeline::stream_horizon_pngs::<u16, _>(
        map.clone(),
        &params,
        &Progress::new(),
        [Vec::new(), Vec::new()],
    )
    .unwrap();
    for (k, (a, b)) in p8.into_iter().zip(p16).enumerate() {
        out.insert(format!("horizon_{k}.png8"), a);
        out.insert(format!("horizon_{k}.png16"), b);
    }
    let (layers, _) = bake::bake_horizon(&map, &params, Precisions::ALL, &Progress::new()).unwrap();
    let mut rest = Formats::parse("exr,ktx2,dds", TexturePrecision::Unorm8).unwrap();
    // The KTX2 file states the bake's y_axis and encoding (SPEC §8), as the service's does.
    rest.conventions = horizon_bake::pipeline::conventions(&params);
    for file in encode::horizon_files(&layers, &rest).unwrap() {
        out.insert(file.name.to_owned(), file.bytes);
    }
    out
}

/// The download URL path (after `/v1/bakes/{id}`) of a result name.
pub fn result_path(name: &str) -> String {
    match name {
        "horizon.ktx2" | "horizon.dds" => format!("/{name}"),
        _ => {
            let (stem, fmt) = name.split_once('.').unwrap();
            let layer = stem.trim_start_matches("horizon_");
            format!("/horizon/{layer}?format={fmt}")
        }
    }
}

/// A server running in this process on 127.0.0.1:0.
pub struct Server {
    pub base: String,
    pub dir: tempfile::TempDir,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    handle: Option<tokio::task::JoinHandle<horizon_bake::Result<()>>>,
}

impl Server {
    /// Starts a server on a fresh data directory, `tweak`ing the default config first.
    pub async fn start(tweak: impl FnOnce(&mut Config)) -> Server {
        let dir = tempfile::tempdir().unwrap();
        Self::start_in(dir, tweak).await
    }

    /// Starts a server on `dir`.
    pub async fn start_in(dir: tempfile::TempDir, tweak: impl FnOnce(&mut Config)) -> Server {
        let mut config = Config::for_dir(dir.path()).unwrap();
        config.bake_threads = 2;
        tweak(&mut config);
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let base = format!("http://{}", listener.local_addr().unwrap());
        let (tx, rx) = tokio::sync::oneshot::channel::<()>();
        let handle = tokio::spawn(service::run(config, listener, async move {
            let _ = rx.await;
        }));
        Server { base, dir, stop: Some(tx), handle: Some(handle) }
    }

    /// Shuts down gracefully and returns the data directory.
    pub async fn stop(mut self) -> tempfile::TempDir {
        if let Some(tx) = self.stop.take() {
            let _ = tx.send(());
        }
        if let Some(h) = self.handle.take() {
            h.await.unwrap().unwrap();
        }
        let dir = tempfile::tempdir().unwrap();
        std::mem::replace(&mut self.dir, dir)
    }

    pub fn url(&self, path: &str) -> String {
        format!("{}{}", self.base, path)
    }
}

/// An AppState on a fresh directory whose dispatcher is NOT started: bakes stay queued.
pub fn idle_state(tweak: impl FnOnce(&mut Config)) -> (AppState, tempfile::TempDir) {
    let dir = tempfile::tempdir().unwrap();
    let mut config = Config::for_dir(dir.path()).unwrap();
    config.bake_threads = 1;
    tweak(&mut config);
    (AppState::open(config).unwrap(), dir)
}

/// Like [`idle_state`], also returning the embedded repository, whose record table a test can
/// edit directly (to age a record, say).
pub fn idle_state_with_repo(
    tweak: impl FnOnce(&mut Config),
) -> (AppState, std::sync::Arc<horizon_bake::jobs::repo::EmbeddedRepo>, tempfile::TempDir) {
    let dir = tempfile::tempdir().unwrap();
    let mut config = Config::for_dir(dir.path()).unwrap();
    config.bake_threads = 1;
    tweak(&mut config);
    let repo = std::sync::Arc::new(
        horizon_bake::jobs::repo::EmbeddedRepo::open(&dir.path().join("bakes.redb")).unwrap(),
    );
    let blobs = std::sync::Arc::new(
        horizon_bake::jobs::blob::FsBlobStore::open(&dir.path().join("blobs")).unwrap(),
    );
    (AppState::with_stores(config, repo.clone(), blobs).unwrap(), repo, dir)
}

pub fn client() -> reqwest::Client {
    reqwest::Client::builder().timeout(Duration::from_secs(120)).build().unwrap()
}

/// `GET url` of a result, asking again while the server answers 202 (a format the bake did not
/// encode is encoded in the background after its first request); the first answer that is not
/// 202.
pub async fn get_result(c: &reqwest::Client, url: &str) -> reqwest::Response {
    let t = Instant::now();
    loop {
        let res = c.get(url).send().await.unwrap();
        if res.status() != 202 {
            return res;
        }
        assert!(res.headers().contains_key("retry-after"), "202 without Retry-After: {url}");
        assert!(t.elapsed() < Duration::from_secs(120), "{url} still encoding after 2 minutes");
        tokio::time::sleep(Duration::from_millis(25)).await;
    }
}

/// POSTs `png` as a raw `image/png` body with `query`, expects 202, waits until the bake
/// succeeded and returns its `Location`.
pub async fn submit_png_done(c: &reqwest::Client, srv: &Server, query: &str, png: &[u8]) -> String {
    let res = c
        .post(srv.url(&format!("/v1/bakes?{query}")))
        .header("content-type", "image/png")
        .body(png.to_vec())
        .send()
        .await
        .unwrap();
    assert_eq!(res.status(), 202, "{query}");
    let loc = res.headers()["location"].to_str().unwrap().to_owned();
    let done = wait_done(c, &srv.url(&loc), Duration::from_secs(60)).await;
    assert_eq!(done["status"], "succeeded", "{done}");
    loc
}

/// Polls `GET url` until `status` is terminal; returns the resource.
pub async fn wait_done(c: &reqwest::Client, url: &str, limit: Duration) -> Value {
    let t = Instant::now();
    loop {
        let v: Value = c.get(url).send().await.unwrap().json().await.unwrap();
        let s = v["status"].as_str().unwrap().to_owned();
        if matches!(s.as_str(), "succeeded" | "failed" | "canceled") {
            return v;
        }
        assert!(t.elapsed() < limit, "bake not finished after {limit:?}: {v}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// Files under `dir` (recursively), excluding the redb file.
pub fn blob_files(dir: &std::path::Path) -> Vec<std::path::PathBuf> {
    let mut out = Vec::new();
    let mut stack = vec![dir.join("blobs")];
    while let Some(d) = stack.pop() {
        let Ok(rd) = std::fs::read_dir(&d) else { continue };
        for e in rd.flatten() {
            let p = e.path();
            if p.is_dir() {
                stack.push(p);
            } else {
                out.push(p);
            }
        }
    }
    out
}

/// A PNG whose IHDR claims `w`×`h` (valid CRC) with no pixel data: a decompression bomb header.
pub fn bomb_png(w: u32, h: u32) -> Vec<u8> {
    let mut ihdr = Vec::new();
    ihdr.extend_from_slice(b"IHDR");
    ihdr.extend_from_slice(&w.to_be_bytes());
    ihdr.extend_from_slice(&h.to_be_bytes());
    ihdr.extend_from_slice(&[8, 0, 0, 0, 0]);
    let crc = crc32(&ihdr);
    let mut png = b"\x89PNG\r\n\x1a\n".to_vec();
    png.extend_from_slice(&13u32.to_be_bytes());
    png.extend_from_slice(&ihdr);
    png.extend_from_slice(&crc.to_be_bytes());
    // A tiny IDAT (an empty zlib stream): whatever it claims, the header alone must reject it.
    let idat: &[u8] = b"IDAT\x78\x9c\x03\x00\x00\x00\x00\x01";
    png.extend_from_slice(&((idat.len() - 4) as u32).to_be_bytes());
    png.extend_from_slice(idat);
    png.extend_from_slice(&crc32(idat).to_be_bytes());
    png.extend_from_slice(&0u32.to_be_bytes());
    png.extend_from_slice(b"IEND");
    png.extend_from_slice(&crc32(b"IEND").to_be_bytes());
    png
}

fn crc32(data: &[u8]) -> u32 {
    let mut crc = 0xffff_ffffu32;
    for &b in data {
        crc ^= b as u32;
        for _ in 0..8 {
            crc = if crc & 1 != 0 { (crc >> 1) ^ 0xedb8_8320 } else { crc >> 1 };
        }
    }
    !crc
}

/// The binary under test, as a command.
pub fn bin() -> std::process::Command {
    std::process::Command::new(env!("CARGO_BIN_EXE_horizon-bake"))
}

/// POSTs `png` as a raw `image/png` body to `/v1/bakes{query}`, expects 202, returns `Location`.
pub async fn submit_ok(c: &reqwest::Client, srv: &Server, png: &[u8], query: &str) -> String {
    let res = c
        .post(srv.url(&format!("/v1/bakes{query}")))
        .header("content-type", "image/png")
        .body(png.to_vec())
        .send()
        .await
        .unwrap();
    assert_eq!(res.status(), 202);
    res.headers()["location"].to_str().unwrap().to_owned()
}

/// A raw `image/png` submission of `png` to `/v1/bakes{query}`, for `oneshot`.
pub fn raw_submit(png: &[u8], query: &str) -> axum::http::Request<axum::body::Body> {
    axum::http::Request::post(format!("/v1/bakes{query}"))
        .header("content-type", "image/png")
        .body(axum::body::Body::from(png.to_vec()))
        .unwrap()
}

/// The status and body of a problem+json answer (asserting its content type).
pub async fn problem(res: reqwest::Response) -> (u16, Value) {
    let status = res.status().as_u16();
    assert_eq!(res.headers()["content-type"], "application/problem+json");
    (status, res.json().await.unwrap())
}

/// The value of the counter line `series` (name and labels, as exposed) in the server's
/// /metrics; panics if the server does not expose it.
pub async fn counter(c: &reqwest::Client, srv: &Server, series: &str) -> u64 {
    let text = c.get(srv.url("/metrics")).send().await.unwrap().text().await.unwrap();
    let key = format!("{series} ");
    let line = text.lines().find(|l| l.starts_with(&key)).unwrap_or_else(|| panic!("{series}"));
    line[key.len()..].parse().unwrap()
}

/// Sends `req` to the router in this process: the status and the body as JSON (null if none).
pub async fn oneshot(
    app: &axum::Router,
    req: axum::http::Request<axum::body::Body>,
) -> (axum::http::StatusCode, serde_json::Value) {
    let (status, _, v) = oneshot_with_headers(app, req).await;
    (axum::http::StatusCode::from_u16(status).unwrap(), v)
}

/// [`oneshot`] with the response's headers too.
pub async fn oneshot_with_headers(
    app: &axum::Router,
    req: axum::http::Request<axum::body::Body>,
) -> (u16, axum::http::HeaderMap, serde_json::Value) {
    use tower::ServiceExt;
    let res = app.clone().oneshot(req).await.unwrap();
    let (parts, body) = res.into_parts();
    let bytes = axum::body::to_bytes(body, usize::MAX).await.unwrap();
    let v = serde_json::from_slice(&bytes).unwrap_or(serde_json::Value::Null);
    (parts.status.as_u16(), parts.headers, v)
}
