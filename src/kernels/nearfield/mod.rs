//! The exact near field on its own, shared by `exact` and `sweep`.
//!
//! [`StripMarch`] marches [`LANES`] texels of a row along one azimuth through the pieces of their
//! rays (between grid-line crossings), each piece's maximum of (h − h0)/s in closed form; `exact`
//! runs it for the first 1024 texels of every ray. [`NearField`] adds what `sweep` needs to join
//! it to a far field: a floor from the far field that culls pieces, the earth-curvature drop as
//! a term of the closed form, and a crossing walk (each piece's exit as the lerp of two texels,
//! the piece solved whole only where its cell's twist can lift it above the best value).

mod strip;

pub(crate) use strip::{StripMarch, LANES};

use crate::kernels::exact::walk::Ray;
use crate::kernels::isa::Isa;
use crate::kernels::Grid;
use crate::params::Edge;
use std::sync::Arc;
use strip::{fmax, fmin, piece, Seg};

/// Texels per strip of [`NearField::strip`].
pub(crate) const NEAR_LANES: usize = LANES;

/// The vectorised exact near field on its own, for kernels that join it to another far field
/// (`method=sweep`): tan α of §3.2 over 0 < s ≤ `cuts[n]` on each texel's own ray, with the
/// curvature drop as a term of the per-cell quadratic, exact up to f32 rounding.
#[derive(Debug, Clone)]
pub(crate) struct NearField<'a> {
    grid: Grid<'a>,
    near: StripMarch,
    /// Shared (`Arc`) with the near field's row windows ([`NearField::window`]), as are
    /// `xings`, `hole_segs` and `hole_xings`.
    dirs: Arc<Vec<(f64, f64)>>,
    cuts: Arc<Vec<f64>>,
    /// Highest height of the map relative to `near.reference`.
    hmax: f32,
    /// Per direction and piece, its exit crossing ([`Xing`]), for the crossing walk.
    xings: Arc<Vec<Vec<Xing>>>,
    /// Per padded texel (r, c), the twist k3 − k1 − k2 + k0 of the cell it is the top left of:
    /// the bilinear surface's only second-order term, so a piece (less the curvature drop)
    /// bulges above its chord only where twist·dx·dy is below the drop's c.
    twist: Vec<f32>,
    /// With nodata holes ([`NearField::with_holes`]), per padded texel (r, c), 0 when the cell
    /// it is the top left of is surface and −∞ when a corner of it is a hole: added to what the
    /// crossing walk reads of that cell, it drops the cell as `exact`'s walk skips it. Empty
    /// without holes.
    hole_cells: Vec<f32>,
    /// The holes' flags (one per texel of the grid), kept to make a window's `hole_cells`.
    holes: Option<&'a [bool]>,
    /// With holes, every direction's pieces and crossings out to the longest cut (rounded
    /// up), the reach of `exact`'s walk that `sweep` took near holes before the crossing walk
    /// honoured them: near a hole the far field's lines, a third of a texel beside the ray,
    /// see a hole's edge where the ray does not, so there the exact part runs that far.
    hole_segs: Arc<Vec<Vec<Seg>>>,
    hole_xings: Arc<Vec<Vec<Xing>>>,
}

/// Where a piece of a direction leaves its cell, as [`NearField`]'s crossing walk reads it:
/// on a grid line, the bilinear surface there is the lerp of two texels of that line, so the
/// piece's end value is two loads and a lerp per lane rather than the cell's four corners.
#[derive(Debug, Clone, Copy)]
struct Xing {
    /// Padded offset (relative to the strip's first texel) of the first of the two texels, of
    /// the second from it (1 along a row, `pw` down a column), and the lerp weight.
    at: i32,
    step: i32,
    f: f32,
    /// The piece's cell (cyo·pw + cxo), as [`StripMarch::culls`] has it.
    cell: i32,
    inv_sb: f32,
    /// The curvature drop at the exit, curv·s_b².
    drop: f32,
    /// The bound on the bulge above the chord: where t = twist·`bulge` + `lift` > 0
    /// (`bulge` = −dx·dy·len²/(4·s_a), `lift` = curv·len²/(4·s_a)), tan α inside the piece is
    /// at most the larger end's plus t; `margin` covers the rounding of the ends.
    bulge: f32,
    lift: f32,
    margin: f32,
    /// 1/q, s_a, s_b, len, 1/len and s_b² − s_a²: for the test of the stationary point.
    qi: f32,
    s_a: f32,
    s_b: f32,
    len: f32,
    len_inv: f32,
    l2: f32,
    /// False when the piece ends between grid lines (at a cut short of the next one): then it
    /// is the direction's last and is solved whole.
    on_grid: bool,
}

impl Xing {
    /// The exit crossings of `segs` (a direction's pieces along (dx, dy)) in a padded layout
    /// `pw` wide, with curvature drop `curv` per texel².
    fn of(segs: &[Seg], (dx, dy): (f64, f64), pw: usize, curv: f32, range: f64) -> Vec<Xing> {
        let pw = pw as i64;
        segs.iter()
            .map(|g| {
                let s_b = g.s_a + g.len;
                let q = g.len * g.len / (4.0 * g.s_a);
                // The exit in the cell's own coordinates: one of them is 0 or 1 on a grid line.
                let (ex, ey) = (s_b * dx - f64::from(g.cxo), s_b * dy - f64::from(g.cyo));
                let off = |e: f64| e.abs().min((e - 1.0).abs());
                let (cx, cy) = (i64::from(g.cxo), i64::from(g.cyo));
                let (at, step, f) = if off(ex) <= off(ey) {
                    ((cx + ex.round() as i64) + cy * pw, pw, ey.clamp(0.0, 1.0))
                } else {
                    (cx + (cy + ey.round() as i64) * pw, 1, ex.clamp(0.0, 1.0))
                };
                Xing {
                    at: at as i32,
                    step: step as i32,
                    f: f as f32,
                    cell: (cy * pw + cx) as i32,
                    inv_sb: (1.0 / s_b) as f32,
                    drop: (f64::from(curv) * s_b * s_b) as f32,
                    bulge: (-dx * dy * q) as f32,
                    lift: (f64::from(curv) * q) as f32,
                    margin: (1e-6 * (1.0 + range) / g.s_a) as f32,
                    qi: (1.0 / q) as f32,
                    s_a: g.s_a as f32,
                    s_b: s_b as f32,
                    len: g.len as f32,
                    len_inv: (1.0 / g.len) as f32,
                    l2: (s_b * s_b - g.s_a * g.s_a) as f32,
                    on_grid: off(ex).min(off(ey)) < 1e-9,
                }
            })
            .collect()
    }
}

impl<'a> NearField<'a> {
    /// The near field of `grid` along image directions `dirs`, each to its own cut (texels of
    /// arc length), with curvature drop `curv` per texel², run with `isa`'s instructions.
    pub(crate) fn new(
        grid: Grid<'a>,
        dirs: &[(f64, f64)],
        cuts: &[f64],
        curv: f64,
        isa: Isa,
    ) -> Self {
        Self::about(grid, dirs, cuts, curv, isa, grid.range(), true)
    }

    /// [`NearField::new`] with no rows: its strips run only on the windows it makes
    /// ([`NearField::refill`]), so a caller that joins band by band holds a band's padded rows,
    /// twists and cell maxima rather than the whole map's (12 bytes a texel).
    pub(crate) fn without_rows(
        grid: Grid<'a>,
        dirs: &[(f64, f64)],
        cuts: &[f64],
        curv: f64,
        isa: Isa,
    ) -> Self {
        Self::about(grid, dirs, cuts, curv, isa, grid.range(), false)
    }

    /// [`NearField::new`] for a surface whose heights span `lo..=hi` (the grid's own range, or
    /// with holes the range of the texels that are not), with every row's tables or none.
    fn about(
        grid: Grid<'a>,
        dirs: &[(f64, f64)],
        cuts: &[f64],
        curv: f64,
        isa: Isa,
        (lo, hi): (f32, f32),
        rows: bool,
    ) -> Self {
        let mut near = StripMarch::without_rows(&grid, dirs, cuts, (lo, hi));
        near.curv = if curv.is_finite() && curv > 0.0 { curv as f32 } else { 0.0 };
        near.isa = near.isa.min(isa);
        let hmax = (f64::from(hi) - near.reference) as f32;
        let range = f64::from(hi - lo);
        let xings =
            dirs.iter().zip(&*near.segs).map(|(&d, g)| Xing::of(g, d, near.pw, near.curv, range));
        let xings = Arc::new(xings.collect());
        let (dirs, cuts) = (Arc::new(dirs.to_vec()), Arc::new(cuts.to_vec()));
        let (hole_segs, hole_xings) = (Arc::default(), Arc::default());
        let mut field = NearField {
            grid,
            near,
            dirs,
            cuts,
            hmax,
            xings,
            twist: Vec::new(),
            hole_cells: Vec::new(),
            holes: None,
            hole_segs,
            hole_xings,
        };
        if rows {
            field.near.fill_rows(&grid, 0, field.near.padded_rows(&grid));
            field.fill_twist();
        }
        field
    }

    /// The twists of the padded rows the march holds.
    fn fill_twist(&mut self) {
        let (pw, p) = (self.near.pw, &self.near.padded);
        let mut twist = std::mem::take(&mut self.twist);
        twist.clear();
        twist.resize(p.len(), 0.0);
        for r in 0..(p.len() / pw).saturating_sub(1) {
            let (a, b) = (&p[r * pw..][..pw], &p[(r + 1) * pw..][..pw]);
            for (c, t) in twist[r * pw..][..pw - 1].iter_mut().enumerate() {
                *t = b[c + 1] - a[c + 1] - b[c] + a[c];
            }
        }
        self.twist = twist;
    }

    /// A window ([`NearField::window`]) filled with rows `y0..y1` ([`NearField::refill`]).
    #[cfg(test)]
    pub(crate) fn rows(&self, y0: usize, y1: usize) -> NearField<'a> {
        let mut field = self.window();
        field.refill(y0, y1);
        field
    }

    /// A near field without rows that shares this one's pieces, for [`NearField::refill`].
    pub(crate) fn window(&self) -> NearField<'a> {
        NearField {
            grid: self.grid,
            near: self.near.clone_light(),
            dirs: Arc::clone(&self.dirs),
            cuts: Arc::clone(&self.cuts),
            hmax: self.hmax,
            xings: Arc::clone(&self.xings),
            twist: Vec::new(),
            hole_cells: Vec::new(),
            holes: self.holes,
            hole_segs: Arc::clone(&self.hole_segs),
            hole_xings: Arc::clone(&self.hole_xings),
        }
    }

    /// Makes this the near field of texel rows `y0..y1` alone, with the tables of the padded
    /// rows their rays read: its strips there give the bits of the whole map's near field (the
    /// same heights, pieces and crossings; see [`StripMarch::fill_window`]). The tables'
    /// allocations are kept: a thread that runs window after window (one per azimuth and
    /// group of bands) faults no new pages.
    pub(crate) fn refill(&mut self, y0: usize, y1: usize) {
        self.near.fill_window(&self.grid, y0, y1);
        self.fill_twist();
        if let Some(holes) = self.holes {
            self.fill_hole_rows(holes);
        }
    }

    /// Nodata holes (SPEC §2), one flag per texel (`holes[row · W + col]`): the cells that
    /// touch a hole are no surface, as in `exact` (`ExactHorizon::with_holes`). The crossing
    /// walk then honours them itself: a cell with a hole corner is never solved whole, and a
    /// crossing counts only where a cell on either side of it is surface (the grid line
    /// between two such cells is their edge; the bake's fill of the holes, far below the map,
    /// otherwise lifts nothing). [`NearField::strip_near_holes`] runs that walk;
    /// [`NearField::strip_from`] stays the walk without holes.
    ///
    /// Heights are then taken about the middle of the surface's own range: about the middle
    /// of a range that reached down to the fill, 1000 ranges below, the f32 lanes lost three
    /// digits (tan α off by 6e-5 of the range, a few hundredths of a degree).
    pub(crate) fn with_holes(self, holes: &'a [bool]) -> Self {
        let (w, h) = (self.grid.width, self.grid.height);
        if holes.len() != w * h || !holes.contains(&true) {
            return self;
        }
        let surface = self.grid.heights.iter().zip(holes).filter(|(_, &o)| !o);
        let (lo, hi) = surface
            .fold((f32::INFINITY, f32::NEG_INFINITY), |(a, b), (&v, _)| (a.min(v), b.max(v)));
        let (grid, curv, isa) = (self.grid, f64::from(self.near.curv), self.near.isa);
        let rows = !self.near.padded.is_empty();
        let (dirs, cuts) = (self.dirs, self.cuts);
        drop(self.near);
        let mut near = Self::about(grid, &dirs, &cuts, curv, isa, (lo, hi), rows);
        near.holes = Some(holes);
        near.fill_hole_pieces((lo, hi));
        if rows {
            near.fill_hole_rows(holes);
        }
        near
    }

    /// [`NearField::with_holes`]'s cells, for the padded rows the march holds.
    fn fill_hole_rows(&mut self, holes: &[bool]) {
        let w = self.grid.width;
        let (pw, pad, r0) = (self.near.pw, self.near.pad, self.near.r0);
        let ph = self.near.padded.len() / pw;
        let xs = strip::padded_columns(&self.grid, pad, pw);
        // The hole flags of padded row r, by the padding's own rule (wrapped or clamped).
        let flags = |r: usize| {
            let src = &holes[strip::padded_row(&self.grid, pad, r0 + r) * w..][..w];
            xs.iter().map(|&x| src[x]).collect::<Vec<bool>>()
        };
        let mut cells = std::mem::take(&mut self.hole_cells);
        cells.clear();
        cells.resize(pw * ph, f32::NEG_INFINITY);
        let mut b = flags(0);
        for r in 0..ph.saturating_sub(1) {
            let a = std::mem::replace(&mut b, flags(r + 1));
            for (c, v) in cells[r * pw..][..pw - 1].iter_mut().enumerate() {
                if !(a[c] || a[c + 1] || b[c] || b[c + 1]) {
                    *v = 0.0;
                }
            }
        }
        self.hole_cells = cells;
    }

    /// [`NearField::with_holes`]'s longer pieces, on a near field built about the surface's
    /// range `lo..=hi`.
    fn fill_hole_pieces(&mut self, (lo, hi): (f32, f32)) {
        let reach = self.hole_reach();
        let range = f64::from(hi - lo);
        let pieces = |&(dx, dy): &(f64, f64)| StripMarch::pieces(dx, dy, reach);
        let segs: Vec<Vec<Seg>> = self.dirs.iter().map(pieces).collect();
        let (pw, curv) = (self.near.pw, self.near.curv);
        let xings = self.dirs.iter().zip(&segs).map(|(&d, g)| Xing::of(g, d, pw, curv, range));
        self.hole_xings = Arc::new(xings.collect());
        self.hole_segs = Arc::new(segs);
    }

    /// Whether [`NearField::strip_near_holes`] may run for the strip at (`x`, `y`) along
    /// direction `n` (with [`NearField::with_holes`]): where every ray runs to the reach (so it
    /// walks by crossings, with the cells' maxima), and the
    /// direction is neither along a grid axis nor a diagonal. An axis ray runs on the edge
    /// between two cells, surface where either is (`exact` gives a cell with a hole that edge;
    /// the crossing walk reads one side's cells). A diagonal ray passes through texels, where
    /// four cells meet: which of them it touches, and so whether that texel counts when the
    /// two it crosses have holes, is decided by the rounding of its step, which the crossing
    /// walk (offsets from the strip) and `exact` (positions on the map) do not share. Elsewhere
    /// a caller takes the texels near a hole from `exact`'s walk.
    #[inline(always)]
    pub(crate) fn honours_holes(&self, n: usize, x: usize, y: usize) -> bool {
        let (dx, dy) = self.dirs[n];
        self.holes.is_some()
            && self.near.cells
            && dx != 0.0
            && dy != 0.0
            && (dx.abs() - dy.abs()).abs() > 1e-9
            && !self.border(n, x, y, self.hole_reach())
    }

    /// The longest cut, rounded up: how far [`NearField::strip_near_holes`] walks.
    fn hole_reach(&self) -> f64 {
        self.cuts.iter().copied().fold(0.0, f64::max).ceil()
    }

    /// [`NearField::strip_from`] for a strip near nodata holes, honouring them as `exact`'s
    /// walk does (see [`NearField::with_holes`]), out to the longest cut in every direction
    /// rather than the direction's own. Only where [`NearField::honours_holes`] says so.
    #[inline(always)]
    pub(crate) fn strip_near_holes(
        &self,
        n: usize,
        x: usize,
        y: usize,
        h0: &[f32; LANES],
        best: &mut [f32; LANES],
    ) {
        debug_assert!(self.honours_holes(n, x, y));
        self.crossings_with(n, x, y, h0, best, true);
        for b in best.iter_mut() {
            *b = b.max(0.0);
        }
    }

    /// With `edge=none`, whether some ray of the strip at (`x`, `y`) along direction `n` leaves
    /// the surface before arc length `cut`. When the cut points of the strip's two end lanes
    /// are on the surface, every lane's is (the surface is convex) and the rays all run to it.
    #[inline(always)]
    fn border(&self, n: usize, x: usize, y: usize, cut: f64) -> bool {
        let lanes = LANES.min(self.grid.width - x);
        let (dx, dy) = self.dirs[n];
        let (wm, hm) = ((self.grid.width - 1) as f64, (self.grid.height - 1) as f64);
        let inside = |xx: usize| {
            let (px, py) = (xx as f64 + cut * dx, y as f64 + cut * dy);
            (0.0..=wm).contains(&px) && (0.0..=hm).contains(&py)
        };
        self.grid.edge == Edge::None && !(inside(x) && inside(x + lanes - 1))
    }

    /// [`NearField::strip_from`] with the strip's heights looked up (for the tests).
    #[cfg(test)]
    pub(crate) fn strip_above(&self, n: usize, x: usize, y: usize, best: &mut [f32; LANES]) {
        let h0 = self.lanes_h0(x, y);
        self.strip_from(n, x, y, &h0, best);
    }

    /// The heights of texels `x .. x + NEAR_LANES` of row `y` as the near field takes them
    /// (relative to its reference; +∞ past the row's end): the same for every bin of a strip,
    /// so a caller running all bins computes them once.
    #[inline(always)]
    pub(crate) fn lanes_h0(&self, x: usize, y: usize) -> [f32; LANES] {
        let w = self.grid.width;
        let lanes = LANES.min(w - x);
        let reference = self.near.reference;
        let mut h0 = [f32::INFINITY; LANES];
        for (i, v) in h0.iter_mut().enumerate().take(lanes) {
            *v = (f64::from(self.grid.heights[y * w + x + i]) - reference) as f32;
        }
        h0
    }

    /// tan α over 0 < s ≤ the cut of direction `n` (and the surface's end with `edge=none`)
    /// for texels `x .. x + NEAR_LANES` of row `y`, folded by max into `best`, which holds a
    /// floor (≥ 0, 0 for none) on entry; lanes past the row's end are unspecified. A floor
    /// known beforehand (`sweep`'s far field) culls every cell that cannot beat it, so the
    /// walk skips cells where the far horizon is high; the result is max(floor, near field) up
    /// to the f32 rounding of a cell's value, a few ulp of the height range (tested). `h0`:
    /// the strip's heights from [`NearField::lanes_h0`]. Where every lane's ray runs to the
    /// cut, the walk is by crossings ([`NearField::crossings_body`]); else the cell walk of
    /// `exact`, which stops each lane at its own end. Always inlined: `sweep`'s bands call it
    /// per strip and bin from code compiled for AVX-512.
    #[inline(always)]
    pub(crate) fn strip_from(
        &self,
        n: usize,
        x: usize,
        y: usize,
        h0: &[f32; LANES],
        best: &mut [f32; LANES],
    ) {
        self.walk(n, x, y, h0, best, true);
    }

    /// [`NearField::strip_above`] by the cell walk alone (for the tests of its culls).
    #[cfg(test)]
    fn cell_walk_above(&self, n: usize, x: usize, y: usize, best: &mut [f32; LANES]) {
        let h0 = self.lanes_h0(x, y);
        self.walk(n, x, y, &h0, best, false);
    }

    /// [`NearField::strip_from`], by crossings only where `crossings` allows it.
    #[inline(always)]
    fn walk(
        &self,
        n: usize,
        x: usize,
        y: usize,
        h0: &[f32; LANES],
        best: &mut [f32; LANES],
        crossings: bool,
    ) {
        let (dx, dy) = self.dirs[n];
        let mut count = [self.near.segs[n].len() as u32; LANES];
        // With `edge=none`, rays that leave the surface before the cut stop there.
        let border = self.border(n, x, y, self.cuts[n]);
        if border {
            let lanes = LANES.min(self.grid.width - x);
            for (i, c) in count.iter_mut().enumerate().take(lanes) {
                let ray = Ray::new(&self.grid, x + i, y, dx, dy, Some(self.cuts[n]));
                *c = self.near.count(n, ray.s_end);
            }
        }
        // The crossing walk reads the cells' maxima, kept while the near field is short.
        if border || !crossings || !self.near.cells {
            self.near.strip(n, (dx, dy), x, y, h0, &count, self.hmax, best);
        } else {
            self.crossings(n, x, y, h0, best);
        }
        for b in best.iter_mut() {
            *b = b.max(0.0);
        }
    }

    /// Every lane's ray runs to the cut: [`NearField::crossings_body`] with the best
    /// instructions the CPU has.
    #[inline(always)]
    fn crossings(&self, n: usize, x: usize, y: usize, h0: &[f32; LANES], best: &mut [f32; LANES]) {
        self.crossings_with(n, x, y, h0, best, false);
    }

    /// [`NearField::crossings`], or with `holes` the walk of [`NearField::strip_near_holes`].
    #[inline(always)]
    fn crossings_with(
        &self,
        n: usize,
        x: usize,
        y: usize,
        h0: &[f32; LANES],
        best: &mut [f32; LANES],
        holes: bool,
    ) {
        match self.near.isa {
            // SAFETY: the strip march's variant is one this CPU supports.
            #[cfg(target_arch = "x86_64")]
            Isa::Avx512 => unsafe { self.crossings_avx512(n, x, y, h0, best, holes) },
            #[cfg(target_arch = "x86_64")]
            Isa::Avx2 => unsafe { self.crossings_avx2(n, x, y, h0, best, holes) },
            _ if holes => self.crossings_body::<true, true>(n, x, y, h0, best),
            _ => self.crossings_body::<true, false>(n, x, y, h0, best),
        }
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f,avx2,fma")]
    unsafe fn crossings_avx512(
        &self,
        n: usize,
        x: usize,
        y: usize,
        h0: &[f32; LANES],
        best: &mut [f32; LANES],
        holes: bool,
    ) {
        if holes {
            self.crossings_body::<true, true>(n, x, y, h0, best);
        } else {
            self.crossings_body::<true, false>(n, x, y, h0, best);
        }
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn crossings_avx2(
        &self,
        n: usize,
        x: usize,
        y: usize,
        h0: &[f32; LANES],
        best: &mut [f32; LANES],
        holes: bool,
    ) {
        if holes {
            self.crossings_body::<true, true>(n, x, y, h0, best);
        } else {
            self.crossings_body::<true, false>(n, x, y, h0, best);
        }
    }

    /// The crossing walk without the pieces solved whole (the pieces' ends and the first
    /// piece's slope alone), for the test that shows those are needed.
    #[cfg(test)]
    fn crossings_ends(
        &self,
        n: usize,
        x: usize,
        y: usize,
        h0: &[f32; LANES],
        b: &mut [f32; LANES],
    ) {
        self.crossings_body::<false, false>(n, x, y, h0, b);
    }

    /// The near field of a strip whose rays all run to the cut, by crossings. Along a piece
    /// the surface is its chord plus a bulge −d2·t·(len − t), d2 = twist·dx·dy − c, so tan α
    /// peaks inside a piece only where the bulge is upward (d2 < 0) and can lift a value above
    /// the piece's larger end by up to −d2·len²/(4·s_a) (see [`piece`]). So each piece costs
    /// its exit's value (a lerp of the two texels of the grid line it crosses, one load per
    /// texel and lane) and that bound from the cell's twist; where the bound beats the best
    /// value for some lane, the cell walk's own cull would not drop the piece (its highest
    /// corner over s_a beats the best value: on exact values, so the closed form never runs
    /// where its f32 cancellation could invent a horizon) and the stationary point lies inside
    /// the piece, the piece is solved whole in closed form (`INTERIOR`; false only for a test).
    /// No cull before the exit's value: with a piece this cheap, the branch a cull takes costs
    /// more than the piece. The first piece (from the texel itself, whose limit s → 0⁺ counts)
    /// is always solved whole. Measured at 2048² `unlimited` on fBm: 3.4 of 22.7 pieces a strip
    /// pass the bound, 1.05 also the stationary point's test (before the cull joined it); the
    /// cell walk solved 9.4 whole after its culls. `HOLES`: with [`NearField::with_holes`]'s
    /// cells, which drop what lies on no surface.
    #[inline(always)]
    fn crossings_body<const INTERIOR: bool, const HOLES: bool>(
        &self,
        n: usize,
        x: usize,
        y: usize,
        h0: &[f32; LANES],
        best: &mut [f32; LANES],
    ) {
        let near = &self.near;
        let (pw, p) = (near.pw, &near.padded[..]);
        let base = (y + near.pad - near.r0) * pw + x + near.pad;
        let (dx, dy) = (self.dirs[n].0 as f32, self.dirs[n].1 as f32);
        let curv = near.curv;
        let mut out = *best;
        // A function, not a closure: a closure is compiled apart, without the caller's target
        // features, so it would run the cell's closed form in SSE.
        #[inline(always)]
        #[allow(clippy::too_many_arguments)] // the piece and the strip's lane state
        fn whole(
            p: &[f32],
            (oc, pw): (usize, usize),
            seg: &Seg,
            (dx, dy, curv): (f32, f32, f32),
            inv_sb: f32,
            h0: &[f32; LANES],
            valid: impl Fn(usize) -> bool,
            out: &mut [f32; LANES],
            first: bool,
        ) {
            let row0 = &p[oc..oc + LANES + 1];
            let row1 = &p[oc + pw..oc + pw + LANES + 1];
            let g = (seg.fx, seg.fy, dx, dy, curv);
            let (s_a, len) = (seg.s_a as f32, seg.len as f32);
            if first {
                piece::<true>(row0, row1, g, s_a, len, inv_sb, h0, valid, out);
            } else {
                piece::<false>(row0, row1, g, s_a, len, inv_sb, h0, valid, out);
            }
        }
        let hc = &self.hole_cells[..];
        let (segs, xings) = if HOLES {
            (&self.hole_segs[n], &self.hole_xings[n])
        } else {
            (&near.segs[n], &self.xings[n])
        };
        let mut prev = [0.0f32; LANES];
        for (k, (seg, xg)) in segs.iter().zip(xings).enumerate() {
            let oc = (base as isize + xg.cell as isize) as usize;
            // Whether lane i's cell of this piece is surface (always, without holes).
            let surface = |i: usize| !HOLES || hc[oc + i] == 0.0;
            if k == 0 || !xg.on_grid {
                let first = k == 0;
                whole(p, (oc, pw), seg, (dx, dy, curv), xg.inv_sb, h0, surface, &mut out, first);
                if !xg.on_grid {
                    break;
                }
            }
            let oa = (base as isize + xg.at as isize) as usize;
            let a = &p[oa..oa + LANES];
            let b = &p[oa + xg.step as usize..][..LANES];
            // Every field read once, before the lanes: a field read inside a condition that
            // short-circuits was compiled as a masked gather.
            let Xing { f, drop, inv_sb, bulge, lift, margin, qi, .. } = *xg;
            let tw = &self.twist[oc..oc + LANES];
            // With holes: 0 or −∞ for this piece's cell and for the next one (the crossing is
            // the edge of both; at the last piece, the cut, only of this one).
            let zeros = [0.0f32; LANES];
            let (hk, hn): (&[f32], &[f32]) = if HOLES {
                let next =
                    xings.get(k + 1).map_or(oc, |x| (base as isize + x.cell as isize) as usize);
                (&hc[oc..oc + LANES], &hc[next..next + LANES])
            } else {
                (&zeros, &zeros)
            };
            let mut v = [0.0f32; LANES];
            let mut interior = false;
            for i in 0..LANES {
                // Never above the higher texel, whatever the rounding: a lerp that rounded up
                // past it would lift a texel level with its neighbours by an ulp of heights
                // of 1e30, a tan α of 1e22.
                let h = fmin(a[i] + (b[i] - a[i]) * f, fmax(a[i], b[i]));
                v[i] = (h - (h0[i] + drop)) * inv_sb;
                let on = if HOLES { v[i] + fmax(hk[i], hn[i]) } else { v[i] };
                out[i] = fmax(on, out[i]);
                // A hole's cell (−∞) is never solved whole.
                let t = tw[i] * bulge + lift + hk[i];
                interior |= (t > 0.0) & (fmax(prev[i], v[i]) + t + margin > out[i]);
            }
            if INTERIOR & interior & (k > 0) {
                // The bound can beat the best somewhere: whether the stationary point of the
                // piece's quadratic lies inside it, as `piece` asks, before solving it whole.
                let Xing { s_a, s_b, len_inv, len, l2, .. } = *xg;
                // And the cell walk's own cull, on exact values: the cell's highest corner
                // over s_a must beat the best value. Without it the closed form would run on
                // cells it never needed, where its f32 cancellation shows: a ±1e30
                // checkerboard's diagonal gave a high texel tan α 0.23 above nothing.
                let cm = &near.cmax[oc..oc + LANES];
                let mut kept = false;
                for i in 0..LANES {
                    kept |= cm[i] - h0[i] > out[i] * s_a;
                }
                let mut stationary = false;
                for i in 0..LANES {
                    let d2 = -(tw[i] * bulge + lift) * qi;
                    let (ha, hb) = (prev[i] * s_a, v[i] * s_b);
                    let d1 = (hb - ha) * len_inv - d2 * len;
                    let nn = d1 * s_a - ha;
                    let span = l2 * -d2;
                    stationary |= (d2 < 0.0) & (nn > -1e-3 * span) & (nn < 1.001 * span);
                }
                if kept & stationary {
                    whole(p, (oc, pw), seg, (dx, dy, curv), inv_sb, h0, surface, &mut out, false);
                }
            }
            prev = v;
        }
        *best = out;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kernels::exact::direction;
    use crate::params::{Edge, YAxis};
    use std::f64::consts::PI;

    /// A seeded generator of uniform values in [0, 1) (a 64-bit LCG's high bits).
    fn lcg(mut seed: u64) -> impl FnMut() -> f32 {
        move || {
            seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            (seed >> 40) as f32 / (1u64 << 24) as f32
        }
    }

    /// The near-field tests' w × h maps: `kind` 0 smooth waves, 1 rough noise, 2 single-texel
    /// spikes 24 high on 3 % of the texels.
    fn near_map(kind: usize, w: usize, h: usize, rnd: &mut impl FnMut() -> f32) -> Vec<f32> {
        (0..w * h)
            .map(|i| match kind {
                0 => ((i % w) as f32 * 0.2).sin() * 3.0 + ((i / w) as f32 * 0.13).cos() * 2.0,
                1 => rnd() * 6.0,
                _ => {
                    if rnd() < 0.03 {
                        24.0
                    } else {
                        rnd() * 0.5
                    }
                }
            })
            .collect()
    }

    /// `bins` image directions of `g` and near-field cuts of 16 major-axis steps, as `sweep`'s.
    fn near_dirs(g: &Grid<'_>, bins: usize) -> (Vec<(f64, f64)>, Vec<f64>) {
        let dirs: Vec<(f64, f64)> =
            (0..bins).map(|n| direction(n as f64 * 2.0 * PI / bins as f64, g.row_step())).collect();
        let cuts = dirs.iter().map(|d| 16.0 * d.0.hypot(d.1).max(1.0)).collect();
        (dirs, cuts)
    }

    /// A floor given to the near field (`sweep` gives its far field) changes no value beyond
    /// rounding: the result is at least the floor, bit for bit, and max(floor, the near field
    /// without one) to within a few f32 ulp of the map's height range (a cell culled against
    /// a different best may be one whose f32 value rounds above its bound: flat ground gives
    /// tan α of 1e-15 rather than 0), with every ISA, on smooth, rough and spiky maps, with
    /// floors below, at and above the near field's value.
    #[test]
    fn a_floor_culls_cells_but_changes_no_value() {
        let mut rnd = lcg(4242);
        let (w, h) = (53usize, 29usize);
        for kind in 0..3 {
            let heights = near_map(kind, w, h, &mut rnd);
            for edge in [Edge::Wrap, Edge::None] {
                let g = Grid::new(w, h, &heights, edge, YAxis::Up);
                let range = g.range().1 - g.range().0;
                let (dirs, cuts) = near_dirs(&g, 32);
                for isa in [Isa::Avx512, Isa::Avx2, Isa::Baseline] {
                    if !isa.supported() {
                        continue;
                    }
                    let near = NearField::new(g, &dirs, &cuts, 0.0, isa);
                    let mut floored = 0;
                    for y in 0..h {
                        for x in (0..w).step_by(LANES) {
                            let lanes = LANES.min(w - x);
                            for n in 0..dirs.len() {
                                let mut plain = [0.0f32; LANES];
                                near.strip_above(n, x, y, &mut plain);
                                let f = rnd();
                                for scale in [0.5f32, 1.0, 1.5, 0.0] {
                                    let mut floor = [0.0f32; LANES];
                                    for (i, v) in floor.iter_mut().enumerate() {
                                        *v = if scale == 0.0 { f * 3.0 } else { plain[i] * scale };
                                    }
                                    let mut got = floor;
                                    near.strip_above(n, x, y, &mut got);
                                    for i in 0..lanes {
                                        let want = plain[i].max(floor[i]);
                                        floored += usize::from(floor[i] > plain[i]);
                                        assert!(
                                            got[i] >= floor[i]
                                                && (got[i] - want).abs()
                                                    <= 8.0 * f32::EPSILON * (want + range),
                                            "kind {kind} {edge:?} {isa:?} texel ({}, {y}) bin {n} \
                                             floor {}: {} vs {}",
                                            x + i,
                                            floor[i],
                                            got[i],
                                            want
                                        );
                                    }
                                }
                            }
                        }
                    }
                    assert!(floored > 1000, "the floors were above the near field {floored} times");
                }
            }
        }
    }

    /// The crossing walk ([`NearField::crossings`]: each piece's exit as a lerp of two
    /// texels, a piece solved whole only where its bulge can beat the best) gives what the
    /// cell walk gives ([`StripMarch::strip`], every piece in closed form) to within a few f32 ulp
    /// of the height range: on smooth, rough and spiky maps (rough ones have saddles whose
    /// interior maxima top a piece's ends), with and without the curvature drop, with floors
    /// below and above, on every ISA. And the interior maxima are needed: without them the
    /// rough maps' values drop below the cell walk's.
    #[test]
    fn crossings_match_the_cell_walk() {
        let mut rnd = lcg(2712);
        let (w, h) = (45usize, 27usize);
        let mut compared = 0usize;
        let mut raised = 0usize;
        for kind in 0..3 {
            let heights = near_map(kind, w, h, &mut rnd);
            let g = Grid::new(w, h, &heights, Edge::Wrap, YAxis::Up);
            let range = g.range().1 - g.range().0;
            let (dirs, cuts) = near_dirs(&g, 32);
            for curv in [0.0, 2e-3] {
                for isa in [Isa::Avx512, Isa::Avx2, Isa::Baseline] {
                    if !isa.supported() {
                        continue;
                    }
                    let near = NearField::new(g, &dirs, &cuts, curv, isa);
                    for y in 0..h {
                        for x in (0..w).step_by(LANES) {
                            let h0 = near.lanes_h0(x, y);
                            for (n, &d) in dirs.iter().enumerate() {
                                let count = [near.near.segs[n].len() as u32; LANES];
                                let f = rnd() * 0.3;
                                for floor in [0.0, f] {
                                    let (mut got, mut want) = ([floor; LANES], [floor; LANES]);
                                    near.crossings(n, x, y, &h0, &mut got);
                                    near.near.strip(n, d, x, y, &h0, &count, near.hmax, &mut want);
                                    // Without the pieces solved whole: the ends alone.
                                    let mut ends = [floor; LANES];
                                    near.crossings_ends(n, x, y, &h0, &mut ends);
                                    for i in 0..LANES.min(w - x) {
                                        let tol = 8.0 * f32::EPSILON * (want[i].abs() + range);
                                        assert!(
                                            (got[i] - want[i]).abs() <= tol,
                                            "kind {kind} c {curv} {isa:?} ({}, {y}) bin {n} \
                                             floor {floor}: {} vs {}",
                                            x + i,
                                            got[i],
                                            want[i]
                                        );
                                        raised += usize::from(want[i] > ends[i] + tol);
                                        compared += 1;
                                    }
                                }
                            }
                        }
                    }
                }
            }
        }
        assert!(compared > 50_000, "compared {compared}");
        assert!(raised > 100, "interior maxima above both ends of a piece: {raised}");
        // Heights of ±1e30 in a checkerboard: a high texel has nothing above it, in every
        // direction (the diagonals run through cells whose closed form cancels badly in f32,
        // and a lerp rounded up by an ulp of 1e30 would be a tan α of 1e22).
        let (w, h) = (8usize, 6usize);
        let board: Vec<f32> =
            (0..w * h).map(|k| if (k % w + k / w) % 2 == 0 { 1e30 } else { -1e30 }).collect();
        let g = Grid::new(w, h, &board, Edge::Wrap, YAxis::Up);
        let (dirs, cuts) = near_dirs(&g, 32);
        for isa in [Isa::Avx512, Isa::Avx2, Isa::Baseline] {
            if !isa.supported() {
                continue;
            }
            let near = NearField::new(g, &dirs, &cuts, 0.0, isa);
            for y in 0..h {
                let h0 = near.lanes_h0(0, y);
                for n in 0..dirs.len() {
                    let mut got = [0.0f32; LANES];
                    near.crossings(n, 0, y, &h0, &mut got);
                    for (x, &v) in got.iter().enumerate().take(w) {
                        if board[y * w + x] > 0.0 {
                            assert!(v <= 0.0, "{isa:?} high texel ({x}, {y}) bin {n}: {v}");
                        } else {
                            assert!(v > 1e29, "{isa:?} low texel ({x}, {y}) bin {n}: {v}");
                        }
                    }
                }
            }
            // Random heights of ±1e30 scale: the highest texel has nothing above it, even
            // where the lerp towards it from a lower neighbour ends next to it.
            for seed in 0..20u64 {
                let mut r = lcg(seed);
                let (w, h) = (19usize, 17usize);
                let vals: Vec<f32> = (0..w * h).map(|_| (r() * 2.0 - 1.0) * 1e30).collect();
                let top = vals.iter().copied().fold(f32::MIN, f32::max);
                let t = vals.iter().position(|&v| v == top).unwrap();
                let (tx, ty) = (t % w, t / w);
                let g = Grid::new(w, h, &vals, Edge::Wrap, YAxis::Up);
                let (dirs, cuts) = near_dirs(&g, 64);
                let near = NearField::new(g, &dirs, &cuts, 0.0, isa);
                let h0 = near.lanes_h0(tx, ty);
                for n in 0..dirs.len() {
                    let mut got = [0.0f32; LANES];
                    near.crossings(n, tx, ty, &h0, &mut got);
                    assert!(
                        got[0] <= 0.0,
                        "{isa:?} seed {seed} top ({tx}, {ty}) bin {n}: {}",
                        got[0]
                    );
                }
            }
        }
    }

    /// With nodata holes ([`NearField::with_holes`]) the crossing walk gives what `exact`'s
    /// hole-aware walk gives over the same reach, wherever it says it honours them: on smooth,
    /// rough and spiky maps with blobs of holes filled far below as the bake fills them, with
    /// and without the curvature drop, both edges, every ISA, with floors; to a few f32 ulp of
    /// the surface's own range (the fill, 1000 ranges below, costs no precision).
    #[test]
    fn crossings_with_holes_match_exact() {
        use crate::kernels::exact::ExactHorizon;
        use crate::params::Reduce;
        let mut rnd = lcg(5150);
        let (w, h) = (47usize, 31usize);
        let mut compared = 0usize;
        let mut by_holes = 0usize;
        for kind in 0..3 {
            let mut heights = near_map(kind, w, h, &mut rnd);
            // Blobs of holes (discs of radius 1–4) and a few single texels.
            let mut holes = vec![false; w * h];
            for _ in 0..6 {
                let (cx, cy, r) = (rnd() * w as f32, rnd() * h as f32, 1.0 + rnd() * 3.0);
                for (k, o) in holes.iter_mut().enumerate() {
                    let (dx, dy) = ((k % w) as f32 - cx, (k / w) as f32 - cy);
                    *o |= dx * dx + dy * dy <= r * r || rnd() < 0.004;
                }
            }
            let (lo, hi) = heights
                .iter()
                .zip(&holes)
                .filter(|(_, &o)| !o)
                .fold((f32::MAX, f32::MIN), |(a, b), (&v, _)| (a.min(v), b.max(v)));
            let fill = crate::heightmap::hole_fill(lo, hi);
            for (v, &o) in heights.iter_mut().zip(&holes) {
                if o {
                    *v = fill;
                }
            }
            // Hole texels apart: every valid texel a cell or two from one.
            let near = crate::kernels::near_holes(&holes, w, h, 18, true);
            for edge in [Edge::Wrap, Edge::None] {
                let g = Grid::new(w, h, &heights, edge, YAxis::Up);
                let bins = 32;
                let dirs: Vec<(f64, f64)> = (0..bins)
                    .map(|n| direction(n as f64 * 2.0 * PI / bins as f64, g.row_step()))
                    .collect();
                // `sweep`'s cuts (16 steps of the major axis), so the walk near holes runs
                // past a direction's own cut to the longest, as `exact` does over its radius.
                let cuts: Vec<f64> = dirs.iter().map(|d| 16.0 / d.0.abs().max(d.1.abs())).collect();
                let reach = cuts.iter().copied().fold(0.0, f64::max).ceil() as u32;
                for curv in [0.0, 2e-3] {
                    let exact = ExactHorizon::new(g, Some(reach), bins as u32, Reduce::Point)
                        .with_curvature(curv)
                        .with_holes(Some(&holes));
                    for isa in [Isa::Avx512, Isa::Avx2, Isa::Baseline] {
                        if !isa.supported() {
                            continue;
                        }
                        let nf = NearField::new(g, &dirs, &cuts, curv, isa).with_holes(&holes);
                        for y in 0..h {
                            for x in (0..w).step_by(LANES) {
                                for n in 0..bins {
                                    if !nf.honours_holes(n, x, y) {
                                        continue;
                                    }
                                    let f = rnd() * 0.3;
                                    for floor in [0.0, f] {
                                        let mut got = [floor; LANES];
                                        nf.strip_near_holes(n, x, y, &nf.lanes_h0(x, y), &mut got);
                                        for (i, &v) in got.iter().enumerate().take(w - x) {
                                            let t = y * w + x + i;
                                            if holes[t] {
                                                continue;
                                            }
                                            let want =
                                                exact.tan_at(x + i, y, n, f64::from(floor)) as f32;
                                            // A few f32 ulp of the surface's range: the
                                            // fill far below costs it no precision.
                                            let tol = 8.0 * f32::EPSILON * (want.abs() + hi - lo);
                                            assert!(
                                                (v - want).abs() <= tol,
                                                "kind {kind} {edge:?} c {curv} {isa:?} ({}, {y}) \
                                                 bin {n} floor {floor}: {v} vs {want}",
                                                x + i,
                                            );
                                            compared += 1;
                                            by_holes += usize::from(near.get(t));
                                        }
                                    }
                                }
                            }
                        }
                    }
                }
            }
        }
        assert!(compared > 50_000 && by_holes > 20_000, "{compared} compared, {by_holes} near");
    }

    /// A window of rows ([`NearField::rows`]) gives the bits of the whole map's near field on
    /// its rows: by the cell walk and by crossings, near holes and away from them, with and
    /// without curvature and floors, both edges, every ISA, windows at the top, in the middle
    /// and at the bottom of the map; and it holds only the padded rows its rays read.
    #[test]
    fn a_window_of_rows_gives_the_bits_of_the_whole() {
        let mut rnd = lcg(7707);
        let (w, h) = (45usize, 83usize);
        let mut compared = 0usize;
        for kind in 0..3 {
            let mut heights = near_map(kind, w, h, &mut rnd);
            let mut holes = vec![false; w * h];
            for _ in 0..4 {
                let (cx, cy, r) = (rnd() * w as f32, rnd() * h as f32, 1.0 + rnd() * 3.0);
                for (k, o) in holes.iter_mut().enumerate() {
                    let (dx, dy) = ((k % w) as f32 - cx, (k / w) as f32 - cy);
                    *o |= dx * dx + dy * dy <= r * r;
                }
            }
            let fill = crate::heightmap::hole_fill(-10.0, 30.0);
            for (v, &o) in heights.iter_mut().zip(&holes) {
                if o {
                    *v = fill;
                }
            }
            for edge in [Edge::Wrap, Edge::None] {
                let g = Grid::new(w, h, &heights, edge, YAxis::Up);
                let (dirs, cuts) = near_dirs(&g, 24);
                for (with_holes, curv) in [(false, 0.0), (true, 0.0), (true, 2e-3), (false, 2e-3)] {
                    for isa in [Isa::Avx512, Isa::Avx2, Isa::Baseline] {
                        if !isa.supported() {
                            continue;
                        }
                        let make = |rows: bool| {
                            let f = if rows {
                                NearField::new(g, &dirs, &cuts, curv, isa)
                            } else {
                                NearField::without_rows(g, &dirs, &cuts, curv, isa)
                            };
                            if with_holes {
                                f.with_holes(&holes)
                            } else {
                                f
                            }
                        };
                        let (whole, lazy) = (make(true), make(false));
                        assert!(lazy.near.padded.is_empty() && lazy.twist.is_empty());
                        for (y0, y1) in [(0, 7), (30, 46), (h - 5, h), (0, h)] {
                            let win = lazy.rows(y0, y1);
                            if y1 - y0 < h {
                                assert!(win.near.padded.len() < whole.near.padded.len() / 2);
                            }
                            for y in y0..y1 {
                                for x in (0..w).step_by(LANES) {
                                    let h0 = whole.lanes_h0(x, y);
                                    for n in 0..dirs.len() {
                                        let floor = [rnd() * 0.2; LANES];
                                        for f in [[0.0; LANES], floor] {
                                            let (mut a, mut b) = (f, f);
                                            whole.strip_from(n, x, y, &h0, &mut a);
                                            win.strip_from(n, x, y, &h0, &mut b);
                                            let at = || {
                                                format!(
                                                    "kind {kind} {edge:?} holes {with_holes} c \
                                                     {curv} {isa:?} ({x}, {y}) bin {n}"
                                                )
                                            };
                                            let lanes = LANES.min(w - x);
                                            assert_eq!(a[..lanes], b[..lanes], "{}", at());
                                            let hon = whole.honours_holes(n, x, y);
                                            assert_eq!(hon, win.honours_holes(n, x, y), "{}", at());
                                            if hon {
                                                let (mut a, mut b) = (f, f);
                                                whole.strip_near_holes(n, x, y, &h0, &mut a);
                                                win.strip_near_holes(n, x, y, &h0, &mut b);
                                                assert_eq!(
                                                    a[..lanes],
                                                    b[..lanes],
                                                    "{} holes",
                                                    at()
                                                );
                                            }
                                            compared += lanes;
                                        }
                                    }
                                }
                            }
                        }
                    }
                }
            }
        }
        assert!(compared > 100_000, "{compared}");
    }

    /// The cells' maxima ([`StripMarch::cmax`]) cull exactly the pieces the four corners culled: a
    /// near field with them and one without give the same bits, with and without floors, on
    /// smooth, rough and spiky maps, both edges and every ISA; and a wide padding (`exact`'s
    /// long near field) keeps none.
    #[test]
    fn cells_maxima_cull_as_the_corners_do() {
        let mut rnd = lcg(77);
        let (w, h) = (41usize, 23usize);
        let mut compared = 0usize;
        for kind in 0..3 {
            let heights = near_map(kind, w, h, &mut rnd);
            for edge in [Edge::Wrap, Edge::None] {
                let g = Grid::new(w, h, &heights, edge, YAxis::Up);
                let (dirs, cuts) = near_dirs(&g, 24);
                for isa in [Isa::Avx512, Isa::Avx2, Isa::Baseline] {
                    if !isa.supported() {
                        continue;
                    }
                    let with = NearField::new(g, &dirs, &cuts, 0.0, isa);
                    assert!(!with.near.cmax.is_empty(), "a near field of 16 keeps the maxima");
                    let mut without = with.clone();
                    without.near.cmax = Vec::new();
                    without.near.cells = false;
                    for y in 0..h {
                        for x in (0..w).step_by(LANES) {
                            for n in 0..dirs.len() {
                                let f = rnd() * 0.5;
                                for floor in [0.0, f] {
                                    let (mut a, mut b) = ([floor; LANES], [floor; LANES]);
                                    with.cell_walk_above(n, x, y, &mut a);
                                    without.cell_walk_above(n, x, y, &mut b);
                                    for i in 0..LANES.min(w - x) {
                                        assert_eq!(
                                            a[i].to_bits(),
                                            b[i].to_bits(),
                                            "kind {kind} {edge:?} {isa:?} ({}, {y}) bin {n}",
                                            x + i
                                        );
                                        compared += 1;
                                    }
                                }
                            }
                        }
                    }
                }
            }
        }
        assert!(compared > 100_000, "compared {compared}");
        let flat = vec![0.0; w * h];
        let g = Grid::new(w, h, &flat, Edge::Wrap, YAxis::Up);
        let wide = StripMarch::new(&g, &[(1.0, 0.0)], 100.0);
        assert!(
            wide.cmax.is_empty() && !wide.cells,
            "a padding past CELL_MAX_PAD keeps no second copy"
        );
    }
}
