//! `method=sweep` (SPEC §3.2a): the line-of-sight horizon of §3.2 at any radius, `unlimited`
//! included, at a cost per texel that does not grow with R.
//!
//! # Two fields joined by max
//! - **Near field**, 0 < s ≤ [`NEAR`] major-axis steps (N·√(1 + m²) texels of arc, clipped to
//!   R): exact, on the texel's own ray ([`NearField`]: 16 texels of a row in lockstep; the
//!   ray's values at its grid-line crossings, and a piece within a cell solved in closed form,
//!   the per-cell quadratic maximum with the curvature drop as a term of it, wherever the
//!   cell's twist can lift the surface above the chord enough to matter). Near the texel the
//!   azimuth of a sample matters most; sampling only grid-line crossings there would miss the
//!   bilinear saddle inside a cell, which the closed form does not.
//! - **Far field**, beyond: per azimuth, lines parallel to it. The major axis (the one the
//!   azimuth moves along faster) steps one texel; the minor coordinate moves by the slope
//!   m ∈ [−1, 1]. [`SUB`] families of lines sit at minor intercepts k/SUB; a sample of a line at
//!   a major grid line is the bilinear surface there, a lerp of two texels of that grid line
//!   whose weight is the same for every line of a family in a column. Each line is swept from
//!   its far end against the look direction keeping the upper convex hull of its samples at
//!   least N steps ahead of the current position (pushed with a delay of N; amortised O(1) push
//!   and pop), and each texel asks the hulls of the two lines on either side of it (each at
//!   most 1/SUB of a texel away across) for the tangent from its own height, and interpolates
//!   the two by its place between them: the lateral error cancels to first order (measured on
//!   fBm 45°: p99 0.31° with the nearest line alone, 0.10° interpolated, both with [`MIDS`]).
//!
//! The result is max(near, far, the point at exactly R on the texel's own ray) as tan α,
//! stored as sin α. The near field is exact; the far field measures points up to 1/SUB of a
//! texel beside the ray and only at grid lines, which on terrain moves the horizon by
//! hundredths of a degree (`tests/sweep.rs`), and on fields of single-texel spikes by degrees
//! (a spike's flank of slope 24 is 3 texels high an eighth of a texel aside): the stated worst
//! case in the README. The interpolation may also put a value slightly above `exact`.
//!
//! # Radius
//! `unlimited` with `edge=none` is one plain hull per line. A finite R (and `unlimited` with
//! `edge=wrap`, which §3.2 makes max(W, H)) must drop occluders beyond it, which a hull cannot
//! do; blocked hulls honour it exactly: the samples of a line are cut into blocks of
//! B = R' − N + 1 steps (R' = the steps within R), so the window [u + N, u + R'] of a query at
//! u is a suffix of one block and a prefix of the next. A right-to-left pass resets its hull at
//! every block boundary (the suffix), a left-to-right pass builds prefix hulls (queried by
//! binary search); the tangent is the larger of the two. So an occluder beyond R never counts.
//!
//! Opposite azimuths share those passes where they can ([`azimuth_lines`]): a window
//! [s, s + R' − N] of a line is the window of a query at s − N looking one way and of one at
//! s + R' looking the other, so with `edge=wrap` the opposite azimuth's lines are taken to be
//! these lines read backwards ([`Lines::mirror`]), each azimuth's texels queried where on the
//! line (a multiple of W apart: the same texels on a wrapping map) their windows coincide or
//! overlap most ([`mirror_end`]), and one suffix and one prefix pass answer both azimuths,
//! each pass walking one query from the top of its hull and one from the bottom.
//!
//! # Earth curvature
//! A point s texels away is lowered by c·s². Along a line with origin-free coordinate x (major
//! steps, c' = c·L² per step², L = √(1 + m²)), the drop from the query at x to x' is
//! c'(x' − x)², and (h(x') − c'(x' − x)² − h0)/(x' − x) = (g(x') − (h0 − c'x²))/(x' − x) + 2c'x
//! with g(x') = h(x') − c'x'²: a tangent query on the fixed hull of g, in f64 (in f32 on the
//! vector path, see below).
//!
//! # Holes
//! Maps with nodata holes are baked by `exact` instead (see `bake::make_kernel_for`): the
//! sweep's lines would need their samples touching a hole skipped, and so far they are not.
//!
//! # Memory, order and speed
//! The far field is computed when the kernel is built, per azimuth in parallel (a cancel is
//! seen between azimuths), one f32 per texel and bin (4·bins bytes per texel: 0.5 GiB at
//! 2048², 32 bins); the bands then run the near field and join the two. The sweeps make the
//! table azimuth by azimuth (a whole plane each) and the bands read it row by row (every bin
//! of a few rows), so all of it exists between the two. Up to [`MAX_TABLE_BYTES`] it stays in
//! memory; beyond, the bake hands the kernel a [`FarSpill`] (a temporary file: the kernel
//! itself does no I/O) that takes each plane as it is swept and gives each band its rows, and
//! the build sweeps one major axis at a time with as many azimuths at once as
//! `SPILL_SWEEP_BYTES` allows. So the memory is the map, its padded major lines, the planes in
//! flight (up to 3 of W·H each) and a band: about 1.3 GB at 8192², whatever the bins; the disk
//! holds the table. Bigger than [`MAX_SPILL_BYTES`] is refused by [`check_memory`]. The bake's
//! progress only moves once the bands start.
//!
//! On a CPU with AVX-512, the sweeps run 16 lines of a family in lockstep
//! ([`far_field_fast`], f32): the 16 samples of a column are one contiguous lerp of a padded
//! copy of the map's major lines ([`MajorLines`]); each lane's hull is a stack whose three
//! nearest vertices live in registers (so most pops and tangent steps touch no memory) and
//! whose rest sits by depth in a few KiB (a push spills one vertex with a masked scatter, a
//! pop refills one with a masked gather, column and height packed in one 64-bit entry so each
//! moves 16 entries rather than 32); slopes are compared by cross-multiplication, with one
//! division per query; two groups run side by side in one loop ([`GROUPS`]), so their chains
//! of dependent compares overlap; a group's tangents are added to the sums after its sweeps, 8
//! groups of neighbouring lines at a time so each row of the sums is visited once per batch.
//! The curvature drop is the same g = h − c'u² as in f64 (the drops c'u², c'q² and 2c'q
//! computed in f64, then rounded to f32): at u = 4096, g's rounding moves a tangent by about
//! 0.03 millidegrees with 30 m cells and 1 millidegree with 1 km cells (the drop is then 39
//! and 1300 texels). It is tested against the scalar f64 [`far_field`] (the same samples,
//! with and without the drop), which remains the path on other CPUs. The lanes of a group pop
//! as often as their busiest lane, ≈2.4 vector pops per push on fBm against ≈1 pop per line,
//! and each pop or step of a tangent walk waited for the compare before it. Whether a hull
//! vertex is popped, or a walk steps past it, depends only on it, its neighbour and the new
//! sample or query (the predicates are monotone along a convex chain), so the pops test two
//! vertices a round and the walks [`WALK`] (the first that fails decides, which is the vertex
//! a one-at-a-time walk reaches, by the same float operations: the same bits). The bands give
//! each texel's far value to the near field as a floor ([`NearField::strip_from`]); where all
//! of a strip's rays run to the cut, the near field walks crossings: each piece's exit as a
//! lerp of the two texels of the grid line it crosses, and the piece solved whole only where
//! the bulge of the cell's twist can beat the best value and the cell walk would not cull it
//! (3.4 of 22.7 pieces a strip on fBm pass the first test, 1.05 the stationary point's, fewer
//! all). The bands run a row's strips bin by bin, so the points at R and the far table are
//! read along rows; with AVX-512 the join around the near field (the point at R, sin α, the
//! channel sums across a strip) is compiled for it too ([`Sweep::rows_avx512`]).
//!
//! With `edge=wrap` the lines run R past the map and a finite R takes two passes (suffix and
//! prefix hulls, ≈3 pushes per sample at `unlimited`, ≈2 at a short R), shared by the two
//! opposite azimuths, so about half that per azimuth. A query of the prefix pass looks at the
//! far part of its window (from the next block's start on) after the suffix pass gave it the
//! near part's tangent: where the highest sample of that far part cannot beat it, no walk is
//! made (a bound by the same float operations, so the same bits; measured −7 % of the build
//! at 2048² `unlimited`).
//!
//! Counted (temporary counters, 1024² fBm, 32 bins, per group of 16 lines and W = 1024 query
//! columns): `edge=wrap` unlimited pushes 1.75·W samples in the suffix pass and 1.01·W in the
//! prefix pass, with 2.38 vector pop rounds per push; `edge=none` unlimited pushes 0.98·W with
//! 1.65 rounds per push; R = 64 (wrap) pushes 1.03·W + 1.01·W with 2.13. A suffix query walks
//! 4.7 steps (the busiest lane's; from the third on, each a gather), a prefix query 5.7 (plain
//! row loads). Any window split into a suffix and a prefix hull costs at least the span of
//! its queries plus one block per set of queries whose window starts fit in one block, and
//! W > R' − N + 1 needs two such sets, so ≈3·W pushes is the floor of this scheme at
//! `unlimited` with `edge=wrap` for one azimuth; the opposite azimuth's windows are the same
//! windows (module doc, Radius), so a pair of them costs about what one did (measured at
//! 1024², the build's wall time −15 to −20 %, the rest being the queries and the sums).

use super::exact::{self, NearField, NEAR_LANES};
use super::lengyel_fast::Isa;
use super::{reduce_strip, Grid, HorizonRows};
use crate::params::{Edge, Reduce};
use crate::progress::Progress;
use rayon::prelude::*;
use std::f64::consts::PI;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};

/// Major-axis steps covered exactly by the near field. Measured shorter (`tests/sweep.rs`, the
/// frontier bench): 8 steps save ~10 % of the CPU time at 2048² unlimited (14.5 → 13.0 CPU-s)
/// but break the tolerance (fBm 45° wrapped p99 0.32°, white noise mean 0.054°); 12 steps keep
/// terrain within it (p99 0.21°, from 0.17°) but break the stated worst case of a 1×37 strip
/// (p99 1.06°) and leave spikes at p99 7.4° of 8°; so it stays 16.
pub const NEAR: usize = 16;
/// Sub-line families per texel of minor axis. The hull work is proportional to it (every
/// family's lines are swept whole), the queries are not (each texel asks two lines whatever
/// the count). Measured (`tests/sweep.rs`, and interleaved timing binaries at 2048² `unlimited`
/// `edge=wrap`, 32 bins, 2026-12-03): 3 families against 4, the build's CPU time 5.05 against
/// 6.03 s and the worst terrain p99 (fBm 45°, wrapped) 0.196° against 0.170° of the 0.25°
/// tolerance, the stated worst cases' measured means 0.30° against 0.28° (spikes) and 0.017°
/// against 0.016° (white noise); 2 families reach 0.23° on that fBm. So 3: the speed target
/// of 1 Mtexel/s with `edge=wrap` needs the sixth of the build, and a fifth of the margin to
/// the tolerance is left.
pub const SUB: usize = 3;
/// Whether the far field also samples halfway between major grid lines (the bulge of the cells
/// between them). Measured: it halves the terrain p99 (0.17° → 0.10° on fBm 45°) for twice the
/// hull pushes; the tolerance is met without, so it is off.
pub const MIDS: bool = false;

/// One azimuth's line geometry (see the module doc).
#[derive(Debug, Clone, Copy)]
pub struct Lines {
    /// The major axis is x (image columns) rather than y.
    pub major_x: bool,
    /// +1 if the look direction increases the major image coordinate, −1 otherwise.
    pub sign: i64,
    /// Minor-axis image coordinate change per major step.
    pub m: f64,
    /// Arc length per major step, √(1 + m²).
    pub step: f64,
    /// Where the lines are anchored: look-order position u lies on column `at.0 + at.1·u` of
    /// the lines, which pass at minor k/SUB + i + m·at.1·column (family k, line i). (0, 1) for
    /// an azimuth of its own; a [`Lines::mirror`] reads another azimuth's lines backwards.
    pub at: (i64, i64),
}

impl Lines {
    /// The lines of image direction `d` (unit vector).
    pub fn new(d: (f64, f64)) -> Lines {
        let (dx, dy) = d;
        let major_x = dx.abs() >= dy.abs();
        let (a, b) = if major_x { (dx, dy) } else { (dy, dx) };
        let m = b / a.abs();
        let sign = if a < 0.0 { -1 } else { 1 };
        Lines { major_x, sign, m, step: (1.0 + m * m).sqrt(), at: (0, 1) }
    }

    /// The lines of the opposite azimuth that are these very lines read backwards, its
    /// position 0 on position `end` of these: the sweeps of both azimuths then share every
    /// sample and their windows (see `far_field_fast`). With `edge=wrap` a texel's own column
    /// and that column plus a multiple of the major size are the same texel, so `end` may lie
    /// past the map.
    pub fn mirror(&self, end: i64) -> Lines {
        let at = (self.at.0 + self.at.1 * end, -self.at.1);
        Lines { sign: -self.sign, m: -self.m, at, ..*self }
    }

    /// The minor coordinate of line i of family k at look-order position u.
    pub fn minor(&self, k: usize, i: i64, u: f64) -> f64 {
        let (c, m) = self.column(u);
        i as f64 + (k as f64 / SUB as f64 + m * c)
    }

    /// The lines' column of look-order position u, and the minor change per column.
    #[inline]
    fn column(&self, u: f64) -> (f64, f64) {
        (self.at.0 as f64 + self.at.1 as f64 * u, self.m * self.at.1 as f64)
    }

    /// For a texel at major position u (in look order), the family k and shift so that the
    /// texel at minor coordinate b lies nearest line i = b + shift of family k.
    pub fn family(&self, u: i64) -> (usize, i64) {
        let (c, m) = self.column(u as f64);
        let kk = (-m * c * SUB as f64).round() as i64;
        (kk.rem_euclid(SUB as i64) as usize, kk.div_euclid(SUB as i64))
    }

    /// For a texel at major position u: the sub-lines just below (role 0) and above (role 1) it
    /// on the minor axis, as (family k, shift, weight): the texel at minor b lies between line
    /// b + shift of family k of each, and its far field is their tangents weighted so.
    pub fn pair(&self, u: i64) -> [(usize, i64, f64); 2] {
        let (c, m) = self.column(u as f64);
        let f = -m * c * SUB as f64;
        let kk = f.floor();
        let t = f - kk;
        let kk = kk as i64;
        let role =
            |kk: i64, wt: f64| (kk.rem_euclid(SUB as i64) as usize, kk.div_euclid(SUB as i64), wt);
        [role(kk, 1.0 - t), role(kk + 1, t)]
    }

    /// For family k at major position u: minor offset of the lower texel from the line's
    /// integer intercept i, and the lerp weight of the upper one.
    pub fn sample(&self, k: usize, u: i64) -> (i64, f64) {
        self.sample_at(k, u as f64)
    }

    /// [`Lines::sample`] at a fractional major position.
    pub fn sample_at(&self, k: usize, u: f64) -> (i64, f64) {
        let (c, m) = self.column(u);
        let z = k as f64 / SUB as f64 + m * c;
        let off = z.floor();
        (off as i64, z - off)
    }
}

/// The sweep kernel prepared for one grid.
pub struct Sweep<'a> {
    grid: Grid<'a>,
    bins: usize,
    reduce: Reduce,
    near: NearField<'a>,
    /// The far field's tan α per bin and texel (0 when nothing beyond rises).
    far: Far,
    /// The first failure of the spill store (see [`FarSpill`]), as its kind and message so
    /// every band after it can report it; `failed` says there is one without taking the lock.
    failure: Mutex<Option<(std::io::ErrorKind, String)>>,
    failed: AtomicBool,
    progress: Option<Progress>,
    /// Where rays end (`None`: the map's edge), each direction's near-field cut, the image
    /// directions and the curvature: for the point at exactly R (see [`Sweep::end_points`]).
    reach: Option<f64>,
    cuts: Vec<f64>,
    dirs: Vec<(f64, f64)>,
    curv: f64,
    /// The CPU has AVX-512: the bands' join is compiled for it ([`Sweep::rows_avx512`]).
    wide: bool,
}

/// Where the far field waits between the sweeps and the bands.
enum Far {
    /// `far[n · W·H + texel]`.
    Memory(Vec<f32>),
    /// One plane of W·H per bin, in the caller's store.
    Spilled(Arc<dyn FarSpill>),
}

/// A store for the far field's planes outside the process's memory (a temporary file, in
/// `bake.rs`): the kernel stays free of I/O and the caller picks where the bytes go. The far
/// field is made azimuth by azimuth (a whole plane of W·H per sweep) but read band by band (all
/// bins of a few rows), so without a store the whole W·H·bins table sits in memory between the
/// two; with one the kernel holds only the planes being swept and one band of every bin.
pub trait FarSpill: Send + Sync {
    /// Stores `values` of plane `n` (W·H values, texel-major) from texel `start` on. Every
    /// texel of every plane is stored once before the first read.
    ///
    /// # Errors
    /// The store's I/O error; the bake then fails with it.
    fn put(&self, n: usize, start: usize, values: &[f32]) -> std::io::Result<()>;
    /// Fills `out` with plane `n`'s values from texel `start` on.
    ///
    /// # Errors
    /// The store's I/O error; the bake then fails with it.
    fn get(&self, n: usize, start: usize, out: &mut [f32]) -> std::io::Result<()>;
}

/// How the kernel is built beyond the grid, radius, bins and reduction.
#[derive(Clone, Default)]
pub struct Options {
    /// Earth-curvature drop per texel² (0: off).
    pub curvature: f64,
    /// Instruction set of the near field (`None`: the best the CPU has).
    pub isa: Option<Isa>,
    /// Checked between azimuths and strips: a canceled build stops early (its output is then
    /// unspecified and must be discarded, as [`super::run_bands`] does).
    pub progress: Option<Progress>,
    /// Where the far field waits for the bands (`None`: in memory, 4·bins bytes per texel;
    /// see [`spills`] for when the bake provides one).
    pub spill: Option<Arc<dyn FarSpill>>,
}

impl<'a> Sweep<'a> {
    /// Prepares the kernel with default [`Options`]. `radius`: `None` = unlimited.
    pub fn new(grid: Grid<'a>, radius: Option<u32>, bins: u32, reduce: Reduce) -> Self {
        Self::with_options(grid, radius, bins, reduce, Options::default())
    }

    /// Prepares the kernel: runs the far-field sweeps of every azimuth (in parallel on the
    /// current pool).
    pub fn with_options(
        grid: Grid<'a>,
        radius: Option<u32>,
        bins: u32,
        reduce: Reduce,
        opt: Options,
    ) -> Self {
        let (w, h) = (grid.width, grid.height);
        let bins = bins.max(1) as usize;
        let reach = reach_of(&grid, radius);
        let dirs = directions(&grid, bins);
        let curv =
            if opt.curvature.is_finite() && opt.curvature > 0.0 { opt.curvature } else { 0.0 };
        let cuts: Vec<f64> = dirs
            .iter()
            .map(|&d| {
                let near = NEAR as f64 * Lines::new(d).step;
                reach.map_or(near, |r| near.min(r))
            })
            .collect();
        let isa = opt.isa.filter(|i| i.supported()).unwrap_or_else(Isa::detect);
        let make_near = || NearField::new(grid, &dirs, &cuts, curv, isa);
        // Built by the far field's pool when that runs in memory (see below), else here.
        let mut near = None;
        let progress = opt.progress.clone();
        let half = if bins.is_multiple_of(2) { bins / 2 } else { 0 };
        let lines_of = azimuth_lines(&grid, radius, bins as u32);
        // Azimuth n < half whose opposite's lines are its own read backwards.
        let paired: Vec<bool> =
            (0..bins).map(|n| n < half && lines_of[n + half].at.1 < 0).collect();
        // With AVX-512, the vector sweeps of `far_field_fast` (f32); otherwise the scalar f64
        // ones of `far_field`.
        let fast = isa == Isa::Avx512;
        // `fresh`: `out` is memory never touched yet (a plane of the table in memory).
        let sweep_one = |ml: Option<&MajorLines>,
                         lines: Lines,
                         out: &mut [f32],
                         sc: &mut Scratch,
                         fresh: bool| match ml {
            Some(ml) => far_field_fast(&grid, ml, lines, reach, curv, out, sc, None, fresh, None),
            None => far_field(&grid, lines, reach, curv, out, &mut sc.miss),
        };
        let failure = Mutex::new(None);
        let failed = AtomicBool::new(false);
        let far = match opt.spill {
            None => {
                let mut far = vec![0.0f32; w * h * bins];
                // Both axes' padded lines at once, each filled line by line in parallel.
                let (mly, mlx) = rayon::join(
                    || {
                        (fast && lines_of.iter().any(|l| !l.major_x))
                            .then(|| MajorLines::new(&grid, false))
                    },
                    || {
                        (fast && lines_of.iter().any(|l| l.major_x))
                            .then(|| MajorLines::new(&grid, true))
                    },
                );
                let majors = [mly, mlx];
                // One task per azimuth, or per pair when the vector sweeps serve both and the
                // pair's two more scratch planes per thread fit in `PAIR_SCRATCH_BYTES` (a
                // table in memory of few bins can belong to a map of 8192²).
                let threads = rayon::current_num_threads().max(1);
                let pair_fits = 2 * w * h * 4 * threads <= PAIR_SCRATCH_BYTES;
                let mut planes: Vec<Option<&mut [f32]>> = far.chunks_mut(w * h).map(Some).collect();
                let mut tasks = Vec::with_capacity(bins + 1);
                for n in 0..bins {
                    let Some(out) = planes[n].take() else { continue };
                    let two = fast && pair_fits && n < half && paired[n];
                    let other = if two { planes[n + half].take() } else { None };
                    tasks.push(Mutex::new(Some(Task::Far(n, out, other))));
                }
                // The near field's tables last, built by whichever thread runs out of sweeps
                // first while the others finish theirs (built before the sweeps, they were
                // 0.11 s of one thread with the other idle at 2048²; so were the major lines,
                // 0.07 s, now filled in parallel).
                tasks.push(Mutex::new(Some(Task::Near)));
                let next = AtomicUsize::new(0);
                let built = Mutex::new(None);
                // One worker per thread of the pool, each with one scratch for the whole build
                // (per split of the work, each would map its planes, 64 MiB at 2048², afresh, a
                // page fault per 4 KiB), taking the tasks in order.
                (0..threads).into_par_iter().for_each(|_| {
                    let mut sc = Scratch::default();
                    loop {
                        let i = next.fetch_add(1, Ordering::Relaxed);
                        let Some(task) = tasks.get(i) else { break };
                        let task = task.lock().unwrap_or_else(|e| e.into_inner()).take();
                        let (n, out, other) = match task {
                            Some(Task::Far(n, out, other)) => (n, out, other),
                            Some(Task::Near) => {
                                let made = make_near();
                                *built.lock().unwrap_or_else(|e| e.into_inner()) = Some(made);
                                continue;
                            }
                            None => continue,
                        };
                        if progress.as_ref().is_some_and(Progress::is_canceled) {
                            continue;
                        }
                        let lines = lines_of[n];
                        let ml = majors[usize::from(lines.major_x)].as_ref();
                        match (ml, other) {
                            (Some(ml), Some(o)) => {
                                let mirror = Some((lines_of[n + half], o));
                                far_field_fast(
                                    &grid, ml, lines, reach, curv, out, &mut sc, None, true, mirror,
                                );
                            }
                            _ => sweep_one(ml, lines, out, &mut sc, true),
                        }
                    }
                });
                near = built.into_inner().unwrap_or_else(|e| e.into_inner());
                Far::Memory(far)
            }
            Some(store) => {
                // One major axis at a time, so only its padded lines are alive; at most
                // `slots` azimuths at once, each with 2 planes of W·H (the sums or the plane,
                // and the weights: the vector sweeps along x hand their transposed rows to
                // the store band by band), so the build's memory is bounded by the map, not
                // the map × bins.
                let plane = w * h * 4;
                let slots = (SPILL_SWEEP_BYTES / (2 * plane).max(1))
                    .clamp(1, rayon::current_num_threads().max(1));
                let mut work: Vec<(Vec<f32>, Scratch)> =
                    (0..slots).map(|_| (Vec::new(), Scratch::default())).collect();
                for major_x in [false, true] {
                    let ns: Vec<usize> =
                        (0..bins).filter(|&n| lines_of[n].major_x == major_x).collect();
                    if ns.is_empty() {
                        continue;
                    }
                    let ml = fast.then(|| MajorLines::new(&grid, major_x));
                    for chunk in ns.chunks(slots) {
                        if failed.load(Ordering::Relaxed)
                            || progress.as_ref().is_some_and(Progress::is_canceled)
                        {
                            break;
                        }
                        chunk.par_iter().zip(work.par_iter_mut()).for_each(|(&n, (out, sc))| {
                            let lines = lines_of[n];
                            let put = |start: usize, values: &[f32]| {
                                if let Err(e) = store.put(n, start, values) {
                                    record(&failure, &failed, e);
                                }
                            };
                            out.clear();
                            match &ml {
                                Some(ml) if major_x => {
                                    // The plane of the azimuths along y is not needed any more:
                                    // freed, not just emptied, or it stays resident.
                                    *out = Vec::new();
                                    let mut emit = put;
                                    far_field_fast(
                                        &grid,
                                        ml,
                                        lines,
                                        reach,
                                        curv,
                                        out,
                                        sc,
                                        Some(&mut emit),
                                        false,
                                        None,
                                    );
                                }
                                _ => {
                                    out.resize(w * h, 0.0);
                                    sweep_one(ml.as_ref(), lines, out, sc, false);
                                    put(0, out);
                                }
                            }
                        });
                    }
                }
                Far::Spilled(store)
            }
        };
        let near = near.unwrap_or_else(make_near);
        Sweep {
            grid,
            bins,
            reduce,
            near,
            far,
            failure,
            failed,
            progress: opt.progress,
            reach,
            cuts,
            dirs,
            curv,
            wide: fast,
        }
    }

    /// tan of the point at exactly s = R on the texel's own ray, when R ends the far field
    /// between two grid lines (a ray rising to R has its maximum there); 0 if it is off the
    /// surface or R is within the near field. For `lanes` texels x.. of row y, into `ep`.
    #[inline(always)]
    fn end_points(
        &self,
        n: usize,
        x: usize,
        y: usize,
        lanes: usize,
        hs: &[f32; NEAR_LANES],
        ep: &mut [f32; NEAR_LANES],
    ) {
        *ep = [0.0; NEAR_LANES];
        let Some(r) = self.reach else { return };
        if r <= self.cuts[n] {
            return;
        }
        let (dx, dy) = self.dirs[n];
        let g = &self.grid;
        let (w, h) = (g.width as i64, g.height as i64);
        // The point of texel x + i is (x + i + r·dx, y + r·dy): one row pair, one fraction.
        let (ox, oy) = (r * dx, r * dy);
        let (fx0, fy0) = (ox.floor(), (y as f64 + oy).floor());
        let (fx, fy) = (ox - fx0, y as f64 + oy - fy0);
        let (ox, cy) = (fx0 as i64, fy0 as i64);
        let wrap = g.edge == Edge::Wrap;
        let row = |rr: i64, wt: f64| -> Option<Option<&[f32]>> {
            if wt == 0.0 {
                return Some(None);
            }
            let rr = if wrap { rr.rem_euclid(h) } else { rr };
            (0..h).contains(&rr).then(|| Some(&g.heights[(rr * w) as usize..][..w as usize]))
        };
        let (Some(r0), Some(r1)) = (row(cy, 1.0 - fy), row(cy + 1, fy)) else { return };
        let drop = self.curv * r * r;
        if wrap {
            // Every corner is on the surface: one f32 lerp per lane.
            let r0 = r0.unwrap_or(&g.heights[..w as usize]);
            let r1 = r1.unwrap_or(r0);
            let (fx, fy) = (fx as f32, fy as f32);
            let (inv_r, drop) = ((1.0 / r) as f32, drop as f32);
            let h0 = &hs[..lanes];
            let mut c0 = (x as i64 + ox).rem_euclid(w) as usize;
            if c0 + NEAR_LANES < w as usize {
                // No lane wraps: the same arithmetic over runs of a fixed length, which
                // vectorises whole (over `lanes` it ran half its lanes in scalar code).
                let a0 = <&[f32; NEAR_LANES + 1]>::try_from(&r0[c0..=c0 + NEAR_LANES]);
                let a1 = <&[f32; NEAR_LANES + 1]>::try_from(&r1[c0..=c0 + NEAR_LANES]);
                if let (Ok(a0), Ok(a1)) = (a0, a1) {
                    for i in 0..NEAR_LANES {
                        let a = a0[i] + (a0[i + 1] - a0[i]) * fx;
                        let b = a1[i] + (a1[i + 1] - a1[i]) * fx;
                        ep[i] = (a + (b - a) * fy - drop - hs[i]) * inv_r;
                    }
                    return;
                }
            }
            for (e, &h0) in ep.iter_mut().zip(h0) {
                let c1 = if c0 + 1 == w as usize { 0 } else { c0 + 1 };
                let a = r0[c0] + (r0[c1] - r0[c0]) * fx;
                let b = r1[c0] + (r1[c1] - r1[c0]) * fx;
                *e = (a + (b - a) * fy - drop - h0) * inv_r;
                c0 = c1;
            }
            return;
        }
        for (i, e) in ep.iter_mut().enumerate().take(lanes) {
            let c = x as i64 + i as i64 + ox;
            let (c0, c1) = if wrap { (c.rem_euclid(w), (c + 1).rem_euclid(w)) } else { (c, c + 1) };
            let mut v = 0.0;
            let mut ok = true;
            for (rw, wy) in [(r0, 1.0 - fy), (r1, fy)] {
                let Some(rw) = rw else { continue };
                for (cc, wx) in [(c0, 1.0 - fx), (c1, fx)] {
                    if wx == 0.0 {
                        continue;
                    }
                    if (0..w).contains(&cc) {
                        v += f64::from(rw[cc as usize]) * wx * wy;
                    } else {
                        ok = false;
                    }
                }
            }
            if ok {
                let h0 = f64::from(g.heights[y * g.width + x + i]);
                *e = ((v - drop - h0) / r) as f32;
            }
        }
    }
}

/// Where every ray ends: R (clamped to what the service takes, or the map), max(W, H) for
/// `unlimited` when wrapping, or the map's edge (`None`).
fn reach_of(grid: &Grid<'_>, radius: Option<u32>) -> Option<f64> {
    let (w, h) = (grid.width, grid.height);
    let cap = crate::params::MAX_RADIUS.max(w.max(h) as u32);
    match (radius, grid.edge) {
        (Some(r), _) => Some(f64::from(r.clamp(1, cap))),
        (None, Edge::Wrap) => Some(w.max(h) as f64),
        (None, Edge::None) => None,
    }
}

/// The image directions of the `bins` azimuths.
fn directions(grid: &Grid<'_>, bins: usize) -> Vec<(f64, f64)> {
    let row_step = grid.row_step();
    (0..bins).map(|n| exact::direction(n as f64 * 2.0 * PI / bins as f64, row_step)).collect()
}

/// The far field's lines of each of the `bins` azimuths, as [`Sweep`] bakes them: an azimuth's
/// own ([`Lines::new`]), or, with `edge=wrap` and a window of at least N steps, for azimuth
/// n < bins/2 its own anchored a multiple of W along them and for its opposite n + bins/2 the
/// same lines read backwards ([`Lines::mirror`]; `mirror_end` picks where), so that one sweep
/// serves both (`far_field_fast`). Chosen by geometry alone, so every instruction set and
/// every path (in memory or spilled) bakes the same lines.
pub fn azimuth_lines(grid: &Grid<'_>, radius: Option<u32>, bins: u32) -> Vec<Lines> {
    let bins = bins.max(1) as usize;
    let reach = reach_of(grid, radius);
    let mut lines: Vec<Lines> = directions(grid, bins).into_iter().map(Lines::new).collect();
    if bins.is_multiple_of(2) {
        let half = bins / 2;
        for n in 0..half {
            if let Some((a, e)) = mirror_end(grid, lines[n], reach) {
                lines[n].at = (a, 1);
                lines[n + half] = lines[n].mirror(e);
            }
        }
    }
    lines
}

/// Where an azimuth's texels and its opposite's sit on the azimuth's lines so that the two
/// share their windows ([`Lines::mirror`], [`far_field_fast`]): (A, e), the azimuth's texel u
/// on column A + u and the mirror's query column 0 on position e (column A + e), or `None`
/// where that saves nothing. Only with `edge=wrap` (a texel's column plus a multiple of the
/// major size W is the same texel, so A and e + 1 are multiples of W) and a window of R' ≥ N
/// steps: the azimuth's windows start at A + u + N, the mirror's at A + J·W + u − R', so J is
/// the multiple of W nearest R' + N, and A the first multiple of W that starts no window
/// before column 0. Pairs when the shared passes cover at most 1.5·W window starts.
fn mirror_end(grid: &Grid<'_>, lines: Lines, reach: Option<f64>) -> Option<(i64, i64)> {
    if grid.edge != Edge::Wrap {
        return None;
    }
    let r = (reach? / lines.step + 1e-9).floor() as i64;
    let d = NEAR as i64;
    if r < d {
        return None;
    }
    let wa = (if lines.major_x { grid.width } else { grid.height }) as i64;
    let j = ((r + d) as f64 / wa as f64).round() as i64;
    let a = ((r - j * wa).max(0) + wa - 1) / wa * wa;
    let a2 = j * wa;
    let starts = (wa + d).max(a2 + wa - r) - d.min(a2 - r);
    (2 * starts <= 3 * wa).then_some((a, a2 + wa - 1))
}

/// A hull vertex: major position and height (less the curvature term).
type Pt = (f64, f64);

/// Fills `out` (W·H, texel-major) with the far field's tan α of every texel along `lines`:
/// the tangents of the two sub-lines on either side of the texel, interpolated by its place
/// between them (their lateral error cancels to first order). `wsum` is scratch (W·H).
fn far_field(
    grid: &Grid<'_>,
    lines: Lines,
    reach: Option<f64>,
    curv: f64,
    out: &mut [f32],
    wsum: &mut Vec<f32>,
) {
    let (w, h) = (grid.width, grid.height);
    let (wa, hb) = if lines.major_x { (w, h) } else { (h, w) };
    // Steps within R, and where the far field starts.
    let r_steps = reach.map(|r| (r / lines.step + 1e-9).floor() as i64);
    let d = NEAR as i64;
    if r_steps.is_some_and(|r| r < d) {
        return;
    }
    wsum.clear();
    wsum.resize(w * h, 0.0);
    let wrap = grid.edge == Edge::Wrap;
    // Samples run over u' in 0..len (beyond the map when wrapping).
    let len = match (wrap, r_steps) {
        (true, Some(r)) => wa as i64 + r,
        _ => wa as i64,
    };
    let cc = curv * lines.step * lines.step;
    let major = |u: i64| -> i64 {
        let u = if wrap { u.rem_euclid(wa as i64) } else { u };
        if lines.sign > 0 {
            u
        } else {
            wa as i64 - 1 - u
        }
    };
    // Tables so the sweeps do no division: each column's image offset of minor 0, the step
    // of one minor texel.
    let abase: Vec<usize> = (0..len)
        .map(|u| {
            let a = major(u) as usize;
            if lines.major_x {
                a
            } else {
                a * w
            }
        })
        .collect();
    let mstep = if lines.major_x { w } else { 1 };
    let hbi = hb as i64;
    // Per query column, the two sub-lines around its texels: (family, shift, weight) each.
    let fams: Vec<[(usize, i64, f64); 2]> = (0..wa as i64).map(|u| lines.pair(u)).collect();
    let (sh_lo, sh_hi) = fams
        .iter()
        .flatten()
        .fold((i64::MAX, i64::MIN), |(lo, hi), &(_, s, _)| (lo.min(s), hi.max(s)));
    let hs = grid.heights;
    let fams: Vec<[(usize, i64, f64); 2]> = if wrap {
        fams.iter().map(|p| p.map(|(k, sh, wt)| (k, sh.rem_euclid(hbi), wt))).collect()
    } else {
        fams
    };
    let mut samples: Vec<(i64, f64)> = Vec::with_capacity(len as usize);
    let mut mids: Vec<(i64, f64)> = Vec::with_capacity(len as usize);
    let mut hull: Vec<Pt> = Vec::new();
    // Per column and role (lower, upper line): the best slope found (NaN: none yet).
    let mut best: Vec<[f64; 2]> = vec![[f64::NAN; 2]; wa];
    for k in 0..SUB {
        samples.clear();
        // Minor offsets reduced modulo the map when wrapping (the line index adds < hb).
        let reduce = |(off, wt): (i64, f64)| (if wrap { off.rem_euclid(hbi) } else { off }, wt);
        samples.extend((0..len).map(|u| reduce(lines.sample(k, u))));
        mids.clear();
        mids.extend((0..len).map(|u| reduce(lines.sample_at(k, u as f64 + 0.5))));
        // Lines i whose texels b = i − shift lie in the map (all of them when wrapping).
        let (i_lo, i_hi) = if wrap { (0, hb as i64 - 1) } else { (sh_lo, hb as i64 - 1 + sh_hi) };
        for i in i_lo..=i_hi {
            // The line's value at column a, minor lerp (off, wt) (None: off the surface).
            // The line's value at column u, minor lerp (off, wt) (None: off the surface).
            let lerp = |u: i64, (off, wt): (i64, f64)| -> Option<f64> {
                let base = abase[u as usize];
                let b = i + off;
                if wrap {
                    // 0 ≤ i < hb and 0 ≤ off < hb.
                    let b0 = if b >= hbi { b - hbi } else { b };
                    let b1 = if b0 + 1 == hbi { 0 } else { b0 + 1 };
                    let h0 = hs[base + b0 as usize * mstep] as f64;
                    let h1 = hs[base + b1 as usize * mstep] as f64;
                    Some(h0 + (h1 - h0) * wt)
                } else if b >= 0 && b + 1 < hbi {
                    let h0 = hs[base + b as usize * mstep] as f64;
                    let h1 = hs[base + (b + 1) as usize * mstep] as f64;
                    Some(h0 + (h1 - h0) * wt)
                } else if b == hbi - 1 && wt == 0.0 {
                    Some(hs[base + b as usize * mstep] as f64)
                } else {
                    None
                }
            };
            let sample = |u: i64| lerp(u, samples[u as usize]);
            // Halfway between grid lines u and u + 1: the bulge of the cells between them.
            let mid = |u: i64| -> Option<f64> {
                if !MIDS || u + 1 >= len {
                    return None;
                }
                let m = mids[u as usize];
                Some(0.5 * (lerp(u, m)? + lerp(u + 1, m)?))
            };
            let g = |x: f64, v: f64| (x, v - cc * x * x);
            // The texel of column u for which this line is role r (0: the line below it, 1:
            // above), with its height and weight.
            let texel = |u: i64, r: usize| -> Option<(usize, f64, f64)> {
                let (fk, shift, wt) = fams[u as usize][r];
                if fk != k {
                    return None;
                }
                let b = i - shift;
                let b = if wrap {
                    // Shifts are stored modulo hb when wrapping (see `fams`).
                    if b < 0 {
                        b + hbi
                    } else {
                        b
                    }
                } else if (0..hbi).contains(&b) {
                    b
                } else {
                    return None;
                };
                let t = abase[u as usize] + b as usize * mstep;
                Some((t, hs[t] as f64, wt))
            };
            let mut any = false;
            let mut ask = |q: i64, hull: &[Pt], left: bool, best: &mut Vec<[f64; 2]>| {
                for (r, b) in best[q as usize].iter_mut().enumerate() {
                    if let Some((_, h0, _)) = texel(q, r) {
                        let s = if left {
                            tangent_left(hull, q, h0, cc)
                        } else {
                            tangent_right(hull, q, h0, cc)
                        };
                        if let Some(s) = s {
                            // NaN (nothing yet) or smaller: take s.
                            if b.is_nan() || *b < s {
                                *b = s;
                            }
                            any = true;
                        }
                    }
                }
            };
            for b in best.iter_mut() {
                *b = [f64::NAN; 2];
            }
            match r_steps {
                None => {
                    // One plain hull, right to left.
                    hull.clear();
                    for up in (d..len).rev() {
                        if let Some(v) = mid(up) {
                            push_left(&mut hull, g(up as f64 + 0.5, v));
                        }
                        if let Some(v) = sample(up) {
                            push_left(&mut hull, g(up as f64, v));
                        }
                        ask(up - d, &hull, true, &mut best);
                    }
                }
                Some(r) => {
                    let blk = r - d + 1;
                    hull.clear();
                    for up in (d..len).rev() {
                        if up % blk == blk - 1 {
                            hull.clear();
                        } else if let Some(v) = mid(up) {
                            // (A block's last midpoint would lie past R for some queries: the
                            // prefix pass has it.)
                            push_left(&mut hull, g(up as f64 + 0.5, v));
                        }
                        if let Some(v) = sample(up) {
                            push_left(&mut hull, g(up as f64, v));
                        }
                        if up - d < wa as i64 {
                            ask(up - d, &hull, true, &mut best);
                        }
                    }
                    // Prefix hulls, left to right: the window's part in the next block.
                    hull.clear();
                    let mut next = d; // next sample to push
                    for q in 0..wa as i64 {
                        let top = (q + r).min(len - 1);
                        while next <= top {
                            if next % blk == 0 {
                                hull.clear();
                            }
                            // With the midpoint before a block's first sample, which the
                            // suffix pass leaves out.
                            if next > d {
                                if let Some(v) = mid(next - 1) {
                                    push_right(&mut hull, g(next as f64 - 0.5, v));
                                }
                            }
                            if let Some(v) = sample(next) {
                                push_right(&mut hull, g(next as f64, v));
                            }
                            next += 1;
                        }
                        // Only when the window reaches into the next block: otherwise the
                        // suffix pass saw all of it, and this hull may hold samples nearer than
                        // q + d (at the map's end, where q + r is clipped).
                        if top / blk > (q + d) / blk {
                            ask(q, &hull, false, &mut best);
                        }
                    }
                }
            }
            if !any {
                continue;
            }
            for (q, pair) in best.iter().enumerate() {
                for (r, &s) in pair.iter().enumerate() {
                    if s.is_nan() {
                        continue;
                    }
                    if let Some((t, _, wt)) = texel(q as i64, r) {
                        out[t] += (wt * s / lines.step) as f32;
                        wsum[t] += wt as f32;
                    }
                }
            }
        }
    }
    for (o, &ws) in out.iter_mut().zip(wsum.iter()) {
        // One of the two lines may have nothing ahead (off the surface): the other alone.
        *o = if ws > 0.0 { *o / ws } else { 0.0 };
    }
}

/// Pushes `p` (left of every vertex) onto the upper hull `hull` (nearest vertex last).
#[inline]
fn push_left(hull: &mut Vec<Pt>, p: Pt) {
    while hull.len() >= 2 {
        let t1 = hull[hull.len() - 1];
        let t2 = hull[hull.len() - 2];
        // Keep t1 only if the slope p→t1 is above t1→t2.
        if (t1.1 - p.1) * (t2.0 - t1.0) > (t2.1 - t1.1) * (t1.0 - p.0) {
            break;
        }
        hull.pop();
    }
    hull.push(p);
}

/// Pushes `p` (right of every vertex) onto the upper hull `hull` (farthest vertex last).
#[inline]
fn push_right(hull: &mut Vec<Pt>, p: Pt) {
    while hull.len() >= 2 {
        let t1 = hull[hull.len() - 1];
        let t2 = hull[hull.len() - 2];
        // Keep t1 only if the slope t2→t1 is above t1→p.
        if (t1.1 - t2.1) * (p.0 - t1.0) > (p.1 - t1.1) * (t1.0 - t2.0) {
            break;
        }
        hull.pop();
    }
    hull.push(p);
}

/// The query point of major position `q`, height `h0`, on the hulls of g = h − cc·u², and the
/// slope correction (see the module doc): slope to the hull + 2·cc·q.
#[inline]
fn origin(q: i64, h0: f64, cc: f64) -> (f64, f64, f64) {
    let x = q as f64;
    (x, h0 - cc * x * x, 2.0 * cc * x)
}

/// The largest slope from (q, h0) to a vertex of `hull` (nearest vertex last), per major step:
/// the slopes are unimodal along the hull, so a galloping search from the nearest vertex finds
/// the tangent in O(log d) steps for a tangent d vertices away (a far horizon on a long concave
/// hull would make a plain walk O(d)).
#[inline]
fn tangent_left(hull: &[Pt], q: i64, h0: f64, cc: f64) -> Option<f64> {
    let n = hull.len();
    if n == 0 {
        return None;
    }
    let (x, y, corr) = origin(q, h0, cc);
    let f = |j: usize| {
        let p = hull[n - 1 - j];
        (p.1 - y) / (p.0 - x)
    };
    // Rising at j: the next vertex (farther) has the larger slope.
    let rising = |j: usize| j + 1 < n && f(j + 1) > f(j);
    let (mut lo, mut hi) = (0usize, 1usize);
    while hi < n && rising(hi) {
        lo = hi + 1;
        hi *= 2;
    }
    let mut hi = hi.min(n - 1);
    lo = lo.min(hi);
    // The first j in lo..=hi that is not rising.
    while lo < hi {
        let mid = (lo + hi) / 2;
        if rising(mid) {
            lo = mid + 1;
        } else {
            hi = mid;
        }
    }
    Some(f(lo) + corr)
}

/// The largest slope from (q, h0) to a vertex of `hull` (farthest vertex last): binary search
/// of the unimodal slopes.
#[inline]
fn tangent_right(hull: &[Pt], q: i64, h0: f64, cc: f64) -> Option<f64> {
    if hull.is_empty() {
        return None;
    }
    let (x, y, corr) = origin(q, h0, cc);
    let slope = |p: Pt| (p.1 - y) / (p.0 - x);
    let (mut lo, mut hi) = (0usize, hull.len() - 1);
    while lo < hi {
        let mid = (lo + hi) / 2;
        if slope(hull[mid + 1]) > slope(hull[mid]) {
            lo = mid + 1;
        } else {
            hi = mid;
        }
    }
    Some(slope(hull[lo]) + corr)
}

/// Where [`far_field_fast`] hands on a plane's rows (first texel, values) instead of filling a
/// plane in the image layout.
type Emit<'e> = &'e mut dyn FnMut(usize, &[f32]);

/// Rows per band of a plane that [`far_field_fast`] hands on transposed (16 rows at 8192
/// columns: 512 KiB).
const EMIT_ROWS: usize = 16;

/// Lanes of the vector far field: 16 lines of one family in lockstep.
const FL: usize = 16;
/// Margin of the padded major lines ([`MajorLines`]) on either side of the minor axis.
const PADM: usize = FL + 2;

/// Minor texels per chunk of [`MajorLines`] (a power of two).
const CW: usize = 64;
/// A chunk's row: its CW texels and the 16 after them, so a read of 17 starting in the chunk
/// stays in its row.
const RW: usize = CW + FL;

/// The map's major lines (image columns when the major axis is x, rows when it is y), each
/// padded by [`PADM`] on both sides of the minor axis (the wrapped heights with `edge=wrap`, 0
/// with `edge=none`, where those lanes are masked), so 16 adjacent lines of a family read one
/// contiguous run of 17 heights per column with no wrapping or clamping.
///
/// Stored in chunks of [`CW`] minor texels (padded positions), each chunk all major lines'
/// rows of [`RW`] one after the other, so consecutive columns of a group of lines are 320
/// bytes apart rather than a whole line (8 KiB at 2048²): a sweep (or its copy, see
/// [`groups_avx512`]) reads a dozen columns per 4 KiB page, not a new page per column.
/// Measured at 2048², 32 bins (interleaved timing binaries, best of three, the sweeps reading
/// the lines directly): the build's CPU time 7.11 against 7.94 s at `unlimited` with
/// `edge=wrap`, 4.71 against 4.76 with `edge=none`.
struct MajorLines {
    /// Floats per chunk (major lines × RW).
    chunk: usize,
    data: Vec<f32>,
}

impl MajorLines {
    fn new(grid: &Grid<'_>, major_x: bool) -> MajorLines {
        let (w, h) = (grid.width, grid.height);
        let (wa, hb) = if major_x { (w, h) } else { (h, w) };
        let stride = hb + 2 * PADM;
        let chunks = stride.div_ceil(CW);
        let chunk = wa * RW;
        let mut data = vec![0.0f32; chunks * chunk];
        let wrap = grid.edge == Edge::Wrap;
        data.par_chunks_mut(RW).enumerate().for_each(|(i, row)| {
            let (ch, a) = (i / wa, i % wa);
            for (t, v) in row.iter_mut().enumerate() {
                let j = ch * CW + t;
                if j >= stride {
                    break;
                }
                let b = j as i64 - PADM as i64;
                let b = if wrap {
                    b.rem_euclid(hb as i64)
                } else if (0..hb as i64).contains(&b) {
                    b
                } else {
                    continue;
                } as usize;
                *v = if major_x { grid.heights[b * w + a] } else { grid.heights[a * w + b] };
            }
        });
        MajorLines { chunk, data }
    }

    /// Where minor `b` (−PADM ≤ b < hb + PADM − 16) of the major line whose row offset is
    /// `row` (major · RW) lies in `data`.
    #[inline(always)]
    fn at(chunk: usize, row: usize, b: i64) -> isize {
        let j = (b + PADM as i64) as usize;
        ((j / CW) * chunk + row + j % CW) as isize
    }
}

/// Groups of lines whose tangents go into the sums together ([`add_batch_avx512`]).
/// Measured at 2048², 32 bins (A/B pairs of one binary, 8 against 1): the build 5–11 % shorter
/// (`edge=none` unlimited 2.9 s against 3.2 s, `edge=wrap` R = 64 4.4 s against 4.9 s).
const BATCH: usize = 8;

/// Groups of 16 lines swept side by side in one loop ([`groups_avx512`]). Measured at 2048²,
/// 32 bins, `edge=wrap` unlimited (A/B pairs of one binary, a temporary switch): the build
/// took 9.3–9.4 CPU-s with 2 against 10.8–10.9 with 1 (−13 %); 4 took 9.5 (more registers
/// spilled for no more overlap).
const GROUPS: usize = 2;

/// Hull vertices a tangent walk compares per round ([`groups_avx512`]): the pairs of
/// consecutive vertices are compared independently (gathers or loads of several depths at
/// once), so the walk waits for one chain of compares per round rather than per vertex.
/// Measured at 1024², 32 bins, `edge=wrap` unlimited (one process alternating 20 builds each,
/// median): 4 against 2, 1.61 against 1.72 CPU-s; 2 with the pops two at a time against the
/// one-vertex walks and one pop a round, 6.29 against 7.06 CPU-s at 2048².
const WALK: usize = 4;

/// A unit of the in-memory build ([`Sweep::with_options`]): an azimuth's plane (and its
/// mirror's, when the two share their sweeps), or the near field's tables.
enum Task<'p> {
    Far(usize, &'p mut [f32], Option<&'p mut [f32]>),
    Near,
}

/// Per-thread scratch of [`far_field_fast`].
#[derive(Default)]
struct Scratch {
    /// Per texel (major-line layout), when one of its roles found nothing ahead, the other's
    /// weight (0: none missed, so the weights sum to 1).
    miss: Vec<f32>,
    /// The hull stacks below their three registers, `st[depth·16 + lane]`: a vertex's column
    /// in the low 32 bits, the bits of its height in the high ones.
    st: Vec<i64>,
    /// The tangents of a batch of groups, `sb[(slot·W + q)·16 + lane]` (−∞: none).
    sb: Vec<f32>,
    /// The samples of the groups of one [`groups_avx512`] call, `ss[(u·G + g)·16 + lane]`,
    /// and their queries' heights, `sh[((q·2 + mirror)·G + g)·16 + lane]` (see there).
    ss: Vec<f32>,
    sh: Vec<f32>,
    /// Sums in major-line layout when that is not the image's, and per-azimuth tables.
    acc: Vec<f32>,
    /// The mirror azimuth's `acc` and `miss`, and its query columns and sums' offsets.
    acc2: Vec<f32>,
    miss2: Vec<f32>,
    qs2: Vec<QCol>,
    abase2: Vec<usize>,
    fams: Vec<[(usize, i64, f64); 2]>,
    abase: Vec<usize>,
    cols: Vec<Col>,
    qs: Vec<QCol>,
}

/// A column of one family: where lane 0's lower texel lies (minor, reduced modulo the map with
/// `edge=wrap`), the lerp weight, and where its major line lies in [`MajorLines`].
#[derive(Clone, Copy, Default)]
struct Col {
    start: i64,
    wt: f32,
    /// The weight is exactly 0 (a line through the last texel is still on the surface).
    wt0: bool,
    /// The major line's row in each chunk of [`MajorLines`] (major · [`RW`]).
    row: usize,
}

/// A query column of one family: whether the family holds one of the two sub-lines of the
/// column's texels, the shift from line to texel, and the weight.
#[derive(Clone, Copy, Default)]
struct QCol {
    on: bool,
    shift: i64,
    wt: f32,
    /// The other role's weight.
    other: f32,
}

/// Everything a group of lines shares within one family and azimuth.
#[derive(Clone, Copy)]
struct Family<'s> {
    cols: &'s [Col],
    qs: &'s [QCol],
    /// Offset of minor 0 of query column q in the sums' chunk 0 (major-line layout).
    abase: &'s [usize],
    lay: SumLayout,
    data: &'s [f32],
    /// [`MajorLines::chunk`].
    chunk: usize,
    hb: i64,
    wa: i64,
    len: i64,
    d: i64,
    wrap: bool,
    /// Finite window: steps within R and the block length (see the module doc).
    r_steps: Option<(i64, i64)>,
    inv_step: f32,
    /// The curvature drop per major step², c' (0: none): samples are g = h − c'·u² at column
    /// u, a query at q starts from h0 − c'·q² and adds 2c'·q to its slope (module doc).
    cc: f64,
    /// The mirror azimuth swept along ([`Lines::mirror`]): the column e of its query column 0
    /// (its query column u' sits at column e − u' of these lines), and its query columns.
    mirror: Option<i64>,
    mq: &'s [QCol],
    /// The column of query column 0 (0 unless paired with a mirror: [`mirror_end`]).
    qoff: i64,
}

/// The far field of [`far_field`] in f32, 16 lines of a family at a time (AVX-512), the
/// curvature drop included: the same samples and hulls, so the same values up to f32 rounding
/// (tested against it). Each lane's hull is a stack, its top three vertices in registers (see
/// [`groups_avx512`]).
///
/// `mirror`: the opposite azimuth's lines as [`Lines::mirror`] of these, and its plane. Its
/// windows are these lines' windows seen from their other end: a window [s, s + R' − N] is
/// this azimuth's query at s − N looking right and the mirror's at s + R' looking left (with
/// a short window the two sets of windows overlap rather than coincide: [`mirror_end`]), so
/// one suffix pass and one prefix pass answer both, and the hull pushes (a large part of the
/// build) are shared by two azimuths. Only with a finite window (`edge=wrap`): the query
/// columns lie a multiple of the map's major size along the lines, on the same texels.
///
/// `fresh`: `out` was never touched (a plane of the far table, which is allocated zeroed and
/// so not yet mapped). The sums are then added up in the thread's scratch plane, already
/// mapped, and written to `out` once: adding into `out` itself would first map each of its
/// pages to the shared zero page (the add reads) and then copy it on the write, which costs a
/// TLB shootdown across the pool's threads per 4 KiB page.
#[allow(clippy::too_many_arguments)] // the planes, their scratch and how they are handed on
fn far_field_fast(
    grid: &Grid<'_>,
    ml: &MajorLines,
    lines: Lines,
    reach: Option<f64>,
    curv: f64,
    out: &mut [f32],
    sc: &mut Scratch,
    mut emit: Option<Emit<'_>>,
    fresh: bool,
    mut mirror: Option<(Lines, &mut [f32])>,
) {
    let (w, h) = (grid.width, grid.height);
    let (wa, hb) = if lines.major_x { (w, h) } else { (h, w) };
    let r_steps = reach.map(|r| (r / lines.step + 1e-9).floor() as i64);
    let d = NEAR as i64;
    if r_steps.is_some_and(|r| r < d) {
        if let Some(emit) = emit.as_deref_mut() {
            let zeros = vec![0.0f32; w * EMIT_ROWS.min(h)];
            for y0 in (0..h).step_by(EMIT_ROWS) {
                emit(y0 * w, &zeros[..EMIT_ROWS.min(h - y0) * w]);
            }
        }
        return;
    }
    let wrap = grid.edge == Edge::Wrap;
    // The mirror needs a window and lines that wrap; its query column 0 sits at column e.
    let e = match (&mirror, r_steps) {
        (Some((m, _)), Some(_)) if wrap => Some(m.at.0),
        _ => None,
    };
    debug_assert!(e.is_some() == mirror.is_some() && (e.is_none() || emit.is_none()));
    // Paired, the sweeps run over the lines' own columns (the mirror's are columns of these
    // lines too), this azimuth's texel u on column `qoff` + u; alone, over its look order.
    let (base, qoff) = match e {
        Some(_) => (Lines { at: (0, 1), ..lines }, lines.at.0),
        None => (lines, 0),
    };
    let len = match (wrap, r_steps) {
        (true, Some(r)) => (qoff + wa as i64 + r).max(e.map_or(0, |e| e - d + 1)),
        _ => wa as i64,
    };
    // The columns whose heights a query reads reach the mirror's last query column.
    let ncols = len.max(e.map_or(0, |e| e + 1));
    let hbi = hb as i64;
    let major = |u: i64| -> usize {
        let u = if wrap { u.rem_euclid(wa as i64) } else { u };
        (if lines.sign > 0 { u } else { wa as i64 - 1 - u }) as usize
    };
    // Sums are kept in major-line layout (`major · hb + minor`), so the 16 texels of a query
    // are contiguous; that is the image layout when the major axis is y.
    let mut fams = std::mem::take(&mut sc.fams);
    fams.clear();
    fams.extend((0..wa as i64).map(|u| lines.pair(u)));
    let (sh_lo, sh_hi) = fams
        .iter()
        .flatten()
        .fold((i64::MAX, i64::MIN), |(lo, hi), &(_, s, _)| (lo.min(s), hi.max(s)));
    let via_acc = lines.major_x || fresh;
    // Sums in the scratch planes are kept in chunks of CA minor texels (see `SumLayout`); in
    // `out` itself (the spill's planes along y), in its own layout.
    let lay = SumLayout { chunk: if via_acc { wa * CA } else { 0 } };
    let plane = if via_acc { hb.div_ceil(CA) * CA * wa } else { w * h };
    let planes = if e.is_some() { 2 } else { 1 };
    let mut acc = std::mem::take(&mut sc.acc);
    let mut acc2 = std::mem::take(&mut sc.acc2);
    // The scratch planes are all zeros between calls (`finish_avx512` clears what it reads),
    // so they are only resized (a separate clear was a pass over 64 MiB per pair at 2048²).
    for (p, (a, miss)) in
        [(&mut acc, &mut sc.miss), (&mut acc2, &mut sc.miss2)].into_iter().enumerate()
    {
        if p < planes {
            miss.resize(plane, 0.0);
            if via_acc {
                a.resize(plane, 0.0);
            }
        }
    }
    sc.st.resize(GROUPS * len as usize * FL, 0);
    sc.sb.resize(planes * (BATCH + GROUPS) * wa * FL, f32::NEG_INFINITY);
    let mut abase = std::mem::take(&mut sc.abase);
    abase.clear();
    abase.extend((0..wa as i64).map(|u| major(u) * lay.row(hb)));
    let mut abase2 = std::mem::take(&mut sc.abase2);
    let mut fams2: Vec<[(usize, i64, f64); 2]> = Vec::new();
    abase2.clear();
    if let Some((ml2, _)) = &mirror {
        // The mirror's own look order, as `major` for it (its query columns are on the map).
        let m2 = |u: i64| (if ml2.sign > 0 { u } else { wa as i64 - 1 - u }) as usize;
        abase2.extend((0..wa as i64).map(|u| m2(u) * lay.row(hb)));
        fams2.extend((0..wa as i64).map(|u| ml2.pair(u)));
    }
    let mut cols = std::mem::take(&mut sc.cols);
    let mut qs = std::mem::take(&mut sc.qs);
    let mut qs2 = std::mem::take(&mut sc.qs2);
    let (sums, sums2): (&mut [f32], &mut [f32]) = match (via_acc, mirror.as_mut()) {
        (true, _) => (&mut acc, &mut acc2),
        (false, Some((_, o2))) => (out, o2),
        (false, None) => (out, &mut acc2),
    };
    let q_col = |p: &[(usize, i64, f64); 2], k: usize| {
        let role = |r: usize| QCol {
            on: true,
            shift: if wrap { p[r].1.rem_euclid(hbi) } else { p[r].1 },
            wt: p[r].2 as f32,
            other: p[1 - r].2 as f32,
        };
        (0..2).find(|&r| p[r].0 == k).map_or(QCol::default(), role)
    };
    for k in 0..SUB {
        cols.clear();
        cols.extend((0..ncols).map(|u| {
            let (off, wt) = base.sample(k, u);
            let start = if wrap { off.rem_euclid(hbi) } else { off };
            Col { start, wt: wt as f32, wt0: wt == 0.0, row: major(u) * RW }
        }));
        qs.clear();
        qs.extend(fams.iter().map(|p| q_col(p, k)));
        qs2.clear();
        qs2.extend(fams2.iter().map(|p| q_col(p, k)));
        let fam = Family {
            cols: &cols,
            qs: &qs,
            abase: &abase,
            lay,
            data: &ml.data,
            chunk: ml.chunk,
            hb: hbi,
            wa: wa as i64,
            len,
            d,
            wrap,
            r_steps: r_steps.map(|r| (r, r - d + 1)),
            inv_step: (1.0 / lines.step) as f32,
            cc: curv * lines.step * lines.step,
            mirror: e,
            mq: &qs2,
            qoff,
        };
        // The mirror's sums are added as this family's with its query columns.
        let fam2 = Family { qs: &qs2, abase: &abase2, ..fam };
        let (i_lo, i_hi) = if wrap { (0, hbi - 1) } else { (sh_lo, hbi - 1 + sh_hi) };
        let mut i0 = i_lo;
        let mut batch = [(0i64, 0u32); BATCH + GROUPS];
        let mut nb = 0;
        while i0 <= i_hi {
            // Up to GROUPS groups of 16 lines side by side (a missing one has no lines).
            let mut gs = [(0i64, 0u32); GROUPS];
            let mut ng = 0;
            while ng < GROUPS && i0 <= i_hi {
                let nl = (i_hi - i0 + 1).min(FL as i64) as u32;
                gs[ng] = (i0, nl);
                batch[nb + ng] = (i0, nl);
                ng += 1;
                i0 += FL as i64;
            }
            #[cfg(target_arch = "x86_64")]
            // SAFETY: only called when the CPU has AVX-512F (see `Sweep::with_options`).
            unsafe {
                groups_avx512::<GROUPS>(&fam, gs, nb, sc)
            };
            nb += ng;
            if nb >= BATCH || i0 > i_hi {
                #[cfg(target_arch = "x86_64")]
                // SAFETY: as above.
                unsafe {
                    add_batch_avx512(&fam, &batch[..nb], 0, sums, &sc.sb, &mut sc.miss);
                    if e.is_some() {
                        let s0 = BATCH + GROUPS;
                        add_batch_avx512(&fam2, &batch[..nb], s0, sums2, &sc.sb, &mut sc.miss2);
                    }
                };
                nb = 0;
            }
        }
    }
    #[cfg(target_arch = "x86_64")]
    // SAFETY: only called when the CPU has AVX-512F (see `Sweep::with_options`).
    unsafe {
        finish_avx512(lines.major_x, via_acc, lay, emit, &mut acc, &mut sc.miss, out, w, h);
        if let Some((ml2, out2)) = mirror.as_mut().filter(|_| e.is_some()) {
            finish_avx512(ml2.major_x, via_acc, lay, None, &mut acc2, &mut sc.miss2, out2, w, h);
        }
    }
    sc.fams = fams;
    sc.acc = acc;
    sc.acc2 = acc2;
    sc.abase = abase;
    sc.abase2 = abase2;
    sc.cols = cols;
    sc.qs = qs;
    sc.qs2 = qs2;
}

/// The sums of a far-field plane (`acc` if `via_acc`, else already in `out`; see
/// [`SumLayout`]) divided by their weights where a role missed (`miss`), into `out` in the
/// image layout, or band by band to `emit` (the sweeps along x only); `acc` and `miss` are
/// left all zeros for the next plane. Along x, the sums are transposed 16×16 texels at a time
/// in registers (the scalar transpose was 4–5 % of a bake's profile).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
#[allow(clippy::too_many_arguments)] // the plane's layouts and where it goes
unsafe fn finish_avx512(
    major_x: bool,
    via_acc: bool,
    lay: SumLayout,
    emit: Option<Emit<'_>>,
    acc: &mut [f32],
    miss: &mut [f32],
    out: &mut [f32],
    w: usize,
    h: usize,
) {
    use std::arch::x86_64::*;
    // Helpers, not closures: a closure is compiled without the function's target features.
    let mask = |n: usize| if n >= 16 { 0xffff } else { ((1u32 << n) - 1) as u16 };
    if let (true, Some(emit)) = (major_x, emit) {
        // Transposed and normalised a band of rows at a time, each band handed on: no plane
        // in the image layout is ever whole. A band's rows lie in one chunk of the sums.
        let mut buf = vec![0.0f32; w * EMIT_ROWS.min(h)];
        for y0 in (0..h).step_by(EMIT_ROWS) {
            let ny = EMIT_ROWS.min(h - y0);
            for x0 in (0..w).step_by(16) {
                let nx = 16.min(w - x0);
                let t = take_block(lay, acc, miss, x0, y0, nx, ny, h);
                for (j, &v) in t.iter().enumerate().take(ny) {
                    _mm512_mask_storeu_ps(buf.as_mut_ptr().add(j * w + x0), mask(nx), v);
                }
            }
            emit(y0 * w, &buf[..ny * w]);
        }
    } else if major_x {
        let op = out.as_mut_ptr();
        for x0 in (0..w).step_by(16) {
            let nx = 16.min(w - x0);
            for y0 in (0..h).step_by(16) {
                let ny = 16.min(h - y0);
                let t = take_block(lay, acc, miss, x0, y0, nx, ny, h);
                for (j, &v) in t.iter().enumerate().take(ny) {
                    _mm512_mask_storeu_ps(op.add((y0 + j) * w + x0), mask(nx), v);
                }
            }
        }
    } else if via_acc {
        // Rows of the image are rows of the sums, a chunk's run at a time.
        for y in 0..h {
            for x0 in (0..w).step_by(16) {
                let n = 16.min(w - x0);
                let v = take16(acc, miss, lay.at(y * lay.row(w), x0), n);
                _mm512_mask_storeu_ps(out.as_mut_ptr().add(y * w + x0), mask(n), v);
            }
        }
    } else {
        for (o, ws) in out.iter_mut().zip(miss.iter_mut()) {
            if *ws > 0.0 {
                *o /= *ws;
            }
            *ws = 0.0;
        }
    }
}

/// The normalised sums of 16 texels at `o` (the first `n`; the rest 0), cleared.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
#[inline]
unsafe fn take16(
    acc: &mut [f32],
    miss: &mut [f32],
    o: usize,
    n: usize,
) -> std::arch::x86_64::__m512 {
    use std::arch::x86_64::*;
    let zero = _mm512_setzero_ps();
    let m = if n >= 16 { 0xffff } else { ((1u32 << n) - 1) as u16 };
    let (pa, pm) = (acc.as_mut_ptr().add(o), miss.as_mut_ptr().add(o));
    let (a, ws) = (_mm512_maskz_loadu_ps(m, pa), _mm512_maskz_loadu_ps(m, pm));
    _mm512_mask_storeu_ps(pa, m, zero);
    _mm512_mask_storeu_ps(pm, m, zero);
    let div = _mm512_cmp_ps_mask::<_CMP_GT_OQ>(ws, zero);
    _mm512_mask_div_ps(a, div, a, ws)
}

/// Along x: the normalised sums of columns x0 .. x0 + `nx` and rows y0 .. y0 + `ny` (minor
/// size `h`), cleared, transposed: element j of the result is row y0 + j.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
#[inline]
#[allow(clippy::too_many_arguments)] // the block and its layout
unsafe fn take_block(
    lay: SumLayout,
    acc: &mut [f32],
    miss: &mut [f32],
    x0: usize,
    y0: usize,
    nx: usize,
    ny: usize,
    h: usize,
) -> [std::arch::x86_64::__m512; 16] {
    use std::arch::x86_64::*;
    let mut r = [_mm512_setzero_ps(); 16];
    for (i, v) in r.iter_mut().enumerate().take(nx) {
        *v = take16(acc, miss, lay.at((x0 + i) * lay.row(h), y0), ny);
    }
    transpose16(r)
}

/// The 16×16 transpose of `r` (row i: r[i]) in registers: 64 shuffles.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
#[inline]
unsafe fn transpose16(r: [std::arch::x86_64::__m512; 16]) -> [std::arch::x86_64::__m512; 16] {
    use std::arch::x86_64::*;
    let mut t = [_mm512_setzero_ps(); 16];
    for k in 0..8 {
        t[2 * k] = _mm512_unpacklo_ps(r[2 * k], r[2 * k + 1]);
        t[2 * k + 1] = _mm512_unpackhi_ps(r[2 * k], r[2 * k + 1]);
    }
    // Within each 128-bit lane l of u[4j + c]: column 4l + c of rows 4j .. 4j + 4.
    let mut u = [_mm512_setzero_ps(); 16];
    for j in 0..4 {
        let (a, b) = (_mm512_castps_pd(t[4 * j]), _mm512_castps_pd(t[4 * j + 1]));
        let (c, d) = (_mm512_castps_pd(t[4 * j + 2]), _mm512_castps_pd(t[4 * j + 3]));
        u[4 * j] = _mm512_castpd_ps(_mm512_unpacklo_pd(a, c));
        u[4 * j + 1] = _mm512_castpd_ps(_mm512_unpackhi_pd(a, c));
        u[4 * j + 2] = _mm512_castpd_ps(_mm512_unpacklo_pd(b, d));
        u[4 * j + 3] = _mm512_castpd_ps(_mm512_unpackhi_pd(b, d));
    }
    let mut o = [_mm512_setzero_ps(); 16];
    for c in 0..4 {
        let v0 = _mm512_shuffle_f32x4::<0x88>(u[c], u[4 + c]);
        let w0 = _mm512_shuffle_f32x4::<0xdd>(u[c], u[4 + c]);
        let v1 = _mm512_shuffle_f32x4::<0x88>(u[8 + c], u[12 + c]);
        let w1 = _mm512_shuffle_f32x4::<0xdd>(u[8 + c], u[12 + c]);
        o[c] = _mm512_shuffle_f32x4::<0x88>(v0, v1);
        o[4 + c] = _mm512_shuffle_f32x4::<0x88>(w0, w1);
        o[8 + c] = _mm512_shuffle_f32x4::<0xdd>(v0, v1);
        o[12 + c] = _mm512_shuffle_f32x4::<0xdd>(w0, w1);
    }
    o
}

/// Minor texels per chunk of the far field's sums (see [`SumLayout`]).
const CA: usize = 128;

/// Where the sums of a far-field plane are kept: with `chunk` = 0 in major-line layout
/// (`major · hb + minor`), else in chunks of [`CA`] minor texels, each chunk (`chunk` floats)
/// every major line's run of CA in turn (`(minor / CA) · chunk + major · CA + minor % CA`).
/// The tangents of a batch of 8 groups of lines go into 128 adjacent texels of one query
/// column after another, so in major-line layout every column's run was a new row, a new page
/// (8 KiB rows at 2048²), and the adds waited on those misses even prefetched (more than half
/// of [`add_batch_avx512`]'s profile); in chunks, a page holds 8 columns' runs.
#[derive(Clone, Copy)]
struct SumLayout {
    chunk: usize,
}

impl SumLayout {
    /// The floats a major line's run takes within a chunk (the whole minor size `hb` when
    /// not chunked).
    #[inline(always)]
    fn row(self, hb: usize) -> usize {
        if self.chunk == 0 {
            hb
        } else {
            CA
        }
    }

    /// The offset of minor `b` of the line whose run starts at `base` (major · [`Self::row`]).
    #[inline(always)]
    fn at(self, base: usize, b: usize) -> usize {
        if self.chunk == 0 {
            base + b
        } else {
            (b / CA) * self.chunk + base + b % CA
        }
    }
}

/// For the group of `nl` lines from `i0` at a query column whose lines lie `shift` from its
/// texels: the lanes whose texel is in the map, and lane 0's minor (reduced modulo the map
/// with `edge=wrap`, where every lane's texel is).
#[inline]
fn texels_at(f: &Family<'_>, i0: i64, nl: u32, shift: i64) -> (u16, i64) {
    let b0 = i0 - shift;
    if f.wrap {
        let all = if nl >= 16 { 0xffff } else { ((1u32 << nl) - 1) as u16 };
        (all, b0.rem_euclid(f.hb))
    } else {
        (lane_range(b0, f.hb, nl), b0)
    }
}

/// The lanes (bit l: lane l) whose minor b0 + l lies in 0..lim, of the first `nl`.
#[inline]
fn lane_range(b0: i64, lim: i64, nl: u32) -> u16 {
    let lo = (-b0).clamp(0, 16) as u32;
    let hi = (lim - b0).clamp(0, nl as i64) as u32;
    if hi <= lo {
        return 0;
    }
    let upto = |n: u32| if n >= 16 { 0xffffu16 } else { ((1u32 << n) - 1) as u16 };
    upto(hi) & !upto(lo)
}

/// The lanes of `m` of (t, y) into the packed stack `st` at the entries `i` (see
/// [`Scratch::st`]): two scatters of 8 entries, not two of 16 (a gather or scatter costs by
/// the entry here).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
#[inline]
unsafe fn spill(
    st: *mut i64,
    m: u16,
    i: std::arch::x86_64::__m512i,
    t: std::arch::x86_64::__m512i,
    y: std::arch::x86_64::__m512,
) {
    use std::arch::x86_64::*;
    let y = _mm512_castps_si512(y);
    let lo = _mm512_permutex2var_epi32(
        t,
        _mm512_setr_epi32(0, 16, 1, 17, 2, 18, 3, 19, 4, 20, 5, 21, 6, 22, 7, 23),
        y,
    );
    let hi = _mm512_permutex2var_epi32(
        t,
        _mm512_setr_epi32(8, 24, 9, 25, 10, 26, 11, 27, 12, 28, 13, 29, 14, 30, 15, 31),
        y,
    );
    _mm512_mask_i32scatter_epi64::<8>(st, m as u8, _mm512_castsi512_si256(i), lo);
    _mm512_mask_i32scatter_epi64::<8>(st, (m >> 8) as u8, _mm512_extracti64x4_epi64::<1>(i), hi);
}

/// The entries `i` of the packed stack `st` into the lanes of `m` of (t, y).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
#[inline]
unsafe fn refill(
    st: *const i64,
    m: u16,
    i: std::arch::x86_64::__m512i,
    t: std::arch::x86_64::__m512i,
    y: std::arch::x86_64::__m512,
) -> (std::arch::x86_64::__m512i, std::arch::x86_64::__m512) {
    use std::arch::x86_64::*;
    let z = _mm512_setzero_si512();
    let lo = _mm512_mask_i32gather_epi64::<8>(z, m as u8, _mm512_castsi512_si256(i), st);
    let hi =
        _mm512_mask_i32gather_epi64::<8>(z, (m >> 8) as u8, _mm512_extracti64x4_epi64::<1>(i), st);
    unpack(m, lo, hi, t, y)
}

/// Lanes 0–7 (`lo`) and 8–15 (`hi`) of packed entries into the lanes of `m` of (t, y).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
#[inline]
unsafe fn unpack(
    m: u16,
    lo: std::arch::x86_64::__m512i,
    hi: std::arch::x86_64::__m512i,
    t: std::arch::x86_64::__m512i,
    y: std::arch::x86_64::__m512,
) -> (std::arch::x86_64::__m512i, std::arch::x86_64::__m512) {
    use std::arch::x86_64::*;
    let even = _mm512_setr_epi32(0, 2, 4, 6, 8, 10, 12, 14, 16, 18, 20, 22, 24, 26, 28, 30);
    let odd = _mm512_setr_epi32(1, 3, 5, 7, 9, 11, 13, 15, 17, 19, 21, 23, 25, 27, 29, 31);
    let nt = _mm512_permutex2var_epi32(lo, even, hi);
    let ny = _mm512_castsi512_ps(_mm512_permutex2var_epi32(lo, odd, hi));
    (_mm512_mask_mov_epi32(t, m, nt), _mm512_mask_mov_ps(y, m, ny))
}

/// `G` groups of up to 16 lines of a family (group g: lines `gs[g].0 ..` `+ gs[g].1`, its
/// tangents into batch slot `slot0 + g`; a group of 0 lines does nothing), swept in lockstep:
/// the suffix (or whole-line) pass right to left, then with a finite window the prefix pass
/// left to right, the weighted tangents into the slots (and the missing weights into
/// `sc.miss`; major-line layout) by [`add_batch_avx512`].
///
/// Each lane's hull is a stack: the three vertices nearest the sweep's position in registers
/// (t1, t2, t3: column and height), the rest in memory by depth ([`Scratch::st`], a region
/// per group), a few KiB that stay in L1. A push spills t3 (one masked scatter), a pop
/// refills it (one masked gather, needed only a pop later), so short pops and query walks
/// wait for nothing; the prefix pass's queries walk the stack from its bottom with plain
/// loads.
///
/// Why several groups at once: a group's pops and tangent walks are one chain of dependent
/// compares, gathers and data-dependent branches, so one group alone leaves the core waiting
/// on latency. The groups of a call share every column (the same family), so their chains
/// run side by side in one loop, and each loop exit (a branch that mispredicts) is paid once
/// for all of them (measured: [`GROUPS`]).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn groups_avx512<const G: usize>(
    f: &Family<'_>,
    gs: [(i64, u32); G],
    slot0: usize,
    sc: &mut Scratch,
) {
    use std::arch::x86_64::*;
    let wa = f.wa as usize;
    let lane = _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
    let none = _mm512_set1_epi32(-1);
    let zero_i = _mm512_setzero_si512();
    let one_i = _mm512_set1_epi32(1);
    let ninf = _mm512_set1_ps(f32::NEG_INFINITY);
    let data = f.data.as_ptr();
    let region = f.len as usize * FL;
    let (i0, nl) = (gs.map(|g| g.0), gs.map(|g| g.1));
    let all = nl.map(|n| if n >= 16 { 0xffff } else { ((1u32 << n) - 1) as u16 });
    let mut sb = [std::ptr::null_mut::<f32>(); G];
    let mut sbm = [std::ptr::null_mut::<f32>(); G];
    let mut st = [std::ptr::null_mut::<i64>(); G];
    // Samples and queries' heights copied first where the passes are two (see below).
    let copied = f.r_steps.is_some();
    if copied {
        sc.ss.resize(f.len.max(0) as usize * G * FL, 0.0);
        sc.sh.resize(wa * 2 * G * FL, 0.0);
    }
    let (ss, sh) = (sc.ss.as_mut_ptr(), sc.sh.as_mut_ptr());
    for g in 0..G {
        // This group's tangents: its slot of the batch; the query columns the suffix pass does
        // not reach (within N of the line's end) have none.
        let slot = &mut sc.sb[(slot0 + g) * wa * FL..][..wa * FL];
        slot[(f.len - f.d - f.qoff).clamp(0, f.wa) as usize * FL..].fill(f32::NEG_INFINITY);
        sb[g] = slot.as_mut_ptr();
        st[g] = sc.st.as_mut_ptr().add(g * region);
        if f.mirror.is_some() {
            // The mirror's tangents: the same slot in the second half of the batch's slots.
            sbm[g] = sc.sb[(BATCH + GROUPS + slot0 + g) * wa * FL..][..wa * FL].as_mut_ptr();
        }
    }
    // The hulls' registers and memory depths, per group.
    let (mut t1, mut t2, mut t3, mut dep) = ([none; G], [none; G], [none; G], [zero_i; G]);
    let (mut y1, mut y2, mut y3) = ([ninf; G], [ninf; G], [ninf; G]);
    // The highest sample since the last reset, per group (read by the prefix pass only).
    let mut hmax = [ninf; G];
    macro_rules! reset {
        () => {{
            (t1, t2, t3, dep) = ([none; G], [none; G], [none; G], [zero_i; G]);
            (y1, y2, y3) = ([ninf; G], [ninf; G], [ninf; G]);
            hmax = [ninf; G];
        }};
    }
    macro_rules! idx {
        ($t:expr) => {
            _mm512_add_epi32(_mm512_slli_epi32::<4>($t), lane)
        };
    }
    macro_rules! load_h0 {
        ($q:expr, $b0:expr) => {
            _mm512_loadu_ps(data.offset(MajorLines::at(f.chunk, f.cols[$q as usize].row, $b0)))
        };
    }
    // A query at column q (query column `qc`; from the right if `$mir`): its abscissa, the
    // slope's curvature term, and per group the lanes whose texel is on the map and whose hull
    // is not empty, with their heights on the hulls of g (module doc).
    macro_rules! query_at {
        ($q:expr, $qc:expr, $mir:expr, $k:expr) => {{
            let q = $q;
            let shift = $qc.shift;
            let q_drop = _mm512_set1_ps((f.cc * (q * q) as f64) as f32);
            let (mut qm, mut hq) = ([0u16; G], [ninf; G]);
            let row = sh.wrapping_add((($k as usize) * 2 + usize::from($mir)) * G * FL);
            for g in 0..G {
                let (tm, b0) = texels_at(f, i0[g], nl[g], shift);
                qm[g] = tm & _mm512_cmpge_epi32_mask(t1[g], zero_i);
                if qm[g] != 0 {
                    let h = if copied { _mm512_loadu_ps(row.add(g * FL)) } else { load_h0!(q, b0) };
                    hq[g] = _mm512_sub_ps(h, q_drop);
                }
            }
            let corr = 2.0 * f.cc * q as f64;
            let corr = if $mir { -corr } else { corr };
            (_mm512_set1_ps(q as f32), _mm512_set1_ps(corr as f32), qm, hq)
        }};
    }
    // Lanes of group g whose sample at column c (column u) is on the surface, and their
    // samples (copied beforehand with two passes, see below; else read here).
    macro_rules! lanes_at {
        ($c:expr, $g:expr) => {{
            let (c, g) = ($c, $g);
            let s = c.start + i0[g];
            if f.wrap {
                all[g]
            } else {
                lane_range(s, f.hb - 1 + i64::from(c.wt0), nl[g])
            }
        }};
    }
    // The sample of group g at column c, from the major lines.
    macro_rules! lerp_at {
        ($c:expr, $g:expr) => {{
            let (c, g) = ($c, $g);
            let mut s = c.start + i0[g];
            if f.wrap && s >= f.hb {
                s -= f.hb;
            }
            let p = data.offset(MajorLines::at(f.chunk, c.row, s));
            let a = _mm512_loadu_ps(p);
            let b = _mm512_loadu_ps(p.add(1));
            _mm512_add_ps(a, _mm512_mul_ps(_mm512_sub_ps(b, a), _mm512_set1_ps(c.wt)))
        }};
    }
    // Prefetches the heights of column u's samples.
    macro_rules! prefetch {
        ($u:expr) => {{
            let u = $u;
            if (0..f.len).contains(&u) {
                let c = f.cols[u as usize];
                for g in 0..G {
                    let s = (c.start + i0[g]).clamp(-(PADM as i64), f.hb + 1);
                    let s = if f.wrap && s >= f.hb { s - f.hb } else { s };
                    let p = data.wrapping_offset(MajorLines::at(f.chunk, c.row, s));
                    _mm_prefetch::<_MM_HINT_T0>(p as *const i8);
                    _mm_prefetch::<_MM_HINT_T0>(p.wrapping_add(16) as *const i8);
                }
            }
        }};
    }
    macro_rules! sample {
        ($c:expr, $g:expr, $u:expr) => {{
            let (c, g, u) = ($c, $g, $u as usize);
            let vm = lanes_at!(c, g);
            let v = if vm == 0 {
                ninf
            } else if copied {
                _mm512_loadu_ps(ss.add((u * G + g) * FL))
            } else {
                lerp_at!(c, g)
            };
            (vm, v)
        }};
    }
    // Pops the lanes of `pm` of group g: t1 ← t2 ← t3, which leaves a hole in t3 (−1 with
    // vertices left in memory); only a lane that had a hole already refills t2 from memory (a
    // gather). So a pop after a push, or a push after a pop, moves nothing between registers
    // and memory.
    macro_rules! pop {
        ($g:expr, $pm:expr) => {{
            let (g, pm) = ($g, $pm);
            let gm = pm
                & _mm512_cmplt_epi32_mask(t3[g], zero_i)
                & _mm512_cmpgt_epi32_mask(dep[g], zero_i);
            t1[g] = _mm512_mask_mov_epi32(t1[g], pm, t2[g]);
            y1[g] = _mm512_mask_mov_ps(y1[g], pm, y2[g]);
            t2[g] = _mm512_mask_mov_epi32(t2[g], pm, t3[g]);
            y2[g] = _mm512_mask_mov_ps(y2[g], pm, y3[g]);
            t3[g] = _mm512_mask_mov_epi32(t3[g], pm, none);
            if gm != 0 {
                dep[g] = _mm512_mask_sub_epi32(dep[g], gm, dep[g], one_i);
                let i = idx!(dep[g]);
                (t2[g], y2[g]) = refill(st[g], gm, i, t2[g], y2[g]);
            }
        }};
    }
    // Pushes column u (value v) for the lanes of vm of group g, spilling t3 where it is not a
    // hole.
    macro_rules! push {
        ($g:expr, $vm:expr, $u:expr, $v:expr) => {{
            let (g, vm) = ($g, $vm);
            let sm = _mm512_mask_cmpge_epi32_mask(vm, t3[g], zero_i);
            if sm != 0 {
                let i = idx!(dep[g]);
                spill(st[g], sm, i, t3[g], y3[g]);
                dep[g] = _mm512_mask_add_epi32(dep[g], sm, dep[g], one_i);
            }
            t3[g] = _mm512_mask_mov_epi32(t3[g], vm, t2[g]);
            y3[g] = _mm512_mask_mov_ps(y3[g], vm, y2[g]);
            t2[g] = _mm512_mask_mov_epi32(t2[g], vm, t1[g]);
            y2[g] = _mm512_mask_mov_ps(y2[g], vm, y1[g]);
            t1[g] = _mm512_mask_mov_epi32(t1[g], vm, _mm512_set1_epi32($u as i32));
            y1[g] = _mm512_mask_mov_ps(y1[g], vm, $v);
        }};
    }
    // Samples column u for every group, pops while t1 lies on or below the chord from the
    // sample to t2 (`$keep(x1, x2, y1, y2, v)`: the lanes keeping t1), and pushes the sample.
    // A round tests t1 against t2 and, where t1 goes and t3 is in a register, t2 against t3
    // (what the next round would test after popping t1), so it pops up to two vertices.
    macro_rules! step {
        ($u:expr, $track:expr, $keep:expr) => {{
            let u = $u;
            let c = f.cols[u as usize];
            let (mut vm, mut v) = ([0u16; G], [ninf; G]);
            let mut any = 0u16;
            for g in 0..G {
                (vm[g], v[g]) = sample!(c, g, u);
                any |= vm[g];
            }
            if any != 0 {
                let xp = _mm512_set1_ps(u as f32);
                if f.cc != 0.0 {
                    let drop = _mm512_set1_ps((f.cc * (u * u) as f64) as f32);
                    for g in 0..G {
                        v[g] = _mm512_sub_ps(v[g], drop);
                    }
                }
                let keep = $keep;
                let mut act = vm;
                loop {
                    let (mut p1, mut p2, mut more) = ([0u16; G], [0u16; G], [0u16; G]);
                    let mut anyp = 0u16;
                    for g in 0..G {
                        let has2 = _mm512_mask_cmpge_epi32_mask(act[g], t2[g], zero_i);
                        let x1 = _mm512_cvtepi32_ps(t1[g]);
                        let x2 = _mm512_cvtepi32_ps(t2[g]);
                        let x3 = _mm512_cvtepi32_ps(t3[g]);
                        p1[g] = has2 & !keep(x1, x2, y1[g], y2[g], v[g], xp);
                        let has3 = _mm512_mask_cmpge_epi32_mask(p1[g], t3[g], zero_i);
                        p2[g] = has3 & !keep(x2, x3, y2[g], y3[g], v[g], xp);
                        more[g] = p2[g] | (p1[g] & !has3);
                        anyp |= p1[g];
                    }
                    if anyp == 0 {
                        break;
                    }
                    let mut anym = 0u16;
                    for g in 0..G {
                        pop!(g, p1[g]);
                        if p2[g] != 0 {
                            pop!(g, p2[g]);
                        }
                        act[g] = more[g];
                        anym |= more[g];
                    }
                    if anym == 0 {
                        break;
                    }
                }
                for g in 0..G {
                    push!(g, vm[g], u, v[g]);
                    if $track {
                        hmax[g] = _mm512_mask_max_ps(hmax[g], vm[g], hmax[g], v[g]);
                    }
                }
            }
        }};
    }
    // Tangent walks. A query from the left (this azimuth) looks at slopes (y − hq)/(x − xq), one
    // from the right (the mirror azimuth, see `far_field_fast`) at (y − hq)/(xq − x): the same
    // compares with the abscissae's differences negated, and its curvature term is −2c'p.
    macro_rules! dx {
        ($x:expr, $xq:expr, $mir:expr) => {
            if $mir {
                _mm512_sub_ps($xq, $x)
            } else {
                _mm512_sub_ps($x, $xq)
            }
        };
    }
    // Tangent walks. A query from the left (this azimuth) looks at slopes (y − hq)/(x − xq), one
    // from the right (the mirror azimuth, see `far_field_fast`) at (y − hq)/(xq − x): the same
    // compares with the abscissae's differences negated, and its curvature term is −2c'p.
    //
    // The slope from a query to the vertices of a convex hull rises and then falls, so the
    // tangent is the first vertex whose successor does not rise, and whether one vertex's
    // successor rises does not depend on where the walk came from. So a walk compares several
    // pairs of consecutive vertices at once, independently, and takes the first that stops:
    // the same vertex, compared by the same operations, as a walk one vertex at a time, but
    // with one dependent round (and one loop exit) per [`WALK`] vertices rather than per
    // vertex.
    //
    // Whether the slope from the query to (nx, ny) is above that to (cx, cy), for the lanes
    // of `am` of group g.
    macro_rules! rises {
        ($am:expr, $g:expr, $xq:expr, $hq:expr, $mir:expr, $cx:expr, $cy:expr, $nx:expr, $ny:expr) => {{
            let lhs = _mm512_mul_ps(_mm512_sub_ps($ny, $hq[$g]), dx!($cx, $xq, $mir));
            let rhs = _mm512_mul_ps(_mm512_sub_ps($cy, $hq[$g]), dx!($nx, $xq, $mir));
            _mm512_mask_cmp_ps_mask::<_CMP_GT_OQ>($am, lhs, rhs)
        }};
    }
    // The tangent from the query (xq, hq) of groups' lanes qm, walked from the top of each
    // lane's stack: t1 (the vertex nearest the query), t2 and t3 compared in one round, then
    // [`WALK`] vertices of memory a round (independent gathers): per group its vertex (x, y).
    macro_rules! near_walk {
        ($xq:expr, $hq:expr, $qm:expr, $mir:expr) => {{
            let (xq, hq, qm) = ($xq, $hq, $qm);
            let (mut cur_x, mut cur_y) = ([ninf; G], [ninf; G]);
            let mut m = [0u16; G];
            let mut below = dep;
            let mut any = 0u16;
            for g in 0..G {
                let x1 = _mm512_cvtepi32_ps(t1[g]);
                let x2 = _mm512_cvtepi32_ps(t2[g]);
                let x3 = _mm512_cvtepi32_ps(t3[g]);
                let a1 = _mm512_mask_cmpge_epi32_mask(qm[g], t2[g], zero_i);
                let r1 = rises!(a1, g, xq, hq, $mir, x1, y1[g], x2, y2[g]);
                let v3 = _mm512_mask_cmpge_epi32_mask(r1, t3[g], zero_i);
                let r2 = rises!(v3, g, xq, hq, $mir, x2, y2[g], x3, y3[g]);
                cur_x[g] = _mm512_mask_mov_ps(_mm512_mask_mov_ps(x1, r1, x2), r2, x3);
                cur_y[g] = _mm512_mask_mov_ps(_mm512_mask_mov_ps(y1[g], r1, y2[g]), r2, y3[g]);
                m[g] = r2 | (r1 & !v3);
                any |= m[g];
            }
            while any != 0 {
                any = 0;
                for g in 0..G {
                    if m[g] == 0 {
                        continue;
                    }
                    let mut nt = [none; WALK];
                    let mut ny = [ninf; WALK];
                    let mut gm = [0u16; WALK];
                    for k in 0..WALK {
                        let kv = _mm512_set1_epi32(k as i32);
                        gm[k] = _mm512_mask_cmpgt_epi32_mask(m[g], below[g], kv);
                        let i = idx!(_mm512_sub_epi32(below[g], _mm512_set1_epi32(k as i32 + 1)));
                        (nt[k], ny[k]) = refill(st[g], gm[k], i, none, ninf);
                    }
                    let (mut px, mut py) = (cur_x[g], cur_y[g]);
                    let mut r = 0xffffu16;
                    for k in 0..WALK {
                        let nx = _mm512_cvtepi32_ps(nt[k]);
                        r = rises!(r & gm[k], g, xq, hq, $mir, px, py, nx, ny[k]);
                        cur_x[g] = _mm512_mask_mov_ps(cur_x[g], r, nx);
                        cur_y[g] = _mm512_mask_mov_ps(cur_y[g], r, ny[k]);
                        (px, py) = (nx, ny[k]);
                    }
                    below[g] = _mm512_mask_sub_epi32(
                        below[g],
                        r,
                        below[g],
                        _mm512_set1_epi32(WALK as i32),
                    );
                    m[g] = r;
                    any |= r;
                }
            }
            (cur_x, cur_y)
        }};
    }
    // The same tangent walked from the bottom of each lane's stack (the vertex nearest a query
    // on the other side): memory rows 0 .. dep with plain loads, then the registers, [`WALK`]
    // vertices a round.
    macro_rules! far_walk {
        ($xq:expr, $hq:expr, $qm:expr, $mir:expr) => {{
            let (xq, hq, qm) = ($xq, $hq, $qm);
            // The registers' vertices bottom up: [t3, t2, t1] without the empty ones.
            let (mut r0t, mut r0y, mut r1t, mut r1y) = ([none; G], [ninf; G], [none; G], [ninf; G]);
            for g in 0..G {
                if qm[g] == 0 {
                    continue;
                }
                let has3 = _mm512_cmpge_epi32_mask(t3[g], zero_i);
                let has2 = _mm512_cmpge_epi32_mask(t2[g], zero_i);
                r0t[g] =
                    _mm512_mask_mov_epi32(_mm512_mask_mov_epi32(t1[g], has2, t2[g]), has3, t3[g]);
                r0y[g] = _mm512_mask_mov_ps(_mm512_mask_mov_ps(y1[g], has2, y2[g]), has3, y3[g]);
                r1t[g] = _mm512_mask_mov_epi32(t1[g], has3, t2[g]);
                r1y[g] = _mm512_mask_mov_ps(y1[g], has3, y2[g]);
            }
            // Vertex j of a lane's hull from the bottom, group g (t1 again past its last).
            let at = |g: usize, j: i32| -> (__m512i, __m512) {
                let jv = _mm512_set1_epi32(j);
                let k = _mm512_sub_epi32(jv, dep[g]);
                let (mut t, mut y) = (t1[g], y1[g]);
                let k1 = _mm512_cmpeq_epi32_mask(k, one_i);
                t = _mm512_mask_mov_epi32(t, k1, r1t[g]);
                y = _mm512_mask_mov_ps(y, k1, r1y[g]);
                let k0 = _mm512_cmpeq_epi32_mask(k, zero_i);
                t = _mm512_mask_mov_epi32(t, k0, r0t[g]);
                y = _mm512_mask_mov_ps(y, k0, r0y[g]);
                let mm = _mm512_cmpgt_epi32_mask(dep[g], jv);
                if mm != 0 {
                    let row = st[g].add(j as usize * FL);
                    let lo = _mm512_maskz_loadu_epi64(mm as u8, row);
                    let hi = _mm512_maskz_loadu_epi64((mm >> 8) as u8, row.add(8));
                    (t, y) = unpack(mm, lo, hi, t, y);
                }
                (t, y)
            };
            let (mut cur_t, mut cur_y, mut cur_x) = ([none; G], [ninf; G], [ninf; G]);
            let mut m = qm;
            let mut any = 0u16;
            for g in 0..G {
                if qm[g] != 0 {
                    (cur_t[g], cur_y[g]) = at(g, 0);
                    cur_x[g] = _mm512_cvtepi32_ps(cur_t[g]);
                    any |= qm[g];
                }
            }
            let mut j = 0;
            while any != 0 {
                any = 0;
                for g in 0..G {
                    let mut r = m[g] & _mm512_cmpneq_epi32_mask(cur_t[g], t1[g]);
                    if r == 0 {
                        m[g] = 0;
                        continue;
                    }
                    let mut nv = [(none, ninf); WALK];
                    for k in 0..WALK {
                        nv[k] = at(g, j + 1 + k as i32);
                    }
                    let (mut pt, mut px, mut py) = (cur_t[g], cur_x[g], cur_y[g]);
                    for k in 0..WALK {
                        let (nt, ny) = nv[k];
                        let nx = _mm512_cvtepi32_ps(nt);
                        if k > 0 {
                            r &= _mm512_cmpneq_epi32_mask(pt, t1[g]);
                        }
                        r = rises!(r, g, xq, hq, $mir, px, py, nx, ny);
                        cur_t[g] = _mm512_mask_mov_epi32(cur_t[g], r, nt);
                        cur_x[g] = _mm512_mask_mov_ps(cur_x[g], r, nx);
                        cur_y[g] = _mm512_mask_mov_ps(cur_y[g], r, ny);
                        (pt, px, py) = (nt, nx, ny);
                    }
                    m[g] = r;
                    any |= r;
                }
                j += WALK as i32;
            }
            (cur_x, cur_y)
        }};
    }
    // A query's tangents from its walk's vertices into the slots `$sb` at query index `$k`:
    // stored (the first of its two parts, every group's lanes, −∞ where none) or joined by
    // max (the second, only the groups with lanes).
    macro_rules! put {
        ($sb:expr, $k:expr, $xq:expr, $hq:expr, $qm:expr, $corr:expr, $cur:expr, $mir:expr,
         $join:expr) => {{
            let (xq, hq, qm, corr, (cur_x, cur_y)) = ($xq, $hq, $qm, $corr, $cur);
            for g in 0..G {
                if $join && qm[g] == 0 {
                    continue;
                }
                let mut res = ninf;
                if qm[g] != 0 {
                    let slope =
                        _mm512_div_ps(_mm512_sub_ps(cur_y[g], hq[g]), dx!(cur_x[g], xq, $mir));
                    res = _mm512_mask_mov_ps(res, qm[g], _mm512_add_ps(slope, corr));
                }
                let p = $sb[g].add($k as usize * FL);
                if $join {
                    let old = _mm512_loadu_ps(p);
                    res = _mm512_mask_max_ps(old, qm[g], old, res);
                }
                _mm512_storeu_ps(p, res);
            }
        }};
    }
    let blocked = f.r_steps.is_some();
    let blk = f.r_steps.map_or(i64::MAX, |(_, b)| b);
    let r = f.r_steps.map_or(0, |(r, _)| r);
    // The windows' first columns: this azimuth's q + N for q < W, the mirror's p − R' for its
    // query columns p = e − u', u' < W (the mirror exists only with a finite window).
    let (s_lo, s_hi) = match f.mirror {
        Some(e) => ((f.qoff + f.d).min(e - f.wa + 1 - r), (f.qoff + f.wa - 1 + f.d).max(e - r)),
        None => (f.d, f.wa - 1 + f.d),
    };
    // The suffix pass needs the samples up to the end of the block of the last window.
    let last = if blocked { (s_hi / blk + 1) * blk - 1 } else { f.len - 1 };
    // With two passes (a finite window), every sample they read (columns s_lo ..) and every
    // query's height is copied first into contiguous scratch, a few hundred KiB that stay in
    // L2. In the sweeps, a chain of dependent compares and branches, those loads waited for
    // memory even prefetched (at 2048², the sample and height loads and their prefetches were
    // a fifth of the sweeps' profile, at 512², all in L2, a twentieth); this loop has no chain,
    // so its misses overlap, and each column is read once for both passes. Measured at 2048²,
    // 32 bins (interleaved timing binaries, best of three, with the chunked major lines): the
    // build's CPU time −11 % at `unlimited` with `edge=wrap`, −17 % at R = 64. With one pass
    // (`edge=none` unlimited) the copy cost more than it saved (+8 %), so that pass reads the
    // major lines itself, prefetched.
    const PF: i64 = 24;
    for u in s_lo.max(0)..f.len {
        if !copied {
            break;
        }
        prefetch!(u + PF);
        let c = f.cols[u as usize];
        for g in 0..G {
            if lanes_at!(c, g) != 0 {
                _mm512_storeu_ps(ss.add((u as usize * G + g) * FL), lerp_at!(c, g));
            }
        }
    }
    for (mir, qcs) in [(0, f.qs), (1, f.mq)] {
        if !copied {
            break;
        }
        for (k, qc) in qcs.iter().enumerate() {
            if !qc.on {
                continue;
            }
            // This azimuth's query column k sits at column qoff + k, the mirror's at e − k.
            let q = if mir == 0 { f.qoff + k as i64 } else { f.mirror.unwrap_or(0) - k as i64 };
            let row = sh.add((k * 2 + mir) * G * FL);
            for g in 0..G {
                let (tm, b0) = texels_at(f, i0[g], nl[g], qc.shift);
                if tm != 0 {
                    _mm512_storeu_ps(row.add(g * FL), load_h0!(q, b0));
                }
            }
        }
    }
    // Suffix (or whole-line) pass, right to left.
    for up in (s_lo..=last.min(f.len - 1)).rev() {
        if blocked && up % blk == blk - 1 {
            reset!();
        }
        if !copied {
            // The queries' heights (the first to touch a row; the samples read it N later).
            prefetch!(up - f.d - 12);
        }
        // Keep t1 where the slope p→t1 is above t1→t2.
        step!(up, false, |x1: __m512,
                          x2: __m512,
                          y1: __m512,
                          y2: __m512,
                          v: __m512,
                          xp: __m512| {
            let lhs = _mm512_mul_ps(_mm512_sub_ps(y1, v), _mm512_sub_ps(x2, x1));
            let rhs = _mm512_mul_ps(_mm512_sub_ps(y2, y1), _mm512_sub_ps(x1, xp));
            _mm512_cmp_ps_mask::<_CMP_GT_OQ>(lhs, rhs)
        });
        // This azimuth's query whose window starts here (query column q, on column q + qoff).
        let q = up - f.d - f.qoff;
        if (0..f.wa).contains(&q) && f.qs[q as usize].on {
            let (xq, corr, qm, hq) = query_at!(up - f.d, f.qs[q as usize], false, q);
            let cur = near_walk!(xq, hq, qm, false);
            put!(sb, q, xq, hq, qm, corr, cur, false, false);
        }
        if let Some(e) = f.mirror {
            // The mirror's query whose window starts here: its hull is this suffix, seen from
            // the right, so walked from the bottom (the block's end).
            let p = up + r;
            let k = e - p;
            if (0..f.wa).contains(&k) && f.mq[k as usize].on {
                let (xq, corr, qm, hq) = query_at!(p, f.mq[k as usize], true, k);
                let cur = far_walk!(xq, hq, qm, true);
                put!(sbm, k, xq, hq, qm, corr, cur, true, false);
            }
        }
    }
    if !blocked {
        return;
    }
    // Prefix pass, left to right: a window's part in the next block, so only blocks after the
    // first window's start. This azimuth's queries walk each lane's hull from its bottom (the
    // block's first sample, never popped), the mirror's from its top.
    reset!();
    let mut next = (s_lo / blk + 1) * blk;
    let end = match f.mirror {
        Some(e) => (f.qoff + f.wa - 1 + r).max(e - f.d),
        None => f.wa - 1 + r,
    }
    .min(f.len - 1);
    macro_rules! advance {
        ($to:expr) => {{
            let to = $to;
            while next <= to {
                if next % blk == 0 {
                    reset!();
                }
                // Keep t1 where the slope t2→t1 is above t1→p.
                step!(next, true, |x1: __m512,
                                   x2: __m512,
                                   y1: __m512,
                                   y2: __m512,
                                   v: __m512,
                                   xp: __m512| {
                    let lhs = _mm512_mul_ps(_mm512_sub_ps(y1, y2), _mm512_sub_ps(xp, x1));
                    let rhs = _mm512_mul_ps(_mm512_sub_ps(v, y1), _mm512_sub_ps(x1, x2));
                    _mm512_cmp_ps_mask::<_CMP_GT_OQ>(lhs, rhs)
                });
                if let Some(e) = f.mirror {
                    // The mirror's query whose window ends here, when it reaches back into
                    // the previous block.
                    let p = next + f.d;
                    let k = e - p;
                    if (0..f.wa).contains(&k)
                        && f.mq[k as usize].on
                        && (next - blk + 1) / blk < next / blk
                    {
                        let (xq, corr, qm, hq) = query_at!(p, f.mq[k as usize], true, k);
                        if qm.iter().any(|&m| m != 0) {
                            let cur = near_walk!(xq, hq, qm, true);
                            put!(sbm, k, xq, hq, qm, corr, cur, true, true);
                        }
                    }
                }
                next += 1;
            }
        }};
    }
    for q in 0..f.wa {
        let qc = f.qoff + q;
        let top = (qc + r).min(f.len - 1);
        advance!(top);
        if !f.qs[q as usize].on {
            continue;
        }
        // Only when the window reaches into the next block (see `far_field`).
        if top / blk <= (qc + f.d) / blk {
            continue;
        }
        let (xq, corr, mut qm, hq) = query_at!(qc, f.qs[q as usize], false, q);
        if qm.iter().all(|&m| m == 0) {
            continue;
        }
        // This part of the window is the far one (it starts at the block's first column, bs):
        // the lanes whose tangent from the suffix part (already in the slot) no vertex here can
        // beat skip the walk. A vertex's slope is at most (hmax − hq)/D + corr, with D the
        // distance from bs where the numerator is positive and from `top` where it is not;
        // computed by the same float operations on larger operands, so a bound by rounding too.
        let bs = top / blk * blk;
        let dmin = _mm512_set1_ps((bs - qc) as f32);
        let dmax = _mm512_set1_ps((top - qc) as f32);
        let zero = _mm512_setzero_ps();
        for g in 0..G {
            if qm[g] == 0 {
                continue;
            }
            let a = _mm512_sub_ps(hmax[g], hq[g]);
            let d = _mm512_mask_mov_ps(dmax, _mm512_cmp_ps_mask::<_CMP_GT_OQ>(a, zero), dmin);
            let bound = _mm512_add_ps(_mm512_div_ps(a, d), corr);
            let old = _mm512_loadu_ps(sb[g].add(q as usize * FL));
            qm[g] &= !_mm512_cmp_ps_mask::<_CMP_LE_OQ>(bound, old);
        }
        if qm.iter().all(|&m| m == 0) {
            continue;
        }
        let cur = far_walk!(xq, hq, qm, false);
        put!(sb, q, xq, hq, qm, corr, cur, false, true);
    }
    advance!(end);
}

/// The tangents of a batch of groups (slots `slot0`.. of `sb`, groups `batch[g]` = (i0, lines))
/// into the sums, in one pass of independent adds (interleaved with the hull work, every add
/// waited for its cache misses), query column by query column. Each column's sums are a new
/// row of the plane, so one group alone touches a page per column; the groups of a batch are
/// neighbours across the lines, so at each column they add into one run of the row: one page
/// and a few adjacent cache lines for the whole batch. A texel's two roles weigh 1 in all, so
/// only when a role finds nothing ahead (rare) is the other's weight, then the texel's whole
/// valid weight, kept (`miss`; both missing sum to 1 over a sum of 0).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn add_batch_avx512(
    f: &Family<'_>,
    batch: &[(i64, u32)],
    slot0: usize,
    sums: &mut [f32],
    sb: &[f32],
    miss: &mut [f32],
) {
    use std::arch::x86_64::*;
    let ninf = _mm512_set1_ps(f32::NEG_INFINITY);
    let wa = f.wa as usize;
    const PFS: i64 = 24;
    let Some(&(first, _)) = batch.first() else { return };
    let span = batch.last().map_or(0, |&(i0, _)| i0 + FL as i64 - first);
    for q in 0..f.wa {
        // Each query column's sums are a new row: fetch a few ahead, every cache line of the
        // batch's run of it.
        let qa = q + PFS;
        if qa < f.wa && f.qs[qa as usize].on {
            let b_lo = first - f.qs[qa as usize].shift;
            for off in (0..span + 16).step_by(16) {
                let b = b_lo + off;
                let b = if f.wrap { b.rem_euclid(f.hb) } else { b.clamp(0, f.hb - 1) };
                let p = sums.as_ptr().wrapping_add(f.lay.at(f.abase[qa as usize], b as usize));
                _mm_prefetch::<_MM_HINT_T0>(p as *const i8);
            }
        }
        let qc = f.qs[q as usize];
        if !qc.on {
            continue;
        }
        let wt = _mm512_set1_ps(qc.wt * f.inv_step);
        for (g, &(i0, nl)) in batch.iter().enumerate() {
            let (tm, b0) = texels_at(f, i0, nl, qc.shift);
            let res = _mm512_loadu_ps(sb.as_ptr().add(((slot0 + g) * wa + q as usize) * FL));
            let got = tm & _mm512_cmp_ps_mask::<_CMP_GT_OQ>(res, ninf);
            if got != 0 {
                add_lanes(f, q, b0, got, _mm512_mul_ps(wt, res), sums);
            }
            if tm & !got != 0 {
                add_lanes(f, q, b0, tm & !got, _mm512_set1_ps(qc.other), miss);
            }
        }
    }
}

/// Adds `v` in the lanes of `m` (texels b0 + lane of query column q) to `dst` (major-line
/// layout; with `edge=wrap` the lanes past the minor end wrap to its start).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn add_lanes(
    f: &Family<'_>,
    q: i64,
    b0: i64,
    m: u16,
    v: std::arch::x86_64::__m512,
    dst: &mut [f32],
) {
    use std::arch::x86_64::*;
    let base = f.abase[q as usize] as isize;
    // Lanes b0 + l ≥ hb (only with `edge=wrap`) belong hb earlier.
    let hi = if b0 + 16 > f.hb { lane_range(b0 - f.hb, f.hb, 16) } else { 0 };
    for (mm, off) in [(m & !hi, b0), (m & hi, b0 - f.hb)] {
        if mm == 0 {
            continue;
        }
        // In chunks, the lanes from the next chunk's first texel on are that chunk's.
        let (runs, n) = if f.lay.chunk == 0 {
            ([(mm, off as isize), (0, 0)], 1)
        } else {
            let (c, r) = (off.div_euclid(CA as i64), off.rem_euclid(CA as i64));
            let k = CA as i64 - r;
            let lo = if k >= 16 { 0xffff } else { ((1u32 << k) - 1) as u16 };
            let at = |c: i64| c as isize * f.lay.chunk as isize + r as isize;
            ([(mm & lo, at(c)), (mm & !lo, at(c + 1) - CA as isize)], 2)
        };
        for &(mm, o) in &runs[..n] {
            if mm == 0 {
                continue;
            }
            // Masked lanes are neither read nor written, so the pointer may point before the
            // slice for lanes that are masked off.
            let p = dst.as_mut_ptr().wrapping_offset(base + o);
            let old = _mm512_maskz_loadu_ps(mm, p);
            _mm512_mask_storeu_ps(p, mm, _mm512_add_ps(old, v));
        }
    }
}

impl HorizonRows for Sweep<'_> {
    fn width(&self) -> usize {
        self.grid.width
    }
    fn height(&self) -> usize {
        self.grid.height
    }
    fn bins(&self) -> usize {
        self.bins
    }
    fn failure(&self) -> Option<crate::error::Error> {
        if !self.failed.load(Ordering::Relaxed) {
            return None;
        }
        let f = self.failure.lock().ok()?.clone();
        let (kind, message) = f.unwrap_or((std::io::ErrorKind::Other, "unknown".into()));
        Some(spill_error(std::io::Error::new(kind, message)))
    }
    fn rows(&self, y0: usize, channels: &mut [f32], bins_out: Option<&mut [f32]>) {
        #[cfg(target_arch = "x86_64")]
        if self.wide {
            // SAFETY: `wide` only where the CPU has AVX-512F (see `Sweep::with_options`).
            return unsafe { self.rows_avx512(y0, channels, bins_out) };
        }
        self.join(y0, channels, bins_out);
    }
}

impl Sweep<'_> {
    /// [`Sweep::join`] compiled for AVX-512: its per-strip loops over 16 lanes (the point at
    /// R, the max, sin α, the channel sums) become one or two vector instructions each rather
    /// than four SSE ones (measured: the join's own time was about a tenth of a bake).
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f")]
    unsafe fn rows_avx512(&self, y0: usize, channels: &mut [f32], bins_out: Option<&mut [f32]>) {
        self.join(y0, channels, bins_out);
    }

    /// The bands: per row, bin and strip of 16 texels, the far field and the point at R as a
    /// floor for the near field, then sin α; then per strip its bins to the channels (see the
    /// module doc).
    #[inline(always)]
    fn join(&self, y0: usize, channels: &mut [f32], mut bins_out: Option<&mut [f32]>) {
        let (w, h, nb) = (self.grid.width, self.grid.height, self.bins);
        let n_rows = channels.len() / (w * 8);
        // Bin-major (`strip[n][i]`: texel i's bin n), so the channel sums run across the strip.
        let mut strip = vec![[0.0f32; NEAR_LANES]; nb];
        let mut best: [f32; NEAR_LANES];
        let mut ep = [0.0f32; NEAR_LANES];
        let mut sn = [0.0f32; NEAR_LANES];
        // `reduce=point` reads one bin per channel: the others are not computed unless asked.
        let step =
            if self.reduce == Reduce::Point && bins_out.is_none() && nb >= 8 { nb / 8 } else { 1 };
        if self.failed.load(Ordering::Relaxed) {
            return;
        }
        // The band's far field: the table's rows, or every needed bin's rows read from the
        // spill store (`far[n · n_rows·W + r·W + x]` either way, with its own origin).
        let band;
        let (far, plane, origin): (&[f32], usize, usize) = match &self.far {
            Far::Memory(t) => (t, w * h, 0),
            Far::Spilled(store) => {
                let mut b = vec![0.0f32; nb * n_rows * w];
                for n in (0..nb).step_by(step) {
                    let out = &mut b[n * n_rows * w..][..n_rows * w];
                    if let Err(e) = store.get(n, y0 * w, out) {
                        record(&self.failure, &self.failed, e);
                        return;
                    }
                }
                band = b;
                (&band, n_rows * w, y0 * w)
            }
        };
        // A row's strips bin by bin, then each strip's bins to its channels: bin by bin the
        // points at R lie on two rows and the far field on one, read left to right, which the
        // prefetchers follow; strip by strip they were 64 and 32 streams at once.
        let ns = w.div_ceil(NEAR_LANES);
        let mut hs = vec![[0.0f32; NEAR_LANES]; ns];
        let mut h0 = vec![[0.0f32; NEAR_LANES]; ns];
        let mut sines = vec![[0.0f32; NEAR_LANES]; nb * ns];
        for r in 0..n_rows {
            let y = y0 + r;
            // The strips' heights, once for all bins: raw for the points at R, and as the
            // near field takes them.
            for (j, (hs, h0)) in hs.iter_mut().zip(&mut h0).enumerate() {
                let (x, lanes) = (j * NEAR_LANES, NEAR_LANES.min(w - j * NEAR_LANES));
                hs[..lanes].copy_from_slice(&self.grid.heights[y * w + x..][..lanes]);
                *h0 = self.near.lanes_h0(x, y);
            }
            for n in (0..nb).step_by(step) {
                if self.progress.as_ref().is_some_and(Progress::is_canceled) {
                    return;
                }
                let row = &far[n * plane + y * w - origin..][..w];
                for j in 0..ns {
                    let (x, lanes) = (j * NEAR_LANES, NEAR_LANES.min(w - j * NEAR_LANES));
                    self.end_points(n, x, y, lanes, &hs[j], &mut ep);
                    let fb = &row[x..x + lanes];
                    // The far field and the point at R first: the near field then only solves
                    // the pieces that could beat them (the max is the same but for the f32
                    // rounding of a skipped piece's value).
                    best = [0.0; NEAR_LANES];
                    if let Ok(fb) = <&[f32; NEAR_LANES]>::try_from(fb) {
                        // A whole strip: a loop of fixed length, which vectorises.
                        for i in 0..NEAR_LANES {
                            best[i] = best[i].max(fb[i]).max(ep[i]);
                        }
                    } else {
                        for i in 0..lanes {
                            best[i] = best[i].max(fb[i]).max(ep[i]);
                        }
                    }
                    self.near.strip_from(n, x, y, &h0[j], &mut best);
                    for i in 0..NEAR_LANES {
                        // sin α in f32 (tan α ≥ 0; a vertical horizon, ∞, gives 1).
                        let t = best[i].min(1e15);
                        sn[i] = t / (1.0 + t * t).sqrt();
                    }
                    sines[n * ns + j] = sn;
                }
            }
            for j in 0..ns {
                let (x, lanes) = (j * NEAR_LANES, NEAR_LANES.min(w - j * NEAR_LANES));
                for n in (0..nb).step_by(step) {
                    strip[n] = sines[n * ns + j];
                }
                let k = r * w + x;
                reduce_strip(self.reduce, &strip, lanes, &mut channels[k * 8..(k + lanes) * 8]);
                if let Some(bo) = bins_out.as_deref_mut() {
                    for i in 0..lanes {
                        for (n, s) in strip.iter().enumerate() {
                            bo[(k + i) * nb + n] = s[i];
                        }
                    }
                }
            }
        }
    }
}

/// Most bytes the far-field table may take in memory (4·bins bytes per texel: a 2048² map at
/// 32 bins); a bigger one waits in a [`FarSpill`] store instead, so that the process stays
/// within about 1.5 GB for the largest map the service takes (8192² at any bins).
pub const MAX_TABLE_BYTES: u64 = 512 << 20;

/// Most bytes the planes being swept may take when the table is spilled (up to 3 planes of
/// W·H f32 per azimuth in flight: the plane, the missing weights and the transposed sums), so
/// fewer azimuths run at once on a big map: one at 8192², two (on two threads) at 4096².
const SPILL_SWEEP_BYTES: usize = 768 << 20;

/// Most bytes the second azimuth of a pair may add to the sweeps' scratch over all threads
/// (its sums and missing weights, 2 planes of W·H f32 per thread): 2048² pairs on 2 threads
/// with 64 MiB, 4096² with 256 MiB; bigger maps sweep each azimuth alone, as before.
const PAIR_SCRATCH_BYTES: usize = 256 << 20;

/// Most bytes a spilled table may take on disk: 32 GiB, an 8192² map at 128 bins.
pub const MAX_SPILL_BYTES: u64 = 32 << 30;

/// The bytes of the far-field table of a `width` × `height` map at `bins` azimuths.
pub fn table_bytes(width: u32, height: u32, bins: u32) -> u64 {
    u64::from(width) * u64::from(height) * u64::from(bins.max(1)) * 4
}

/// Whether a bake of this size should give the kernel a [`FarSpill`] store (its table would
/// pass [`MAX_TABLE_BYTES`]).
pub fn spills(width: u32, height: u32, bins: u32) -> bool {
    table_bytes(width, height, bins) > MAX_TABLE_BYTES
}

/// Keeps the first failure of the spill store and says there is one.
fn record(
    failure: &Mutex<Option<(std::io::ErrorKind, String)>>,
    failed: &AtomicBool,
    e: std::io::Error,
) {
    if let Ok(mut f) = failure.lock() {
        f.get_or_insert_with(|| (e.kind(), e.to_string()));
    }
    failed.store(true, Ordering::Relaxed);
}

/// A spill failure as the bake's error: a full disk is a condition to retry later (`Unavailable`,
/// so a queued bake goes back to the queue a bounded number of times), anything else an I/O error.
fn spill_error(e: std::io::Error) -> crate::error::Error {
    if e.kind() == std::io::ErrorKind::StorageFull {
        crate::error::Error::Unavailable(format!(
            "method=sweep could not write its far field to disk (no space left): {e}"
        ))
    } else {
        crate::error::Error::Io(std::io::Error::new(
            e.kind(),
            format!("method=sweep's far field on disk: {e}"),
        ))
    }
}

/// Refuses a `width` × `height` map at `bins` azimuths whose far-field table would exceed
/// [`MAX_SPILL_BYTES`] even on disk, before anything is decoded or queued.
///
/// # Errors
/// [`Error::Param`] naming `method`, with the size and what to use instead.
pub fn check_memory(width: u32, height: u32, bins: u32) -> crate::error::Result<()> {
    let bytes = table_bytes(width, height, bins.max(8));
    if bytes > MAX_SPILL_BYTES {
        return Err(crate::error::Error::param(
            "method",
            format!(
                "method=sweep keeps its far field for the whole map (in memory up to {} MiB, \
                 beyond that in a temporary file), width × height × bins × 4 bytes = {} MiB for \
                 this {width}×{height} map at {} bins, over the {} MiB it may use; use fewer \
                 bins, or method=march with a finite radius or max_distance, or method=exact",
                MAX_TABLE_BYTES >> 20,
                bytes >> 20,
                bins.max(8),
                MAX_SPILL_BYTES >> 20
            ),
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The hull tangents against brute force over the same points.
    #[test]
    fn hull_tangents_match_brute_force() {
        let mut seed = 12345u64;
        let mut rnd = || {
            seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            ((seed >> 33) as f64 / (1u64 << 31) as f64) * 10.0 - 5.0
        };
        for &cc in &[0.0, 0.01] {
            let pts: Vec<Pt> = (0..200).map(|u| (u as f64, rnd() - cc * (u * u) as f64)).collect();
            let raw = |u: usize| pts[u].1 + cc * (u * u) as f64;
            for q in 0..150i64 {
                let h0 = rnd();
                let from = (q + 3) as usize;
                let mut left = Vec::new();
                for u in (from..200).rev() {
                    push_left(&mut left, pts[u]);
                }
                let mut right = Vec::new();
                for p in &pts[from..200] {
                    push_right(&mut right, *p);
                }
                let want = (from..200)
                    .map(|u| {
                        let s = (u as i64 - q) as f64;
                        (raw(u) - cc * s * s - h0) / s
                    })
                    .fold(f64::NEG_INFINITY, f64::max);
                let a = tangent_left(&left, q, h0, cc).unwrap();
                let b = tangent_right(&right, q, h0, cc).unwrap();
                assert!((a - want).abs() < 1e-9, "{a} {want}");
                assert!((b - want).abs() < 1e-9, "{b} {want}");
            }
        }
    }

    #[test]
    fn every_texel_has_one_line_at_most_half_a_sub_step_away() {
        for n in 0..64 {
            let d = exact::direction(n as f64 * 2.0 * PI / 64.0, -1);
            let l = Lines::new(d);
            for u in 0..300i64 {
                let (k, shift) = l.family(u);
                for b in -3..3i64 {
                    // Line i = b + shift of family k passes at minor i + k/SUB + m·u.
                    let v = (b + shift) as f64 + k as f64 / SUB as f64 + l.m * u as f64;
                    assert!((v - b as f64).abs() <= 0.5 / SUB as f64 + 1e-9, "{n} {u} {b} {v}");
                }
            }
        }
    }

    /// The vector far field against the scalar f64 one of the same samples (its oracle): random
    /// maps, both edges, odd sizes, thin strips and 1×1, finite R and unlimited, every azimuth
    /// of 32 (both major axes, both signs, slopes of both signs).
    #[test]
    fn the_vector_far_field_matches_the_scalar_one() {
        if !Isa::Avx512.supported() {
            eprintln!("no AVX-512: the vector far field is not used on this CPU");
            return;
        }
        let mut seed = 777u64;
        let mut rnd = || {
            seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            (seed >> 40) as f32 / (1u64 << 24) as f32
        };
        // 150 and 133 lines: more groups than a batch, and an odd count of them, so the last
        // call has a group of no lines beside a real one.
        let sizes = [
            (1usize, 1usize),
            (1, 37),
            (37, 1),
            (2, 3),
            (3, 40),
            (45, 38),
            (70, 17),
            (150, 5),
            (6, 133),
        ];
        let (mut paired, mut shifted) = (0, 0);
        for (w, h) in sizes {
            for rough in [2.0f32, 12.0] {
                let heights: Vec<f32> = (0..w * h).map(|_| rnd() * rough).collect();
                for edge in [Edge::None, Edge::Wrap] {
                    let g = Grid::new(w, h, &heights, edge, crate::params::YAxis::Up);
                    let mls = [MajorLines::new(&g, false), MajorLines::new(&g, true)];
                    for radius in [Some(17.0), Some(30.0), Some(61.5), None] {
                        let reach = match (radius, edge) {
                            (Some(r), _) => Some(r),
                            (None, Edge::Wrap) => Some(w.max(h) as f64),
                            (None, Edge::None) => None,
                        };
                        let mut sc = Scratch::default();
                        // Without the curvature drop, and with one that lowers the far end of
                        // the longest line by several times the relief.
                        for (n, curv) in (0..32).flat_map(|n| [(n, 0.0), (n, 2e-3)]) {
                            let d = exact::direction(n as f64 * 2.0 * PI / 32.0, g.row_step());
                            let lines = Lines::new(d);
                            let mut want = vec![0.0f32; w * h];
                            let mut wsum = Vec::new();
                            far_field(&g, lines, reach, curv, &mut want, &mut wsum);
                            let ml = &mls[usize::from(lines.major_x)];
                            let close = |got: &[f32], want: &[f32], what: &str| {
                                for (t, (a, b)) in got.iter().zip(want).enumerate() {
                                    assert!(
                                        (a - b).abs() <= 2e-5 * (1.0 + b.abs()),
                                        "{w}×{h} {edge:?} R {radius:?} bin {n} curvature \
                                         {curv} texel {t} {what}: {a} vs {b}"
                                    );
                                }
                            };
                            for fresh in [false, true] {
                                let mut got = vec![0.0f32; w * h];
                                far_field_fast(
                                    &g, ml, lines, reach, curv, &mut got, &mut sc, None, fresh,
                                    None,
                                );
                                close(&got, &want, &format!("fresh {fresh}"));
                            }
                            // Swept with the opposite azimuth where the bake pairs them: both
                            // planes against the scalar sweeps of each alone.
                            let Some((a, e)) = mirror_end(&g, lines, reach) else { continue };
                            paired += 1;
                            shifted += usize::from(a > 0);
                            // Its texels where the pairing puts them, and the mirror.
                            let lines = Lines { at: (a, 1), ..lines };
                            let mut want = vec![0.0f32; w * h];
                            far_field(&g, lines, reach, curv, &mut want, &mut wsum);
                            let mirror = lines.mirror(e);
                            let mut want2 = vec![0.0f32; w * h];
                            far_field(&g, mirror, reach, curv, &mut want2, &mut wsum);
                            for fresh in [false, true] {
                                let (mut got, mut got2) = (vec![0.0f32; w * h], vec![0.0; w * h]);
                                far_field_fast(
                                    &g,
                                    ml,
                                    lines,
                                    reach,
                                    curv,
                                    &mut got,
                                    &mut sc,
                                    None,
                                    fresh,
                                    Some((mirror, &mut got2)),
                                );
                                close(&got, &want, &format!("paired, fresh {fresh}"));
                                close(&got2, &want2, &format!("its mirror, fresh {fresh}"));
                            }
                        }
                    }
                }
            }
        }
        // Every wrapped size pairs at `unlimited`, and some at finite radii with the texels
        // a whole map further along the lines (a short window: `mirror_end`).
        assert!(paired >= 9 * 2 * 2 * 32, "only {paired} paired sweeps");
        assert!(shifted > 0, "no pairing of a short window");
    }
}
