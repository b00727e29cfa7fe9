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
        let (layers, _, tapped) = stream_horizon_pngs_tapped::<u8, _>(
            map.clone(),
            &params,
            horizon_bake::bake::Surface::Bytes,
            &p,
            [vec![], vec![]],
        )
        .unwrap();
        let tapped = tapped.unwrap();
        assert!(alone.normal == tapped.normal, "{method}: normal");
        assert!(alone.ao == tapped.ao, "{method}: ao");
        assert!(alone.bent_normal == tapped.bent_normal, "{method}: bent");
        // The values the 16-bit PNGs and EXRs take, streamed with 16-bit layers, too.
        let keep = horizon_bake::bake::Surface::Values;
        let (alone_v, _) = horizon_bake::bake::bake_surface_as(map, &params, keep, &p).unwrap();
        let (_, _, tapped_v) =
            stream_horizon_pngs_tapped::<u16, _>(map.clone(), &params, keep, &p, [vec![], vec![]])
                .unwrap();
        let (a, t) = (alone_v.values.unwrap(), tapped_v.unwrap().values.unwrap());
        assert!(a.normal.is_some() && a.ao.is_some() && a.bent_normal.is_some(), "{method}");
        assert!(a.normal == t.normal && a.ao == t.ao, "{method}: normal and ao values");
        assert!(a.bent_normal == t.bent_normal, "{method}: bent normal values");
        assert!(alone_v.normal == alone.normal, "{method}: the bytes do not depend on the values");
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

/// The samples of channel `name` of an EXR file, as f32 (half samples widened), read by the
/// `exr` crate.
fn exr_channel(bytes: &[u8], name: &str) -> Vec<f32> {
    use exr::prelude::*;
    let img = read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .first_valid_layer()
        .all_attributes()
        .from_buffered(std::io::Cursor::new(bytes))
        .unwrap();
    let c = img.layer_data.channel_data.list.iter().find(|c| c.name.to_string() == name).unwrap();
    match &c.sample_data {
        FlatSamples::F32(v) => v.clone(),
        FlatSamples::F16(v) => v.iter().map(|h| h.to_f32()).collect(),
        FlatSamples::U32(_) => panic!("{name}: u32 samples"),
    }
}

/// Issue 45: the surface maps in the layers' other formats (SPEC §3.8). `png16` writes 16-bit
/// PNGs under the same names, `exr` float or half EXRs of the same values unquantised
/// (normal and bent normal RGB(A), the AO as one Y channel), each read by a decoder we did not
/// write: every 16-bit sample is floor(v·65535 + 0.5) of the EXR's value, and every 8-bit
/// byte of the default bake is that value's byte (a level at most where f32 rounding meets a
/// tie); the half EXR holds the float one's values as halves.
#[test]
fn sixteen_bit_and_exr_surface_maps_hold_the_8_bit_maps_values() {
    use horizon_bake::encode::exr::ExrPrecision;
    use horizon_bake::encode::Formats;
    let (w, h) = (37, 29);
    let mut rng = Rng(4516);
    let map = HeightMap::from_values(w, h, waves(&mut rng, w, h, 4, 0.4)).unwrap();
    for (edge, encoding) in [("wrap", "rgb_ao"), ("none", "rgb"), ("wrap", "rg")] {
        let params = BakeParams::from_pairs([
            ("method", "exact"),
            ("radius", "12"),
            ("height_scale", "20"),
            ("edge", edge),
            ("normal_convention", "directx"),
            ("bent_normal_encoding", encoding),
            ("outputs", "normal,ao,bent_normal"),
        ])
        .unwrap();
        let p = Progress::new();
        let bake = |list: &str, half: bool| {
            let mut f = Formats::parse(list, Default::default()).unwrap();
            if half {
                f.exr_precision = ExrPrecision::Half;
            }
            let (files, _, info) = surface_files(&map, &params, &f, &p).unwrap();
            let files: std::collections::BTreeMap<&str, Vec<u8>> =
                files.into_iter().map(|f| (f.name, f.bytes)).collect();
            (files, info)
        };
        let (eight, _) = bake("png8", false);
        let (deep, info) = bake("png16,exr", false);
        let (half, _) = bake("exr", true);
        let names: Vec<&str> = deep.keys().copied().collect();
        assert_eq!(
            names,
            ["ao.exr", "ao.png", "bent_normal.exr", "bent_normal.png", "normal.exr", "normal.png"],
            "{edge} {encoding}"
        );
        assert_eq!(half.len(), 3, "an EXR-only bake writes the EXRs alone");
        assert_eq!(info["normal.png"]["depth"], "16-bit");
        assert_eq!(info["ao.exr"]["depth"], "float32");
        let bent_ch = if encoding == "rgb_ao" { 4 } else { 3 };
        for (stem, names) in [
            ("normal", &["R", "G", "B"][..]),
            ("ao", &["Y"][..]),
            ("bent_normal", &["R", "G", "B", "A"][..bent_ch]),
        ] {
            let ch = names.len();
            let chans: Vec<Vec<f32>> =
                names.iter().map(|n| exr_channel(&deep[&*format!("{stem}.exr")], n)).collect();
            let halves: Vec<Vec<f32>> =
                names.iter().map(|n| exr_channel(&half[&*format!("{stem}.exr")], n)).collect();
            let png16: Vec<u16> = decode(&deep[&*format!("{stem}.png")])
                .into_bytes()
                .chunks_exact(2)
                .map(|b| u16::from_ne_bytes([b[0], b[1]]))
                .collect();
            let png8 = decode(&eight[&*format!("{stem}.png")]).into_bytes();
            assert_eq!(png16.len(), w * h * ch, "{stem}: a 16-bit PNG of {ch} channels");
            assert_eq!(png8.len(), w * h * ch, "{stem}: an 8-bit PNG of {ch} channels");
            let mut ties = 0;
            for t in 0..w * h {
                for c in 0..ch {
                    let v = chans[c][t];
                    assert!((0.0..=1.0).contains(&v), "{stem} {t} {c}: {v}");
                    let k = t * ch + c;
                    assert_eq!(
                        png16[k],
                        (f64::from(v) * 65535.0 + 0.5).floor() as u16,
                        "{stem} {k}"
                    );
                    let byte = (f64::from(v) * 255.0 + 0.5).floor();
                    let d = (byte - f64::from(png8[k])).abs();
                    assert!(d <= 1.0, "{stem} {k}: {v} against byte {}", png8[k]);
                    ties += usize::from(d > 0.0);
                    let hv = exr::prelude::f16::from_f32(v).to_f32();
                    assert_eq!(halves[c][t].to_bits(), hv.to_bits(), "{stem} half {k}");
                }
            }
            assert!(ties * 1000 <= w * h * ch, "{stem}: {ties} bytes off their value's");
            if encoding == "rg" && stem == "bent_normal" {
                assert!(chans[2].iter().all(|&b| b == 0.0), "rg: blue 0 as in the PNG");
            }
        }
        // As KTX2 and DDS textures in 16 bits and float (SPEC §3.8: as the layers): RGBA16 the
        // 16-bit PNG's samples, RGBA32F the EXR's values, alpha 1 where the map has none, read
        // by the `ktx2` and `ddsfile` crates.
        for (precision, format) in [
            ("unorm16", ktx2::Format::R16G16B16A16_UNORM),
            ("float32", ktx2::Format::R32G32B32A32_SFLOAT),
        ] {
            let mut f = Formats::parse("ktx2,dds", Default::default()).unwrap();
            f.texture.precision = horizon_bake::encode::TexturePrecision::parse(precision).unwrap();
            let (files, _, info) = surface_files(&map, &params, &f, &p).unwrap();
            let files: std::collections::BTreeMap<&str, Vec<u8>> =
                files.into_iter().map(|f| (f.name, f.bytes)).collect();
            assert_eq!(files.len(), 6, "{precision}: {:?}", files.keys());
            assert_eq!(info["normal.ktx2"]["texture_precision"], precision);
            for stem in ["normal", "ao", "bent_normal"] {
                let ktx = &files[&*format!("{stem}.ktx2")];
                let r = ktx2::Reader::new(&ktx[..]).unwrap();
                assert_eq!(r.header().format, Some(format), "{stem} {precision}");
                assert_eq!(r.header().layer_count, 0, "{stem}: a 2D texture");
                let data = r.levels().next().unwrap().data;
                let want: Vec<f32> = match stem {
                    "ao" => exr_channel(&deep["ao.exr"], "Y")
                        .iter()
                        .flat_map(|&a| [a, a, a, 1.0])
                        .collect(),
                    _ => {
                        let names = ["R", "G", "B", "A"];
                        let ch = if stem == "normal" { 3 } else { bent_ch };
                        let c: Vec<Vec<f32>> = names[..ch]
                            .iter()
                            .map(|n| exr_channel(&deep[&*format!("{stem}.exr")], n))
                            .collect();
                        (0..w * h)
                            .flat_map(|t| [0, 1, 2, 3].map(|k| c.get(k).map_or(1.0, |c| c[t])))
                            .collect()
                    }
                };
                let got: Vec<f32> = if precision == "unorm16" {
                    data.chunks_exact(2).map(|b| u16::from_le_bytes([b[0], b[1]]) as f32).collect()
                } else {
                    data.chunks_exact(4)
                        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                        .collect()
                };
                assert_eq!(got.len(), want.len(), "{stem} {precision}");
                for (k, (&g, &v)) in got.iter().zip(&want).enumerate() {
                    let v = if precision == "unorm16" {
                        (f64::from(v) * 65535.0 + 0.5).floor() as f32
                    } else {
                        v
                    };
                    assert_eq!(g.to_bits(), v.to_bits(), "{stem} {precision} {k}");
                }
                let dds = ddsfile::Dds::read(&files[&*format!("{stem}.dds")][..]).unwrap();
                assert_eq!(
                    &dds.data[..],
                    data,
                    "{stem} {precision}: the DDS holds the same texels"
                );
            }
        }
        // The AO is the same in its own map and in the bent normal's alpha.
        if encoding == "rgb_ao" {
            assert_eq!(
                exr_channel(&deep["ao.exr"], "Y"),
                exr_channel(&deep["bent_normal.exr"], "A")
            );
        }
    }
}
