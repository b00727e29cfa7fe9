//! The sweep kernel (`kernels::sweep`, SPEC §3.2a `method=sweep`): against `method=exact` at the
//! same radius for the sweep's tolerance (mean |Δα| ≤ 0.05°, p99 ≤ 0.25° per bin) on the eval
//! corpus, the real terrain excerpt and random rough, smooth and spiky maps (both edges, both y
//! axes, odd sizes), never above `exact`, and at its radius.
//!
//! Measured: corpus and terrain mean ≤ 0.001°, p99 ≤ 0.012° (worst: spikes, wrapped,
//! unlimited); random maps mean ≤ 0.009°, p99 ≤ 0.055° (worst: a 1 % spike field, 25×44
//! wrapped, R = 50). The windowed hull queries are checked against brute force in the
//! module's own unit test.

mod common;

use common::{mean_p99, waves, Rng};
use horizon_bake::eval::corpus;
use horizon_bake::kernels::exact::ExactHorizon;
use horizon_bake::kernels::sweep::Sweep;
use horizon_bake::kernels::{Grid, HorizonRows};
use horizon_bake::params::{Edge, Reduce, YAxis};

/// Per-bin sin α of every texel, in bands of 5 rows.
fn per_bin(k: &dyn HorizonRows) -> Vec<f32> {
    common::per_bin(k, 5)
}

/// Mean and p99 |Δα| (degrees) of the sweep against exact, and its largest overshoot in sin α.
fn against_exact(g: Grid<'_>, radius: Option<u32>) -> (f64, f64, f64) {
    let s = per_bin(&Sweep::new(g, radius, 32, Reduce::Average));
    let e = per_bin(&ExactHorizon::new(g, radius, 32, Reduce::Average));
    let over = s.iter().zip(&e).map(|(&a, &b)| a as f64 - b as f64).fold(f64::MIN, f64::max);
    let (mean, p99) = mean_p99(degrees_apart(&s, &e));
    (mean, p99, over)
}

/// |Δα| in degrees between two sets of sin α.
fn degrees_apart(a: &[f32], b: &[f32]) -> Vec<f64> {
    a.iter()
        .zip(b)
        .map(|(&a, &b)| ((a as f64).asin() - (b as f64).asin()).abs().to_degrees())
        .collect()
}

fn check(name: &str, g: Grid<'_>, radius: Option<u32>) {
    let (mean, p99, over) = against_exact(g, radius);
    eprintln!("{name} {:?} {radius:?}: mean {mean:.4}° p99 {p99:.4}° over {over:.1e}", g.edge);
    // Every value is exact's closed form on a stretch of the texel's own ray (f64) or exact's
    // own near field: at most f32 rounding above exact.
    assert!(over < 2e-5, "{name} {:?} {radius:?}: overshoots exact by {over}", g.edge);
    assert!(mean <= 0.05, "{name} {:?} {radius:?}: mean {mean}°", g.edge);
    assert!(p99 <= 0.25, "{name} {:?} {radius:?}: p99 {p99}°", g.edge);
}

#[test]
fn meets_its_tolerance_on_the_eval_corpus_and_real_terrain() {
    let mut maps = corpus::generated(64);
    let jacksboro =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("docs/corpus/jacksboro_128.png");
    maps.push(corpus::from_file("jacksboro", &jacksboro, 65535.0 / 90.0, 128).unwrap());
    for m in &maps {
        for edge in [Edge::Wrap, Edge::None] {
            let g = Grid::new(m.width, m.height, &m.heights, edge, YAxis::Up);
            for radius in [Some(16u32), Some(40), None] {
                check(&m.name, g, radius);
            }
        }
    }
}

#[test]
fn meets_its_tolerance_on_random_maps() {
    let mut rng = Rng(2024);
    for (i, (w, h)) in [(33usize, 29usize), (41, 17), (25, 44)].into_iter().enumerate() {
        for (kind, edge) in [
            ("white", Edge::Wrap),
            ("waves", Edge::None),
            ("spiky", Edge::Wrap),
            ("spiky", Edge::None),
            ("white", Edge::None),
        ] {
            let heights: Vec<f32> = match kind {
                "white" => (0..w * h).map(|_| rng.f32() * 12.0).collect(),
                "spiky" => (0..w * h)
                    .map(|_| if rng.f32() < 0.01 { 4.0 + 20.0 * rng.f32() } else { 0.0 })
                    .collect(),
                _ => waves(&mut rng, w, h, 3, 4.0),
            };
            let y_axis = if i % 2 == 0 { YAxis::Down } else { YAxis::Up };
            let g = Grid::new(w, h, &heights, edge, y_axis);
            for radius in [Some(5u32), Some(12), Some(50), None] {
                check(&format!("{kind} {w}×{h}"), g, radius);
            }
        }
    }
}

#[test]
fn an_occluder_beyond_the_radius_never_counts() {
    // A flat strip with one tall wall 30 texels east of column 0: seen at R = 31, not at R = 29
    // (nor by texels further than 29 from it), whatever the lattice line finds beyond R.
    let (w, h) = (80usize, 5usize);
    let mut heights = vec![0f32; w * h];
    for y in 0..h {
        heights[y * w + 30] = 20.0;
    }
    let g = Grid::new(w, h, &heights, Edge::None, YAxis::Up);
    let east = |radius| {
        let b = per_bin(&Sweep::new(g, Some(radius), 32, Reduce::Point));
        (0..w).map(|x| b[(2 * w + x) * 32]).collect::<Vec<f32>>()
    };
    let (near, far) = (east(31), east(29));
    assert!(near[0] > 0.5, "the wall at 30 is within 31: {}", near[0]);
    assert_eq!(far[0], 0.0, "the wall at 30 is beyond 29");
    for (x, &v) in far.iter().enumerate().take(30) {
        assert_eq!(v > 0.0, 30 - x <= 29, "texel {x}: {v}");
    }
}

#[test]
fn degenerate_maps_and_other_bin_counts_match_exact() {
    // One texel, one row, one column, 2×2; 16 and 64 bins; both edges, both y axes: the lines
    // are a single texel or wrap onto themselves at once.
    let mut rng = Rng(5);
    for (w, h) in [(1usize, 1usize), (1, 7), (7, 1), (2, 2), (3, 40)] {
        let heights: Vec<f32> = (0..w * h).map(|_| rng.f32() * 6.0).collect();
        for edge in [Edge::Wrap, Edge::None] {
            for y_axis in [YAxis::Up, YAxis::Down] {
                let g = Grid::new(w, h, &heights, edge, y_axis);
                for bins in [16u32, 64] {
                    for radius in [Some(1u32), Some(9), Some(100), None] {
                        let s = per_bin(&Sweep::new(g, radius, bins, Reduce::Point));
                        let e = per_bin(&ExactHorizon::new(g, radius, bins, Reduce::Point));
                        let name = format!("{w}×{h} {edge:?} {y_axis:?} {bins} bins R {radius:?}");
                        let over = s.iter().zip(&e).map(|(&a, &b)| a - b).fold(f32::MIN, f32::max);
                        assert!(over <= 2e-5, "{name}: sweep above exact by {over}");
                        let (mean, p99) = mean_p99(degrees_apart(&s, &e));
                        assert!(mean <= 0.05 && p99 <= 0.25, "{name}: mean {mean}° p99 {p99}°");
                    }
                }
            }
        }
    }
}

#[test]
fn a_radius_many_times_a_wrapped_map_changes_nothing_past_one_period() {
    // On a wrapped 32² map every lattice line repeats within 32 steps of at most 24 texels, so
    // beyond R ≈ 776 a longer radius only adds farther copies of what is already seen: the
    // sweep looks one period past its near field, not R, and gives the same values.
    let mut rng = Rng(77);
    let heights = waves(&mut rng, 32, 32, 3, 5.0);
    let g = Grid::new(32, 32, &heights, Edge::Wrap, YAxis::Up);
    let long = per_bin(&Sweep::new(g, Some(4096), 32, Reduce::Average));
    let shorter = per_bin(&Sweep::new(g, Some(1000), 32, Reduce::Average));
    assert_eq!(long, shorter);
    check("waves 32² (R far past the period)", g, Some(4096));
}
