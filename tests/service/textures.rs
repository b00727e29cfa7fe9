//! SPEC §8 texture variants over HTTP (issue 21): query parameters of the existing texture
//! routes, not bake identity. Each variant answers the bytes the CLI writes for the same
//! options, is encoded once and kept (a second request answers the stored blob, same ETag), and
//! an option that cannot apply is a 422 naming it.

use crate::support::*;
use horizon_bake::bake::{self, Precisions};
use horizon_bake::encode::{self, CubeFormats, Formats, TextureOptions, TexturePrecision};
use horizon_bake::heightmap::{self, Limits};
use horizon_bake::params::BakeParams;
use horizon_bake::progress::Progress;
use serde_json::Value;
use std::time::Duration;

/// The CLI's file `name` for `png`, `pairs` and the texture options of `query`.
fn cli_file(
    png: &[u8],
    pairs: &[(&str, &str)],
    list: &str,
    query: &[(&str, &str)],
    name: &str,
) -> Vec<u8> {
    let params = BakeParams::from_pairs(pairs.iter().copied()).unwrap();
    let (map, _) = heightmap::decode(png, params.channel, &Limits::default()).unwrap();
    let (layers, _) = bake::bake_horizon(&map, &params, Precisions::ALL, &Progress::new()).unwrap();
    let mut f = Formats::parse(list, TexturePrecision::Unorm8).unwrap();
    f.texture = TextureOptions::from_pairs(query.iter().copied()).unwrap();
    let files = encode::horizon_files(&layers, &f).unwrap();
    files.into_iter().find(|f| f.name == name).unwrap_or_else(|| panic!("{name}")).bytes
}

/// `horizon_results_encoded_total` of the server's /metrics.
async fn encoded(c: &reqwest::Client, srv: &Server) -> u64 {
    let text = c.get(srv.url("/metrics")).send().await.unwrap().text().await.unwrap();
    let line = text.lines().find(|l| l.starts_with("horizon_results_encoded_total ")).unwrap();
    line.rsplit(' ').next().unwrap().parse().unwrap()
}

fn query(pairs: &[(&str, &str)]) -> String {
    pairs.iter().map(|(k, v)| format!("{k}={v}")).collect::<Vec<_>>().join("&")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn texture_variants_are_query_parameters_encoded_once() {
    let srv = Server::start(|_| {}).await;
    let c = client();
    let png = terrain_png16(40, 28, 3);
    let pairs = [("radius", "6"), ("height_scale", "10")];
    let loc = submit_png_done(&c, &srv, &query(&pairs), &png).await;

    let bc7 = [("texture_precision", "bc7"), ("mips", "full"), ("supercompression", "zstd")];
    let bc5 = [
        ("texture_precision", "bc5"),
        ("texture_layout", "separate"),
        ("dds_header", "legacy"),
        ("mips", "full"),
        ("mip_filter", "max"),
    ];
    // Files encoded on request: one per variant, four for the separate BC5 one (all its layers
    // come from one encode), none on the repeated requests.
    for (route, opts, extra, list, name, files) in [
        ("horizon.ktx2", &bc7[..], "", "ktx2", "horizon.ktx2", 1),
        ("horizon.dds", &bc5[..], "&layer=3", "dds", "horizon_3.dds", 4),
        ("horizon.dds", &bc5[..], "&layer=1", "dds", "horizon_1.dds", 0),
        ("horizon.ktx2", &[][..], "", "ktx2", "horizon.ktx2", 1),
    ] {
        let before = encoded(&c, &srv).await;
        let url = srv.url(&format!("{loc}/{route}?{}{extra}", query(opts)));
        // A variant the bake did not encode answers 202 until its background encode is done.
        let first = get_result(&c, &url).await;
        assert_eq!(first.status(), 200, "{url}");
        let etag = first.headers()["etag"].to_str().unwrap().to_owned();
        let bytes = first.bytes().await.unwrap();
        assert_eq!(
            &bytes[..],
            &cli_file(&png, &pairs, list, opts, name)[..],
            "{url}: the CLI's bytes"
        );
        let again = c.get(&url).send().await.unwrap();
        assert_eq!(again.headers()["etag"].to_str().unwrap(), etag, "{url}: kept, not re-encoded");
        assert_eq!(encoded(&c, &srv).await - before, files, "{url}: files encoded");
    }
    let v: Value = c.get(srv.url(&loc)).send().await.unwrap().json().await.unwrap();
    let stored: Vec<&str> =
        v["formats"]["stored"].as_array().unwrap().iter().map(|s| s.as_str().unwrap()).collect();
    assert!(
        stored.contains(&"horizon.ktx2?texture_precision=bc7&mips=full&supercompression=zstd"),
        "{stored:?}"
    );
    // One encode made all four files of the separate BC5 variant.
    let bc5_files = stored.iter().filter(|s| s.contains("texture_precision=bc5")).count();
    assert_eq!(bc5_files, 4, "{stored:?}");

    for (route, q, field) in [
        ("horizon.dds", "supercompression=zstd", "supercompression"),
        ("horizon.ktx2", "texture_layout=separate", "layer"),
        ("horizon.ktx2", "layer=0", "layer"),
        ("horizon.ktx2", "texture_layout=separate&layer=2", "layer"),
        ("horizon.dds", "dds_header=legacy", "dds_header"),
        ("horizon.ktx2", "mip_filter=min", "mip_filter"),
        ("horizon.ktx2", "texture_precision=bc1", "texture_precision"),
        ("horizon.ktx2", "supercompression=zstd&zstd_level=30", "zstd_level"),
    ] {
        let res = c.get(srv.url(&format!("{loc}/{route}?{q}"))).send().await.unwrap();
        assert_eq!(res.status(), 422, "{route}?{q}");
        let p: Value = res.json().await.unwrap();
        assert!(
            p["detail"].as_str().unwrap_or_default().contains(field) || p["field"] == field,
            "{route}?{q}: {p}"
        );
    }

    // The cube map takes mips (and zstd for KTX2, the legacy header for DDS).
    let url = srv.url("/v1/cubemap.ktx2?size=8&mips=full&supercompression=zstd");
    let res = c.get(&url).send().await.unwrap();
    assert_eq!(res.status(), 200);
    let texture =
        TextureOptions::from_pairs([("mips", "full"), ("supercompression", "zstd")]).unwrap();
    let want = horizon_bake::pipeline::cube_files(
        8,
        CubeFormats { ktx2: true, texture, ..Default::default() },
    )
    .unwrap();
    assert_eq!(&res.bytes().await.unwrap()[..], &want[0].bytes[..]);
    // BC7 blocks of the UNORM faces, for loaders that read no uncompressed cube (three.js).
    let res = c.get(srv.url("/v1/cubemap.ktx2?size=8&texture_precision=bc7")).send().await.unwrap();
    assert_eq!(res.status(), 200);
    let texture = TextureOptions::from_pairs([("texture_precision", "bc7")]).unwrap();
    let want = horizon_bake::pipeline::cube_files(
        8,
        CubeFormats { ktx2: true, texture, ..Default::default() },
    )
    .unwrap();
    assert_eq!(&res.bytes().await.unwrap()[..], &want[0].bytes[..]);
    for route in ["cubemap.ktx2", "cubemap.dds"] {
        let res = c.get(srv.url(&format!("/v1/{route}?texture_precision=unorm16"))).send();
        let res = res.await.unwrap();
        assert_eq!(res.status(), 422, "{route}");
        let p: Value = res.json().await.unwrap();
        assert_eq!(p["field"], "texture_precision", "{route}: {p}");
    }
    let res =
        c.get(srv.url("/v1/cubemap.dds?size=8&mips=full&dds_header=legacy")).send().await.unwrap();
    assert_eq!(res.status(), 200);
    let res = c.get(srv.url("/v1/cubemap.dds?supercompression=zstd")).send().await.unwrap();
    assert_eq!(
        res.status(),
        200,
        "a KTX2-only key on the DDS route is ignored like any unknown key"
    );
    srv.stop().await;
}

/// The library's file `name` for `png`, `pairs` and the texture options of `query`, through the
/// pipeline (which bakes the levels of `mip_filter=rebake` again from the map).
fn pipeline_file(
    png: &[u8],
    pairs: &[(&str, &str)],
    list: &str,
    query: &[(&str, &str)],
    name: &str,
) -> Vec<u8> {
    let params = BakeParams::from_pairs(pairs.iter().copied()).unwrap();
    let (map, _) = heightmap::decode(png, params.channel, &Limits::default()).unwrap();
    let (layers, _) = bake::bake_horizon(&map, &params, Precisions::ALL, &Progress::new()).unwrap();
    let mut f = Formats::parse(list, TexturePrecision::Unorm8).unwrap();
    f.texture = TextureOptions::from_pairs(query.iter().copied()).unwrap();
    let files =
        horizon_bake::pipeline::encode_each(&layers, Some((&map, &params)), &f, &Progress::new())
            .unwrap();
    files.into_iter().find(|f| f.name == name).unwrap_or_else(|| panic!("{name}")).bytes
}

/// `?mips=full&mip_filter=rebake` on the texture routes: the bytes the library's pipeline
/// writes (each level a bake of the box-filtered heights at the halved radius, proven level by
/// level in tests/encode/textures.rs), distinct from the box chain, encoded once.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn rebake_variants_over_http() {
    let srv = Server::start(|_| {}).await;
    let c = client();
    let png = terrain_png16(36, 20, 5);
    let pairs = [("radius", "6"), ("height_scale", "10")];
    let loc = submit_png_done(&c, &srv, &query(&pairs), &png).await;
    let rebake = [("mips", "full"), ("mip_filter", "rebake")];
    for (route, list) in [("horizon.ktx2", "ktx2"), ("horizon.dds", "dds")] {
        let before = encoded(&c, &srv).await;
        let url = srv.url(&format!("{loc}/{route}?{}", query(&rebake)));
        let first = get_result(&c, &url).await;
        assert_eq!(first.status(), 200, "{url}");
        let bytes = first.bytes().await.unwrap();
        assert_eq!(&bytes[..], &pipeline_file(&png, &pairs, list, &rebake, route)[..], "{url}");
        let boxed = cli_file(&png, &pairs, list, &[("mips", "full")], route);
        assert_eq!(bytes.len(), boxed.len(), "{url}: the same chain of sizes as box");
        assert_ne!(&bytes[..], &boxed[..], "{url}: not the box chain");
        let again = c.get(&url).send().await.unwrap();
        assert_eq!(again.status(), 200);
        assert_eq!(encoded(&c, &srv).await - before, 1, "{url}: encoded once");
    }
    srv.stop().await;
}

/// A multipart submission body: the PNG and a `params` JSON part.
fn multipart(png: &[u8], params: &str) -> (String, Vec<u8>) {
    let b = "TeXbOuNdArY";
    let mut body = format!(
        "--{b}\r\ncontent-disposition: form-data; name=\"heightmap\"; filename=\"h.png\"\r\n\
         content-type: image/png\r\n\r\n"
    )
    .into_bytes();
    body.extend_from_slice(png);
    body.extend_from_slice(
        format!(
            "\r\n--{b}\r\ncontent-disposition: form-data; name=\"params\"\r\n\r\n{params}\r\n--{b}--\r\n"
        )
        .as_bytes(),
    );
    (format!("multipart/form-data; boundary={b}"), body)
}

/// SPEC §5: the texture options are submission keys too (query or multipart JSON). The variant
/// they name is encoded with the bake and stored under the name its download looks up, so the
/// first download answers 200 with no encode; an option without ktx2/dds is a 422 naming it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn texture_options_at_submission_are_encoded_with_the_bake() {
    let srv = Server::start(|_| {}).await;
    let c = client();
    let pairs = [("radius", "5"), ("height_scale", "9")];
    let bc7 = [("texture_precision", "bc7"), ("mips", "full"), ("supercompression", "zstd")];
    let bc5 = [
        ("texture_precision", "bc5"),
        ("texture_layout", "separate"),
        ("dds_header", "legacy"),
        ("mips", "full"),
        ("mip_filter", "rebake"),
    ];
    // Query: KTX2 and DDS of one variant (zstd is the KTX2's, the DDS is written without it).
    let png_q = terrain_png16(32, 24, 11);
    let url = srv.url(&format!("/v1/bakes?formats=ktx2,dds&{}&{}", query(&pairs), query(&bc7)));
    let res =
        c.post(url).header("content-type", "image/png").body(png_q.clone()).send().await.unwrap();
    assert_eq!(res.status(), 202);
    let loc_q = res.headers()["location"].to_str().unwrap().to_owned();
    // Multipart JSON: the separate BC5 DDS with rebaked levels.
    let png_m = terrain_png16(32, 24, 12);
    let json = serde_json::json!({
        "radius": 5, "height_scale": 9, "formats": "dds", "texture_precision": "bc5",
        "texture_layout": "separate", "dds_header": "legacy", "mips": "full",
        "mip_filter": "rebake",
    });
    let (ct, body) = multipart(&png_m, &json.to_string());
    let res =
        c.post(srv.url("/v1/bakes")).header("content-type", ct).body(body).send().await.unwrap();
    assert_eq!(res.status(), 202);
    let loc_m = res.headers()["location"].to_str().unwrap().to_owned();
    for loc in [&loc_q, &loc_m] {
        let done = wait_done(&c, &srv.url(loc), Duration::from_secs(60)).await;
        assert_eq!(done["status"], "succeeded", "{done}");
    }
    let v: Value = c.get(srv.url(&loc_q)).send().await.unwrap().json().await.unwrap();
    assert_eq!(
        v["formats"]["requested"], "ktx2,dds?texture_precision=bc7&mips=full&supercompression=zstd",
        "{v}"
    );
    let bc7_dds = &bc7[..2];
    let before = encoded(&c, &srv).await;
    for (loc, png, route, opts, extra, list, name) in [
        (&loc_q, &png_q, "horizon.ktx2", &bc7[..], "", "ktx2", "horizon.ktx2"),
        (&loc_q, &png_q, "horizon.dds", bc7_dds, "", "dds", "horizon.dds"),
        (&loc_m, &png_m, "horizon.dds", &bc5[..], "&layer=0", "dds", "horizon_0.dds"),
        (&loc_m, &png_m, "horizon.dds", &bc5[..], "&layer=3", "dds", "horizon_3.dds"),
    ] {
        let url = srv.url(&format!("{loc}/{route}?{}{extra}", query(opts)));
        let res = c.get(&url).send().await.unwrap();
        assert_eq!(res.status(), 200, "{url}: stored with the bake, no 202");
        let bytes = res.bytes().await.unwrap();
        assert_eq!(&bytes[..], &pipeline_file(png, &pairs, list, opts, name)[..], "{url}");
    }
    assert_eq!(encoded(&c, &srv).await, before, "no download re-encoded a submitted variant");
    // The plain variant was not asked: its first download encodes it.
    let url = srv.url(&format!("{loc_q}/horizon.ktx2"));
    assert_eq!(get_result(&c, &url).await.status(), 200);
    assert_eq!(encoded(&c, &srv).await, before + 1);

    for (q, field) in [
        ("mips=full", "mips"),
        ("formats=png8&texture_precision=bc7", "texture_precision"),
        ("formats=exr&mip_filter=rebake", "mip_filter"),
        ("formats=dds&supercompression=zstd", "supercompression"),
        ("formats=ktx2&dds_header=legacy", "dds_header"),
        ("formats=dds&dds_header=legacy", "dds_header"),
        ("formats=ktx2&mip_filter=max", "mip_filter"),
        ("formats=ktx2&mips=full&mips=none", "mips"),
        ("formats=ktx2&texture_layout=spread", "texture_layout"),
    ] {
        let res = c
            .post(srv.url(&format!("/v1/bakes?{q}")))
            .header("content-type", "image/png")
            .body(png_q.clone())
            .send()
            .await
            .unwrap();
        assert_eq!(res.status(), 422, "{q}");
        let p: Value = res.json().await.unwrap();
        assert!(
            p["field"] == field || p["detail"].as_str().unwrap_or_default().contains(field),
            "{q}: {p}"
        );
    }
    srv.stop().await;
}
