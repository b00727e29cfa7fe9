//! Shading kernels for the CPU preview (SPEC §3.3, §3.5): the illumination factor, GPU-style
//! texture and cube-map sampling, normals, and the ground-truth shadow ray.
//!
//! The preview must show what a shader will show, so the horizon path decodes exactly what a GPU
//! is given: the 8- or 16-bit layers sampled bilinearly (wrap = REPEAT, none = CLAMP_TO_EDGE), the
//! channel-factor cube map as UNORM8 texels filtered bilinearly and seamlessly across faces (as
//! WebGL2, Direct3D 11+ and Vulkan always do), decoded f = t·2 − 1 — so a stored 128 gives
//! +1/255, not 0, exactly the UNORM zero offset a shader sees. Bilinear weights are f32
//! (real GPUs quantise them to ~8 bits; that difference is below one output LSB).
//!
//! The ground truth is a ray on the bilinear surface h̃ through the texel centres (SPEC §3.2),
//! traced cell by cell: along a straight line through one cell, h̃ is a quadratic in the distance
//! S, so (h̃(S) − h0)/S = A/S + B + c·S has its maximum over the cell at an end or at
//! S* = √(A/c): three evaluations per cell give the exact supremum, no step size involved. The
//! march stops as soon as no farther texel could change the answer ((h_max − h0)/S below the best
//! tangent found), which makes high lights cheap whatever the radius, and it jumps over whole
//! 8×8-cell blocks whose maximum cannot beat the best tangent from the nearest point still ahead
//! (low lights on peaks and ridges, where the first rule alone marched to the radius). Radius is unlimited as
//! SPEC §3.2 defines it: max(W, H) texels when wrapping; with `edge=none` the surface ends at the
//! outermost texel centres and the ray stops there.

use super::cubemap;
use super::Grid;
use crate::params::Edge;
use rayon::prelude::*;

/// Default `hardness` k of the soft shadow edge (Lengyel eq. 5.4).
pub const DEFAULT_HARDNESS: f64 = 8.0;

/// The illumination factor F = clamp(k·(L_z − s) + 1, 0, 1); 0 for a light at or below the
/// tangent plane (SPEC §3.3).
#[inline]
pub fn illumination(lz: f64, s: f64, hardness: f64) -> f64 {
    if lz.is_nan() || lz <= 0.0 {
        return 0.0;
    }
    let f = hardness * (lz - s) + 1.0;
    if f.is_nan() {
        return 0.0;
    }
    f.clamp(0.0, 1.0)
}

/// Lengyel eq. 5.3: s = Σ max(f,0)·h0 + max(−f,0)·h1 over the 4 slots.
#[inline]
pub fn horizon_s(f: [f32; 4], h0: [f32; 4], h1: [f32; 4]) -> f32 {
    let mut s = 0.0f32;
    for i in 0..4 {
        s += f[i].max(0.0) * h0[i] + (-f[i]).max(0.0) * h1[i];
    }
    s
}

/// Stored samples of a texture, normalised on fetch (v/255 or v/65535) as UNORM formats are.
#[derive(Debug, Clone, Copy)]
pub enum Samples<'a> {
    U8(&'a [u8]),
    U16(&'a [u16]),
}

/// An interleaved UNORM texture sampled like a GPU does.
#[derive(Debug, Clone, Copy)]
pub struct Texture<'a> {
    pub width: usize,
    pub height: usize,
    pub channels: usize,
    pub samples: Samples<'a>,
    /// REPEAT (true) or CLAMP_TO_EDGE (false).
    pub wrap: bool,
}

impl Texture<'_> {
    #[inline]
    fn index(&self, x: i64, y: i64) -> usize {
        let (w, h) = (self.width as i64, self.height as i64);
        let (x, y) = if self.wrap {
            (x.rem_euclid(w), y.rem_euclid(h))
        } else {
            (x.clamp(0, w - 1), y.clamp(0, h - 1))
        };
        (y * w + x) as usize * self.channels
    }

    #[inline]
    fn fetch(&self, i: usize) -> f32 {
        match self.samples {
            Samples::U8(s) => s[i] as f32 / 255.0,
            Samples::U16(s) => s[i] as f32 / 65535.0,
        }
    }

    /// Bilinear sample at texel coordinates (`x`, `y`) — texel (i, j)'s centre is at (i, j), i.e.
    /// the GPU's uv·size − ½ — into `out` (`channels` values, at most 4).
    #[inline]
    pub fn sample(&self, x: f64, y: f64, out: &mut [f32; 4]) {
        let (x0, y0) = (x.floor(), y.floor());
        let (fx, fy) = ((x - x0) as f32, (y - y0) as f32);
        let (xi, yi) = (x0 as i64, y0 as i64);
        let i00 = self.index(xi, yi);
        let i10 = self.index(xi + 1, yi);
        let i01 = self.index(xi, yi + 1);
        let i11 = self.index(xi + 1, yi + 1);
        for (c, o) in out.iter_mut().enumerate().take(self.channels.min(4)) {
            let a = self.fetch(i00 + c) + (self.fetch(i10 + c) - self.fetch(i00 + c)) * fx;
            let b = self.fetch(i01 + c) + (self.fetch(i11 + c) - self.fetch(i01 + c)) * fx;
            *o = a + (b - a) * fy;
        }
    }
}

/// The channel-factor cube map as a shader receives it: UNORM8 texels (SPEC §2), filtered
/// seamlessly across faces (SPEC §3.5).
///
/// Each face is kept with a one-texel border taken from its neighbours, so a bilinear footprint
/// that crosses an edge reads the adjacent face's texels, as WebGL2, Direct3D 11+ and Vulkan
/// always filter cube maps. A border texel is the neighbour-face texel its centre falls in when
/// the face's plane is continued past the edge (less than half a texel from that texel's centre,
/// so it is the texel along the shared edge that the GL rule names). A corner of the border has
/// no unique neighbour: it is the mean of the three texels that exist, the rule the GL ES 3.0
/// specification recommends (§3.8.9.1) and SwiftShader follows.
#[derive(Debug, Clone)]
pub struct CubeMap {
    size: usize,
    /// `6 · (size + 2)² · 4` decoded UNORM values t ∈ [0, 1], faces +X, −X, +Y, −Y, +Z, −Z, each
    /// with its border; bordered row 1 = face row 0 = t = −1.
    texels: Vec<f32>,
}

impl CubeMap {
    /// The cube map the bake writes at `size` (≥ 1) texels per side, quantised to UNORM8.
    pub fn new(size: usize) -> Self {
        let n = size.max(1);
        // Shared per size: every preview of one size reuses the same table.
        let unorm: Vec<u8> =
            cubemap::cube_factors_shared(n).iter().map(|&f| cubemap::unorm8(f)).collect();
        let b = n + 2;
        let mut texels = vec![0.0f32; 6 * b * b * 4];
        let inside = |face: usize, u: usize, v: usize| ((face * n + v) * n + u) * 4;
        for face in 0..6 {
            for bv in 0..b {
                for bu in 0..b {
                    let (u, v) = (bu as i64 - 1, bv as i64 - 1);
                    let out_u = u < 0 || u >= n as i64;
                    let out_v = v < 0 || v >= n as i64;
                    if out_u && out_v {
                        continue; // corners below, once the edges are in
                    }
                    let src = if !out_u && !out_v {
                        inside(face, u as usize, v as usize)
                    } else {
                        let sc = 2.0 * (u as f64 + 0.5) / n as f64 - 1.0;
                        let tc = 2.0 * (v as f64 + 0.5) / n as f64 - 1.0;
                        let (f2, s, t) =
                            cubemap::select_face(cubemap::face_direction(face, sc, tc));
                        let pick = |c: f64| ((c * n as f64).floor() as i64).clamp(0, n as i64 - 1);
                        inside(f2, pick(s) as usize, pick(t) as usize)
                    };
                    let dst = ((face * b + bv) * b + bu) * 4;
                    for c in 0..4 {
                        texels[dst + c] = unorm[src + c] as f32 / 255.0;
                    }
                }
            }
            // Each corner: the mean of the three texels of its footprint that exist.
            for (cu, cv, du, dv) in
                [(0, 0, 1i64, 1i64), (b - 1, 0, -1, 1), (0, b - 1, 1, -1), (b - 1, b - 1, -1, -1)]
            {
                let at = |u: usize, v: usize| ((face * b + v) * b + u) * 4;
                let nu = (cu as i64 + du) as usize;
                let nv = (cv as i64 + dv) as usize;
                let (a, e, d) = (at(nu, cv), at(cu, nv), at(nu, nv));
                for c in 0..4 {
                    texels[at(cu, cv) + c] = (texels[a + c] + texels[e + c] + texels[d + c]) / 3.0;
                }
            }
        }
        CubeMap { size: n, texels }
    }

    /// Face size in texels.
    pub fn size(&self) -> usize {
        self.size
    }

    /// The signed factors for tangent-space direction `d` (need not be normalised, must not be
    /// zero): bilinear, seamless across faces, decoded f = t·2 − 1.
    #[inline]
    pub fn factors(&self, d: [f64; 3]) -> [f32; 4] {
        let (face, s, t) = cubemap::select_face(d);
        let n = self.size;
        let b = n + 2;
        // Texel coordinates in the bordered face: the face's texel 0 is bordered texel 1.
        let x = (s * n as f64 - 0.5).clamp(-0.5, n as f64 - 0.5) + 1.0;
        let y = (t * n as f64 - 0.5).clamp(-0.5, n as f64 - 0.5) + 1.0;
        let (x0, y0) = (x.floor(), y.floor());
        let (fx, fy) = ((x - x0) as f32, (y - y0) as f32);
        let (xi, yi) = ((x0 as usize).min(b - 2), (y0 as usize).min(b - 2));
        let at = |u: usize, v: usize| ((face * b + v) * b + u) * 4;
        let (i00, i10, i01, i11) = (at(xi, yi), at(xi + 1, yi), at(xi, yi + 1), at(xi + 1, yi + 1));
        let mut f = [0.0f32; 4];
        for (c, o) in f.iter_mut().enumerate() {
            let g = |i: usize| self.texels[i + c];
            let a = g(i00) + (g(i10) - g(i00)) * fx;
            let e = g(i01) + (g(i11) - g(i01)) * fx;
            *o = (a + (e - a) * fy) * 2.0 - 1.0;
        }
        f
    }
}

/// Per-texel unit normals (`W·H·3`, tangent space) by central differences in texel units of the
/// heights in `grid` (neighbours wrapped or clamped per `edge`).
pub fn normals(grid: &Grid<'_>) -> Vec<f32> {
    let (w, h) = (grid.width, grid.height);
    let step = grid.row_step();
    let mut out = vec![0.0f32; w * h * 3];
    if w == 0 || h == 0 {
        return out;
    }
    let at = |c: i64, r: i64| -> f64 {
        let (c, r) = match grid.edge {
            Edge::Wrap => (c.rem_euclid(w as i64), r.rem_euclid(h as i64)),
            Edge::None => (c.clamp(0, w as i64 - 1), r.clamp(0, h as i64 - 1)),
        };
        grid.heights[r as usize * w + c as usize] as f64
    };
    out.par_chunks_mut(w * 3).enumerate().for_each(|(r, row)| {
        let r = r as i64;
        for (c, n) in row.chunks_exact_mut(3).enumerate() {
            let c = c as i64;
            let dx = (at(c + 1, r) - at(c - 1, r)) * 0.5;
            let dy = (at(c, r + step) - at(c, r - step)) * 0.5;
            let len = (dx * dx + dy * dy + 1.0).sqrt();
            n[0] = (-dx / len) as f32;
            n[1] = (-dy / len) as f32;
            n[2] = (1.0 / len) as f32;
        }
    });
    out
}

/// Cells per side of the blocks whose maximum lets a ray skip terrain that cannot matter.
const BLOCK: i64 = 8;

/// The bilinear height surface h̃ of a grid, for ground-truth shadow rays.
#[derive(Debug, Clone)]
pub struct Surface<'a> {
    grid: Grid<'a>,
    hmax: f64,
    /// Blocks of BLOCK×BLOCK cells (cell (i, j) spans texel centres i..i+1, j..j+1): the
    /// maximum of every corner height of the block's cells, `bw × bh` of them.
    block_max: Vec<f32>,
    bw: usize,
}

impl<'a> Surface<'a> {
    /// Wraps `grid` (computes its maximum and the block maxima once, O(W·H)).
    pub fn new(grid: Grid<'a>) -> Self {
        let (_, hi) = grid.range();
        let (w, h) = (grid.width as i64, grid.height as i64);
        let bw = (w.max(1) + BLOCK - 1) / BLOCK;
        let bh = (h.max(1) + BLOCK - 1) / BLOCK;
        let mut block_max = vec![f32::NEG_INFINITY; (bw * bh) as usize];
        let mut s = Surface { grid, hmax: hi as f64, block_max: Vec::new(), bw: bw as usize };
        for by in 0..bh {
            for bx in 0..bw {
                let mut m = f32::NEG_INFINITY;
                for r in by * BLOCK..=((by + 1) * BLOCK).min(h) {
                    for c in bx * BLOCK..=((bx + 1) * BLOCK).min(w) {
                        m = m.max(s.corner(c, r) as f32);
                    }
                }
                block_max[(by * bw + bx) as usize] = m;
            }
        }
        s.block_max = block_max;
        s
    }

    /// The block holding (unwrapped) cell (`ix`, `ir`): its maximum and its cell rectangle in
    /// the same unwrapped coordinates as the cell (x_lo, x_hi, r_lo, r_hi).
    #[inline]
    fn block_of(&self, ix: i64, ir: i64) -> (f64, [i64; 4]) {
        let (w, h) = (self.grid.width as i64, self.grid.height as i64);
        let wrapped = |i: i64, n: i64| match self.grid.edge {
            Edge::Wrap => i.rem_euclid(n),
            Edge::None => i.clamp(0, n - 1),
        };
        let (cx, cr) = (wrapped(ix, w), wrapped(ir, h));
        let (bx, by) = (cx / BLOCK, cr / BLOCK);
        let x_lo = ix - (cx - bx * BLOCK);
        let r_lo = ir - (cr - by * BLOCK);
        let x_len = BLOCK.min(w - bx * BLOCK).max(1);
        let r_len = BLOCK.min(h - by * BLOCK).max(1);
        let m = self.block_max[(by as usize) * self.bw + bx as usize] as f64;
        (m, [x_lo, x_lo + x_len, r_lo, r_lo + r_len])
    }

    /// The grid.
    pub fn grid(&self) -> &Grid<'a> {
        &self.grid
    }

    #[inline]
    fn corner(&self, c: i64, r: i64) -> f64 {
        let (w, h) = (self.grid.width as i64, self.grid.height as i64);
        let (c, r) = match self.grid.edge {
            Edge::Wrap => (c.rem_euclid(w), r.rem_euclid(h)),
            Edge::None => (c.clamp(0, w - 1), r.clamp(0, h - 1)),
        };
        self.grid.heights[(r * w + c) as usize] as f64
    }

    /// h̃ at image coordinates (`x` = column, `r` = row; integers are texel centres).
    #[inline]
    pub fn height(&self, x: f64, r: f64) -> f64 {
        let (x0, r0) = (x.floor(), r.floor());
        let (fx, fr) = (x - x0, r - r0);
        let (c, rr) = (x0 as i64, r0 as i64);
        let a = self.corner(c, rr) + (self.corner(c + 1, rr) - self.corner(c, rr)) * fx;
        let b = self.corner(c, rr + 1) + (self.corner(c + 1, rr + 1) - self.corner(c, rr + 1)) * fx;
        a + (b - a) * fr
    }

    /// The image-plane direction (columns, rows) of tangent-space (`tx`, `ty`).
    #[inline]
    pub fn image_dir(&self, tx: f64, ty: f64) -> (f64, f64) {
        (tx, ty * self.grid.row_step() as f64)
    }

    /// Brings a point into the domain of the surface: wrapped into the map, or clamped to the
    /// rectangle of texel centres with `edge=none`.
    #[inline]
    pub fn canonical(&self, x: f64, r: f64) -> (f64, f64) {
        let (w, h) = (self.grid.width as f64, self.grid.height as f64);
        match self.grid.edge {
            Edge::Wrap => (x.rem_euclid(w), r.rem_euclid(h)),
            Edge::None => (x.clamp(0.0, w - 1.0), r.clamp(0.0, h - 1.0)),
        }
    }

    /// How far a ray from (`px`, `pr`) along the unit image direction (`dx`, `dr`) may go:
    /// max(W, H) when wrapping, to the rectangle of texel centres otherwise.
    fn ray_limit(&self, px: f64, pr: f64, dx: f64, dr: f64) -> f64 {
        let (w, h) = (self.grid.width as f64, self.grid.height as f64);
        match self.grid.edge {
            Edge::Wrap => w.max(h),
            Edge::None => {
                let exit = |p: f64, d: f64, hi: f64| -> f64 {
                    if d > 0.0 {
                        (hi - p) / d
                    } else if d < 0.0 {
                        -p / d
                    } else {
                        f64::INFINITY
                    }
                };
                exit(px, dx, w - 1.0).min(exit(pr, dr, h - 1.0)).max(0.0)
            }
        }
    }

    /// The largest tangent of elevation sup over 0 < S ≤ limit of (h̃(p + S·d) − h̃(p)) / S seen
    /// from (`px`, `pr`) along the unit image direction (`dx`, `dr`), but never below `floor`.
    /// Stops early once the answer exceeds `ceiling` (then it is only known to be > `ceiling`).
    /// Exact per cell (see the module doc); `floor` ≥ 0 lets it stop early.
    pub fn horizon_tan(&self, px: f64, pr: f64, dx: f64, dr: f64, floor: f64, ceiling: f64) -> f64 {
        // Directions built from degrees carry ~1e-16 residues (cos 90°); snapping them keeps a
        // ray along a 1-texel-wide strip on the strip instead of leaving it at once.
        let snap = |d: f64| if d.abs() < 1e-12 { 0.0 } else { d };
        let (dx, dr) = (snap(dx), snap(dr));
        let (px, pr) = self.canonical(px, pr);
        let limit = self.ray_limit(px, pr, dx, dr);
        let z0 = self.height(px, pr);
        let headroom = self.hmax - z0;
        let mut best = floor;
        let cell = |p: f64, d: f64| -> f64 {
            let i = p.floor();
            if d < 0.0 && i == p {
                i - 1.0
            } else {
                i
            }
        };
        let (mut ix, mut ir) = (cell(px, dx), cell(pr, dr));
        let sx = if dx > 0.0 { 1.0 } else { -1.0 };
        let sr = if dr > 0.0 { 1.0 } else { -1.0 };
        let next = |i: f64, p: f64, d: f64| -> f64 {
            if d > 0.0 {
                (i + 1.0 - p) / d
            } else if d < 0.0 {
                (i - p) / d
            } else {
                f64::INFINITY
            }
        };
        let (mut tx, mut tr) = (next(ix, px, dx), next(ir, pr, dr));
        let (tdx, tdr) = (1.0 / dx.abs(), 1.0 / dr.abs());
        let mut s_in = 0.0f64;
        let mut skipped: Option<[i64; 4]> = None;
        while s_in < limit {
            if s_in > 0.0 && headroom <= best * s_in {
                break;
            }
            // Nothing in this block can beat `best` if even its highest corner, seen from the
            // nearest distance still ahead, is no steeper: jump to where the ray leaves it.
            if s_in > 0.0 {
                let (m, rect) = self.block_of(ix as i64, ir as i64);
                if m - z0 <= best * s_in && skipped != Some(rect) {
                    let exit = |p: f64, d: f64, lo: i64, hi: i64| -> f64 {
                        if d > 0.0 {
                            (hi as f64 - p) / d
                        } else if d < 0.0 {
                            (lo as f64 - p) / d
                        } else {
                            f64::INFINITY
                        }
                    };
                    let s_exit = exit(px, dx, rect[0], rect[1]).min(exit(pr, dr, rect[2], rect[3]));
                    if s_exit > s_in {
                        skipped = Some(rect);
                        s_in = s_exit;
                        if s_in >= limit {
                            break;
                        }
                        let (qx, qr) = (px + dx * s_in, pr + dr * s_in);
                        ix = cell(qx, dx);
                        ir = cell(qr, dr);
                        tx = s_in + next(ix, qx, dx);
                        tr = s_in + next(ir, qr, dr);
                        // Rounding may leave the point a hair inside the skipped block; then
                        // its remaining cells are simply processed (exactly) below.
                        continue;
                    }
                }
            }
            let s_out = tx.min(tr).min(limit);
            let (c, r) = (ix as i64, ir as i64);
            let h00 = self.corner(c, r);
            let h10 = self.corner(c + 1, r);
            let h01 = self.corner(c, r + 1);
            let h11 = self.corner(c + 1, r + 1);
            let fx = (px + dx * s_in - ix).clamp(0.0, 1.0);
            let fr = (pr + dr * s_in - ir).clamp(0.0, 1.0);
            let d = h00 - h10 - h01 + h11;
            // h̃(s_in + σ) = a + bσ + cσ².
            let a = h00 + (h10 - h00) * fx + (h01 - h00) * fr + d * fx * fr;
            let b = (h10 - h00 + d * fr) * dx + (h01 - h00 + d * fx) * dr;
            let cq = d * dx * dr;
            let len = s_out - s_in;
            if s_out > 0.0 {
                let g = (a + (b + cq * len) * len - z0) / s_out;
                best = best.max(g);
            }
            if s_in == 0.0 {
                // S → 0+: the directional derivative at p.
                best = best.max(b);
            } else if cq != 0.0 {
                let big_a = (a - z0) - b * s_in + cq * s_in * s_in;
                let q = big_a / cq;
                if q > 0.0 {
                    let st = q.sqrt();
                    if st > s_in && st < s_out {
                        let sg = st - s_in;
                        best = best.max((a + (b + cq * sg) * sg - z0) / st);
                    }
                }
            }
            if best > ceiling || s_out >= limit {
                break;
            }
            if tx < tr {
                ix += sx;
                s_in = tx;
                tx += tdx;
            } else {
                ir += sr;
                s_in = tr;
                tr += tdr;
            }
        }
        best
    }

    /// Whether the surface point under (`px`, `pr`) is in shadow for tangent-space light `l`
    /// (unit): the ray toward the light is blocked, i.e. the horizon is strictly above it.
    pub fn shadowed(&self, px: f64, pr: f64, l: [f64; 3]) -> bool {
        if l[2].is_nan() || l[2] <= 0.0 {
            return true;
        }
        let hl = (l[0] * l[0] + l[1] * l[1]).sqrt();
        if hl == 0.0 {
            return false;
        }
        let tan_l = l[2] / hl;
        let (dx, dr) = self.image_dir(l[0] / hl, l[1] / hl);
        self.horizon_tan(px, pr, dx, dr, tan_l, tan_l) > tan_l
    }

    /// The ground-truth horizon value s = sin α at the light's azimuth, clamped to
    /// [L_z, L_z + 1/k] — exactly what F = clamp(k·(L_z − s) + 1, 0, 1) needs, and much cheaper
    /// than the full horizon (the ray stops once the answer is decided).
    pub fn horizon_sin_for_light(&self, px: f64, pr: f64, l: [f64; 3], hardness: f64) -> f64 {
        let lz = l[2];
        let hl = (l[0] * l[0] + l[1] * l[1]).sqrt();
        if lz.is_nan() || lz <= 0.0 || hl == 0.0 {
            return lz.max(0.0);
        }
        let sin_to_tan = |s: f64| {
            if s >= 1.0 {
                f64::INFINITY
            } else {
                s / (1.0 - s * s).sqrt()
            }
        };
        let floor = sin_to_tan(lz);
        let ceiling = sin_to_tan(lz + 1.0 / hardness.max(1e-9));
        let (dx, dr) = self.image_dir(l[0] / hl, l[1] / hl);
        let t = self.horizon_tan(px, pr, dx, dr, floor, ceiling);
        if t.is_infinite() {
            1.0
        } else {
            t / (1.0 + t * t).sqrt()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::params::YAxis;

    #[test]
    fn illumination_formula() {
        assert_eq!(illumination(0.5, 0.2, 8.0), 1.0);
        assert!((illumination(0.5, 0.55, 8.0) - 0.6).abs() < 1e-12);
        assert_eq!(illumination(0.5, 0.7, 8.0), 0.0);
        assert_eq!(illumination(0.0, 0.0, 8.0), 0.0);
        assert_eq!(illumination(-0.1, 0.0, 8.0), 0.0);
    }

    #[test]
    fn cube_zero_offset_is_reproduced() {
        // Light along +x: channel 0 only, slot 0 = +1 → 255; the other slots store 0 → 128,
        // which decodes to +1/255 and so picks up 1/255 of layer 0's value in those slots.
        // An odd face size puts a texel centre exactly on +x, so no filtering is involved.
        let cube = CubeMap::new(15);
        let f = cube.factors([1.0, 0.0, 0.0]);
        assert!((f[0] - 1.0).abs() < 1e-6, "{f:?}");
        for v in &f[1..] {
            assert!((v - 1.0 / 255.0).abs() < 1e-6, "{f:?}");
        }
        let s = horizon_s(f, [0.0, 1.0, 0.0, 0.0], [0.0; 4]);
        assert!((s - 1.0 / 255.0).abs() < 1e-6);
        // With an even size +x falls between four texels and bilinear filtering blends in the
        // neighbouring channels' factors (channel 7 negated in slot 3), as a GPU does.
        let f = CubeMap::new(16).factors([1.0, 0.0, 0.0]);
        assert!(f[0] > 0.9 && f[1] > 0.0 && f[3] < 0.0, "{f:?}");
    }

    /// The UNORM8 value of texel (u, v) of `face`, decoded to t ∈ [0, 1] (the oracle's fetch).
    fn stored(size: usize, face: usize, u: usize, v: usize) -> [f32; 4] {
        let f = cubemap::factors_for_direction(cubemap::texel_direction(face, u, v, size));
        f.map(|x| cubemap::unorm8(x) as f32 / 255.0)
    }

    #[test]
    fn cube_filtering_is_seamless_across_faces() {
        // On the seam between +X and +Y (azimuth 45°), GL's seamless rule blends the texels of
        // both faces along the shared edge, half of each at the seam itself. Clamping within a
        // face read one face's texels only, and the value jumped across the seam.
        let n = 16;
        let cube = CubeMap::new(n);
        for e_deg in [3.0f64, 15.0, 30.0] {
            let e = e_deg.to_radians();
            let at = |a_deg: f64| {
                let a = a_deg.to_radians();
                cube.factors([e.cos() * a.cos(), e.cos() * a.sin(), e.sin()])
            };
            let (below, above) = (at(45.0 - 1e-9), at(45.0 + 1e-9));
            for (b, a) in below.iter().zip(&above) {
                assert!((b - a).abs() < 1e-5, "e={e_deg}: {below:?} vs {above:?}");
            }
            // Oracle from the face table alone. At azimuth 45° the direction lies on +X's edge
            // tc = −y/x = −1 (its row 0), which +X shares with +Y's edge sc = x/y = 1 (its column
            // n−1); +X's sc = −z/x is +Y's tc = z/y negated, so +X column u meets +Y row n−1−u.
            // The footprint straddles the seam: half +X row 0, half that +Y texel.
            let d =
                [e.cos() * 45f64.to_radians().cos(), e.cos() * 45f64.to_radians().sin(), e.sin()];
            let sc = -d[2] / d[0];
            let x = 0.5 * (sc + 1.0) * n as f64 - 0.5;
            let (u0, fx) = (x.floor() as usize, (x - x.floor()) as f32);
            let want: Vec<f32> = (0..4)
                .map(|c| {
                    let col = |u: usize| {
                        0.5 * stored(n, 0, u, 0)[c] + 0.5 * stored(n, 2, n - 1, n - 1 - u)[c]
                    };
                    (col(u0) + (col(u0 + 1) - col(u0)) * fx) * 2.0 - 1.0
                })
                .collect();
            for (a, w) in above.iter().zip(&want) {
                assert!((a - w).abs() < 1e-5, "e={e_deg}: {above:?} vs {want:?}");
            }
        }
        // Away from every edge nothing changes: the four texels of the face's own footprint.
        let f = cube.factors([1.0, 0.1, 0.05]);
        let (face, s, t) = cubemap::select_face([1.0, 0.1, 0.05]);
        let (x, y) = (s * n as f64 - 0.5, t * n as f64 - 0.5);
        let (u, v) = (x.floor() as usize, y.floor() as usize);
        let (fx, fy) = ((x - x.floor()) as f32, (y - y.floor()) as f32);
        for (c, fc) in f.iter().enumerate() {
            let g = |u, v| stored(n, face, u, v)[c];
            let a = g(u, v) + (g(u + 1, v) - g(u, v)) * fx;
            let b = g(u, v + 1) + (g(u + 1, v + 1) - g(u, v + 1)) * fx;
            assert!(((a + (b - a) * fy) * 2.0 - 1.0 - fc).abs() < 1e-6);
        }
        // A corner: the mean of the three texels that exist, so the cube stays continuous there.
        let c3 = 1.0 / 3f64.sqrt();
        let (p, q) = (cube.factors([c3, c3 + 1e-9, c3]), cube.factors([c3 + 1e-9, c3, c3]));
        for (pc, qc) in p.iter().zip(&q) {
            assert!((pc - qc).abs() < 1e-5, "{p:?} vs {q:?}");
        }
    }

    #[test]
    fn texture_bilinear_and_edges() {
        let data = [0u8, 255, 51, 102]; // 2×2 gray
        let wrap =
            Texture { width: 2, height: 2, channels: 1, samples: Samples::U8(&data), wrap: true };
        let clamp = Texture { wrap: false, ..wrap };
        let mut o = [0.0f32; 4];
        wrap.sample(0.5, 0.0, &mut o);
        assert!((o[0] - 0.5).abs() < 1e-6);
        wrap.sample(1.5, 0.0, &mut o); // halfway between texel 1 and texel 0 (wrapped)
        assert!((o[0] - 0.5).abs() < 1e-6);
        clamp.sample(1.5, 0.0, &mut o); // clamped: texel 1
        assert!((o[0] - 1.0).abs() < 1e-6);
        clamp.sample(0.0, 0.5, &mut o);
        assert!((o[0] - 0.1).abs() < 1e-6);
    }

    #[test]
    fn wall_ray_is_exact() {
        // A wall of height 2 at column 4 of a 9×1 strip (edge=none): from column 0 along +x the
        // tangent is max over the ramp 3→4 ((2·(S−3))/S, max 2/4 at S=4).
        let mut h = vec![0.0f32; 9];
        h[4] = 2.0;
        let g = Grid::new(9, 1, &h, Edge::None, YAxis::Up);
        let s = Surface::new(g);
        let t = s.horizon_tan(0.0, 0.0, 1.0, 0.0, 0.0, f64::INFINITY);
        assert!((t - 0.5).abs() < 1e-12, "{t}");
        // Looking −x from column 0 there is nothing.
        assert_eq!(s.horizon_tan(0.0, 0.0, -1.0, 0.0, 0.0, f64::INFINITY), 0.0);
        // Light at 26° from +x: tan 0.4877 < 0.5 → shadowed; at 27° (0.5095) lit.
        let l = |deg: f64| [deg.to_radians().cos(), 0.0, deg.to_radians().sin()];
        assert!(s.shadowed(0.0, 0.0, l(26.0)));
        assert!(!s.shadowed(0.0, 0.0, l(27.0)));
    }

    #[test]
    fn diagonal_ray_finds_interior_maximum() {
        // One raised corner in a 2×2 cell: h̃ = 4·fx·fr; along the diagonal from (0,0) the
        // surface is 4S²/2 = 2S², so (h̃ − 0)/S = 2S, max at the far corner S = √2 → 2√2.
        let h = vec![0.0f32, 0.0, 0.0, 4.0];
        let g = Grid::new(2, 2, &h, Edge::None, YAxis::Down);
        let s = Surface::new(g);
        let r = std::f64::consts::FRAC_1_SQRT_2;
        let t = s.horizon_tan(0.0, 0.0, r, r, 0.0, f64::INFINITY);
        assert!((t - 2.0 * 2f64.sqrt()).abs() < 1e-9, "{t}");
    }

    #[test]
    fn normals_of_a_ramp() {
        // Heights rise by 1 per column: ∂h/∂x = 1 → n = (−1, 0, 1)/√2 away from the wrap seam.
        let h: Vec<f32> = (0..5 * 3).map(|k| (k % 5) as f32).collect();
        let g = Grid::new(5, 3, &h, Edge::None, YAxis::Up);
        let n = normals(&g);
        let k = (5 + 2) * 3;
        assert!((n[k] + std::f32::consts::FRAC_1_SQRT_2).abs() < 1e-6);
        assert!(n[k + 1].abs() < 1e-6);
        // Rows rising downward: with y up, +y is toward smaller rows, so ∂h/∂y < 0 → n_y > 0.
        let h: Vec<f32> = (0..3 * 5).map(|k| (k / 3) as f32).collect();
        let up = normals(&Grid::new(3, 5, &h, Edge::None, YAxis::Up));
        let down = normals(&Grid::new(3, 5, &h, Edge::None, YAxis::Down));
        let k = (2 * 3 + 1) * 3 + 1;
        assert!(up[k] > 0.5 && down[k] < -0.5, "{} {}", up[k], down[k]);
    }
}
