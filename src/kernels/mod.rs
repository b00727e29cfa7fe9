//! Pure numeric kernels: no I/O, no async, no knowledge of the service.
//!
//! Every horizon kernel is prepared once for a height grid (padding, offset tables, ...) and then
//! asked for whole rows of output through [`HorizonRows`]. The driver [`run_bands`] splits the
//! image into bands of rows, runs them on the current rayon pool, checks for cancellation and
//! reports progress between bands, and hands each finished band to a sink that quantises it
//! straight into the requested output encodings. That keeps the f32 working set to one band per
//! thread, whatever the map size.
//!
//! Layout conventions (SPEC §2): heights are row-major from the top image row, in texel units.
//! Channel c holds the horizon at azimuth c·45° measured from +x toward +y; the per-texel output
//! of a kernel is 8 consecutive f32 (channel 0..7), texel-major.

pub mod cubemap;
pub mod exact;
pub mod fourier;
pub mod lengyel;
pub mod lengyel_fast;
pub mod parallax;
pub mod shade;

use crate::error::{Error, Result};
use crate::params::{Edge, YAxis};
use crate::progress::Progress;
use rayon::prelude::*;

/// A height grid in texel units with the conventions needed to find neighbours.
#[derive(Debug, Clone, Copy)]
pub struct Grid<'a> {
    pub width: usize,
    pub height: usize,
    /// Row-major from the top image row, `width * height` heights in texels.
    pub heights: &'a [f32],
    pub edge: Edge,
    pub y_axis: YAxis,
}

impl<'a> Grid<'a> {
    /// A grid over `heights`.
    ///
    /// # Panics
    /// If `heights.len() != width * height` (a programming error, not an input error).
    pub fn new(width: usize, height: usize, heights: &'a [f32], edge: Edge, y_axis: YAxis) -> Self {
        assert_eq!(heights.len(), width * height, "grid size mismatch");
        Grid { width, height, heights, edge, y_axis }
    }

    /// Image row step for one unit of tangent-space +y: −1 with `y_axis=up` (toward the top).
    #[inline]
    pub fn row_step(&self) -> i64 {
        match self.y_axis {
            YAxis::Up => -1,
            YAxis::Down => 1,
        }
    }

    /// Height at image column `col`, row `row` (may be outside the map): wrapped, or `None`
    /// outside the map with `edge=none`.
    #[inline]
    pub fn at(&self, col: i64, row: i64) -> Option<f32> {
        let (w, h) = (self.width as i64, self.height as i64);
        let (c, r) = match self.edge {
            Edge::Wrap => (col.rem_euclid(w), row.rem_euclid(h)),
            Edge::None => {
                if col < 0 || row < 0 || col >= w || row >= h {
                    return None;
                }
                (col, row)
            }
        };
        Some(self.heights[(r * w + c) as usize])
    }

    /// Height at texel (`x`, `y` image coords) displaced by tangent-space offset (`i`, `j`).
    #[inline]
    pub fn at_offset(&self, x: usize, y: usize, i: i64, j: i64) -> Option<f32> {
        self.at(x as i64 + i, y as i64 + j * self.row_step())
    }

    /// Minimum and maximum height (0, 0 for an empty grid).
    pub fn range(&self) -> (f32, f32) {
        let mut lo = f32::INFINITY;
        let mut hi = f32::NEG_INFINITY;
        for &v in self.heights {
            lo = lo.min(v);
            hi = hi.max(v);
        }
        if lo > hi {
            (0.0, 0.0)
        } else {
            (lo, hi)
        }
    }
}

/// A horizon kernel prepared for one grid. Implementations must be pure: the same rows always
/// give the same values, whichever thread computes them and in whichever order.
pub trait HorizonRows: Sync {
    /// Output width in texels.
    fn width(&self) -> usize;
    /// Output height in texels.
    fn height(&self) -> usize;
    /// Number of azimuth bins the kernel works with internally.
    fn bins(&self) -> usize;
    /// Computes rows `y0 .. y0 + n` where `n = channels.len() / (width * 8)`:
    /// `channels[(r * width + x) * 8 + c]` = sin of the horizon elevation in channel c, in [0, 1].
    /// When `bins_out` is given (`n * width * bins` f32), also writes the per-bin horizon
    /// s(φ_n), φ_n = n·2π/bins, before the reduction to channels.
    fn rows(&self, y0: usize, channels: &mut [f32], bins_out: Option<&mut [f32]>);
}

/// Rows per band: small enough to balance across threads and to cancel promptly, large enough
/// to amortise per-band setup.
pub fn band_rows(width: usize, height: usize) -> usize {
    let threads = rayon::current_num_threads().max(1);
    // Aim for ~16 bands per thread and at most ~256k texels per band.
    let by_balance = height.div_ceil(threads * 16).max(1);
    let by_memory = (262_144 / width.max(1)).max(1);
    by_balance.min(by_memory).min(height.max(1))
}

/// One band's results handed to the sink: its first row and the f32 values.
pub struct Band<'a> {
    pub y0: usize,
    pub rows: usize,
    /// `rows * width * 8` channel values.
    pub channels: &'a [f32],
    /// `rows * width * bins` per-bin values, when asked for.
    pub bins: Option<&'a [f32]>,
}

/// Runs `kernel` over every row in parallel bands, calling `sink(band_index, band)` for each
/// finished band (from rayon threads, in any order). The sink receives the band index so it can
/// write into pre-split output slices without locking.
///
/// Checks `progress` for cancellation before each band and advances it by the band's rows.
///
/// # Errors
/// [`Error::Canceled`] when cancellation was asked for; already-finished bands are kept by the
/// sink but the caller must discard them.
pub fn run_bands<K, S>(
    kernel: &K,
    band: usize,
    want_bins: bool,
    progress: &Progress,
    sink: S,
) -> Result<()>
where
    K: HorizonRows + ?Sized,
    S: Fn(usize, Band<'_>) + Sync,
{
    let (w, h, nb) = (kernel.width(), kernel.height(), kernel.bins());
    let band = band.max(1);
    let nbands = h.div_ceil(band);
    (0..nbands).into_par_iter().try_for_each_init(
        || (Vec::<f32>::new(), Vec::<f32>::new()),
        |(ch, bn), b| {
            if progress.is_canceled() {
                return Err(Error::Canceled);
            }
            let y0 = b * band;
            let rows = band.min(h - y0);
            ch.resize(rows * w * 8, 0.0);
            let bins = if want_bins {
                bn.resize(rows * w * nb, 0.0);
                Some(&mut bn[..])
            } else {
                None
            };
            kernel.rows(y0, &mut ch[..], bins);
            // A kernel may return early on cancel; never hand its partial band on.
            if progress.is_canceled() {
                return Err(Error::Canceled);
            }
            sink(b, Band { y0, rows, channels: ch, bins: want_bins.then_some(&bn[..]) });
            progress.advance(rows as u64);
            Ok(())
        },
    )
}

/// Runs `kernel` over the whole grid and returns the channels as one `H·W·8` f32 buffer.
/// Meant for tests, oracles and small maps; bakes stream bands into encoders instead.
///
/// # Errors
/// [`Error::Canceled`] when `progress` asks for it.
pub fn compute_all<K: HorizonRows + ?Sized>(kernel: &K, progress: &Progress) -> Result<Vec<f32>> {
    let (w, h) = (kernel.width(), kernel.height());
    let mut out = vec![0.0f32; w * h * 8];
    let band = band_rows(w, h);
    let chunks: Vec<std::sync::Mutex<&mut [f32]>> =
        out.chunks_mut(band * w * 8).map(std::sync::Mutex::new).collect();
    run_bands(kernel, band, false, progress, |b, band| {
        // Each band index is visited exactly once, so the lock is never contended.
        if let Ok(mut dst) = chunks[b].lock() {
            dst.copy_from_slice(band.channels);
        }
    })?;
    drop(chunks);
    Ok(out)
}

/// Reduces per-bin values to 8 channels: channel c = mean over the `B/8 + 1` bins centred on bin
/// c·B/8 (SPEC §3.1).
#[inline]
pub fn reduce_average(bins: &[f32], out: &mut [f32; 8]) {
    let b = bins.len();
    let step = b / 8;
    let half = (b / 16) as i64;
    let inv = 1.0 / (step + 1) as f64;
    for (c, o) in out.iter_mut().enumerate() {
        let centre = (c * step) as i64;
        let mut sum = 0.0f64;
        for k in -half..=half {
            sum += bins[(centre + k).rem_euclid(b as i64) as usize] as f64;
        }
        *o = (sum * inv) as f32;
    }
}

/// Reduces per-bin values to 8 channels by taking the bin at each channel's azimuth.
#[inline]
pub fn reduce_point(bins: &[f32], out: &mut [f32; 8]) {
    let step = bins.len() / 8;
    for (c, o) in out.iter_mut().enumerate() {
        *o = bins[c * step];
    }
}
