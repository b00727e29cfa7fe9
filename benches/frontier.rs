//! The accuracy frontier (issue "fast ray march, radius-independent sweep"): every horizon
//! method on one 2048² terrain-like map, in one run, as a Markdown table: ms, Mtexel/s, the
//! ratio to the fast Lengyel kernel at R = 16 measured in the same run, and the mean and p99
//! |Δα| (degrees, per azimuth bin) against `method=exact` at the same radius on the same map.
//!
//! The error needs the exact kernel on the same texels, which costs minutes at 2048², so it is
//! measured on a crop: the first `CROP_ROWS` rows (every column) of the same map, whose rays
//! still run over the whole map. `exact` itself is timed on that crop too and scaled by the
//! texel count; the table says so.
//!
//! Build once with `cargo bench --bench frontier --no-run`, then run the binary it names, or
//! `cargo bench --bench frontier`. Arguments: `[size]` (default 2048).

use horizon_bake::bake::FileSpill;
use horizon_bake::heightmap::hole_fill;
use horizon_bake::kernels::exact::ExactHorizon;
use horizon_bake::kernels::lengyel::LengyelFast;
use horizon_bake::kernels::march::March;
use horizon_bake::kernels::sweep::{FarSpill, Options, Sweep, NEAR_STEPS, SUB};
use horizon_bake::kernels::{compute_all, Grid, HorizonRows};
use horizon_bake::params::{Edge, Reduce, YAxis};
use horizon_bake::progress::Progress;
use std::sync::Arc;
use std::time::Instant;

/// Rows of the map whose per-bin values are compared with `exact` (and on which `exact` is
/// timed when it is not run whole).
const CROP_ROWS: usize = 8;

mod common;

use common::fbm;

/// Per-bin sin α of the first `rows` rows.
fn bins_of(k: &dyn HorizonRows, rows: usize) -> Vec<f32> {
    let (w, nb) = (k.width(), k.bins());
    let mut ch = vec![0f32; rows * w * 8];
    let mut bins = vec![0f32; rows * w * nb];
    k.rows(0, &mut ch, Some(&mut bins));
    bins
}

/// Per-bin sin α of row `y` alone.
fn rows_at(k: &dyn HorizonRows, y: usize) -> Vec<f32> {
    let (w, nb) = (k.width(), k.bins());
    let mut ch = vec![0f32; w * 8];
    let mut bins = vec![0f32; w * nb];
    k.rows(y, &mut ch, Some(&mut bins));
    bins
}

/// Nodata holes of an n² map as a reprojected DEM has them: everything outside a square
/// turned 17° whose corners touch the map's sides, and five round lakes inside; and the
/// heights with the holes filled as the bake fills them ([`hole_fill`]).
fn collar(n: usize, heights: &[f32]) -> (Vec<bool>, Vec<f32>) {
    let (c, (sin, cos)) = ((n as f64 - 1.0) / 2.0, 17f64.to_radians().sin_cos());
    let half = n as f64 / (cos + sin) / 2.0;
    let lakes = [(0.4, 0.45, 0.03), (0.6, 0.3, 0.02), (0.55, 0.65, 0.04), (0.3, 0.6, 0.015)];
    let holes: Vec<bool> = (0..n * n)
        .map(|k| {
            let (x, y) = ((k % n) as f64 - c, (k / n) as f64 - c);
            let (u, v) = (x * cos + y * sin, -x * sin + y * cos);
            let lake = lakes.iter().chain(&[(0.5, 0.5, 0.01)]).any(|&(lx, ly, r)| {
                let (dx, dy) = (x + c - lx * n as f64, y + c - ly * n as f64);
                dx.hypot(dy) < r * n as f64
            });
            u.abs() > half || v.abs() > half || lake
        })
        .collect();
    let valid = heights.iter().zip(&holes).filter(|(_, &o)| !o).map(|(&v, _)| v);
    let (lo, hi) = valid.fold((f32::MAX, f32::MIN), |(a, b), v| (a.min(v), b.max(v)));
    let fill = hole_fill(lo, hi);
    let filled = heights.iter().zip(&holes).map(|(&v, &o)| if o { fill } else { v }).collect();
    (holes, filled)
}

/// Mean and p99 |Δα| in degrees.
fn errors(got: &[f32], want: &[f32]) -> (f64, f64) {
    let mut d: Vec<f64> = got
        .iter()
        .zip(want)
        .map(|(&a, &b)| ((a as f64).asin() - (b as f64).asin()).abs().to_degrees())
        .collect();
    let mean = d.iter().sum::<f64>() / d.len() as f64;
    d.sort_by(f64::total_cmp);
    (mean, d[((d.len() as f64 * 0.99) as usize).min(d.len() - 1)])
}

fn time(k: &dyn HorizonRows) -> f64 {
    let t = Instant::now();
    let out = compute_all(k, &Progress::new()).expect("not canceled");
    std::hint::black_box(&out);
    t.elapsed().as_secs_f64()
}

/// A rough map for the error columns: 512² periodic fBm whose finest octave is 2 texels,
/// scaled to a median slope of about 30° (the smooth bench map alone would flatter every method).
fn rough_map() -> Vec<f32> {
    fbm(ROUGH).iter().map(|v| v * 48.0).collect()
}

/// Side of the rough map.
const ROUGH: usize = 512;

fn main() {
    let n: usize =
        std::env::args().skip(1).find_map(|a| a.parse().ok()).unwrap_or(2048).max(CROP_ROWS);
    let threads = rayon::current_num_threads();
    let heights: Vec<f32> = fbm(n).iter().map(|v| v * 8.0).collect();
    let grid = Grid::new(n, n, &heights, Edge::Wrap, YAxis::Up);
    let rough_h = rough_map();
    let rough = Grid::new(ROUGH, ROUGH, &rough_h, Edge::Wrap, YAxis::Up);
    let bins = 32u32;
    let texels = (n * n) as f64;
    let crop = (CROP_ROWS * n) as f64;
    println!("fBm value noise {n}², height_scale 8, edge=wrap, {bins} bins, {threads} threads.");
    println!(
        "Errors: per bin against `exact` at the same radius, on the first {CROP_ROWS} rows of \
         the smooth bench map and of a rough {ROUGH}² fBm (finest octave 2 texels, ×48).\n"
    );
    println!(
        "| method | R | ms | Mtexel/s | × lengyel R16 (same run) | mean Δα smooth | p99 smooth \
         | mean Δα rough | p99 rough | note |"
    );
    println!("|---|---|---:|---:|---:|---:|---:|---:|---:|---|");
    let lengyel = LengyelFast::new(grid, 16, bins);
    let base = time(&lengyel);
    let fmt = |e: Option<(f64, f64)>| {
        e.map_or(("–".to_string(), "–".to_string()), |(m, p)| {
            (format!("{m:.4}°"), format!("{p:.4}°"))
        })
    };
    let row = |method: &str,
               r: &str,
               secs: f64,
               err: Option<(f64, f64)>,
               err_rough: Option<(f64, f64)>,
               note: &str| {
        let (m, p) = fmt(err);
        let (mr, pr) = fmt(err_rough);
        println!(
            "| {method} | {r} | {:.0} | {:.2} | {:.2} | {m} | {p} | {mr} | {pr} | {note} |",
            secs * 1e3,
            texels / secs / 1e6,
            base / secs
        );
    };
    let exact_crop = |g: Grid<'_>, r: Option<u32>| {
        bins_of(&ExactHorizon::new(g, r, bins, Reduce::Average), CROP_ROWS)
    };
    let exact16 = exact_crop(grid, Some(16));
    let exact16_rough = exact_crop(rough, Some(16));
    row(
        "lengyel (fast)",
        "16",
        base,
        Some(errors(&bins_of(&lengyel, CROP_ROWS), &exact16)),
        Some(errors(&bins_of(&LengyelFast::new(rough, 16, bins), CROP_ROWS), &exact16_rough)),
        "the baseline; a splat, not a line of sight",
    );
    for r in [16u32, 64] {
        let k = March::new(grid, r, bins, Reduce::Average);
        let secs = time(&k);
        let want = if r == 16 { exact16.clone() } else { exact_crop(grid, Some(r)) };
        let kr = March::new(rough, r, bins, Reduce::Average);
        let want_r = exact_crop(rough, Some(r));
        let note = format!("{:.1} samples per ray", k.samples_per_ray());
        row(
            "march",
            &r.to_string(),
            secs,
            Some(errors(&bins_of(&k, CROP_ROWS), &want)),
            Some(errors(&bins_of(&kr, CROP_ROWS), &want_r)),
            &note,
        );
    }
    // A sweep timed on the bench map (its build included), its errors on both maps, and where
    // the time went: the build is the far field's sweeps, the bands the near field and joins.
    let sweep = |g: Grid<'_>, rg: Grid<'_>, r: Option<u32>| {
        let t = Instant::now();
        let k = Sweep::new(g, r, bins, Reduce::Average);
        let built = t.elapsed().as_secs_f64();
        let out = compute_all(&k, &Progress::new()).expect("not canceled");
        std::hint::black_box(&out);
        let secs = t.elapsed().as_secs_f64();
        drop(out);
        let err = errors(&bins_of(&k, CROP_ROWS), &exact_crop(g, r));
        drop(k);
        let kr = Sweep::new(rg, r, bins, Reduce::Average);
        let err_r = errors(&bins_of(&kr, CROP_ROWS), &exact_crop(rg, r));
        let split = format!(
            "build (far field) {:.0} ms + bands {:.0} ms",
            built * 1e3,
            (secs - built) * 1e3
        );
        (secs, err, err_r, split)
    };
    for r in [Some(64u32), Some(256), None] {
        let (secs, err, err_r, split) = sweep(grid, rough, r);
        let name = r.map_or("unlimited".to_string(), |r| r.to_string());
        let note = format!("near field {NEAR_STEPS} steps, {SUB} sub-lines; {split}");
        row("sweep", &name, secs, Some(err), Some(err_r), &note);
    }
    {
        // `edge=none` (a DEM's edge): one plain hull per line at `unlimited`, no suffix and
        // prefix passes, so the cheapest case of the far field.
        let grid_none = Grid::new(n, n, &heights, Edge::None, YAxis::Up);
        let rough_none = Grid::new(ROUGH, ROUGH, &rough_h, Edge::None, YAxis::Up);
        let (secs, err, err_r, split) = sweep(grid_none, rough_none, None);
        row("sweep, edge=none", "unlimited", secs, Some(err), Some(err_r), &split);
    }
    {
        // A DEM's nodata, as a reprojection leaves it: a collar around a square turned 17°
        // (36 % of the map) and a few lakes of holes inside, filled far below as the bake
        // fills them, `edge=none`. `sweep` honours the holes itself (the crossing walk drops
        // the cells that touch one); `exact` (the scalar walk with holes) is timed on every
        // 64th row, which cross the collar as the map does, and scaled.
        let (holes, filled) = collar(n, &heights);
        let g = Grid::new(n, n, &filled, Edge::None, YAxis::Up);
        let t = Instant::now();
        let k = Sweep::new(g, None, bins, Reduce::Average).with_holes(Some(&holes));
        let out = compute_all(&k, &Progress::new()).expect("not canceled");
        std::hint::black_box(&out);
        let secs = t.elapsed().as_secs_f64();
        drop(out);
        let exact = ExactHorizon::new(g, None, bins, Reduce::Average).with_holes(Some(&holes));
        let sample: Vec<usize> = (0..n).step_by(64.min(n)).collect();
        let (mut got, mut want) = (Vec::new(), Vec::new());
        let mut exact_secs = 0.0;
        for &y in &sample {
            let a = rows_at(&k, y);
            let t = Instant::now();
            let b = rows_at(&exact, y);
            exact_secs += t.elapsed().as_secs_f64();
            for x in (0..n).filter(|&x| !holes[y * n + x]) {
                got.extend_from_slice(&a[x * bins as usize..][..bins as usize]);
                want.extend_from_slice(&b[x * bins as usize..][..bins as usize]);
            }
        }
        let exact_secs = exact_secs * n as f64 / sample.len() as f64 / threads as f64;
        let share = holes.iter().filter(|&&o| o).count() as f64 / texels;
        let note = format!(
            "{:.0} % nodata (a collar and lakes), edge=none; errors off the holes on every 64th \
             row; `exact` with the holes: {:.0} ms (timed on those rows, 1 thread, scaled), \
             so sweep is {:.1}× exact",
            share * 100.0,
            exact_secs * 1e3,
            exact_secs / secs
        );
        row("sweep, holes", "unlimited", secs, Some(errors(&got, &want)), None, &note);
    }
    {
        // The same bake with its far field in a temporary file, as a map whose table passes
        // `MAX_TABLE_BYTES` gets it: the cost of the disk's round trip (the values are the same
        // bits, `tests/kernels/sweep.rs`).
        let t = Instant::now();
        let spill =
            Some(Arc::new(FileSpill::new(n * n, std::env::temp_dir())) as Arc<dyn FarSpill>);
        let opt = Options { spill, ..Options::default() };
        let k = Sweep::with_options(grid, None, bins, Reduce::Average, opt);
        let out = compute_all(&k, &Progress::new()).expect("not canceled");
        std::hint::black_box(&out);
        let secs = t.elapsed().as_secs_f64();
        let note = format!(
            "far field in a file in {} ({} MiB), build included",
            std::env::temp_dir().display(),
            (n * n * bins as usize * 4) >> 20
        );
        row("sweep, spilled", "unlimited", secs, None, None, &note);
    }
    for r in [Some(16u32), None] {
        let k = ExactHorizon::new(grid, r, bins, Reduce::Average);
        let t = Instant::now();
        let out = bins_of(&k, CROP_ROWS);
        std::hint::black_box(&out);
        // One thread did the crop (`rows` is called directly); the whole map would use all.
        let secs = t.elapsed().as_secs_f64() * texels / crop / threads as f64;
        let name = r.map_or("unlimited".to_string(), |r| r.to_string());
        row(
            "exact",
            &name,
            secs,
            Some((0.0, 0.0)),
            Some((0.0, 0.0)),
            &format!("timed on {CROP_ROWS}×{n}, 1 thread, scaled to {n}² and {threads} threads"),
        );
    }
}
