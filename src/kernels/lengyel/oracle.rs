//! The Lengyel/Max horizon map, written the plain way: the oracle (SPEC §3.1).
//!
//! This is deliberately the obvious loop (texel → neighbour → bin) in f64, transcribed from the
//! specification line by line so that it can be read against it. It is far too slow for
//! production maps (≈0.4 Mtexel/s); [`super::fast`] computes the same function and is tested
//! against this one on random inputs and on the golden files.
//!
//! For texel p with height h0 and every offset (i, j), |i|, |j| < R, 0 < i² + j² < R², whose
//! neighbour height h ≥ h0:
//!   tan² = (h − h0)² / (i² + j²),  θ = atan2(j, i),  δ = atan(√2 / (2·√(i² + j²)))
//! and every bin n in floor((θ − δ)·B/2π) ..= ceil((θ + δ)·B/2π) (mod B) keeps the largest tan².
//! Then s_n = √(tan² / (tan² + 1)) and channel c is the mean of the B/8 + 1 bins centred on c·B/8.

use crate::kernels::{reduce_average, Grid, HorizonRows};
use crate::progress::Progress;
use std::f64::consts::PI;

/// The plain Lengyel kernel for one grid.
#[derive(Debug, Clone)]
pub struct LengyelNaive<'a> {
    grid: Grid<'a>,
    radius: u32,
    bins: usize,
    /// Watched between neighbour rows: at a radius of thousands one texel alone takes seconds.
    cancel: Option<Progress>,
}

impl<'a> LengyelNaive<'a> {
    /// Prepares the kernel. `radius ≥ 1`, `bins` a multiple of 16 (validated by `params`).
    pub fn new(grid: Grid<'a>, radius: u32, bins: u32) -> Self {
        LengyelNaive { grid, radius, bins: bins as usize, cancel: None }
    }

    /// Makes [`HorizonRows::rows`] return early (leaving the rest of its rows unspecified) once
    /// `progress` is canceled; the band driver then discards the band.
    pub fn with_cancel(mut self, progress: &Progress) -> Self {
        self.cancel = Some(progress.clone());
        self
    }

    fn canceled(&self) -> bool {
        self.cancel.as_ref().is_some_and(Progress::is_canceled)
    }

    /// The per-bin s values of texel (x, y), written into `s` (`bins` long); unspecified if
    /// the kernel's progress is canceled meanwhile.
    pub fn texel_bins(&self, x: usize, y: usize, s: &mut [f32]) {
        let b = self.bins;
        let r = self.radius as i64;
        let h0 = self.grid.heights[y * self.grid.width + x] as f64;
        let mut tan2 = vec![0.0f64; b];
        let scale = b as f64 / (2.0 * PI);
        for j in (1 - r)..r {
            // One relaxed load per neighbour row (2R − 1 loads against (2R − 1)² neighbours).
            if self.canceled() {
                return;
            }
            for i in (1 - r)..r {
                let d2 = (i * i + j * j) as f64;
                if d2 == 0.0 || d2 >= (r * r) as f64 {
                    continue;
                }
                let Some(h) = self.grid.at_offset(x, y, i, j) else {
                    continue;
                };
                let h = h as f64;
                if h < h0 {
                    continue;
                }
                let t2 = (h - h0) * (h - h0) / d2;
                let theta = (j as f64).atan2(i as f64);
                let delta = (2f64.sqrt() / (2.0 * d2.sqrt())).atan();
                let lo = ((theta - delta) * scale).floor() as i64;
                let hi = ((theta + delta) * scale).ceil() as i64;
                for n in lo..=hi {
                    let k = n.rem_euclid(b as i64) as usize;
                    if t2 > tan2[k] {
                        tan2[k] = t2;
                    }
                }
            }
        }
        for (o, &t) in s.iter_mut().zip(&tan2) {
            *o = (t / (t + 1.0)).sqrt() as f32;
        }
    }
}

impl HorizonRows for LengyelNaive<'_> {
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
        let w = self.grid.width;
        let b = self.bins;
        let mut s = vec![0.0f32; b];
        for (k, out) in channels.chunks_exact_mut(8).enumerate() {
            let (x, y) = (k % w, y0 + k / w);
            self.texel_bins(x, y, &mut s);
            if self.canceled() {
                return;
            }
            let mut ch = [0.0f32; 8];
            reduce_average(&s, &mut ch);
            out.copy_from_slice(&ch);
            if let Some(bo) = bins_out.as_deref_mut() {
                bo[k * b..(k + 1) * b].copy_from_slice(&s);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kernels::compute_all;
    use crate::params::{Edge, YAxis};
    use crate::progress::Progress;

    #[test]
    fn flat_map_is_all_zero() {
        let h = vec![3.5f32; 7 * 5];
        let g = Grid::new(7, 5, &h, Edge::Wrap, YAxis::Up);
        let out = compute_all(&LengyelNaive::new(g, 6, 32), &Progress::new()).unwrap();
        assert!(out.iter().all(|&v| v == 0.0));
    }

    #[test]
    fn single_wall_east_of_texel() {
        // 1×N strip is awkward; use a 9×1 row with a tall texel 2 to the east of texel 0
        // and edge=none: only channel 0 (and its neighbours' shares) sees it.
        let mut h = vec![0.0f32; 9];
        h[2] = 2.0;
        let g = Grid::new(9, 1, &h, Edge::None, YAxis::Up);
        let k = LengyelNaive::new(g, 4, 32);
        let mut s = vec![0.0f32; 32];
        k.texel_bins(0, 0, &mut s);
        // tan = 2/2 = 1 → s = √½ on bins around 0; δ = atan(√2/4) ≈ 0.3398 rad → bins -2..=2.
        let expect = (0.5f64).sqrt() as f32;
        for n in [30usize, 31, 0, 1, 2] {
            assert!((s[n] - expect).abs() < 1e-6, "bin {n}: {}", s[n]);
        }
        assert_eq!(s[3], 0.0);
        assert_eq!(s[16], 0.0);
    }
}
