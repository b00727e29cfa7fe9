//! Tiled bakes (SPEC §7.1) on one node: a tiled bake's layers are byte-identical to the
//! untiled bake of the same input and parameters (every kernel, both edges, odd sizes, maps of
//! one tile), the embedded service tiles a map with the same bytes and reports its tiles, and
//! what tiles cannot do is a 422 at submission.

use crate::support::*;
use horizon_bake::encode::{Formats, TexturePrecision};
use horizon_bake::heightmap::{self, HeightMap, Limits};
use horizon_bake::params::BakeParams;
use horizon_bake::pipeline::tiled::{self, TileSettings};
use horizon_bake::progress::Progress;
use serde_json::Value;
use std::time::{Duration, Instant};

fn map_of(png: &[u8]) -> HeightMap {
    heightmap::decode(png, horizon_bake::params::Channel::Luma, &Limits::default()).unwrap().0
}

fn untiled(map: &HeightMap, params: &BakeParams, png16: bool) -> [Vec<u8>; 2] {
    let outs = [Vec::new(), Vec::new()];
    let p = Progress::new();
    if png16 {
        horizon_bake::pipeline::stream_horizon_pngs::<u16, _>(map.clone(), params, &p, outs)
            .unwrap()
            .0
    } else {
        horizon_bake::pipeline::stream_horizon_pngs::<u8, _>(map.clone(), params, &p, outs)
            .unwrap()
            .0
    }
}

fn params(q: &str) -> BakeParams {
    let pairs: Vec<(&str, &str)> =
        q.split('&').filter(|p| !p.is_empty()).map(|p| p.split_once('=').unwrap()).collect();
    BakeParams::from_pairs(pairs).unwrap()
}

/// Every kernel, both edges, an odd-sized map in tiles of 16 with a narrower last column and
/// row: the tiled layers are the untiled bake's, byte for byte.
#[test]
fn tiled_layers_are_byte_identical_to_the_untiled_bake() {
    let map = map_of(&terrain_png16(67, 53, 5));
    let png8 = Formats::parse("png8", TexturePrecision::Unorm8).unwrap();
    let png16 = Formats::parse("png16", TexturePrecision::Unorm8).unwrap();
    let mut checked = 0;
    for method in ["lengyel", "march", "exact"] {
        for edge in ["wrap", "none"] {
            let p = params(&format!("method={method}&edge={edge}&radius=6&height_scale=24"));
            for (formats, sixteen) in [(&png8, false), (&png16, true)] {
                let tiled = tiled::bake_tiled_in_memory(&map, &p, formats, 16).unwrap();
                let whole = untiled(&map, &p, sixteen);
                assert!(
                    tiled == whole,
                    "{method} edge={edge} png16={sixteen}: the tiled layers differ"
                );
                checked += 1;
            }
        }
    }
    assert_eq!(checked, 12);
}

/// Nodata holes across tile seams (march and exact, both edges): each window gets the hole
/// mask and fill of the whole map's decode, and a texel near a hole takes the exact walk with
/// the holes wherever its window starts (`tests/kernels/march.rs` checks the march's choice texel by
/// texel in f32), so the tiled layers are the untiled bake's.
#[test]
fn holes_across_tile_seams_give_the_untiled_bytes() {
    let (w, h) = (67, 53);
    let mut v = terrain16(w, h, 11);
    for y in 14..22 {
        v[y * w + 12..y * w + 21].fill(0);
    }
    let png =
        horizon_bake::encode::png::encode16(w, h, horizon_bake::encode::png::PngColor::Gray, &v)
            .unwrap();
    // 16 bits: the two walks differ by less than 8 bits show.
    let png16 = Formats::parse("png16", TexturePrecision::Unorm8).unwrap();
    for method in ["march", "exact"] {
        for edge in ["wrap", "none"] {
            let mut p =
                params(&format!("method={method}&edge={edge}&radius=6&height_scale=24&nodata=0"));
            let (map, _) = heightmap::decode_for(&png, &mut p, &Limits::default()).unwrap();
            assert!(map.terrain.holes.as_ref().is_some_and(|m| m.iter().any(|&x| x)));
            let tiled = tiled::bake_tiled_in_memory(&map, &p, &png16, 16).unwrap();
            assert!(tiled == untiled(&map, &p, true), "{method} edge={edge}: holes");
        }
    }
}

/// `radius=auto` resolves on the whole map's height range, and the kernels that work relative
/// to the middle of the range (march, exact) see the whole map's: tiles whose own range differs
/// a lot from the map's give the same bytes.
#[test]
fn whole_map_constants_reach_every_tile() {
    // A ramp: every tile's own range is a small part of the map's.
    let (w, h) = (70, 45);
    let values: Vec<f32> = (0..w * h)
        .map(|k| ((k % w) as f32 / w as f32) * 0.9 + ((k / w) % 3) as f32 * 0.01)
        .collect();
    let map = HeightMap::from_values(w, h, values).unwrap();
    let png8 = Formats::parse("png8", TexturePrecision::Unorm8).unwrap();
    for method in ["march", "exact", "lengyel"] {
        for edge in ["wrap", "none"] {
            let p = params(&format!(
                "method={method}&edge={edge}&radius=auto&min_elevation_deg=60&height_scale=9"
            ));
            let tiled = tiled::bake_tiled_in_memory(&map, &p, &png8, 16).unwrap();
            assert!(tiled == untiled(&map, &p, false), "{method} edge={edge}: auto radius");
        }
    }
}

/// A map of one tile (the window is the map, or the map plus its wrapped halo), and tiles as
/// small as their halo.
#[test]
fn one_tile_maps_and_tiles_as_small_as_the_halo() {
    let map = map_of(&terrain_png16(23, 19, 9));
    let png8 = Formats::parse("png8", TexturePrecision::Unorm8).unwrap();
    for edge in ["wrap", "none"] {
        let p = params(&format!("method=lengyel&edge={edge}&radius=4&height_scale=16"));
        for tile in [64, 5] {
            let tiled = tiled::bake_tiled_in_memory(&map, &p, &png8, tile).unwrap();
            assert!(tiled == untiled(&map, &p, false), "edge={edge} tile={tile}");
        }
    }
}

/// Refusals of the plan, before any work.
#[test]
fn what_tiles_cannot_do_is_refused_with_the_parameter_named() {
    let s = TileSettings { tile_above: 64 * 64, tile_size: 32 };
    let png8 = Formats::parse("png8", TexturePrecision::Unorm8).unwrap();
    let field = |q: &str, f: &Formats, w: u32, h: u32| match tiled::check(&params(q), f, w, h, &s) {
        Err(horizon_bake::Error::Param { field, message }) => Some((field, message)),
        Err(e) => panic!("{q}: {e}"),
        Ok(()) => None,
    };
    let (f, m) = field("radius=unlimited", &png8, 100, 100).unwrap();
    assert_eq!(f, "radius");
    assert!(m.contains("auto") && m.contains("max_distance") && m.contains("whole map"), "{m}");
    // The same map below --tile-above is not tiled: unlimited is fine.
    assert!(field("radius=unlimited", &png8, 64, 64).is_none());
    // sweep's far field spans the whole map: refused on a tiled map, fine below.
    let (f, m) = field("method=sweep&radius=8", &png8, 100, 100).unwrap();
    assert_eq!(f, "method");
    assert!(m.contains("march") && m.contains("tile"), "{m}");
    assert!(field("method=sweep&radius=8", &png8, 64, 64).is_none());
    assert_eq!(field("radius=40", &png8, 100, 100).unwrap().0, "tile_size");
    let s2 = TileSettings { tile_above: 64 * 64, tile_size: 200 };
    let halo = tiled::check(&params("radius=120"), &png8, 100, 100, &s2).unwrap_err();
    assert!(
        matches!(&halo, horizon_bake::Error::Param { field, .. } if field == "radius"),
        "{halo}"
    );
    let exr = Formats::parse("exr", TexturePrecision::Unorm8).unwrap();
    assert_eq!(field("radius=8", &exr, 100, 100).unwrap().0, "formats");
    let mut bc7 = Formats::parse("ktx2", TexturePrecision::Bc7).unwrap();
    bc7.texture.precision = horizon_bake::encode::TexturePrecision::Bc7;
    assert_eq!(field("radius=8", &bc7, 100, 100).unwrap().0, "texture_precision");
    let ktx2 = Formats::parse("ktx2,dds", TexturePrecision::Unorm8).unwrap();
    assert!(field("radius=8", &ktx2, 100, 100).is_none());
    assert_eq!(field("radius=8&outputs=horizon,fourier", &png8, 100, 100).unwrap().0, "outputs");
    let (f, m) = field("radius=8&outputs=angles,horizon_distance", &png8, 100, 100).unwrap();
    assert!(f == "outputs" && m.contains("horizon_distance"), "{f}: {m}");
    // The terrain products are assembled tile by tile, within the untiled limit per file.
    assert!(field("radius=8&outputs=horizon,angles,svf", &png8, 100, 100).is_none());
    let (f, m) = field("radius=8&outputs=angles&bins=32", &png8, 4000, 4000).unwrap();
    assert_eq!(f, "bins", "{m}");
    assert!(field("radius=8&outputs=angles&bins=16", &png8, 4000, 4000).is_none());
    assert_eq!(field("radius=8&outputs=svf", &png8, 20000, 20000).unwrap().0, "outputs");
    assert!(field("radius=8&outputs=svf", &png8, 16384, 16384).is_none());
    assert!(field("radius=8", &png8, 100, 100).is_none());
}

fn metric(text: &str, name: &str) -> f64 {
    text.lines()
        .find(|l| l.starts_with(name))
        .and_then(|l| l.rsplit(' ').next())
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("{name} missing:\n{text}"))
}

/// The embedded service tiles a map above --tile-above on its own pool: the downloads are the
/// library's untiled bytes, the resource says 9 of 9 tiles, /metrics counts them, and the 422s
/// come back as problem+json.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_embedded_service_tiles_a_map_with_the_same_bytes() {
    let srv =
        Server::start(|c| c.tiles = TileSettings { tile_above: 64 * 64, tile_size: 32 }).await;
    let c = client();
    let png = terrain_png16(96, 80, 21);
    for edge in ["wrap", "none"] {
        let q = format!("radius=8&edge={edge}");
        let loc = submit_png_done(&c, &srv, &q, &png).await;
        let v: Value = c.get(srv.url(&loc)).send().await.unwrap().json().await.unwrap();
        assert_eq!(v["tiles"]["done"], 9, "{v}");
        assert_eq!(v["tiles"]["total"], 9, "{v}");
        assert_eq!(v["params"]["resolved_radius"]["texels"], 8, "{v}");
        let lib = library_files(&png, &[("radius", "8"), ("edge", edge)]);
        for k in 0..2 {
            let r = get_result(&c, &srv.url(&format!("{loc}/horizon/{k}"))).await;
            assert_eq!(r.status(), 200);
            let bytes = r.bytes().await.unwrap();
            assert!(bytes[..] == lib[&format!("horizon_{k}.png8")][..], "edge={edge} layer {k}");
        }
    }
    // KTX2 and DDS (level 0, unorm8) are assembled from the tiles too: the library's bytes.
    // (A new bake: `formats` is not part of a bake's identity.)
    let loc = submit_png_done(&c, &srv, "radius=7&formats=png8,ktx2,dds", &png).await;
    let lib = library_files(&png, &[("radius", "7")]);
    for name in ["horizon.ktx2", "horizon.dds"] {
        let r = get_result(&c, &srv.url(&format!("{loc}/{name}"))).await;
        assert_eq!(r.status(), 200, "{name}");
        assert!(r.bytes().await.unwrap()[..] == lib[name][..], "{name} differs");
    }
    // Another format would decode the whole map again: refused (422) rather than done.
    let last = c.get(srv.url("/v1/bakes?limit=1&order=desc")).send().await.unwrap();
    let last: Value = last.json().await.unwrap();
    let id = last["items"][0]["id"].as_str().unwrap().to_owned();
    let url = srv.url(&format!("/v1/bakes/{id}/horizon/0?format=png16"));
    let t = Instant::now();
    let status = loop {
        let r = c.get(&url).send().await.unwrap();
        if r.status() != 202 {
            break r.status().as_u16();
        }
        assert!(t.elapsed() < Duration::from_secs(10), "still encoding");
        tokio::time::sleep(Duration::from_millis(50)).await;
    };
    assert_eq!(status, 422);
    let m = c.get(srv.url("/metrics")).send().await.unwrap().text().await.unwrap();
    assert_eq!(metric(&m, "horizon_tiles_total{status=\"succeeded\"}"), 27.0);
    assert_eq!(metric(&m, "horizon_tiles_total{status=\"failed\"}"), 0.0);

    // Refusals at submission.
    for (q, field) in [
        ("radius=unlimited", "radius"),
        ("radius=40", "tile_size"),
        ("radius=8&formats=exr", "formats"),
        ("radius=8&method=sweep", "method"),
    ] {
        let r = c
            .post(srv.url(&format!("/v1/bakes?{q}")))
            .header("content-type", "image/png")
            .body(png.clone())
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), 422, "{q}");
        assert_eq!(r.headers()["content-type"], "application/problem+json");
        let p: Value = r.json().await.unwrap();
        assert_eq!(p["code"], "invalid_parameter", "{p}");
        assert_eq!(p["field"], field, "{p}");
    }
}

/// DELETE of a running tiled bake stops every tile within 2 s.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn delete_stops_every_tile_of_an_embedded_tiled_bake() {
    let srv = Server::start(|c| {
        c.tiles = TileSettings { tile_above: 64 * 64, tile_size: 48 };
        c.max_concurrent_bakes = 2;
    })
    .await;
    let c = client();
    let png = terrain_png16(192, 192, 4);
    let r = c
        .post(srv.url("/v1/bakes?method=exact&bins=256&radius=40"))
        .header("content-type", "image/png")
        .body(png)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 202);
    let loc = r.headers()["location"].to_str().unwrap().to_owned();
    let t = Instant::now();
    loop {
        let v: Value = c.get(srv.url(&loc)).send().await.unwrap().json().await.unwrap();
        // Once a tile has finished, the pool's two slots hold the next tiles: the DELETE then
        // lands with tiles in flight (right after the tiles were inserted none may have been
        // claimed yet, and no tile would be canceled: the test failed that way under load).
        let m = c.get(srv.url("/metrics")).send().await.unwrap().text().await.unwrap();
        let done = metric(&m, "horizon_tiles_total{status=\"succeeded\"}");
        if v["status"] == "running" && v["tiles"]["total"].as_u64().is_some() && done >= 1.0 {
            break;
        }
        assert!(t.elapsed() < Duration::from_secs(30), "never running in tiles: {v}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let t = Instant::now();
    let r = c.delete(srv.url(&loc)).send().await.unwrap();
    assert_eq!(r.status(), 202);
    let v = wait_done(&c, &srv.url(&loc), Duration::from_secs(10)).await;
    assert_eq!(v["status"], "canceled", "{v}");
    assert!(t.elapsed() < Duration::from_secs(2), "cancel took {:?}", t.elapsed());
    // Nothing keeps baking: the tile counters settle with no tile succeeding after the cancel.
    tokio::time::sleep(Duration::from_millis(500)).await;
    let m1 = c.get(srv.url("/metrics")).send().await.unwrap().text().await.unwrap();
    tokio::time::sleep(Duration::from_millis(1500)).await;
    let m2 = c.get(srv.url("/metrics")).send().await.unwrap().text().await.unwrap();
    let running = |m: &str| metric(m, "horizon_bakes_running");
    assert_eq!(running(&m2), 0.0, "{m2}");
    let ok = |m: &str| metric(m, "horizon_tiles_total{status=\"succeeded\"}");
    assert_eq!(ok(&m1), ok(&m2), "tiles still finishing after the cancel");
    assert!(metric(&m2, "horizon_tiles_total{status=\"canceled\"}") >= 1.0, "{m2}");
}
