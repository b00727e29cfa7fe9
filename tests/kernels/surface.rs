//! The surface maps (SPEC §3.8) against an independent computation: the normal by its own
//! central differences, and the AO and bent normal by a quadrature over elevation of the plain
//! exact oracle's horizon at 64 azimuths, on random maps with both edges; the PNGs decoded by
//! the `image` crate.

use crate::support::*;
use horizon_bake::heightmap::HeightMap;
use horizon_bake::kernels::exact::ExactMarch;
use horizon_bake::kernels::Grid;
use horizon_bake::params::{BakeParams, Edge, Reduce};
use horizon_bake::pipeline::surface::surface_files;
use horizon_bake::progress::Progress;
use std::f64::consts::{FRAC_PI_2, PI};

fn unit(v: [f64; 3]) -> [f64; 3] {
    let l = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    v.map(|c| c / l)
}

/// The SPEC §3.8 normal of texel (x, y), written out from the definition: y_axis=up, so the
/// tangent +y neighbour is the row above.
fn reference_normal(h: &[f32], w: usize, ht: usize, edge: Edge, x: usize, y: usize) -> [f64; 3] {
    let get = |c: i64, r: i64| -> Option<f64> {
        match edge {
            Edge::Wrap => Some(
                h[(r.rem_euclid(ht as i64) * w as i64 + c.rem_euclid(w as i64)) as usize] as f64,
            ),
            Edge::None => (c >= 0 && r >= 0 && c < w as i64 && r < ht as i64)
                .then(|| h[r as usize * w + c as usize] as f64),
        }
    };
    let (c, r) = (x as i64, y as i64);
    let here = h[y * w + x] as f64;
    let d = |p: Option<f64>, m: Option<f64>| match (p, m) {
        (Some(p), Some(m)) => (p - m) / 2.0,
        (Some(p), None) => p - here,
        (None, Some(m)) => here - m,
        (None, None) => 0.0,
    };
    let dx = d(get(c + 1, r), get(c - 1, r));
    let dy = d(get(c, r - 1), get(c, r + 1));
    unit([-dx, -dy, 1.0])
}

/// AO and bent normal by the midpoint rule over elevation (4000 steps) of the definition, at
/// the 64 azimuths of `s`.
fn reference_occlusion(s: &[f32], n: [f64; 3]) -> (f64, [f64; 3]) {
    let (nb, steps) = (s.len(), 4000);
    let (dphi, dth) = (2.0 * PI / nb as f64, FRAC_PI_2 / steps as f64);
    let (mut ao, mut v) = (0.0, [0.0; 3]);
    for (k, &sk) in s.iter().enumerate() {
        let phi = k as f64 * dphi;
        let alpha = (sk as f64).clamp(0.0, 1.0).asin();
        for i in 0..steps {
            let th = (i as f64 + 0.5) * dth;
            if th > alpha {
                let w = [th.cos() * phi.cos(), th.cos() * phi.sin(), th.sin()];
                let m = (n[0] * w[0] + n[1] * w[1] + n[2] * w[2]).max(0.0) * th.cos() * dth * dphi;
                ao += m;
                (0..3).for_each(|c| v[c] += m * w[c]);
            }
        }
    }
    (ao / PI, unit(v))
}

fn decode(png: &[u8]) -> image::DynamicImage {
    image::load_from_memory(png).unwrap()
}

/// Bytes → [−1, 1].
fn signed(b: u8) -> f64 {
    b as f64 / 255.0 * 2.0 - 1.0
}

#[test]
fn surface_maps_match_an_independent_quadrature_of_the_exact_horizon() {
    let mut rng = Rng(45);
    for (case, edge) in [Edge::Wrap, Edge::None, Edge::Wrap, Edge::None].into_iter().enumerate() {
        let (w, h) = (rng.range(14, 22), rng.range(12, 20));
        let mut values = waves(&mut rng, w, h, 3, 0.5);
        // Some texel-scale roughness, so horizons and normals differ texel to texel.
        values.iter_mut().for_each(|v| *v = (*v + 0.6 + 0.2 * rng.f32()) / 2.0);
        let map = HeightMap::from_values(w, h, values.clone()).unwrap();
        let edge_name = if edge == Edge::Wrap { "wrap" } else { "none" };
        let params = BakeParams::from_pairs([
            ("method", "exact"),
            ("radius", "12"),
            ("bins", "64"),
            ("edge", edge_name),
            ("height_scale", "6"),
            ("outputs", "normal,ao,bent_normal"),
        ])
        .unwrap();
        let (files, _, _) = pngs(&map, &params);
        let get = |n: &str| decode(&files.iter().find(|f| f.name == n).unwrap().bytes);
        let (normal, ao, bent) = (
            get("normal.png").to_rgb8(),
            get("ao.png").to_luma8(),
            get("bent_normal.png").to_rgb8(),
        );
        let scaled: Vec<f32> = values.iter().map(|v| v * 6.0).collect();
        let grid = Grid::new(w, h, &scaled, edge, horizon_bake::params::YAxis::Up);
        let oracle = ExactMarch::new(grid, Some(12), 64, Reduce::Average);
        let mut s = vec![0f32; 64];
        let (mut worst_ao, mut worst_bent, mut worst_n) = (0f64, 0f64, 0f64);
        for y in 0..h {
            for x in 0..w {
                let n = reference_normal(&scaled, w, h, edge, x, y);
                let px = normal.get_pixel(x as u32, y as u32).0;
                for c in 0..3 {
                    worst_n = worst_n.max((signed(px[c]) - n[c]).abs());
                }
                oracle.texel_bins(x, y, &mut s);
                let (a, b) = reference_occlusion(&s, n);
                worst_ao =
                    worst_ao.max((ao.get_pixel(x as u32, y as u32).0[0] as f64 / 255.0 - a).abs());
                let px = bent.get_pixel(x as u32, y as u32).0;
                for c in 0..3 {
                    worst_bent = worst_bent.max((signed(px[c]) - b[c]).abs());
                }
            }
        }
        eprintln!("case {case} ({w}×{h}, edge={edge_name}): normal {worst_n:.4}, ao {worst_ao:.4}, bent {worst_bent:.4}");
        // Half a level of quantisation, plus what the exact kernel and the oracle may differ by
        // (the same definition; the kernel's near field is vectorised) and the quadrature's step.
        assert!(worst_n <= 1.01 / 255.0, "case {case}: normal off by {worst_n}");
        assert!(worst_ao <= 1.5 / 255.0, "case {case}: ao off by {worst_ao}");
        assert!(worst_bent <= 3.0 / 255.0, "case {case}: bent normal off by {worst_bent}");
    }
}

#[test]
fn a_flat_open_map_is_unoccluded_for_every_method_and_conventions_flip_green() {
    let map = HeightMap::from_values(16, 16, vec![0.5; 256]).unwrap();
    for method in ["lengyel", "exact", "march", "sweep"] {
        for (conv, green) in [("opengl", 128u8), ("directx", 128u8)] {
            let params = BakeParams::from_pairs([
                ("method", method),
                ("normal_convention", conv),
                ("bent_normal_encoding", "rgb_ao"),
                ("outputs", "normal,ao,bent_normal"),
            ])
            .unwrap();
            let (files, _, _) = pngs(&map, &params);
            let get = |n: &str| decode(&files.iter().find(|f| f.name == n).unwrap().bytes);
            assert!(
                get("normal.png").to_rgb8().pixels().all(|p| p.0 == [128, green, 255]),
                "{method}"
            );
            let a = get("ao.png").to_luma8();
            assert!(a.pixels().all(|p| p.0 == [255]), "{method}: {:?}", &a.as_raw()[..16]);
            let b = get("bent_normal.png").to_rgba8();
            assert!(
                b.pixels().all(|p| p.0 == [128, green, 255, 255]),
                "{method}: {:?}",
                &b.as_raw()[..8]
            );
        }
    }
    // A ramp: y flips with the convention only.
    let map =
        HeightMap::from_values(8, 8, (0..64).map(|i| (i / 8) as f32 / 8.0).collect()).unwrap();
    let n = |conv: &str| {
        let params = BakeParams::from_pairs([
            ("normal_convention", conv),
            ("edge", "none"),
            ("outputs", "normal"),
        ])
        .unwrap();
        let (files, _, _) = pngs(&map, &params);
        decode(&files[0].bytes).to_rgb8().get_pixel(3, 3).0
    };
    let (gl, dx) = (n("opengl"), n("directx"));
    // Heights rise with the row (down the image), so with y_axis=up they fall toward +y and the
    // normal leans to +y: green above 128 in opengl, below in directx.
    assert!(gl[1] > 128 && dx[1] < 128 && gl[0] == dx[0] && gl[2] == dx[2], "{gl:?} {dx:?}");
    assert!((gl[1] as i32 + dx[1] as i32 - 255).abs() <= 1, "y negated: {gl:?} {dx:?}");
    // The convention names the image direction of the stored y: the same file whichever
    // way `y_axis` turned the tangent frame.
    let m = HeightMap::from_values(24, 20, waves(&mut Rng(7), 24, 20, 3, 0.4)).unwrap();
    for conv in ["opengl", "directx"] {
        let files = |y: &str| {
            let params = BakeParams::from_pairs([
                ("method", "exact"),
                ("radius", "8"),
                ("y_axis", y),
                ("normal_convention", conv),
                ("outputs", "normal,ao"),
            ])
            .unwrap();
            pngs(&m, &params).0
        };
        let (up, down) = (files("up"), files("down"));
        assert!(up[0].bytes == down[0].bytes, "{conv}: normal.png depends on y_axis");
        let (a, b) = (decode(&up[1].bytes).to_luma8(), decode(&down[1].bytes).to_luma8());
        assert!(
            a.pixels().zip(b.pixels()).all(|(p, q)| p.0[0].abs_diff(q.0[0]) <= 1),
            "{conv}: ao"
        );
    }
}

/// The surface maps computed in the streamed horizon layers' own kernel pass (what
/// `--outputs horizon,normal,ao,bent_normal` runs) are the maps of a pass of their own, for
/// every method, both edges and a map with holes; the layers are unchanged by the tap.
#[test]
fn the_same_pass_as_the_horizon_layers_gives_the_same_maps() {
    use horizon_bake::bake::bake_surface;
    use horizon_bake::pipeline::{stream_horizon_pngs, stream_horizon_pngs_tapped};
    let mut rng = Rng(451);
    let (w, h) = (37, 29);
    let values = waves(&mut rng, w, h, 3, 0.6);
    let mut holed = HeightMap::from_values(w, h, values.clone()).unwrap();
    let mut mask = vec![false; w * h];
    for i in [40usize, 41, 77, 300, 301, 302, 640] {
        mask[i] = true;
    }
    holed.terrain.holes = Some(mask);
    let plain = HeightMap::from_values(w, h, values).unwrap();
    for (method, edge, map) in [
        ("lengyel", "wrap", &plain),
        ("exact", "none", &plain),
        ("march", "wrap", &plain),
        ("sweep", "none", &plain),
        ("exact", "none", &holed),
    ] {
        let params = BakeParams::from_pairs([
            ("method", method),
            ("radius", "10"),
            ("edge", edge),
            ("bent_normal_encoding", "rgb_ao"),
            ("outputs", "horizon,normal,ao,bent_normal"),
        ])
        .unwrap();
        let p = Progress::new();
        let (alone, _) = bake_surface(map, &params, &p).unwrap();
        let (layers, _, tapped) =
            stream_horizon_pngs_tapped::<u8, _>(map.clone(), &params, true, &p, [vec![], vec![]])
                .unwrap();
        let tapped = tapped.unwrap();
        assert!(alone.normal == tapped.normal, "{method}: normal");
        assert!(alone.ao == tapped.ao, "{method}: ao");
        assert!(alone.bent_normal == tapped.bent_normal, "{method}: bent");
        if let Some(m) = &map.terrain.holes {
            // Every output of a hole is 0 (SPEC §2), and a hole's neighbour is still surface.
            let (n, a) = (alone.normal.as_ref().unwrap(), alone.ao.as_ref().unwrap());
            for (i, _) in m.iter().enumerate().filter(|(_, &h)| h) {
                assert_eq!((&n[i * 3..i * 3 + 3], a[i]), (&[0u8, 0, 0][..], 0), "hole {i}");
                if !m[i + w] {
                    assert!(n[(i + w) * 3 + 2] > 0 && a[i + w] > 0, "below hole {i}");
                }
            }
        }
        let (plain_layers, _) =
            stream_horizon_pngs::<u8, _>(map.clone(), &params, &p, [vec![], vec![]]).unwrap();
        assert!(layers == plain_layers, "{method}: the tap changed the layers");
    }
}

/// The surface maps' files of `params` for `map` with the default formats (their PNGs).
fn pngs(
    map: &HeightMap,
    params: &BakeParams,
) -> (Vec<horizon_bake::encode::OutFile>, horizon_bake::bake::ResolvedRadius, serde_json::Value) {
    surface_files(map, params, &horizon_bake::encode::Formats::default(), &Progress::new()).unwrap()
}
