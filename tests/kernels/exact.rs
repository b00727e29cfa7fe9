//! `method=exact` (SPEC §3.2) against an independent brute-force march and closed-form cases.
//!
//! # Tolerance
//! The kernels analyse each cell of a ray in closed form, so they are exact up to f64 rounding
//! and the f32 they store. The brute-force oracle below samples the bilinear surface every
//! 1/128 texel along the ray, at every grid-line crossing (where the ratio has kinks), at R and
//! at s = 1e-7, 1e-5, 1e-3 (the supremum may be the limit s → 0⁺, the slope at the texel), so it
//! approaches the definition from below with an error of order h''·δ²/8 ≈ 1e-4 in tan α on the
//! spikiest maps here. Stated and asserted, per bin:
//! - never below the oracle: sin α_kernel ≥ sin α_march − 1e-5 (the supremum is at least any
//!   sample of it; 1e-5 covers the f32 arithmetic of the vectorised near field);
//! - |α_kernel − α_march| ≤ 0.01° (≈ 0.044 LSB of an 8-bit output near the horizon, where
//!   1 LSB = 1/255 in sin α ≈ 0.225°);
//! - 8-bit outputs (floor(s·255 + 0.5)) differ by at most 1 LSB, and on at most 0.5 % of values
//!   (only where s sits within 0.044 LSB of a rounding boundary).
//!
//! The near field is included: every ray starts at the texel centre, and the random maps have
//! radii 1 and 2 as well as larger and unlimited ones.

use crate::support::{surface, waves, Rng};
use horizon_bake::bake::{self, Precisions};
use horizon_bake::heightmap::HeightMap;
use horizon_bake::kernels::exact::{direction, horizon_sin, ExactHorizon, ExactMarch};
use horizon_bake::kernels::HorizonRows;
use horizon_bake::kernels::{compute_all, reduce_average, reduce_point, run_bands, Grid};
use horizon_bake::params::{BakeParams, Edge, Reduce, YAxis};
use horizon_bake::progress::{Progress, Stage};
use horizon_bake::Error;
use std::f64::consts::PI;

const TOL_DEG: f64 = 0.01;
const STEP: f64 = 1.0 / 128.0;

/// Brute force: sin α of texel (x, y) at azimuth phi, sampling every STEP and every grid-line
/// crossing up to R (`None`: max(W, H) when wrapping, the map edge with edge=none).
fn march(g: &Grid<'_>, x: usize, y: usize, phi: f64, radius: Option<f64>) -> f64 {
    march_curved(g, x, y, phi, radius, 0.0)
}

/// [`march`] with the earth-curvature drop: a point at arc length s lowered by `curv`·s².
fn march_curved(g: &Grid<'_>, x: usize, y: usize, phi: f64, radius: Option<f64>, curv: f64) -> f64 {
    let (dx, dy) = direction(phi, g.row_step());
    let (x0, y0) = (x as f64, y as f64);
    let h0 = g.heights[y * g.width + x] as f64;
    let r = match (radius, g.edge) {
        (Some(r), _) => r,
        (None, Edge::Wrap) => g.width.max(g.height) as f64,
        (None, Edge::None) => f64::INFINITY,
    };
    let inside = |s: f64| {
        let (px, py) = (x0 + s * dx, y0 + s * dy);
        g.edge == Edge::Wrap
            || (px >= -1e-9
                && py >= -1e-9
                && px <= (g.width - 1) as f64 + 1e-9
                && py <= (g.height - 1) as f64 + 1e-9)
    };
    let mut best = 0.0f64;
    let mut eval = |s: f64| {
        if s > 0.0 && s <= r && inside(s) {
            let t = (surface(g, x0 + s * dx, y0 + s * dy) - curv * s * s - h0) / s;
            best = best.max(t);
        }
    };
    let far = r.min(2.0 * (g.width + g.height) as f64);
    // The supremum can be the limit s → 0⁺ (the directional slope): sample close to it.
    for s in [1e-7, 1e-5, 1e-3] {
        eval(s);
    }
    let mut k = 1;
    while k as f64 * STEP <= far {
        eval(k as f64 * STEP);
        k += 1;
    }
    eval(far);
    for d in [dx, dy] {
        if d != 0.0 {
            let mut i = 1;
            while i as f64 / d.abs() <= far {
                eval(i as f64 / d.abs());
                i += 1;
            }
        }
    }
    best / (1.0 + best * best).sqrt()
}

fn q8(s: f64) -> i32 {
    (s * 255.0 + 0.5).floor() as i32
}

fn random_map(rng: &mut Rng, w: usize, h: usize, spiky: bool) -> Vec<f32> {
    if spiky {
        let scale = 1.0 + 15.0 * rng.f32();
        (0..w * h).map(|_| rng.f32() * scale).collect()
    } else {
        waves(rng, w, h, 2, 3.0)
    }
}

struct Stats {
    values: usize,
    byte_off: usize,
    worst_deg: f64,
}

/// Checks every bin of every texel of `kernel` (per-bin output) against the brute force.
fn check_against_march<K: HorizonRows>(
    name: &str,
    g: &Grid<'_>,
    kernel: &K,
    radius: Option<f64>,
    stats: &mut Stats,
) {
    let (w, h, b) = (g.width, g.height, kernel.bins());
    let mut ch = vec![0.0f32; w * 8];
    let mut bins = vec![0.0f32; w * b];
    for y in 0..h {
        kernel.rows(y, &mut ch, Some(&mut bins));
        for x in 0..w {
            for n in 0..b {
                let phi = n as f64 * 2.0 * PI / b as f64;
                let want = march(g, x, y, phi, radius);
                let got = bins[x * b + n] as f64;
                assert!(
                    got >= want - 1e-5,
                    "{name}: texel ({x},{y}) bin {n}: {got} below the march {want}"
                );
                let d = (got.asin() - want.asin()).abs().to_degrees();
                assert!(d <= TOL_DEG, "{name}: texel ({x},{y}) bin {n}: {got} vs {want} ({d}°)");
                let lsb = (q8(got) - q8(want)).abs();
                assert!(lsb <= 1, "{name}: texel ({x},{y}) bin {n}: {lsb} LSB");
                stats.byte_off += (lsb > 0) as usize;
                stats.values += 1;
                stats.worst_deg = stats.worst_deg.max(d);
            }
        }
    }
}

#[test]
fn kernels_match_brute_force_march_on_random_maps() {
    let mut rng = Rng(0x5eed_e4ac);
    let sizes = [(1, 1), (1, 6), (7, 1), (2, 2), (5, 4), (9, 7), (12, 11)];
    let mut stats = Stats { values: 0, byte_off: 0, worst_deg: 0.0 };
    for &(w, h) in &sizes {
        for edge in [Edge::Wrap, Edge::None] {
            for y_axis in [YAxis::Up, YAxis::Down] {
                for radius in [Some(1u32), Some(2), Some(5), None] {
                    for spiky in [false, true] {
                        let heights = random_map(&mut rng, w, h, spiky);
                        let g = Grid::new(w, h, &heights, edge, y_axis);
                        let name =
                            format!("{w}x{h} {edge:?} {y_axis:?} R={radius:?} spiky={spiky}");
                        let rf = radius.map(f64::from);
                        let fast = ExactHorizon::new(g, radius, 32, Reduce::Average);
                        check_against_march(&format!("fast {name}"), &g, &fast, rf, &mut stats);
                        if w * h <= 30 {
                            let plain = ExactMarch::new(g, radius, 32, Reduce::Average);
                            check_against_march(
                                &format!("plain {name}"),
                                &g,
                                &plain,
                                rf,
                                &mut stats,
                            );
                        }
                    }
                }
            }
        }
    }
    assert!(stats.values > 100_000, "{} values", stats.values);
    assert!(
        stats.byte_off as f64 <= 0.005 * stats.values as f64,
        "{} of {} bytes off by one",
        stats.byte_off,
        stats.values
    );
    eprintln!(
        "exact vs march: {} values, worst {:.5}°, {} bytes 1 LSB off",
        stats.values, stats.worst_deg, stats.byte_off
    );
}

#[test]
fn fast_kernel_equals_plain_oracle_on_larger_maps() {
    let mut rng = Rng(42);
    for (w, h, edge, radius) in [
        (37, 29, Edge::Wrap, None),
        (40, 33, Edge::None, None),
        (31, 31, Edge::Wrap, Some(9)),
        (25, 44, Edge::None, Some(20)),
        (64, 3, Edge::Wrap, None),
        // Rays longer than the vectorised near field (1024 texels) continue with the scalar walk.
        (1100, 2, Edge::Wrap, None),
        (1040, 2, Edge::None, None),
        (1030, 2, Edge::Wrap, Some(1029)),
        (300, 4, Edge::Wrap, None),
        (70, 9, Edge::Wrap, Some(100)),
        (60, 50, Edge::None, None),
        (53, 7, Edge::None, Some(60)),
    ] {
        for spiky in [false, true] {
            let heights = random_map(&mut rng, w, h, spiky);
            let g = Grid::new(w, h, &heights, edge, YAxis::Up);
            let fast = ExactHorizon::new(g, radius, 32, Reduce::Point);
            let plain = ExactMarch::new(g, radius, 32, Reduce::Point);
            // `rows` is the production path: the f32 near field over strips of texels and the
            // seeded far-field walk; culling and skipping must not change the result.
            let (mut ch, mut fast_bins, mut b) =
                (vec![0f32; w * 8], vec![0f32; w * 32], vec![0f32; 32]);
            // On the maps past the near field the plain march is slow (rays of ~1400 cells):
            // every 5th texel of their rows, plus the last, is enough to cross strip borders.
            let step = if w > 512 { 5 } else { 1 };
            for y in 0..h {
                fast.rows(y, &mut ch, Some(&mut fast_bins));
                for x in (0..w).step_by(step).chain([w - 1]) {
                    let a = &fast_bins[x * 32..(x + 1) * 32];
                    plain.texel_bins(x, y, &mut b);
                    for n in 0..32 {
                        assert!(
                            (a[n] - b[n]).abs() <= 1e-5,
                            "{w}x{h} {edge:?} {radius:?}: ({x},{y}) bin {n}: {} vs {}",
                            a[n],
                            b[n]
                        );
                    }
                }
            }
        }
    }
}

/// Far pieces are culled a span at a time against block maxima of the map. On flat ground with
/// a few thin spikes far away, nearly every span is culled and a spike is seen only through
/// the one span whose box holds it: a box short by a column, a row or a lane would lose it.
#[test]
fn spans_culled_together_keep_every_thin_occluder() {
    let mut rng = Rng(7);
    for (w, h, edge) in [(300usize, 40usize, Edge::None), (260, 36, Edge::Wrap)] {
        let mut heights = vec![0f32; w * h];
        for _ in 0..12 {
            let (x, y) = (rng.range(100, w - 1), rng.range(0, h - 1));
            heights[y * w + x] = 2.0 + 10.0 * rng.f32();
        }
        // A low step nearer in, so some lanes start with a horizon and others without.
        for y in 0..h {
            for x in 20..24 {
                heights[y * w + x] = 0.25;
            }
        }
        let g = Grid::new(w, h, &heights, edge, YAxis::Down);
        let fast = ExactHorizon::new(g, None, 32, Reduce::Average);
        let plain = ExactMarch::new(g, None, 32, Reduce::Average);
        let (mut ch, mut bins, mut b) = (vec![0f32; w * 8], vec![0f32; w * 32], vec![0f32; 32]);
        let mut seen = 0;
        for y in 0..h {
            fast.rows(y, &mut ch, Some(&mut bins));
            for x in 0..w {
                plain.texel_bins(x, y, &mut b);
                for n in 0..32 {
                    let a = bins[x * 32 + n];
                    // East-facing bins of texels past the step: only the spikes, 40+ away.
                    let east = (n as f64 * PI / 16.0).cos() > 0.3;
                    seen += usize::from(b[n] > 0.01 && east && (30..60).contains(&x));
                    assert!(
                        (a - b[n]).abs() <= 1e-5,
                        "{edge:?} ({x},{y}) bin {n}: {a} vs {}",
                        b[n]
                    );
                }
            }
        }
        // The spikes are really seen from far away (s > 40), where spans are culled.
        assert!(seen > 100, "{edge:?}: only {seen} far horizons");
    }
}

#[test]
fn arbitrary_azimuths_match_the_march() {
    let mut rng = Rng(7);
    let (w, h) = (11, 9);
    for edge in [Edge::Wrap, Edge::None] {
        let heights = random_map(&mut rng, w, h, true);
        let g = Grid::new(w, h, &heights, edge, YAxis::Down);
        let k = ExactHorizon::new(g, None, 16, Reduce::Average);
        for _ in 0..300 {
            let (x, y) = (rng.range(0, w - 1), rng.range(0, h - 1));
            let phi = (rng.f32() as f64 - 0.5) * 20.0;
            let want = march(&g, x, y, phi, None);
            for got in [horizon_sin(&g, x, y, phi, None), k.horizon_sin(x, y, phi)] {
                assert!(got >= want - 1e-7, "({x},{y}) φ={phi}: {got} < {want}");
                let d = (got.asin() - want.asin()).abs().to_degrees();
                assert!(d <= TOL_DEG, "({x},{y}) φ={phi}: {got} vs {want}");
            }
        }
    }
}

#[test]
fn flat_map_is_all_zero() {
    let heights = vec![2.5f32; 9 * 6];
    for edge in [Edge::Wrap, Edge::None] {
        let g = Grid::new(9, 6, &heights, edge, YAxis::Up);
        let out = compute_all(&ExactHorizon::new(g, None, 32, Reduce::Average), &Progress::new());
        assert!(out.unwrap().iter().all(|&v| v == 0.0));
    }
}

#[test]
fn linear_ramp_gives_the_directional_slope() {
    // h = k·column on a 12×9 map, edge=none: tan α = max(0, k·cos φ) wherever the ray has
    // room to go, for y_axis either way (the ramp does not vary with the row).
    let (w, h, k) = (12usize, 9usize, 0.7f64);
    let heights: Vec<f32> = (0..w * h).map(|i| (k * (i % w) as f64) as f32).collect();
    for y_axis in [YAxis::Up, YAxis::Down] {
        let g = Grid::new(w, h, &heights, Edge::None, y_axis);
        let ker = ExactHorizon::new(g, None, 32, Reduce::Point);
        let mut s = vec![0f32; 32];
        ker.texel_bins(5, 4, &mut s);
        for (n, &v) in s.iter().enumerate() {
            let phi = n as f64 * 2.0 * PI / 32.0;
            let t = (k * phi.cos()).max(0.0);
            let want = t / (1.0 + t * t).sqrt();
            assert!((v as f64 - want).abs() < 1e-6, "bin {n}: {v} vs {want}");
        }
        // On the right border nothing lies east: the rays with cos φ > 0 leave the surface.
        ker.texel_bins(w - 1, 4, &mut s);
        for n in [0, 1, 2, 30, 31] {
            assert_eq!(s[n], 0.0, "bin {n}");
        }
    }
}

#[test]
fn diamond_pyramid_has_closed_form_horizons() {
    // h = c − k·(|X − X0| + |Y − Y0|) is linear inside every cell (the creases lie on grid
    // lines), so the bilinear surface is the pyramid itself. From (X0 − d, Y0) the ratio along
    // the ray is k·(cos φ − |sin φ|) until the ray crosses X = X0, and falls after:
    // tan α = max(0, k·(cos φ − |sin φ|)).
    let (n, c0, k) = (21usize, 40.0f64, 1.25f64);
    let heights: Vec<f32> = (0..n * n)
        .map(|i| {
            let (x, y) = ((i % n) as f64 - 10.0, (i / n) as f64 - 10.0);
            (c0 - k * (x.abs() + y.abs())) as f32
        })
        .collect();
    for y_axis in [YAxis::Up, YAxis::Down] {
        let g = Grid::new(n, n, &heights, Edge::None, y_axis);
        for x in [3usize, 9] {
            for b in 0..64 {
                let phi = b as f64 * 2.0 * PI / 64.0;
                let t = (k * (phi.cos() - phi.sin().abs())).max(0.0);
                let want = t / (1.0 + t * t).sqrt();
                let got = horizon_sin(&g, x, 10, phi, None);
                assert!((got - want).abs() < 1e-9, "x={x} φ={phi}: {got} vs {want}");
            }
        }
    }
}

#[test]
fn single_wall_on_a_strip() {
    // A 9×1 strip: the ray along +x is the profile between centres, piecewise linear, so the
    // wall of height 3 at column 5 seen from column 0 gives tan α = 3/5 exactly.
    let mut heights = vec![0.0f32; 9];
    heights[5] = 3.0;
    let g = Grid::new(9, 1, &heights, Edge::None, YAxis::Up);
    let k = ExactHorizon::new(g, None, 32, Reduce::Point);
    let mut s = vec![0f32; 32];
    k.texel_bins(0, 0, &mut s);
    let want = (3.0f64 / 5.0) / (1.0 + 0.36f64).sqrt();
    assert!((s[0] as f64 - want).abs() < 1e-6, "{}", s[0]);
    // Every other azimuth leaves a 1-texel-high strip at once (or looks away from the wall).
    assert!(s[1..].iter().all(|&v| v == 0.0), "{s:?}");
    // A radius shorter than the wall distance does not see it; R = 5 does.
    let mut s4 = vec![0f32; 32];
    ExactHorizon::new(g, Some(4), 32, Reduce::Point).texel_bins(0, 0, &mut s4);
    assert_eq!(s4[0], 0.0);
    ExactHorizon::new(g, Some(5), 32, Reduce::Point).texel_bins(0, 0, &mut s4);
    assert!((s4[0] as f64 - want).abs() < 1e-6);
    // Wrapping, the wall is also 4 texels west of column 0: tan = 3/4.
    let gw = Grid::new(9, 1, &heights, Edge::Wrap, YAxis::Up);
    ExactHorizon::new(gw, None, 32, Reduce::Point).texel_bins(0, 0, &mut s4);
    let west = 0.75f64 / (1.0 + 0.5625f64).sqrt();
    assert!((s4[16] as f64 - west).abs() < 1e-6, "{}", s4[16]);
}

#[test]
fn edge_none_surface_ends_at_the_border_centres() {
    // The outer half texel is not surface: a ray leaving through the border sees the border
    // point it crosses and nothing beyond. Here all heights are 0 except a tall texel two rows
    // further along the border column: a surface extended past the centres would rise toward it.
    let (w, h) = (4usize, 6usize);
    let mut heights = vec![0.0f32; w * h];
    heights[4 * w + 3] = 100.0; // column 3 (the border), row 4
    let g = Grid::new(w, h, &heights, Edge::None, YAxis::Down);
    // From (2, 1) at 45° (down-right with y_axis=down): the ray meets the border column at row 2.
    let s = horizon_sin(&g, 2, 1, PI / 4.0, None);
    assert_eq!(s, 0.0);
    // Along the border column itself the tall texel is on the surface and is seen.
    let s = horizon_sin(&g, 3, 1, PI / 2.0, None);
    let want = (100.0f64 / 3.0) / (1.0 + (100.0f64 / 3.0).powi(2)).sqrt();
    assert!((s - want).abs() < 1e-12, "{s} vs {want}");
}

#[test]
fn unlimited_edge_none_reaches_the_far_corner() {
    // The diagonal of an 8×8 map (7·√2 ≈ 9.9) is longer than max(W, H) = 8.
    let n = 8usize;
    let mut heights = vec![0.0f32; n * n];
    heights[n - 1] = 5.0; // column 7, row 0: top right
    let g = Grid::new(n, n, &heights, Edge::None, YAxis::Up);
    let d = 7.0 * 2f64.sqrt();
    let want = (5.0 / d) / (1.0 + (5.0 / d).powi(2)).sqrt();
    let got = horizon_sin(&g, 0, n - 1, PI / 4.0, None);
    assert!((got - want).abs() < 1e-9, "{got} vs {want}");
    assert_eq!(horizon_sin(&g, 0, n - 1, PI / 4.0, Some(8.0)), 0.0);
    // And through the bake path, unlimited reaches it too.
    let mut p = BakeParams::default();
    for (k, v) in [("method", "exact"), ("radius", "unlimited"), ("edge", "none"), ("bins", "32")] {
        p.set(k, v).unwrap();
    }
    p.set("height_scale", "1").unwrap();
    p.set("reduce", "point").unwrap();
    let map =
        HeightMap { width: n, height: n, values: heights.clone(), terrain: Default::default() };
    let (layers, _) = bake::bake_horizon(&map, &p, Precisions::ALL, &Progress::new()).unwrap();
    // Channel 1 (45°) of texel (0, 7) is layer 0 G.
    let f = layers.f32.as_ref().unwrap();
    let v = f[0][((n - 1) * n) * 4 + 1] as f64;
    assert!((v - want).abs() < 1e-6, "{v} vs {want}");
}

#[test]
fn point_without_bins_casts_only_the_channel_azimuths_and_keeps_their_values() {
    // `reduce=point` with no per-bin output skips the bins between channels; the 8 channels
    // must be bit-for-bit those of the full computation, and match the plain march.
    let mut rng = Rng(4242);
    for (w, h, edge, radius, bins) in [
        (23, 9, Edge::Wrap, None, 32u32),
        (19, 12, Edge::None, None, 32),
        (40, 6, Edge::Wrap, Some(7), 64),
        (17, 17, Edge::None, Some(30), 48),
    ] {
        let heights = random_map(&mut rng, w, h, true);
        let g = Grid::new(w, h, &heights, edge, YAxis::Down);
        let k = ExactHorizon::new(g, radius, bins, Reduce::Point);
        let plain = ExactMarch::new(g, radius, bins, Reduce::Point);
        let nb = bins as usize;
        let (mut skip, mut full) = (vec![f32::NAN; w * 8], vec![f32::NAN; w * 8]);
        let (mut all_bins, mut b) = (vec![0f32; w * nb], vec![0f32; nb]);
        for y in 0..h {
            k.rows(y, &mut skip, None);
            k.rows(y, &mut full, Some(&mut all_bins));
            assert_eq!(skip, full, "{w}x{h} {edge:?} {radius:?} {bins} bins: row {y}");
            for x in 0..w {
                plain.texel_bins(x, y, &mut b);
                for c in 0..8 {
                    let (got, want) = (skip[x * 8 + c], b[c * nb / 8]);
                    assert!((got - want).abs() <= 1e-5, "({x},{y}) channel {c}: {got} vs {want}");
                }
            }
        }
    }
}

#[test]
fn reduce_point_and_average_follow_the_bins() {
    let mut rng = Rng(99);
    let heights = random_map(&mut rng, 10, 7, true);
    let g = Grid::new(10, 7, &heights, Edge::Wrap, YAxis::Up);
    let pt = ExactHorizon::new(g, Some(6), 48, Reduce::Point);
    let av = ExactHorizon::new(g, Some(6), 48, Reduce::Average);
    let (mut cp, mut ca) = (vec![0f32; 10 * 8], vec![0f32; 10 * 8]);
    let (mut bp, mut ba) = (vec![0f32; 10 * 48], vec![0f32; 10 * 48]);
    for y in 0..7 {
        pt.rows(y, &mut cp, Some(&mut bp));
        av.rows(y, &mut ca, Some(&mut ba));
        assert_eq!(bp, ba, "the reduction does not change the bins");
        for x in 0..10 {
            let bins = &bp[x * 48..(x + 1) * 48];
            let (mut p8, mut a8) = ([0f32; 8], [0f32; 8]);
            reduce_point(bins, &mut p8);
            reduce_average(bins, &mut a8);
            assert_eq!(&cp[x * 8..x * 8 + 8], &p8);
            assert_eq!(&ca[x * 8..x * 8 + 8], &a8);
            for c in 0..8 {
                // Point is bin c·6; average is the mean of bins c·6−3 ..= c·6+3.
                assert_eq!(p8[c], bins[c * 6]);
                let mean: f64 = (-3i64..=3)
                    .map(|k| bins[(c as i64 * 6 + k).rem_euclid(48) as usize] as f64)
                    .sum::<f64>()
                    / 7.0;
                assert!((a8[c] as f64 - mean).abs() < 1e-6);
            }
        }
    }
    // On a ramp the two differ in the expected direction: the average over ±33.75° of
    // k·cos φ is below the point value at 0°.
    let ramp: Vec<f32> = (0..64).map(|i| 0.5 * (i % 8) as f32).collect();
    let g = Grid::new(8, 8, &ramp, Edge::None, YAxis::Up);
    let mut c = vec![0f32; 8 * 8];
    ExactHorizon::new(g, None, 48, Reduce::Point).rows(3, &mut c, None);
    let point = c[3 * 8];
    ExactHorizon::new(g, None, 48, Reduce::Average).rows(3, &mut c, None);
    let avg = c[3 * 8];
    let want_point = 0.5 / 1.25f64.sqrt();
    assert!((point as f64 - want_point).abs() < 1e-6);
    let want_avg = (-3i32..=3)
        .map(|k| {
            let t = 0.5 * (k as f64 * 2.0 * PI / 48.0).cos();
            t / (1.0 + t * t).sqrt()
        })
        .sum::<f64>()
        / 7.0;
    assert!((avg as f64 - want_avg).abs() < 1e-6, "{avg} vs {want_avg}");
}

#[test]
fn cancel_stops_between_bands_and_within_a_band() {
    let mut rng = Rng(3);
    let (w, h) = (16usize, 40usize);
    let heights = random_map(&mut rng, w, h, true);
    let g = Grid::new(w, h, &heights, Edge::Wrap, YAxis::Up);

    // Canceled by the sink after the first finished band: the driver reports Canceled and
    // progress shows that not every row was done. One thread so the count is deterministic.
    let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
    let progress = Progress::new();
    progress.start(Stage::Bake, h as u64);
    let k = ExactHorizon::new(g, None, 16, Reduce::Average).with_cancel(&progress);
    let res = pool.install(|| {
        run_bands(&k, 4, false, &progress, |_, band| {
            assert_eq!(band.rows, 4);
            progress.cancel();
        })
    });
    assert!(matches!(res, Err(Error::Canceled)));
    let (done, total) = progress.counts();
    assert_eq!(total, h as u64);
    assert_eq!(done, 4, "exactly one band of 4 rows was reported");

    // Canceled before a band starts: the kernel leaves the band at its first row check.
    let mut ch = vec![f32::NAN; w * 3 * 8];
    k.rows(0, &mut ch, None);
    assert!(ch.iter().all(|v| v.is_nan()), "no texel was computed after the cancel");

    // Not canceled: progress reaches the total.
    let p2 = Progress::new();
    p2.start(Stage::Bake, h as u64);
    let k2 = ExactHorizon::new(g, None, 16, Reduce::Average).with_cancel(&p2);
    run_bands(&k2, 7, false, &p2, |_, _| {}).unwrap();
    assert_eq!(p2.counts(), (h as u64, h as u64));
}

#[test]
fn bake_uses_the_exact_kernel() {
    let mut rng = Rng(11);
    let (w, h) = (13usize, 10usize);
    let values: Vec<f32> = (0..w * h).map(|_| rng.f32()).collect();
    let map =
        HeightMap { width: w, height: h, values: values.clone(), terrain: Default::default() };
    let mut p = BakeParams::default();
    p.set("method", "exact").unwrap();
    p.set("radius", "6").unwrap();
    p.set("height_scale", "4").unwrap();
    let (layers, r) = bake::bake_horizon(&map, &p, Precisions::ALL, &Progress::new()).unwrap();
    assert_eq!(r.texels, 6);
    let heights: Vec<f32> = values.iter().map(|v| v * 4.0).collect();
    let g = Grid::new(w, h, &heights, p.edge, p.y_axis);
    let want = compute_all(&ExactMarch::new(g, Some(6), 32, Reduce::Average), &Progress::new());
    let got = bake::layers_to_channels(layers.f32.as_ref().unwrap());
    for (a, b) in got.iter().zip(&want.unwrap()) {
        assert!((a - b).abs() <= 1e-5, "{a} vs {b}");
    }
}

/// The earth-curvature drop (SPEC §3.7) in the vectorised kernel: its near field takes the drop
/// as a term of the cell quadratic and the walk beyond it the same drop, so a curved bake no
/// longer walks every ray from s = 0 in scalar code. Against the brute-force march of the
/// lowered surface within 0.01°, and against the scalar walk from s = 0 (`texel_bins`, the
/// path curved bakes took before) to f32 rounding. The drop is strong here (a 40-texel ray
/// loses 8 texels), so a near field without it would be degrees off.
#[test]
fn curvature_in_the_vectorised_kernel_matches_brute_force_and_the_scalar_walk() {
    let mut rng = Rng(0xC0A7);
    let curv = 5e-3;
    for (w, h, edge, radius) in [
        (37usize, 29usize, Edge::None, None),
        (31, 34, Edge::Wrap, Some(20u32)),
        (40, 23, Edge::None, Some(12)),
    ] {
        let heights = random_map(&mut rng, w, h, false);
        let g = Grid::new(w, h, &heights, edge, YAxis::Up);
        let k = ExactHorizon::new(g, radius, 32, Reduce::Average).with_curvature(curv);
        let mut bins = vec![0.0f32; w * h * 32];
        let mut ch = vec![0.0f32; w * h * 8];
        k.rows(0, &mut ch, Some(&mut bins));
        let mut scalar = vec![0.0f32; 32];
        let (mut worst_walk, mut worst_deg) = (0.0f64, 0.0f64);
        for t in 0..w * h {
            let (x, y) = (t % w, t / w);
            k.texel_bins(x, y, &mut scalar);
            for n in 0..32 {
                let v = bins[t * 32 + n] as f64;
                worst_walk = worst_walk.max((v - scalar[n] as f64).abs());
                if (x * 7 + y * 3 + n) % 11 == 0 {
                    let phi = n as f64 * 2.0 * PI / 32.0;
                    let r = radius.map(f64::from);
                    let m = march_curved(&g, x, y, phi, r, curv);
                    worst_deg = worst_deg.max((v.asin() - m.asin()).abs().to_degrees());
                }
            }
        }
        eprintln!(
            "{w}×{h} {edge:?} R={radius:?}: vs walk {worst_walk:.2e}, vs march {worst_deg:.4}°"
        );
        assert!(worst_walk < 2e-5, "{edge:?} R={radius:?}: {worst_walk} from the scalar walk");
        assert!(worst_deg <= TOL_DEG, "{edge:?} R={radius:?}: {worst_deg}° from brute force");
    }
}

/// A ray along a grid line runs on the edge of the cells on both sides of it: with holes on
/// one side only, that edge is still surface (SPEC §2: only the cells touching a hole are no
/// surface), so a peak on the texel's own row occludes, whichever side holds the holes, at the
/// four axis azimuths. The walk used to look at one side's cell only and lost the peak when
/// that side's cells touched a hole (found against `sweep` on a reprojected DEM's rim).
#[test]
fn a_ray_along_a_grid_line_beside_holes_keeps_the_edge() {
    let (w, h) = (21usize, 21usize);
    let (c, peak) = (10usize, 6.0f32);
    for side in [-1i64, 1] {
        // Peaks 6 texels west, east, north and south of the centre; the line of holes beside
        // each ray, on one side.
        let mut heights = vec![0.0f32; w * h];
        let mut holes = vec![false; w * h];
        for (px, py) in [(c - 6, c), (c + 6, c), (c, c - 6), (c, c + 6)] {
            heights[py * w + px] = peak;
        }
        for k in 0..w {
            if k.abs_diff(c) >= 2 {
                let r = (c as i64 + side) as usize;
                holes[r * w + k] = true;
                holes[k * w + r] = true;
            }
        }
        for (v, &o) in heights.iter_mut().zip(&holes) {
            if o {
                *v = -6000.0;
            }
        }
        for edge in [Edge::None, Edge::Wrap] {
            let g = Grid::new(w, h, &heights, edge, YAxis::Up);
            let k = ExactHorizon::new(g, None, 32, Reduce::Average).with_holes(Some(&holes));
            let want = (6.0f64 / 6.0).atan().sin();
            for phi_deg in [0.0f64, 90.0, 180.0, 270.0] {
                let got = k.horizon_sin(c, c, phi_deg.to_radians());
                assert!(
                    (got - want).abs() < 1e-6,
                    "side {side} {edge:?} azimuth {phi_deg}: {got}, want {want}"
                );
            }
        }
    }
}
