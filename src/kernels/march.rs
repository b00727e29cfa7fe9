//! `method=march` (SPEC §3.2a): the line-of-sight horizon of §3.2 for a finite radius, sampled
//! instead of solved, vectorised across texels.
//!
//! Along a ray from a texel centre the bilinear surface h̃ is piecewise quadratic, with a knee
//! wherever the ray crosses a grid line. For one azimuth the crossings fall at the same offsets
//! from every texel centre, so the pieces between them, their cells and all their constants are
//! the same for every texel: the hot loop runs over a strip of consecutive texels, over
//! contiguous memory, and LLVM vectorises it. Per piece it samples the end (a crossing, where h̃
//! is a lerp of two texels) and K interior points (the chord minus twist·dx·dy·t·(L − t), the
//! cell's twist kept in a second tile): K = [`K_NEAR`] up to s = [`K_NEAR_UNTIL`], where the
//! bulge the chord misses is worth degrees, [`K_FAR`] beyond; plus the slope at s → 0 and the
//! point s = R, so the radius is honoured exactly. The earth's curvature costs one more
//! constant per sample ([`March::with_curvature`]).
//!
//! A segment of pieces is skipped when a bound from the largest height of the windows its cells
//! lie in (a third tile) beats no lane's best so far: the same f32 result as without the skip.
//! The layout mirrors the fast Lengyel kernel: a padded tile per band of rows (wrapped, or
//! `f32::MIN` for `edge=none`), heights relative to the middle of their range, the hot function
//! compiled per [`Isa`]. A tile larger than [`MAX_TILE`] falls back to the exact kernel.
//!
//! Precision: every sample is a real point of the ray within R, so the march never overshoots
//! §3.2 (sin α ≤ `exact`'s up to f32 rounding); what it misses is the top of a bulge between
//! samples. `tests/kernels/march.rs` checks it against a scalar f64 oracle of the same samples and
//! against [`super::exact`] at the same radius: mean ≤ 0.1° and p99 ≤ 0.5° of |Δα| per bin on
//! the corpus, real terrain, white noise and smooth maps; dense fields of tall single-texel
//! spikes are the stated worst case (p99 ≤ 1.5°). docs/march.md has the full account and the
//! measurements.

use super::exact::{self, ExactHorizon};
use super::isa::Isa;
use super::{near_holes, Grid, HorizonRows};
use crate::params::{Edge, Reduce};
use crate::progress::Progress;
use std::cell::RefCell;
use std::f64::consts::PI;

/// Up to this distance (texels) a piece gets [`K_NEAR`] interior points, beyond it [`K_FAR`].
pub const K_NEAR_UNTIL: f64 = 12.0;
/// Interior points per piece in the near field.
pub const K_NEAR: usize = 3;
/// Interior points per piece beyond [`K_NEAR_UNTIL`].
pub const K_FAR: usize = 1;

/// Widest strip of any variant; the tile keeps this many spare columns.
const STRIP: usize = 64;

/// Largest padded tile (floats, per thread) before falling back to the exact kernel: 64 MiB,
/// and as much again for each of the twist and window-max tiles beside it.
pub const MAX_TILE: usize = 1 << 24;

/// Height outside the map with `edge=none`.
const LOW: f32 = f32::MIN;

/// An interior point of a piece: r = rA + α·(rB − rA) + β·twist, ratio = r·inv − drop.
#[derive(Debug, Clone, Copy, Default)]
struct Inner {
    alpha: f32,
    beta: f32,
    inv: f32,
    /// The curvature drop over s at the point, c·s (0 without curvature).
    drop: f32,
}

/// One piece of a ray, between two crossings (or a crossing and R) inside one cell. Its end
/// interpolates t[i + o] (two taps at a crossing, four at R); `cell` is the offset of the
/// cell's twist.
#[derive(Debug, Clone, Copy)]
struct Piece {
    o: [isize; 4],
    /// Interpolation fractions of the end: along the line for 2 taps, (fx, fy) for 4. Lerps
    /// rather than weighted sums, so a flat neighbourhood gives exactly 0 (weights that sum
    /// to 1 only up to f32 rounding left ~1e-8 on a plane).
    f: [f32; 2],
    /// Taps of the end in use: 2 (a crossing) or 4 (a point inside a cell, the end at R).
    taps: usize,
    cell: isize,
    inv: f32,
    /// The curvature drop over s at the end, c·s (0 without curvature).
    drop: f32,
    inner: [Inner; MAX_INNER],
    /// Interior points in use.
    k: usize,
}

/// Interior points a piece can have: K_NEAR, plus the slope at s → 0 on the first piece (an
/// "interior point" too: with rA = 0 it is rB·(1/L) − dx·dy·twist·L, times inv = 1).
const MAX_INNER: usize = K_NEAR + 1;

/// Consecutive pieces of a ray with the same number of end taps and interior points, so one
/// monomorphised loop runs them.
#[derive(Debug, Clone, Copy)]
struct Run {
    taps: usize,
    k: usize,
    start: usize,
    end: usize,
}

/// Consecutive pieces of a ray that are skipped together when no lane of a strip can beat its
/// best tangent there (see [`strip_body`]). Every sample of the segment lies at s ≥ `s_start`
/// and in a cell (or on the edge of one) whose corners all lie inside the union of the
/// [`WIN`]×[`WIN`] windows whose top-left texels are at `win` from the texel; a bilinear value
/// is a convex combination of its cell's corners, so h̃ − h0 ≤ max(window maxima) − h0 there.
#[derive(Debug, Clone)]
struct Segment {
    /// 1/s at the segment's start (its samples lie beyond), rounded up: an upper bound.
    inv_start: f32,
    /// Offsets of the windows in the window-max tile (the second repeats the first when one
    /// covers the segment: a fixed count keeps the check a straight-line vector loop).
    win: [isize; 2],
    /// False for the first segment (s_start = 0: nothing to bound it by).
    check: bool,
    /// First piece, and the runs of the segment in [`Ray::runs`].
    start: usize,
    runs: std::ops::Range<usize>,
}

/// The pieces of one azimuth in order of s, grouped into runs, and the runs into segments.
#[derive(Debug, Clone, Default)]
struct Ray {
    pieces: Vec<Piece>,
    runs: Vec<Run>,
    segments: Vec<Segment>,
}

/// Side of the square windows of the window-max tile.
const WIN: i64 = 4;

/// Most pieces in one segment: a skipped segment saves its work, a checked one costs two loads
/// and a few vector ops per lane, so a segment is long enough to amortise the check but short
/// enough that its bound stays tight.
const SEG_PIECES: usize = 8;

/// The march kernel prepared for one grid (see the module doc).
pub struct March<'a> {
    grid: Grid<'a>,
    radius: u32,
    bins: usize,
    reduce: Reduce,
    /// Tile padding on every side (rows and columns), ≥ the farthest tap.
    pad: usize,
    /// Tile row length: pad + width + pad + STRIP.
    stride: usize,
    rays: Vec<Ray>,
    /// Heights are stored relative to this (the middle of the range).
    reference: f32,
    /// A margin, in height, over the f32 rounding of any sample against the exact bilinear
    /// value of its corners: interior points add twist·β to a lerp, a few roundings of values
    /// up to 4·max|h − reference|.
    tol: f32,
    isa: Isa,
    fallback: Option<ExactHorizon<'a>>,
    progress: Option<Progress>,
    /// Earth-curvature drop per texel² (see [`March::with_curvature`]).
    curv: f64,
    /// With nodata holes: the exact kernel (with the holes) and, per texel, whether a hole lies
    /// within R + 1 (see [`March::with_holes`]).
    holes: Option<(ExactHorizon<'a>, super::Flags)>,
    /// Which bins the reduction reads: all of them, or one per channel for `reduce=point`
    /// (unless the per-bin values are asked for, as the Fourier output does).
    cast: Vec<bool>,
    all: Vec<bool>,
}

// The tile a thread reuses band after band.
thread_local! {
    static TILE: RefCell<[Vec<f32>; 3]> = const { RefCell::new([Vec::new(), Vec::new(), Vec::new()]) };
}

impl<'a> March<'a> {
    /// Prepares the kernel for `grid` with a finite `radius` (≥ 1) and `bins` azimuths.
    pub fn new(grid: Grid<'a>, radius: u32, bins: u32, reduce: Reduce) -> Self {
        let radius = radius.max(1);
        let bins = bins.max(8) as usize;
        let pad = radius as usize + 2;
        let stride = pad + grid.width + pad + STRIP;
        let row_step = grid.row_step();
        let rays = make_rays(bins, row_step, radius, stride, 0.0);
        let (lo, hi) = grid.range();
        let reference = ((lo as f64 + hi as f64) * 0.5) as f32;
        let tol = 64.0 * f32::EPSILON * (hi - reference).abs().max((lo - reference).abs());
        // A band is at least one row; its tile is that plus the padding above and below.
        let tile = (1 + 2 * pad) * stride;
        let fallback =
            (tile > MAX_TILE).then(|| ExactHorizon::new(grid, Some(radius), bins as u32, reduce));
        let step = bins / 8;
        let cast = (0..bins).map(|n| reduce == Reduce::Average || n % step == 0).collect();
        March {
            grid,
            radius,
            bins,
            reduce,
            pad,
            stride,
            rays,
            reference,
            tol,
            isa: Isa::detect(),
            fallback,
            progress: None,
            curv: 0.0,
            holes: None,
            cast,
            all: vec![true; bins],
        }
    }

    /// Checks `progress` for cancel between strips (a band can be long at large radii).
    pub fn with_cancel(mut self, progress: &Progress) -> Self {
        self.fallback = self.fallback.map(|f| f.with_cancel(progress));
        self.holes = self.holes.take().map(|(e, near)| (e.with_cancel(progress), near));
        self.progress = Some(progress.clone());
        self
    }

    /// Lowers a point at arc length s by `curv`·s² texels (the earth's curvature, SPEC §3.7:
    /// `curv` = cell_size² · height_scale / (2 R_e), as [`ExactHorizon::with_curvature`] takes
    /// it; the fallback for huge tiles gets it too). The drop only lowers samples, so a
    /// segment's bound from the window maxima stays an upper bound and the skips stay exact.
    pub fn with_curvature(mut self, curv: f64) -> Self {
        let curv = if curv.is_finite() && curv > 0.0 { curv } else { 0.0 };
        if curv != self.curv {
            self.curv = curv;
            let row_step = self.grid.row_step();
            self.rays = make_rays(self.bins, row_step, self.radius, self.stride, curv);
            self.fallback = self.fallback.map(|f| f.with_curvature(curv));
            self.holes = self.holes.take().map(|(e, near)| (e.with_curvature(curv), near));
        }
        self
    }

    /// Nodata holes (SPEC §2), one flag per texel: the cells touching a hole are not surface.
    /// The bake fills holes far below the map ([`crate::heightmap::HOLE_DEPTH`]); that keeps
    /// the samples that lerp a hole corner low, but not the rest of such a cell: its twist is
    /// enormous, so the interior points of a piece through it rise far above the surface, and
    /// an edge between two such cells is no surface either. The march measured 25° p99 over
    /// `exact` near 6 % random holes (`tests/kernels/march.rs`). So a texel with a hole within
    /// R + 1 (the farthest corner its rays can read) takes [`ExactHorizon`]'s walk with the
    /// holes instead; the rest of the map keeps the vectorised march. A DEM whose nodata is a
    /// border pays the exact kernel's price only within R of it.
    pub fn with_holes(mut self, holes: Option<&'a [bool]>) -> Self {
        let (w, h) = (self.grid.width, self.grid.height);
        let holes = holes.filter(|m| m.len() == w * h && m.iter().any(|&o| o));
        self.fallback = self.fallback.map(|f| f.with_holes(holes));
        self.holes = holes.map(|m| {
            let exact =
                ExactHorizon::walker(self.grid, Some(self.radius), self.bins as u32, self.reduce)
                    .with_curvature(self.curv)
                    .with_holes(Some(m));
            let exact = match &self.progress {
                Some(p) => exact.with_cancel(p),
                None => exact,
            };
            (exact, near_holes(m, w, h, self.radius as usize + 1, self.grid.edge == Edge::Wrap))
        });
        self
    }

    /// Forces a compiled variant (benches and tests compare them).
    pub fn with_isa(mut self, isa: Isa) -> Self {
        if isa.supported() {
            self.isa = isa;
        }
        self
    }

    /// Samples per ray (piece ends and interior points), averaged over the azimuths.
    pub fn samples_per_ray(&self) -> f64 {
        let n: usize = self.rays.iter().flat_map(|r| &r.pieces).map(|p| 1 + p.k).sum();
        n as f64 / self.rays.len() as f64
    }

    /// Fills `tile` with rows `y0 − pad .. y0 + rows + pad` of the map, relative to the
    /// reference height, wrapped or padded with [`LOW`], and `twist` with each cell's
    /// h00 − h10 − h01 + h11 (the cell whose top-left texel has that index); 0 for a cell with
    /// a corner off the map (an interior point of a piece off the surface lerps an end at
    /// [`LOW`] and never counts; only a piece along the map's border line, where β = 0, has
    /// both ends on the surface there, and its interior points are real points of the ray:
    /// with the curvature drop they can beat both ends, and the slope at s → 0 is one); and
    /// `wmax` with the largest height of the WIN×WIN window whose top-left texel has that index
    /// (clipped at the tile's end). Returns a margin, in height, that covers the f32 rounding
    /// of a sample against the exact bilinear value of its corners (see [`strip_body`]).
    fn fill(
        &self,
        tile: &mut Vec<f32>,
        twist: &mut Vec<f32>,
        wmax: &mut Vec<f32>,
        y0: usize,
        rows: usize,
    ) -> f32 {
        let (w, h) = (self.grid.width as i64, self.grid.height as i64);
        let pad = self.pad as i64;
        let tile_rows = rows + 2 * self.pad;
        tile.clear();
        tile.resize(tile_rows * self.stride, LOW);
        for tr in 0..tile_rows {
            let ir = y0 as i64 - pad + tr as i64;
            let dst = &mut tile[tr * self.stride..(tr + 1) * self.stride];
            let src_row = match self.grid.edge {
                Edge::Wrap => ir.rem_euclid(h),
                Edge::None if (0..h).contains(&ir) => ir,
                Edge::None => continue,
            } as usize;
            let src = &self.grid.heights[src_row * w as usize..(src_row + 1) * w as usize];
            match self.grid.edge {
                Edge::Wrap => {
                    for (tc, d) in dst[..(pad + w + pad) as usize].iter_mut().enumerate() {
                        *d = src[(tc as i64 - pad).rem_euclid(w) as usize] - self.reference;
                    }
                }
                Edge::None => {
                    let row = &mut dst[pad as usize..(pad + w) as usize];
                    for (d, &s) in row.iter_mut().zip(src) {
                        *d = s - self.reference;
                    }
                }
            }
        }
        let n = tile.len();
        twist.clear();
        twist.resize(n, 0.0);
        let st = self.stride;
        for i in 0..n.saturating_sub(st + 1) {
            let (a, b, c, d) = (tile[i], tile[i + 1], tile[i + st], tile[i + st + 1]);
            if a != LOW && b != LOW && c != LOW && d != LOW {
                twist[i] = a - b - c + d;
            }
        }
        // Window maxima: along the row (running into the next row's start only widens a
        // window, which keeps it an upper bound), then down the columns in place (row i + k is
        // still unchanged when row i reads it).
        // (A plain comparison rather than f32::max: the tile holds no NaN, and it vectorises
        // without NaN fix-ups.)
        let max = |a: f32, b: f32| if a > b { a } else { b };
        let w = WIN as usize;
        wmax.clear();
        wmax.extend_from_slice(tile);
        for k in 1..w.min(n) {
            for (m, &v) in wmax.iter_mut().zip(&tile[k..]) {
                *m = max(*m, v);
            }
        }
        for r in 0..tile_rows {
            let (cur, below) = wmax[r * st..].split_at_mut(st);
            for k in 0..(w - 1).min(below.len() / st) {
                for (m, &v) in cur.iter_mut().zip(&below[k * st..(k + 1) * st]) {
                    *m = max(*m, v);
                }
            }
        }
        self.tol
    }
}

/// The rays of `bins` azimuths (see [`ray_samples`]).
fn make_rays(bins: usize, row_step: i64, radius: u32, stride: usize, curv: f64) -> Vec<Ray> {
    (0..bins)
        .map(|n| {
            let (dx, dy) = exact::direction(n as f64 * 2.0 * PI / bins as f64, row_step);
            ray_samples(dx, dy, radius as f64, stride as isize, curv)
        })
        .collect()
}

/// The pieces of the ray along image direction (`dx`, `dy`) (unit), up to `radius`, as offsets
/// into tiles of row length `stride`, with the curvature drop `curv`·s² (texels).
fn ray_samples(dx: f64, dy: f64, radius: f64, stride: isize, curv: f64) -> Ray {
    let off = |c: i64, r: i64| r as isize * stride + c as isize;
    let (ax, ay) = (dx.abs(), dy.abs());
    // Grid-line crossings, in order of s, then R.
    let mut ends: Vec<f64> = Vec::new();
    for a in [ax, ay] {
        if a > 1e-12 {
            let mut k = 1.0;
            while k / a <= radius + 1e-9 {
                ends.push(k / a);
                k += 1.0;
            }
        }
    }
    ends.push(radius);
    ends.sort_by(f64::total_cmp);
    ends.dedup_by(|a, b| (*a - *b).abs() < 1e-9);
    let snap = |v: f64| {
        let r = v.round();
        if (v - r).abs() < 1e-9 {
            r
        } else {
            v
        }
    };
    let mut pieces = Vec::with_capacity(ends.len());
    // Per piece: where it starts (s) and the box of texels (c0, r0, c1, r1) its samples
    // interpolate: its cell's corners and its end's taps.
    let mut spans: Vec<(f64, [i64; 4])> = Vec::with_capacity(ends.len());
    let mut prev = 0.0;
    for &s in &ends {
        let (x, y) = (snap(s * dx), snap(s * dy));
        let (x0, y0) = (x.floor(), y.floor());
        let (fx, fy) = (x - x0, y - y0);
        let (c, r) = (x0 as i64, y0 as i64);
        // The end: on a column line (fx = 0) the two texels above and below, on a row line the
        // two beside, at a corner one texel, anywhere else (the end at R) all four.
        let (o, f, taps) = if fx == 0.0 || fy == 0.0 {
            let (o1, f) = if fx == 0.0 { (off(c, r + 1), fy) } else { (off(c + 1, r), fx) };
            ([off(c, r), o1, 0, 0], [f as f32, 0.0], 2)
        } else {
            let o = [off(c, r), off(c + 1, r), off(c, r + 1), off(c + 1, r + 1)];
            (o, [fx as f32, fy as f32], 4)
        };
        let len = s - prev;
        // The piece's cell: the one its middle lies in.
        let mid = prev + len * 0.5;
        let (cx, cy) = ((mid * dx).floor() as i64, (mid * dy).floor() as i64);
        let mut k = if mid <= K_NEAR_UNTIL { K_NEAR } else { K_FAR };
        let mut inner = [Inner::default(); MAX_INNER];
        for (j, p) in inner.iter_mut().enumerate().take(k) {
            let t = len * (j + 1) as f64 / (k + 1) as f64;
            *p = Inner {
                alpha: (t / len) as f32,
                beta: (-dx * dy * t * (len - t)) as f32,
                inv: (1.0 / (prev + t)) as f32,
                drop: (curv * (prev + t)) as f32,
            };
        }
        if pieces.is_empty() {
            // The slope at s → 0: the derivative of chord − dx·dy·twist·t·(L − t) at t = 0.
            // (At s = 0 the drop's slope 2·c·s is 0 too.)
            inner[k] = Inner {
                alpha: (1.0 / len) as f32,
                beta: (-dx * dy * len) as f32,
                inv: 1.0,
                drop: 0.0,
            };
            k += 1;
        }
        let (inv, drop) = ((1.0 / s) as f32, (curv * s) as f32);
        pieces.push(Piece { o, f, taps, cell: off(cx, cy), inv, drop, inner, k });
        let (tc1, tr1) = if taps == 4 || fy == 0.0 { (c + 1, r) } else { (c, r) };
        let tr1 = if taps == 4 || fx == 0.0 { tr1.max(r + 1) } else { tr1 };
        let bx = [cx.min(c), cy.min(r), (cx + 1).max(tc1), (cy + 1).max(tr1)];
        spans.push((prev, bx));
        prev = s;
    }
    // Segments: the first piece alone (it starts at s = 0), then greedily as many pieces as
    // two windows cover, up to SEG_PIECES.
    let windows = |b: &[i64; 4]| ((b[2] - b[0] + WIN) / WIN, (b[3] - b[1] + WIN) / WIN);
    let mut bounds: Vec<(usize, usize, [i64; 4])> = Vec::new();
    let mut i = 0;
    while i < pieces.len() {
        let mut bx = spans[i].1;
        let mut j = i + 1;
        while i > 0 && j < pieces.len() && j - i < SEG_PIECES {
            let b = spans[j].1;
            let u = [bx[0].min(b[0]), bx[1].min(b[1]), bx[2].max(b[2]), bx[3].max(b[3])];
            let (nx, ny) = windows(&u);
            if nx * ny > 2 {
                break;
            }
            bx = u;
            j += 1;
        }
        bounds.push((i, j, bx));
        i = j;
    }
    let mut runs: Vec<Run> = Vec::new();
    let mut segments = Vec::with_capacity(bounds.len());
    for &(a, b, bx) in &bounds {
        let first = runs.len();
        for (i, p) in pieces.iter().enumerate().take(b).skip(a) {
            // A run never spans two segments: the strip may skip one and run the other.
            match runs[first..].last_mut() {
                Some(r) if r.taps == p.taps && r.k == p.k => r.end = i + 1,
                _ => runs.push(Run { taps: p.taps, k: p.k, start: i, end: i + 1 }),
            }
        }
        let (nx, ny) = windows(&bx);
        let w0 = off(bx[0], bx[1]);
        let w1 = if nx > 1 { off(bx[0] + WIN, bx[1]) } else { off(bx[0], bx[1] + WIN) };
        let s_a = spans[a].0;
        segments.push(Segment {
            inv_start: if s_a > 0.0 { (1.0 / s_a * (1.0 + 1e-6)) as f32 } else { f32::INFINITY },
            win: [w0, if nx * ny > 1 { w1 } else { w0 }],
            check: s_a > 0.0,
            start: a,
            runs: first..runs.len(),
        });
    }
    Ray { pieces, runs, segments }
}

/// a·b + c, fused where the variant has FMA (Rust never fuses on its own; without the
/// feature `mul_add` would call the C library's `fmaf`).
#[inline(always)]
fn madd<const FMA: bool>(a: f32, b: f32, c: f32) -> f32 {
    if FMA {
        a.mul_add(b, c)
    } else {
        a * b + c
    }
}

/// The `L` values of a tile at offset `o` from the strip's first texel.
#[inline(always)]
fn lanes_at<const L: usize>(buf: &[f32], base: usize, o: isize) -> &[f32; L] {
    buf[(base as isize + o) as usize..][..L].try_into().expect("offset inside the tile")
}

/// The end value rB = h̃ − h0 of piece `p` from its taps' heights `t` (the first `TAPS`).
/// The one formula for it, so that an end recomputed after a skipped segment is the same f32
/// as had it been run.
#[inline(always)]
fn end_value<const TAPS: usize, const FMA: bool>(p: &Piece, t: [f32; TAPS], h0: f32) -> f32 {
    if TAPS == 2 {
        madd::<FMA>(p.f[0], t[1] - t[0], t[0] - h0)
    } else {
        let top = madd::<FMA>(p.f[0], t[1] - t[0], t[0]);
        let bottom = madd::<FMA>(p.f[0], t[3] - t[2], t[2]);
        madd::<FMA>(p.f[1], bottom - top, top) - h0
    }
}

/// The end values of piece `p` (with `TAPS` taps) in every lane, into `r`.
#[inline(always)]
fn end_values<const L: usize, const TAPS: usize, const FMA: bool>(
    tile: &[f32],
    base: usize,
    p: &Piece,
    h0: &[f32; L],
    r: &mut [f32; L],
) {
    let taps: [&[f32; L]; TAPS] = std::array::from_fn(|j| lanes_at(tile, base, p.o[j]));
    for l in 0..L {
        r[l] = end_value::<TAPS, FMA>(p, std::array::from_fn(|j| taps[j][l]), h0[l]);
    }
}

/// The pieces of one run over a strip of `L` lanes: each lane's end value rB, its ratio, the
/// `K` interior points from rA, rB and the cell's twist; one fused loop over the lanes, so the
/// values stay in registers.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn run<const L: usize, const TAPS: usize, const K: usize, const FMA: bool>(
    tile: &[f32],
    twist: &[f32],
    base: usize,
    pieces: &[Piece],
    h0: &[f32; L],
    best: &mut [f32; L],
    r_a: &mut [f32; L],
) {
    for p in pieces {
        let taps: [&[f32; L]; TAPS] = std::array::from_fn(|j| lanes_at(tile, base, p.o[j]));
        let tw: &[f32; L] = lanes_at(twist, base, p.cell);
        let inner: [Inner; K] = std::array::from_fn(|j| p.inner[j]);
        for l in 0..L {
            let rb = end_value::<TAPS, FMA>(p, std::array::from_fn(|j| taps[j][l]), h0[l]);
            let (ra, t) = (r_a[l], tw[l]);
            let d = rb - ra;
            let mut m = best[l];
            let v = madd::<FMA>(rb, p.inv, -p.drop);
            m = if v > m { v } else { m };
            for q in &inner {
                let r = madd::<FMA>(t, q.beta, madd::<FMA>(d, q.alpha, ra));
                let v = madd::<FMA>(r, q.inv, -q.drop);
                m = if v > m { v } else { m };
            }
            best[l] = m;
            r_a[l] = rb;
        }
    }
}

/// The band's tiles: heights, twists and window maxima (see [`March::fill`]), and the margin
/// that covers a sample's rounding.
#[derive(Clone, Copy)]
struct Tiles<'t> {
    tile: &'t [f32],
    twist: &'t [f32],
    wmax: &'t [f32],
    tol: f32,
}

/// One strip: `L` consecutive texels of one row, every cast azimuth; writes sin α per bin into
/// `sbuf[n * L + lane]`. `base` is the strip's first texel in the tiles.
///
/// Samples run from near to far, and a segment whose bound (max(window maxima) − h0 + tol) / s
/// at its start cannot beat the best tangent found so far in any lane is skipped: the horizon
/// is a maximum, so leaving out samples that are no larger changes nothing, bit for bit. After a
/// skip, the next segment's rA (the end value before it) is recomputed exactly as it would have
/// been.
#[inline(always)]
fn strip_body<const L: usize, const FMA: bool>(
    t: Tiles<'_>,
    base: usize,
    rays: &[Ray],
    cast: &[bool],
    sbuf: &mut [f32],
) {
    let (tile, twist) = (t.tile, t.twist);
    let h0: &[f32; L] = tile[base..base + L].try_into().expect("strip inside the tile");
    for (n, ray) in rays.iter().enumerate() {
        if !cast[n] {
            continue;
        }
        let mut best = [0.0f32; L];
        let mut r_a = [0.0f32; L];
        let mut stale = false;
        for seg in &ray.segments {
            if seg.check {
                let w0: &[f32; L] = lanes_at(t.wmax, base, seg.win[0]);
                let w1: &[f32; L] = lanes_at(t.wmax, base, seg.win[1]);
                let mut any = false;
                for l in 0..L {
                    // (The curvature drop only lowers samples: still an upper bound.)
                    let bound = (w0[l].max(w1[l]) - h0[l] + t.tol) * seg.inv_start;
                    any |= bound > best[l];
                }
                if !any {
                    stale = true;
                    continue;
                }
                if stale {
                    // rA of the segment's first piece: the end of the (skipped) one before.
                    let p = &ray.pieces[seg.start - 1];
                    match p.taps {
                        2 => end_values::<L, 2, FMA>(tile, base, p, h0, &mut r_a),
                        _ => end_values::<L, 4, FMA>(tile, base, p, h0, &mut r_a),
                    }
                    stale = false;
                }
            }
            for r in &ray.runs[seg.runs.clone()] {
                let ps = &ray.pieces[r.start..r.end];
                let (b, ra) = (&mut best, &mut r_a);
                match (r.taps, r.k) {
                    (2, K_FAR) => run::<L, 2, K_FAR, FMA>(tile, twist, base, ps, h0, b, ra),
                    (2, K_NEAR) => run::<L, 2, K_NEAR, FMA>(tile, twist, base, ps, h0, b, ra),
                    (2, MAX_INNER) => run::<L, 2, MAX_INNER, FMA>(tile, twist, base, ps, h0, b, ra),
                    (4, K_FAR) => run::<L, 4, K_FAR, FMA>(tile, twist, base, ps, h0, b, ra),
                    (4, K_NEAR) => run::<L, 4, K_NEAR, FMA>(tile, twist, base, ps, h0, b, ra),
                    (4, MAX_INNER) => run::<L, 4, MAX_INNER, FMA>(tile, twist, base, ps, h0, b, ra),
                    _ => unreachable!("ray_samples makes only these runs"),
                }
            }
        }
        // sin α = t / √(1 + t²); t is capped so that t² stays finite (1e18 is 90° to f32).
        let out = &mut sbuf[n * L..(n + 1) * L];
        for l in 0..L {
            let t = best[l].min(1e18);
            out[l] = t / (1.0 + t * t).sqrt();
        }
    }
}

impl March<'_> {
    /// Lanes per strip of the selected variant.
    fn lanes(&self) -> usize {
        match self.isa {
            Isa::Avx512 => 32,
            Isa::Avx2 => 16,
            Isa::Baseline => 8,
        }
    }

    fn strip(&self, t: Tiles<'_>, base: usize, cast: &[bool], sbuf: &mut [f32]) {
        let rays = &self.rays;
        match self.isa {
            // SAFETY: `Isa::detect`/`with_isa` only select a variant the CPU supports.
            #[cfg(target_arch = "x86_64")]
            Isa::Avx512 => unsafe { strip_avx512(t, base, rays, cast, sbuf) },
            #[cfg(target_arch = "x86_64")]
            Isa::Avx2 => unsafe { strip_avx2(t, base, rays, cast, sbuf) },
            _ => strip_body::<8, false>(t, base, rays, cast, sbuf),
        }
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx2,fma")]
unsafe fn strip_avx512(t: Tiles<'_>, base: usize, rays: &[Ray], cast: &[bool], sbuf: &mut [f32]) {
    strip_body::<32, true>(t, base, rays, cast, sbuf)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn strip_avx2(t: Tiles<'_>, base: usize, rays: &[Ray], cast: &[bool], sbuf: &mut [f32]) {
    strip_body::<16, true>(t, base, rays, cast, sbuf)
}

impl HorizonRows for March<'_> {
    fn width(&self) -> usize {
        self.grid.width
    }
    fn height(&self) -> usize {
        self.grid.height
    }
    fn bins(&self) -> usize {
        self.bins
    }
    fn texel_cost(&self) -> f64 {
        // Samples grow linearly with R; at R = 16 a texel costs about 3× Lengyel's (measured
        // with benches/frontier.rs), which keeps a band near the 25 ms a cancel waits for.
        (3.0 * self.radius as f64 / 16.0).max(1.0)
    }
    fn rows(&self, y0: usize, channels: &mut [f32], mut bins_out: Option<&mut [f32]>) {
        if let Some(f) = &self.fallback {
            return f.rows(y0, channels, bins_out);
        }
        let (w, nb) = (self.grid.width, self.bins);
        let rows = channels.len() / (w * 8);
        let lanes = self.lanes();
        let mut sbuf = vec![0.0f32; nb * lanes];
        let mut hbuf = vec![0.0f32; if self.holes.is_some() { nb } else { 0 }];
        let mut chans = vec![0.0f32; 8 * lanes];
        let step = nb / 8;
        let half = (nb / 16) as i64;
        let inv = 1.0 / (step + 1) as f32;
        let cast = if bins_out.is_some() { &self.all } else { &self.cast };
        TILE.with(|cell| {
            let [tile, twist, wmax] = &mut *cell.borrow_mut();
            let tol = self.fill(tile, twist, wmax, y0, rows);
            let tiles = Tiles { tile, twist, wmax, tol };
            for r in 0..rows {
                for x0 in (0..w).step_by(lanes) {
                    if self.progress.as_ref().is_some_and(Progress::is_canceled) {
                        return;
                    }
                    // Texel by texel, not strip by strip: which walk a texel takes must not
                    // depend on where the strips start (a tile's window starts anywhere in the
                    // map, and the strip width is the CPU's), so a tiled bake is the untiled
                    // one's bytes. The march's lanes are independent of each other.
                    let row = (y0 + r) * w;
                    let span = row + x0..row + (x0 + lanes).min(w);
                    let near_hole = self.holes.as_ref().filter(|(_, near)| near.any(span.clone()));
                    let all_near =
                        near_hole.is_some_and(|(_, near)| span.clone().all(|t| near.get(t)));
                    if !all_near {
                        let base = (r + self.pad) * self.stride + self.pad + x0;
                        self.strip(tiles, base, cast, &mut sbuf);
                    }
                    if let Some((exact, near)) = near_hole {
                        for l in (0..lanes.min(w - x0)).filter(|&l| near.get(row + x0 + l)) {
                            exact.texel_bins(x0 + l, y0 + r, &mut hbuf);
                            for (n, &v) in hbuf.iter().enumerate() {
                                sbuf[n * lanes + l] = v;
                            }
                        }
                    }
                    // The reduction across the strip's lanes at once, bins in the same order
                    // as one texel at a time (so the same f32 sums).
                    for (c, acc) in chans.chunks_exact_mut(lanes).enumerate() {
                        let centre = (c * step) as i64;
                        match self.reduce {
                            Reduce::Point => {
                                acc.copy_from_slice(&sbuf[c * step * lanes..][..lanes])
                            }
                            Reduce::Average => {
                                acc.fill(0.0);
                                for k in -half..=half {
                                    let n = (centre + k).rem_euclid(nb as i64) as usize;
                                    for (a, &v) in acc.iter_mut().zip(&sbuf[n * lanes..]) {
                                        *a += v;
                                    }
                                }
                                acc.iter_mut().for_each(|a| *a *= inv);
                            }
                        }
                    }
                    for l in 0..lanes.min(w - x0) {
                        let texel = r * w + x0 + l;
                        let ch = &mut channels[texel * 8..texel * 8 + 8];
                        for (c, o) in ch.iter_mut().enumerate() {
                            *o = chans[c * lanes + l];
                        }
                        if let Some(b) = bins_out.as_deref_mut() {
                            for (n, o) in b[texel * nb..(texel + 1) * nb].iter_mut().enumerate() {
                                *o = sbuf[n * lanes + l];
                            }
                        }
                    }
                }
            }
        });
    }
}
