//! `method=sweep` (SPEC §3.2a), first version: the line-of-sight horizon of §3.2 at any radius,
//! `unlimited` included, with the far field found by a sweep whose cost does not grow with R.
//!
//! # Why three parts
//! A sweep is radius-independent because many texels share one line: walking the line once
//! from its far end, the upper convex hull of the samples passed answers every texel on it
//! (the horizon from a point is the tangent to the hull of what lies ahead). Lines shared by
//! texel centres must run along lattice vectors (q, p), and a texel costs about |q| + |p|
//! samples per azimuth, so the vector must be short, and the 32 bin azimuths are not lattice
//! directions: the line answers at an azimuth up to 0.7° off (|q| + |p| ≤ [`LATTICE`]). On its
//! own that misses SPEC's tolerance badly on thin occluders (`cargo bench --bench sweep_bound`:
//! p99 0.6–12° on the corpus spikes and random spike fields). So the sweep is used only to
//! *find* the far occluder, never to measure it:
//! 1. **near field**: the exact kernel ([`ExactHorizon`], vectorised) on the texel's own ray up to
//!    [`NEAR`] texels, where the azimuth error would be worth the most;
//! 2. **far field, located**: per bin, a sweep along the nearest lattice direction gives, for
//!    every texel, the distance s* of the sample that maximises (h − h0)/s beyond [`NEAR`]
//!    (and within R: a finite window is two hull queries, on the suffix of one block of length
//!    R − NEAR and the prefix of the next, so an occluder beyond R is never found);
//! 3. **far field, measured**: the exact closed form on the texel's *own* ray, over
//!    s* ± [`WINDOW`] texels only (clipped to R).
//!
//! The result is the larger of 1 and 3: always a value of the true ray within R, so the kernel
//! never overshoots §3.2. It undershoots only when the lattice line's best far occluder is not
//! the true ray's, which the constants keep rare: with |q| + |p| ≤ 8 (azimuths up to 0.7° off)
//! a simulation of this scheme still gave p99 0.7° on the corpus spikes; at 24 the worst snap
//! is 0.12° (22.5° → (12, 5)) and `tests/sweep.rs` measures, against `exact` at the same
//! radius (R = 16, 40, unlimited; 5, 12, 50 on the random maps): eval corpus and terrain mean
//! ≤ 0.001°, p99 ≤ 0.012° (worst: the spikes map, wrapped, unlimited); random white noise,
//! waves and 1 % spike fields mean ≤ 0.009°, p99 ≤ 0.055°, against 0.05° / 0.25° allowed.
//!
//! Along a lattice line the samples are every grid-line crossing (a knee of the surface along
//! the line), the middle of every piece between crossings (inside a cell the surface along the
//! line is a parabola: a diagonal line crosses no grid line between texels yet passes the tent
//! of a spike beside it), every texel, and the point at exactly R from each texel (a ray cut
//! at R on a rising flank has its maximum there).
//!
//! # Cost and what is left
//! Per texel and bin the sweep inserts about |q| + |p| crossings and as many midpoints into two
//! hulls (one pass each way) and makes two binary-search queries; the re-reading walks a few
//! cells. All of it is scalar f64 and runs for the whole map when the kernel is built (keeping
//! one u16 distance per texel and bin: 2·bins bytes per texel), so a cancel is seen only once
//! the bands start. Measured (`cargo bench --bench frontier`): about 0.1 Mtexel/s whatever the
//! radius, against SPEC's aim of 5; so it is not yet offered as `method=sweep`. What it
//! settles is the accuracy: the lattice sweep finds the occluder and the texel's own ray
//! measures it. Speed has to come from running many lines in SIMD lanes, as the other kernels
//! run texels. The re-reading is about 45 % of the time at 512² (`perf`), the hull pushes most
//! of the rest.
//!
//! # Tried: lines at the bin's own azimuth
//! Lines parallel to the bin (one column per step, v = c + m·k) need only 2–3 samples per
//! step instead of about 2(|q| + |p|), but a texel is up to half a texel off its line, and
//! that loses thin occluders: spikes p99 1.1–4° at SUB = 1 sub-line per texel row, still
//! 0.4–2.6° at 4 or 8. Taking, at each column, the highest point within ±0.5 of the line
//! finds the grazed spikes but then picks the wrong occluder on rough maps (white noise p99
//! 1.6°); only both (a plain and a bounding hull, both re-read, 5 sub-lines) met the tolerance
//! everywhere (worst p99 0.03°), and that is 5 × 2 hulls per texel: 55–84 s at 2048² against
//! this design's 43–53 s (`cargo bench --bench frontier`), so it was not kept.

use super::exact::{self, ExactHorizon};
use super::{reduce_into, Grid, HorizonRows};
use crate::params::{Edge, Reduce};
use rayon::prelude::*;
use std::f64::consts::PI;

/// Largest |q| + |p| of a line's lattice direction.
pub const LATTICE: i64 = 24;
/// Radius of the near field, measured exactly on each texel's own ray.
pub const NEAR: u32 = 8;
/// Half-length of the stretch of the texel's own ray re-read around the located occluder.
pub const WINDOW: f64 = 2.0;

/// The sweep kernel prepared for one grid (see the module doc).
pub struct Sweep<'a> {
    grid: Grid<'a>,
    /// Where every ray is clipped: R, max(W, H) for `unlimited` with `edge=wrap`, or infinity
    /// (`unlimited`, `edge=none`: the surface's edge ends it).
    reach: f64,
    bins: usize,
    reduce: Reduce,
    /// True image direction of each bin.
    dirs: Vec<(f64, f64)>,
    near: ExactHorizon<'a>,
    /// `far[n · W·H + texel]`: distance of the located far occluder in units of `unit`, 0 for
    /// none (nothing beyond the near field rises above the texel along the lattice line).
    far: Vec<u16>,
    unit: f64,
}

impl<'a> Sweep<'a> {
    /// Prepares the kernel: runs the sweeps for every bin (in parallel on the current pool).
    /// `radius`: `None` = unlimited.
    pub fn new(grid: Grid<'a>, radius: Option<u32>, bins: u32, reduce: Reduce) -> Self {
        let (w, h) = (grid.width, grid.height);
        let bins = bins.max(8) as usize;
        // Bounded as the exact kernel bounds it: the unrolled lines grow with R when wrapping.
        let cap = crate::params::MAX_RADIUS.max(w.max(h) as u32);
        let radius = radius.map(|r| r.clamp(1, cap));
        let reach = match (radius, grid.edge) {
            (Some(r), _) => f64::from(r),
            (None, Edge::Wrap) => w.max(h) as f64,
            (None, Edge::None) => f64::INFINITY,
        };
        // Never past R: a wrapped map smaller than the near field has `unlimited` = max(W, H).
        let near_r = if reach.is_finite() { (reach as u32).clamp(1, NEAR) } else { NEAR };
        let near = ExactHorizon::new(grid, Some(near_r), bins as u32, reduce);
        let row_step = grid.row_step();
        let phis: Vec<f64> = (0..bins).map(|n| n as f64 * 2.0 * PI / bins as f64).collect();
        let dirs = phis.iter().map(|&p| exact::direction(p, row_step)).collect();
        // The longest distance stored: the whole reach (a wrapped ray can be longer than the
        // map), or the map's diagonal (`edge=none`: the surface ends there).
        // A wrapped line repeats within lcm(W, H) steps of at most LATTICE texels, and nothing
        // is located past one period beyond the near field (see `locate`), so that bounds it
        // too: the same map then quantises alike at any R past it.
        let longest = match grid.edge {
            Edge::Wrap => {
                let period = (w / gcd(w as i64, h as i64) as usize * h) as f64 * LATTICE as f64;
                reach.min(period + f64::from(NEAR) + 1.0)
            }
            Edge::None => reach.min(((w * w + h * h) as f64).sqrt() + 2.0),
        }
        .max(1.0);
        let unit = longest / 65535.0;
        let texels = w * h;
        let mut far = vec![0u16; bins * texels];
        if reach > f64::from(NEAR) {
            let padded = Padded::new(&grid);
            far.par_chunks_mut(texels.max(1)).zip(&phis).for_each(|(out, &phi)| {
                let (q, p) = lattice(phi);
                let step = (q, p * row_step);
                locate(&grid, &padded, step, f64::from(NEAR), reach, unit, out);
            });
        }
        Sweep { grid, reach, bins, reduce, dirs, near, far, unit }
    }
}

/// The lattice vector (q, p) (tangent space, gcd 1, |q| + |p| ≤ [`LATTICE`]) nearest in
/// azimuth to `phi`.
fn lattice(phi: f64) -> (i64, i64) {
    let mut best = (f64::MAX, (1, 0));
    for q in -LATTICE..=LATTICE {
        let room = LATTICE - q.abs();
        for p in -room..=room {
            if gcd(q.abs(), p.abs()) != 1 {
                continue;
            }
            let a = (p as f64).atan2(q as f64);
            let d = ((a - phi + PI).rem_euclid(2.0 * PI) - PI).abs();
            if d < best.0 {
                best = (d, (q, p));
            }
        }
    }
    best.1
}

fn gcd(a: i64, b: i64) -> i64 {
    if b == 0 {
        a
    } else {
        gcd(b, a % b)
    }
}

/// A sample of a line between two consecutive texels T and T + step, at fraction `t` ∈ (0, 1]:
/// the bilinear surface at T + `c` + (`fx`, `fy`) (cell corner `c`, fractions in [0, 1)).
#[derive(Debug, Clone, Copy)]
struct Tap {
    t: f64,
    c: (i64, i64),
    fx: f64,
    fy: f64,
}

/// The samples of one step along image vector `step`, in order of t: every grid-line crossing
/// (where the surface along the line has a knee), the middle of every piece between them
/// (inside a cell the surface along the line is a parabola whose top can lie there: a diagonal
/// line crosses no grid line between texels, yet passes the tent of a spike beside it), and
/// the next texel.
fn taps(step: (i64, i64)) -> Vec<Tap> {
    let (sx, sy) = (step.0 as f64, step.1 as f64);
    let mut ts: Vec<f64> = vec![0.0, 1.0];
    ts.extend((1..step.0.abs()).map(|i| i as f64 / step.0.abs() as f64));
    ts.extend((1..step.1.abs()).map(|j| j as f64 / step.1.abs() as f64));
    ts.sort_by(f64::total_cmp);
    ts.dedup_by(|a, b| (*a - *b).abs() < 1e-12);
    let mids: Vec<f64> = ts.windows(2).map(|p| 0.5 * (p[0] + p[1])).collect();
    ts.extend(mids);
    ts.sort_by(f64::total_cmp);
    ts.into_iter()
        .filter(|&t| t > 0.0)
        .map(|t| {
            // Snap to the grid line a crossing lies on, so its cell and fraction are exact.
            let snap = |v: f64| if (v - v.round()).abs() < 1e-9 { v.round() } else { v };
            let (x, y) = (snap(t * sx), snap(t * sy));
            let (x0, y0) = (x.floor(), y.floor());
            Tap { t, c: (x0 as i64, y0 as i64), fx: x - x0, fy: y - y0 }
        })
        .collect()
}

/// The heights with a margin of [`PAD`] texels on every side (wrapped, or the border repeated
/// for `edge=none`, where a repeated value is only ever read with weight 0 or from off the
/// surface, which is checked first), so a sample's four corners are read without wrapping.
struct Padded {
    v: Vec<f32>,
    /// Row length.
    pw: usize,
}

/// Margin of [`Padded`]: a sample lies within |q|, |p| ≤ [`LATTICE`] of its step's texel.
const PAD: i64 = LATTICE + 2;

impl Padded {
    fn new(grid: &Grid<'_>) -> Padded {
        let (w, h) = (grid.width as i64, grid.height as i64);
        let pw = (w + 2 * PAD) as usize;
        let mut v = Vec::with_capacity(pw * (h + 2 * PAD) as usize);
        for r in -PAD..h + PAD {
            for c in -PAD..w + PAD {
                let (c, r) = match grid.edge {
                    Edge::Wrap => (c.rem_euclid(w), r.rem_euclid(h)),
                    Edge::None => (c.clamp(0, w - 1), r.clamp(0, h - 1)),
                };
                v.push(grid.heights[(r * w + c) as usize]);
            }
        }
        Padded { v, pw }
    }

    /// Index of map texel (x, y) (0 ≤ x < W, 0 ≤ y < H).
    #[inline]
    fn at(&self, x: i64, y: i64) -> usize {
        (y + PAD) as usize * self.pw + (x + PAD) as usize
    }

    /// The bilinear surface at image point (x, y): wrapped, or `NaN` off the texel centres'
    /// hull (`edge=none`).
    fn bilinear(&self, grid: &Grid<'_>, x: f64, y: f64) -> f64 {
        let (w, h) = (grid.width as i64, grid.height as i64);
        let eps = 1e-9;
        if grid.edge == Edge::None
            && (x < -eps || y < -eps || x > (w - 1) as f64 + eps || y > (h - 1) as f64 + eps)
        {
            return f64::NAN;
        }
        let (x0, y0) = (x.floor(), y.floor());
        let (fx, fy) = (x - x0, y - y0);
        // One wrap (or clamp) for the cell; its other corners are in the margin.
        let (c, r) = match grid.edge {
            Edge::Wrap => ((x0 as i64).rem_euclid(w), (y0 as i64).rem_euclid(h)),
            Edge::None => ((x0 as i64).clamp(0, w - 1), (y0 as i64).clamp(0, h - 1)),
        };
        let (v, pw, i) = (&self.v, self.pw, self.at(c, r));
        let (h00, h10) = (f64::from(v[i]), f64::from(v[i + 1]));
        let (h01, h11) = (f64::from(v[i + pw]), f64::from(v[i + pw + 1]));
        let top = h00 + (h10 - h00) * fx;
        let bottom = h01 + (h11 - h01) * fx;
        top + (bottom - top) * fy
    }
}

/// For every texel, along lattice vector `step`: the distance (in `unit`s, 0 for none) of the
/// sample of its line, at near < s ≤ reach, that maximises (h − h0)/s, if that ratio is > 0.
#[allow(clippy::too_many_arguments)]
fn locate(
    grid: &Grid<'_>,
    padded: &Padded,
    step: (i64, i64),
    near: f64,
    reach: f64,
    unit: f64,
    out: &mut [u16],
) {
    let (w, h) = (grid.width as i64, grid.height as i64);
    let len = ((step.0 * step.0 + step.1 * step.1) as f64).sqrt();
    let taps = taps(step);
    let inside = |x: i64, y: i64| (0..w).contains(&x) && (0..h).contains(&y);
    let pv = &padded.v[..];
    let pw = padded.pw;
    // Each tap's cell corner as an offset into the padded heights.
    let offs: Vec<usize> =
        taps.iter().map(|t| ((t.c.1 + PAD) * pw as i64 + t.c.0 + PAD) as usize).collect();
    let mut line = Line::default();
    let mut hull = Vec::new();
    let mut visited = vec![false; (w * h) as usize];
    // How far a line of `n` texels (a whole cycle when wrapping) needs looking. A wrapped line
    // repeats every n·len: a sample a period further on has the same height at a larger
    // distance, so its ratio is lower wherever it is positive, and nothing beyond one period
    // past the near field can be the best. Capping there keeps the cost per texel bounded
    // when R is many times the map (the result is the same).
    let ray_reach = |n: i64| match grid.edge {
        Edge::Wrap => reach.min(n as f64 * len + near),
        Edge::None => reach,
    };
    let full = reach;
    for y0 in 0..h {
        for x0 in 0..w {
            // Each line once: from its first texel (edge=none), or from any texel of its cycle.
            let first = match grid.edge {
                Edge::None => !inside(x0 - step.0, y0 - step.1),
                Edge::Wrap => !visited[(y0 * w + x0) as usize],
            };
            if !first {
                continue;
            }
            line.clear();
            // The texels of the line, and how many steps its samples run on.
            let mut k = 0i64;
            let (count, steps) = match grid.edge {
                Edge::None => {
                    let mut n = 0;
                    while inside(x0 + n * step.0, y0 + n * step.1) {
                        n += 1;
                    }
                    (n, n)
                }
                Edge::Wrap => {
                    let mut n = 0;
                    loop {
                        let (x, y) =
                            ((x0 + n * step.0).rem_euclid(w), (y0 + n * step.1).rem_euclid(h));
                        if n > 0 && (x, y) == (x0, y0) {
                            break;
                        }
                        visited[(y * w + x) as usize] = true;
                        n += 1;
                    }
                    // Enough turns of the cycle that every texel of the first sees `ray`.
                    (n, n + (ray_reach(n) / len).ceil() as i64 + 1)
                }
            };
            let reach = ray_reach(count);
            while k < steps {
                let (x, y) = (x0 + k * step.0, y0 + k * step.1);
                // The step's texel, wrapped into the map: the taps read around it.
                let (xw, yw) = match grid.edge {
                    Edge::Wrap => (x.rem_euclid(w), y.rem_euclid(h)),
                    Edge::None => (x, y),
                };
                let here = padded.at(xw, yw);
                if k < count {
                    // Only where the ray is really cut at R (a capped line's cut is dominated,
                    // see `ray_reach`).
                    let h_end = if reach.is_finite() && reach == full {
                        let f = reach / len;
                        let (ex, ey) =
                            (xw as f64 + f * step.0 as f64, yw as f64 + f * step.1 as f64);
                        padded.bilinear(grid, ex, ey)
                    } else {
                        f64::NAN
                    };
                    let i = (yw * w + xw) as usize;
                    line.texels.push((k as f64 * len, f64::from(pv[here]), i, h_end));
                }
                // The tap origin: PAD rows and columns up and left of the texel.
                let base = here - PAD as usize * pw - PAD as usize;
                let on_surface = |t: f64| {
                    // Past the last texel the line still crosses the surface until it leaves
                    // the hull of the texel centres (`edge=none`).
                    let eps = 1e-9;
                    let (px, py) = (x as f64 + t * step.0 as f64, y as f64 + t * step.1 as f64);
                    grid.edge == Edge::Wrap
                        || (px >= -eps
                            && py >= -eps
                            && px <= (w - 1) as f64 + eps
                            && py <= (h - 1) as f64 + eps)
                };
                let value = |tap: &Tap, o: usize| {
                    let i = base + o;
                    let (h00, h10) = (f64::from(pv[i]), f64::from(pv[i + 1]));
                    let (h01, h11) = (f64::from(pv[i + pw]), f64::from(pv[i + pw + 1]));
                    let top = h00 + (h10 - h00) * tap.fx;
                    let bottom = h01 + (h11 - h01) * tap.fx;
                    top + (bottom - top) * tap.fy
                };
                // Every sample of the step, in order (on the surface only, with edge=none).
                let mut gone = false;
                for (tap, &o) in taps.iter().zip(&offs) {
                    if !on_surface(tap.t) {
                        gone = true;
                        break;
                    }
                    line.samples.push(((k as f64 + tap.t) * len, value(tap, o)));
                }
                if gone {
                    break;
                }
                k += 1;
            }
            answer(&line, near, reach, &mut hull, |i, d| {
                out[i] =
                    if d > 0.0 { ((d / unit).round() as u64).clamp(1, 65535) as u16 } else { 0 };
            });
        }
    }
}

/// One line: its samples (s, h) in order of s, and its texels (s, h0, index, h_end), where
/// h_end is the surface at s + reach on the line (NaN when the line does not get there): with
/// a finite radius the ray is cut at R, where a rising flank has its highest point, which no
/// crossing need hit.
#[derive(Debug, Default)]
struct Line {
    samples: Vec<(f64, f64)>,
    texels: Vec<(f64, f64, usize, f64)>,
}

impl Line {
    fn clear(&mut self) {
        self.samples.clear();
        self.texels.clear();
    }
}

/// For each texel of `line`, the sample at s0 + near < s ≤ s0 + reach maximising
/// (h − h0)/(s − s0): `found(index, s − s0)`, with 0 when no such sample has a positive ratio.
///
/// A window of fixed length W = reach − near over the line: blocks (kW, (k+1)W] of the line's
/// arc length split every window into the suffix of one block and the prefix of the next. A
/// backward pass keeps the upper hull of the current block's samples beyond each window's
/// start, a forward pass the hull of the next block's samples up to each window's end; the
/// tangent from the texel to each hull is a binary search (the ratio is unimodal along an upper
/// hull seen from its left). Unlimited reach (`edge=none`) is one block.
fn answer(
    line: &Line,
    near: f64,
    reach: f64,
    hull: &mut Vec<(f64, f64)>,
    mut found: impl FnMut(usize, f64),
) {
    let span = reach - near;
    let pts = &line.samples;
    let mut best = vec![(0.0f64, 0.0f64); line.texels.len()];
    // The current block is (lo_b, lo_b + span]; it changes rarely (once per `span` of arc), so
    // the division that finds a sample's block runs only then.
    let lower = |s: f64| {
        if span.is_finite() {
            ((s / span).ceil() - 1.0) * span
        } else {
            f64::NEG_INFINITY
        }
    };
    let holds = |lo_b: f64, s: f64| s > lo_b && (span.is_infinite() || s <= lo_b + span);
    let starts_in = |lo_b: f64, lo: f64| span.is_infinite() || (lo >= lo_b && lo < lo_b + span);
    // Backward: texels from the far end, samples inserted while beyond the window's start.
    hull.clear();
    let mut lo_b = f64::NAN;
    let mut j = pts.len();
    for (k, &(s0, h0, ..)) in line.texels.iter().enumerate().rev() {
        let lo = s0 + near;
        while j > 0 && pts[j - 1].0 > lo {
            let p = pts[j - 1];
            if !holds(lo_b, p.0) {
                hull.clear();
                lo_b = lower(p.0);
            }
            push(hull, p);
            j -= 1;
        }
        // The window starts in this block (lo in [lo_b, lo_b + span)): the hull is its suffix.
        if !hull.is_empty() && starts_in(lo_b, lo) {
            best[k] = tangent(hull, s0, h0);
        }
    }
    if span.is_finite() {
        // Forward: texels from the near end, samples inserted up to the window's end.
        hull.clear();
        lo_b = f64::NAN;
        j = 0;
        for (k, &(s0, h0, ..)) in line.texels.iter().enumerate() {
            let (lo, hi) = (s0 + near, s0 + reach);
            while j < pts.len() && pts[j].0 <= hi {
                let p = pts[j];
                if !holds(lo_b, p.0) {
                    hull.clear();
                    lo_b = lower(p.0);
                }
                push(hull, p);
                j += 1;
            }
            // The window started in the block before this one: the hull is its prefix.
            if !hull.is_empty() && lo >= lo_b - span && lo < lo_b {
                let t = tangent(hull, s0, h0);
                if t.0 > best[k].0 {
                    best[k] = t;
                }
            }
        }
    }
    for (&(s0, h0, i, h_end), &(ratio, s)) in line.texels.iter().zip(&best) {
        let end = (h_end - h0) / reach;
        if end > ratio && end > 0.0 {
            found(i, reach);
        } else {
            found(i, if ratio > 0.0 { s - s0 } else { 0.0 });
        }
    }
}

/// Adds `c` at one end of an upper hull kept in order of insertion (always further along the
/// same direction of s), dropping the points it hides.
fn push(hull: &mut Vec<(f64, f64)>, c: (f64, f64)) {
    while hull.len() >= 2 {
        let (a, b) = (hull[hull.len() - 2], hull[hull.len() - 1]);
        // b is hidden when it lies on or below the segment a–c; the cross product's sign
        // flips with the direction of insertion.
        let cross = (b.1 - a.1) * (c.0 - a.0) - (c.1 - a.1) * (b.0 - a.0);
        if cross * (c.0 - a.0).signum() <= 0.0 {
            hull.pop();
        } else {
            break;
        }
    }
    hull.push(c);
}

/// The largest (h − h0)/(s − s0) over an upper hull all of whose points lie beyond s0, and the
/// s where it is reached (a binary search: the ratio rises then falls along the hull).
fn tangent(hull: &[(f64, f64)], s0: f64, h0: f64) -> (f64, f64) {
    // ratio(m) < ratio(m + 1), cross-multiplied (both distances are positive): no division
    // in the search.
    let rises = |m: usize| {
        let (a, b) = (hull[m], hull[m + 1]);
        (a.1 - h0) * (b.0 - s0) < (b.1 - h0) * (a.0 - s0)
    };
    let (mut lo, mut hi) = (0, hull.len() - 1);
    while lo < hi {
        let m = (lo + hi) / 2;
        if rises(m) {
            lo = m + 1;
        } else {
            hi = m;
        }
    }
    ((hull[lo].1 - h0) / (hull[lo].0 - s0), hull[lo].0)
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
    fn rows(&self, y0: usize, channels: &mut [f32], mut bins_out: Option<&mut [f32]>) {
        let (w, nb) = (self.grid.width, self.bins);
        let texels = w * self.grid.height;
        let n_rows = channels.len() / (w * 8);
        let mut near_ch = vec![0f32; n_rows * w * 8];
        let mut near = vec![0f32; n_rows * w * nb];
        self.near.rows(y0, &mut near_ch, Some(&mut near));
        let mut s = vec![0f32; nb];
        for r in 0..n_rows {
            let y = y0 + r;
            for x in 0..w {
                let o = r * w + x;
                for (n, v) in s.iter_mut().enumerate() {
                    let mut best = f64::from(near[o * nb + n]);
                    let d = self.far[n * texels + y * w + x];
                    if d > 0 {
                        let d = f64::from(d) * self.unit;
                        let from = (d - WINDOW).max(0.0);
                        let to = (d + WINDOW).min(self.reach);
                        let t = exact::tan_between(&self.grid, x, y, self.dirs[n], from, to);
                        best = best.max(exact::sin_of_tan(t));
                    }
                    *v = best as f32;
                }
                reduce_into(self.reduce, &s, &mut channels[o * 8..o * 8 + 8]);
                if let Some(b) = bins_out.as_deref_mut() {
                    b[o * nb..(o + 1) * nb].copy_from_slice(&s);
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `answer` against the plain definition: every sample in the window, every texel.
    #[test]
    fn windowed_hull_queries_match_brute_force() {
        let mut seed = 11u64;
        let mut unit = || {
            seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            (seed >> 11) as f64 / (1u64 << 53) as f64
        };
        let mut hull = Vec::new();
        for case in 0..300 {
            let mut line = Line::default();
            let n = 5 + (unit() * 80.0) as usize;
            let step = 0.5 + unit() * 3.0;
            let mut s = 0.0;
            for i in 0..n {
                let h = if unit() < 0.1 { 10.0 * unit() } else { unit() };
                line.samples.push((s, h));
                if unit() < 0.5 || i == 0 {
                    line.texels.push((s, h, line.texels.len(), f64::NAN));
                }
                s += step * (0.2 + unit());
            }
            let near = unit() * 4.0;
            let reach = if case % 3 == 0 { f64::INFINITY } else { near + 0.5 + unit() * 30.0 };
            let mut got = vec![f64::NAN; line.texels.len()];
            answer(&line, near, reach, &mut hull, |i, d| got[i] = d);
            for (i, &(s0, h0, ..)) in line.texels.iter().enumerate() {
                let mut best = (0.0f64, 0.0f64);
                for &(s, h) in &line.samples {
                    if s > s0 + near && s <= s0 + reach {
                        let r = (h - h0) / (s - s0);
                        if r > best.0 {
                            best = (r, s - s0);
                        }
                    }
                }
                // Ties between equal ratios may pick either sample: compare ratios.
                let ratio_of = |d: f64| {
                    line.samples
                        .iter()
                        .find(|p| ((p.0 - s0) - d).abs() < 1e-9)
                        .map_or(0.0, |p| (p.1 - h0) / d)
                };
                let r_got = if got[i] > 0.0 { ratio_of(got[i]) } else { 0.0 };
                assert!(
                    (r_got - best.0).abs() <= 1e-12 * (1.0 + best.0.abs()),
                    "case {case} texel {i}: got d {} (ratio {r_got}), want d {} (ratio {}); near {near} reach {reach}",
                    got[i],
                    best.1,
                    best.0
                );
            }
        }
    }
}
