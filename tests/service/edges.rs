//! Regression tests of the sharp edges of issue 25, each written to fail before its fix: ranged
//! downloads, parameter combinations that make no sense, error messages that leave out what a
//! client needs, the CLI on a closed pipe and contact sheets, security headers, PNG sizes, and
//! the first request of a format the bake did not encode.

use crate::support::*;
use serde_json::Value;
use std::time::Duration;

async fn submit_ok(c: &reqwest::Client, srv: &Server, png: &[u8], query: &str) -> String {
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

/// A succeeded bake of a small map on a fresh server: (server, client, bake path).
async fn baked(query: &str) -> (Server, reqwest::Client, String) {
    let srv = Server::start(|_| {}).await;
    let c = client();
    let loc = submit_ok(&c, &srv, &terrain_png16(48, 40, 7), query).await;
    let v = wait_done(&c, &srv.url(&loc), Duration::from_secs(60)).await;
    assert_eq!(v["status"], "succeeded", "{v}");
    (srv, c, loc)
}

/// Downloads answer one byte range with 206 and only those bytes, a range past the end with
/// 416 and `Content-Range: bytes */len`, and say `Accept-Ranges: bytes`.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn downloads_answer_byte_ranges() {
    let (srv, c, loc) = baked("?radius=4").await;
    let url = srv.url(&format!("{loc}/horizon/0"));
    let full = c.get(&url).send().await.unwrap();
    assert_eq!(full.status(), 200);
    assert_eq!(full.headers()["accept-ranges"], "bytes");
    let etag = full.headers()["etag"].to_str().unwrap().to_owned();
    let full = full.bytes().await.unwrap();
    let len = full.len();
    assert!(len > 100, "{len}");

    let cases: [(String, usize, usize); 4] = [
        ("bytes=10-19".into(), 10, 20),
        (format!("bytes={}-", len - 7), len - 7, len),
        ("bytes=-5".into(), len - 5, len),
        (format!("bytes=3-{}", len + 1000), 3, len),
    ];
    for (range, a, b) in cases {
        let res = c.get(&url).header("range", &range).send().await.unwrap();
        assert_eq!(res.status(), 206, "{range}");
        assert_eq!(res.headers()["accept-ranges"], "bytes");
        assert_eq!(res.headers()["content-range"], format!("bytes {a}-{}/{len}", b - 1), "{range}");
        assert_eq!(res.headers()["content-length"], (b - a).to_string().as_str());
        assert_eq!(res.headers()["etag"], etag.as_str());
        assert_eq!(&res.bytes().await.unwrap()[..], &full[a..b], "{range}");
    }

    let res = c.get(&url).header("range", format!("bytes={len}-")).send().await.unwrap();
    assert_eq!(res.status(), 416);
    assert_eq!(res.headers()["content-range"], format!("bytes */{len}"));
    assert_eq!(res.headers()["content-type"], "application/problem+json");
    let v: Value = res.json().await.unwrap();
    assert_eq!(v["code"], "range_not_satisfiable");

    // An If-Range that no longer matches, or several ranges, get the whole body.
    let res = c
        .get(&url)
        .header("range", "bytes=0-3")
        .header("if-range", "\"stale\"")
        .send()
        .await
        .unwrap();
    assert_eq!(res.status(), 200);
    assert_eq!(res.bytes().await.unwrap().len(), len);
    let res = c.get(&url).header("range", "bytes=0-3, 8-9").send().await.unwrap();
    assert_eq!(res.status(), 200);
    let res =
        c.get(&url).header("range", "bytes=0-3").header("if-range", &etag).send().await.unwrap();
    assert_eq!(res.status(), 206);
    assert_eq!(&res.bytes().await.unwrap()[..], &full[0..4]);
    srv.stop().await;
}

async fn oneshot(
    app: &axum::Router,
    req: axum::http::Request<axum::body::Body>,
) -> (u16, axum::http::HeaderMap, Value) {
    use tower::ServiceExt;
    let res = app.clone().oneshot(req).await.unwrap();
    let (parts, body) = res.into_parts();
    let bytes = axum::body::to_bytes(body, usize::MAX).await.unwrap();
    (parts.status.as_u16(), parts.headers, serde_json::from_slice(&bytes).unwrap_or(Value::Null))
}

fn raw_submit(png: &[u8], query: &str) -> axum::http::Request<axum::body::Body> {
    axum::http::Request::post(format!("/v1/bakes{query}"))
        .header("content-type", "image/png")
        .body(axum::body::Body::from(png.to_vec()))
        .unwrap()
}

fn multipart_submit(
    png: &[u8],
    query: &str,
    params: &str,
) -> axum::http::Request<axum::body::Body> {
    let b = "XbOuNdArY";
    let mut body = Vec::new();
    body.extend_from_slice(
        format!(
            "--{b}\r\ncontent-disposition: form-data; name=\"heightmap\"; filename=\"h.png\"\r\n\
             content-type: image/png\r\n\r\n"
        )
        .as_bytes(),
    );
    body.extend_from_slice(png);
    body.extend_from_slice(
        format!(
            "\r\n--{b}\r\ncontent-disposition: form-data; name=\"params\"\r\n\r\n{params}\r\n--{b}--\r\n"
        )
        .as_bytes(),
    );
    axum::http::Request::post(format!("/v1/bakes{query}"))
        .header("content-type", format!("multipart/form-data; boundary={b}"))
        .body(axum::body::Body::from(body))
        .unwrap()
}

/// `reduce=point` means nothing to Lengyel's splat: a 422 naming `reduce`, however the two keys
/// arrive, while the ray methods take it.
#[tokio::test]
async fn point_reduction_with_lengyel_is_refused() {
    let (st, _dir) = idle_state(|_| {});
    let app = horizon_bake::service::app(st);
    let png = terrain_png16(16, 16, 3);
    for q in ["?reduce=point", "?method=lengyel&reduce=point"] {
        let (s, _, v) = oneshot(&app, raw_submit(&png, q)).await;
        assert_eq!(s, 422, "{q}: {v}");
        assert_eq!(v["field"], "reduce", "{q}: {v}");
        assert!(v["detail"].as_str().unwrap().contains("lengyel"), "{v}");
    }
    let (s, _, v) =
        oneshot(&app, multipart_submit(&png, "?reduce=point", r#"{"method":"lengyel"}"#)).await;
    assert_eq!((s, v["field"].as_str()), (422, Some("reduce")), "{v}");
    let (s, _, v) =
        oneshot(&app, multipart_submit(&png, "?reduce=point", r#"{"method":"exact"}"#)).await;
    assert_eq!(s, 202, "{v}");
    let (s, _, v) = oneshot(&app, raw_submit(&png, "?method=march&reduce=point")).await;
    assert_eq!(s, 202, "{v}");
}

/// The CLI refuses the same combination with exit code 2 and one line naming `reduce`.
#[test]
fn cli_refuses_point_reduction_with_lengyel() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("h.png");
    std::fs::write(&input, terrain_png16(16, 16, 3)).unwrap();
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_horizon-bake"))
        .args(["bake", input.to_str().unwrap(), "-o"])
        .arg(dir.path().join("out"))
        .args(["--reduce", "point"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("reduce") && err.trim().lines().count() == 1, "{err}");
    assert!(!dir.path().join("out").exists());
}

/// A 413 states the limit; an unknown key lists every key a submission takes (the bake
/// parameters from the library's own list, `formats` and `exr_precision`), in the query and in
/// a `params` part alike.
#[tokio::test]
async fn errors_state_the_limit_and_the_known_keys() {
    let (st, _dir) = idle_state(|c| c.max_body_bytes = 3000);
    let app = horizon_bake::service::app(st);
    let big = noise_png8(64, 64, 1);
    assert!(big.len() > 3000);
    let (s, _, v) = oneshot(&app, raw_submit(&big, "")).await;
    assert_eq!(s, 413, "{v}");
    assert!(v["detail"].as_str().unwrap().contains("3000 bytes"), "{v}");

    let (st, _dir) = idle_state(|_| {});
    let app = horizon_bake::service::app(st);
    let png = terrain_png16(16, 16, 3);
    for req in [raw_submit(&png, "?radiuss=4"), multipart_submit(&png, "", r#"{"radiuss": 4}"#)] {
        let (s, _, v) = oneshot(&app, req).await;
        assert_eq!((s, v["field"].as_str()), (422, Some("radiuss")), "{v}");
        let detail = v["detail"].as_str().unwrap();
        let delivery = ["formats", "exr_precision"];
        let texture = horizon_bake::encode::texture::OPTION_KEYS;
        for k in horizon_bake::params::PARAM_NAMES.iter().chain(&delivery).chain(&texture) {
            assert!(detail.contains(&format!(" {k}")), "`{k}` missing from: {detail}");
        }
    }
    // The list is the setter's truth: each listed name is a parameter it knows.
    for k in horizon_bake::params::PARAM_NAMES {
        let mut p = horizon_bake::params::BakeParams::default();
        if let Err(e) = p.set(k, "?") {
            assert!(!e.to_string().contains("unknown parameter"), "{k}: {e}");
        }
    }
    // application/octet-stream is accepted (and documented below).
    let req = axum::http::Request::post("/v1/bakes")
        .header("content-type", "application/octet-stream")
        .body(axum::body::Body::from(png.clone()))
        .unwrap();
    assert_eq!(oneshot(&app, req).await.0, 202);
}

/// openapi.yaml says what the server does: previews on their own pool, preview `size` at most
/// 4096, octet-stream uploads, ranged downloads.
#[test]
fn openapi_states_pools_sizes_uploads_and_ranges() {
    let doc: serde_yaml_ng::Value =
        serde_yaml_ng::from_str(horizon_bake::service::handlers::OPENAPI_YAML).unwrap();
    let paths = &doc["paths"];
    let preview = &paths["/v1/bakes/{id}/preview"]["get"];
    let desc = preview["description"].as_str().unwrap();
    assert!(!desc.contains("bake pool.") && desc.contains("preview pool"), "{desc}");
    let size =
        preview["parameters"].as_sequence().unwrap().iter().find(|p| p["name"] == "size").unwrap();
    assert!(size["description"].as_str().unwrap().contains("4096"), "{size:?}");
    assert_eq!(horizon_bake::preview::MAX_SIZE, 4096);
    let body = &paths["/v1/bakes"]["post"]["requestBody"]["content"];
    assert!(!body["application/octet-stream"].is_null());
    for p in ["/v1/bakes/{id}/horizon/{layer}", "/v1/bakes/{id}/horizon.ktx2"] {
        let r = &paths[p]["get"]["responses"];
        assert!(!r["206"].is_null() && !r["416"].is_null(), "{p}");
    }
}

/// `preview -o - | head -c 8`: the reader closes the pipe after 8 bytes; the CLI exits 0 and
/// prints nothing (a real pipe, from a real process; the PNG is far larger than a pipe buffer).
#[test]
fn preview_to_a_closed_pipe_exits_quietly() {
    use std::io::Read;
    use std::process::{Command, Stdio};
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("h.png");
    std::fs::write(&input, noise_png8(256, 256, 9)).unwrap();
    let mut child = Command::new(env!("CARGO_BIN_EXE_horizon-bake"))
        .args(["preview", input.to_str().unwrap(), "-o", "-", "--shading", "none"])
        .args(["--size", "1024", "--radius", "2"])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut head = [0u8; 8];
    let mut stdout = child.stdout.take().unwrap();
    stdout.read_exact(&mut head).unwrap();
    assert_eq!(&head, b"\x89PNG\r\n\x1a\n");
    drop(stdout);
    let out = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.is_empty(), "stderr: {err}");
    assert_eq!(out.status.code(), Some(0), "{:?}", out.status);
}

/// A contact sheet of a large map: tiles default to 512 px and labels scale with them (the CLI,
/// on a real file).
#[test]
fn contact_sheet_tiles_default_to_512_with_scaled_labels() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("h.png");
    std::fs::write(&input, terrain_png16(1024, 768, 5)).unwrap();
    let out_png = dir.path().join("sheet.png");
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_horizon-bake"))
        .args(["preview", input.to_str().unwrap(), "-o", out_png.to_str().unwrap()])
        .args(["--contact-sheet", "4", "--shading", "none"])
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let img = image::open(&out_png).unwrap().to_rgba8();
    // 2×2 tiles of 512×384 with a 4 px gap, labels 8× the 7 px font plus two 4 px gaps.
    let (tw, th, gap, scale) = (512u32, 384u32, 4u32, 8u32);
    let label_h = 7 * scale + 2 * gap;
    assert_eq!(img.dimensions(), (gap + 2 * (tw + gap), gap + 2 * (th + label_h + gap)));
    // The first label ("AZ …°") is drawn with 8×8 px font pixels: its lit rows span 7·8 px.
    let (x0, y0) = (gap, gap + th + gap);
    let lit_rows: Vec<u32> = (y0..y0 + label_h)
        .filter(|&y| (x0..x0 + tw).any(|x| img.get_pixel(x, y).0[..3] == [240, 240, 240]))
        .collect();
    assert_eq!(lit_rows.len() as u32, 7 * scale, "{lit_rows:?}");
    assert_eq!(horizon_bake::preview::label_scale(40), 1);
}

fn get(path: &str) -> axum::http::Request<axum::body::Body> {
    axum::http::Request::get(path).body(axum::body::Body::empty()).unwrap()
}

/// Every answer carries nosniff and no-referrer; the page a CSP that forbids framing and
/// anything not from this server, and the page has nothing inline for it to block. CORS is off
/// unless `--cors-origin` names an origin.
#[tokio::test]
async fn security_headers_and_cors() {
    let (st, _dir) = idle_state(|_| {});
    let app = horizon_bake::service::app(st);
    for path in ["/", "/healthz", "/v1/bakes", "/v1/bakes/nope", "/no/such/route", "/ui/app.js"] {
        let (_, h, _) = oneshot(&app, get(path)).await;
        assert_eq!(h["x-content-type-options"], "nosniff", "{path}");
        assert_eq!(h["referrer-policy"], "no-referrer", "{path}");
        assert!(h.get("access-control-allow-origin").is_none(), "{path}");
    }
    let (s, h, _) = oneshot(&app, get("/")).await;
    assert_eq!(s, 200);
    let csp = h["content-security-policy"].to_str().unwrap();
    assert!(csp.contains("default-src 'self'") && csp.contains("frame-ancestors 'none'"), "{csp}");
    assert!(!csp.contains("unsafe-inline") && !csp.contains("unsafe-eval"), "{csp}");

    // Nothing inline: scripts only by src (a JSON data block is not script), no handler or
    // style attributes, no `javascript:` URLs; the modules build no HTML with them either.
    let html = horizon_bake::service::ui::INDEX_HTML;
    let lower = html.to_ascii_lowercase();
    for (i, _) in lower.match_indices("<script") {
        let tag = &lower[i..i + lower[i..].find('>').unwrap()];
        assert!(tag.contains(" src=") || tag.contains("application/json"), "inline script: {tag}");
    }
    let attr = |text: &str, what: &str| {
        let b = text.as_bytes();
        text.match_indices(what).any(|(i, _)| i > 0 && b[i - 1].is_ascii_whitespace())
    };
    for bad in ["style=", "javascript:"] {
        assert!(!lower.contains(bad) || !attr(&lower, bad), "index.html has `{bad}`");
    }
    for ev in ["onclick=", "onload=", "onchange=", "oninput=", "onsubmit=", "onerror="] {
        assert!(!attr(&lower, ev), "index.html has an inline handler `{ev}`");
    }
    for (name, _, js) in horizon_bake::service::ui::ASSETS {
        for bad in
            ["innerHTML", "eval(", "new Function", "setAttribute('style'", "'style':", "style: '"]
        {
            assert!(!js.contains(bad), "{name} uses `{bad}`, which the CSP blocks or invites");
        }
    }

    let (st, _dir) = idle_state(|c| c.cors_origin = Some("https://tools.example".into()));
    let app = horizon_bake::service::app(st);
    let pre = axum::http::Request::builder()
        .method("OPTIONS")
        .uri("/v1/bakes")
        .header("origin", "https://tools.example")
        .header("access-control-request-method", "POST")
        .header("access-control-request-headers", "authorization, content-type")
        .body(axum::body::Body::empty())
        .unwrap();
    let (s, h, _) = oneshot(&app, pre).await;
    assert_eq!(s, 204);
    assert_eq!(h["access-control-allow-origin"], "https://tools.example");
    assert!(h["access-control-allow-methods"].to_str().unwrap().contains("POST"));
    assert!(h["access-control-allow-headers"].to_str().unwrap().contains("authorization"));
    let (s, h, _) = oneshot(&app, get("/v1/bakes")).await;
    assert_eq!(s, 200);
    assert_eq!(h["access-control-allow-origin"], "https://tools.example");
    assert!(h["access-control-expose-headers"].to_str().unwrap().contains("location"));

    let bad = horizon_bake::service::ServeArgs {
        cors_origin: Some("tools.example/path".into()),
        ..Default::default()
    };
    match horizon_bake::service::Config::from_args(bad) {
        Err(horizon_bake::Error::Param { field, .. }) => assert_eq!(field, "cors_origin"),
        other => panic!("{other:?}"),
    }
}

/// Downloads name their file as the CLI would, with 8- and 16-bit layers (and float and half
/// EXR) apart.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn downloads_name_their_files() {
    let (srv, c, loc) = baked("?radius=3&formats=png8,exr").await;
    for (q, want) in [
        ("/horizon/0", "horizon_0.png"),
        ("/horizon/1?format=png8", "horizon_1.png"),
        ("/horizon/0?format=exr", "horizon_0.exr"),
        ("/horizon/1?format=png16", "horizon_1_16.png"),
        ("/horizon/0?format=exr&exr_precision=half", "horizon_0_half.exr"),
        ("/horizon.ktx2", "horizon.ktx2"),
    ] {
        let res = fetch_ready(&c, &srv.url(&format!("{loc}{q}"))).await;
        assert_eq!(res.status(), 200, "{q}");
        let cd = res.headers()["content-disposition"].to_str().unwrap().to_owned();
        assert!(cd.ends_with(&format!("filename=\"{want}\"")), "{q}: {cd}");
        assert_eq!(res.headers()["x-content-type-options"], "nosniff");
    }
    srv.stop().await;
}

/// GET `url`, following the 202 of a result that is being encoded (Retry-After) until it is
/// ready.
async fn fetch_ready(c: &reqwest::Client, url: &str) -> reqwest::Response {
    let t = std::time::Instant::now();
    loop {
        let res = c.get(url).send().await.unwrap();
        if res.status() != 202 {
            return res;
        }
        assert!(t.elapsed() < Duration::from_secs(120), "{url} still encoding");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// The README links the reference in the repository (a clone has no ../shared), and the
/// reference covers every bake parameter, every preview parameter and every route.
#[test]
fn readme_links_the_reference_which_covers_every_parameter_and_route() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    let readme = std::fs::read_to_string(root.join("README.md")).unwrap();
    assert!(readme.contains("(docs/reference.md)"), "README does not link docs/reference.md");
    let mut docs = vec![("README.md".to_owned(), readme)];
    for e in std::fs::read_dir(root.join("docs")).unwrap().flatten() {
        if e.path().extension().is_some_and(|x| x == "md") {
            docs.push((e.path().display().to_string(), std::fs::read_to_string(e.path()).unwrap()));
        }
    }
    for (name, text) in &docs {
        assert!(!text.contains("../shared") && !text.contains("shared/SPEC"), "{name}");
    }
    let reference = std::fs::read_to_string(root.join("docs/reference.md")).unwrap();
    let names = horizon_bake::params::PARAM_NAMES
        .iter()
        .chain(horizon_bake::preview::PREVIEW_PARAM_NAMES)
        .chain(&["formats", "exr_precision"])
        .chain(&horizon_bake::encode::texture::OPTION_KEYS);
    for k in names {
        assert!(reference.contains(&format!("`{k}`")), "docs/reference.md lacks `{k}`");
    }
    for (route, _) in horizon_bake::service::ROUTES {
        assert!(reference.contains(&format!("`{route}`")), "docs/reference.md lacks {route}");
    }
    for topic in ["height_scale", "y_axis", "edge=wrap", "encoding=sqrt", "+X, −X", "hardness"] {
        assert!(reference.contains(topic), "docs/reference.md lacks {topic}");
    }
}

/// Bytes a PNG of `raw` sample bytes in `rows` rows may add: a filter byte per row, 5 bytes per
/// stored deflate block (at most 64 KiB each; counted per 16 KiB to be safe), 12 per IDAT chunk
/// (1 MiB each), and the signature, IHDR, IEND and zlib header and checksum.
fn framing(raw: usize, rows: usize) -> usize {
    rows + 5 * (raw + rows).div_ceil(16 * 1024) + 12 * (raw / (1 << 20) + 1) + 8 + 25 + 12 + 6
}

/// A PNG layer is never larger than its raw samples (plus the framing), at every size and in
/// every band: a noise-like 1024² layer streamed in bands, 8- and 16-bit; a smooth one still
/// compresses.
#[test]
fn png_layers_are_never_larger_than_raw_at_any_size() {
    use horizon_bake::encode::png::{PngColor, PngRowWriter};
    let n = 1024usize;
    let mut rng = Rng(25);
    let noise8: Vec<u8> = (0..n * n * 4).map(|_| (rng.next_u64() >> 56) as u8).collect();
    let noise16: Vec<u16> = (0..n * n * 4).map(|_| (rng.next_u64() >> 48) as u16).collect();
    let band = 37 * n * 4; // uneven bands, as the streaming bake writes them
    let mut w8 = PngRowWriter::<_, u8>::new(Vec::new(), n, n, PngColor::Rgba).unwrap();
    let mut sizes = Vec::new();
    for rows in noise8.chunks(band) {
        w8.write_rows(rows).unwrap();
    }
    let png8 = w8.finish().unwrap();
    sizes.push(("png8 noise", png8.len(), n * n * 4));
    let mut w16 = PngRowWriter::<_, u16>::new(Vec::new(), n, n, PngColor::Rgba).unwrap();
    for rows in noise16.chunks(band) {
        w16.write_rows(rows).unwrap();
    }
    let png16 = w16.finish().unwrap();
    sizes.push(("png16 noise", png16.len(), n * n * 8));
    for (what, len, raw) in &sizes {
        assert!(*len <= raw + framing(*raw, n), "{what}: {len} bytes for {raw} of samples");
    }
    // Same samples back (a reader we did not write).
    let img = image::load_from_memory(&png16).unwrap().to_rgba16();
    assert!(img.as_raw() == &noise16);
    let img = image::load_from_memory(&png8).unwrap().to_rgba8();
    assert!(img.as_raw() == &noise8);

    // Half noise, half flat, in one image: each band is judged on its own (the flat half
    // compresses to almost nothing, the noisy half is stored), so the total is about half.
    let mut mixed = noise8.clone();
    mixed[n * n * 2..].fill(7);
    let mut w = PngRowWriter::<_, u8>::new(Vec::new(), n, n, PngColor::Rgba).unwrap();
    for rows in mixed.chunks(band) {
        w.write_rows(rows).unwrap();
    }
    let half = w.finish().unwrap();
    let raw_half = n * n * 2;
    assert!(half.len() <= raw_half + framing(raw_half, n / 2) + 64 * 1024, "{}", half.len());

    // A real bake of a rough 1024² map through the streaming pipeline, both precisions.
    let png = noise_png8(n, n, 77);
    let params =
        horizon_bake::params::BakeParams::from_pairs([("height_scale", "200"), ("radius", "4")])
            .unwrap();
    let (map, _) =
        horizon_bake::heightmap::decode(&png, params.channel, &Default::default()).unwrap();
    let progress = horizon_bake::progress::Progress::new();
    let (p8, _) = horizon_bake::pipeline::stream_horizon_pngs::<u8, _>(
        map.clone(),
        &params,
        &progress,
        [Vec::new(), Vec::new()],
    )
    .unwrap();
    let (p16, _) = horizon_bake::pipeline::stream_horizon_pngs::<u16, _>(
        map,
        &params,
        &progress,
        [Vec::new(), Vec::new()],
    )
    .unwrap();
    for (k, (a, b)) in p8.iter().zip(&p16).enumerate() {
        let (r8, r16) = (n * n * 4, n * n * 8);
        assert!(a.len() <= r8 + framing(r8, n), "layer {k} png8: {} for {r8}", a.len());
        assert!(b.len() <= r16 + framing(r16, n), "layer {k} png16: {} for {r16}", b.len());
    }

    // A smooth layer still compresses well.
    let smooth: Vec<u8> = (0..n * n * 4).map(|i| ((i / 4 % n) / 8) as u8).collect();
    let mut w = PngRowWriter::<_, u8>::new(Vec::new(), n, n, PngColor::Rgba).unwrap();
    w.write_rows(&smooth).unwrap();
    let small = w.finish().unwrap();
    assert!(small.len() * 20 < smooth.len(), "smooth layer: {} bytes", small.len());
}

async fn counter(c: &reqwest::Client, srv: &Server, series: &str) -> u64 {
    let text = c.get(srv.url("/metrics")).send().await.unwrap().text().await.unwrap();
    let key = format!("{series} ");
    let line = text.lines().find(|l| l.starts_with(&key)).unwrap_or_else(|| panic!("{series}"));
    line[key.len()..].parse().unwrap()
}

/// The first request of a format the bake did not encode is answered 202 + Retry-After at
/// once; the encode runs once in the background however many requests arrive, shows in the
/// bake's events and resource, and the same request then answers the file. EXR float and half
/// come from one re-bake; KTX2 goes through the same path.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn first_request_of_an_unencoded_format_is_answered_at_once() {
    let srv = Server::start(|c| c.preview_threads = 1).await;
    let c = client();
    // Large enough that the re-bake takes a while (exact kernel, R = 48, 384²).
    let png = terrain_png16(384, 384, 12);
    let q = "?method=exact&radius=48&height_scale=40";
    let loc = submit_ok(&c, &srv, &png, q).await;
    let v = wait_done(&c, &srv.url(&loc), Duration::from_secs(120)).await;
    assert_eq!(v["status"], "succeeded", "{v}");
    let encoded = || counter(&c, &srv, "horizon_results_encoded_total");
    assert_eq!(encoded().await, 0);

    // Four first requests at once: every one answered at once, 202 or (if it was that quick)
    // the file; one encode.
    let url = srv.url(&format!("{loc}/horizon/0?format=exr"));
    let t = std::time::Instant::now();
    let first = c.get(&url).send().await.unwrap();
    let first_ms = t.elapsed().as_millis();
    assert_eq!(first.status(), 202);
    let retry: u64 = first.headers()["retry-after"].to_str().unwrap().parse().unwrap();
    assert!((1..=30).contains(&retry), "{retry}");
    let body: Value = first.json().await.unwrap();
    assert_eq!(body["status"], "encoding", "{body}");
    assert_eq!(body["result"], "horizon_0.exr", "{body}");
    let bake_ms = v["timings_ms"]["bake"].as_f64().unwrap();
    assert!((first_ms as f64) < bake_ms.max(200.0), "202 took {first_ms} ms (bake {bake_ms} ms)");

    // While it runs: the resource lists it, the events show it, and more requests join it.
    let res: Value = c.get(srv.url(&loc)).send().await.unwrap().json().await.unwrap();
    let listed = res["formats"]["encoding"].as_array().unwrap().clone();
    let events = c.get(srv.url(&format!("{loc}/events"))).send().await.unwrap();
    let others = (0..3).map(|k| {
        let (c, url) = (c.clone(), srv.url(&format!("{loc}/horizon/{}?format=exr", k % 2)));
        tokio::spawn(async move { get_result(&c, &url).await.bytes().await.unwrap() })
    });
    let text =
        tokio::time::timeout(Duration::from_secs(120), events.text()).await.unwrap().unwrap();
    let bodies = futures_util::future::join_all(others).await;
    let mine = get_result(&c, &url).await;
    assert_eq!(mine.status(), 200);
    assert_eq!(mine.headers()["content-type"], "image/x-exr");
    let mine = mine.bytes().await.unwrap();
    let want =
        library_files(&png, &[("method", "exact"), ("radius", "48"), ("height_scale", "40")]);
    assert!(mine[..] == want["horizon_0.exr"][..]);
    for (k, b) in bodies.into_iter().enumerate() {
        let name = format!("horizon_{}.exr", k % 2);
        assert!(b.unwrap()[..] == want[&name][..], "{name}");
    }
    // Seen while running (either the resource or the event stream caught it: the resource was
    // read right after the 202, well within the re-bake).
    assert!(
        listed.iter().any(|e| e["result"] == "horizon_0.exr") || text.contains("event: encoding"),
        "the encode showed nowhere: {listed:?} / {text}"
    );
    assert!(text.contains("event: encoding"), "{text}");
    let done = text.split("\n\n").find(|e| e.contains("event: done")).expect(&text);
    assert!(done.contains("horizon_0.half.exr"), "done before the encode stored: {done}");
    let enc_pos = text.find("event: encoding").unwrap();
    assert!(enc_pos < text.find("event: done").unwrap());

    // One re-bake gave float and half of both layers.
    assert_eq!(encoded().await, 4);
    let half = c
        .get(srv.url(&format!("{loc}/horizon/1?format=exr&exr_precision=half")))
        .send()
        .await
        .unwrap();
    assert_eq!(half.status(), 200, "half was not derived from the same re-bake");
    assert_eq!(encoded().await, 4);

    // Other variants go through the same path: png16, KTX2.
    for (path, name) in
        [("/horizon/1?format=png16", "horizon_1.png16"), ("/horizon.ktx2", "horizon.ktx2")]
    {
        let u = srv.url(&format!("{loc}{path}"));
        let r = c.get(&u).send().await.unwrap();
        assert_eq!(r.status(), 202, "{path}");
        let r = get_result(&c, &u).await;
        assert_eq!(r.status(), 200, "{path}");
        assert!(r.bytes().await.unwrap()[..] == want[name][..], "{name}");
    }
    srv.stop().await;
}
