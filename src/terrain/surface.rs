//! Surface maps from the same bake (SPEC §3.8): the tangent-space normal, the ambient occlusion
//! and the bent normal an artist imports beside the horizon layers, from the heights and the
//! per-bin horizons the kernels already compute.
//!
//! - [`normal`]: n = normalize(−∂h/∂x, −∂h/∂y, 1) by central differences in texels of the scaled
//!   heights, one-sided at an `edge=none` border, in the tangent frame of SPEC §2 (x = +column,
//!   y as `y_axis` says).
//! - [`occlusion`]: AO = (1/π) ∫ V max(0, n·ω) dω over the directions above the horizontal plane
//!   and the bent normal normalize(∫ V max(0, n·ω) ω dω), V = 1 above the horizon α_k of each
//!   bin. For one azimuth the elevation integral has a closed form (below), so a texel costs a
//!   few operations per bin: the azimuth integral is the midpoint rule over the bake's bins, as
//!   the definition says ("evaluated at the bake's bins azimuths"). [`occlusion`] is that
//!   closed form in f64, bin after bin, the reference; a bake runs [`occlusion_fast`], the same
//!   in f32 eight bins per vector step with no branch, held within 10⁻⁵ of it.
//!
//! With ω = (cos θ cos φ, cos θ sin φ, sin θ) at elevation θ and a = n_z, b = n_x cos φ + n_y sin φ,
//! n·ω = a sin θ + b cos θ and dω = cos θ dθ dφ. The integrand is positive for θ above
//! θ₀ = atan(−b / a) when b < 0 (the normal leans away from φ) and everywhere when b ≥ 0, so per
//! bin the integrals run from θ₁ = max(α, θ₀) to π/2:
//! - AO: ∫ (a sin θ + b cos θ) cos θ dθ = [a sin²θ / 2 + b (θ + sin θ cos θ) / 2];
//! - horizontal part of the bent normal, along (cos φ, sin φ):
//!   ∫ (a sin θ + b cos θ) cos²θ dθ = [−a cos³θ / 3 + b (sin θ − sin³θ / 3)];
//! - vertical part: ∫ (a sin θ + b cos θ) sin θ cos θ dθ = [a sin³θ / 3 − b cos³θ / 3].
//!
//! The oracle beside it (tests) integrates the same definition numerically over elevation, and
//! the tests/ binary holds the maps against an independent quadrature of the exact horizon.

use crate::kernels::isa::Isa;
use crate::kernels::Grid;
use crate::params::{NormalConvention, YAxis};
use std::f64::consts::PI;

/// The unit normal of texel (`x`, `y`) (image column and row) of `grid`, in the tangent frame.
/// Central differences in texel units; at an `edge=none` border, and beside a nodata hole
/// (whose decoder fill is no surface, SPEC §2), the one-sided difference toward the side that
/// is there (slope 0 along an axis with neither).
pub fn normal(grid: &Grid<'_>, holes: Option<&[bool]>, x: usize, y: usize) -> [f64; 3] {
    let (gw, gh) = (grid.width, grid.height);
    if holes.is_none() && x > 0 && y > 0 && x + 1 < gw && y + 1 < gh {
        // Inside the map with no hole: all four neighbours are there, whatever the edge (the
        // same differences as below, without the per-neighbour wrap and lookups).
        let at = |c: usize, r: usize| f64::from(grid.heights[r * gw + c]);
        let (up, down) = if grid.row_step() > 0 { (y + 1, y - 1) } else { (y - 1, y + 1) };
        let dx = (at(x + 1, y) - at(x - 1, y)) * 0.5;
        let dy = (at(x, up) - at(x, down)) * 0.5;
        let len = (dx * dx + dy * dy + 1.0).sqrt();
        return [-dx / len, -dy / len, 1.0 / len];
    }
    let w = grid.width as i64;
    let h = |i: i64, j: i64| {
        let v = grid.at_offset(x, y, i, j)?;
        if let Some(m) = holes {
            let (c, r) = (x as i64 + i, y as i64 + j * grid.row_step());
            let (c, r) = (c.rem_euclid(w), r.rem_euclid(grid.height as i64));
            if m[(r * w + c) as usize] {
                return None;
            }
        }
        Some(f64::from(v))
    };
    let here = grid.heights[y * grid.width + x] as f64;
    let slope = |plus: Option<f64>, minus: Option<f64>| match (plus, minus) {
        (Some(p), Some(m)) => (p - m) * 0.5,
        (Some(p), None) => p - here,
        (None, Some(m)) => here - m,
        (None, None) => 0.0,
    };
    // A wrapped grid always has both neighbours; only `edge=none` misses one at a border.
    let (dx, dy) = (slope(h(1, 0), h(-1, 0)), slope(h(0, 1), h(0, -1)));
    let len = (dx * dx + dy * dy + 1.0).sqrt();
    [-dx / len, -dy / len, 1.0 / len]
}

/// [`normal`] of the `lanes` texels `x0..` of row `y`, when every one of them and its four
/// neighbours lie inside the map and there are no holes: the same f64 operations over the
/// strip at once (so the same bits), into `out`. False, with `out` untouched, when the strip
/// touches a border (the caller takes [`normal`] texel by texel there).
#[inline]
pub fn normals_strip(
    grid: &Grid<'_>,
    x0: usize,
    y: usize,
    lanes: usize,
    out: &mut [[f64; 3]; STRIP],
) -> bool {
    let (gw, gh) = (grid.width, grid.height);
    if lanes != STRIP || x0 == 0 || x0 + STRIP + 1 > gw || y == 0 || y + 1 >= gh {
        return false;
    }
    let (up, down) = if grid.row_step() > 0 { (y + 1, y - 1) } else { (y - 1, y + 1) };
    let row = |r: usize| -> &[f32; STRIP + 2] {
        let s = &grid.heights[r * gw + x0 - 1..][..STRIP + 2];
        s.try_into().expect("a strip and its two neighbours")
    };
    let (here, above, below) = (row(y), row(up), row(down));
    let (mut dx, mut dy) = ([0.0f64; STRIP], [0.0f64; STRIP]);
    for l in 0..STRIP {
        dx[l] = (f64::from(here[l + 2]) - f64::from(here[l])) * 0.5;
        dy[l] = (f64::from(above[l + 1]) - f64::from(below[l + 1])) * 0.5;
    }
    for l in 0..STRIP {
        let len = (dx[l] * dx[l] + dy[l] * dy[l] + 1.0).sqrt();
        out[l] = [-dx[l] / len, -dy[l] / len, 1.0 / len];
    }
    true
}

/// Ambient occlusion and bent normal of one texel.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Occlusion {
    /// In [0, 1]; 1 on an open, flat texel.
    pub ao: f64,
    /// Unit vector in the tangent frame; the normal itself where nothing is visible.
    pub bent: [f64; 3],
}

/// (sin φ_k, cos φ_k) of the `bins` azimuths φ_k = 2πk / bins.
pub fn bin_directions(bins: usize) -> Vec<(f64, f64)> {
    let step = 2.0 * PI / bins.max(1) as f64;
    (0..bins).map(|k| (k as f64 * step).sin_cos()).collect()
}

/// [`Occlusion`] of a texel whose unit normal is `n` and whose horizon at bin k is sin α_k =
/// `s[k]` (clamped to [0, 1], so α ≥ 0), at azimuths φ_k = 2πk / bins from +x toward +y: the
/// closed form in f64, one bin after another. The reference [`occlusion_fast`] (what a bake
/// runs) is held to.
pub fn occlusion(s: &[f32], n: [f64; 3]) -> Occlusion {
    occlusion_with(s, n, &bin_directions(s.len()))
}

/// The bins' directions as [`occlusion_fast`] reads them: cosines and sines of φ_k in f32, in
/// lanes of [`LANES`] (padded with zero-weight bins), computed once per bake.
#[derive(Debug, Clone, PartialEq)]
pub struct BinDirs {
    bins: usize,
    cos: Vec<[f32; LANES]>,
    sin: Vec<[f32; LANES]>,
    /// The compiled variant [`occlusion_fast`] runs (the same IEEE operations in each, so the
    /// same results: no fused multiply-add is formed).
    isa: Isa,
}

/// Bins per step of [`occlusion_fast`]: eight f32 lanes (one AVX register, two SSE ones).
pub const LANES: usize = 8;
// `occlusion_body`'s lane sums are written for eight lanes.
const _: () = assert!(LANES == 8);

impl BinDirs {
    /// The directions of `bins` azimuths φ_k = 2πk / bins.
    pub fn new(bins: usize) -> Self {
        let chunks = bins.div_ceil(LANES);
        let (mut cos, mut sin) = (vec![[0.0; LANES]; chunks], vec![[0.0; LANES]; chunks]);
        for (k, (sk, ck)) in bin_directions(bins).into_iter().enumerate() {
            cos[k / LANES][k % LANES] = ck as f32;
            sin[k / LANES][k % LANES] = sk as f32;
        }
        BinDirs { bins, cos, sin, isa: Isa::detect() }
    }

    /// The same directions, run by the compiled variant `isa` (or the best this CPU has).
    pub fn with_isa(mut self, isa: Isa) -> Self {
        self.isa = isa.or_detected();
        self
    }

    /// How many bins.
    pub fn bins(&self) -> usize {
        self.bins
    }

    /// The compiled variant these directions run.
    pub fn isa(&self) -> Isa {
        self.isa
    }
}

/// asin of x ∈ [0, 1]: Abramowitz & Stegun 4.4.46, π/2 − √(1 − x)·P(x), |error| ≤ 2·10⁻⁸ (in
/// f32 arithmetic about 2·10⁻⁷); exactly π/2 at 1, as the closed form needs. Plain multiply-adds:
/// `mul_add` is a library call on the baseline x86-64 the release binary is built for.
#[inline(always)]
#[allow(clippy::excessive_precision)] // the published coefficients, as printed
fn asin01(x: f32) -> f32 {
    let p = -0.001_262_491_1f32;
    let p = p * x + 0.006_670_090_1;
    let p = p * x - 0.017_088_125_6;
    let p = p * x + 0.030_891_881;
    let p = p * x - 0.050_174_304_6;
    let p = p * x + 0.088_978_987_4;
    let p = p * x - 0.214_598_801_6;
    let p = p * x + 1.570_796_305;
    std::f32::consts::FRAC_PI_2 - (1.0 - x).max(0.0).sqrt() * p
}

/// [`occlusion`] as a bake computes it: the same closed form in f32, eight bins at a time with
/// no branch (each bin's θ₁ picked by a select, asin by [`asin01`]), so the compiler keeps the
/// lanes in vector registers; a bin at or above the zenith contributes 0 by the closed form
/// itself. Within 10⁻⁵ of [`occlusion`] (tested on random texels).
pub fn occlusion_fast(s: &[f32], n: [f64; 3], dirs: &BinDirs) -> Occlusion {
    if s.is_empty() || s.len() != dirs.bins {
        return occlusion(s, n);
    }
    match dirs.isa {
        // SAFETY: `BinDirs` holds only a variant `Isa::detect`/`or_detected` found supported.
        #[cfg(target_arch = "x86_64")]
        Isa::Avx512 | Isa::Avx2 => unsafe { occlusion_avx2(s, n, dirs) },
        _ => occlusion_body(s, n, dirs),
    }
}

/// [`occlusion_body`] compiled for AVX2 (eight lanes in one register, `vsqrtps`): the baseline
/// compiler splits the square roots into scalar ones.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn occlusion_avx2(s: &[f32], n: [f64; 3], dirs: &BinDirs) -> Occlusion {
    occlusion_body(s, n, dirs)
}

const THIRD: f32 = 1.0 / 3.0;

/// One bin's terms of the closed form (see the module doc) in f32, with no branch: the AO
/// integrand's integral from θ₁ = max(α, θ₀) to π/2, and the bent normal's horizontal part
/// (along the bin's direction) and vertical part, for a = n_z, b = n·(cos φ, sin φ, 0) and the
/// horizon `s` = sin α (clamped to [0, 1]; at the zenith every term is 0).
#[inline(always)]
fn bin_terms(a: f32, b: f32, s: f32) -> (f32, f32, f32) {
    let sa = s.clamp(0.0, 1.0);
    let ca = (1.0 - sa * sa).max(0.0).sqrt();
    // One division per bin: the others are multiplications by reciprocals (a vector division
    // costs as much as several of the rest).
    let inv_r = 1.0 / (a * a + b * b).sqrt();
    let s0 = -b * inv_r;
    let below = s0 > sa;
    let st = if below { s0 } else { sa };
    let ct = if below { a * inv_r } else { ca };
    let from = asin01(st);
    let (st2, ct3) = (st * st, ct * ct * ct);
    let st3 = st2 * st;
    let ao =
        a * 0.5 + b * std::f32::consts::FRAC_PI_4 - (a * st2 * 0.5 + b * (from + st * ct) * 0.5);
    let horiz = b * (2.0 / 3.0) - (-a * ct3 * THIRD + b * (st - st3 * THIRD));
    let vert = a * THIRD - (a * st3 * THIRD - b * ct3 * THIRD);
    (ao, horiz, vert)
}

#[inline(always)]
fn occlusion_body(s: &[f32], n: [f64; 3], dirs: &BinDirs) -> Occlusion {
    let bins = s.len();
    let (nx, ny, a) = (n[0] as f32, n[1] as f32, n[2] as f32);
    let (mut ao, mut bx, mut by, mut bz) =
        ([0.0f32; LANES], [0.0; LANES], [0.0; LANES], [0.0; LANES]);
    let mut lane = [0.0f32; LANES];
    for (c, (cos, sin)) in dirs.cos.iter().zip(&dirs.sin).enumerate() {
        let part = &s[c * LANES..bins.min((c + 1) * LANES)];
        lane[..part.len()].copy_from_slice(part);
        // A padding bin gets the zenith (1): it contributes 0.
        lane[part.len()..].fill(1.0);
        for l in 0..LANES {
            let (cp, sp) = (cos[l], sin[l]);
            let b = nx * cp + ny * sp;
            let (o, horiz, vert) = bin_terms(a, b, lane[l]);
            ao[l] += o;
            bx[l] += horiz * cp;
            by[l] += horiz * sp;
            bz[l] += vert;
        }
    }
    // The lanes summed pairwise in f32 (a tree of three vector adds): eight sequential f64
    // additions per sum cost more than a chunk of bins.
    let sum = |v: [f32; LANES]| {
        let q = [v[0] + v[4], v[1] + v[5], v[2] + v[6], v[3] + v[7]];
        f64::from((q[0] + q[2]) + (q[1] + q[3]))
    };
    let step = 2.0 * PI / bins as f64;
    let ao = (sum(ao) * step / PI).clamp(0.0, 1.0);
    let (bx, by, bz) = (sum(bx), sum(by), sum(bz));
    let len = (bx * bx + by * by + bz * bz).sqrt();
    let bent = if len > 1e-9 { [bx / len, by / len, bz / len] } else { n };
    Occlusion { ao, bent }
}

/// Texels per call of [`occlusion_strip`]: sixteen f32 lanes (one AVX-512 register, two AVX2
/// ones).
pub const STRIP: usize = 16;

/// Normals of a strip of [`STRIP`] texels, by component (f32, as the closed form takes them).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct StripNormals {
    pub x: [f32; STRIP],
    pub y: [f32; STRIP],
    pub z: [f32; STRIP],
}

/// [`occlusion_fast`] of the first `lanes` texels of a strip at once, one lane per texel and
/// the bins one after another, so nothing is summed across lanes and the per-texel tail (the
/// AO's scale, the bent normal's length) is vector work too: what a bake runs over a row.
/// `s` holds their horizons texel-major (`s[l·bins + k]`, `lanes · bins` values), `n` their
/// unit normals; into `ao` and `bent` (unit vectors; the normal itself where nothing is
/// visible). Lanes past `lanes` are left unspecified. The same closed form and f32 operations
/// as [`occlusion_fast`] but for the order of the sums (bin after bin here), so within 10⁻⁵ of
/// [`occlusion`] too (tested).
pub fn occlusion_strip(
    s: &[f32],
    lanes: usize,
    n: &StripNormals,
    dirs: &BinDirs,
    ao: &mut [f32; STRIP],
    bent: &mut StripNormals,
) {
    let lanes = lanes.min(STRIP);
    if lanes == 0 || s.len() < lanes * dirs.bins {
        return;
    }
    match dirs.isa {
        // SAFETY: `BinDirs` holds only a variant `Isa::detect`/`or_detected` found supported.
        #[cfg(target_arch = "x86_64")]
        Isa::Avx512 => unsafe { strip_avx512(s, lanes, n, dirs, ao, bent) },
        #[cfg(target_arch = "x86_64")]
        Isa::Avx2 => unsafe { strip_avx2(s, lanes, n, dirs, ao, bent) },
        _ => strip_body(s, lanes, n, dirs, ao, bent),
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn strip_avx512(
    s: &[f32],
    lanes: usize,
    n: &StripNormals,
    dirs: &BinDirs,
    ao: &mut [f32; STRIP],
    bent: &mut StripNormals,
) {
    strip_body(s, lanes, n, dirs, ao, bent);
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn strip_avx2(
    s: &[f32],
    lanes: usize,
    n: &StripNormals,
    dirs: &BinDirs,
    ao: &mut [f32; STRIP],
    bent: &mut StripNormals,
) {
    strip_body(s, lanes, n, dirs, ao, bent);
}

/// Bins per block of [`strip_body`]'s transposed horizons.
const BLOCK: usize = 8;

#[inline(always)]
fn strip_body(
    s: &[f32],
    lanes: usize,
    n: &StripNormals,
    dirs: &BinDirs,
    ao_out: &mut [f32; STRIP],
    bent: &mut StripNormals,
) {
    let bins = dirs.bins;
    let (nx, ny, a) = (&n.x, &n.y, &n.z);
    let (mut ao, mut bx, mut by, mut bz) =
        ([0.0f32; STRIP], [0.0f32; STRIP], [0.0f32; STRIP], [0.0f32; STRIP]);
    // A block of bins transposed to lanes (`tile[k][l]`: texel l's bin k0 + k), so the lanes
    // load as one vector; lanes past `lanes` repeat the last texel (their results are unused).
    let mut tile = [[0.0f32; STRIP]; BLOCK];
    for k0 in (0..bins).step_by(BLOCK) {
        let kn = BLOCK.min(bins - k0);
        for l in 0..STRIP {
            let t = &s[l.min(lanes - 1) * bins + k0..][..kn];
            for (k, &v) in t.iter().enumerate() {
                tile[k][l] = v;
            }
        }
        for (k, row) in tile.iter().enumerate().take(kn) {
            let (cp, sp) = (
                dirs.cos[(k0 + k) / LANES][(k0 + k) % LANES],
                dirs.sin[(k0 + k) / LANES][(k0 + k) % LANES],
            );
            for l in 0..STRIP {
                let b = nx[l] * cp + ny[l] * sp;
                let (o, horiz, vert) = bin_terms(a[l], b, row[l]);
                ao[l] += o;
                bx[l] += horiz * cp;
                by[l] += horiz * sp;
                bz[l] += vert;
            }
        }
    }
    let scale = (2.0 / bins as f64) as f32;
    for l in 0..STRIP {
        ao_out[l] = (ao[l] * scale).clamp(0.0, 1.0);
        let len = (bx[l] * bx[l] + by[l] * by[l] + bz[l] * bz[l]).sqrt();
        let keep = len > 1e-9;
        let inv = if keep { 1.0 / len } else { 0.0 };
        bent.x[l] = if keep { bx[l] * inv } else { nx[l] };
        bent.y[l] = if keep { by[l] * inv } else { ny[l] };
        bent.z[l] = if keep { bz[l] * inv } else { a[l] };
    }
}

/// [`occlusion`] with the bins' directions given ([`bin_directions`] of `s.len()`).
pub fn occlusion_with(s: &[f32], n: [f64; 3], dirs: &[(f64, f64)]) -> Occlusion {
    let bins = s.len();
    if bins == 0 {
        return Occlusion { ao: 1.0, bent: n };
    }
    let a = n[2];
    let (mut ao, mut bx, mut by, mut bz) = (0.0, 0.0, 0.0, 0.0);
    let step = 2.0 * PI / bins as f64;
    for (&sk, &(sin_phi, cos_phi)) in s.iter().zip(dirs) {
        let b = n[0] * cos_phi + n[1] * sin_phi;
        // θ₁ = max(α, θ₀), both in [0, π/2]: compared by their sines, so only the larger one's
        // angle is taken (for the AO's θ term).
        let sa = (sk as f64).clamp(0.0, 1.0);
        let (st, ct) = if b < 0.0 {
            let r = (a * a + b * b).sqrt();
            let s0 = -b / r;
            if s0 > sa {
                (s0, a / r)
            } else {
                (sa, (1.0 - sa * sa).max(0.0).sqrt())
            }
        } else {
            (sa, (1.0 - sa * sa).max(0.0).sqrt())
        };
        if st >= 1.0 {
            continue;
        }
        let from = st.asin();
        // Each antiderivative at π/2 minus its value at θ₁.
        ao += a * 0.5 + b * PI * 0.25 - (a * st * st * 0.5 + b * (from + st * ct) * 0.5);
        let horiz = b * (2.0 / 3.0) - (-a * ct * ct * ct / 3.0 + b * (st - st * st * st / 3.0));
        let vert = a / 3.0 - (a * st * st * st / 3.0 - b * ct * ct * ct / 3.0);
        bx += horiz * cos_phi;
        by += horiz * sin_phi;
        bz += vert;
    }
    let ao = (ao * step / PI).clamp(0.0, 1.0);
    let len = (bx * bx + by * by + bz * bz).sqrt();
    let bent = if len > 1e-12 { [bx / len, by / len, bz / len] } else { n };
    Occlusion { ao, bent }
}

/// Whether the stored y is the tangent frame's y negated: `normal_convention` names the
/// direction of the stored y in the image, whatever `y_axis` (SPEC §2) made the frame: `opengl`
/// (Y+) up the image, `directx` (Y−) down it. So `y_axis=up` with `opengl`, and `y_axis=down`
/// with `directx`, store the frame's y as it is.
pub fn flips_y(y_axis: YAxis, convention: NormalConvention) -> bool {
    (y_axis == YAxis::Up) != (convention == NormalConvention::OpenGl)
}

/// A unit vector's components in [−1, 1] as bytes: floor(((v + 1) / 2)·255 + 0.5), y negated
/// when `flip_y` ([`flips_y`]). 0 sits exactly on a rounding tie (127.5 + 0.5), so a component
/// within 1e-6 of it (what the f32 sums over symmetric azimuths leave of a flat texel's bent
/// normal; 1e-6 is 0.0001 of a level) is 0: flat is 128, 128, 255 whichever way the last bit
/// fell.
#[inline]
pub fn encode_unit(v: [f64; 3], flip_y: bool) -> [u8; 3] {
    let y = if flip_y { -v[1] } else { v[1] };
    // The value is ≥ 0.5 here, so truncation is floor (and needs no libm call).
    [v[0], y, v[2]].map(|c| {
        let c = if c.abs() < 1e-6 { 0.0 } else { c.clamp(-1.0, 1.0) };
        (((c + 1.0) * 0.5) * 255.0 + 0.5) as u8
    })
}

/// A value in [0, 1] as a byte: floor(v·255 + 0.5) (truncation: the value is ≥ 0.5).
#[inline]
pub fn encode_unorm(v: f64) -> u8 {
    (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8
}

/// What [`encode_unit`] quantises, unquantised: ((v + 1) / 2) per component in [0, 1], y
/// negated when `flip_y`, a component within 1e-6 of 0 taken as 0 (so flat is exactly 0.5,
/// 0.5, 1). The 16-bit PNG and EXR surface maps hold these (SPEC §3.8: formats as the layers).
#[inline]
pub fn unit_values(v: [f64; 3], flip_y: bool) -> [f32; 3] {
    let y = if flip_y { -v[1] } else { v[1] };
    [v[0], y, v[2]].map(|c| {
        let c = if c.abs() < 1e-6 { 0.0 } else { c.clamp(-1.0, 1.0) };
        ((c + 1.0) * 0.5) as f32
    })
}

/// A value in [0, 1] as a 16-bit sample: floor(v·65535 + 0.5), SPEC §2's 16-bit rule.
#[inline]
pub fn encode_unorm16(v: f32) -> u16 {
    (f64::from(v).clamp(0.0, 1.0) * 65535.0 + 0.5) as u16
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::params::Edge;
    use std::f64::consts::FRAC_PI_2;

    /// The definition integrated numerically: for each bin, the midpoint rule over elevation
    /// with `steps` steps of V(θ > α) max(0, n·ω) cos θ (and ω times it).
    fn oracle(s: &[f32], n: [f64; 3], steps: usize) -> (f64, [f64; 3]) {
        let bins = s.len();
        let dphi = 2.0 * PI / bins as f64;
        let dth = FRAC_PI_2 / steps as f64;
        let (mut ao, mut v) = (0.0, [0.0; 3]);
        for (k, &sk) in s.iter().enumerate() {
            let phi = k as f64 * dphi;
            let alpha = (sk as f64).clamp(0.0, 1.0).asin();
            for i in 0..steps {
                let th = (i as f64 + 0.5) * dth;
                if th <= alpha {
                    continue;
                }
                let w = [th.cos() * phi.cos(), th.cos() * phi.sin(), th.sin()];
                let d = (n[0] * w[0] + n[1] * w[1] + n[2] * w[2]).max(0.0);
                let m = d * th.cos() * dth * dphi;
                ao += m;
                for c in 0..3 {
                    v[c] += m * w[c];
                }
            }
        }
        let len = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        (ao / PI, v.map(|c| c / len))
    }

    /// Uniform values in [0, 1) from a xorshift64 generator seeded with `seed`.
    fn xorshift(mut seed: u64) -> impl FnMut() -> f64 {
        move || {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            (seed >> 11) as f64 / (1u64 << 53) as f64
        }
    }

    fn unit(v: [f64; 3]) -> [f64; 3] {
        let l = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        v.map(|c| c / l)
    }

    #[test]
    fn open_flat_texel_is_unoccluded_and_bends_nowhere() {
        let o = occlusion(&[0.0; 32], [0.0, 0.0, 1.0]);
        assert!((o.ao - 1.0).abs() < 1e-12, "{o:?}");
        assert!(
            o.bent[0].abs() < 1e-12 && o.bent[1].abs() < 1e-12 && (o.bent[2] - 1.0).abs() < 1e-12
        );
    }

    #[test]
    fn a_uniform_horizon_on_a_flat_texel_is_cos_squared() {
        // AO of a flat texel under a horizon α at every azimuth: ∫_α^{π/2} sin θ cos θ dθ · 2 =
        // cos² α (the radiative sky-view factor).
        let alpha = 30f64.to_radians();
        let o = occlusion(&[alpha.sin() as f32; 16], [0.0, 0.0, 1.0]);
        assert!((o.ao - alpha.cos().powi(2)).abs() < 1e-6, "{o:?}");
    }

    #[test]
    fn closed_form_matches_the_numerical_integral_on_random_texels() {
        let mut rnd = xorshift(0x9e37_79b9_7f4a_7c15);
        for case in 0..200 {
            let bins = [8, 16, 32, 64][case % 4];
            let s: Vec<f32> = (0..bins).map(|_| (rnd() * rnd()) as f32).collect();
            // Normals up to ~70° from vertical, some with the horizon below their tangent plane.
            let n = unit([rnd() * 4.0 - 2.0, rnd() * 4.0 - 2.0, 0.7 + rnd()]);
            let o = occlusion(&s, n);
            // The midpoint rule steps over the kink at α and θ₀: within π/40000 per bin.
            let (ao, bent) = oracle(&s, n, 20_000);
            assert!((o.ao - ao).abs() < 1e-4, "case {case}: ao {} vs {ao}", o.ao);
            for c in 0..3 {
                assert!(
                    (o.bent[c] - bent[c]).abs() < 2e-4,
                    "case {case}: {:?} vs {bent:?}",
                    o.bent
                );
            }
        }
    }

    #[test]
    fn the_fast_occlusion_is_the_closed_form() {
        let mut rnd = xorshift(0x2545_f491_4f6c_dd1d);
        for case in 0..2000 {
            let bins = [8, 12, 16, 32, 64, 360][case % 6];
            let dirs = BinDirs::new(bins);
            // Horizons from open to the zenith (s = 1), normals up to ~75° from vertical.
            let s: Vec<f32> = (0..bins)
                .map(|_| if rnd() < 0.05 { 1.0 } else { (rnd() * rnd()) as f32 })
                .collect();
            let n = unit([rnd() * 6.0 - 3.0, rnd() * 6.0 - 3.0, 0.8 + rnd()]);
            let (fast, slow) = (occlusion_fast(&s, n, &dirs), occlusion(&s, n));
            let base = occlusion_fast(&s, n, &dirs.clone().with_isa(Isa::Baseline));
            assert_eq!(fast, base, "case {case}: the compiled variants differ");
            assert!((fast.ao - slow.ao).abs() < 1e-5, "case {case}: {fast:?} vs {slow:?}");
            for c in 0..3 {
                assert!(
                    (fast.bent[c] - slow.bent[c]).abs() < 1e-5,
                    "case {case}: {fast:?} vs {slow:?}"
                );
            }
        }
        // asin01 against the library's asin over [0, 1].
        for i in 0..=10_000 {
            let x = i as f32 / 10_000.0;
            assert!((asin01(x) - x.asin()).abs() < 1e-6, "{x}");
        }
        assert_eq!(asin01(1.0), std::f32::consts::FRAC_PI_2);
        let flat = occlusion_fast(&[0.0; 32], [0.0, 0.0, 1.0], &BinDirs::new(32));
        assert_eq!(encode_unit(flat.bent, false), [128, 128, 255]);
        assert_eq!(encode_unorm(flat.ao), 255);
    }

    /// The strip of texels is the closed form too, every compiled variant alike, with any
    /// number of lanes.
    #[test]
    fn the_strip_occlusion_is_the_closed_form() {
        let mut rnd = xorshift(0x9e37_79b9_7f4a_7c15);
        for case in 0..300 {
            let bins = [8, 12, 16, 32, 64, 360, 7][case % 7];
            let lanes = 1 + case % STRIP;
            let dirs = BinDirs::new(bins);
            let s: Vec<f32> = (0..bins * lanes)
                .map(|_| if rnd() < 0.05 { 1.0 } else { (rnd() * rnd()) as f32 })
                .collect();
            let mut n = StripNormals::default();
            let mut ns = Vec::new();
            for l in 0..lanes {
                let v = unit([rnd() * 6.0 - 3.0, rnd() * 6.0 - 3.0, 0.8 + rnd()]);
                (n.x[l], n.y[l], n.z[l]) = (v[0] as f32, v[1] as f32, v[2] as f32);
                ns.push(v);
            }
            let mut results = Vec::new();
            for isa in [Isa::detect(), Isa::Avx2.or_detected(), Isa::Baseline] {
                let (mut ao, mut bent) = ([0.0; STRIP], StripNormals::default());
                occlusion_strip(&s, lanes, &n, &dirs.clone().with_isa(isa), &mut ao, &mut bent);
                for l in 0..lanes {
                    let slow = occlusion(&s[l * bins..(l + 1) * bins], ns[l]);
                    assert!((f64::from(ao[l]) - slow.ao).abs() < 1e-5, "case {case} lane {l}");
                    let got = [bent.x[l], bent.y[l], bent.z[l]];
                    for c in 0..3 {
                        let d = (f64::from(got[c]) - slow.bent[c]).abs();
                        assert!(d < 1e-5, "case {case} lane {l}: {got:?} vs {slow:?}");
                    }
                }
                results.push((ao[..lanes].to_vec(), bent.x[..lanes].to_vec()));
            }
            assert!(results.windows(2).all(|w| w[0] == w[1]), "case {case}: variants differ");
        }
        // Flat and open: AO 1, the bent normal straight up, exactly as the bytes need.
        let (mut ao, mut bent) = ([0.0; STRIP], StripNormals::default());
        let up = StripNormals { z: [1.0; STRIP], ..Default::default() };
        occlusion_strip(&[0.0; 32 * 3], 3, &up, &BinDirs::new(32), &mut ao, &mut bent);
        let b = [f64::from(bent.x[2]), f64::from(bent.y[2]), f64::from(bent.z[2])];
        assert_eq!((encode_unit(b, false), encode_unorm(f64::from(ao[2]))), ([128, 128, 255], 255));
    }

    /// The strip's normals are [`normal`]'s, bit for bit, and it declines at the borders.
    #[test]
    fn strip_normals_are_the_texel_normals() {
        let mut rnd = xorshift(99);
        let (w, h) = (40, 7);
        let hs: Vec<f32> = (0..w * h).map(|_| (rnd() * 30.0) as f32).collect();
        for y_axis in [YAxis::Up, YAxis::Down] {
            let grid = Grid::new(w, h, &hs, Edge::Wrap, y_axis);
            let mut out = [[0.0; 3]; STRIP];
            for y in 0..h {
                for x0 in 0..w - STRIP + 1 {
                    let inside = x0 > 0 && x0 + STRIP < w && y > 0 && y + 1 < h;
                    assert_eq!(normals_strip(&grid, x0, y, STRIP, &mut out), inside, "{x0} {y}");
                    if inside {
                        for (l, n) in out.iter().enumerate() {
                            assert_eq!(*n, normal(&grid, None, x0 + l, y), "{x0} {y} {l}");
                        }
                    }
                }
            }
            assert!(!normals_strip(&grid, 1, 1, STRIP - 1, &mut out), "a short strip");
        }
    }

    #[test]
    fn normals_by_central_and_one_sided_differences() {
        // h = 2·col + 3·row: ∂h/∂x = 2; tangent +y is up the image (row − 1) with y_axis=up, so
        // ∂h/∂y = −3 there and +3 with y_axis=down.
        let (w, h) = (5, 4);
        let heights: Vec<f32> = (0..w * h).map(|i| (2 * (i % w) + 3 * (i / w)) as f32).collect();
        for (y_axis, dy) in [(YAxis::Up, -3.0), (YAxis::Down, 3.0)] {
            let grid = Grid::new(w, h, &heights, Edge::None, y_axis);
            let want = unit([-2.0, -dy, 1.0]);
            for (x, y) in [(2, 1), (0, 0), (4, 3), (0, 3)] {
                let n = normal(&grid, None, x, y);
                for c in 0..3 {
                    assert!((n[c] - want[c]).abs() < 1e-12, "{y_axis:?} ({x},{y}): {n:?}");
                }
            }
        }
        // Wrapped, the border differences reach across: a ramp 0..4 wraps from 4 back to 0.
        let ramp: Vec<f32> = (0..5).map(|i| i as f32).collect();
        let grid = Grid::new(5, 1, &ramp, Edge::Wrap, YAxis::Up);
        // Beside a hole the difference is one-sided, as at a border: the hole at column 1
        // leaves (h(0) − h(4)) = −4 toward −x only.
        let holes = [false, true, false, false, false];
        let n = normal(&grid, Some(&holes), 0, 0);
        assert!((n[0] - unit([4.0, 0.0, 1.0])[0]).abs() < 1e-12, "{n:?}");
        let n = normal(&grid, None, 0, 0);
        // (h(1) − h(4)) / 2 = −1.5.
        assert!((n[0] - unit([1.5, 0.0, 1.0])[0]).abs() < 1e-12, "{n:?}");
    }

    #[test]
    fn conventions_round_trip() {
        let v = unit([0.3, -0.5, 0.8]);
        let gl = encode_unit(v, flips_y(YAxis::Up, NormalConvention::OpenGl));
        let dx = encode_unit(v, flips_y(YAxis::Up, NormalConvention::DirectX));
        // A frame already pointing down the image is DirectX's as it is.
        assert!(!flips_y(YAxis::Down, NormalConvention::DirectX));
        assert!(flips_y(YAxis::Down, NormalConvention::OpenGl));
        assert_eq!((gl[0], gl[2]), (dx[0], dx[2]));
        let decode = |b: u8| b as f64 / 255.0 * 2.0 - 1.0;
        assert!((decode(gl[1]) - v[1]).abs() <= 1.0 / 255.0);
        assert!((decode(dx[1]) + v[1]).abs() <= 1.0 / 255.0);
        assert_eq!(encode_unit([0.0, 0.0, 1.0], false), [128, 128, 255]);
        assert_eq!(encode_unit([-1e-7, 1e-7, 1.0], true), [128, 128, 255]);
        assert_eq!(encode_unorm(1.0), 255);
        assert_eq!(encode_unorm(0.5), 128);
    }

    /// The 16-bit and float maps hold what the bytes quantise: the byte of each value is the
    /// byte [`encode_unit`] writes, and the 16-bit sample is SPEC §2's floor(v·65535 + 0.5).
    #[test]
    fn values_are_what_the_bytes_quantise() {
        let mut rnd = xorshift(7);
        for _ in 0..2000 {
            let v = unit([rnd() * 2.0 - 1.0, rnd() * 2.0 - 1.0, rnd()]);
            for flip in [false, true] {
                let f = unit_values(v, flip);
                let b = encode_unit(v, flip);
                for c in 0..3 {
                    // The same rounding from the f32 value, but at a tie the f64 decides.
                    let from_f = (f64::from(f[c]) * 255.0 + 0.5).floor();
                    assert!((from_f - f64::from(b[c])).abs() <= 1.0, "{v:?} {c}");
                    let want = (f64::from(f[c]) * 65535.0 + 0.5).floor() as u16;
                    assert_eq!(encode_unorm16(f[c]), want);
                }
            }
        }
        assert_eq!(unit_values([1e-7, -1e-7, 1.0], true), [0.5, 0.5, 1.0]);
        assert_eq!(encode_unorm16(0.5), 32768);
        assert_eq!(encode_unorm16(1.0), 65535);
        assert_eq!(encode_unorm16(-0.1), 0);
    }
}
