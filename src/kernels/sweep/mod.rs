//! `method=sweep` (SPEC §3.2a): the line-of-sight horizon of §3.2 at any radius, `unlimited`
//! included, at a cost per texel that does not grow with R.
//!
//! The result is max(near, far, the point at exactly R on the texel's own ray) as tan α, stored
//! as sin α:
//! - **Near field**, 0 < s ≤ [`NEAR_STEPS`] major-axis steps: exact, on the texel's own ray, 16
//!   texels of a row in lockstep ([`NearField`], shared with `exact`). Near the texel the
//!   azimuth of a sample matters most, and the bilinear saddle inside a cell must not be missed.
//! - **Far field**, beyond: per azimuth, lines parallel to it, [`SUB`] families of them per texel
//!   of minor axis ([`Lines`], `lines.rs`). Each line is swept from its far end keeping the
//!   upper convex hull of its samples (one per major grid line, a lerp of two texels); a texel
//!   asks the two lines beside it for the tangent from its height and interpolates the two, so
//!   the lateral error cancels to first order. A finite window (any R, and `unlimited` with
//!   `edge=wrap`, which §3.2 makes max(W, H)) is honoured exactly with blocked hulls: a suffix
//!   hull of one block joined to a prefix hull of the next; opposite azimuths share those passes.
//!   The earth-curvature drop c·s² becomes a tangent query on the fixed hull of h − c'x².
//!
//! Files: `hull.rs` is the scalar f64 far field (the path without AVX-512, and the oracle of the
//! vector one); `vector.rs` and `avx512.rs` run 16 lines of a family in lockstep in f32, with
//! each hull's nearest vertices in registers; `bands.rs` joins the fields row by row;
//! `budget.rs` keeps the far-field table (4·bins bytes per texel) in memory or hands it to a
//! [`FarSpill`] store, and refuses what would not fit ([`check_memory`]).
//!
//! The far field only samples grid lines up to 1/SUB of a texel beside the ray: on terrain that
//! moves the horizon by hundredths of a degree, on fields of single-texel spikes by degrees (the
//! stated worst case, `tests/kernels/sweep.rs`). Nodata holes: [`Sweep::with_holes`]. docs/sweep.md holds the whole account: how each part works,
//! the measurements behind each constant, what was tried and dropped.

use super::exact;
use super::isa::Isa;
use super::nearfield::{NearField, NEAR_LANES};
use super::{reduce_strip, Grid, HorizonRows};
use crate::params::{Edge, Reduce};
use crate::progress::Progress;
use rayon::prelude::*;
use std::f64::consts::PI;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};

mod avx512;
mod bands;
mod budget;
mod hull;
mod lines;
mod planes;
mod vector;

#[cfg(target_arch = "x86_64")]
use avx512::*;
use budget::*;
pub use budget::{check_memory, spills, table_bytes, MAX_SPILL_BYTES, MAX_TABLE_BYTES};
use hull::*;
use lines::*;
pub use lines::{azimuth_lines, Lines};
use vector::*;

/// Major-axis steps covered exactly by the near field; chosen by measurement (docs/sweep.md,
/// "Constants").
pub const NEAR_STEPS: usize = 16;
/// Sub-line families per texel of minor axis; chosen by measurement (docs/sweep.md, "Constants").
pub const SUB: usize = 3;
/// Whether the far field also samples halfway between major grid lines; off by measurement
/// (docs/sweep.md, "Constants").
pub const MIDS: bool = false;
/// Rows per window of the near field's tables in [`Sweep::planes`] (a window reads 2·pad + 1
/// more, 37 at 16 steps): the whole map's tables are 12 bytes a texel, a window's at 8192
/// columns about 30 MB. Fewer rows would make the overlap, remade with every chunk of
/// azimuths, a larger share (docs/sweep.md, "Memory without a table", has the cost).
pub const NEAR_WINDOW_ROWS: usize = 256;

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
    /// The CPU has AVX-512: the bands' join is compiled for it ([`Sweep::join`]).
    wide: bool,
    /// With nodata holes (see [`Sweep::with_holes`]).
    holes: Option<Holes<'a>>,
    /// Each bin's lines, for the azimuth-major planes ([`Sweep::planes`]).
    lines_of: Vec<Lines>,
    /// Windows of the near field's rows ([`NearField::window`]) that [`Sweep::planes`]' threads
    /// fill group after group and hand back, so a window's tables are allocated once per
    /// thread rather than once per azimuth; emptied when the planes end.
    windows: Mutex<Vec<NearField<'a>>>,
}

/// What the bands need near nodata holes: the exact walk over the near field's reach, which
/// skips the cells touching a hole, and per texel whether its near field can reach one.
struct Holes<'a> {
    exact: exact::ExactHorizon<'a>,
    near: super::Flags,
    mask: &'a [bool],
}

/// Where the far field waits between the sweeps and the bands.
enum Far {
    /// `far[n · W·H + texel]`.
    Memory(Vec<f32>),
    /// One plane of W·H per bin, in the caller's store.
    Spilled(Arc<dyn FarSpill>),
    /// Not made: the kernel runs azimuth by azimuth ([`Sweep::planes`]) and holds one plane
    /// per azimuth in flight, never the table.
    Deferred,
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
    /// Azimuth-major: no far-field table at all; the kernel gives its horizons plane by plane
    /// ([`Sweep::planes`]), each azimuth swept when its plane is asked for, so its memory does
    /// not grow with the bins. [`HorizonRows::rows`] then gives nothing (every value 0): only
    /// a caller that folds planes asks for this.
    pub azimuth_major: bool,
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
                let near = NEAR_STEPS as f64 * Lines::new(d).step;
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
            None => far_field(&grid, lines, reach, curv, out, &mut sc.wsum),
        };
        let failure = Mutex::new(None);
        let failed = AtomicBool::new(false);
        let far = match opt.spill {
            _ if opt.azimuth_major => Far::Deferred,
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
                tasks.push(Mutex::new(Some(Task::NearTables)));
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
                            Some(Task::NearTables) => {
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
        // Azimuth-major, the near field's tables are made per window of rows as the planes
        // are joined ([`Sweep::planes`]), never for the whole map.
        let near = match near {
            Some(near) => near,
            None if opt.azimuth_major => NearField::without_rows(grid, &dirs, &cuts, curv, isa),
            None => make_near(),
        };
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
            holes: None,
            lines_of,
            windows: Mutex::new(Vec::new()),
        }
    }

    /// Nodata holes (SPEC §2), one flag per texel: the cells that touch a hole are no surface.
    /// The bake fills holes far below the map ([`crate::heightmap::HOLE_DEPTH`]), which is all
    /// the far field needs: its samples lie on grid lines, a lerp of two texels, so one that
    /// touches a hole is lowered below every observer (but within 1/`HOLE_DEPTH` of a texel's
    /// end). The near field solves whole cells, whose bilinear twist the fill makes enormous,
    /// so it is told the holes (`NearField::with_holes`): its crossing walk never solves a cell
    /// with a hole corner and counts a crossing only where a cell beside it is surface, as
    /// `exact`'s walk does, and near a hole it runs out to the longest cut in every direction
    /// (the far field's lines, a third of a texel beside the ray, see a hole's edge where the
    /// ray does not). Where it cannot (rays along a grid axis or a diagonal, and strips whose
    /// rays leave an `edge=none` surface before that reach: `NearField::honours_holes`), a
    /// texel whose near field can reach a hole (a Chebyshev distance of at most the reach plus
    /// one) takes it from the exact walk with the holes instead, over the same reach, seeded
    /// with the far field.
    pub fn with_holes(mut self, holes: Option<&'a [bool]>) -> Self {
        let (w, h) = (self.grid.width, self.grid.height);
        let Some(mask) = holes.filter(|m| m.len() == w * h && m.iter().any(|&o| o)) else {
            return self;
        };
        let reach = self.cuts.iter().copied().fold(0.0, f64::max).ceil().max(1.0);
        let exact = exact::ExactHorizon::walker(
            self.grid,
            Some(reach as u32),
            self.bins as u32,
            self.reduce,
        )
        .with_curvature(self.curv)
        .with_holes(Some(mask));
        let exact = match &self.progress {
            Some(p) => exact.with_cancel(p),
            None => exact,
        };
        let near = super::near_holes(mask, w, h, reach as usize + 1, self.grid.edge == Edge::Wrap);
        self.near = self.near.with_holes(mask);
        self.holes = Some(Holes { exact, near, mask });
        self
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
