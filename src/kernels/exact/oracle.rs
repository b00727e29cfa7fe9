//! The plain oracle of `exact`: every cell of every ray, no skipping and no vector near field.

use super::walk::{corners, walk, Ray};
use super::{bin_directions, sin_of_tan};
use crate::kernels::{reduce_into, Grid, HorizonRows};
use crate::params::Reduce;

/// The plain oracle: every cell of every ray, no skipping. Slow (O(R) per ray); the tests check
/// [`ExactHorizon`] against it, and it against a brute-force fine-step march.
#[derive(Debug, Clone)]
pub struct ExactMarch<'a> {
    grid: Grid<'a>,
    radius: Option<f64>,
    dirs: Vec<(f64, f64)>,
    reduce: Reduce,
}

impl<'a> ExactMarch<'a> {
    /// `radius`: `None` = unlimited. `bins` a multiple of 16 (validated by `params`).
    pub fn new(grid: Grid<'a>, radius: Option<u32>, bins: u32, reduce: Reduce) -> Self {
        let dirs = bin_directions(bins as usize, grid.row_step());
        ExactMarch { grid, radius: radius.map(f64::from), dirs, reduce }
    }

    /// Per-bin sin α of texel (x, y) into `s` (`bins` long).
    pub fn texel_bins(&self, x: usize, y: usize, s: &mut [f32]) {
        for (o, &(dx, dy)) in s.iter_mut().zip(&self.dirs) {
            let ray = Ray::new(&self.grid, x, y, dx, dy, self.radius);
            let t = walk(&self.grid, &ray, None, ((0.0, 0.0), 0.0), 0.0, |cx, cy| {
                corners(&self.grid, cx, cy)
            })
            .0;
            *o = sin_of_tan(t) as f32;
        }
    }
}

impl HorizonRows for ExactMarch<'_> {
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
        let (w, b) = (self.grid.width, self.dirs.len());
        let mut s = vec![0.0f32; b];
        for (k, out) in channels.chunks_exact_mut(8).enumerate() {
            self.texel_bins(k % w, y0 + k / w, &mut s);
            reduce_into(self.reduce, &s, out);
            if let Some(bo) = bins_out.as_deref_mut() {
                bo[k * b..(k + 1) * b].copy_from_slice(&s);
            }
        }
    }
}
