//! The acceptance test of the conventions: every case of tests/golden/cases.json.
//!
//! f32 values within the file's `f32_abs`; 8-bit layers within `png_lsb` on at most
//! `png_lsb_fraction` of the bytes. Both the plain oracle and the production bake path are
//! checked, so a convention slip in either shows up here.

use crate::support;
use horizon_bake::bake::{self, layers_to_channels, Precisions};
use horizon_bake::heightmap::{self, Limits};
use horizon_bake::kernels::{compute_all, cubemap, lengyel::LengyelNaive, Grid};
use horizon_bake::params::BakeParams;
use horizon_bake::progress::Progress;
use serde_json::Value;

fn cases() -> Value {
    let dir = support::golden_dir();
    serde_json::from_slice(&std::fs::read(dir.join("cases.json")).unwrap()).unwrap()
}

fn params_of(case: &Value) -> BakeParams {
    let mut p = BakeParams::default();
    for key in ["height_scale", "radius", "edge", "y_axis", "channel", "method", "bins"] {
        let v = &case[key];
        let text = v.as_str().map(str::to_owned).unwrap_or_else(|| v.to_string());
        p.set(key, &text).unwrap();
    }
    p
}

fn png_layer(path: &std::path::Path) -> Vec<u8> {
    image::open(path).unwrap().to_rgba8().into_raw()
}

fn assert_png_close(name: &str, got: &[u8], want: &[u8], tol: &Value) {
    assert_eq!(got.len(), want.len(), "{name}: size");
    let lsb = tol["png_lsb"].as_i64().unwrap() as i32;
    let frac = tol["png_lsb_fraction"].as_f64().unwrap();
    let mut off = 0usize;
    for (k, (&g, &w)) in got.iter().zip(want).enumerate() {
        let d = (g as i32 - w as i32).abs();
        assert!(d <= lsb, "{name}: byte {k} is {g}, expected {w}");
        off += (d > 0) as usize;
    }
    assert!(
        off as f64 <= frac * got.len() as f64,
        "{name}: {off} of {} bytes off by one LSB",
        got.len()
    );
}

#[test]
fn horizon_cases_match_golden() {
    let all = cases();
    let dir = support::golden_dir();
    let tol = &all["tolerance"];
    let f32_abs = tol["f32_abs"].as_f64().unwrap() as f32;
    let cases = all["horizon_cases"].as_array().unwrap();
    assert!(cases.len() >= 6);
    for case in cases {
        let name = case["name"].as_str().unwrap();
        let params = params_of(case);
        let bytes =
            std::fs::read(dir.join("inputs").join(case["input"].as_str().unwrap())).unwrap();
        let (map, info) = heightmap::decode(&bytes, params.channel, &Limits::default()).unwrap();
        assert_eq!(info.width as u64, case["width"].as_u64().unwrap(), "{name}");
        assert_eq!(info.height as u64, case["height"].as_u64().unwrap(), "{name}");
        let want = support::read_f32(&dir.join(case["expected_f32"].as_str().unwrap()));

        // The oracle, directly.
        let heights = map.scaled(params.height_scale);
        let grid = Grid::new(map.width, map.height, &heights, params.edge, params.y_axis);
        let r = match params.radius {
            horizon_bake::params::Radius::Texels(r) => r,
            _ => unreachable!(),
        };
        let got = compute_all(&LengyelNaive::new(grid, r, params.bins), &Progress::new()).unwrap();
        assert_eq!(got.len(), want.len(), "{name}");
        let worst = got.iter().zip(&want).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
        assert!(worst <= f32_abs, "{name}: oracle max |error| {worst}");

        // The production path, f32 and 8-bit.
        let (layers, _) = bake::bake_horizon(
            &map,
            &params,
            Precisions { u8: true, u16: false, f32: true },
            &Progress::new(),
        )
        .unwrap();
        let chans = layers_to_channels(layers.f32.as_ref().unwrap());
        let worst = chans.iter().zip(&want).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
        assert!(worst <= f32_abs, "{name}: bake max |error| {worst}");
        let u8s = layers.u8.as_ref().unwrap();
        for (l, file) in case["expected_layers"].as_array().unwrap().iter().enumerate() {
            let want = png_layer(&dir.join(file.as_str().unwrap()));
            assert_png_close(&format!("{name} layer {l}"), &u8s[l], &want, tol);
        }
    }
}

#[test]
fn cube_cases_match_golden() {
    let all = cases();
    let dir = support::golden_dir();
    let tol = &all["tolerance"];
    let f32_abs = tol["f32_abs"].as_f64().unwrap() as f32;
    for case in all["cube_cases"].as_array().unwrap() {
        let size = case["size"].as_u64().unwrap() as usize;
        let got = cubemap::cube_factors(size);
        let want = support::read_f32(&dir.join(case["expected_f32"].as_str().unwrap()));
        assert_eq!(got.len(), want.len());
        for (k, (a, b)) in got.iter().zip(&want).enumerate() {
            assert!((a - b).abs() <= f32_abs, "cube texel value {k}: {a} vs {b}");
        }
        for (face, file) in case["expected_faces"].as_array().unwrap().iter().enumerate() {
            let want = png_layer(&dir.join(file.as_str().unwrap()));
            let n = size * size * 4;
            let ours: Vec<u8> =
                got[face * n..(face + 1) * n].iter().map(|&f| cubemap::unorm8(f)).collect();
            assert_png_close(&format!("cube face {face}"), &ours, &want, tol);
        }
    }
}
