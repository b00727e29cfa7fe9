//! The exact line-of-sight horizon (SPEC §3.2): the ground truth the approximations are judged
//! against.
//!
//! For texel p with height h0 and azimuth φ, u = (cos φ, sin φ) in tangent space,
//!   tan α = max(0, sup over 0 < s ≤ R of (h̃(p + s·u) − h0) / s)
//! where h̃ is the bilinear surface through the texel centres, and the stored value is
//! sin α = tan α / √(1 + tan² α).
//!
//! Along a straight line the bilinear surface inside one cell is a quadratic in s, so the
//! ratio's maximum over the ray's piece in that cell has a closed form (its exit point and at
//! most one interior critical point): a ray costs one small evaluation per cell it crosses,
//! every candidate is a real point of the ray, and no maximum between samples is missed. At
//! s → 0 the ratio tends to the first cell's slope, which counts. A convex-hull sweep would be
//! O(1) per texel, but its lines miss the texel centres, so [`ExactHorizon`] keeps every ray
//! texel-centred and exact and makes rays cheap instead:
//! - near field (s ≤ `NEAR_ARC` texels or R): 16 texels of a row in lockstep (`StripMarch`),
//!   whose rays cross the same pieces at one azimuth; a piece, and beyond 32 texels a whole span
//!   of pieces, is culled when no lane could beat its best value there;
//! - far field (longer rays): a scalar walk seeded with the near-field value that skips every
//!   block of a max pyramid which cannot beat the best so far, and stops once the map's highest
//!   point cannot.
//!
//! Culling and skipping are conservative, so the result is that of visiting every cell, which
//! [`ExactMarch`] (the plain oracle) does; the tests compare the two.
//!
//! Precision: exact up to f64 rounding; the f32 near field is within 1e-5 in sin α of the f64
//! oracle (asserted). `edge=none` ends a ray where it leaves [0, W−1] × [0, H−1] (the outer half
//! texel is not surface); `radius` clips it at s = R exactly, and `unlimited` runs to the map's
//! edge (`none`) or max(W, H) texels (`wrap`). docs/exact.md has the full account: each part's
//! working, the edges, and the measurements behind the constants.

mod oracle;
pub(crate) mod walk;

pub use oracle::ExactMarch;
pub use walk::{horizon_sin, signed_elevation, SignedElevations};

use super::nearfield::{StripMarch, LANES};
use super::{reduce_into, Grid, HorizonRows};
use crate::params::{Edge, Reduce};
use crate::progress::Progress;
use std::f64::consts::PI;
use walk::{walk, Pyramid, Ray};

/// Image-space unit direction (column step, row step) of tangent-space azimuth `phi` (radians).
/// Components within 1e-12 of 0 are snapped to exactly 0, so rays at multiples of 90° stay on
/// their row or column (sin π is 1.2e-16 in floating point; with `edge=none` such a ray along a
/// border row would otherwise leave the surface at once).
pub fn direction(phi: f64, row_step: i64) -> (f64, f64) {
    let snap = |v: f64| if v.abs() < 1e-12 { 0.0 } else { v };
    let (s, c) = phi.sin_cos();
    let (c, s) = (snap(c), snap(s));
    // Renormalise after snapping so (dx, dy) stays a unit vector.
    let n = (c * c + s * s).sqrt();
    (c / n, s / n * row_step as f64)
}

/// Image-space directions of the `bins` azimuths φ_n = n·2π/bins.
fn bin_directions(bins: usize, row_step: i64) -> Vec<(f64, f64)> {
    (0..bins).map(|n| direction(n as f64 * 2.0 * PI / bins as f64, row_step)).collect()
}

/// sin α from tan α ≥ 0 (1 for a vertical horizon, t = ∞).
#[inline]
pub(crate) fn sin_of_tan(t: f64) -> f64 {
    if t.is_infinite() {
        1.0
    } else {
        t / (1.0 + t * t).sqrt()
    }
}

/// Arc length the vectorised near field covers before the seeded, pyramid-skipping [`walk`];
/// chosen by measurement (docs/exact.md, "Constants").
const NEAR_ARC: f64 = 1024.0;

/// The production exact kernel: the same rays as [`ExactMarch`], with empty space skipped
/// through a max pyramid and each ray stopped once nothing left can raise it.
#[derive(Debug, Clone)]
pub struct ExactHorizon<'a> {
    grid: Grid<'a>,
    radius: Option<f64>,
    dirs: Vec<(f64, f64)>,
    reduce: Reduce,
    pyramid: Pyramid,
    hmax: f64,
    progress: Option<Progress>,
    /// Unwrapped cell column `lo + i` → stored column, for i in 0..; likewise rows → row·W.
    /// Replaces two `rem_euclid` per corner fetch in the hot loop.
    lo: i64,
    cols: Vec<u32>,
    rows: Vec<u32>,
    near: StripMarch,
    /// Whether `near` has its padded rows (not for an [`ExactHorizon::walker`]).
    strips: bool,
    /// Earth-curvature drop per texel² (see [`ExactHorizon::with_curvature`]).
    curv: f64,
    /// Nodata holes (see [`ExactHorizon::with_holes`]).
    holes: Option<&'a [bool]>,
}

impl<'a> ExactHorizon<'a> {
    /// Prepares the kernel (O(W·H) block maxima). `radius`: `None` = unlimited, otherwise at
    /// most max(`MAX_RADIUS`, W, H) (larger values are clamped; `params` rejects them); `bins`
    /// a multiple of 16 (validated by `params`).
    pub fn new(grid: Grid<'a>, radius: Option<u32>, bins: u32, reduce: Reduce) -> Self {
        Self::build(grid, radius, bins, reduce, true)
    }

    /// [`ExactHorizon::new`] for a caller that only walks single rays ([`ExactHorizon::tan_at`],
    /// [`ExactHorizon::horizon_and_distance`]): without the vectorised near field's padded
    /// rows, which only [`HorizonRows::rows`] reads (8 bytes a texel: 545 MB at 8192², which
    /// `sweep` on a map with holes held for nothing). Its `rows` must not be called.
    pub(crate) fn walker(grid: Grid<'a>, radius: Option<u32>, bins: u32, reduce: Reduce) -> Self {
        Self::build(grid, radius, bins, reduce, false)
    }

    fn build(grid: Grid<'a>, radius: Option<u32>, bins: u32, reduce: Reduce, strips: bool) -> Self {
        let (w, h) = (grid.width, grid.height);
        // Bounded so a caller bypassing `params` cannot ask for gigantic tables.
        let cap = crate::params::MAX_RADIUS.max(w.max(h) as u32);
        let radius = radius.map(|r| f64::from(r.min(cap)));
        // How far outside the map a ray can go: the tables below must cover it.
        let reach = match grid.edge {
            Edge::Wrap => radius.unwrap_or(w.max(h) as f64),
            Edge::None => 1.0,
        };
        let pyramid = Pyramid::new(&grid, reach);
        let dirs = bin_directions(bins as usize, grid.row_step());
        let hmax = grid.range().1 as f64;
        let lo = -(reach.ceil() as i64) - 4;
        let map = |n: usize, mul: usize| -> Vec<u32> {
            let hi = n as i64 + reach.ceil() as i64 + 4;
            (lo..=hi)
                .map(|c| {
                    let c = match grid.edge {
                        Edge::Wrap => c.rem_euclid(n as i64),
                        Edge::None => c.clamp(0, n as i64 - 1),
                    };
                    (c as usize * mul) as u32
                })
                .collect()
        };
        let (cols, rows) = (map(w, 1), map(h, w));
        // Where every ray is clipped alike: a piece straddling a lane's own end would be lost
        // (edge=none ends fall on grid lines, i.e. on piece boundaries, so they may differ).
        let r_all = match grid.edge {
            Edge::Wrap => radius.unwrap_or(w.max(h) as f64),
            Edge::None => radius.unwrap_or(f64::INFINITY),
        };
        let s_cut = r_all.min(NEAR_ARC);
        let near = if strips {
            StripMarch::new(&grid, &dirs, s_cut)
        } else {
            StripMarch::without_rows(&grid, &dirs, &vec![s_cut; dirs.len()], grid.range())
        };
        ExactHorizon {
            grid,
            radius,
            dirs,
            reduce,
            pyramid,
            hmax,
            progress: None,
            lo,
            cols,
            rows,
            near,
            strips,
            curv: 0.0,
            holes: None,
        }
    }

    /// Treats the cells that touch a hole texel (`holes[row · W + col]`) as no surface (SPEC §2
    /// "Nodata"): a ray passes over them and they occlude nothing, the slope at s → 0 included.
    /// Such a cell is skipped whole by the walk, exactly as a cell that cannot beat the best
    /// value is; the pyramid's block maxima stay upper bounds of what is left. Rays then take
    /// the scalar walk from the start, as with the curvature.
    pub fn with_holes(mut self, holes: Option<&'a [bool]>) -> Self {
        self.holes = holes.filter(|h| h.len() == self.grid.width * self.grid.height);
        if self.holes.is_some() && self.strips {
            // With holes every ray takes the scalar walk (see `rows`): the vectorised near
            // field's padded rows (8 bytes a texel) are let go.
            self.near = self.near.clone_light();
            self.strips = false;
        }
        self
    }

    /// Lowers a point at arc length s by `curv`·s² texels (the earth's curvature, SPEC §3.7:
    /// `curv` = cell_size² · height_scale / (2 R_e)). The drop only lowers the surface, so the
    /// pyramid's and the near field's skips stay conservative. The vectorised near field takes
    /// the drop as a term of its per-cell quadratic (as the sweep's does) and the walk beyond
    /// it the same drop in f64: a DEM's default (`earth_curvature=on`) used to send every ray
    /// down the scalar walk from s = 0, 5.6× the CPU of the flat kernel on a 1024² DEM
    /// (docs/peers.md), level with GRASS `r.horizon`.
    pub fn with_curvature(mut self, curv: f64) -> Self {
        self.curv = if curv.is_finite() && curv > 0.0 { curv } else { 0.0 };
        self.near.curv = self.curv as f32;
        self
    }

    fn ray(&self, x: usize, y: usize, dx: f64, dy: f64) -> Ray {
        let mut ray = Ray::new(&self.grid, x, y, dx, dy, self.radius);
        ray.curv = self.curv;
        ray
    }

    /// The accelerated walk of one ray from arc length `start`, where `seed` is a value of the
    /// ratio the ray already reaches (from the near field; 0 if none): returns tan α and the arc
    /// length where it is reached.
    #[inline]
    fn walk(&self, ray: &Ray, start: f64, seed: f64) -> (f64, f64) {
        let hs = self.grid.heights;
        let (cols, rows, lo) = (&self.cols[..], &self.rows[..], self.lo);
        let holes = self.holes;
        let (w, h) = (self.grid.width as i64, self.grid.height as i64);
        let wrap = self.grid.edge == Edge::Wrap;
        // Texel indices of cell (cx, cy)'s corners [top left, top right, bottom left, bottom
        // right]; `None` for a cell off the map with `edge=none`.
        let cell = |cx: i64, cy: i64| -> Option<[usize; 4]> {
            let inside = (0..(w - 1).max(1)).contains(&cx) && (0..(h - 1).max(1)).contains(&cy);
            if !wrap && !inside {
                return None;
            }
            let (i, j) = ((cx - lo) as usize, (cy - lo) as usize);
            let (c0, c1, r0, r1) = (cols[i], cols[i + 1], rows[j], rows[j + 1]);
            Some([(r0 + c0) as usize, (r0 + c1) as usize, (r1 + c0) as usize, (r1 + c1) as usize])
        };
        let corners = |cx: i64, cy: i64| {
            let (i, j) = ((cx - lo) as usize, (cy - lo) as usize);
            let (c0, c1, r0, r1) = (cols[i], cols[i + 1], rows[j], rows[j + 1]);
            let k =
                [(r0 + c0) as usize, (r0 + c1) as usize, (r1 + c0) as usize, (r1 + c1) as usize];
            if let Some(m) = holes.filter(|m| k.iter().any(|&t| m[t])) {
                // A ray along a grid line walks the cells on one side of it, but the line is
                // the edge of the cells on both: surface if the cell across has no hole. The
                // cell is then given that edge on both sides, so along the ray it is the edge.
                let clear = |c: Option<[usize; 4]>| c.is_some_and(|c| !c.iter().any(|&t| m[t]));
                let edge = if ray.dy == 0.0 && ray.y0 == cy as f64 && clear(cell(cx, cy - 1)) {
                    Some([k[0], k[1], k[0], k[1]])
                } else if ray.dy == 0.0 && ray.y0 == (cy + 1) as f64 && clear(cell(cx, cy + 1)) {
                    Some([k[2], k[3], k[2], k[3]])
                } else if ray.dx == 0.0 && ray.x0 == cx as f64 && clear(cell(cx - 1, cy)) {
                    Some([k[0], k[0], k[2], k[2]])
                } else if ray.dx == 0.0 && ray.x0 == (cx + 1) as f64 && clear(cell(cx + 1, cy)) {
                    Some([k[1], k[1], k[3], k[3]])
                } else {
                    None
                };
                // No surface: below everything, so the walk skips the cell.
                return edge.map_or([f64::NEG_INFINITY; 4], |e| e.map(|t| hs[t] as f64));
            }
            k.map(|t| hs[t] as f64)
        };
        walk(&self.grid, ray, Some((&self.pyramid, self.hmax)), ((seed, 0.0), 0.0), start, corners)
    }

    /// Makes [`HorizonRows::rows`] return early (leaving the rest of its rows unspecified) once
    /// `progress` is canceled, so a cancel lands within one texel rather than one band. The band
    /// driver notices the cancel and discards the result.
    pub fn with_cancel(mut self, progress: &Progress) -> Self {
        self.progress = Some(progress.clone());
        self
    }

    /// Exact sin α of texel (`x`, `y`) at any azimuth `phi` (radians), with this kernel's radius.
    ///
    /// # Panics
    /// If (`x`, `y`) is outside the grid or `phi` is not finite (programming errors).
    pub fn horizon_sin(&self, x: usize, y: usize, phi: f64) -> f64 {
        assert!(x < self.grid.width && y < self.grid.height, "texel outside the grid");
        assert!(phi.is_finite(), "azimuth must be finite");
        let (dx, dy) = direction(phi, self.grid.row_step());
        let ray = self.ray(x, y, dx, dy);
        sin_of_tan(self.walk(&ray, 0.0, 0.0).0)
    }

    /// tan α of texel (`x`, `y`) at bin `n`, at least `seed` (a value the ray is known to reach,
    /// which lets the walk skip what cannot beat it): the scalar walk, holes included. The near
    /// field of `sweep` around holes ([`crate::kernels::sweep::Sweep::with_holes`]).
    pub(crate) fn tan_at(&self, x: usize, y: usize, n: usize, seed: f64) -> f64 {
        let (dx, dy) = self.dirs[n];
        let ray = self.ray(x, y, dx, dy);
        self.walk(&ray, 0.0, seed).0.max(seed)
    }

    /// tan α of texel (`x`, `y`) at bin `n` and the horizontal distance, in texels, to the point
    /// of the ray that sets it (the walk's arg max: SPEC §3.7 `horizon_distance`); (0, 0) when
    /// nothing rises above the horizontal.
    pub fn horizon_and_distance(&self, x: usize, y: usize, n: usize) -> (f64, f64) {
        let (dx, dy) = self.dirs[n];
        self.distance_along(x, y, dx, dy)
    }

    /// [`ExactHorizon::horizon_and_distance`] at any azimuth `phi` (radians).
    pub fn horizon_and_distance_at(&self, x: usize, y: usize, phi: f64) -> (f64, f64) {
        let (dx, dy) = direction(phi, self.grid.row_step());
        self.distance_along(x, y, dx, dy)
    }

    fn distance_along(&self, x: usize, y: usize, dx: f64, dy: f64) -> (f64, f64) {
        assert!(x < self.grid.width && y < self.grid.height, "texel outside the grid");
        let ray = self.ray(x, y, dx, dy);
        let (t, s) = self.walk(&ray, 0.0, 0.0);
        if t > 0.0 {
            (t, s)
        } else {
            (0.0, 0.0)
        }
    }

    /// Per-bin sin α of texel (x, y) into `s` (`bins` long), one scalar walk per azimuth (the
    /// vectorised path is [`HorizonRows::rows`]).
    pub fn texel_bins(&self, x: usize, y: usize, s: &mut [f32]) {
        for (o, &(dx, dy)) in s.iter_mut().zip(&self.dirs) {
            let ray = self.ray(x, y, dx, dy);
            *o = sin_of_tan(self.walk(&ray, 0.0, 0.0).0) as f32;
        }
    }
}

impl HorizonRows for ExactHorizon<'_> {
    fn width(&self) -> usize {
        self.grid.width
    }
    fn height(&self) -> usize {
        self.grid.height
    }
    fn bins(&self) -> usize {
        self.dirs.len()
    }
    fn rows(&self, y0: usize, channels: &mut [f32], mut bins_out: Option<&mut [f32]>) {
        let (w, nb) = (self.grid.width, self.dirs.len());
        let n_rows = channels.len() / (w * 8);
        if self.holes.is_some() {
            // With holes: the scalar exact walk for every ray.
            let mut s = vec![0.0f32; nb];
            for (k, out) in channels.chunks_exact_mut(8).enumerate() {
                if k % w == 0 && self.progress.as_ref().is_some_and(Progress::is_canceled) {
                    return;
                }
                self.texel_bins(k % w, y0 + k / w, &mut s);
                reduce_into(self.reduce, &s, out);
                if let Some(bo) = bins_out.as_deref_mut() {
                    bo[k * nb..(k + 1) * nb].copy_from_slice(&s);
                }
            }
            return;
        }
        assert!(self.strips, "ExactHorizon::walker runs single rays, not rows");
        // Per strip: LANES texels × bins values, texel-major.
        let mut strip = vec![0.0f32; LANES * nb];
        let near = &self.near;
        let r_all = match self.grid.edge {
            Edge::Wrap => self.radius.unwrap_or(w.max(self.grid.height) as f64),
            Edge::None => f64::INFINITY,
        };
        // The near field works relative to `near.reference` (see [`StripMarch`]).
        let reference = near.reference;
        let hmax = (self.hmax - reference) as f32;
        // `reduce=point` reads one bin per channel: unless the per-bin values are asked for
        // (Fourier), the other bins are never looked at, so their rays are not cast (a quarter
        // of the work at 32 bins, an eighth at 64).
        let step = if self.reduce == Reduce::Point && bins_out.is_none() { nb / 8 } else { 1 };
        for r in 0..n_rows {
            let y = y0 + r;
            for x in (0..w).step_by(LANES) {
                // One relaxed load per strip: negligible, and a cancel lands within a strip
                // rather than a band.
                if self.progress.as_ref().is_some_and(Progress::is_canceled) {
                    return;
                }
                let lanes = LANES.min(w - x);
                let mut h0 = [f32::INFINITY; LANES];
                for (i, v) in h0.iter_mut().enumerate().take(lanes) {
                    *v = (f64::from(self.grid.heights[y * w + x + i]) - reference) as f32;
                }
                for (n, &(dx, dy)) in self.dirs.iter().enumerate().step_by(step) {
                    // Each lane's end: shared when wrapping, at its own border otherwise.
                    let mut s_end = [r_all; LANES];
                    let mut count = [near.segs[n].len() as u32; LANES];
                    if self.grid.edge == Edge::None {
                        for i in 0..lanes {
                            s_end[i] = Ray::new(&self.grid, x + i, y, dx, dy, self.radius).s_end;
                            count[i] = near.count(n, s_end[i]);
                        }
                    }
                    let mut best = [0.0f32; LANES];
                    near.strip(n, (dx, dy), x, y, &h0, &count, hmax, &mut best);
                    if s_end.iter().take(lanes).any(|&e| e > near.s_cut) {
                        for i in 0..lanes {
                            let t = best[i].max(0.0) as f64;
                            // The ray goes on past the near field and something there could
                            // still beat it: continue with the scalar walk, seeded.
                            let rise = self.hmax - reference - f64::from(h0[i]);
                            if s_end[i] > near.s_cut && rise > t * near.s_cut {
                                let ray = self.ray(x + i, y, dx, dy);
                                best[i] = self.walk(&ray, near.s_cut, t).0 as f32;
                            }
                        }
                    }
                    for i in 0..LANES {
                        // In f64: t² overflows f32 past 1.8e19 (cliffs of 1e30 texels), and
                        // t / √(1 + t²) would become t / ∞ = 0 instead of 1.
                        let t = best[i].max(0.0) as f64;
                        strip[i * nb + n] = (t / (1.0 + t * t).sqrt()) as f32;
                    }
                }
                for i in 0..lanes {
                    let k = r * w + x + i;
                    let s = &strip[i * nb..(i + 1) * nb];
                    reduce_into(self.reduce, s, &mut channels[k * 8..k * 8 + 8]);
                    if let Some(bo) = bins_out.as_deref_mut() {
                        bo[k * nb..(k + 1) * nb].copy_from_slice(s);
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn direction_snaps_axes() {
        assert_eq!(direction(PI, -1), (-1.0, 0.0));
        assert_eq!(direction(PI / 2.0, -1), (0.0, -1.0));
        assert_eq!(direction(PI / 2.0, 1), (0.0, 1.0));
    }
}
