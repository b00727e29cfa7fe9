//! Results and their downloads: byte ranges, file names, cache busters ignored on immutable
//! results, formats named at submission encoded with the bake, other formats encoded once on
//! their first request (answered 202 at once) and half-float EXR. Regression tests from
//! tests/edges.rs (issue 25's sharp edges) and tests/service_defects.rs (issue 14's service
//! defects), each written to fail before its fix.

use crate::support::*;
use serde_json::Value;
use std::time::Duration;

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

/// Cache busters (`?v=123`) on immutable results are ignored; known keys are still checked.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn unknown_query_keys_on_immutable_results_are_ignored() {
    let srv = Server::start(|_| {}).await;
    let c = client();
    let loc = submit_ok(&c, &srv, &terrain_png16(12, 10, 41), "?radius=3").await;
    let v = wait_done(&c, &srv.url(&loc), Duration::from_secs(60)).await;
    assert_eq!(v["status"], "succeeded", "{v}");
    for path in [
        format!("{loc}/horizon/0?v=123"),
        format!("{loc}/horizon/1?format=png16&_=9"),
        format!("{loc}/horizon.ktx2?v=1"),
        format!("{loc}/horizon.dds?v=1"),
        "/v1/cubemap/0?v=2".to_owned(),
        "/v1/cubemap.ktx2?size=4&v=2".to_owned(),
    ] {
        let res = get_result(&c, &srv.url(&path)).await;
        assert_eq!(res.status(), 200, "{path}");
    }
    let (s, p) =
        problem(c.get(srv.url(&format!("{loc}/horizon/0?format=jpg&v=1"))).send().await.unwrap())
            .await;
    assert_eq!((s, p["field"].as_str()), (422, Some("format")));
    srv.stop().await;
}

/// A submission can name the formats to encode with the bake (`formats`, `exr_precision`: the
/// CLI's `--format` and `--exr-precision`), so a pipeline that wants EXR pays for it once, during
/// the bake, instead of a re-bake on its first download; the resource says what was asked and
/// what is stored, and the downloads are the library's bytes with nothing encoded on request.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn formats_named_at_submission_are_encoded_with_the_bake() {
    let srv = Server::start(|_| {}).await;
    let c = client();
    let png = terrain_png16(36, 28, 63);
    let encoded = || counter(&c, &srv, "horizon_results_encoded_total");
    // Refused at submission, naming the key, with nothing stored.
    for (q, field) in [
        ("?formats=gif", "formats"),
        ("?formats=png8,png16", "formats"),
        ("?formats=exr&formats=png8", "formats"),
        ("?exr_precision=half", "exr_precision"),
        ("?formats=exr&exr_precision=quarter", "exr_precision"),
        ("?outputs=fourier&formats=exr", "formats"),
    ] {
        let res = c
            .post(srv.url(&format!("/v1/bakes{q}")))
            .header("content-type", "image/png")
            .body(png.clone())
            .send()
            .await
            .unwrap();
        let (s, p) = problem(res).await;
        assert_eq!((s, p["field"].as_str()), (422, Some(field)), "{q}: {p}");
    }
    assert!(blob_files(srv.dir.path()).is_empty());

    let loc = submit_ok(&c, &srv, &png, "?radius=4&formats=png16,exr,ktx2").await;
    let v = wait_done(&c, &srv.url(&loc), Duration::from_secs(60)).await;
    assert_eq!(v["status"], "succeeded", "{v}");
    assert_eq!(v["formats"]["requested"], "png16,exr,ktx2", "{v}");
    let stored: Vec<&str> =
        v["formats"]["stored"].as_array().unwrap().iter().map(|s| s.as_str().unwrap()).collect();
    assert_eq!(
        stored,
        ["horizon.ktx2", "horizon_0.exr", "horizon_0.png16", "horizon_1.exr", "horizon_1.png16"]
    );
    assert!(v["links"]["horizon_0"].is_string(), "{v}");
    let want = library_files(&png, &[("radius", "4")]);
    for name in ["horizon_0.png16", "horizon_1.exr", "horizon.ktx2"] {
        let res = c.get(srv.url(&format!("{loc}{}", result_path(name)))).send().await.unwrap();
        assert_eq!(res.status(), 200, "{name}");
        assert!(res.bytes().await.unwrap() == want[name], "{name} differs from the library's");
    }
    assert_eq!(encoded().await, 0, "nothing was encoded on request");
    // A format not asked is still there, encoded on its first request.
    let res = get_result(&c, &srv.url(&format!("{loc}/horizon/1"))).await;
    assert_eq!(res.status(), 200);
    assert!(res.bytes().await.unwrap() == want["horizon_1.png8"]);
    assert_eq!(encoded().await, 2);

    // Formats are not part of the bake's identity: the same input and parameters with other
    // formats is the same bake. In a multipart `params` part they are JSON like the rest.
    let form = reqwest::multipart::Form::new()
        .part("heightmap", reqwest::multipart::Part::bytes(png.clone()))
        .text("params", r#"{"radius": 4, "formats": ["dds"]}"#);
    let res = c.post(srv.url("/v1/bakes")).multipart(form).send().await.unwrap();
    assert_eq!(res.status(), 200);
    let again: Value = res.json().await.unwrap();
    assert_eq!(again["id"], v["id"]);

    // Half-float EXR asked at submission is stored as such.
    let loc = submit_ok(&c, &srv, &png, "?radius=3&formats=png8,exr&exr_precision=half").await;
    let v = wait_done(&c, &srv.url(&loc), Duration::from_secs(60)).await;
    assert_eq!(v["formats"]["requested"], "png8,exr,half", "{v}");
    let stored = v["formats"]["stored"].to_string();
    assert!(stored.contains("horizon_0.half.exr") && !stored.contains("horizon_0.exr\""), "{v}");
    let before = encoded().await;
    let res = c
        .get(srv.url(&format!("{loc}/horizon/0?format=exr&exr_precision=half")))
        .send()
        .await
        .unwrap();
    assert_eq!(res.status(), 200);
    assert_eq!(encoded().await, before);
    srv.stop().await;
}

/// Pay only for what is asked: a bake stores its png8 layers only; another format is encoded on
/// its first request, once however many requests ask at the same time, then kept.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn formats_other_than_png8_are_encoded_once_on_first_request() {
    let srv = Server::start(|_| {}).await;
    let c = client();
    let png = terrain_png16(40, 30, 61);
    let loc = submit_ok(&c, &srv, &png, "?radius=5").await;
    let v = wait_done(&c, &srv.url(&loc), Duration::from_secs(60)).await;
    assert_eq!(v["status"], "succeeded", "{v}");
    assert_eq!(blob_files(srv.dir.path()).len(), 3, "input + two png8 layers");
    let encoded = || counter(&c, &srv, "horizon_results_encoded_total");
    assert_eq!(encoded().await, 0);

    let url = srv.url(&format!("{loc}/horizon/0?format=exr"));
    let gets = (0..4).map(|_| {
        let (c, url) = (c.clone(), url.clone());
        tokio::spawn(async move {
            let res = get_result(&c, &url).await;
            assert_eq!(res.status(), 200);
            res.bytes().await.unwrap()
        })
    });
    let bodies: Vec<_> = futures_util::future::join_all(gets).await;
    let want = library_files(&png, &[("radius", "5")]);
    for b in bodies {
        assert!(b.unwrap()[..] == want["horizon_0.exr"][..], "EXR differs from the library's");
    }
    // Both layers at both EXR precisions, from one re-bake (issue 25).
    assert_eq!(encoded().await, 4, "both EXR layers, float and half, encoded once");
    let res = c.get(srv.url(&format!("{loc}/horizon/1?format=exr"))).send().await.unwrap();
    assert!(res.bytes().await.unwrap()[..] == want["horizon_1.exr"][..]);
    let half = format!("{loc}/horizon/1?format=exr&exr_precision=half");
    assert_eq!(c.get(srv.url(&half)).send().await.unwrap().status(), 200);
    assert_eq!(encoded().await, 4, "layer 1 and half precision were encoded with layer 0");
    assert_eq!(blob_files(srv.dir.path()).len(), 7);
    srv.stop().await;
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

/// `exr_precision=half` serves half-float layers: the library's f32 values rounded to f16.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn half_precision_exr_is_the_f32_layer_in_half() {
    use exr::prelude::*;
    let srv = Server::start(|_| {}).await;
    let c = client();
    let png = terrain_png16(24, 18, 91);
    let loc = submit_ok(&c, &srv, &png, "?radius=4").await;
    let v = wait_done(&c, &srv.url(&loc), Duration::from_secs(60)).await;
    assert_eq!(v["status"], "succeeded", "{v}");
    let res =
        get_result(&c, &srv.url(&format!("{loc}/horizon/1?format=exr&exr_precision=half"))).await;
    assert_eq!(res.status(), 200);
    let bytes = res.bytes().await.unwrap();
    let img = read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .first_valid_layer()
        .all_attributes()
        .from_buffered(std::io::Cursor::new(&bytes[..]))
        .unwrap();
    let list = &img.layer_data.channel_data.list;
    assert!(list.iter().all(|ch| matches!(ch.sample_data, FlatSamples::F16(_))));
    let params = horizon_bake::params::BakeParams::from_pairs([("radius", "4")]).unwrap();
    let (map, _) =
        horizon_bake::heightmap::decode(&png, params.channel, &Default::default()).unwrap();
    let (layers, _) = horizon_bake::bake::bake_horizon(
        &map,
        &params,
        horizon_bake::bake::Precisions::ALL,
        &horizon_bake::progress::Progress::new(),
    )
    .unwrap();
    let want = &layers.f32.as_ref().unwrap()[1];
    let find = |n: &str| list.iter().find(|ch| ch.name == *n).unwrap();
    for (k, name) in ["R", "G", "B", "A"].iter().enumerate() {
        let FlatSamples::F16(got) = &find(name).sample_data else { unreachable!() };
        for (t, g) in got.iter().enumerate() {
            assert_eq!(*g, f16::from_f32(want[t * 4 + k]), "{name} texel {t}");
        }
    }
    // exr_precision without format=exr names itself.
    let (s, p) = problem(
        c.get(srv.url(&format!("{loc}/horizon/0?exr_precision=half"))).send().await.unwrap(),
    )
    .await;
    assert_eq!((s, p["field"].as_str()), (422, Some("exr_precision")));
    srv.stop().await;
}
