//! Tiled bakes (SPEC §7.1): the pure tile plan, and the tile record the jobs core claims,
//! leases, heartbeats and fences exactly as it does a bake.
//!
//! # The plan
//! A map of W × H texels is cut into a grid of `tile_size`² interiors (the last column and row
//! take what is left). Each tile is baked on a *window*: its interior plus a halo of
//! `halo` = resolved radius + 1 texels on every side (the kernels read up to the radius, and the
//! bilinear surface one texel further). With `edge=none` the window is clipped to the map (nothing
//! outside it occludes); with `edge=wrap` it extends past the map's edges and its texels are taken
//! modulo the map's size, as the untiled kernel would read them. Every texel of the map lies in
//! exactly one interior, and every texel an interior texel's horizon reads lies in its window, so
//! baking the window and keeping the interior gives the untiled bake's values there (with the
//! whole map's height range handed to the kernels: see [`crate::kernels::Grid::with_range`]).
//!
//! The plan is pure (no I/O) and tested on its own; the jobs core stores one [`TileRecord`] per
//! tile.

use crate::error::{Error, Result};
use crate::params::Edge;
use serde::{Deserialize, Serialize};

/// A rectangle of texels in the map: columns `x .. x + w`, rows `y .. y + h`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Rect {
    pub x: u32,
    pub y: u32,
    pub w: u32,
    pub h: u32,
}

/// One tile of a plan.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct TileGeom {
    /// Row-major index in the plan (`row · cols + col`).
    pub index: u32,
    pub col: u32,
    pub row: u32,
    /// The texels this tile's results hold, in the map.
    pub interior: Rect,
    /// First column and row of the window in map coordinates: negative or past the map with
    /// `edge=wrap` (taken modulo the map's size), inside it with `edge=none`.
    pub window_x: i64,
    pub window_y: i64,
    pub window_w: u32,
    pub window_h: u32,
}

impl TileGeom {
    /// Where the interior starts inside the window (column, row).
    pub fn interior_offset(&self) -> (u32, u32) {
        (
            (self.interior.x as i64 - self.window_x) as u32,
            (self.interior.y as i64 - self.window_y) as u32,
        )
    }

    /// The map column of window column `c` (wrapped into the map).
    pub fn map_col(&self, c: u32, width: u32) -> u32 {
        (self.window_x + c as i64).rem_euclid(width as i64) as u32
    }

    /// The map row of window row `r` (wrapped into the map).
    pub fn map_row(&self, r: u32, height: u32) -> u32 {
        (self.window_y + r as i64).rem_euclid(height as i64) as u32
    }
}

/// The tile grid of one map.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct TilePlan {
    pub width: u32,
    pub height: u32,
    pub tile_size: u32,
    pub halo: u32,
    pub edge: Edge,
    pub cols: u32,
    pub rows: u32,
}

/// The halo a resolved radius needs: the radius, plus one texel for the bilinear surface.
pub fn halo_for(radius: u32) -> u32 {
    radius.saturating_add(1)
}

/// Whether a map of `width` × `height` texels is baked in tiles with `--tile-above`
/// `tile_above` (width · height above it).
pub fn is_tiled(width: u32, height: u32, tile_above: u64) -> bool {
    width as u64 * height as u64 > tile_above
}

impl TilePlan {
    /// The plan of a `width` × `height` map in `tile_size`² tiles with a halo of `halo`.
    ///
    /// # Errors
    /// [`Error::Param`] naming `tile_size` when it is smaller than the halo (a window would be
    /// mostly halo), or `radius` when the halo is larger than the map (the map would have to be
    /// read whole by every tile: bake it untiled or use a smaller radius).
    pub fn new(width: u32, height: u32, tile_size: u32, halo: u32, edge: Edge) -> Result<Self> {
        if width == 0 || height == 0 {
            return Err(Error::InvalidInput(format!("a {width}×{height} map has no texels")));
        }
        if tile_size < halo {
            return Err(Error::param(
                "tile_size",
                format!(
                    "--tile-size {tile_size} is smaller than the halo of {halo} texels (the \
                     resolved radius + 1) each tile reads around it; use --tile-size {halo} or \
                     more, or a smaller radius"
                ),
            ));
        }
        if halo > width || halo > height {
            return Err(Error::param(
                "radius",
                format!(
                    "the halo of {halo} texels (the resolved radius + 1) is larger than the \
                     {width}×{height} map: a tiled bake needs a radius below the map's size; use \
                     a smaller radius or max_distance"
                ),
            ));
        }
        Ok(TilePlan {
            width,
            height,
            tile_size,
            halo,
            edge,
            cols: width.div_ceil(tile_size),
            rows: height.div_ceil(tile_size),
        })
    }

    /// How many tiles.
    pub fn len(&self) -> usize {
        self.cols as usize * self.rows as usize
    }

    /// Whether the plan has no tile (never: a map has a texel).
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Tile `index` (row-major).
    ///
    /// # Panics
    /// If `index >= len()` (a programming error).
    pub fn tile(&self, index: u32) -> TileGeom {
        assert!((index as usize) < self.len(), "tile {index} of {}", self.len());
        let (col, row) = (index % self.cols, index / self.cols);
        let x = col * self.tile_size;
        let y = row * self.tile_size;
        let interior = Rect {
            x,
            y,
            w: self.tile_size.min(self.width - x),
            h: self.tile_size.min(self.height - y),
        };
        let span = |start: u32, len: u32, size: u32| -> (i64, u32) {
            let halo = self.halo as i64;
            match self.edge {
                Edge::Wrap => (start as i64 - halo, len + 2 * self.halo),
                Edge::None => {
                    let lo = (start as i64 - halo).max(0);
                    let hi = (start as i64 + len as i64 + halo).min(size as i64);
                    (lo, (hi - lo) as u32)
                }
            }
        };
        let (window_x, window_w) = span(interior.x, interior.w, self.width);
        let (window_y, window_h) = span(interior.y, interior.h, self.height);
        TileGeom { index, col, row, interior, window_x, window_y, window_w, window_h }
    }

    /// Every tile, row-major.
    pub fn tiles(&self) -> impl Iterator<Item = TileGeom> + '_ {
        (0..self.len() as u32).map(|i| self.tile(i))
    }

    /// The tiles whose interiors hold map rows `y .. y + tile_size` (one row of tiles).
    pub fn tile_row(&self, row: u32) -> impl Iterator<Item = TileGeom> + '_ {
        (0..self.cols).map(move |c| self.tile(row * self.cols + c))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn covered(plan: &TilePlan) -> Vec<u32> {
        let mut hits = vec![0u32; (plan.width * plan.height) as usize];
        for t in plan.tiles() {
            for y in t.interior.y..t.interior.y + t.interior.h {
                for x in t.interior.x..t.interior.x + t.interior.w {
                    hits[(y * plan.width + x) as usize] += 1;
                }
            }
        }
        hits
    }

    #[test]
    fn every_texel_is_in_exactly_one_interior() {
        for (w, h, ts, halo) in [(64, 64, 16, 5), (67, 41, 16, 9), (5, 7, 3, 2), (10, 10, 10, 3)] {
            for edge in [Edge::Wrap, Edge::None] {
                let plan = TilePlan::new(w, h, ts, halo, edge).unwrap();
                assert_eq!(plan.len() as u32, w.div_ceil(ts) * h.div_ceil(ts));
                assert!(covered(&plan).iter().all(|&n| n == 1), "{w}×{h} in {ts}: {edge:?}");
            }
        }
    }

    #[test]
    fn odd_sizes_leave_a_narrower_last_column_and_row() {
        let plan = TilePlan::new(67, 41, 16, 4, Edge::None).unwrap();
        assert_eq!((plan.cols, plan.rows), (5, 3));
        let last = plan.tile(plan.len() as u32 - 1);
        assert_eq!(last.interior, Rect { x: 64, y: 32, w: 3, h: 9 });
        assert_eq!((last.col, last.row), (4, 2));
    }

    #[test]
    fn halos_are_clipped_with_edge_none() {
        let plan = TilePlan::new(67, 41, 16, 4, Edge::None).unwrap();
        let first = plan.tile(0);
        assert_eq!(
            (first.window_x, first.window_y, first.window_w, first.window_h),
            (0, 0, 20, 20)
        );
        assert_eq!(first.interior_offset(), (0, 0));
        let mid = plan.tile(plan.cols + 1);
        assert_eq!((mid.window_x, mid.window_y, mid.window_w, mid.window_h), (12, 12, 24, 24));
        assert_eq!(mid.interior_offset(), (4, 4));
        let last = plan.tile(plan.len() as u32 - 1);
        assert_eq!((last.window_x, last.window_y), (60, 28));
        assert_eq!((last.window_w, last.window_h), (7, 13));
        assert_eq!(last.interior_offset(), (4, 4));
    }

    #[test]
    fn halos_wrap_with_edge_wrap() {
        let plan = TilePlan::new(67, 41, 16, 4, Edge::Wrap).unwrap();
        let first = plan.tile(0);
        assert_eq!(
            (first.window_x, first.window_y, first.window_w, first.window_h),
            (-4, -4, 24, 24)
        );
        assert_eq!(first.map_col(0, 67), 63);
        assert_eq!(first.map_row(3, 41), 40);
        assert_eq!(first.map_col(4, 67), 0);
        let last = plan.tile(plan.len() as u32 - 1);
        assert_eq!((last.window_w, last.window_h), (3 + 8, 9 + 8));
        // Past the right and bottom edges, the window reads the first columns and rows again.
        assert_eq!(last.map_col(last.window_w - 1, 67), 3);
        assert_eq!(last.map_row(last.window_h - 1, 41), 3);
    }

    #[test]
    fn a_map_of_one_tile_is_one_window() {
        for edge in [Edge::Wrap, Edge::None] {
            let plan = TilePlan::new(12, 9, 16, 3, edge).unwrap();
            assert_eq!(plan.len(), 1);
            let t = plan.tile(0);
            assert_eq!(t.interior, Rect { x: 0, y: 0, w: 12, h: 9 });
            let expect = match edge {
                Edge::None => (0, 0, 12, 9),
                Edge::Wrap => (-3, -3, 18, 15),
            };
            assert_eq!((t.window_x, t.window_y, t.window_w, t.window_h), expect);
        }
    }

    #[test]
    fn refusals_name_the_parameter() {
        let e = TilePlan::new(100, 100, 8, 9, Edge::Wrap).unwrap_err();
        assert!(matches!(&e, Error::Param { field, .. } if field == "tile_size"), "{e}");
        let e = TilePlan::new(100, 30, 64, 31, Edge::None).unwrap_err();
        assert!(matches!(&e, Error::Param { field, .. } if field == "radius"), "{e}");
        assert!(TilePlan::new(100, 31, 64, 31, Edge::None).is_ok());
    }

    #[test]
    fn tiling_starts_above_the_threshold() {
        assert!(!is_tiled(4096, 4096, 4096 * 4096));
        assert!(is_tiled(4097, 4096, 4096 * 4096));
        assert_eq!(halo_for(40), 41);
    }
}
