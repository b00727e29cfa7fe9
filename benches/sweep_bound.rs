//! What a line sweep over lines through texel centres can reach (issue "fast ray march,
//! radius-independent sweep", `method=sweep`, SPEC §3.2a: mean |Δα| ≤ 0.05°, p99 ≤ 0.25°
//! against `exact`).
//!
//! A sweep is radius-independent because many texels share one line: walking the line once,
//! a hull of what lies ahead answers every texel on it. A line shares texel centres only when
//! its direction is a lattice vector (q, p), and a texel costs about q + p crossings of the
//! surface per azimuth, so q + p must stay small. The 32 bin azimuths are not lattice
//! directions (tan 11.25° = 0.1989…, whose next good approximation after 1/5 is 36/181), so
//! such a sweep answers at the nearest lattice azimuth instead. This bench measures that error
//! alone, with the *exact* kernel at both azimuths: a sweep that *measures* the horizon on the
//! lattice line, whatever its hull or SIMD, cannot do better than this on these maps. Lines
//! that are not texel-centred instead (shared lines at the exact azimuth, interpolated between
//! neighbouring lines) miss a thin occluder by up to half its height, which is worse on the
//! spikes. `kernels::sweep` therefore uses the lattice line only to *locate* the far occluder
//! and measures it on the texel's own ray, which meets the tolerance (`tests/sweep.rs`).
//!
//! Maps: the eval's generated corpus at 64² and the real-terrain excerpt, as the tolerance
//! tests of `method=march` read them, plus the random white-noise and spike fields of those
//! tests. Run: `cargo bench --bench sweep_bound` (about 15 s); argument: the largest
//! q + p allowed (default: 8, 24 and 64 in turn).

use horizon_bake::eval::corpus;
use horizon_bake::kernels::exact::ExactHorizon;
use horizon_bake::kernels::Grid;
use horizon_bake::params::{Edge, Reduce, YAxis};
use std::f64::consts::PI;

mod common;

use common::splitmix;

/// The lattice direction (q, p), |q| + |p| ≤ `n`, nearest in azimuth to `phi`, as an azimuth.
fn lattice_azimuth(phi: f64, n: i64) -> f64 {
    let mut best = (f64::MAX, phi);
    for q in -n..=n {
        for p in -(n - q.abs())..=(n - q.abs()) {
            if (q, p) == (0, 0) {
                continue;
            }
            let a = (p as f64).atan2(q as f64);
            let d = ((a - phi + PI).rem_euclid(2.0 * PI) - PI).abs();
            if d < best.0 {
                best = (d, a);
            }
        }
    }
    best.1
}

fn mean_p99(mut d: Vec<f64>) -> (f64, f64) {
    let mean = d.iter().sum::<f64>() / d.len() as f64;
    d.sort_by(f64::total_cmp);
    (mean, d[((d.len() as f64 * 0.99) as usize).min(d.len() - 1)])
}

fn main() {
    let limits: Vec<i64> = match std::env::args().skip(1).find_map(|a| a.parse().ok()) {
        Some(n) => vec![n],
        None => vec![8, 24, 64],
    };
    let mut maps = corpus::generated(64);
    let jacksboro =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("docs/corpus/jacksboro_128.png");
    maps.push(corpus::from_file("jacksboro", &jacksboro, 65535.0 / 90.0, 128).expect("corpus"));
    let mut seed = 99u64;
    let mut unit = || (splitmix(&mut seed) >> 40) as f32 / (1u64 << 24) as f32;
    let (w, h) = (41usize, 37usize);
    let white = (0..w * h).map(|_| 12.0 * unit()).collect();
    maps.push(corpus::Map { name: "white noise ×12".into(), width: w, height: h, heights: white });
    let spiky = (0..w * h).map(|_| if unit() < 0.01 { 4.0 + 20.0 * unit() } else { 0.0 }).collect();
    maps.push(corpus::Map { name: "spike field 1%".into(), width: w, height: h, heights: spiky });
    let bins = 32usize;
    let phis: Vec<f64> = (0..bins).map(|k| k as f64 * 2.0 * PI / bins as f64).collect();
    println!("Exact horizon at the nearest lattice azimuth against exact at the bin azimuth,");
    println!("per bin, 32 bins, y_axis=up. The sweep tolerance is mean 0.05°, p99 0.25°.\n");
    println!("| q + p ≤ | worst azimuth snap | map | edge | radius | mean Δα | p99 Δα | within |");
    println!("|---:|---:|---|---|---|---:|---:|---|");
    for &n in &limits {
        let snapped: Vec<f64> = phis.iter().map(|&p| lattice_azimuth(p, n)).collect();
        let worst = phis
            .iter()
            .zip(&snapped)
            .map(|(a, b)| ((a - b + PI).rem_euclid(2.0 * PI) - PI).abs().to_degrees())
            .fold(0.0f64, f64::max);
        for m in &maps {
            for edge in [Edge::Wrap, Edge::None] {
                for radius in [Some(16u32), None] {
                    let g = Grid::new(m.width, m.height, &m.heights, edge, YAxis::Up);
                    let k = ExactHorizon::new(g, radius, bins as u32, Reduce::Average);
                    let mut d = Vec::with_capacity(m.width * m.height * bins);
                    let mut s = vec![0f32; bins];
                    for y in 0..m.height {
                        for x in 0..m.width {
                            k.texel_bins(x, y, &mut s);
                            for (b, &v) in s.iter().enumerate() {
                                let a = k.horizon_sin(x, y, snapped[b]);
                                d.push((a.asin() - f64::from(v).asin()).abs().to_degrees());
                            }
                        }
                    }
                    let (mean, p99) = mean_p99(d);
                    let r = radius.map_or("unlimited".into(), |r| r.to_string());
                    let ok = if mean <= 0.05 && p99 <= 0.25 { "yes" } else { "**no**" };
                    println!(
                        "| {n} | {worst:.3}° | {} | {edge:?} | {r} | {mean:.4}° | {p99:.4}° | {ok} |",
                        m.name
                    );
                }
            }
        }
    }
}
