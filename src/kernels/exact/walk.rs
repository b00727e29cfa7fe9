//! The scalar exact walk of SPEC §3.2: one ray, cell by cell, each cell's maximum of
//! (h − h0)/s solved in closed form ([`cell_max`]), with a max pyramid of the surface
//! ([`Pyramid`]) that skips blocks of cells which cannot beat the best value so far and stops a
//! ray once the map's highest point cannot. `exact` runs it beyond its vectorised near field,
//! and [`super::ExactMarch`] (the oracle) runs it without the pyramid.

use super::{direction, sin_of_tan};
use crate::kernels::Grid;
use crate::params::Edge;

/// The ray from texel (x0, y0) along image direction (dx, dy) and the arc length where it ends.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Ray {
    pub(super) x0: f64,
    pub(super) y0: f64,
    pub(super) dx: f64,
    pub(super) dy: f64,
    pub(super) h0: f64,
    pub(crate) s_end: f64,
    /// Earth-curvature drop per texel² (texels): a point at arc length s is lowered by
    /// `curv`·s² (0: flat earth).
    pub(super) curv: f64,
}

impl Ray {
    /// The ray of texel (x, y) along (dx, dy), ending at `radius` (`None`: unlimited) or where it
    /// leaves the surface (`edge=none`).
    pub(crate) fn new(
        grid: &Grid<'_>,
        x: usize,
        y: usize,
        dx: f64,
        dy: f64,
        radius: Option<f64>,
    ) -> Ray {
        let (w, h) = (grid.width, grid.height);
        let h0 = grid.heights[y * w + x] as f64;
        let (x0, y0) = (x as f64, y as f64);
        let s_end = match grid.edge {
            Edge::Wrap => radius.unwrap_or(w.max(h) as f64),
            Edge::None => {
                let to_edge = |p: f64, d: f64, last: f64| {
                    if d > 0.0 {
                        (last - p) / d
                    } else if d < 0.0 {
                        p / -d
                    } else {
                        f64::INFINITY
                    }
                };
                let e = to_edge(x0, dx, (w - 1) as f64).min(to_edge(y0, dy, (h - 1) as f64));
                radius.map_or(e, |r| r.min(e))
            }
        };
        Ray { x0, y0, dx, dy, h0, s_end, curv: 0.0 }
    }

    /// The first cell: texel (x0, y0) is one of its corners, chosen so the ray enters it.
    /// A ray along a cell edge (d = 0) may use either side; with `edge=none` the one inside.
    pub(super) fn first_cell(&self, grid: &Grid<'_>) -> (i64, i64) {
        let pick = |p: f64, d: f64, n: usize| {
            let c = p as i64;
            if d < 0.0 || (d == 0.0 && grid.edge == Edge::None && c == n as i64 - 1 && n > 1) {
                c - 1
            } else {
                c
            }
        };
        (pick(self.x0, self.dx, grid.width), pick(self.y0, self.dy, grid.height))
    }
}

/// Heights of the four corners of cell (cx, cy) (unwrapped image coordinates), as
/// [h(cx, cy), h(cx+1, cy), h(cx, cy+1), h(cx+1, cy+1)]: wrapped, or clamped to the map with
/// `edge=none` (rays never leave the map there, so clamping only meets degenerate cells of a
/// 1-texel-wide map, where the clamped side has weight 0).
#[inline]
pub(super) fn corners(grid: &Grid<'_>, cx: i64, cy: i64) -> [f64; 4] {
    let (w, h) = (grid.width as i64, grid.height as i64);
    let (c0, c1, r0, r1) = match grid.edge {
        Edge::Wrap => {
            // Most cells are already inside the map: the division of `rem_euclid` was a large
            // part of re-reading a short stretch of a ray (the sweep kernel's refine).
            let wrap = |v: i64, n: i64| if (0..n).contains(&v) { v } else { v.rem_euclid(n) };
            let c0 = wrap(cx, w);
            let r0 = wrap(cy, h);
            (c0, if c0 + 1 == w { 0 } else { c0 + 1 }, r0, if r0 + 1 == h { 0 } else { r0 + 1 })
        }
        Edge::None => {
            let c0 = cx.clamp(0, w - 1);
            let r0 = cy.clamp(0, h - 1);
            (c0, (cx + 1).clamp(0, w - 1), r0, (cy + 1).clamp(0, h - 1))
        }
    };
    let at = |c: i64, r: i64| grid.heights[(r * w + c) as usize] as f64;
    [at(c0, r0), at(c1, r0), at(c0, r1), at(c1, r1)]
}

/// The exact maximum of (h(s) − h0)/s over the part s ∈ [s_a, s_a + len] of a ray inside one
/// cell, given the corner heights `k` and the ray's local position (fx, fy) ∈ [0,1]² at s_a.
/// `first`: s_a = 0 and the ray starts at a corner of this cell, at height h0; the supremum then
/// includes the limit s → 0⁺, the directional slope. `entry`: the entry point s_a counts too
/// (the ray comes out of a skipped nodata cell, whose exit was not analysed).
#[inline]
pub(super) fn cell_max(
    k: [f64; 4],
    fx: f64,
    fy: f64,
    ray: &Ray,
    s_a: f64,
    len: f64,
    (first, entry): (bool, bool),
) -> (f64, f64) {
    let (dx, dy) = (ray.dx, ray.dy);
    let bx = k[1] - k[0];
    let by = k[2] - k[0];
    let bxy = k[3] - k[1] - k[2] + k[0];
    // h(t) = d0 + d1 t + d2 t² along the segment.
    let d0 = k[0] + bx * fx + by * fy + bxy * fx * fy;
    // The curvature drop c·(s_a + t)² keeps h a quadratic in t (SPEC §3.7): it moves the
    // coefficients, so the closed form below stays exact.
    let c = ray.curv;
    let d1 = bx * dx + by * dy + bxy * (fx * dy + fy * dx) - 2.0 * c * s_a;
    let d2 = bxy * dx * dy - c;
    let a = if first { 0.0 } else { d0 - ray.h0 - c * s_a * s_a };
    let s_b = s_a + len;
    let mut best =
        if s_b > 0.0 { ((a + (d1 + d2 * len) * len) / s_b, s_b) } else { (f64::NEG_INFINITY, 0.0) };
    if first && d1 > best.0 {
        best = (d1, 0.0);
    }
    // The entry point is the previous cell's exit and was analysed there, unless that cell was
    // skipped: a cell that cannot beat the best value (its exit cannot either), or a cell
    // touching a nodata hole, which is no surface while this cell's edge is. `entry` says the
    // ray comes from such a hole cell.
    if entry && s_a > 0.0 && a / s_a > best.0 {
        best = (a / s_a, s_a);
    }
    if d2 != 0.0 {
        // Interior critical point: (s_a + t)² = s_a² − (d1·s_a − a)/d2.
        let q = s_a * s_a - (d1 * s_a - a) / d2;
        if q > 0.0 {
            let d = q.sqrt();
            let t = d - s_a;
            if t > 0.0 && t < len {
                let v = (a + (d1 + d2 * t) * t) / d;
                if v > best.0 {
                    best = (v, d);
                }
            }
        }
    }
    best
}

/// Per-level block maxima of the surface in unwrapped cell coordinates (see module docs).
#[derive(Debug, Clone)]
pub(super) struct Pyramid {
    /// Level k ≥ 1 covers blocks of 4^k × 4^k cells; `levels[k - 1]`.
    pub(super) levels: Vec<Level>,
}

#[derive(Debug, Clone)]
pub(super) struct Level {
    /// Block index of the first stored block in x and y.
    pub(super) bx0: i64,
    pub(super) by0: i64,
    pub(super) nx: usize,
    pub(super) ny: usize,
    pub(super) max: Vec<f32>,
}

impl Level {
    #[inline]
    pub(super) fn at(&self, bx: i64, by: i64) -> f32 {
        let i = (bx - self.bx0).clamp(0, self.nx as i64 - 1) as usize;
        let j = (by - self.by0).clamp(0, self.ny as i64 - 1) as usize;
        self.max[j * self.nx + i]
    }
}

impl Pyramid {
    /// Block maxima for every cell a ray of length ≤ `reach` from a texel of `grid` can enter.
    pub(super) fn new(grid: &Grid<'_>, reach: f64) -> Pyramid {
        let (w, h) = (grid.width as i64, grid.height as i64);
        let reach = reach.min(1e7).ceil() as i64 + 2;
        let (lo_x, hi_x, lo_y, hi_y) = match grid.edge {
            Edge::Wrap => (-reach, w + reach, -reach, h + reach),
            Edge::None => (0, w - 1, 0, h - 1),
        };
        // Cell maxima over the wrapped (or clamped) cells, one per texel position.
        let mut cell = vec![0f32; (w * h) as usize];
        for r in 0..h {
            for c in 0..w {
                let k = corners(grid, c, r);
                cell[(r * w + c) as usize] = k[0].max(k[1]).max(k[2]).max(k[3]) as f32;
            }
        }
        let cell_at = |c: i64, r: i64| -> f32 {
            let (c, r) = match grid.edge {
                Edge::Wrap => (c.rem_euclid(w), r.rem_euclid(h)),
                Edge::None => (c.clamp(0, w - 1), r.clamp(0, h - 1)),
            };
            cell[(r * w + c) as usize]
        };
        let mut levels: Vec<Level> = Vec::new();
        let span = (hi_x - lo_x).max(hi_y - lo_y).max(1);
        let mut k = 1u32;
        while 4i64.pow(k - 1) < span && k <= 15 {
            let shift = 2 * k;
            let (bx0, by0) = (lo_x >> shift, lo_y >> shift);
            let (nx, ny) =
                (((hi_x >> shift) - bx0 + 1) as usize, ((hi_y >> shift) - by0 + 1) as usize);
            let mut max = vec![f32::NEG_INFINITY; nx * ny];
            for j in 0..ny {
                for i in 0..nx {
                    let (bx, by) = (bx0 + i as i64, by0 + j as i64);
                    let mut m = f32::NEG_INFINITY;
                    for cj in 0..4 {
                        for ci in 0..4 {
                            let (x, y) = (bx * 4 + ci, by * 4 + cj);
                            m = m.max(match levels.last() {
                                None => cell_at(x, y),
                                Some(prev) => prev.at(x, y),
                            });
                        }
                    }
                    max[j * nx + i] = m;
                }
            }
            levels.push(Level { bx0, by0, nx, ny, max });
            k += 1;
        }
        Pyramid { levels }
    }
}

/// Walks `ray` cell by cell and returns max(floor, sup (h − h0)/s): `floor` 0 for a horizon
/// (α ≥ 0), −∞ for the signed maximum of openness (then without `accel`, whose early exit
/// assumes nothing below the horizontal matters). With `accel`, blocks that cannot beat the
/// best value so far are skipped whole (identical result, see module docs).
///
/// `seed` = (t, s): a value t of the ratio already achieved at arc length s on this very ray
/// (or (0, 0)); it only lets more blocks be skipped. Returns the best ratio and where it is.
pub(super) fn walk<F>(
    grid: &Grid<'_>,
    ray: &Ray,
    accel: Option<(&Pyramid, f64)>,
    (seed, floor): ((f64, f64), f64),
    start: f64,
    corners: F,
) -> (f64, f64)
where
    F: Fn(i64, i64) -> [f64; 4],
{
    let mut best = seed.0.max(floor);
    let mut best_s = if seed.0 > floor { seed.1 } else { 0.0 };
    if ray.s_end <= 0.0 {
        return (floor, 0.0);
    }
    if let Some((_, hmax)) = accel {
        // Nothing on the map rises above the texel (with a floor of 0 or more: a signed
        // walk, floor −∞, still wants its highest point below).
        if floor >= 0.0 && hmax <= ray.h0 {
            return (floor, 0.0);
        }
    }
    // Mid-ray starts take the cell just ahead of the start point.
    let ahead = |p: f64, d: f64| (p + start * d + 1e-7 * d).floor() as i64;
    let (mut cx, mut cy) = if start > 0.0 {
        (ahead(ray.x0, ray.dx), ahead(ray.y0, ray.dy))
    } else {
        ray.first_cell(grid)
    };
    let mut s = start;
    let mut level = 0usize;
    let mut after_hole = false;
    let max_level = accel.map_or(0, |(p, _)| p.levels.len());
    loop {
        if let Some((_, hmax)) = accel {
            if best >= 0.0 && s > 0.0 && hmax - ray.h0 <= best * s {
                break;
            }
        }
        let shift = 2 * level as u32;
        let (bx, by) = (cx >> shift, cy >> shift);
        let k = if level == 0 { Some(corners(cx, cy)) } else { None };
        // A nodata cell (corners at −∞, see `ExactHorizon::with_holes`) is skipped, and the
        // next analysed cell's entry point has to be looked at. (Analysed, as the plain walk
        // once did, it cleared that flag: the entry of the surface beyond a hole was lost.)
        let hole_cell = k.is_some_and(|k| k[0] == f64::NEG_INFINITY);
        if hole_cell {
            after_hole = true;
        }
        // Where the ray leaves the current block (cell at level 0).
        let size = 1i64 << shift;
        let bound_x = if ray.dx > 0.0 { (bx + 1) * size } else { bx * size };
        let bound_y = if ray.dy > 0.0 { (by + 1) * size } else { by * size };
        let tx = if ray.dx != 0.0 { (bound_x as f64 - ray.x0) / ray.dx } else { f64::INFINITY };
        let ty = if ray.dy != 0.0 { (bound_y as f64 - ray.y0) / ray.dy } else { f64::INFINITY };
        let s_exit = tx.min(ty).max(s);
        let skip = hole_cell
            || match accel {
                None => false,
                Some((p, _)) => {
                    let m = match k {
                        Some(k) => k[0].max(k[1]).max(k[2]).max(k[3]),
                        None => p.levels[level - 1].at(bx, by) as f64,
                    };
                    // The block's values are at most (m − h0)/s' over its stretch [s, s_exit]
                    // of the ray: for a best ≥ 0 the bound is tightest at s; below 0 (a signed
                    // walk), at the far end.
                    let s_far = if best < 0.0 { s_exit.min(ray.s_end) } else { s };
                    m - ray.h0 <= best * s_far
                }
            };
        if !skip && level > 0 {
            level -= 1;
            continue;
        }
        if !skip {
            // level == 0: exact analysis of this cell on [s, min(s_exit, s_end)].
            let k = k.unwrap_or([0.0; 4]);
            let fx = (ray.x0 + s * ray.dx - cx as f64).clamp(0.0, 1.0);
            let fy = (ray.y0 + s * ray.dy - cy as f64).clamp(0.0, 1.0);
            let len = s_exit.min(ray.s_end) - s;
            let (v, at) = cell_max(k, fx, fy, ray, s, len, (s == 0.0, after_hole));
            after_hole = false;
            if v > best {
                (best, best_s) = (v, at);
            }
        }
        if s_exit >= ray.s_end {
            break;
        }
        // Step into the next cell: across the exited boundary on the axis (or both) that left
        // the block; the other coordinate from the exit point, kept inside the block's range.
        let inside = |p: f64, b: i64| (p.floor() as i64).clamp(b * size, (b + 1) * size - 1);
        let (ncx, ncy) = (
            if tx <= ty {
                if ray.dx > 0.0 {
                    bound_x
                } else {
                    bound_x - 1
                }
            } else {
                inside(ray.x0 + s_exit * ray.dx, bx)
            },
            if ty <= tx {
                if ray.dy > 0.0 {
                    bound_y
                } else {
                    bound_y - 1
                }
            } else {
                inside(ray.y0 + s_exit * ray.dy, by)
            },
        );
        cx = ncx;
        cy = ncy;
        s = s_exit;
        if skip && level < max_level {
            level += 1;
        }
    }
    (best, best_s)
}

/// Exact sin α of texel (`x`, `y`) at tangent-space azimuth `phi` (radians, any value), by the
/// plain cell-by-cell walk: the single-texel ground truth for shading and evaluation.
///
/// `radius`: `Some(R)` limits occluders to 0 < s ≤ R texels; `None` is `unlimited` (to the map
/// edge with `edge=none`, max(W, H) texels with `edge=wrap`). Cost O(R) per call; for many calls
/// on one grid, [`ExactHorizon::horizon_sin`] skips empty space and is much faster.
///
/// A radius beyond max(`MAX_RADIUS`, W, H) is clamped to it (`params` never passes more).
///
/// # Panics
/// If (`x`, `y`) is outside the grid or `phi` is not finite (programming errors).
pub fn horizon_sin(grid: &Grid<'_>, x: usize, y: usize, phi: f64, radius: Option<f64>) -> f64 {
    assert!(x < grid.width && y < grid.height, "texel outside the grid");
    assert!(phi.is_finite(), "azimuth must be finite");
    let cap = f64::from(crate::params::MAX_RADIUS).max(grid.width.max(grid.height) as f64);
    let radius = radius.map(|r| r.clamp(0.0, cap));
    let (dx, dy) = direction(phi, grid.row_step());
    let ray = Ray::new(grid, x, y, dx, dy, radius);
    sin_of_tan(walk(grid, &ray, None, ((0.0, 0.0), 0.0), 0.0, |cx, cy| corners(grid, cx, cy)).0)
}

/// The signed maximum elevation angle (radians, no clamp at 0) of texel (`x`, `y`) along
/// tangent-space azimuth `phi` within `radius` texels (SPEC §3.7 openness's β), by the plain
/// cell walk over the bilinear surface; a cell with a corner in `holes` is no surface. None when
/// the ray meets no surface (no length at an `edge=none` border looking out, or holes only).
pub fn signed_elevation(
    grid: &Grid<'_>,
    holes: Option<&[bool]>,
    x: usize,
    y: usize,
    phi: f64,
    radius: f64,
) -> Option<f64> {
    let (dx, dy) = direction(phi, grid.row_step());
    let ray = Ray::new(grid, x, y, dx, dy, Some(radius));
    if ray.s_end <= 0.0 {
        return None;
    }
    let corners = hole_corners(grid, holes);
    let (t, _) =
        walk(grid, &ray, None, ((f64::NEG_INFINITY, 0.0), f64::NEG_INFINITY), 0.0, corners);
    t.is_finite().then(|| t.atan())
}

/// The corners of cell (cx, cy) as [`walk`] takes them, all −∞ for a cell with a corner in
/// `holes` (wrapped, or clamped at an `edge=none` border, as the corners are found).
fn hole_corners<'g>(
    grid: &'g Grid<'_>,
    holes: Option<&'g [bool]>,
) -> impl Fn(i64, i64) -> [f64; 4] + 'g {
    let (w, h) = (grid.width as i64, grid.height as i64);
    let hole = move |c: i64, r: i64| {
        let (c, r) = match grid.edge {
            Edge::Wrap => (c.rem_euclid(w), r.rem_euclid(h)),
            Edge::None => (c.clamp(0, w - 1), r.clamp(0, h - 1)),
        };
        holes.is_some_and(|m| m[(r * w + c) as usize])
    };
    move |cx: i64, cy: i64| {
        if [(0, 0), (1, 0), (0, 1), (1, 1)].iter().any(|&(i, j)| hole(cx + i, cy + j)) {
            [f64::NEG_INFINITY; 4]
        } else {
            corners(grid, cx, cy)
        }
    }
}

/// [`signed_elevation`] for the texels of one grid, the same values sooner: a max pyramid of
/// the grid lets each ray skip the blocks that cannot beat its best so far, and stop once
/// nothing left can, as `exact`'s rays do. With a best below 0 (a signed maximum below the
/// horizontal), a block below the texel has a ratio (m − h0)/s that rises along the ray, so
/// the walk bounds it at the block's far end rather than its near one. The pyramid bounds the
/// grid's heights, holes included: fill them low (the bake's fill, far below the map) or it
/// skips nothing near them.
#[derive(Debug)]
pub struct SignedElevations<'a> {
    grid: Grid<'a>,
    holes: Option<&'a [bool]>,
    radius: f64,
    pyramid: Pyramid,
    hmax: f64,
}

impl<'a> SignedElevations<'a> {
    /// The walks of `grid` within `radius` texels, `holes` no surface.
    pub fn new(grid: Grid<'a>, holes: Option<&'a [bool]>, radius: f64) -> Self {
        let pyramid = Pyramid::new(&grid, radius);
        let hmax = f64::from(grid.range().1);
        SignedElevations { grid, holes, radius, pyramid, hmax }
    }

    /// [`signed_elevation`] of texel (`x`, `y`) along azimuth `phi`, bit for bit.
    pub fn at(&self, x: usize, y: usize, phi: f64) -> Option<f64> {
        let g = &self.grid;
        let (dx, dy) = direction(phi, g.row_step());
        let ray = Ray::new(g, x, y, dx, dy, Some(self.radius));
        if ray.s_end <= 0.0 {
            return None;
        }
        let corners = hole_corners(g, self.holes);
        let accel = Some((&self.pyramid, self.hmax));
        let none = ((f64::NEG_INFINITY, 0.0), f64::NEG_INFINITY);
        let (t, _) = walk(g, &ray, accel, none, 0.0, corners);
        t.is_finite().then(|| t.atan())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::params::YAxis;

    /// The accelerated walks of [`SignedElevations`] give [`signed_elevation`]'s values bit for
    /// bit: on rough, spiky and smooth maps with and without holes (filled far below as the
    /// bake fills them), both edges, many azimuths and radii, positive and negative maxima.
    #[test]
    fn signed_elevations_are_the_plain_walk_s() {
        let mut seed = 99u64;
        let mut rnd = move || {
            seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            (seed >> 40) as f32 / (1u64 << 24) as f32
        };
        let (w, h) = (37usize, 29usize);
        let (mut compared, mut negative) = (0usize, 0usize);
        for kind in 0..3 {
            let mut heights: Vec<f32> = (0..w * h)
                .map(|k| match kind {
                    0 => rnd() * 6.0,
                    1 => {
                        if rnd() < 0.05 {
                            20.0
                        } else {
                            rnd()
                        }
                    }
                    _ => ((k % w) as f32 * 0.3).sin() * 4.0 + (k / w) as f32 * 0.2,
                })
                .collect();
            let holes: Vec<bool> = (0..w * h)
                .map(|k| {
                    ((k % w) as i64 - 20).pow(2) + ((k / w) as i64 - 9).pow(2) < 12 || rnd() < 0.02
                })
                .collect();
            let (lo, hi) = (0.0f32, 25.0f32);
            for (v, &o) in heights.iter_mut().zip(&holes) {
                if o {
                    *v = crate::heightmap::hole_fill(lo, hi);
                }
            }
            for mask in [None, Some(&holes[..])] {
                for edge in [Edge::Wrap, Edge::None] {
                    let g = Grid::new(w, h, &heights, edge, YAxis::Up);
                    for radius in [3.0, 11.5, 40.0] {
                        let fast = SignedElevations::new(g, mask, radius);
                        for y in 0..h {
                            for x in 0..w {
                                for n in 0..24 {
                                    let phi = n as f64 * std::f64::consts::TAU / 24.0 + 0.01;
                                    let want = signed_elevation(&g, mask, x, y, phi, radius);
                                    let got = fast.at(x, y, phi);
                                    assert_eq!(
                                        got.map(f64::to_bits),
                                        want.map(f64::to_bits),
                                        "kind {kind} {edge:?} R {radius} ({x}, {y}) phi {phi}"
                                    );
                                    compared += 1;
                                    negative += usize::from(want.is_some_and(|b| b < 0.0));
                                }
                            }
                        }
                    }
                }
            }
        }
        assert!(compared > 100_000 && negative > 10_000, "{compared} compared, {negative} < 0");
    }

    #[test]
    fn cell_max_finds_interior_peak() {
        // Ray along x through a cell whose bilinear surface along the diagonal bulges.
        let h = [0.0f32, 0.0, 0.0, 0.0];
        let g = Grid::new(2, 2, &h, Edge::None, YAxis::Down);
        let ray = Ray::new(&g, 0, 0, 1.0, 0.0, None);
        // A ridge h(t) = −1 + 4t − 4t² (peak 0 at t = ½) seen from s_a = 1: the ratio
        // (h − 0)/(1 + t) peaks where t² + 2t − 5/4 = 0… check against a fine scan.
        let k = [-1.0, -1.0, 3.0, -5.0];
        let (fx, fy) = (0.0, 0.0);
        let r =
            Ray { dx: std::f64::consts::FRAC_1_SQRT_2, dy: std::f64::consts::FRAC_1_SQRT_2, ..ray };
        let len = std::f64::consts::SQRT_2;
        let got = cell_max(k, fx, fy, &r, 1.0, len, (false, false)).0;
        let mut want = f64::NEG_INFINITY;
        for i in 0..=100_000 {
            let t = len * i as f64 / 100_000.0;
            let (u, v) = (t * r.dx, t * r.dy);
            let hh = k[0] * (1.0 - u) * (1.0 - v)
                + k[1] * u * (1.0 - v)
                + k[2] * (1.0 - u) * v
                + k[3] * u * v;
            want = want.max(hh / (1.0 + t));
        }
        assert!((got - want).abs() < 1e-9 && got >= want - 1e-12, "{got} vs {want}");
    }
}
