//! `method=exact` throughput: prints a Markdown table (ms, Mtexel/s, ratio to the plain
//! cell-by-cell march measured in the same run).
//!
//! The plain march ([`ExactMarch`]) is far too slow for a whole 2048² map, so it is timed on a
//! crop of texels (its rays still run over the whole map) and scaled by the texel count; the
//! table says so. Input: deterministic fBm value noise in [0, 1] × `height_scale` 8 (the
//! default), a terrain-like map; a white-noise map is timed too, the worst case for skipping.
//!
//! Build once with `cargo bench --bench exact --no-run`, then run the binary it names.
//! Arguments: `[size] [radius] [point]` (default 2048, every radius; a radius outside the
//! usual set runs alone; `point` times `reduce=point`, which casts 8 of the 32 azimuths).
//! Finite radii also time the fast Lengyel kernel on the same map: the last column is its CPU
//! time over exact's (≥ 1 means exact is no slower). The "cpu ms" column is the process CPU
//! time (all threads, from /proc/self/stat): on a shared machine it is the fairer figure.
//! At the current speed the `unlimited` rows take minutes at 2048²; `1024 unlimited` is quicker.

use horizon_bake::kernels::exact::{ExactHorizon, ExactMarch};
use horizon_bake::kernels::lengyel::LengyelFast;
use horizon_bake::kernels::{compute_all, Grid};
use horizon_bake::params::{Edge, Reduce, YAxis};
use horizon_bake::progress::Progress;
use std::time::Instant;

mod common;

use common::{cpu_secs, fbm, white};

/// Seconds for the plain march over a `crop`×`crop` block of texels, scaled to the whole map.
fn plain_scaled(grid: Grid<'_>, radius: Option<u32>, bins: u32, crop: usize) -> f64 {
    let k = ExactMarch::new(grid, radius, bins, Reduce::Average);
    let mut s = vec![0f32; bins as usize];
    let t = Instant::now();
    let mut sink = 0f32;
    for y in 0..crop {
        for x in 0..crop {
            k.texel_bins(x * grid.width / crop, y * grid.height / crop, &mut s);
            sink += s[0];
        }
    }
    std::hint::black_box(sink);
    t.elapsed().as_secs_f64() * (grid.width * grid.height) as f64 / (crop * crop) as f64
}

fn main() {
    let n: usize = std::env::args().nth(1).and_then(|a| a.parse().ok()).unwrap_or(2048);
    // Optional second argument: only the rows whose radius is this ("unlimited" or a number).
    let only: Option<String> = std::env::args().nth(2);
    // Optional third argument `point`: `reduce=point`, which casts only the 8 channel azimuths.
    let reduce = match std::env::args().nth(3).as_deref() {
        Some("point") => Reduce::Point,
        _ => Reduce::Average,
    };
    let method = if reduce == Reduce::Point { "exact, reduce=point" } else { "exact" };
    let threads = rayon::current_num_threads();
    let scale = 8.0f32;
    println!("| map | method | size | radius | bins | threads | ms | cpu ms | Mtexel/s | Mtexel/s per cpu-s | × plain march | × fast lengyel, same R (cpu) |");
    println!("|---|---|---|---|---|---|---|---|---|---|---|---|");
    for (map_name, values) in [("fbm", fbm(n)), ("white", white(n))] {
        let heights: Vec<f32> = values.iter().map(|v| v * scale).collect();
        let grid = Grid::new(n, n, &heights, Edge::Wrap, YAxis::Up);
        let mut radii: Vec<Option<u32>> = if map_name == "fbm" {
            vec![None, Some(16), Some(32), Some(64)]
        } else {
            vec![None, Some(32)]
        };
        // Any other radius asked for on the command line runs on its own.
        if let Some(r) = only.as_deref().and_then(|o| o.parse::<u32>().ok()) {
            if !radii.contains(&Some(r)) {
                radii = vec![Some(r)];
            }
        }
        for &radius in &radii {
            let r = radius.map_or("unlimited".to_string(), |r| r.to_string());
            if only.as_ref().is_some_and(|o| *o != r) {
                continue;
            }
            let bins = 32u32;
            let (t, c0) = (Instant::now(), cpu_secs());
            let k = ExactHorizon::new(grid, radius, bins, reduce);
            let out = compute_all(&k, &Progress::new()).expect("not canceled");
            let secs = t.elapsed().as_secs_f64();
            let cpu = cpu_secs() - c0;
            std::hint::black_box(&out);
            // The finite-radius target is "no slower than lengyel at the same radius": the fast
            // Lengyel kernel on the same map, in the same run.
            let vs_lengyel = match radius {
                Some(r) => {
                    let c0 = cpu_secs();
                    let l = LengyelFast::new(grid, r, bins);
                    let out = compute_all(&l, &Progress::new()).expect("not canceled");
                    std::hint::black_box(&out);
                    let lc = cpu_secs() - c0;
                    format!("{:.2} (lengyel: {:.0} cpu ms)", lc / cpu.max(1e-3), lc * 1e3)
                }
                None => "–".to_string(),
            };
            let crop = if radius.is_none() { 16 } else { 48 };
            // The plain march always casts every bin; with `point` only 8 of them count.
            let cast = if reduce == Reduce::Point { 8.0 / bins as f64 } else { 1.0 };
            let plain = plain_scaled(grid, radius, bins, crop) * cast;
            println!(
                "| {map_name} | {method} | {n}² | {r} | {bins} | {threads} | {:.0} | {:.0} | {:.2} | {:.2} | {:.1} (plain: {crop}² crop, 1 thread, scaled{}: {:.0} ms) | {vs_lengyel} |",
                secs * 1e3,
                cpu * 1e3,
                (n * n) as f64 / secs / 1e6,
                (n * n) as f64 / cpu.max(1e-3) / 1e6,
                plain / secs,
                if cast < 1.0 { " to 8 bins" } else { "" },
                plain * 1e3
            );
        }
    }
}
