//! [`StripMarch`], the vectorised exact near field: the rays of [`LANES`] consecutive texels of
//! a row along one azimuth cross the same pieces at the same local positions, so the pieces are
//! listed once per azimuth and the lanes read contiguous corners from a padded copy of the map.

use crate::kernels::isa::Isa;
use crate::kernels::Grid;
use crate::params::Edge;
use std::sync::Arc;

/// Texels per strip of the near-field march: one AVX-512 vector of f32, two AVX2 vectors.
pub(crate) const LANES: usize = 16;

/// One piece of a ray between two grid-line crossings, shared by all rays of a direction: the
/// crossings of a ray from an integer texel centre fall at s = k/|dx| and s = k/|dy| whatever
/// the texel, so consecutive texels of a row see the same pieces at the same local positions in
/// cells one column apart. Only the corner heights differ per texel, and they are contiguous.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Seg {
    pub(crate) s_a: f64,
    pub(crate) len: f64,
    pub(crate) fx: f32,
    pub(crate) fy: f32,
    /// Cell offset from the texel: columns (x + cxo .. x + cxo + 1), rows likewise.
    pub(crate) cxo: i32,
    pub(crate) cyo: i32,
}

/// The near-field march: per-direction pieces up to `s_cut` and a padded copy of the heights
/// (wrapped, or clamped for `edge=none` where the padding is masked out) so the hot loop never
/// wraps or clamps.
#[derive(Debug, Clone)]
pub(crate) struct StripMarch {
    /// Shared (`Arc`) with the march's row windows ([`StripMarch::fill_window`]), as are `spans` and
    /// `culls`: what does not depend on the rows is made once.
    pub(crate) segs: Arc<Vec<Vec<Seg>>>,
    pub(crate) s_cut: f64,
    pub(crate) pad: usize,
    pub(crate) pw: usize,
    /// Padded rows `r0 ..` of the map (padded row r is texel row r − `pad`): all of them, or
    /// a window's ([`StripMarch::fill_window`]).
    pub(crate) padded: Vec<f32>,
    pub(crate) r0: usize,
    /// Subtracted from every height in `padded` (and from the lanes' h0): the middle of the
    /// map's range. The f32 lanes interpolate heights before subtracting h0, so absolute
    /// heights of 1e4 (a DEM in metres) would cost 1e-3 of precision; centred, the error
    /// scales with the range instead.
    pub(crate) reference: f64,
    /// Per direction, the pieces grouped into spans that one bound can cull together (see
    /// [`Spans`]).
    pub(crate) spans: Arc<Vec<Spans>>,
    /// Block maxima of `padded`, for the spans' bounds.
    pub(crate) blocks: PadPyramid,
    /// Per padded texel (r, c), the largest of the four corners of the cell it is the top left
    /// of: a piece's cull then reads one run of 16 rather than four and three maxima (the same
    /// values, so the same culls). Empty when the padding is wide (`exact`'s long near field:
    /// another copy of a padded 8192² map would cost 0.4 GB); [`CELL_MAX_PAD`].
    pub(crate) cmax: Vec<f32>,
    /// Whether the padding is narrow enough for `cmax` ([`CELL_MAX_PAD`]); the crossing walk
    /// needs it. `cmax` is then filled wherever `padded` is.
    pub(crate) cells: bool,
    /// Per direction and piece, where its cell lies in the padded layout relative to the
    /// strip's first texel (cyo·pw + cxo) and its s_a in f32: all a piece's cull reads
    /// (empty without `cmax`).
    pub(crate) culls: Arc<Vec<Vec<(i32, f32)>>>,
    /// The compiled variant the strips run ([`Isa::detect`], or narrower when asked).
    pub(crate) isa: Isa,
    /// Earth-curvature drop per texel² in the pieces' closed form (0: flat).
    pub(crate) curv: f32,
}

/// Widest padding for which [`StripMarch`] keeps its cells' maxima (a near field of up to 62 texels).
pub(crate) const CELL_MAX_PAD: usize = 64;

/// Where a span of pieces can start: nearer, a span's bound (M − h0)/s_start is too loose to
/// cull much, and single pieces are cheap to cull one by one.
pub(crate) const SPAN_FROM: f64 = 32.0;

/// Where a coarse span starts being split into fine spans.
pub(crate) const FINE_FROM: f64 = 96.0;

/// Consecutive pieces `start..end` of one direction whose cells, for every lane of a strip,
/// lie in the box `c0..=c1`, `r0..=r1` of padded texels relative to the strip's first texel
/// (lane i's cells are i columns further right, so `c1` includes the lanes). Every sample of
/// the span is at s ≥ `s_start`, so (max of the box − h0)/`s_start` bounds it (`best` ≥ 0).
#[derive(Debug, Clone, Copy)]
pub(crate) struct Span {
    pub(crate) start: usize,
    pub(crate) end: usize,
    /// The first piece's `s_a`, converted exactly as the per-piece cull converts it, so a span
    /// is culled only when each of its pieces would be (see [`StripMarch::strip_body`]).
    pub(crate) s_start: f32,
    pub(crate) c0: i32,
    pub(crate) r0: i32,
    pub(crate) c1: i32,
    pub(crate) r1: i32,
    /// Level of [`PadPyramid`] whose blocks read the box in at most 3 × 3 lookups.
    pub(crate) level: u8,
}

/// A direction's spans, two deep: coarse spans of about s/2 of arc, each made of fine spans
/// of about s/8. A coarse span is tried first; when it cannot be culled, its fine spans are;
/// pieces before [`SPAN_FROM`] run one by one.
#[derive(Debug, Clone, Default)]
pub(crate) struct Spans {
    /// Pieces before the first span.
    pub(crate) head: usize,
    pub(crate) coarse: Vec<(Span, std::ops::Range<usize>)>,
    pub(crate) fine: Vec<Span>,
}

impl Spans {
    pub(crate) fn new(segs: &[Seg], levels: usize) -> Spans {
        let head = segs.partition_point(|g| g.s_a < SPAN_FROM);
        let make = |a: usize, b: usize| -> Span {
            let (mut c0, mut r0, mut c1, mut r1) = (i32::MAX, i32::MAX, i32::MIN, i32::MIN);
            for g in &segs[a..b] {
                c0 = c0.min(g.cxo);
                r0 = r0.min(g.cyo);
                c1 = c1.max(g.cxo + 1);
                r1 = r1.max(g.cyo + 1);
            }
            // Lane i reads its cell's columns i further right: up to cxo + 1 + (LANES − 1).
            c1 += LANES as i32 - 1;
            let side = (c1 - c0 + 1).max(r1 - r0 + 1) as i64;
            let mut level = 0usize;
            while level < levels && 2 * (1i64 << (2 * level)) < side {
                level += 1;
            }
            Span {
                start: a,
                end: b,
                s_start: segs[a].s_a as f32,
                c0,
                r0,
                c1,
                r1,
                level: level as u8,
            }
        };
        // Groups pieces from..to into runs of about `frac` of their starting arc length.
        let group = |from: usize, to: usize, frac: f64, min: f64| -> Vec<(usize, usize)> {
            let mut out = Vec::new();
            let mut a = from;
            while a < to {
                let s0 = segs[a].s_a;
                let mut b = a + 1;
                while b < to && segs[b].s_a + segs[b].len - s0 <= (s0 * frac).max(min) {
                    b += 1;
                }
                out.push((a, b));
                a = b;
            }
            out
        };
        let mut spans = Spans { head, ..Spans::default() };
        for (a, b) in group(head, segs.len(), 0.5, 32.0) {
            let first = spans.fine.len();
            // StripMarch spans are short: were their fine spans checked too, the checks would cost
            // more than they save where the coarse one fails (rough maps).
            if segs[a].s_a >= FINE_FROM {
                for (fa, fb) in group(a, b, 1.0 / 8.0, 8.0) {
                    spans.fine.push(make(fa, fb));
                }
            }
            spans.coarse.push((make(a, b), first..spans.fine.len()));
        }
        spans
    }
}

/// The map column of each padded column, by the padding's rule: wrapped, or clamped for
/// `edge=none` (where the padding is masked out).
pub(crate) fn padded_columns(grid: &Grid<'_>, pad: usize, pw: usize) -> Vec<usize> {
    let w = grid.width as i64;
    let col = |c: usize| {
        let x = c as i64 - pad as i64;
        match grid.edge {
            Edge::Wrap => x.rem_euclid(w),
            Edge::None => x.clamp(0, w - 1),
        }
    };
    (0..pw).map(|c| col(c) as usize).collect()
}

/// The map row of padded row `r`, by the same rule.
pub(crate) fn padded_row(grid: &Grid<'_>, pad: usize, r: usize) -> usize {
    let (y, h) = (r as i64 - pad as i64, grid.height as i64);
    (match grid.edge {
        Edge::Wrap => y.rem_euclid(h),
        Edge::None => y.clamp(0, h - 1),
    }) as usize
}

/// Maxima of 4^k × 4^k blocks of the padded heights (level k ≥ 1; level 0 is the heights).
#[derive(Debug, Clone, Default)]
pub(crate) struct PadPyramid {
    /// `levels[k - 1]`: (blocks per row, maxima).
    pub(crate) levels: Vec<(usize, Vec<f32>)>,
}

impl PadPyramid {
    /// Fills the levels up to `top` from `padded` (`pw` × `ph`), keeping the allocations
    /// held (a window of rows made again per azimuth).
    pub(crate) fn fill(&mut self, padded: &[f32], pw: usize, ph: usize, top: usize) {
        self.levels.resize_with(top, Default::default);
        let (mut src_w, mut src_h) = (pw, ph);
        for k in 0..top {
            let (nw, nh) = (src_w.div_ceil(4), src_h.div_ceil(4));
            let (done, rest) = self.levels.split_at_mut(k);
            let src: &[f32] = done.last().map_or(padded, |l| &l.1[..]);
            let (lw, max) = &mut rest[0];
            *lw = nw;
            max.clear();
            max.resize(nw * nh, f32::NEG_INFINITY);
            for (r, row) in src.chunks_exact(src_w).take(src_h).enumerate() {
                let out = &mut max[(r / 4) * nw..][..nw];
                for (m, q) in out.iter_mut().zip(row.chunks(4)) {
                    *m = q.iter().fold(*m, |a, &v| a.max(v));
                }
            }
            (src_w, src_h) = (nw, nh);
        }
    }

    /// The largest padded height in columns `c0..=c1`, rows `r0..=r1`, read at `level`.
    #[inline]
    pub(crate) fn box_max(
        &self,
        padded: &[f32],
        pw: usize,
        level: u8,
        (c0, r0, c1, r1): (usize, usize, usize, usize),
    ) -> f32 {
        let mut m = f32::NEG_INFINITY;
        if level == 0 {
            for r in r0..=r1 {
                for &v in &padded[r * pw + c0..=r * pw + c1] {
                    m = m.max(v);
                }
            }
            return m;
        }
        let (nw, max) = &self.levels[level as usize - 1];
        let sh = 2 * level as u32;
        for r in (r0 >> sh)..=(r1 >> sh) {
            for &v in &max[r * nw + (c0 >> sh)..=r * nw + (c1 >> sh)] {
                m = m.max(v);
            }
        }
        m
    }
}

impl StripMarch {
    pub(crate) fn new(grid: &Grid<'_>, dirs: &[(f64, f64)], s_cut: f64) -> StripMarch {
        Self::with_cuts(grid, dirs, &vec![s_cut; dirs.len()])
    }

    /// [`StripMarch::new`] with its own cut per direction (`s_cut` is then the largest).
    pub(crate) fn with_cuts(grid: &Grid<'_>, dirs: &[(f64, f64)], cuts: &[f64]) -> StripMarch {
        Self::with_cuts_about(grid, dirs, cuts, grid.range())
    }

    /// [`StripMarch::with_cuts`] with heights taken relative to the middle of `lo..=hi` rather
    /// than of the grid's whole range (a map with holes: the middle of its surface's range, not
    /// of the fill far below it, so the f32 lanes keep the surface's precision).
    pub(crate) fn with_cuts_about(
        grid: &Grid<'_>,
        dirs: &[(f64, f64)],
        cuts: &[f64],
        lohi: (f32, f32),
    ) -> StripMarch {
        let mut march = Self::without_rows(grid, dirs, cuts, lohi);
        march.fill_rows(grid, 0, march.padded_rows(grid));
        march
    }

    /// [`StripMarch::with_cuts_about`] with no padded rows yet: the pieces, spans and culls
    /// alone, for a caller that makes the rows of each band it runs ([`StripMarch::fill_window`]).
    pub(crate) fn without_rows(
        grid: &Grid<'_>,
        dirs: &[(f64, f64)],
        cuts: &[f64],
        (lo, hi): (f32, f32),
    ) -> StripMarch {
        let s_cut = cuts.iter().copied().fold(0.0f64, f64::max);
        let pad = s_cut.ceil() as usize + 2;
        let pw = grid.width + 2 * pad + LANES + 1;
        let reference = 0.5 * (f64::from(lo) + f64::from(hi));
        let segs: Vec<Vec<Seg>> =
            dirs.iter().zip(cuts).map(|(&(dx, dy), &cut)| Self::pieces(dx, dy, cut)).collect();
        let top = Self::levels(pad);
        let spans = segs.iter().map(|g| Spans::new(g, top)).collect();
        let cells = pad <= CELL_MAX_PAD;
        let mut culls = Vec::new();
        if cells {
            culls = segs
                .iter()
                .map(|d| d.iter().map(|g| (g.cyo * pw as i32 + g.cxo, g.s_a as f32)).collect())
                .collect();
        }
        StripMarch {
            segs: Arc::new(segs),
            s_cut,
            pad,
            pw,
            padded: Vec::new(),
            r0: 0,
            reference,
            spans: Arc::new(spans),
            blocks: PadPyramid::default(),
            cmax: Vec::new(),
            cells,
            culls: Arc::new(culls),
            isa: Isa::detect(),
            curv: 0.0,
        }
    }

    /// Levels of [`PadPyramid`] for a padding: up to blocks of 4^5 = 1024, a span's box being
    /// at most about s_cut / 2 on a side.
    fn levels(pad: usize) -> usize {
        (1..=5).take_while(|&k| (1usize << (2 * (k - 1))) < pad).count()
    }

    /// Padded rows of the whole map.
    pub(crate) fn padded_rows(&self, grid: &Grid<'_>) -> usize {
        grid.height + 2 * self.pad + 1
    }

    /// Padded rows `ra..rb` of `grid` (and their block and cell maxima), replacing any held.
    /// The allocations held are kept: a window made again per azimuth costs no page faults.
    pub(crate) fn fill_rows(&mut self, grid: &Grid<'_>, ra: usize, rb: usize) {
        let (w, pad, pw) = (grid.width, self.pad, self.pw);
        let ph = rb - ra;
        let reference = self.reference;
        let mut padded = std::mem::take(&mut self.padded);
        padded.clear();
        padded.resize(pw * ph, 0.0);
        // The map's own columns are a run of each padded row (pad .. pad + W); only the
        // padding goes through the edge rule.
        let xs = padded_columns(grid, pad, pw);
        for (r, out) in padded.chunks_exact_mut(pw).enumerate() {
            let src = &grid.heights[padded_row(grid, pad, ra + r) * w..][..w];
            let centred = |v: f32| (f64::from(v) - reference) as f32;
            for (o, &v) in out[pad..pad + w].iter_mut().zip(src) {
                *o = centred(v);
            }
            for c in (0..pad).chain(pad + w..pw) {
                out[c] = centred(src[xs[c]]);
            }
        }
        self.blocks.fill(&padded, pw, ph, Self::levels(pad));
        let mut cmax = std::mem::take(&mut self.cmax);
        cmax.clear();
        if self.cells {
            cmax.resize(pw * ph, f32::INFINITY);
            for r in 0..ph.saturating_sub(1) {
                let (a, b) = (&padded[r * pw..][..pw], &padded[(r + 1) * pw..][..pw]);
                let out = &mut cmax[r * pw..][..pw - 1];
                for (c, m) in out.iter_mut().enumerate() {
                    *m = a[c].max(a[c + 1]).max(b[c]).max(b[c + 1]);
                }
            }
        }
        self.cmax = cmax;
        self.padded = padded;
        self.r0 = ra;
    }

    /// Makes this the march over texel rows `y0..y1` alone: the padded rows their rays read
    /// (`y0 .. y1 + 2·pad + 1`), with the same pieces. Every lane of those rows gets the bits of the
    /// whole map's march: the heights are the same, and the block maxima only cull what a
    /// piece's own cull would (see [`StripMarch::culled`]), whatever the blocks' alignment.
    pub(crate) fn fill_window(&mut self, grid: &Grid<'_>, y0: usize, y1: usize) {
        self.fill_rows(grid, y0, (y1 + 2 * self.pad + 1).min(self.padded_rows(grid)));
    }

    /// A copy without the rows (the `Arc`s shared).
    pub(crate) fn clone_light(&self) -> StripMarch {
        StripMarch {
            segs: Arc::clone(&self.segs),
            s_cut: self.s_cut,
            pad: self.pad,
            pw: self.pw,
            padded: Vec::new(),
            r0: 0,
            reference: self.reference,
            spans: Arc::clone(&self.spans),
            blocks: PadPyramid::default(),
            cmax: Vec::new(),
            cells: self.cells,
            culls: Arc::clone(&self.culls),
            isa: self.isa,
            curv: self.curv,
        }
    }

    /// How many pieces of direction `n` end at or before `s_end` (a lane's own end with
    /// `edge=none`, which falls on a piece boundary).
    pub(crate) fn count(&self, n: usize, s_end: f64) -> u32 {
        self.segs[n].partition_point(|g| g.s_a + g.len <= s_end + 1e-9) as u32
    }

    /// The pieces of a ray from the origin along (dx, dy) up to `s_cut`.
    pub(crate) fn pieces(dx: f64, dy: f64, s_cut: f64) -> Vec<Seg> {
        let mut out = Vec::new();
        let (ix, iy) = (1.0 / dx.abs(), 1.0 / dy.abs());
        let (mut kx, mut ky) = (1u32, 1u32);
        let mut s_a = 0.0f64;
        while s_a < s_cut {
            let (tx, ty) = (kx as f64 * ix, ky as f64 * iy);
            let s_b = tx.min(ty).min(s_cut);
            if tx <= s_b {
                kx += 1;
            }
            if ty <= s_b {
                ky += 1;
            }
            if s_b <= s_a {
                continue;
            }
            let mid = 0.5 * (s_a + s_b);
            let (cxo, cyo) = ((mid * dx).floor(), (mid * dy).floor());
            out.push(Seg {
                s_a,
                len: s_b - s_a,
                fx: (s_a * dx - cxo).clamp(0.0, 1.0) as f32,
                fy: (s_a * dy - cyo).clamp(0.0, 1.0) as f32,
                cxo: cxo as i32,
                cyo: cyo as i32,
            });
            s_a = s_b;
        }
        out
    }

    /// tan α over 0 < s ≤ min(s_cut, s_end[i]) for the texels x .. x + LANES of row y along
    /// direction `n`, folded by max into `best` (lanes past the row end are garbage). `best`
    /// holds a floor on entry (0 for none): pieces that cannot beat it are culled, so a higher
    /// floor known beforehand saves work (values move by their f32 rounding at most; see
    /// `NearField::strip_from`).
    #[allow(clippy::too_many_arguments)] // the strip's place and lane state, hot path
    pub(crate) fn strip(
        &self,
        n: usize,
        d: (f64, f64),
        x: usize,
        y: usize,
        h0: &[f32; LANES],
        count: &[u32; LANES],
        hmax: f32,
        best: &mut [f32; LANES],
    ) {
        match self.isa {
            // SAFETY: `isa` is a variant this CPU supports (detected at construction, or
            // narrower), the one requirement of calling a `#[target_feature]` function.
            #[cfg(target_arch = "x86_64")]
            Isa::Avx512 => unsafe { self.strip_avx512(n, d, x, y, h0, count, hmax, best) },
            #[cfg(target_arch = "x86_64")]
            Isa::Avx2 => unsafe { self.strip_avx2(n, d, x, y, h0, count, hmax, best) },
            _ => self.strip_body(n, d, x, y, h0, count, hmax, best),
        }
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f,avx2,fma")]
    #[allow(clippy::too_many_arguments)] // the strip's place and lane state, hot path
    unsafe fn strip_avx512(
        &self,
        n: usize,
        d: (f64, f64),
        x: usize,
        y: usize,
        h0: &[f32; LANES],
        count: &[u32; LANES],
        hmax: f32,
        best: &mut [f32; LANES],
    ) {
        self.strip_body(n, d, x, y, h0, count, hmax, best);
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    #[allow(clippy::too_many_arguments)] // the strip's place and lane state, hot path
    unsafe fn strip_avx2(
        &self,
        n: usize,
        d: (f64, f64),
        x: usize,
        y: usize,
        h0: &[f32; LANES],
        count: &[u32; LANES],
        hmax: f32,
        best: &mut [f32; LANES],
    ) {
        self.strip_body(n, d, x, y, h0, count, hmax, best);
    }

    /// The vectorised body: per piece, four contiguous loads per lane, a cheap cull against the
    /// best values so far, then the closed-form cell maximum of [`cell_max`] in f32 lanes.
    #[inline(always)]
    #[allow(clippy::too_many_arguments)] // the strip's place and lane state, hot path
    pub(crate) fn strip_body(
        &self,
        n: usize,
        d: (f64, f64),
        x: usize,
        y: usize,
        h0: &[f32; LANES],
        count: &[u32; LANES],
        hmax: f32,
        best: &mut [f32; LANES],
    ) {
        let base_c = (x + self.pad) as i64;
        let base_r = (y + self.pad - self.r0) as i64;
        let cx = Strip {
            n,
            d: (d.0 as f32, d.1 as f32),
            base_c,
            base_r,
            h0,
            count,
            hmax,
            curv: self.curv,
        };
        let spans = &self.spans[n];
        if !self.run(&cx, 0, spans.head, best) {
            return;
        }
        for (coarse, fine) in &spans.coarse {
            if done(&cx, best, coarse.s_start) {
                return;
            }
            if self.culled(&cx, coarse, best) {
                continue;
            }
            if fine.is_empty() {
                if !self.run(&cx, coarse.start, coarse.end, best) {
                    return;
                }
                continue;
            }
            // Fine spans are checked until two in a row fail: on rough ground a box of any
            // size holds something higher than the lowest-horizon lane, and the checks would
            // only add to the pieces' own culls.
            let mut misses = 0;
            for sp in &spans.fine[fine.clone()] {
                if misses < 2 && self.culled(&cx, sp, best) {
                    misses = 0;
                    continue;
                }
                misses += 1;
                if !self.run(&cx, sp.start, sp.end, best) {
                    return;
                }
            }
        }
    }

    /// Whether span `sp` can be culled: no lane's bound beats its best. The box's maximum is
    /// ≥ every corner a piece of the span reads and `s_start` ≤ every piece's s_a, both rounded
    /// alike, so each piece's own cull in [`StripMarch::run`] would have culled it too: skipping the
    /// span changes nothing, not even the last bit.
    #[inline(always)]
    pub(crate) fn culled(&self, cx: &Strip<'_>, sp: &Span, best: &[f32; LANES]) -> bool {
        let c0 = (cx.base_c + sp.c0 as i64) as usize;
        let r0 = (cx.base_r + sp.r0 as i64) as usize;
        let c1 = (cx.base_c + sp.c1 as i64) as usize;
        let r1 = (cx.base_r + sp.r1 as i64) as usize;
        let m = self.blocks.box_max(&self.padded, self.pw, sp.level, (c0, r0, c1, r1));
        let mut any = false;
        for (&h0, &b) in cx.h0.iter().zip(best) {
            any |= m - h0 > b * sp.s_start;
        }
        !any
    }

    /// Pieces `a..b` of the strip's direction one by one, each culled on its own corners or
    /// solved in closed form; false once every lane is done. With the cells' maxima, as
    /// [`StripMarch::run_cells`].
    #[inline(always)]
    pub(crate) fn run(&self, cx: &Strip<'_>, a: usize, b: usize, best: &mut [f32; LANES]) -> bool {
        if self.cells {
            return self.run_cells(cx, a, b, best);
        }
        let (dx, dy) = cx.d;
        let (h0, count) = (cx.h0, cx.count);
        for (k, seg) in self.segs[cx.n].iter().enumerate().take(b).skip(a) {
            let s_b = seg.s_a + seg.len;
            let s_a = seg.s_a as f32;
            if k % 8 == 7 && done(cx, best, s_a) {
                return false;
            }
            let c = (cx.base_c + seg.cxo as i64) as usize;
            let r = (cx.base_r + seg.cyo as i64) as usize;
            let row0 = &self.padded[r * self.pw + c..r * self.pw + c + LANES + 1];
            let row1 = &self.padded[(r + 1) * self.pw + c..(r + 1) * self.pw + c + LANES + 1];
            let mut any = false;
            for i in 0..LANES {
                let m = row0[i].max(row0[i + 1]).max(row1[i]).max(row1[i + 1]);
                any |= m - h0[i] > best[i] * s_a;
            }
            if !any {
                continue;
            }
            let (fx, fy, len) = (seg.fx, seg.fy, seg.len as f32);
            let inv_sb = (1.0 / s_b) as f32;
            let valid = |i: usize| (k as u32) < count[i];
            if seg.s_a == 0.0 {
                let g = (fx, fy, dx, dy, cx.curv);
                piece::<true>(row0, row1, g, s_a, len, inv_sb, h0, valid, best);
            } else {
                let g = (fx, fy, dx, dy, cx.curv);
                piece::<false>(row0, row1, g, s_a, len, inv_sb, h0, valid, best);
            }
        }
        true
    }

    /// [`StripMarch::run`] with the cells' maxima: each piece's cull is one load at the piece's
    /// offset in the padded layout ([`StripMarch::culls`]) and one compare per lane; the piece's
    /// rows are sliced only for the pieces that pass.
    #[inline(always)]
    pub(crate) fn run_cells(
        &self,
        cx: &Strip<'_>,
        a: usize,
        b: usize,
        best: &mut [f32; LANES],
    ) -> bool {
        let (dx, dy) = cx.d;
        let (h0, count) = (cx.h0, cx.count);
        let pw = self.pw;
        let base = (cx.base_r * pw as i64 + cx.base_c) as isize;
        let culls = &self.culls[cx.n][a..b];
        let segs = &self.segs[cx.n][a..b];
        for (j, (&(off, s_a), seg)) in culls.iter().zip(segs).enumerate() {
            let k = a + j;
            if k % 8 == 7 && done(cx, best, s_a) {
                return false;
            }
            let o = (base + off as isize) as usize;
            let m = &self.cmax[o..o + LANES];
            let mut any = false;
            for i in 0..LANES {
                any |= m[i] - h0[i] > best[i] * s_a;
            }
            if !any {
                continue;
            }
            let row0 = &self.padded[o..o + LANES + 1];
            let row1 = &self.padded[o + pw..o + pw + LANES + 1];
            let (fx, fy, len) = (seg.fx, seg.fy, seg.len as f32);
            let inv_sb = (1.0 / (seg.s_a + seg.len)) as f32;
            let valid = |i: usize| (k as u32) < count[i];
            let g = (fx, fy, dx, dy, cx.curv);
            if seg.s_a == 0.0 {
                piece::<true>(row0, row1, g, s_a, len, inv_sb, h0, valid, best);
            } else {
                piece::<false>(row0, row1, g, s_a, len, inv_sb, h0, valid, best);
            }
        }
        true
    }
}

/// A strip's place and lane state, as the near field's helpers need it.
pub(crate) struct Strip<'a> {
    pub(crate) n: usize,
    pub(crate) d: (f32, f32),
    pub(crate) base_c: i64,
    pub(crate) base_r: i64,
    pub(crate) h0: &'a [f32; LANES],
    pub(crate) count: &'a [u32; LANES],
    pub(crate) hmax: f32,
    /// Earth-curvature drop per texel² (0: flat).
    pub(crate) curv: f32,
}

/// All lanes done: nothing left at s ≥ `s_a` can beat any of them.
#[inline(always)]
pub(crate) fn done(cx: &Strip<'_>, best: &[f32; LANES], s_a: f32) -> bool {
    let mut done = true;
    for (&h0, &b) in cx.h0.iter().zip(best) {
        done &= cx.hmax - h0 <= b * s_a;
    }
    done
}

/// `a < b ? a : b`: one `minps`, as [`fmax`].
#[inline(always)]
pub(crate) fn fmin(a: f32, b: f32) -> f32 {
    if a < b {
        a
    } else {
        b
    }
}

/// `a > b ? a : b`: one `maxps`, unlike `f32::max` whose NaN rules cost two more instructions
/// (NaN cannot win here: it only arises in masked-out lanes).
#[inline(always)]
pub(crate) fn fmax(a: f32, b: f32) -> f32 {
    if a > b {
        a
    } else {
        b
    }
}

/// [`cell_max`] for LANES cells side by side in f32, folded into `best`. `FIRST`: the piece
/// starting at the texel itself (a = 0, and the limit s → 0⁺ counts).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
pub(crate) fn piece<const FIRST: bool>(
    row0: &[f32],
    row1: &[f32],
    (fx, fy, dx, dy, curv): (f32, f32, f32, f32, f32),
    s_a: f32,
    len: f32,
    inv_sb: f32,
    h0: &[f32; LANES],
    valid: impl Fn(usize) -> bool,
    best: &mut [f32; LANES],
) {
    let (row0, row1) = (&row0[..LANES + 1], &row1[..LANES + 1]);
    let s_a2 = s_a * s_a;
    let mut out = *best;
    if !FIRST {
        // The end value for every lane first. Then the interior: along the piece the surface
        // is its chord plus a bulge −d2·t·(len − t) ≤ −d2·len²/4, and the chord's ratio is
        // monotone in t, so g ≤ max(g(s_a), g(s_b)) − d2·len²/(4·s_a). Only where that bound
        // can beat the best value, d2 < 0 and the stationary point
        // 0 < N = d1·s_a − a < (s_b² − s_a²)·(−d2) lies inside (g = A/s + B + E·s is concave
        // iff A, E < 0), is the general path with its divisions and square root needed.
        let l2 = (s_a + len) * (s_a + len) - s_a2;
        let (inv_sa, q) = (1.0 / s_a, len * len / (4.0 * s_a));
        let mut interior = false;
        for i in 0..LANES {
            let (k0, k1, k2, k3) = (row0[i], row0[i + 1], row1[i], row1[i + 1]);
            let (bx, by, bxy) = (k1 - k0, k2 - k0, k3 - k1 - k2 + k0);
            let d0 = k0 + bx * fx + by * fy + bxy * fx * fy;
            // The curvature drop c·(s_a + t)² moves the coefficients (as in `cell_max`).
            let d1 = bx * dx + by * dy + bxy * (fx * dy + fy * dx) - 2.0 * curv * s_a;
            let d2 = bxy * dx * dy - curv;
            let a = d0 - h0[i] - curv * s_a2;
            let v = (a + (d1 + d2 * len) * len) * inv_sb;
            let v = if valid(i) { v } else { f32::NEG_INFINITY };
            out[i] = fmax(v, out[i]);
            let nn = d1 * s_a - a;
            let bound = fmax(a * inv_sa, v) - d2 * q;
            // Generous margins: a false positive only costs time.
            interior |= d2 < 0.0
                && nn > -1e-3 * l2 * -d2
                && nn < 1.001 * l2 * -d2
                && bound + 1e-6 * (1.0 + bound.abs()) > out[i]
                && valid(i);
        }
        if !interior {
            *best = out;
            return;
        }
    }
    for i in 0..LANES {
        let (k0, k1, k2, k3) = (row0[i], row0[i + 1], row1[i], row1[i + 1]);
        let bx = k1 - k0;
        let by = k2 - k0;
        let bxy = k3 - k1 - k2 + k0;
        let d1 = bx * dx + by * dy + bxy * (fx * dy + fy * dx) - 2.0 * curv * s_a;
        let d2 = bxy * dx * dy - curv;
        let mut v;
        if FIRST {
            v = fmax((d1 + d2 * len) * len * inv_sb, d1);
        } else {
            let d0 = k0 + bx * fx + by * fy + bxy * fx * fy;
            let a = d0 - h0[i] - curv * s_a2;
            v = (a + (d1 + d2 * len) * len) * inv_sb;
            // Interior critical point; d2 = 0 gives q = ±inf or NaN and fails `ok`.
            let q = s_a2 - (d1 * s_a - a) / d2;
            let dd = fmax(q, 1e-30).sqrt();
            let t = dd - s_a;
            let vi = (a + (d1 + d2 * t) * t) / dd;
            let ok = q > 0.0 && t > 0.0 && t < len;
            v = if ok { fmax(vi, v) } else { v };
        }
        let v = if valid(i) { v } else { f32::NEG_INFINITY };
        out[i] = fmax(v, out[i]);
    }
    *best = out;
}
