//! `method=sweep` (SPEC §3.2a): the kernel against a scalar f64 oracle of the same samples for
//! every instruction set, against `method=exact` at the same radius for its tolerance, at its
//! radius, with the earth's curvature and with holes.
//!
//! # Stated tolerance (README, SPEC §3.2a)
//! Against `exact` at the same radius, |Δα| per azimuth bin, on terrain-like maps (the real
//! Jacksboro excerpt, fBm with median slopes of 10°, 30° and 45°, smooth waves): mean ≤ 0.05°,
//! p99 ≤ 0.25°. Worst cases, stated and bounded here: white noise and fields of single-texel
//! spikes (see [`WORST_NOISE`], [`WORST_SPIKES`]).

use crate::support;
use crate::support::{mean_p99, surface, waves, Rng};
use horizon_bake::eval::corpus;
use horizon_bake::kernels::exact::{self, ExactHorizon};
use horizon_bake::kernels::isa::Isa;
use horizon_bake::kernels::sweep::{azimuth_lines, Options, Sweep, NEAR_STEPS};
use horizon_bake::kernels::{Grid, HorizonRows};
use horizon_bake::params::{BakeParams, Edge, Reduce, YAxis};
use horizon_bake::progress::Progress;
use std::f64::consts::PI;

/// White noise (heights uniform in 0..12, slopes up to 12): stated worst (mean, p99) in degrees.
const WORST_NOISE: (f64, f64) = (0.05, 1.0);
/// 1 % of texels are spikes 4–24 texels tall: stated worst (mean, p99) in degrees.
const WORST_SPIKES: (f64, f64) = (0.6, 8.0);

/// Per-bin sin α of every texel, in bands of 5 rows.
fn per_bin(k: &dyn HorizonRows) -> Vec<f32> {
    support::per_bin(k, 5)
}

/// |Δα| in degrees between two sets of sin α.
fn degrees_apart(a: &[f32], b: &[f32]) -> Vec<f64> {
    a.iter()
        .zip(b)
        .map(|(&a, &b)| ((a as f64).asin() - (b as f64).asin()).abs().to_degrees())
        .collect()
}

/// Mean and p99 |Δα| (degrees) of the sweep against exact at `radius`, with curvature `c`.
fn against_exact(g: Grid<'_>, radius: Option<u32>, c: f64) -> (f64, f64) {
    let opt = Options { curvature: c, ..Options::default() };
    let s = per_bin(&Sweep::with_options(g, radius, 32, Reduce::Average, opt));
    let e = per_bin(&ExactHorizon::new(g, radius, 32, Reduce::Average).with_curvature(c));
    mean_p99(degrees_apart(&s, &e))
}

fn check(name: &str, g: Grid<'_>, radius: Option<u32>, limit: (f64, f64)) -> (f64, f64) {
    let (mean, p99) = against_exact(g, radius, 0.0);
    eprintln!("{name} {:?} R {radius:?}: mean {mean:.4}° p99 {p99:.4}°", g.edge);
    assert!(mean <= limit.0, "{name} {:?} R {radius:?}: mean {mean}°", g.edge);
    if std::env::var("SWEEP_ALL").is_err() {
        assert!(p99 <= limit.1, "{name} {:?} R {radius:?}: p99 {p99}°", g.edge);
    }
    (mean, p99)
}

const TERRAIN: (f64, f64) = (0.05, 0.25);

/// Periodic fBm from bilinear value noise (octaves of about 32, 16, …, 2 texels, gain ½; whole
/// lattice periods across the map, so `edge=wrap` has no seam cliff), scaled so the median
/// central-difference slope is `slope_deg`.
fn fbm(rng: &mut Rng, w: usize, h: usize, slope_deg: f64) -> Vec<f32> {
    let mut v = vec![0.0f64; w * h];
    let mut amp = 1.0;
    let mut cell = 32usize;
    while cell >= 2 {
        let (gw, gh) = ((w / cell).max(1), (h / cell).max(1));
        let lat: Vec<f64> = (0..gw * gh).map(|_| rng.f32() as f64).collect();
        for r in 0..h {
            for c in 0..w {
                let (fx, fy) = (c as f64 * gw as f64 / w as f64, r as f64 * gh as f64 / h as f64);
                let (ix, iy) = (fx as usize, fy as usize);
                let (tx, ty) = (fx - ix as f64, fy - iy as f64);
                let at = |i: usize, j: usize| lat[(j % gh) * gw + i % gw];
                let top = at(ix, iy) * (1.0 - tx) + at(ix + 1, iy) * tx;
                let bot = at(ix, iy + 1) * (1.0 - tx) + at(ix + 1, iy + 1) * tx;
                v[r * w + c] += amp * (top * (1.0 - ty) + bot * ty);
            }
        }
        amp *= 0.5;
        cell /= 2;
    }
    let mut slopes = Vec::new();
    for r in 1..h - 1 {
        for c in 1..w - 1 {
            let gx = (v[r * w + c + 1] - v[r * w + c - 1]) / 2.0;
            let gy = (v[(r + 1) * w + c] - v[(r - 1) * w + c]) / 2.0;
            slopes.push((gx * gx + gy * gy).sqrt());
        }
    }
    slopes.sort_by(f64::total_cmp);
    let median = slopes.get(slopes.len() / 2).copied().unwrap_or(1.0).max(1e-12);
    let k = slope_deg.to_radians().tan() / median;
    v.iter().map(|&x| (x * k) as f32).collect()
}

/// The sweep's definition, scalar and f64, straight from the bilinear surface: the exact
/// horizon of the texel's own ray up to N·√(1+m²) (clipped to R), and beyond it the samples of
/// the nearest sub-line at every major grid line u' with N ≤ u' − u ≤ R/√(1+m²) and halfway
/// between two of them, each lowered
/// by c·s², and the point at exactly R on the texel's own ray, as sin α. Samples off the
/// surface (edge=none) do not count.
fn oracle(g: &Grid<'_>, x: usize, y: usize, n: usize, bins: usize, r: Option<f64>, c: f64) -> f64 {
    let phi = n as f64 * 2.0 * PI / bins as f64;
    let d = exact::direction(phi, g.row_step());
    // The kernel's lines of this azimuth (with `edge=wrap`, maybe the opposite's read
    // backwards: `azimuth_lines`).
    let lines = azimuth_lines(g, r.map(|r| r as u32), bins as u32)[n];
    let reach = match (r, g.edge) {
        (Some(r), _) => Some(r),
        (None, Edge::Wrap) => Some(g.width.max(g.height) as f64),
        (None, Edge::None) => None,
    };
    let near_cut =
        reach.map_or(NEAR_STEPS as f64 * lines.step, |r| r.min(NEAR_STEPS as f64 * lines.step));
    let h0 = g.heights[y * g.width + x] as f64;
    // Near: exact over 0 < s ≤ near_cut, with the curvature.
    let near = if c > 0.0 {
        // A fine scan of the ray (the kernel's closed form can only be above it).
        // The supremum includes the limit s → 0⁺ (the directional slope): s = 1e-7 stands for it.
        let mut best = 0.0f64;
        let steps = 20000;
        for i in 0..=steps {
            let s = if i == 0 { 1e-7 } else { near_cut * i as f64 / steps as f64 };
            let (px, py) = (x as f64 + s * d.0, y as f64 + s * d.1);
            if g.edge == Edge::None
                && (px < -1e-9
                    || py < -1e-9
                    || px > (g.width - 1) as f64 + 1e-9
                    || py > (g.height - 1) as f64 + 1e-9)
            {
                break;
            }
            best = best.max((surface(g, px, py) - c * s * s - h0) / s);
        }
        best
    } else {
        let s = exact::horizon_sin(g, x, y, phi, Some(near_cut));
        s / (1.0 - s * s).max(1e-300).sqrt()
    };
    // Far: the nearest sub-line's samples.
    let (wa, a, b) =
        if lines.major_x { (g.width, x as i64, y as f64) } else { (g.height, y as i64, x as f64) };
    let u = if lines.sign > 0 { a } else { wa as i64 - 1 - a };
    let r_steps = reach.map_or(i64::MAX, |r| (r / lines.step + 1e-9).floor() as i64);
    // Far: each of the two sub-lines around the texel, then their weighted mean.
    let (mut sum, mut wsum) = (0.0f64, 0.0f64);
    for (k, shift, wt) in lines.pair(u) {
        let i = b as i64 + shift;
        let line_at = |up: f64| lines.minor(k, i, up);
        let mut line_best = f64::NEG_INFINITY;
        // Every major grid line from N to R, and halfway between two of them.
        let mut k_off = NEAR_STEPS as f64;
        while k_off <= r_steps as f64 {
            let up = u as f64 + k_off;
            if g.edge == Edge::None && up > (wa - 1) as f64 {
                break;
            }
            let major = a as f64 + lines.sign as f64 * k_off;
            let minor = line_at(up);
            let (px, py) = if lines.major_x { (major, minor) } else { (minor, major) };
            let inside = g.edge == Edge::Wrap
                || (px >= -1e-9
                    && py >= -1e-9
                    && px <= (g.width - 1) as f64 + 1e-9
                    && py <= (g.height - 1) as f64 + 1e-9);
            if inside {
                let s = k_off * lines.step;
                line_best = line_best.max((surface(g, px, py) - c * s * s - h0) / s);
            }
            k_off += if horizon_bake::kernels::sweep::MIDS { 0.5 } else { 1.0 };
        }
        if line_best > f64::NEG_INFINITY {
            sum += wt * line_best;
            wsum += wt;
        }
    }
    let mut far = if wsum > 0.0 { sum / wsum } else { 0.0 };
    // And the point at exactly R on the texel's own ray, when the far field reaches it.
    if let Some(r) = reach.filter(|&r| r > near_cut) {
        let (px, py) = (x as f64 + r * d.0, y as f64 + r * d.1);
        let inside = g.edge == Edge::Wrap
            || (px >= -1e-9
                && py >= -1e-9
                && px <= (g.width - 1) as f64 + 1e-9
                && py <= (g.height - 1) as f64 + 1e-9);
        if inside {
            far = far.max((surface(g, px, py) - c * r * r - h0) / r);
        }
    }
    let t = near.max(far).max(0.0);
    t / (1.0 + t * t).sqrt()
}

#[test]
fn every_isa_matches_the_scalar_oracle_of_the_same_samples() {
    let mut rng = Rng(31);
    let isas: Vec<Isa> =
        [Isa::Avx512, Isa::Avx2, Isa::Baseline].into_iter().filter(|i| i.supported()).collect();
    for (w, h, edge, radius, c) in [
        (37usize, 23usize, Edge::Wrap, None, 0.0),
        (37, 23, Edge::None, None, 0.0),
        (29, 41, Edge::None, Some(27u32), 0.0),
        (29, 41, Edge::Wrap, Some(20), 0.0),
        (40, 33, Edge::None, None, 2e-3),
        (1, 37, Edge::None, None, 0.0),
        (37, 1, Edge::Wrap, Some(25), 0.0),
    ] {
        let heights = fbm(&mut rng, w, h, 30.0);
        let g = Grid::new(w, h, &heights, edge, YAxis::Up);
        let bins = 16usize;
        let want: Vec<f64> = (0..w * h)
            .flat_map(|t| (0..bins).map(move |n| (t, n)).collect::<Vec<_>>())
            .map(|(t, n)| oracle(&g, t % w, t / w, n, bins, radius.map(f64::from), c))
            .collect();
        for &isa in &isas {
            let opt = Options { curvature: c, isa: Some(isa), ..Options::default() };
            let got = per_bin(&Sweep::with_options(g, radius, bins as u32, Reduce::Point, opt));
            // With the curvature the oracle scans the near field finely instead of solving it.
            let tol = if c > 0.0 { 5e-4 } else { 3e-5 };
            for (k, (&a, &b)) in got.iter().zip(&want).enumerate() {
                assert!(
                    (a as f64 - b).abs() <= tol,
                    "{isa:?} {w}×{h} {edge:?} R {radius:?} c {c}: texel {} bin {}: {a} vs {b}",
                    k / bins,
                    k % bins
                );
            }
        }
    }
}

#[test]
fn meets_its_tolerance_on_the_real_terrain_and_fbm_and_waves() {
    let jacksboro =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("docs/corpus/jacksboro_128.png");
    let m = corpus::from_file("jacksboro", &jacksboro, 65535.0 / 90.0, 128).unwrap();
    for edge in [Edge::Wrap, Edge::None] {
        let g = Grid::new(m.width, m.height, &m.heights, edge, YAxis::Up);
        for radius in [Some(40u32), None] {
            check("jacksboro", g, radius, TERRAIN);
        }
    }
    let mut rng = Rng(2026);
    for (i, (w, h)) in [(64usize, 64usize), (53, 41)].into_iter().enumerate() {
        for slope in [10.0, 30.0, 45.0] {
            let heights = fbm(&mut rng, w, h, slope);
            let y_axis = if i % 2 == 0 { YAxis::Up } else { YAxis::Down };
            for edge in [Edge::Wrap, Edge::None] {
                let g = Grid::new(w, h, &heights, edge, y_axis);
                for radius in [Some(24u32), Some(50), None] {
                    check(&format!("fbm {slope}° {w}×{h}"), g, radius, TERRAIN);
                }
            }
        }
        let heights = waves(&mut rng, w, h, 3, 6.0);
        for edge in [Edge::Wrap, Edge::None] {
            let g = Grid::new(w, h, &heights, edge, YAxis::Up);
            check(&format!("waves {w}×{h}"), g, None, TERRAIN);
        }
    }
}

#[test]
fn states_its_worst_case_on_white_noise_and_spike_fields() {
    let mut rng = Rng(7);
    let (w, h) = (45usize, 38usize);
    let noise: Vec<f32> = (0..w * h).map(|_| rng.f32() * 12.0).collect();
    let spikes: Vec<f32> =
        (0..w * h).map(|_| if rng.f32() < 0.01 { 4.0 + 20.0 * rng.f32() } else { 0.0 }).collect();
    for edge in [Edge::Wrap, Edge::None] {
        for radius in [Some(30u32), None] {
            check("white noise", Grid::new(w, h, &noise, edge, YAxis::Up), radius, WORST_NOISE);
            check("spikes", Grid::new(w, h, &spikes, edge, YAxis::Up), radius, WORST_SPIKES);
        }
    }
}

#[test]
fn odd_sizes_and_thin_strips_match_exact() {
    let mut rng = Rng(5);
    for (w, h) in [(1usize, 1usize), (1, 37), (37, 1), (2, 2), (3, 40)] {
        let heights: Vec<f32> = (0..w * h).map(|_| rng.f32() * 6.0).collect();
        for edge in [Edge::Wrap, Edge::None] {
            for y_axis in [YAxis::Up, YAxis::Down] {
                let g = Grid::new(w, h, &heights, edge, y_axis);
                for radius in [Some(1u32), Some(30), None] {
                    let s = per_bin(&Sweep::new(g, radius, 16, Reduce::Point));
                    let e = per_bin(&ExactHorizon::new(g, radius, 16, Reduce::Point));
                    let name = format!("{w}×{h} {edge:?} {y_axis:?} R {radius:?}");
                    // White noise: its stated worst case.
                    let (mean, p99) = mean_p99(degrees_apart(&s, &e));
                    let ok = mean <= WORST_NOISE.0 && p99 <= WORST_NOISE.1;
                    assert!(ok, "{name}: mean {mean}° p99 {p99}°");
                }
            }
        }
    }
}

#[test]
fn an_occluder_just_beyond_the_radius_never_counts() {
    // A flat map with one wall column at x = 60: texel (x, y) looking east (bin 0) sees it
    // within R only if 60 − x ≤ R; the bilinear ramp up to it starts at 59, so a texel exactly
    // R + 1 away sees nothing at all, literally 0.
    let (w, h) = (100usize, 9usize);
    let mut heights = vec![0f32; w * h];
    for y in 0..h {
        heights[y * w + 60] = 30.0;
    }
    for edge in [Edge::None, Edge::Wrap] {
        let g = Grid::new(w, h, &heights, edge, YAxis::Up);
        for radius in [20u32, 37] {
            let b = per_bin(&Sweep::new(g, Some(radius), 32, Reduce::Point));
            for x in 0..60 {
                let v = b[(4 * w + x) * 32];
                let dist = 60 - x as u32;
                if dist > radius {
                    assert_eq!(v, 0.0, "{edge:?} R {radius}: texel {x} sees the wall at {dist}");
                } else {
                    assert!(v > 0.3, "{edge:?} R {radius}: texel {x} misses the wall: {v}");
                }
            }
        }
        // Unlimited sees it from everywhere to its west.
        let b = per_bin(&Sweep::new(g, None, 32, Reduce::Point));
        assert!((0..60).all(|x| b[(4 * w + x) * 32] > 0.2), "{edge:?} unlimited");
    }
}

#[test]
fn earth_curvature_matches_exact_with_curvature() {
    let mut rng = Rng(99);
    let heights = fbm(&mut rng, 64, 48, 20.0);
    for edge in [Edge::None, Edge::Wrap] {
        let g = Grid::new(64, 48, &heights, edge, YAxis::Up);
        // 1e-3 texels per texel²: 1.6 texels of drop at 40, far more than a real DEM's.
        for radius in [Some(40u32), None] {
            let (mean, p99) = against_exact(g, radius, 1e-3);
            eprintln!("curvature {edge:?} R {radius:?}: mean {mean:.4}° p99 {p99:.4}°");
            assert!(mean <= TERRAIN.0 && p99 <= TERRAIN.1, "mean {mean} p99 {p99}");
        }
        // And the drop matters: without it the horizons are higher.
        let flat = per_bin(&Sweep::new(g, None, 32, Reduce::Average));
        let opt = Options { curvature: 1e-3, ..Options::default() };
        let curved = per_bin(&Sweep::with_options(g, None, 32, Reduce::Average, opt));
        let lower = flat.iter().zip(&curved).filter(|(a, b)| b < a).count();
        assert!(lower > flat.len() / 4, "{lower} of {} lowered", flat.len());
    }
}

/// Fills `holes` as the decoder does (heightmap.rs): HOLE_DEPTH ranges below the lowest texel.
fn fill_holes(heights: &mut [f32], holes: &[bool]) {
    let valid = heights.iter().zip(holes).filter(|(_, &o)| !o).map(|(&v, _)| v);
    let (lo, hi) = valid.fold((f32::MAX, f32::MIN), |(a, b), v| (a.min(v), b.max(v)));
    let fill = lo - horizon_bake::heightmap::HOLE_DEPTH * (hi - lo).max(1.0);
    for (v, &o) in heights.iter_mut().zip(holes) {
        if o {
            *v = fill;
        }
    }
}

/// Per texel: whether a hole lies within Chebyshev distance `r` (clipped, not wrapped).
fn within(holes: &[bool], w: usize, h: usize, r: usize) -> Vec<bool> {
    let mut near = vec![false; w * h];
    for (t, _) in holes.iter().enumerate().filter(|(_, &o)| o) {
        let (x, y) = (t % w, t / w);
        for yy in y.saturating_sub(r)..(y + r + 1).min(h) {
            for xx in x.saturating_sub(r)..(x + r + 1).min(w) {
                near[yy * w + xx] = true;
            }
        }
    }
    near
}

/// Nodata holes (SPEC §2, §3.2a): `sweep` handles them itself, with `exact`'s semantics (the
/// cells touching a hole occlude nothing), no fallback to `exact`. Three kinds of holes: the
/// rim of a DEM reprojected by a rotation (every warped DEM has one), 3 % random texels, and a
/// lake-sized block. Against `exact` with the same holes, at both edges, unlimited and R = 40:
/// within the stated tolerance at the texels with no hole within 2 texels; nearer, within
/// march's (0.1°, 0.5°); and what the bake runs is the sweep's own result, not `exact`'s (until
/// this, `make_kernel_for` handed such maps to `exact`).
#[test]
fn holes_are_swept_within_tolerance_of_exact() {
    use horizon_bake::bake::make_kernel_for;
    let (w, h) = (72usize, 60usize);
    let mut rng = Rng(0x5EE9);
    let base = fbm(&mut rng, w, h, 30.0);
    let (cx, cy) = (w as f64 / 2.0, h as f64 / 2.0);
    let rim: Vec<bool> = (0..w * h)
        .map(|t| {
            let (x, y) = ((t % w) as f64 - cx, (t / w) as f64 - cy);
            let (u, v) = (x * 0.94 + y * 0.34, -x * 0.34 + y * 0.94);
            u.abs() > 0.42 * w as f64 || v.abs() > 0.40 * h as f64
        })
        .collect();
    let random: Vec<bool> = (0..w * h).map(|_| rng.f32() < 0.03).collect();
    let block: Vec<bool> =
        (0..w * h).map(|t| (30..42).contains(&(t % w)) && (20..29).contains(&(t / w))).collect();
    let mut stats = vec![];
    for (name, holes) in [("rim", &rim), ("random", &random), ("block", &block)] {
        let mut heights = base.clone();
        fill_holes(&mut heights, holes);
        let close = within(holes, w, h, 2);
        for edge in [Edge::None, Edge::Wrap] {
            let g = Grid::new(w, h, &heights, edge, YAxis::Up);
            for radius in [None, Some(40u32)] {
                let r = radius.map_or("unlimited".to_string(), |r| r.to_string());
                let params =
                    BakeParams::from_pairs([("method", "sweep"), ("radius", r.as_str())]).unwrap();
                let k = make_kernel_for(
                    &params,
                    g,
                    radius.unwrap_or(72),
                    &Progress::new(),
                    Some(holes),
                );
                let got = per_bin(k.as_ref());
                let own = per_bin(
                    &Sweep::new(g, radius, 32, Reduce::Average).with_holes(Some(holes.as_slice())),
                );
                assert!(got == own, "{name} {edge:?} R {r}: the bake did not run the sweep");
                let want = per_bin(
                    &ExactHorizon::new(g, radius, 32, Reduce::Average).with_holes(Some(holes)),
                );
                let (mut away, mut near) = (vec![], vec![]);
                for t in (0..w * h).filter(|&t| !holes[t]) {
                    let d = degrees_apart(&got[t * 32..][..32], &want[t * 32..][..32]);
                    if close[t] { &mut near } else { &mut away }.extend(d);
                }
                let (am, ap) = mean_p99(away);
                let (nm, np) = mean_p99(near);
                eprintln!(
                    "holes {name} {edge:?} R {r}: away mean {am:.4}° p99 {ap:.4}°, \
                     near mean {nm:.4}° p99 {np:.4}°"
                );
                stats.push((format!("{name} {edge:?} R {r}"), edge, (am, ap), (nm, np)));
            }
        }
    }
    for (label, edge, away, near) in stats {
        // A wrapping map with a reprojection's rim (no DEM's default: those bake with
        // `edge=none`) sends every long ray across the rim's staircase twice; there the far
        // field's lines, a third of a texel beside the ray, see the rim's last surface cells a
        // third of a texel off: the stated worst case of holes (README), march's tolerance.
        let p99 = if label.starts_with("rim") && edge == Edge::Wrap { 0.5 } else { TERRAIN.1 };
        assert!(away.0 <= TERRAIN.0 && away.1 <= p99, "{label}: away {away:?}");
        assert!(near.0 <= 0.1 && near.1 <= 0.5, "{label}: near {near:?}");
    }
}

#[test]
fn a_canceled_build_stops_early() {
    let heights = vec![1.0f32; 64 * 64];
    let g = Grid::new(64, 64, &heights, Edge::Wrap, YAxis::Up);
    let p = Progress::new();
    p.cancel();
    let opt = Options { progress: Some(p.clone()), ..Options::default() };
    let k = Sweep::with_options(g, None, 32, Reduce::Average, opt);
    let r = horizon_bake::kernels::compute_all(&k, &p);
    assert!(r.is_err());
}

/// The CLI offers `--method sweep` at `--radius unlimited`: its 8-bit layers are within a couple
/// of LSB of `--method exact`'s on the golden bump (read back with the `image` crate).
#[test]
fn cli_bakes_with_method_sweep_close_to_exact() {
    let tmp = tempfile::tempdir().unwrap();
    let input = support::golden_dir().join("inputs/bump64.png");
    let bake = |method: &str| {
        let out = tmp.path().join(method);
        let o = std::process::Command::new(env!("CARGO_BIN_EXE_horizon-bake"))
            .args(["bake", input.to_str().unwrap(), "-o", out.to_str().unwrap()])
            .args(["--method", method, "--radius", "unlimited", "--height-scale", "16"])
            .output()
            .unwrap();
        assert!(o.status.success(), "{method}: {}", String::from_utf8_lossy(&o.stderr));
        let img = image::open(out.join("horizon_0.png")).unwrap().to_rgba8().into_raw();
        let report = std::fs::read_to_string(out.join("bake.json")).unwrap();
        assert!(report.contains(&format!("\"{method}\"")), "{report}");
        img
    };
    let (s, e) = (bake("sweep"), bake("exact"));
    assert_eq!(s.len(), e.len());
    let worst = s.iter().zip(&e).map(|(&a, &b)| (a as i32 - b as i32).abs()).max().unwrap();
    let lit = e.iter().filter(|&&v| v > 10).count();
    assert!(lit > e.len() / 10, "the bump casts horizons: {lit} of {}", e.len());
    assert!(worst <= 2, "sweep vs exact: {worst} LSB");
}

/// The far-field table is one f32 per texel and bin of the whole map: up to `MAX_TABLE_BYTES`
/// in memory, beyond that in a temporary file, and only a table that would pass
/// `MAX_SPILL_BYTES` even there is refused before the bake (a 422 naming `method`, exit 2 in
/// the CLI). 700² at 720 bins (1.3 GiB) was refused while the table had to fit in memory; it is
/// spilled now. 8192² at 256 bins (64 GiB) is refused.
#[test]
fn only_a_far_field_too_big_even_for_the_disk_is_refused() {
    use horizon_bake::bake::check_method_fits;
    use horizon_bake::encode::png::{encode8, PngColor};
    use horizon_bake::heightmap::{decode_for, Limits};
    use horizon_bake::kernels::sweep::{spills, MAX_SPILL_BYTES};
    let png = encode8(700, 700, PngColor::Gray, &vec![0u8; 700 * 700]).unwrap();
    let parse = |q: &str| {
        BakeParams::from_pairs(q.split('&').map(|kv| kv.split_once('=').unwrap())).unwrap()
    };
    let mut p = parse("method=sweep&bins=720&outputs=angles&reduce=point");
    assert!(decode_for(&png, &mut p, &Limits::default()).is_ok());
    assert!(spills(700, 700, 720) && !spills(700, 700, 32) && !spills(2048, 2048, 32));
    let p = parse("method=sweep&bins=256");
    const { assert!(8192u64 * 8192 * 256 * 4 > MAX_SPILL_BYTES) };
    match check_method_fits(&p, 8192, 8192) {
        Err(horizon_bake::Error::Param { field, message }) => {
            assert_eq!(field, "method");
            assert!(message.contains("MiB") && message.contains("march"), "{message}");
        }
        other => panic!("not refused: {other:?}"),
    }
    assert!(check_method_fits(&parse("method=sweep&bins=32"), 8192, 8192).is_ok());
    // `angles` and a plain SVF alone keep no table (`Sweep::planes`): any bins at any size;
    // a tilted SVF takes its bins from the bands, so it keeps one.
    const { assert!(65_536u64 * 65_536 * 720 * 4 > MAX_SPILL_BYTES) };
    let planes = parse("method=sweep&bins=720&outputs=angles,svf&reduce=point");
    assert!(check_method_fits(&planes, 65_536, 65_536).is_ok());
    let tilted = parse("method=sweep&bins=720&outputs=svf&svf_model=tilted&reduce=point");
    assert!(check_method_fits(&tilted, 65_536, 65_536).is_err());
    // Other methods keep no such table.
    assert!(check_method_fits(&parse("method=march&radius=8&bins=256"), 8192, 8192).is_ok());
}

/// A [`FarSpill`] in memory, counting what passes through it, or failing on demand.
#[derive(Default)]
struct MemSpill {
    planes: std::sync::Mutex<std::collections::HashMap<usize, Vec<f32>>>,
    fail_put: Option<std::io::ErrorKind>,
    fail_get: bool,
}

impl horizon_bake::kernels::sweep::FarSpill for MemSpill {
    fn put(&self, n: usize, start: usize, values: &[f32]) -> std::io::Result<()> {
        if let Some(kind) = self.fail_put {
            return Err(std::io::Error::new(kind, "the test's store refuses"));
        }
        let mut planes = self.planes.lock().unwrap();
        let plane = planes.entry(n).or_default();
        if plane.len() < start + values.len() {
            plane.resize(start + values.len(), f32::NAN);
        }
        plane[start..start + values.len()].copy_from_slice(values);
        Ok(())
    }
    fn get(&self, n: usize, start: usize, out: &mut [f32]) -> std::io::Result<()> {
        if self.fail_get {
            return Err(std::io::Error::other("the test's store cannot read"));
        }
        let planes = self.planes.lock().unwrap();
        out.copy_from_slice(&planes[&n][start..start + out.len()]);
        Ok(())
    }
}

/// The far field read back from a spill store, in memory or in a real temporary file
/// (`bake::FileSpill`), gives the bits of the in-memory table: random fBm, both edges, finite
/// and unlimited radii, both reductions, the per-bin output, odd sizes and several band
/// heights (bands whose rows straddle planes' boundaries in the file).
#[test]
fn a_spilled_far_field_gives_the_bits_of_the_table_in_memory() {
    use horizon_bake::bake::FileSpill;
    use horizon_bake::kernels::run_bands;
    use std::sync::Arc;
    let mut rng = Rng(0x5e11);
    for (w, h, edge, radius, reduce, bins) in [
        (67, 45, Edge::Wrap, None, Reduce::Average, 32u32),
        (67, 45, Edge::None, None, Reduce::Point, 32),
        (50, 71, Edge::None, Some(30), Reduce::Average, 48),
        (33, 1, Edge::Wrap, Some(20), Reduce::Point, 16),
    ] {
        let hts = fbm(&mut rng, w, h, 30.0);
        let g = Grid::new(w, h, &hts, edge, YAxis::Down);
        let run = |spill: Option<Arc<dyn horizon_bake::kernels::sweep::FarSpill>>, band: usize| {
            let opt = Options { spill, ..Options::default() };
            let k = Sweep::with_options(g, radius, bins, reduce, opt);
            let nb = k.bins();
            let ch = std::sync::Mutex::new(vec![0.0f32; w * h * 8]);
            let bo = std::sync::Mutex::new(vec![0.0f32; w * h * nb]);
            run_bands(&k, band, true, &Progress::new(), |_, b| {
                let start = b.y0 * w;
                ch.lock().unwrap()[start * 8..][..b.channels.len()].copy_from_slice(b.channels);
                let bins = b.bins.unwrap();
                bo.lock().unwrap()[start * nb..][..bins.len()].copy_from_slice(bins);
            })
            .unwrap();
            (ch.into_inner().unwrap(), bo.into_inner().unwrap())
        };
        let want = run(None, 7);
        let nonzero = want.1.iter().filter(|&&v| v > 0.0).count();
        assert!(nonzero > want.1.len() / 4, "the map casts horizons: {nonzero}");
        for band in [1, 4, h] {
            let mem = Arc::new(MemSpill::default());
            let got = run(Some(mem.clone()), band);
            assert_eq!(mem.planes.lock().unwrap().len(), bins as usize, "every plane stored");
            assert!(got == want, "{w}×{h} {edge:?} R {radius:?}: memory spill, band {band}");
            let file = Arc::new(FileSpill::new(w * h, std::env::temp_dir()));
            let got = run(Some(file), band);
            assert!(got == want, "{w}×{h} {edge:?} R {radius:?}: file spill, band {band}");
        }
    }
}

/// Azimuth-major (`Options::azimuth_major`, no far-field table): `Sweep::planes` hands every
/// bin of every band once, bins in the order 0, 1, … within each band, with the per-bin values
/// of the table's bands bit for bit: random fBm, both edges, finite and unlimited radii, odd
/// sizes, holes, curvature, every ISA, several band heights; its `rows` give nothing. A sink
/// that sums in the bins' order therefore gets the bands' sums.
#[test]
fn azimuth_major_planes_give_the_bits_of_the_bands() {
    use std::sync::Mutex;
    let mut rng = Rng(0xa21);
    let cases = [
        (67, 45, Edge::Wrap, None, 32u32, false, 0.0),
        (67, 45, Edge::None, None, 48, true, 0.0),
        (50, 71, Edge::None, Some(30), 32, false, 1e-3),
        (33, 1, Edge::Wrap, Some(20), 16, false, 0.0),
        (40, 37, Edge::Wrap, Some(25), 360, true, 0.0),
        (41, 36, Edge::Wrap, Some(25), 64, false, 2e-4),
    ];
    for (w, h, edge, radius, bins, with_holes, curvature) in cases {
        let mut hts = fbm(&mut rng, w, h, 30.0);
        let holes: Vec<bool> = (0..w * h).map(|_| with_holes && rng.f32() < 0.04).collect();
        if with_holes {
            fill_holes(&mut hts, &holes);
        }
        let holes = with_holes.then_some(holes.as_slice());
        let g = Grid::new(w, h, &hts, edge, YAxis::Down);
        for isa in [Isa::Avx512, Isa::Avx2, Isa::Baseline].into_iter().filter(|i| i.supported()) {
            let opt = |azimuth_major| Options {
                curvature,
                isa: Some(isa),
                azimuth_major,
                ..Options::default()
            };
            let table =
                Sweep::with_options(g, radius, bins, Reduce::Average, opt(false)).with_holes(holes);
            let want = per_bin(&table);
            let nb = bins as usize;
            let lit = want.iter().filter(|&&v| v > 0.0).count();
            assert!(lit > want.len() / 4, "the map casts horizons: {lit}");
            let k =
                Sweep::with_options(g, radius, bins, Reduce::Average, opt(true)).with_holes(holes);
            assert!(k.is_azimuth_major() && !table.is_azimuth_major());
            assert!(per_bin(&k).iter().all(|&v| v == 0.0), "rows give nothing");
            // On a pool of one thread one azimuth is in flight, and those along x hand their
            // rows on as they sweep (`Sweep::streamed_x`), as on a big map.
            let one = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
            for (band, pool) in [(1, None), (4, None), (h, None), (1, Some(&one)), (7, Some(&one))]
            {
                let got = Mutex::new(vec![f32::NAN; w * h * nb]);
                let next = Mutex::new(vec![0usize; h.div_ceil(band)]);
                let p = Progress::new();
                p.start(horizon_bake::progress::Stage::Bake, (h * nb) as u64);
                let run = |sink: &(dyn Fn(usize, usize, &[f32]) + Sync)| match pool {
                    Some(pool) => pool.install(|| k.planes(band, &p, sink)),
                    None => k.planes(band, &p, sink),
                };
                run(&|b, n, s| {
                    let mut next = next.lock().unwrap();
                    assert_eq!(next[b], n, "band {b}: bins in order");
                    next[b] += 1;
                    assert_eq!(s.len(), band.min(h - b * band) * w);
                    let mut got = got.lock().unwrap();
                    for (t, &v) in s.iter().enumerate() {
                        got[(b * band * w + t) * nb + n] = v;
                    }
                })
                .unwrap();
                assert!(next.into_inner().unwrap().iter().all(|&n| n == nb), "every bin");
                assert_eq!(p.counts(), ((h * nb) as u64, (h * nb) as u64));
                let got = got.into_inner().unwrap();
                // The table sweeps an azimuth and its opposite in one pass where the window is
                // finite on a wrapping map (`far_field_fast`'s mirror); with curvature its
                // drop is then taken from the other end of the lines, which rounds otherwise
                // in f32 than a sweep of its own (as the planes and a spilled table run).
                let paired = edge == Edge::Wrap && radius.is_some() && curvature > 0.0;
                let (worst, at) = got
                    .iter()
                    .zip(&want)
                    .enumerate()
                    .map(|(i, (&a, &b))| {
                        (if a.to_bits() == b.to_bits() { 0.0 } else { (a - b).abs().max(1e-30) }, i)
                    })
                    .max_by(|a, b| a.0.total_cmp(&b.0))
                    .unwrap();
                let allowed = if paired { 1e-6 } else { 0.0 };
                assert!(
                    worst <= allowed,
                    "{w}×{h} {edge:?} R {radius:?} {isa:?} band {band} one thread {}: texel {} bin {}: {} vs {}",
                    pool.is_some(),
                    at / nb,
                    at % nb,
                    got[at],
                    want[at]
                );
                if paired && band == 1 {
                    eprintln!("{w}×{h} {edge:?} R {radius:?} {isa:?}: paired, {worst:e} at most");
                }
            }
        }
    }
}

/// A cancel stops the planes between azimuths or bands, with `Canceled`.
#[test]
fn canceled_planes_stop_with_canceled() {
    let mut rng = Rng(3);
    let hts = fbm(&mut rng, 64, 64, 30.0);
    let g = Grid::new(64, 64, &hts, Edge::Wrap, YAxis::Up);
    let opt = Options { azimuth_major: true, ..Options::default() };
    let k = Sweep::with_options(g, None, 32, Reduce::Average, opt);
    let p = Progress::new();
    let handed = std::sync::atomic::AtomicUsize::new(0);
    let r = k.planes(8, &p, |_, n, _| {
        if n == 3 {
            p.cancel();
        }
        handed.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    });
    assert!(matches!(r, Err(horizon_bake::Error::Canceled)), "{r:?}");
    let handed = handed.into_inner();
    assert!(handed < 32 * 8, "stopped early: {handed}");
}

/// A file spill goes to the directory it is given (the service hands it its data directory's
/// `tmp`, not a process-wide setting): one that cannot be made fails the put with its name.
#[test]
fn a_file_spill_uses_the_directory_it_is_given() {
    use horizon_bake::bake::FileSpill;
    use horizon_bake::kernels::sweep::FarSpill;
    let root = tempfile::tempdir().unwrap();
    let blocker = root.path().join("not-a-dir");
    std::fs::write(&blocker, b"x").unwrap();
    let bad = FileSpill::new(4, blocker.join("tmp"));
    let err = bad.put(0, 0, &[1.0; 4]).unwrap_err().to_string();
    assert!(err.contains("not-a-dir"), "{err}");
    let good = FileSpill::new(4, root.path().join("tmp"));
    good.put(1, 0, &[1.0, 2.0, 3.0, 4.0]).unwrap();
    let mut back = [0.0; 4];
    good.get(1, 0, &mut back).unwrap();
    assert_eq!(back, [1.0, 2.0, 3.0, 4.0]);
    assert!(root.path().join("tmp").is_dir(), "the directory is made on first use");
}

/// A spill store that fails makes the bake fail with the store's error, never hands on a band
/// made of what it could not read: a full disk is `Unavailable` (retried later), a read error
/// an I/O error.
#[test]
fn a_failing_spill_fails_the_bake() {
    use horizon_bake::kernels::run_bands;
    use std::sync::Arc;
    let mut rng = Rng(7);
    let hts = fbm(&mut rng, 40, 30, 30.0);
    let g = Grid::new(40, 30, &hts, Edge::Wrap, YAxis::Down);
    let bake = |store: MemSpill| {
        let opt = Options { spill: Some(Arc::new(store)), ..Options::default() };
        let k = Sweep::with_options(g, None, 32, Reduce::Average, opt);
        let handed = std::sync::atomic::AtomicUsize::new(0);
        let r = run_bands(&k, 4, false, &Progress::new(), |_, _| {
            handed.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        });
        (r, handed.into_inner())
    };
    let full = MemSpill { fail_put: Some(std::io::ErrorKind::StorageFull), ..MemSpill::default() };
    match bake(full) {
        (Err(horizon_bake::Error::Unavailable(m)), 0) => assert!(m.contains("no space"), "{m}"),
        (other, n) => panic!("a full disk: {other:?} after {n} bands"),
    }
    match bake(MemSpill { fail_get: true, ..MemSpill::default() }) {
        (Err(horizon_bake::Error::Io(e)), 0) => assert!(e.to_string().contains("far field"), "{e}"),
        (other, n) => panic!("a read error: {other:?} after {n} bands"),
    }
    let (ok, n) = bake(MemSpill::default());
    assert!(ok.is_ok() && n == 30usize.div_ceil(4), "{ok:?} {n}");
}

/// The bake itself hands `sweep` a temporary file once the table passes `MAX_TABLE_BYTES`
/// (726² at 256 bins: 515 MiB), and its layers are those of the kernel with the table in
/// memory.
#[test]
fn a_bake_past_the_memory_table_spills_and_keeps_its_values() {
    use horizon_bake::bake::bake_horizon;
    use horizon_bake::heightmap::HeightMap;
    use horizon_bake::kernels::compute_all;
    use horizon_bake::kernels::sweep::spills;
    use horizon_bake::layers::Precisions;
    let n = 726;
    assert!(spills(n as u32, n as u32, 256));
    let mut rng = Rng(0xb16);
    let hts = fbm(&mut rng, n, n, 20.0);
    let q = "method=sweep&radius=unlimited&edge=none&bins=256&reduce=point&height_scale=1";
    let p = BakeParams::from_pairs(q.split('&').map(|kv| kv.split_once('=').unwrap())).unwrap();
    let map = HeightMap::from_values(n, n, hts.clone()).unwrap();
    let (layers, _) =
        bake_horizon(&map, &p, Precisions { u8: false, u16: false, f32: true }, &Progress::new())
            .unwrap();
    let [l0, l1] = layers.f32.unwrap();
    let g = Grid::new(n, n, &hts, Edge::None, p.y_axis);
    let want = compute_all(&Sweep::new(g, None, 256, Reduce::Point), &Progress::new()).unwrap();
    let lit = want.iter().filter(|&&v| v > 0.01).count();
    assert!(lit > want.len() / 4, "the map casts horizons: {lit}");
    for (t, (a, b)) in want.chunks_exact(8).zip(l0.chunks_exact(4).zip(l1.chunks_exact(4))) {
        assert_eq!(&t[..4], a);
        assert_eq!(&t[4..], b);
    }
}
