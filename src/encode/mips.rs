//! Mip filters (SPEC §8 `mip_filter`): one level of a mip chain from the level above, as pure
//! functions over RGBA slices.
//!
//! A level of `w × h` texels has a child of `max(1, w/2) × max(1, h/2)` (the size rule of every
//! GPU API, rounding down). Child texel (x, y) reads the 2×2 parent texels (2x + i, 2y + j),
//! i, j ∈ {0, 1}, each coordinate clamped to the parent (so a parent 1 texel wide or high is read
//! twice; of an odd parent the last row or column is not read, as with every API's floor rule):
//! - `box`: the mean of the four, per channel. Integer samples round half up:
//!   floor((a + b + c + d + 2) / 4); floats are (a + b + c + d) / 4.
//! - `min` / `max`: the smallest / largest of the four, per channel.
//! - `rebake`: not a filter of the stored samples: each level is baked again from the heights,
//!   box-filtered to its size by [`box_heights`] (the mean of the 2×2 parent heights, level by
//!   level, in f32), with the radius halved per level (see `pipeline::rebake_levels`). Images
//!   that come from no heights (the cube map's faces) are box-filtered under `rebake`.
//!
//! The filters work on the stored samples (what a GPU's own mip generation would average), so a
//! chain of 8-bit layers is filtered in 8 bits and block-compressed formats are filtered before
//! compression. Rows of the child are independent: they run on rayon, one row per task chunk.

use rayon::prelude::*;

/// How a mip level is made from the level above (SPEC §8).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum MipFilter {
    /// Mean of the stored values over the 2×2 parent texels.
    #[default]
    Box,
    /// Smallest of the 2×2 parent texels (never raises a horizon: shadows stay).
    Min,
    /// Largest of the 2×2 parent texels (never lowers a horizon).
    Max,
    /// Each level baked again from the heights box-filtered to its size, the radius halved per
    /// level (SPEC §8); see the module doc.
    Rebake,
}

impl MipFilter {
    /// The spelling in parameters and flags.
    pub fn name(self) -> &'static str {
        match self {
            MipFilter::Box => "box",
            MipFilter::Min => "min",
            MipFilter::Max => "max",
            MipFilter::Rebake => "rebake",
        }
    }

    /// Parses `box`, `min`, `max` or `rebake`.
    ///
    /// # Errors
    /// [`crate::Error::Param`] naming `mip_filter`.
    pub fn parse(value: &str) -> crate::Result<Self> {
        match value.trim().to_ascii_lowercase().as_str() {
            "box" => Ok(MipFilter::Box),
            "min" => Ok(MipFilter::Min),
            "max" => Ok(MipFilter::Max),
            "rebake" => Ok(MipFilter::Rebake),
            _ => Err(crate::Error::param(
                "mip_filter",
                format!("`{value}` is not one of box, min, max, rebake"),
            )),
        }
    }
}

/// A sample type the filters work on.
pub trait Sample: Copy + Send + Sync + PartialOrd + 'static {
    /// The mean of four samples, rounded as the module doc says.
    fn mean4(a: Self, b: Self, c: Self, d: Self) -> Self;
}

impl Sample for u8 {
    fn mean4(a: u8, b: u8, c: u8, d: u8) -> u8 {
        ((a as u32 + b as u32 + c as u32 + d as u32 + 2) / 4) as u8
    }
}

impl Sample for u16 {
    fn mean4(a: u16, b: u16, c: u16, d: u16) -> u16 {
        ((a as u32 + b as u32 + c as u32 + d as u32 + 2) / 4) as u16
    }
}

impl Sample for i8 {
    fn mean4(a: i8, b: i8, c: i8, d: i8) -> i8 {
        (a as i32 + b as i32 + c as i32 + d as i32 + 2).div_euclid(4) as i8
    }
}

impl Sample for f32 {
    fn mean4(a: f32, b: f32, c: f32, d: f32) -> f32 {
        (a + b + c + d) * 0.25
    }
}

/// Width or height of the level below one of `n` texels.
pub fn next_size(n: usize) -> usize {
    (n / 2).max(1)
}

/// Number of levels of a full chain down to 1×1: floor(log2(max(w, h))) + 1.
pub fn full_levels(width: usize, height: usize) -> usize {
    let m = width.max(height).max(1);
    (usize::BITS - m.leading_zeros()) as usize
}

fn min2<T: PartialOrd>(a: T, b: T) -> T {
    if b < a {
        b
    } else {
        a
    }
}

fn max2<T: PartialOrd>(a: T, b: T) -> T {
    if b > a {
        b
    } else {
        a
    }
}

/// Fills `dst` (`next_size(sw) × next_size(sh)` RGBA texels) from `src` (`sw × sh` RGBA) with
/// `filter` (`rebake` is `box` here: stored samples carry no heights to bake again).
///
/// # Panics
/// When the slice lengths do not match the sizes (a caller's bug).
pub fn downsample<T: Sample>(src: &[T], sw: usize, sh: usize, filter: MipFilter, dst: &mut [T]) {
    match filter {
        MipFilter::Box | MipFilter::Rebake => reduce(src, sw, sh, dst, T::mean4),
        MipFilter::Min => reduce(src, sw, sh, dst, |a, b, c, d| min2(min2(a, b), min2(c, d))),
        MipFilter::Max => reduce(src, sw, sh, dst, |a, b, c, d| max2(max2(a, b), max2(c, d))),
    }
}

fn reduce<T: Sample>(
    src: &[T],
    sw: usize,
    sh: usize,
    dst: &mut [T],
    f: impl Fn(T, T, T, T) -> T + Sync,
) {
    let (dw, dh) = (next_size(sw), next_size(sh));
    assert_eq!(src.len(), sw * sh * 4, "parent level size");
    assert_eq!(dst.len(), dw * dh * 4, "child level size");
    let row_len = sw * 4;
    dst.par_chunks_mut(dw * 4).enumerate().for_each(|(y, out)| {
        let r0 = &src[(2 * y).min(sh - 1) * row_len..][..row_len];
        let r1 = &src[(2 * y + 1).min(sh - 1) * row_len..][..row_len];
        for (x, texel) in out.chunks_exact_mut(4).enumerate() {
            let x0 = (2 * x).min(sw - 1) * 4;
            let x1 = (2 * x + 1).min(sw - 1) * 4;
            for (c, v) in texel.iter_mut().enumerate() {
                *v = f(r0[x0 + c], r0[x1 + c], r1[x0 + c], r1[x1 + c]);
            }
        }
    });
}

/// The heights of the level below a `sw × sh` map: `next_size(sw) × next_size(sh)` values,
/// each the mean of the 2×2 parent heights read as [`downsample`] reads texels (coordinates
/// clamped, the floor rule for odd sizes), summed in f64 and rounded once to f32.
///
/// # Panics
/// When `src` is not `sw × sh` values (a caller's bug).
pub fn box_heights(src: &[f32], sw: usize, sh: usize) -> Vec<f32> {
    let (dw, dh) = (next_size(sw), next_size(sh));
    assert_eq!(src.len(), sw * sh, "parent heights");
    let mut dst = vec![0f32; dw * dh];
    dst.par_chunks_mut(dw).enumerate().for_each(|(y, out)| {
        let r0 = &src[(2 * y).min(sh - 1) * sw..][..sw];
        let r1 = &src[(2 * y + 1).min(sh - 1) * sw..][..sw];
        for (x, v) in out.iter_mut().enumerate() {
            let (x0, x1) = ((2 * x).min(sw - 1), (2 * x + 1).min(sw - 1));
            let sum = r0[x0] as f64 + r0[x1] as f64 + r1[x0] as f64 + r1[x1] as f64;
            *v = (sum * 0.25) as f32;
        }
    });
    dst
}

/// The hole mask of the level below a `sw × sh` mask: a texel is a hole when any of its 2×2
/// parents is (its box-filtered height mixes in the fill far below the map).
///
/// # Panics
/// When `src` is not `sw × sh` values (a caller's bug).
pub fn any_holes(src: &[bool], sw: usize, sh: usize) -> Vec<bool> {
    let (dw, dh) = (next_size(sw), next_size(sh));
    assert_eq!(src.len(), sw * sh, "parent mask");
    let mut dst = vec![false; dw * dh];
    for (y, out) in dst.chunks_mut(dw).enumerate() {
        let (y0, y1) = ((2 * y).min(sh - 1), (2 * y + 1).min(sh - 1));
        for (x, v) in out.iter_mut().enumerate() {
            let (x0, x1) = ((2 * x).min(sw - 1), (2 * x + 1).min(sw - 1));
            *v = src[y0 * sw + x0] || src[y0 * sw + x1] || src[y1 * sw + x0] || src[y1 * sw + x1];
        }
    }
    dst
}

/// The levels below `level0` (`width × height` RGBA), each from the one above: `levels − 1`
/// images, largest first. `keep_going` is asked before each level (cancellation).
///
/// # Errors
/// [`crate::Error::Canceled`] when `keep_going` says no.
pub fn chain<T: Sample + Default>(
    width: usize,
    height: usize,
    level0: &[T],
    filter: MipFilter,
    levels: usize,
    keep_going: &dyn Fn() -> bool,
) -> crate::Result<Vec<Vec<T>>> {
    let mut out: Vec<Vec<T>> = Vec::with_capacity(levels.saturating_sub(1));
    let (mut w, mut h) = (width, height);
    for _ in 1..levels {
        if !keep_going() {
            return Err(crate::Error::Canceled);
        }
        let (dw, dh) = (next_size(w), next_size(h));
        let mut next = vec![T::default(); dw * dh * 4];
        downsample(out.last().map_or(level0, Vec::as_slice), w, h, filter, &mut next);
        out.push(next);
        (w, h) = (dw, dh);
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The oracle: every child texel from its definition, in f64, one at a time.
    fn naive(src: &[f64], sw: usize, sh: usize, filter: MipFilter, int: bool) -> Vec<f64> {
        let (dw, dh) = (next_size(sw), next_size(sh));
        let mut out = Vec::new();
        for y in 0..dh {
            for x in 0..dw {
                for c in 0..4 {
                    let mut v = Vec::new();
                    for j in 0..2 {
                        for i in 0..2 {
                            let (px, py) = ((2 * x + i).min(sw - 1), (2 * y + j).min(sh - 1));
                            v.push(src[(py * sw + px) * 4 + c]);
                        }
                    }
                    out.push(match filter {
                        MipFilter::Box | MipFilter::Rebake if int => {
                            ((v.iter().sum::<f64>() + 2.0) / 4.0).floor()
                        }
                        MipFilter::Box | MipFilter::Rebake => v.iter().sum::<f64>() / 4.0,
                        MipFilter::Min => v.iter().copied().fold(f64::INFINITY, f64::min),
                        MipFilter::Max => v.iter().copied().fold(f64::NEG_INFINITY, f64::max),
                    });
                }
            }
        }
        out
    }

    fn lcg(seed: &mut u64) -> u64 {
        *seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        *seed >> 33
    }

    #[test]
    fn literal_texels() {
        // 2×2 → 1×1: R of the four texels 0, 1, 2, 4 → box (7+2)/4 = 2, min 0, max 4.
        let mut src = [0u8; 16];
        for (k, r) in [0u8, 1, 2, 4].into_iter().enumerate() {
            src[k * 4] = r;
            src[k * 4 + 3] = 255;
        }
        let mut dst = [0u8; 4];
        downsample(&src, 2, 2, MipFilter::Box, &mut dst);
        assert_eq!(dst, [2, 0, 0, 255]);
        downsample(&src, 2, 2, MipFilter::Min, &mut dst);
        assert_eq!(dst[0], 0);
        downsample(&src, 2, 2, MipFilter::Max, &mut dst);
        assert_eq!(dst[0], 4);
        // i8 rounds half up: (−1 −1 0 0 + 2)/4 = 0, (−3 −3 −3 −2 + 2)/4 = −2.25 → −3.
        assert_eq!(i8::mean4(-1, -1, 0, 0), 0);
        assert_eq!(i8::mean4(-3, -3, -3, -2), -3);
        assert_eq!(u8::mean4(255, 255, 255, 254), 255);
        assert_eq!(u16::mean4(65535, 65535, 65535, 65535), 65535);
        assert_eq!(full_levels(1, 1), 1);
        assert_eq!(full_levels(2048, 2048), 12);
        assert_eq!(full_levels(13, 5), 4);
    }

    #[test]
    fn filters_match_the_oracle_on_random_sizes() {
        let mut seed = 3u64;
        for _ in 0..60 {
            let sw = 1 + (lcg(&mut seed) % 19) as usize;
            let sh = 1 + (lcg(&mut seed) % 19) as usize;
            let n = sw * sh * 4;
            let a8: Vec<u8> = (0..n).map(|_| lcg(&mut seed) as u8).collect();
            let a16: Vec<u16> = (0..n).map(|_| lcg(&mut seed) as u16).collect();
            let ai8: Vec<i8> =
                (0..n).map(|_| ((lcg(&mut seed) % 255) as i32 - 127) as i8).collect();
            let af: Vec<f32> = (0..n).map(|_| (lcg(&mut seed) % 1000) as f32 / 999.0).collect();
            let m = next_size(sw) * next_size(sh) * 4;
            for filter in [MipFilter::Box, MipFilter::Min, MipFilter::Max] {
                let mut d8 = vec![0u8; m];
                downsample(&a8, sw, sh, filter, &mut d8);
                let want =
                    naive(&a8.iter().map(|&v| v as f64).collect::<Vec<_>>(), sw, sh, filter, true);
                assert_eq!(
                    d8.iter().map(|&v| v as f64).collect::<Vec<_>>(),
                    want,
                    "u8 {sw}×{sh} {filter:?}"
                );
                let mut d16 = vec![0u16; m];
                downsample(&a16, sw, sh, filter, &mut d16);
                let want =
                    naive(&a16.iter().map(|&v| v as f64).collect::<Vec<_>>(), sw, sh, filter, true);
                assert_eq!(
                    d16.iter().map(|&v| v as f64).collect::<Vec<_>>(),
                    want,
                    "u16 {sw}×{sh} {filter:?}"
                );
                let mut di8 = vec![0i8; m];
                downsample(&ai8, sw, sh, filter, &mut di8);
                let want =
                    naive(&ai8.iter().map(|&v| v as f64).collect::<Vec<_>>(), sw, sh, filter, true);
                assert_eq!(
                    di8.iter().map(|&v| v as f64).collect::<Vec<_>>(),
                    want,
                    "i8 {sw}×{sh} {filter:?}"
                );
                let mut df = vec![0f32; m];
                downsample(&af, sw, sh, filter, &mut df);
                let want =
                    naive(&af.iter().map(|&v| v as f64).collect::<Vec<_>>(), sw, sh, filter, false);
                for (k, (&g, &w)) in df.iter().zip(&want).enumerate() {
                    assert!(
                        (g as f64 - w).abs() < 1e-6,
                        "f32 {sw}×{sh} {filter:?} value {k}: {g} vs {w}"
                    );
                }
            }
        }
    }

    #[test]
    fn box_heights_and_holes_by_hand() {
        // 3×3 → 1×1 reads the top-left 2×2 (floor rule): (1 + 2 + 4 + 5) / 4 = 3.
        let h = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0];
        assert_eq!(box_heights(&h, 3, 3), vec![3.0]);
        // 1×3 → 1×1: the column read twice: (1 + 1 + 2 + 2) / 4 = 1.5.
        assert_eq!(box_heights(&[1.0, 2.0, 3.0], 1, 3), vec![1.5]);
        // 4×2 → 2×1.
        let h = [0.0, 4.0, 1.0, 1.0, 8.0, 0.0, 1.0, 5.0];
        assert_eq!(box_heights(&h, 4, 2), vec![3.0, 2.0]);
        let m = [false, false, false, true, false, false, false, false];
        assert_eq!(any_holes(&m, 4, 2), vec![false, true]);
        assert_eq!(MipFilter::parse("ReBake").unwrap(), MipFilter::Rebake);
        assert_eq!(MipFilter::Rebake.name(), "rebake");
    }

    #[test]
    fn chain_goes_down_to_one_texel_and_stops_when_canceled() {
        let (w, h) = (13, 5);
        let src: Vec<u8> = (0..w * h * 4).map(|k| (k * 7 % 256) as u8).collect();
        let levels = chain(w, h, &src, MipFilter::Max, full_levels(w, h), &|| true).unwrap();
        let sizes: Vec<usize> = levels.iter().map(Vec::len).collect();
        assert_eq!(sizes, [6 * 2 * 4, 3 * 4, 4]);
        // Max of max is the max of the parent block: the 1×1 level holds each channel's max
        // over the texels the chain read.
        let mut one = vec![0u8; 4];
        downsample(&levels[1], 3, 1, MipFilter::Max, &mut one);
        assert_eq!(levels[2], one);
        assert!(matches!(
            chain(w, h, &src, MipFilter::Box, 3, &|| false),
            Err(crate::Error::Canceled)
        ));
    }
}
