//! Symmetry properties of the horizon map (SPEC §2, §3.1), on the plain oracle `LengyelNaive`
//! through `kernels::compute_all`, over random maps and sizes (1×1, 1×N, N×1 and odd sizes
//! included), radii and both `y_axis` conventions.
//!
//! - Rotating the image 90° counter-clockwise (as displayed) turns every tangent-space direction
//!   by +90° when y points up, so channel c moves to c+2. With `y_axis=down` the tangent frame is
//!   mirrored against the screen, so the same on-screen rotation turns directions by −90° and
//!   channel c moves to c−2 (c+6) — equivalently a clockwise rotation moves c to c+2.
//! - Mirroring left-right maps azimuth φ to 180°−φ: channel c to (4−c) mod 8, in both conventions.
//! - Shifting a wrapped map shifts the output.
//! - A flat map has no horizon: all zeros.
//! - Raising `height_scale` scales every rise, so it never lowers a horizon value.

use horizon_bake::kernels::{compute_all, lengyel::LengyelNaive, Grid};
use horizon_bake::params::{Edge, YAxis};
use horizon_bake::progress::Progress;
use proptest::prelude::*;

/// Values equal up to f32/f64 rounding of the same arithmetic done in another order.
const TOL: f32 = 2e-6;

fn horizon(w: usize, h: usize, heights: &[f32], edge: Edge, y: YAxis, r: u32) -> Vec<f32> {
    let grid = Grid::new(w, h, heights, edge, y);
    compute_all(&LengyelNaive::new(grid, r, 32), &Progress::new()).expect("not canceled")
}

/// Rotates a row-major `w × h` image 90° counter-clockwise as displayed (rows go down): the
/// result is `h × w`, and its top-left texel is the source's top-right one.
fn rotate_ccw<T: Copy>(w: usize, h: usize, src: &[T]) -> Vec<T> {
    let (nw, nh) = (h, w);
    let mut out = Vec::with_capacity(src.len());
    for r in 0..nh {
        for c in 0..nw {
            // new (c, r) ← old (col = w−1−r, row = c)
            out.push(src[c * w + (w - 1 - r)]);
        }
    }
    out
}

fn texel(out: &[f32], w: usize, x: usize, y: usize) -> &[f32] {
    &out[(y * w + x) * 8..(y * w + x) * 8 + 8]
}

/// Heights in texels: random, with plateaus (equal heights) and steps mixed in.
fn map_strategy() -> impl Strategy<Value = (usize, usize, Vec<f32>)> {
    (1usize..=9, 1usize..=9).prop_flat_map(|(w, h)| {
        let cell = prop_oneof![0.0f32..8.0, Just(0.0f32), Just(3.0f32)];
        (Just(w), Just(h), proptest::collection::vec(cell, w * h))
    })
}

fn edge_strategy() -> impl Strategy<Value = Edge> {
    prop_oneof![Just(Edge::Wrap), Just(Edge::None)]
}

fn y_strategy() -> impl Strategy<Value = YAxis> {
    prop_oneof![Just(YAxis::Up), Just(YAxis::Down)]
}

fn assert_texels_match(got: &[f32], want: &[f32], what: &str) -> Result<(), TestCaseError> {
    for (k, (g, w)) in got.iter().zip(want).enumerate() {
        prop_assert!((g - w).abs() <= TOL, "{}: value {} is {}, expected {}", what, k, g, w);
    }
    Ok(())
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 96, .. ProptestConfig::default() })]

    #[test]
    fn rotating_ccw_moves_channels(
        (w, h, heights) in map_strategy(), edge in edge_strategy(), y in y_strategy(), r in 1u32..7,
    ) {
        let a = horizon(w, h, &heights, edge, y, r);
        let rot = rotate_ccw(w, h, &heights);
        let b = horizon(h, w, &rot, edge, y, r);
        // Where each source texel lands, and how channels move.
        let shift = match y { YAxis::Up => 2, YAxis::Down => 6 };
        for row in 0..h {
            for col in 0..w {
                let (nc, nr) = (row, w - 1 - col);
                let src = texel(&a, w, col, row);
                let dst = texel(&b, h, nc, nr);
                let moved: Vec<f32> = (0..8).map(|c| dst[(c + shift) % 8]).collect();
                assert_texels_match(&moved, src, &format!("texel ({col}, {row})"))?;
            }
        }
    }

    #[test]
    fn mirroring_left_right_reflects_channels(
        (w, h, heights) in map_strategy(), edge in edge_strategy(), y in y_strategy(), r in 1u32..7,
    ) {
        let a = horizon(w, h, &heights, edge, y, r);
        let mirrored: Vec<f32> =
            (0..h).flat_map(|row| (0..w).rev().map(move |col| (row, col))).map(|(row, col)| heights[row * w + col]).collect();
        let b = horizon(w, h, &mirrored, edge, y, r);
        for row in 0..h {
            for col in 0..w {
                let src = texel(&a, w, col, row);
                let dst = texel(&b, w, w - 1 - col, row);
                let moved: Vec<f32> = (0..8).map(|c| dst[(4 + 8 - c) % 8]).collect();
                assert_texels_match(&moved, src, &format!("texel ({col}, {row})"))?;
            }
        }
    }

    #[test]
    fn shifting_a_wrapped_map_shifts_the_output(
        (w, h, heights) in map_strategy(), y in y_strategy(), r in 1u32..7, dx in 0usize..9, dy in 0usize..9,
    ) {
        let a = horizon(w, h, &heights, Edge::Wrap, y, r);
        // shifted(col, row) = heights((col − dx) mod w, (row − dy) mod h)
        let mut shifted = vec![0.0f32; w * h];
        for row in 0..h {
            for col in 0..w {
                shifted[((row + dy) % h) * w + (col + dx) % w] = heights[row * w + col];
            }
        }
        let b = horizon(w, h, &shifted, Edge::Wrap, y, r);
        for row in 0..h {
            for col in 0..w {
                let src = texel(&a, w, col, row);
                let dst = texel(&b, w, (col + dx) % w, (row + dy) % h);
                prop_assert_eq!(src, dst, "texel ({}, {})", col, row);
            }
        }
    }

    #[test]
    fn a_flat_map_has_no_horizon(
        w in 1usize..=9, h in 1usize..=9, level in -100.0f32..100.0, edge in edge_strategy(),
        y in y_strategy(), r in 1u32..7,
    ) {
        let out = horizon(w, h, &vec![level; w * h], edge, y, r);
        prop_assert!(out.iter().all(|&v| v == 0.0), "non-zero horizon on a flat map");
    }

    #[test]
    fn larger_height_scale_never_lowers_a_horizon(
        (w, h, heights) in map_strategy(), edge in edge_strategy(), y in y_strategy(), r in 1u32..7,
        k1 in 0.0f32..4.0, factor in 1.0f32..4.0,
    ) {
        let k2 = k1 * factor;
        let s1: Vec<f32> = heights.iter().map(|v| v * k1).collect();
        let s2: Vec<f32> = heights.iter().map(|v| v * k2).collect();
        let a = horizon(w, h, &s1, edge, y, r);
        let b = horizon(w, h, &s2, edge, y, r);
        for (k, (lo, hi)) in a.iter().zip(&b).enumerate() {
            prop_assert!(*hi >= lo - TOL, "value {}: {} at scale {} but {} at scale {}", k, lo, k1, hi, k2);
        }
    }
}

/// The properties above would hold trivially for an all-zero kernel; make sure the random maps
/// do produce horizons, and that rotation is not also a symmetry of the channels themselves.
#[test]
fn random_maps_produce_nontrivial_horizons() {
    let heights: Vec<f32> = (0..5 * 3).map(|k| ((k * 7 % 11) as f32) * 0.8).collect();
    let out = horizon(5, 3, &heights, Edge::None, YAxis::Up, 4);
    assert!(out.iter().any(|&v| v > 0.3));
    let rot = horizon(3, 5, &rotate_ccw(5, 3, &heights), Edge::None, YAxis::Up, 4);
    // Without the channel shift the rotated output does not match.
    let differs = (0..3).any(|row| {
        (0..5).any(|col| {
            let a = texel(&out, 5, col, row);
            let b = texel(&rot, 3, row, 4 - col);
            a.iter().zip(b).any(|(x, y)| (x - y).abs() > 0.01)
        })
    });
    assert!(differs);
    // A single texel up: a 3×1 map with a bump on the right of texel 0 raises channel 0 only
    // among the axis channels.
    let out = horizon(3, 1, &[0.0, 5.0, 0.0], Edge::None, YAxis::Up, 2);
    let t0 = texel(&out, 3, 0, 0);
    assert!(t0[0] > 0.9 && t0[4] == 0.0, "{t0:?}");
}
