//! The eval's corpus: height maps generated deterministically in code, so the table regenerates
//! bit for bit on any machine, plus any map the user passes from a file.
//!
//! Each generated map stresses a different failure of the approximations: a smooth bump (long,
//! low horizons: the radius matters), fractal terrain (occluders at every distance and
//! azimuth), bricks (straight walls aligned with and across the channel azimuths) and sparse
//! spikes (thin occluders that a 45° channel spacing can miss). Heights are in texels and every
//! map tiles (`edge=wrap`), so the ground truth has no border effects to explain.

use crate::error::{Error, Result};
use crate::heightmap::{self, Limits};
use crate::params::Channel;

/// One map of the corpus: heights in texel units, row-major from the top row.
#[derive(Debug, Clone, PartialEq)]
pub struct Map {
    pub name: String,
    pub width: usize,
    pub height: usize,
    pub heights: Vec<f32>,
}

/// SplitMix64: tiny, deterministic, good enough to place spikes and lattice values.
struct Rng(u64);

impl Rng {
    fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    /// Uniform in [0, 1).
    fn unit(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// A smooth, tileable bump: a raised cosine of radius `n/3` and peak `0.2·n` texels, so its
/// shadows reach far (a low light sees the bump from ~n/2 away).
pub fn bump(n: usize) -> Map {
    let c = n as f64 / 2.0;
    let r = n as f64 / 3.0;
    let peak = 0.2 * n as f64;
    let mut h = vec![0.0f32; n * n];
    for y in 0..n {
        for x in 0..n {
            let d = ((x as f64 + 0.5 - c).powi(2) + (y as f64 + 0.5 - c).powi(2)).sqrt() / r;
            if d < 1.0 {
                h[y * n + x] = (peak * 0.5 * (1.0 + (std::f64::consts::PI * d).cos())) as f32;
            }
        }
    }
    Map { name: "bump".into(), width: n, height: n, heights: h }
}

/// Tileable fBm: value noise on periodic lattices of 4, 8, 16, … cells with smoothstep
/// interpolation, amplitude halving per octave, scaled to a height range of `0.15·n` texels.
pub fn fractal(n: usize, seed: u64) -> Map {
    let mut rng = Rng(seed);
    let mut h = vec![0.0f64; n * n];
    let mut cells = 4usize;
    let mut amp = 1.0f64;
    while cells <= n.max(4) && cells <= 64 {
        let lattice: Vec<f64> = (0..cells * cells).map(|_| rng.unit()).collect();
        let at = |i: usize, j: usize| lattice[(j % cells) * cells + (i % cells)];
        let smooth = |t: f64| t * t * (3.0 - 2.0 * t);
        for y in 0..n {
            let fy = (y as f64 + 0.5) * cells as f64 / n as f64;
            let (j, ty) = (fy.floor() as usize, smooth(fy.fract()));
            for x in 0..n {
                let fx = (x as f64 + 0.5) * cells as f64 / n as f64;
                let (i, tx) = (fx.floor() as usize, smooth(fx.fract()));
                let top = at(i, j) * (1.0 - tx) + at(i + 1, j) * tx;
                let bot = at(i, j + 1) * (1.0 - tx) + at(i + 1, j + 1) * tx;
                h[y * n + x] += amp * (top * (1.0 - ty) + bot * ty);
            }
        }
        cells *= 2;
        amp *= 0.5;
    }
    normalise(&mut h, 0.15 * n as f64);
    Map {
        name: "fractal".into(),
        width: n,
        height: n,
        heights: h.iter().map(|&v| v as f32).collect(),
    }
}

/// Bricks in running bond: `n/4 × n/8` texel bricks, 2-texel mortar joints at height 0, brick
/// faces 3 texels up with a 1-texel bevel and a per-brick tilt, so walls run along the 0° and
/// 90° channels and the bevels catch the diagonals.
pub fn bricks(n: usize) -> Map {
    // At least 8×4 so that small maps still have brick faces between the joints.
    let bw = (n / 4).max(8);
    let bh = (n / 8).max(4);
    let mut rng = Rng(0xB51C);
    let rows = n.div_ceil(bh) + 1;
    let tilts: Vec<f64> = (0..rows * 8).map(|_| rng.unit() - 0.5).collect();
    let mut h = vec![0.0f32; n * n];
    for y in 0..n {
        let row = y / bh;
        let shift = if row % 2 == 1 { bw / 2 } else { 0 };
        for x in 0..n {
            let xs = (x + shift) % n;
            let col = xs / bw;
            let (u, v) = ((xs % bw) as f64 + 0.5, (y % bh) as f64 + 0.5);
            // Distance to the nearest joint, minus the half mortar width.
            let edge = u.min(bw as f64 - u).min(v).min(bh as f64 - v) - 1.0;
            let face = if edge <= 0.0 { 0.0 } else { 3.0 * edge.min(1.0) };
            let tilt = tilts[(row * 8 + col) % tilts.len()] * 0.6 * (u / bw as f64 - 0.5);
            h[y * n + x] = if face > 0.0 { (face + tilt).max(0.0) as f32 } else { 0.0 };
        }
    }
    Map { name: "bricks".into(), width: n, height: n, heights: h }
}

/// Sparse spikes: a flat plane with ~0.3% of texels raised to 4..`0.16·n` texels, each a single
/// texel (the hardest occluder for an angular splat: it subtends almost nothing).
pub fn spikes(n: usize, seed: u64) -> Map {
    let mut rng = Rng(seed);
    let mut h = vec![0.0f32; n * n];
    let count = (n * n * 3 / 1000).max(1);
    let top = (0.16 * n as f64).max(4.0);
    for _ in 0..count {
        let k = (rng.next_u64() % (n * n) as u64) as usize;
        h[k] = (4.0 + rng.unit() * (top - 4.0)) as f32;
    }
    Map { name: "spikes".into(), width: n, height: n, heights: h }
}

fn normalise(h: &mut [f64], range: f64) {
    let lo = h.iter().copied().fold(f64::INFINITY, f64::min);
    let hi = h.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let span = if hi > lo { hi - lo } else { 1.0 };
    for v in h.iter_mut() {
        *v = (*v - lo) / span * range;
    }
}

/// The generated corpus: bump, fractal, bricks and spikes at `n × n`.
pub fn generated(n: usize) -> Vec<Map> {
    vec![bump(n), fractal(n, 0x5EED), bricks(n), spikes(n, 0x5B1C)]
}

/// A map from an image file (luma of PNG/TIFF/EXR), heights = value × `height_scale`, cropped
/// to at most `max_side` texels from the top-left so the eval stays fast.
///
/// # Errors
/// I/O errors reading the file; whatever [`heightmap::decode`] rejects.
pub fn from_file(
    name: &str,
    path: &std::path::Path,
    height_scale: f64,
    max_side: usize,
) -> Result<Map> {
    let bytes = std::fs::read(path)?;
    let (hm, _) = heightmap::decode(&bytes, Channel::Luma, &Limits::default())?;
    let (w, h) = (hm.width.min(max_side), hm.height.min(max_side));
    if w == 0 || h == 0 {
        return Err(Error::InvalidInput(format!("{}: empty map", path.display())));
    }
    let mut heights = Vec::with_capacity(w * h);
    for y in 0..h {
        for x in 0..w {
            heights.push((hm.values[y * hm.width + x] as f64 * height_scale) as f32);
        }
    }
    Ok(Map { name: name.into(), width: w, height: h, heights })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn maps_are_deterministic_and_in_range() {
        for n in [16usize, 48] {
            let a = generated(n);
            let b = generated(n);
            assert_eq!(a, b);
            for m in &a {
                assert_eq!(m.heights.len(), n * n, "{}", m.name);
                let hi = m.heights.iter().copied().fold(0.0f32, f32::max);
                let lo = m.heights.iter().copied().fold(f32::INFINITY, f32::min);
                assert!(
                    lo >= 0.0 && hi > 1.0 && hi <= 0.2 * n as f32 + 4.0,
                    "{} {lo} {hi}",
                    m.name
                );
            }
        }
        // The bump peaks at its centre.
        let b = bump(32);
        assert!(b.heights[16 * 32 + 16] > 6.0);
        assert_eq!(b.heights[0], 0.0);
    }
}
