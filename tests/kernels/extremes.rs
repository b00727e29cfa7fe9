//! Numerical extremes: every bake path must give finite values in range, and the documented
//! properties must still hold, at the edges of what the parameters and inputs allow.
//!
//! Both methods go through `bake::make_kernel` (the production path, whichever kernel it picks),
//! so a fast kernel that overflows where the plain oracle does not shows up here. Each test
//! checks a property that fails loudly if a value is wrong, not only that nothing panicked.

use crate::support::Rng;
use horizon_bake::bake::{self, Precisions};
use horizon_bake::eval;
use horizon_bake::heightmap::{self, HeightMap, Limits};
use horizon_bake::kernels::{self, cubemap, Grid};
use horizon_bake::params::{BakeParams, Channel, Edge, Method, YAxis};
use horizon_bake::progress::Progress;
use std::f64::consts::PI;

const METHODS: [Method; 4] = [Method::Lengyel, Method::Exact, Method::March, Method::Sweep];

fn params(method: Method, radius: &str, edge: Edge) -> BakeParams {
    let mut p = BakeParams { method, edge, ..BakeParams::default() };
    p.set("radius", radius).unwrap();
    p
}

/// Channels (`H·W·8`) and per-bin values (`H·W·bins`) of a bake of `heights` (texel units).
fn run(p: &BakeParams, w: usize, h: usize, heights: &[f32]) -> (Vec<f32>, Vec<f32>) {
    let r = bake::resolve_radius(p, w, h, heights);
    let grid = Grid::new(w, h, heights, p.edge, p.y_axis);
    let k = bake::make_kernel(p, grid, r.texels, &Progress::new());
    let nb = k.bins();
    let mut ch = vec![f32::NAN; w * h * 8];
    let mut bins = vec![f32::NAN; w * h * nb];
    let band = kernels::band_rows(w, h);
    let ch_chunks: Vec<std::sync::Mutex<&mut [f32]>> =
        ch.chunks_mut(band * w * 8).map(std::sync::Mutex::new).collect();
    let bin_chunks: Vec<std::sync::Mutex<&mut [f32]>> =
        bins.chunks_mut(band * w * nb).map(std::sync::Mutex::new).collect();
    kernels::run_bands(k.as_ref(), band, true, &Progress::new(), |b, out| {
        ch_chunks[b].lock().unwrap().copy_from_slice(out.channels);
        bin_chunks[b].lock().unwrap().copy_from_slice(out.bins.unwrap());
    })
    .unwrap();
    drop((ch_chunks, bin_chunks));
    (ch, bins)
}

fn assert_in_range(what: &str, v: &[f32]) {
    for (k, &x) in v.iter().enumerate() {
        assert!(x.is_finite() && (0.0..=1.0).contains(&x), "{what}: value {k} is {x}");
    }
}

#[test]
fn flat_map_has_no_horizon() {
    for m in METHODS {
        for edge in [Edge::Wrap, Edge::None] {
            let h = vec![123.25f32; 9 * 7];
            let (ch, bins) = run(&params(m, "8", edge), 9, 7, &h);
            assert!(ch.iter().chain(&bins).all(|&v| v == 0.0), "{m:?} {edge:?}");
        }
    }
}

#[test]
fn one_texel_spike() {
    // A spike of height 6 at the centre of a 15×15 plane, edge=none. The texel 3 to its west
    // sees it due east (φ = 0, bin 0) at elevation atan(6/3) in both definitions: the splat
    // keeps tan = Δh/d for the bins the offset covers, the line of sight peaks at the spike's
    // centre. The spike itself has nothing above it.
    let (n, c, top) = (15usize, 7usize, 6.0f32);
    let mut h = vec![0.0f32; n * n];
    h[c * n + c] = top;
    let want = (6.0f64 / (36.0f64 + 9.0).sqrt()) as f32;
    for m in METHODS {
        let (ch, bins) = run(&params(m, "8", Edge::None), n, n, &h);
        assert_in_range("spike", &ch);
        let nb = bins.len() / (n * n);
        let west = c * n + c - 3;
        assert!((bins[west * nb] - want).abs() < 2e-3, "{m:?}: {} vs {want}", bins[west * nb]);
        // Nothing shadows the spike's own top, and the opposite direction of its neighbour
        // (due west, bin nb/2) sees only the flat plane.
        assert!(ch[(c * n + c) * 8..(c * n + c) * 8 + 8].iter().all(|&v| v == 0.0), "{m:?}");
        assert_eq!(bins[west * nb + nb / 2], 0.0, "{m:?}");
        // Far beyond the radius (edge=none, radius 8): the corner texel sees nothing.
        assert!(ch[..8].iter().all(|&v| v == 0.0), "{m:?}: {:?}", &ch[..8]);
    }
}

#[test]
fn checkerboard_of_extreme_heights() {
    // ±1e30 texels: differences of 2e30, squares of 4e60 (beyond f32) must not overflow into
    // NaN. High texels have nothing above them; low texels are walled in on all sides.
    let (w, h) = (8usize, 6usize);
    let big = 1e30f32;
    let heights: Vec<f32> =
        (0..w * h).map(|k| if (k % w + k / w) % 2 == 0 { big } else { -big }).collect();
    for m in METHODS {
        let (ch, bins) = run(&params(m, "4", Edge::Wrap), w, h, &heights);
        assert_in_range("checkerboard channels", &ch);
        assert_in_range("checkerboard bins", &bins);
        for t in 0..w * h {
            let c = &ch[t * 8..t * 8 + 8];
            if heights[t] > 0.0 {
                assert!(c.iter().all(|&v| v == 0.0), "{m:?} high texel {t}: {c:?}");
            } else {
                // Axis neighbours are high at 1 texel: s = 2e30/√(4e60 + 1) ≈ 1.
                for ax in [0, 2, 4, 6] {
                    assert!(c[ax] > 0.99, "{m:?} low texel {t} channel {ax}: {c:?}");
                }
            }
        }
    }
}

#[test]
fn huge_float_values_with_height_scale() {
    // A float map near f32::MAX: scaled by the default height_scale (8) it overflows f32. The
    // bake must either refuse it with a typed error or give finite values in range.
    let vals: Vec<f32> = (0..25).map(|k| if k % 3 == 0 { 3.0e38 } else { -3.0e38 }).collect();
    let map = HeightMap::from_values(5, 5, vals).unwrap();
    for m in METHODS {
        let p = params(m, "4", Edge::Wrap);
        match bake::bake_horizon(&map, &p, Precisions::ALL, &Progress::new()) {
            Ok((layers, _)) => {
                for l in layers.f32.as_ref().unwrap() {
                    assert_in_range("huge floats", l);
                }
            }
            Err(e) => assert!(
                matches!(
                    e,
                    horizon_bake::Error::InvalidInput(_) | horizon_bake::Error::Param { .. }
                ),
                "{m:?}: {e}"
            ),
        }
    }
}

#[test]
fn negative_float_heights_are_shift_invariant() {
    // Only height differences matter: a map shifted by −1e4 bakes like the original (the
    // shift is exact in f32 for these values).
    let mut rng = Rng(7);
    let (w, h) = (11usize, 9usize);
    let base: Vec<f32> = (0..w * h).map(|_| (rng.f32() * 64.0).round() / 8.0).collect();
    let shifted: Vec<f32> = base.iter().map(|v| v - 10_000.0).collect();
    for m in METHODS {
        let p = params(m, "6", Edge::Wrap);
        let (a, _) = run(&p, w, h, &base);
        let (b, _) = run(&p, w, h, &shifted);
        assert_in_range("negative heights", &b);
        // Both kernels work on height differences, the exact one relative to the middle of the
        // map's range: the shift costs nothing beyond f32 rounding of the inputs. (The exact
        // kernel used to interpolate absolute heights in f32 and lost ~1.1e-4 here.)
        let tol = 1e-6;
        for (k, (x, y)) in a.iter().zip(&b).enumerate() {
            assert!((x - y).abs() < tol, "{m:?} value {k}: {x} vs {y}");
        }
    }
}

#[test]
fn height_scale_extremes() {
    let mut rng = Rng(11);
    let (w, h) = (12usize, 10usize);
    let vals: Vec<f32> = (0..w * h).map(|_| rng.f32()).collect();
    let map = HeightMap::from_values(w, h, vals.clone()).unwrap();
    for m in METHODS {
        let mut lo = params(m, "6", Edge::Wrap);
        lo.set("height_scale", "1e-6").unwrap();
        let (layers, _) = bake::bake_horizon(&map, &lo, Precisions::ALL, &Progress::new()).unwrap();
        // Height differences of at most 1e-6 texels: the steepest slope on the bilinear surface
        // is √2·1e-6 (diagonally across a cell), so s ≤ 1.42e-6 everywhere, which stores as 0
        // in 8 and 16 bits.
        for l in layers.f32.as_ref().unwrap() {
            assert_in_range("height_scale 1e-6", l);
            let mx = l.iter().copied().fold(0.0f32, f32::max);
            assert!(mx <= 1.5e-6, "{m:?}: {mx}");
        }
        assert!(layers.u8.as_ref().unwrap().iter().all(|l| l.iter().all(|&v| v == 0)));
        assert!(layers.u16.as_ref().unwrap().iter().all(|l| l.iter().all(|&v| v == 0)));

        let mut hi = params(m, "6", Edge::Wrap);
        hi.set("height_scale", "1e6").unwrap();
        let (layers, _) = bake::bake_horizon(&map, &hi, Precisions::ALL, &Progress::new()).unwrap();
        let f = layers.f32.as_ref().unwrap();
        for l in f {
            assert_in_range("height_scale 1e6", l);
        }
        // Cliffs 1e6 texels high: every texel but the highest has a neighbour above it within
        // the radius, whose bins reach s ≈ 1; a channel averages 5 bins, so its largest
        // channel is at least ~1/5. And the horizon grows with height_scale, texel by texel.
        let top = vals.iter().copied().fold(f32::MIN, f32::max);
        let chans = bake::layers_to_channels(f);
        let unit = BakeParams { height_scale: 1.0, ..hi.clone() };
        let (l1, _) = bake::bake_horizon(&map, &unit, Precisions::ALL, &Progress::new()).unwrap();
        let c1 = bake::layers_to_channels(l1.f32.as_ref().unwrap());
        for (k, (a, b)) in c1.iter().zip(&chans).enumerate() {
            assert!(b + 1e-6 >= *a, "{m:?} value {k}: {b} at 1e6 below {a} at 1");
        }
        for t in 0..w * h {
            let mx = chans[t * 8..t * 8 + 8].iter().copied().fold(0.0f32, f32::max);
            if vals[t] < top {
                assert!(mx > 0.15, "{m:?} texel {t}: largest channel {mx}");
            } else {
                assert_eq!(mx, 0.0, "{m:?}: the highest texel is never shadowed");
            }
        }
    }
}

#[test]
fn degenerate_sizes() {
    let mut rng = Rng(3);
    for (w, h) in [(1usize, 1usize), (1, 9), (9, 1), (4099, 3)] {
        let heights: Vec<f32> = (0..w * h).map(|_| rng.f32() * 10.0).collect();
        for m in METHODS {
            for edge in [Edge::Wrap, Edge::None] {
                // A bounded radius keeps the 4099-wide map cheap for the plain oracles.
                let (ch, bins) = run(&params(m, "12", edge), w, h, &heights);
                assert_in_range(&format!("{w}×{h} {m:?} {edge:?}"), &ch);
                assert_in_range(&format!("{w}×{h} {m:?} {edge:?} bins"), &bins);
                if w * h == 1 {
                    assert!(ch.iter().all(|&v| v == 0.0), "1×1 sees only itself");
                }
                if h == 1 && edge == Edge::None {
                    // A single row with nothing outside: straight up-image (φ = 90°, channel
                    // 2) and down-image (channel 6) there is no terrain at all.
                    for t in 0..w {
                        assert_eq!(ch[t * 8 + 2], 0.0, "{w}×{h} {m:?} texel {t}");
                        assert_eq!(ch[t * 8 + 6], 0.0, "{w}×{h} {m:?} texel {t}");
                    }
                }
                if w == 1 && edge == Edge::None {
                    for t in 0..h {
                        assert_eq!(ch[t * 8], 0.0, "{w}×{h} {m:?} texel {t}");
                        assert_eq!(ch[t * 8 + 4], 0.0, "{w}×{h} {m:?} texel {t}");
                    }
                }
            }
        }
    }
}

#[test]
fn sixteen_bit_full_range() {
    // 0 and 65535 decode to exactly 0 and 1; a bake of the resulting step keeps values in range
    // and the low side of the step sees the wall at 1 texel.
    let (w, h) = (6u32, 4u32);
    let data: Vec<u16> = (0..w * h).map(|k| if k % w < 3 { 0 } else { 65535 }).collect();
    let be: Vec<u8> = data.iter().flat_map(|v| v.to_be_bytes()).collect();
    let mut png = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut png, w, h);
        enc.set_color(png::ColorType::Grayscale);
        enc.set_depth(png::BitDepth::Sixteen);
        enc.write_header().unwrap().write_image_data(&be).unwrap();
    }
    let (map, info) = heightmap::decode(&png, Channel::Luma, &Limits::default()).unwrap();
    assert_eq!(info.bit_depth, 16);
    assert_eq!(map.values.iter().copied().fold(f32::MAX, f32::min), 0.0);
    assert_eq!(map.values.iter().copied().fold(f32::MIN, f32::max), 1.0);
    for m in METHODS {
        let p = params(m, "4", Edge::Wrap);
        let (layers, _) = bake::bake_horizon(&map, &p, Precisions::ALL, &Progress::new()).unwrap();
        let f = layers.f32.as_ref().unwrap();
        let chans = bake::layers_to_channels(f);
        assert_in_range("16-bit", &chans);
        // Texel (2, 1) is low with the wall (height 8) one texel east: s = 8/√65 (the exact
        // kernel's ±22.5° bins see it at 8·cos φ / 1, within 0.001 of that).
        let s = chans[(6 + 2) * 8];
        assert!((s - (8.0 / 65f32.sqrt())).abs() < 0.02, "{m:?}: {s}");
    }
}

#[test]
fn mirrored_map_mirrors_channels() {
    // Mirroring the columns maps azimuth φ to π − φ: channel c to channel (4 − c) mod 8. This
    // holds only if occluders exactly on bin boundaries and channel azimuths are handled
    // symmetrically.
    let mut rng = Rng(21);
    let (w, h) = (13usize, 11usize);
    let a: Vec<f32> = (0..w * h).map(|_| (rng.f32() * 16.0).floor()).collect();
    let b: Vec<f32> = (0..w * h).map(|k| a[(k / w) * w + (w - 1 - k % w)]).collect();
    for m in METHODS {
        let p = params(m, "5", Edge::Wrap);
        let (ca, _) = run(&p, w, h, &a);
        let (cb, _) = run(&p, w, h, &b);
        for y in 0..h {
            for x in 0..w {
                for c in 0..8 {
                    let va = ca[(y * w + x) * 8 + c];
                    let vb = cb[(y * w + (w - 1 - x)) * 8 + (12 - c) % 8];
                    assert!((va - vb).abs() < 1e-4, "{m:?} ({x},{y}) ch {c}: {va} vs {vb}");
                }
            }
        }
    }
}

fn illumination(lz: f64, s: f64, k: f64) -> f64 {
    if lz <= 0.0 {
        0.0
    } else {
        (k * (lz - s) + 1.0).clamp(0.0, 1.0)
    }
}

#[test]
fn lights_at_the_extremes() {
    let mut rng = Rng(5);
    let ch: Vec<f64> = (0..8).map(|_| rng.f32() as f64).collect();
    let cases: Vec<[f64; 3]> = vec![
        [0.0, 0.0, 1.0],                            // zenith: azimuth undefined
        [1.0, 0.0, 1e-6],                           // grazing
        [0.3, -0.4, -0.5],                          // below the horizon
        [0.0, 0.0, -1.0],                           // nadir
        [(PI / 4.0).cos(), (PI / 4.0).sin(), 1e-6], // on channel 1's azimuth, grazing
    ];
    for d in cases {
        let f = cubemap::factors_for_direction(d).map(|v| v as f64);
        assert!(f.iter().all(|v| v.is_finite()), "{d:?}: {f:?}");
        let sum: f64 = f.iter().map(|v| v.abs()).sum();
        assert!((sum - 1.0).abs() < 1e-6, "{d:?}: Σ|f| = {sum}");
        let s = eval::blend(&f, &ch);
        let (lo, hi) = ch.iter().fold((1.0f64, 0.0f64), |(l, h), &v| (l.min(v), h.max(v)));
        assert!(s >= lo - 1e-9 && s <= hi + 1e-9, "{d:?}: s {s} outside the channels' range");
        let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        let lz = d[2] / n;
        let big_f = illumination(lz, s, 8.0);
        assert!((0.0..=1.0).contains(&big_f));
        if lz <= 0.0 {
            assert_eq!(big_f, 0.0, "{d:?}: a light below the tangent plane gives F = 0");
        }
        if lz == 1.0 {
            // At the zenith nothing can shadow: s ≤ 1 = L_z.
            assert_eq!(big_f, 1.0);
        }
    }
}

#[test]
fn decoding_is_continuous_at_channel_azimuths_and_bin_boundaries() {
    // The blend must not jump where the bracketing channels change (every 45°, including the
    // layer switch at 180° and the wrap at 360°) nor at the kernels' bin boundaries.
    let mut rng = Rng(9);
    for _ in 0..50 {
        let ch: Vec<f64> = (0..8).map(|_| rng.f32() as f64).collect();
        let mut azimuths: Vec<f64> = (0..=8).map(|c| c as f64 * PI / 4.0).collect();
        azimuths.extend((0..64).map(|n| (n as f64 + 0.5) * 2.0 * PI / 64.0));
        for phi in azimuths {
            let s = |p: f64| eval::blend(&cubemap::factors_for_azimuth(p).map(|v| v as f64), &ch);
            let (a, b, c) = (s(phi - 1e-9), s(phi), s(phi + 1e-9));
            assert!((a - b).abs() < 1e-6 && (b - c).abs() < 1e-6, "φ {phi}: {a} {b} {c}");
        }
        for c in 0..8 {
            let s = eval::blend(
                &cubemap::factors_for_azimuth(c as f64 * PI / 4.0).map(|v| v as f64),
                &ch,
            );
            assert!((s - ch[c]).abs() < 1e-6, "on channel {c}: {s} vs {}", ch[c]);
        }
    }
}

#[test]
fn cube_map_edges_corners_and_poles() {
    let mut dirs: Vec<[f64; 3]> = vec![[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]];
    for sx in [-1.0, 1.0] {
        for sy in [-1.0, 1.0] {
            for sz in [-1.0, 1.0] {
                dirs.push([sx, sy, sz]); // corners
            }
            dirs.push([sx, sy, 0.0]); // edges between side faces
            dirs.push([sx, 0.0, sy]); // edges with the poles' faces
            dirs.push([0.0, sx, sy]);
        }
    }
    for d in dirs {
        let (face, s, t) = cubemap::select_face(d);
        assert!(face < 6 && (0.0..=1.0).contains(&s) && (0.0..=1.0).contains(&t), "{d:?}");
        let f = cubemap::factors_for_direction(d);
        let sum: f32 = f.iter().map(|v| v.abs()).sum();
        assert!((sum - 1.0).abs() < 1e-6, "{d:?}: {f:?}");
    }
    for size in [1usize, 2, 3, 4, 32] {
        let cube = cubemap::cube_factors(size);
        assert_eq!(cube.len(), 6 * size * size * 4);
        for (k, t) in cube.chunks_exact(4).enumerate() {
            let sum: f32 = t.iter().map(|v| v.abs()).sum();
            assert!(t.iter().all(|v| v.is_finite()) && (sum - 1.0).abs() < 1e-5, "{size} {k}");
        }
        // The texel centres of the +Z face's corners look along the diagonals (+Z: x = sc,
        // y = −tc): their factors put all the weight on the diagonal channels 1, 3, 5, 7.
        let face = 4;
        for (u, v, ch) in
            [(0, 0, 3usize), (size - 1, 0, 1), (0, size - 1, 5), (size - 1, size - 1, 7)]
        {
            if size < 2 {
                break;
            }
            let t = &cube[((face * size + v) * size + u) * 4..][..4];
            let want = if ch >= 4 { -1.0 } else { 1.0 };
            assert!((t[ch % 4] - want).abs() < 1e-5, "size {size} ({u},{v}) → {t:?}");
        }
    }
}

#[test]
fn y_axis_down_reads_the_flipped_image_identically() {
    // The vertically flipped image read with y_axis=down is the same surface in the same
    // tangent frame: every texel keeps its eight channels.
    let mut rng = Rng(33);
    let (w, h) = (9usize, 7usize);
    let a: Vec<f32> = (0..w * h).map(|_| (rng.f32() * 12.0).floor()).collect();
    let flipped: Vec<f32> = (0..w * h).map(|k| a[(h - 1 - k / w) * w + k % w]).collect();
    for m in METHODS {
        let up = params(m, "4", Edge::Wrap);
        let down = BakeParams { y_axis: YAxis::Down, ..up.clone() };
        let (ca, _) = run(&up, w, h, &a);
        let (cb, _) = run(&down, w, h, &flipped);
        for y in 0..h {
            for x in 0..w {
                for c in 0..8 {
                    let va = ca[(y * w + x) * 8 + c];
                    let vb = cb[((h - 1 - y) * w + x) * 8 + c];
                    assert!((va - vb).abs() < 1e-4, "{m:?} ({x},{y}) ch {c}: {va} vs {vb}");
                }
            }
        }
    }
}

#[test]
fn fourier_at_the_extremes() {
    // Flat and 1×1 maps have no horizon: C_0 stores as the encoded zero (128 in the standard
    // range, ½ + ½·√0) and every band as the encoded zero too. On the ±1e30 checkerboard the low
    // texels are walled in (s ≈ 1 at every azimuth, C_0 = 1, stored 255) and the high ones see
    // nothing (128): a NaN anywhere in the projection would quantise to 0 and show up.
    let cases: Vec<(usize, usize, Vec<f32>)> = vec![
        (7, 5, vec![2.5; 35]),
        (1, 1, vec![0.7]),
        (8, 6, (0..48).map(|k| if (k % 8 + k / 8) % 2 == 0 { 1e30 } else { -1e30 }).collect()),
    ];
    for m in METHODS {
        for terms in ["3", "5", "9"] {
            for (w, h, vals) in &cases {
                let map = HeightMap::from_values(*w, *h, vals.clone()).unwrap();
                let mut p = params(m, "4", Edge::Wrap);
                p.set("height_scale", "1").unwrap();
                p.set("fourier_terms", terms).unwrap();
                let (f, _) = bake::bake_fourier(&map, &p, &Progress::new()).unwrap();
                for t in 0..w * h {
                    let low = vals[t] < vals.iter().copied().fold(f32::MIN, f32::max);
                    let want = if low { 255 } else { 128 };
                    assert_eq!(f.constant[t], want, "{m:?} {terms} {w}×{h} texel {t}");
                    if !low {
                        assert!(f.bands[t * 4..t * 4 + 4].iter().all(|&b| b == 128), "{m:?}");
                    }
                }
            }
        }
    }
}
