//! The fast Lengyel kernel against the plain oracle on random maps, and cancellation of a bake.
//!
//! Agreement means: every f32 channel within 1e-5, every per-bin value within 1e-5, and every
//! 8-bit sample identical unless the oracle's value sits within 1e-5 of a rounding tie
//! (v·255 + 0.5 near an integer), where f32 and f64 may legitimately round apart.

use crate::support::Rng;
use horizon_bake::bake::{self, Precisions};
use horizon_bake::encode::quantize8;
use horizon_bake::heightmap::HeightMap;
use horizon_bake::kernels::isa::Isa;
use horizon_bake::kernels::lengyel::LengyelFast;
use horizon_bake::kernels::lengyel::LengyelNaive;
use horizon_bake::kernels::{compute_all, Grid, HorizonRows};
use horizon_bake::params::{BakeParams, Edge, YAxis};
use horizon_bake::progress::{Progress, Stage};
use horizon_bake::Error;

/// Random heights: smooth-ish noise, or sparse tall spikes over a low floor.
fn heights(rng: &mut Rng, w: usize, h: usize, spiky: bool) -> Vec<f32> {
    let amp = 1.0 + 20.0 * rng.f32();
    (0..w * h)
        .map(|_| {
            if spiky {
                if rng.f32() < 0.05 {
                    amp * (1.0 + rng.f32())
                } else {
                    0.1 * rng.f32()
                }
            } else {
                amp * rng.f32()
            }
        })
        .collect()
}

/// Whether `v` lies within `eps` of an 8-bit rounding tie (v·255 + 0.5 an integer).
fn near_tie(v: f32, eps: f64) -> bool {
    let x = v as f64 * 255.0 + 0.5;
    (x - x.round()).abs() <= eps * 255.0
}

fn per_bin<K: HorizonRows>(k: &K) -> Vec<f32> {
    let (w, h, b) = (k.width(), k.height(), k.bins());
    let mut ch = vec![0.0f32; w * h * 8];
    let mut bins = vec![0.0f32; w * h * b];
    k.rows(0, &mut ch, Some(&mut bins));
    bins
}

/// Compares fast and oracle on one configuration; returns the number of tie-excused bytes.
fn check(w: usize, h: usize, hs: &[f32], edge: Edge, y_axis: YAxis, r: u32, b: u32) -> usize {
    let ctx = format!("{w}x{h} R={r} B={b} {edge:?} {y_axis:?}");
    let g = Grid::new(w, h, hs, edge, y_axis);
    let oracle = LengyelNaive::new(g, r, b);
    let fast = LengyelFast::new(g, r, b);
    let want = compute_all(&oracle, &Progress::new()).unwrap();
    let got = compute_all(&fast, &Progress::new()).unwrap();
    assert_eq!(got.len(), want.len(), "{ctx}");
    let mut ties = 0;
    for (k, (&a, &o)) in got.iter().zip(&want).enumerate() {
        assert!((a - o).abs() <= 1e-5, "{ctx}: value {k}: fast {a} oracle {o}");
        if quantize8(a) != quantize8(o) {
            assert!(near_tie(o, 1e-5), "{ctx}: byte {k}: fast {a} oracle {o} not a tie");
            ties += 1;
        }
    }
    let (wb, gb) = (per_bin(&oracle), per_bin(&fast));
    for (k, (&a, &o)) in gb.iter().zip(&wb).enumerate() {
        assert!((a - o).abs() <= 1e-5, "{ctx}: bin value {k}: fast {a} oracle {o}");
    }
    ties
}

#[test]
fn fast_matches_oracle_on_random_maps() {
    let mut rng = Rng(0x5eed_1e96);
    let mut ties = 0;
    let mut bytes = 0;
    let fixed: [(usize, usize); 8] =
        [(1, 1), (1, 9), (9, 1), (1, 40), (33, 1), (2, 2), (17, 5), (3, 31)];
    for case in 0..60 {
        let (w, h) =
            if case < fixed.len() { fixed[case] } else { (rng.range(1, 70), rng.range(1, 45)) };
        // Radii from 1 to well past the map size (the padding must wrap several times).
        let r = match case % 4 {
            0 => rng.range(1, 4),
            1 => rng.range(4, 12),
            2 => (w.max(h) + rng.range(1, 20)) as u32 as usize,
            _ => rng.range(1, 24),
        } as u32;
        let b = [16u32, 32, 48, 64][rng.range(0, 3)];
        let edge = if rng.range(0, 1) == 0 { Edge::Wrap } else { Edge::None };
        let y_axis = if rng.range(0, 1) == 0 { YAxis::Up } else { YAxis::Down };
        let hs = heights(&mut rng, w, h, case % 3 == 0);
        ties += check(w, h, &hs, edge, y_axis, r, b);
        bytes += w * h * 8;
    }
    // Ties are rare: a handful at most among tens of thousands of samples.
    assert!(ties * 1000 <= bytes, "{ties} tie bytes of {bytes}");
}

#[test]
fn fast_matches_oracle_on_flat_and_extreme_heights() {
    // Flat maps are all zero; huge height steps saturate s at 1 without NaN.
    let flat = vec![5.0f32; 13 * 11];
    let g = Grid::new(13, 11, &flat, Edge::None, YAxis::Up);
    let got = compute_all(&LengyelFast::new(g, 7, 32), &Progress::new()).unwrap();
    assert!(got.iter().all(|&v| v == 0.0));

    let mut hs = vec![-1.0e30f32; 9 * 8];
    hs[4 * 9 + 4] = 3.0e38;
    hs[0] = -3.0e38;
    for edge in [Edge::Wrap, Edge::None] {
        check(9, 8, &hs, edge, YAxis::Up, 6, 32);
        let g = Grid::new(9, 8, &hs, edge, YAxis::Up);
        let got = compute_all(&LengyelFast::new(g, 6, 32), &Progress::new()).unwrap();
        assert!(got.iter().all(|v| v.is_finite() && (0.0..=1.0).contains(v)));
    }
}

#[test]
fn every_cpu_variant_matches_the_oracle() {
    let mut rng = Rng(42);
    let (w, h) = (71, 13);
    let hs = heights(&mut rng, w, h, false);
    let g = Grid::new(w, h, &hs, Edge::None, YAxis::Down);
    let want = compute_all(&LengyelNaive::new(g, 10, 64), &Progress::new()).unwrap();
    for isa in [Isa::Baseline, Isa::Avx2, Isa::Avx512] {
        let got = compute_all(&LengyelFast::with_isa(g, 10, 64, isa), &Progress::new()).unwrap();
        let worst = got.iter().zip(&want).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
        assert!(worst <= 1e-5, "{isa:?}: {worst}");
    }
}

#[test]
fn bake_through_the_fast_path_matches_the_oracle_bytes() {
    let mut rng = Rng(7);
    let (w, h) = (50, 37);
    let values: Vec<f32> = (0..w * h).map(|_| rng.f32()).collect();
    let map = HeightMap::from_values(w, h, values).unwrap();
    let params = BakeParams::from_pairs([("radius", "9"), ("height_scale", "6")]).unwrap();
    let (layers, _) = bake::bake_horizon(&map, &params, Precisions::ALL, &Progress::new()).unwrap();
    let hs = map.scaled(params.height_scale);
    let g = Grid::new(w, h, &hs, params.edge, params.y_axis);
    let want = compute_all(&LengyelNaive::new(g, 9, params.bins), &Progress::new()).unwrap();
    let got = bake::layers_to_channels(layers.f32.as_ref().unwrap());
    let u8s = layers.u8.as_ref().unwrap();
    for (k, (&a, &o)) in got.iter().zip(&want).enumerate() {
        assert!((a - o).abs() <= 1e-5, "value {k}");
        let (t, c) = (k / 8, k % 8);
        let byte = u8s[c / 4][t * 4 + c % 4];
        if !near_tie(o, 1e-5) {
            assert_eq!(byte, quantize8(o), "byte of value {k}");
        }
    }
}

#[test]
fn cancel_from_another_thread_stops_the_bake_early() {
    let (w, h) = (512, 2048);
    let mut rng = Rng(99);
    let values: Vec<f32> = (0..w * h).map(|_| rng.f32()).collect();
    let map = HeightMap::from_values(w, h, values).unwrap();
    let params = BakeParams::from_pairs([("radius", "48")]).unwrap();
    let progress = Progress::new();
    let watcher = progress.clone();
    let canceller = std::thread::spawn(move || {
        // Cancel as soon as the bake has made some progress.
        loop {
            let (done, _) = watcher.counts();
            if watcher.stage() == Stage::Bake && done > 0 {
                watcher.cancel();
                return done;
            }
            std::thread::yield_now();
        }
    });
    let res = bake::bake_horizon(&map, &params, Precisions::U8, &progress);
    let seen_at_cancel = canceller.join().unwrap();
    assert!(matches!(res, Err(Error::Canceled)), "expected Canceled, got {:?}", res.map(|_| ()));
    let (done, total) = progress.counts();
    assert_eq!(total, h as u64);
    assert!(seen_at_cancel > 0);
    // Bands already running finish, then no new band starts: far fewer rows than the map.
    assert!(done < total / 2, "{done} of {total} rows done after cancel");
}
