//! Issue 24, terrain users: DEM input, nodata holes, terrain products, GeoTIFF output.
//!
//! The GeoTIFF outputs and the real DEM (R terra's `elev.tif`, SRTM-derived) are checked by GDAL
//! through rasterio in tests/terrain/check_dem.py, run from here; under CI=true a missing
//! rasterio fails the test instead of skipping it.

use horizon_bake::bake;
use horizon_bake::heightmap::georef::{apply_dem_defaults, Georef};
use horizon_bake::heightmap::{decode_with, Limits};
use horizon_bake::kernels::exact::ExactHorizon;
use horizon_bake::kernels::Grid;
use horizon_bake::params::{BakeParams, Channel, Edge, NoData, Reduce, YAxis};
use horizon_bake::progress::Progress;
use horizon_bake::terrain::sun::SunAzimuth;
use horizon_bake::Error;

/// A gray float32 TIFF of `values` (no georeferencing), written by the `tiff` crate.
fn tiff_f32(w: u32, h: u32, values: &[f32]) -> Vec<u8> {
    let mut buf = std::io::Cursor::new(Vec::new());
    let mut enc = tiff::encoder::TiffEncoder::new(&mut buf).unwrap();
    enc.write_image::<tiff::encoder::colortype::Gray32Float>(w, h, values).unwrap();
    buf.into_inner()
}

/// Uniform numbers in [0, 1) from a linear congruential generator seeded with `seed`.
fn lcg(mut seed: u64) -> impl FnMut() -> f32 {
    move || {
        seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        (seed >> 33) as f32 / (1u64 << 31) as f32
    }
}

/// A float32 TIFF of `v` (`w × h`) decoded with −9999 as nodata, as a DEM with holes.
fn dem_of(w: usize, h: usize, v: &[f32]) -> horizon_bake::heightmap::HeightMap {
    decode_with(
        &tiff_f32(w as u32, h as u32, v),
        Channel::Luma,
        NoData::Value(-9999.0),
        &Limits::default(),
    )
    .unwrap()
    .0
}

/// A signed 16-bit TIFF, as SRTM tiles are.
fn tiff_i16(w: u32, h: u32, values: &[i16]) -> Vec<u8> {
    let mut buf = std::io::Cursor::new(Vec::new());
    let mut enc = tiff::encoder::TiffEncoder::new(&mut buf).unwrap();
    enc.write_image::<tiff::encoder::colortype::GrayI16>(w, h, values).unwrap();
    buf.into_inner()
}

/// Parameters as a submission reads them, before the input: the rules a DEM's defaults may
/// change wait for [`apply_dem_defaults`].
fn params(pairs: &[(&str, &str)]) -> BakeParams {
    let p = BakeParams::from_pairs_unchecked(pairs.iter().copied()).unwrap();
    p.check_before_input().unwrap();
    p
}

#[test]
fn signed_16_bit_samples_are_used_as_they_are() {
    let v: Vec<i16> = vec![-32768, -5, 0, 1200];
    let (map, info) =
        decode_with(&tiff_i16(2, 2, &v), Channel::Luma, NoData::None, &Limits::default()).unwrap();
    assert_eq!(map.values, vec![-32768.0, -5.0, 0.0, 1200.0]);
    assert_eq!((info.bit_depth, info.float), (16, false));
    // Declared nodata: the hole is filled far below the map, and marked.
    let (map, _) = decode_with(
        &tiff_i16(2, 2, &v),
        Channel::Luma,
        NoData::Value(-32768.0),
        &Limits::default(),
    )
    .unwrap();
    assert_eq!(map.terrain.holes.as_deref(), Some(&[true, false, false, false][..]));
    assert!(map.values[0] < -5.0 - 1000.0 * 1205.0 + 1.0, "fill {}", map.values[0]);
}

#[test]
fn refusals_name_the_fix() {
    let l = Limits::default();
    // NaN without a nodata declaration.
    let nan = tiff_f32(2, 2, &[0.0, f32::NAN, 1.0, 2.0]);
    let e = decode_with(&nan, Channel::Luma, NoData::Auto, &l).unwrap_err();
    assert!(matches!(&e, Error::InvalidInput(m) if m.contains("nodata=nan")), "{e}");
    // ... and accepted with one.
    let (map, _) = decode_with(&nan, Channel::Luma, NoData::Nan, &l).unwrap();
    assert_eq!(map.terrain.holes.as_deref(), Some(&[false, true, false, false][..]));
    // All nodata.
    let all = tiff_f32(2, 2, &[-9999.0; 4]);
    let e = decode_with(&all, Channel::Luma, NoData::Value(-9999.0), &l).unwrap_err();
    assert!(matches!(&e, Error::InvalidInput(m) if m.contains("every texel is nodata")), "{e}");
    assert_eq!(e.exit_code(), 2);
}

/// A projected DEM's tags: 30 m pixels, UTM 32N (EPSG:32632), metres.
fn utm_georef(sx: f64, sy: f64, model: u16) -> Georef {
    Georef {
        pixel_scale: Some(vec![sx, sy, 0.0]),
        tiepoints: Some(vec![0.0, 0.0, 0.0, 500000.0, 5500000.0, 0.0]),
        geo_keys: Some(vec![1, 1, 0, 3, 1024, 0, 1, model, 3072, 0, 1, 32632, 3076, 0, 1, 9001]),
        ..Georef::default()
    }
}

#[test]
fn dem_defaults_apply_unless_given() {
    let g = utm_georef(30.0, 30.0, 1);
    assert_eq!(g.epsg(), Some(32632));
    assert_eq!(g.transform(), Some([500000.0, 30.0, 0.0, 5500000.0, 0.0, -30.0]));
    let mut p = params(&[("method", "exact")]);
    apply_dem_defaults(&mut p, Some(&g)).unwrap();
    assert_eq!(p.cell_size, Some(30.0));
    assert_eq!(p.height_scale, 1.0 / 30.0);
    assert_eq!(p.edge, Edge::None);
    assert_eq!(p.earth_curvature, horizon_bake::params::EarthCurvature::On);
    // Explicit parameters win.
    let mut p = params(&[("method", "exact"), ("height_scale", "2"), ("edge", "wrap")]);
    apply_dem_defaults(&mut p, Some(&g)).unwrap();
    assert_eq!((p.height_scale, p.edge), (2.0, Edge::Wrap));
    // Lengyel does not model the curvature: off by default, refused when asked.
    let mut p = params(&[("method", "lengyel")]);
    apply_dem_defaults(&mut p, Some(&g)).unwrap();
    assert_eq!(p.earth_curvature, horizon_bake::params::EarthCurvature::Off);
    let mut p = params(&[("method", "lengyel"), ("earth_curvature", "on")]);
    let e = apply_dem_defaults(&mut p, Some(&g)).unwrap_err();
    assert!(matches!(&e, Error::Param { field, .. } if field == "earth_curvature"), "{e}");
    // The march casts rays: on by default for a DEM, as for exact.
    let mut p = params(&[("method", "march"), ("radius", "64")]);
    apply_dem_defaults(&mut p, Some(&g)).unwrap();
    assert_eq!(p.earth_curvature, horizon_bake::params::EarthCurvature::On);
    // Geographic, non-square: refused naming the fix, unless cell_size is given.
    let geo = utm_georef(0.001, 0.001, 2);
    let e = apply_dem_defaults(&mut params(&[]), Some(&geo)).unwrap_err();
    assert!(e.to_string().contains("gdalwarp -t_srs"), "{e}");
    let mut p = params(&[("cell_size", "90")]);
    apply_dem_defaults(&mut p, Some(&geo)).unwrap();
    assert_eq!(p.height_scale, 1.0 / 90.0);
    let e = apply_dem_defaults(&mut params(&[]), Some(&utm_georef(30.0, 20.0, 1))).unwrap_err();
    assert!(e.to_string().contains("not square"), "{e}");
    // max_distance needs a cell size.
    let e = apply_dem_defaults(&mut params(&[("max_distance", "100")]), None).unwrap_err();
    assert!(matches!(&e, Error::Param { field, .. } if field == "max_distance"), "{e}");
}

/// SPEC §2: without `method` and `radius` a DEM is baked by a line of sight to the map's edge
/// (`sweep`, `exact` where `sweep` cannot run), curvature on; a plain image keeps `lengyel` at
/// 16 texels. Before this, a DEM without flags was baked by `lengyel` at 16 texels (degrees off
/// by 2–4° on average on real DEMs).
#[test]
fn a_dem_without_method_is_a_line_of_sight_to_the_edge() {
    use horizon_bake::params::{EarthCurvature, Method, Radius};
    let g = utm_georef(30.0, 30.0, 1);
    let mut p = params(&[]);
    apply_dem_defaults(&mut p, Some(&g)).unwrap();
    assert_eq!(
        (p.method, p.radius, p.earth_curvature),
        (Method::Sweep, Radius::Unlimited, EarthCurvature::On)
    );
    // A reach given is kept, with the line of sight.
    let mut p = params(&[("radius", "40")]);
    apply_dem_defaults(&mut p, Some(&g)).unwrap();
    assert_eq!((p.method, p.radius), (Method::Sweep, Radius::Texels(40)));
    let mut p = params(&[("max_distance", "3000")]);
    apply_dem_defaults(&mut p, Some(&g)).unwrap();
    assert_eq!(p.method, Method::Sweep);
    // A method given is kept, with its radius.
    let mut p = params(&[("method", "exact")]);
    apply_dem_defaults(&mut p, Some(&g)).unwrap();
    assert_eq!((p.method, p.radius), (Method::Exact, Radius::Texels(16)));
    // A plain image: today's defaults.
    let mut p = params(&[]);
    apply_dem_defaults(&mut p, None).unwrap();
    assert_eq!(
        (p.method, p.radius, p.earth_curvature),
        (Method::Lengyel, Radius::Texels(16), EarthCurvature::Off)
    );
    // `bins` for angles alone waits for the method: any count on a DEM (a ray method), a
    // multiple of 16 on a plain image (lengyel), refused naming `bins`.
    let b36 = || {
        let p = BakeParams::from_pairs_unchecked([("bins", "36"), ("outputs", "angles")]).unwrap();
        p.check_before_input().unwrap();
        p
    };
    let mut p = b36();
    apply_dem_defaults(&mut p, Some(&g)).unwrap();
    assert_eq!(p.bins, 36);
    let e = apply_dem_defaults(&mut b36(), None).unwrap_err();
    assert!(matches!(&e, Error::Param { field, .. } if field == "bins"), "{e}");
    // Given, lengyel's rules hold at once.
    let p = BakeParams::from_pairs_unchecked([
        ("bins", "36"),
        ("outputs", "angles"),
        ("method", "lengyel"),
    ])
    .unwrap();
    assert!(p.check_before_input().is_err());
}

/// The DEM defaults' `sweep` becomes `exact` where `sweep` cannot run: a far field too large
/// even for the disk (only for outputs taken from its bands: `angles` and a plain SVF come
/// from its planes, with no table, at any size), or a map baked in tiles; the choice is then
/// marked given, so the stored parameters replay to it. A `sweep` the user asked for is
/// refused instead.
#[test]
fn the_default_sweep_gives_way_to_exact_where_it_cannot_run() {
    use horizon_bake::params::Method;
    let g = utm_georef(30.0, 30.0, 1);
    let dem = |outputs: &str, bins: &str| {
        let mut p = params(&[("bins", bins), ("outputs", outputs)]);
        apply_dem_defaults(&mut p, Some(&g)).unwrap();
        p
    };
    let mut p = dem("angles", "720");
    bake::fit_method(&mut p, 500, 400, false).unwrap();
    assert_eq!(p.method, Method::Sweep);
    assert!(p.explicit.has("method"));
    let huge = 60_000;
    assert!(horizon_bake::kernels::sweep::check_memory(huge, huge, 256).is_err());
    let mut p = dem("angles,svf", "720");
    bake::fit_method(&mut p, huge, huge, false).unwrap();
    assert_eq!(p.method, Method::Sweep, "angles and svf need no table");
    let mut p = dem("horizon", "256");
    bake::fit_method(&mut p, huge, huge, false).unwrap();
    assert_eq!(p.method, Method::Exact);
    let mut p = dem("angles", "720");
    bake::fit_method(&mut p, 500, 400, true).unwrap();
    assert_eq!(p.method, Method::Exact);
    let mut asked = params(&[("bins", "256"), ("outputs", "horizon"), ("method", "sweep")]);
    apply_dem_defaults(&mut asked, Some(&g)).unwrap();
    let e = bake::fit_method(&mut asked, huge, huge, false).unwrap_err();
    assert!(matches!(&e, Error::Param { field, .. } if field == "method"), "{e}");
    // In tiles, the default reach (to the edge) is refused naming what to give.
    let s = horizon_bake::pipeline::tiled::TileSettings { tile_above: 1 << 20, tile_size: 512 };
    let mut p = params(&[("outputs", "angles,svf")]);
    apply_dem_defaults(&mut p, Some(&g)).unwrap();
    bake::fit_method(&mut p, 2048, 2048, true).unwrap();
    let f = horizon_bake::encode::Formats::default();
    let e = horizon_bake::pipeline::tiled::check(&p, &f, 2048, 2048, &s).unwrap_err();
    assert!(
        matches!(&e, Error::Param { field, message } if field == "radius" && message.contains("max_distance")),
        "{e}"
    );
    let mut p = params(&[("outputs", "angles,svf"), ("max_distance", "5000")]);
    apply_dem_defaults(&mut p, Some(&g)).unwrap();
    bake::fit_method(&mut p, 2048, 2048, true).unwrap();
    assert_eq!(p.method, Method::Exact);
    horizon_bake::pipeline::tiled::check(&p, &f, 2048, 2048, &s).unwrap();
}

/// Parameters from pairs with the rules joining several keys checked, as a submission or the
/// CLI checks them once every key is set.
fn checked<'a>(
    pairs: impl IntoIterator<Item = (&'a str, &'a str)>,
) -> horizon_bake::Result<BakeParams> {
    let p = BakeParams::from_pairs(pairs)?;
    p.check()?;
    Ok(p)
}

#[test]
fn bins_rules_depend_on_outputs_and_method() {
    // Horizon layers: multiples of 16.
    assert!(checked([("bins", "24")]).is_err());
    // Angles alone with a ray method: any count 1..720.
    for b in ["1", "7", "720"] {
        let p = checked([("bins", b), ("outputs", "angles"), ("method", "exact")]);
        assert!(p.is_ok(), "bins={b}: {p:?}");
    }
    assert!(checked([("bins", "721"), ("outputs", "angles"), ("method", "exact")]).is_err());
    // ... not with lengyel, nor with the horizon layers too.
    assert!(checked([("bins", "7"), ("outputs", "angles")]).is_err());
    assert!(checked([("bins", "7"), ("outputs", "angles,horizon"), ("method", "exact")]).is_err());
    // Compass bands need north among the bins.
    let e = checked([
        ("bins", "6"),
        ("outputs", "angles"),
        ("method", "exact"),
        ("azimuth_from", "north_cw"),
    ])
    .unwrap_err();
    assert!(matches!(&e, Error::Param { field, .. } if field == "azimuth_from"), "{e}");
}

/// A flat 41² map with a 20-texel tower at its centre, the tower marked nodata.
fn towered(nodata: bool) -> horizon_bake::heightmap::HeightMap {
    let n = 41;
    let mut v = vec![0f32; n * n];
    for y in 19..22 {
        for x in 19..22 {
            v[y * n + x] = 20.0;
        }
    }
    let nd = if nodata { NoData::Value(20.0) } else { NoData::None };
    decode_with(&tiff_f32(n as u32, n as u32, &v), Channel::Luma, nd, &Limits::default()).unwrap().0
}

#[test]
fn a_hole_casts_no_shadow_and_has_no_value() {
    let p = params(&[
        ("method", "exact"),
        ("radius", "unlimited"),
        ("edge", "none"),
        ("height_scale", "1"),
        ("outputs", "angles,svf,horizon"),
        ("bins", "32"),
    ]);
    // Without nodata, the tower shadows the plain around it.
    let (t, _) = bake::bake_terrain(&towered(false), &p, &Progress::new()).unwrap();
    let a = t.angles.unwrap();
    assert!(a.iter().any(|&v| v > 10.0), "the tower casts shadows");
    // As a hole: every valid texel sees an open sky, every hole is NaN (no nodata declared:
    // here 20 was, so 20 is written).
    let map = towered(true);
    let holes = map.terrain.holes.clone().unwrap();
    assert_eq!(holes.iter().filter(|&&h| h).count(), 9);
    let (t, _) = bake::bake_terrain(&map, &p, &Progress::new()).unwrap();
    let (a, s) = (t.angles.unwrap(), t.svf.unwrap());
    let plane = 41 * 41;
    for (k, &hole) in holes.iter().enumerate() {
        for n in 0..32 {
            let v = a[n * plane + k];
            if hole {
                assert_eq!(v, 20.0, "hole {k} band {n}");
            } else {
                assert_eq!(v, 0.0, "texel {k} band {n}: a hole occluded it");
            }
        }
        assert_eq!(s[k], if hole { 20.0 } else { 1.0 }, "svf at {k}");
    }
    // The horizon layers: 0 at holes and, here, everywhere.
    let (layers, _) =
        bake::bake_horizon(&map, &p, horizon_bake::bake::Precisions::U8, &Progress::new()).unwrap();
    let l = layers.u8.as_ref().unwrap();
    assert!(l.iter().all(|layer| layer.iter().all(|&b| b == 0)));
    assert_eq!(l[0].len(), plane * 4);
}

#[test]
fn hole_ridden_maps_never_show_values_in_holes() {
    // Rough random terrain with a fifth of it missing, every method.
    let (w, h) = (37, 29);
    let mut rnd = lcg(24u64);
    let v: Vec<f32> =
        (0..w * h).map(|_| if rnd() < 0.2 { -9999.0 } else { rnd() * 30.0 }).collect();
    let map = dem_of(w, h, &v);
    let holes = map.terrain.holes.clone().unwrap();
    for method in ["exact", "march", "lengyel"] {
        let p = params(&[
            ("method", method),
            ("radius", "12"),
            ("height_scale", "1"),
            ("outputs", "angles,svf,horizon"),
        ]);
        let (t, _) = bake::bake_terrain(&map, &p, &Progress::new()).unwrap();
        let (a, s) = (t.angles.unwrap(), t.svf.unwrap());
        let plane = w * h;
        for (k, &hole) in holes.iter().enumerate() {
            assert_eq!(s[k] == -9999.0, hole, "{method} svf at {k}");
            for n in 0..32 {
                assert_eq!(a[n * plane + k] == -9999.0, hole, "{method} band {n} at {k}");
            }
        }
        let (layers, _) =
            bake::bake_horizon(&map, &p, bake::Precisions::U8, &Progress::new()).unwrap();
        let l = layers.u8.as_ref().unwrap();
        for (k, &hole) in holes.iter().enumerate() {
            if hole {
                assert!(
                    l.iter().all(|layer| layer[k * 4..k * 4 + 4] == [0, 0, 0, 0]),
                    "{method} {k}"
                );
            }
        }
    }
}

#[test]
fn curvature_lowers_a_far_wall_exactly() {
    // A wall of height 50 texels, 100 texels east of the observer; the drop there is
    // k·100² = 10 texels with k = 1e-3, so tan α = (50 − 10)/100 = 0.4 (0.5 without).
    let (w, h) = (201, 3);
    let mut v = vec![0f32; w * h];
    for r in 0..h {
        v[r * w + 100] = 50.0;
    }
    let g = Grid::new(w, h, &v, Edge::None, YAxis::Up);
    let flat = ExactHorizon::new(g, None, 16, Reduce::Point).horizon_sin(0, 1, 0.0);
    let curved =
        ExactHorizon::new(g, None, 16, Reduce::Point).with_curvature(1e-3).horizon_sin(0, 1, 0.0);
    let sin = |t: f64| t / (1.0 + t * t).sqrt();
    assert!((flat - sin(0.5)).abs() < 1e-6, "flat {flat}");
    assert!((curved - sin(0.4)).abs() < 1e-6, "curved {curved}");
    // The bake's k from SPEC §3.7: cell² · height_scale / (2 R_e).
    let p = params(&[
        ("method", "exact"),
        ("cell_size", "30"),
        ("earth_curvature", "on"),
        ("height_scale", "0.5"),
        ("refraction", "0.13"),
    ]);
    let k = bake::curvature(&p);
    let want = 30.0 * 30.0 * 0.5 / (2.0 * 6_371_000.0 / (1.0 - 0.13));
    assert!((k - want).abs() < 1e-18, "{k} vs {want}");
}

#[test]
fn dem_products_read_by_gdal() {
    let ci = std::env::var("CI").is_ok_and(|v| v == "true");
    let has = std::process::Command::new("python3")
        .args(["-c", "import rasterio, numpy, pvlib"])
        .status()
        .is_ok_and(|s| s.success());
    if !has {
        assert!(!ci, "CI=true: python3 with rasterio, numpy and pvlib is required (pip install rasterio pvlib)");
        eprintln!(
            "skipped: python3 with rasterio or pvlib is missing (pip install rasterio pvlib)"
        );
        return;
    }
    let work = tempfile::tempdir().unwrap();
    let out = std::process::Command::new("python3")
        .arg(concat!(env!("CARGO_MANIFEST_DIR"), "/tests/terrain/check_dem.py"))
        .arg(env!("CARGO_BIN_EXE_horizon-bake"))
        .arg(work.path())
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    eprintln!("{text}{}", String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "tests/terrain/check_dem.py failed");
}

#[test]
fn lengyel_shadow_is_lz_above_the_decoded_layers() {
    // SPEC §3.7: with `lengyel` (no ray) lit means L_z > s of §3.3 decoded from the baked layers.
    // The oracle: the two stored 8-bit channels that bracket the sun's azimuth, blended linearly
    // by its position between them (§3.3's factors written out), against sin e; on a rough map
    // with holes, every texel, both encodings, both azimuth conventions.
    let (w, h) = (48usize, 40usize);
    let mut rnd = lcg(0x5AD0u64);
    let v: Vec<f32> = (0..w * h)
        .map(|k| {
            let (x, y) = ((k % w) as f32, (k / w) as f32);
            if rnd() < 0.02 {
                -9999.0
            } else {
                6.0 * (x * 0.31).sin() * (y * 0.23).cos() + 3.0 * rnd()
            }
        })
        .collect();
    let map = dem_of(w, h, &v);
    let holes = map.terrain.holes.clone().unwrap();
    let pr = Progress::new();
    for (encoding, el) in [("linear", 14.0f64), ("sqrt", 27.0)] {
        let base = [("radius", "16"), ("height_scale", "1"), ("encoding", encoding)];
        let with = |extra: &[(&'static str, &'static str)]| {
            let mut kv = base.to_vec();
            kv.extend_from_slice(extra);
            params(&kv)
        };
        let p = with(&[("method", "lengyel")]);
        let az = 200.0f64; // east_ccw: 250° from north, clockwise (y up)
        let got = bake::shadow(&map, &p, SunAzimuth::Grid(az), el, &pr).unwrap();
        let compass = bake::shadow(
            &map,
            &with(&[("method", "lengyel"), ("azimuth_from", "north_cw")]),
            SunAzimuth::True(250.0),
            el,
            &pr,
        )
        .unwrap();
        assert_eq!(got, compass, "{encoding}: the same sun counted from north");
        let (layers, _) = bake::bake_horizon(&map, &p, bake::Precisions::U8, &pr).unwrap();
        let [l0, l1] = layers.u8.as_ref().unwrap();
        let channel = |t: usize, c: usize| {
            let b = if c < 4 { l0[t * 4 + c] } else { l1[t * 4 + c - 4] };
            let v = b as f64 / 255.0;
            if encoding == "sqrt" {
                v * v
            } else {
                v
            }
        };
        let pos = az / 45.0;
        let (c, frac) = (pos.floor() as usize % 8, pos - pos.floor());
        let lz = el.to_radians().sin();
        let (mut lit, mut dark, mut ties) = (0, 0, 0);
        for t in 0..w * h {
            if holes[t] {
                assert_eq!(got[t], 255, "{encoding}: hole {t} is nodata");
                continue;
            }
            let s = (1.0 - frac) * channel(t, c) + frac * channel(t, (c + 1) % 8);
            if (lz - s).abs() < 1e-5 {
                ties += 1;
                continue;
            }
            let want = u8::from(lz > s);
            assert_eq!(got[t], want, "{encoding}: texel {t}, L_z {lz} vs s {s}");
            if want == 1 {
                lit += 1;
            } else {
                dark += 1;
            }
        }
        assert!(ties < 10, "{encoding}: {ties} texels within 1e-5 of the sun");
        assert!(lit > 100 && dark > 100, "{encoding}: {lit} lit, {dark} shadowed");
        // The exact ray at the same radius disagrees somewhere: the layers are 8 channels of a
        // bin maximum, not the horizon at the sun's azimuth.
        let ray = bake::shadow(&map, &with(&[("method", "exact")]), SunAzimuth::Grid(az), el, &pr)
            .unwrap();
        let differ = ray.iter().zip(&got).filter(|(a, b)| a != b).count();
        eprintln!("{encoding}: lengyel {lit} lit, {dark} shadowed; differs from the exact ray on {differ} texels");
        assert!(differ > 0, "{encoding}: the lengyel shadow equals the exact ray's");
    }
}

/// Issue 44 ("same tiling as angles"): a tile's window gives the whole map's horizon distance,
/// openness, sun hours, insolation and true-north compass bands, bit for bit, on a UTM DEM
/// 2.6° east of its central meridian (1.9° of convergence): true north and the sun's place are
/// the whole map's, whatever the window.
#[test]
fn a_window_gives_the_whole_map_s_ray_products() {
    use horizon_bake::heightmap::georef::CrsModel;
    let (w, h) = (70usize, 54usize);
    let mut rng = crate::support::Rng(44);
    let v: Vec<f32> = (0..w * h)
        .map(|i| {
            let (x, y) = ((i % w) as f32, (i / w) as f32);
            300.0 * ((x * 0.21).sin() * (y * 0.17).cos()) + 40.0 * rng.f32()
        })
        .collect();
    let mut map = horizon_bake::heightmap::HeightMap::from_values(w, h, v).unwrap();
    let g = Georef::from_gdal(
        [700_000.0, 100.0, 0.0, 5_200_000.0, 0.0, -100.0],
        Some(CrsModel::Projected),
        32632,
        9001,
        None,
    );
    map.terrain.georef = Some(g.clone());
    let q = "method=exact&radius=6&bins=8&azimuth_from=north_cw&date=2026-06-21\
             &time_step_minutes=60&outputs=angles,horizon_distance,openness,sun_hours,insolation";
    let mut p = params(&q.split('&').filter_map(|kv| kv.split_once('=')).collect::<Vec<_>>());
    apply_dem_defaults(&mut p, Some(&g)).unwrap();
    let pr = Progress::new();
    let (whole, radius) = bake::bake_terrain(&map, &p, &pr).unwrap();
    assert_eq!(radius.texels, 6);
    assert_eq!(whole.north.as_ref().unwrap().reference, "true");
    let heights = map.scaled(p.height_scale);
    let range = Grid::new(w, h, &heights, p.edge, p.y_axis).range();
    let r = 6 + 1;
    for (x0, y0, iw, ih) in [(0usize, 0usize, 24usize, 20usize), (24, 20, 24, 20), (48, 40, 22, 14)]
    {
        let (wx, wy) = (x0.saturating_sub(r), y0.saturating_sub(r));
        let (wx1, wy1) = ((x0 + iw + r).min(w), (y0 + ih + r).min(h));
        let (ww, wh) = (wx1 - wx, wy1 - wy);
        let vals: Vec<f32> =
            (wy..wy1).flat_map(|y| map.values[y * w + wx..y * w + wx1].to_vec()).collect();
        let mut win = horizon_bake::heightmap::HeightMap::from_values(ww, wh, vals).unwrap();
        win.terrain.georef = Some(g.clone());
        let place = bake::WindowPlace { origin: (wx, wy), map: (w, h) };
        let t = bake::bake_terrain_window(
            win,
            &p,
            (x0 - wx, y0 - wy, iw, ih),
            Some(place),
            range,
            6,
            &pr,
        )
        .unwrap();
        let crop = |v: &[f32], planes: usize| -> Vec<f32> {
            (0..planes)
                .flat_map(|k| {
                    (y0..y0 + ih).flat_map(move |y| {
                        let at = k * w * h + y * w + x0;
                        v[at..at + iw].to_vec()
                    })
                })
                .collect()
        };
        let same = |a: &[f32], b: &[f32]| a.iter().zip(b).all(|(x, y)| x.to_bits() == y.to_bits());
        let nb = 8;
        assert!(same(t.angles.as_ref().unwrap(), &crop(whole.angles.as_ref().unwrap(), nb)));
        assert!(same(t.distance.as_ref().unwrap(), &crop(whole.distance.as_ref().unwrap(), nb)));
        let (o, wo) = (t.openness.as_ref().unwrap(), whole.openness.as_ref().unwrap());
        assert!(same(&o[0], &crop(&wo[0], 1)) && same(&o[1], &crop(&wo[1], 1)));
        assert!(same(t.sun_hours.as_ref().unwrap(), &crop(whole.sun_hours.as_ref().unwrap(), 1)));
        assert!(same(t.insolation.as_ref().unwrap(), &crop(whole.insolation.as_ref().unwrap(), 1)));
    }
    // Compass bands are true azimuths: not the grid's bins renumbered.
    let mut grid_p = p.clone();
    grid_p.azimuth_from = horizon_bake::params::AzimuthFrom::EastCcw;
    grid_p.outputs =
        horizon_bake::params::Outputs { angles: true, ..horizon_bake::params::Outputs::NONE };
    let (g_ang, _) = bake::bake_terrain(&map, &grid_p, &pr).unwrap();
    let (a, b) = (whole.angles.unwrap(), g_ang.angles.unwrap());
    let north_band = &a[..w * h];
    let grid_north = &b[2 * w * h..3 * w * h]; // east_ccw bin 2 = 90°: grid north
    assert!(north_band.iter().zip(grid_north).any(|(x, y)| (x - y).abs() > 1e-3));
}

/// `sweep`'s `angles` and plain SVF come from its planes, azimuth by azimuth with no far-field
/// table (`Sweep::planes`): the products equal, bit for bit, those folded from the table's
/// per-bin bands as before (every band's angle, the SVF's sum in the bins' order), on a rough
/// map with holes (nodata in both), both plain SVF models, compass and grid bands, degrees and
/// sines, finite and unlimited radii; and `tilted` still reads the bands.
#[test]
fn sweep_products_from_planes_are_those_of_the_bands() {
    use horizon_bake::terrain::{angles, svf};
    let (w, h) = (53usize, 47usize);
    let mut rnd = lcg(0x9A7Eu64);
    let v: Vec<f32> = (0..w * h)
        .map(|k| {
            let (x, y) = ((k % w) as f32, (k / w) as f32);
            if rnd() < 0.03 {
                -9999.0
            } else {
                9.0 * (x * 0.21).sin() * (y * 0.17).cos() + 4.0 * rnd()
            }
        })
        .collect();
    let map = dem_of(w, h, &v);
    let holes = map.terrain.holes.clone().unwrap();
    let pr = Progress::new();
    let cases = [
        ("unlimited", "radiative", "east_ccw", "degrees", "32", "none"),
        ("24", "visual", "north_cw", "sin", "48", "wrap"),
        ("unlimited", "radiative", "north_cw", "radians", "360", "none"),
    ];
    for (radius, model, from, unit, bins, edge) in cases {
        let p = params(&[
            ("method", "sweep"),
            ("radius", radius),
            ("height_scale", "1"),
            ("outputs", "angles,svf"),
            ("svf_model", model),
            ("azimuth_from", from),
            ("angle_unit", unit),
            ("bins", bins),
            ("edge", edge),
            ("reduce", "point"),
        ]);
        let (t, r) = bake::bake_terrain(&map, &p, &pr).unwrap();
        let heights = map.scaled(p.height_scale);
        let g = Grid::new(w, h, &heights, p.edge, p.y_axis);
        let k = bake::make_kernel_for(&p, g, r.texels, &pr, Some(&holes));
        let nb = k.bins();
        let mut per_bin = vec![0.0f32; w * h * nb];
        let mut ch = vec![0.0f32; w * 8];
        for y in 0..h {
            k.rows(y, &mut ch, Some(&mut per_bin[y * w * nb..(y + 1) * w * nb]));
        }
        let order = angles::band_bins(nb, p.azimuth_from, p.y_axis);
        let (got_a, got_s) = (t.angles.unwrap(), t.svf.unwrap());
        let nodata = t.nodata;
        assert!(nodata.is_finite());
        let lit = per_bin.iter().filter(|&&s| s > 0.05).count();
        assert!(lit > per_bin.len() / 5, "{radius} {bins}: the map casts horizons: {lit}");
        for tx in 0..w * h {
            let s = &per_bin[tx * nb..][..nb];
            let want_s = if holes[tx] { nodata } else { svf::svf(s, p.svf_model) };
            let ctx = format!("{radius} {model} {from} {unit} {bins} {edge}: texel {tx}");
            assert_eq!(got_s[tx].to_bits(), want_s.to_bits(), "{ctx}: svf");
            for (band, &bin) in order.iter().enumerate() {
                let want = if holes[tx] { nodata } else { angles::angle(s[bin], p.angle_unit) };
                assert_eq!(got_a[band * w * h + tx].to_bits(), want.to_bits(), "{ctx} band {band}");
            }
        }
    }
    // A tilted SVF takes every bin of a texel with its normal: the table's bands, as before.
    let tilted = params(&[("method", "sweep"), ("outputs", "svf"), ("svf_model", "tilted")]);
    assert!(bake::needs_table(&tilted));
    let plain = params(&[("method", "sweep"), ("outputs", "angles,svf,openness")]);
    assert!(!bake::needs_table(&plain));
    let layers = params(&[("method", "sweep"), ("outputs", "horizon,svf")]);
    assert!(bake::needs_table(&layers));
}

/// Issue 41: 360 azimuths of a sky-view factor on a map whose table (700² × 360 × 4 bytes =
/// 673 MiB) would have gone to a temporary file now bake with no file at all: the CLI
/// succeeds with a `TMPDIR` where no file can be made, and its `svf.tif` (read back by the
/// `tiff` crate) holds the library's values bit for bit, nodata at the holes. A tilted SVF,
/// which still reads the table's bands, fails there naming the far field on disk: the check
/// is the one the table would meet.
#[test]
fn svf_at_360_azimuths_needs_no_temporary_file() {
    let (w, h) = (700usize, 700usize);
    let v: Vec<f32> = (0..w * h)
        .map(|k| {
            let (x, y) = ((k % w) as f32, (k / w) as f32);
            if (x - 300.0).powi(2) + (y - 420.0).powi(2) < 400.0 {
                -9999.0
            } else {
                40.0 * (x * 0.013).sin() * (y * 0.011).cos() + 6.0 * (x * 0.07 + y * 0.05).sin()
            }
        })
        .collect();
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("dem.tif");
    std::fs::write(&input, tiff_f32(w as u32, h as u32, &v)).unwrap();
    let blocker = dir.path().join("not-a-dir");
    std::fs::write(&blocker, b"x").unwrap();
    let bake = |model: &str, out: &std::path::Path| {
        std::process::Command::new(env!("CARGO_BIN_EXE_horizon-bake"))
            .env("TMPDIR", blocker.join("tmp"))
            .args(["bake", input.to_str().unwrap(), "-o", out.to_str().unwrap()])
            .args(["--method", "sweep", "--radius", "unlimited", "--edge", "none"])
            .args(["--height-scale", "1", "--bins", "360", "--outputs", "svf"])
            .args(["--svf-model", model, "--nodata", "-9999", "--format", "geotiff"])
            .output()
            .unwrap()
    };
    assert!(horizon_bake::kernels::sweep::spills(w as u32, h as u32, 360));
    let out = dir.path().join("plain");
    let run = bake("radiative", &out);
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    let file = std::fs::File::open(out.join("svf.tif")).unwrap();
    let mut dec = tiff::decoder::Decoder::new(std::io::BufReader::new(file)).unwrap();
    let tiff::decoder::DecodingResult::F32(got) = dec.read_image().unwrap() else {
        panic!("svf.tif is not float32");
    };
    let map = dem_of(w, h, &v);
    let p = params(&[
        ("method", "sweep"),
        ("radius", "unlimited"),
        ("edge", "none"),
        ("height_scale", "1"),
        ("bins", "360"),
        ("outputs", "svf"),
    ]);
    let (t, _) = bake::bake_terrain(&map, &p, &Progress::new()).unwrap();
    let want = t.svf.unwrap();
    assert_eq!(got.len(), want.len());
    let holes = map.terrain.holes.clone().unwrap();
    assert!(holes.iter().filter(|&&o| o).count() > 1000);
    for (k, (a, b)) in got.iter().zip(&want).enumerate() {
        if holes[k] {
            assert_eq!(*a, -9999.0, "texel {k}: nodata");
        } else {
            assert_eq!(a.to_bits(), b.to_bits(), "texel {k}");
        }
    }
    let shaded = want.iter().zip(&holes).filter(|(&s, &o)| !o && s < 0.97).count();
    assert!(shaded > w * h / 10, "the map hides some sky: {shaded}");
    let tilted = bake("tilted", &dir.path().join("tilted"));
    let err = String::from_utf8_lossy(&tilted.stderr);
    assert!(!tilted.status.success() && err.contains("far field on disk"), "{err}");
}

/// A terrain bake handed the map's values scaled in place (`take_scaled`, what the pipeline
/// does when the terrain products are the only outputs) gives the bits of the bake that scales
/// a copy, for `sweep`'s planes and `exact`'s rows, with holes; and a bake that would read the
/// taken values (the sun products' heights in metres) is refused rather than run on nothing.
#[test]
fn a_bake_of_taken_values_gives_the_bits_of_a_copy() {
    for method in ["sweep", "exact"] {
        let p = params(&[
            ("method", method),
            ("radius", "unlimited"),
            ("edge", "none"),
            ("height_scale", "1"),
            ("outputs", "angles,svf"),
            ("bins", "16"),
        ]);
        let map = towered(true);
        let (want, _) = bake::bake_terrain(&map, &p, &Progress::new()).unwrap();
        let mut taken = map.clone();
        let heights = taken.take_scaled(p.height_scale);
        assert_eq!(heights, map.scaled(p.height_scale));
        assert!(taken.values.is_empty());
        let (got, _) = bake::bake_terrain_from(&taken, heights, &p, &Progress::new()).unwrap();
        let bits = |v: &Option<Vec<f32>>| {
            v.as_ref().unwrap().iter().map(|x| x.to_bits()).collect::<Vec<_>>()
        };
        assert_eq!(bits(&got.angles), bits(&want.angles), "{method} angles");
        assert_eq!(bits(&got.svf), bits(&want.svf), "{method} svf");
    }
    let p = params(&[
        ("method", "exact"),
        ("height_scale", "1"),
        ("outputs", "sun_hours"),
        ("date", "2026-06-21"),
        ("latitude", "46"),
        ("longitude", "7"),
    ]);
    let mut taken = towered(false);
    let heights = taken.take_scaled(p.height_scale);
    let e = bake::bake_terrain_from(&taken, heights, &p, &Progress::new()).unwrap_err();
    assert!(matches!(e, horizon_bake::Error::Internal(_)), "{e:?}");
}
