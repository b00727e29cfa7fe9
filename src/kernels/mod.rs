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
pub mod isa;
pub mod lengyel;
pub mod march;
pub(crate) mod nearfield;
pub mod parallax;
pub mod shade;
pub mod sweep;

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
    /// The height range of the whole map when this grid is a window of it (a tile of a tiled
    /// bake, SPEC §7.1): kernels that work relative to the range see the whole map's, so a
    /// texel's result does not depend on the window it is computed in.
    pub whole_range: Option<(f32, f32)>,
}

impl<'a> Grid<'a> {
    /// A grid over `heights`.
    ///
    /// # Panics
    /// If `heights.len() != width * height` (a programming error, not an input error).
    pub fn new(width: usize, height: usize, heights: &'a [f32], edge: Edge, y_axis: YAxis) -> Self {
        assert_eq!(heights.len(), width * height, "grid size mismatch");
        Grid { width, height, heights, edge, y_axis, whole_range: None }
    }

    /// This grid as a window of a map whose heights span `lo ..= hi` ([`Grid::range`] answers
    /// that instead of the window's own range).
    pub fn with_range(mut self, lo: f32, hi: f32) -> Self {
        self.whole_range = Some((lo, hi));
        self
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

    /// Minimum and maximum height (0, 0 for an empty grid); the whole map's for a window of it
    /// ([`Grid::with_range`]).
    pub fn range(&self) -> (f32, f32) {
        if let Some(r) = self.whole_range {
            return r;
        }
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

    /// Cost of one texel relative to the default bake (`lengyel`, R = 16, 32 bins), so that
    /// [`band_rows_for`] keeps bands short enough to cancel promptly at large radii. Kernels
    /// that check for cancel inside a band can keep the default.
    fn texel_cost(&self) -> f64 {
        1.0
    }

    /// A failure of the kernel's own storage (`sweep`'s spilled far field), reported by every
    /// call once it has happened: after one, [`HorizonRows::rows`] may have left its rows
    /// unfinished, and no band may be handed on. Kernels that keep everything in memory never
    /// fail.
    fn failure(&self) -> Option<Error> {
        None
    }
}

/// Rows per band for a default-cost kernel: small enough to balance across threads and to
/// cancel promptly, large enough to amortise per-band setup.
pub fn band_rows(width: usize, height: usize) -> usize {
    band_rows_weighted(width, height, 1.0)
}

/// Rows per band for `kernel`, weighing its [`HorizonRows::texel_cost`]: a band holds at most
/// ~256k default-cost texels (≈ 25 ms of one thread), so a cancel is seen within that even at
/// R = 128, where a texel costs 64 times as much. One row is the floor.
pub fn band_rows_for<K: HorizonRows + ?Sized>(kernel: &K) -> usize {
    band_rows_weighted(kernel.width(), kernel.height(), kernel.texel_cost())
}

fn band_rows_weighted(width: usize, height: usize, cost: f64) -> usize {
    let threads = rayon::current_num_threads().max(1);
    // Aim for ~16 bands per thread and at most ~256k default-cost texels per band.
    let by_balance = height.div_ceil(threads * 16).max(1);
    let budget = 262_144.0 / cost.max(1.0);
    let by_work = ((budget / width.max(1) as f64) as usize).max(1);
    by_balance.min(by_work).min(height.max(1))
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
            // A kernel may return early on cancel or a failure; never hand its partial band on.
            if let Some(e) = kernel.failure() {
                return Err(e);
            }
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
    let band = band_rows_for(kernel);
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
    let half = b / 16;
    let inv = 1.0 / (step + 1) as f64;
    for (c, o) in out.iter_mut().enumerate() {
        // Bins centre − half ..= centre + half, modulo b (a compare, not a division: this
        // runs per texel, and a `rem_euclid` by a run-time b cost 5 % of a sweep bake).
        let mut i = (c * step + b - half) % b;
        let mut sum = 0.0f64;
        for _ in 0..=2 * half {
            sum += bins[i] as f64;
            i = if i + 1 == b { 0 } else { i + 1 };
        }
        *o = (sum * inv) as f32;
    }
}

/// Fills `out` (8 channels) from per-bin values with `reduce` (SPEC §3.2).
#[inline]
pub fn reduce_into(reduce: crate::params::Reduce, bins: &[f32], out: &mut [f32]) {
    let mut ch = [0.0f32; 8];
    match reduce {
        crate::params::Reduce::Average => reduce_average(bins, &mut ch),
        crate::params::Reduce::Point => reduce_point(bins, &mut ch),
    }
    out.copy_from_slice(&ch);
}

/// [`reduce_into`] for the `L` texels of a strip at once, bins lane-major: `bins[n][i]` is
/// texel i's bin n; texel i's 8 channels go to `out[8i .. 8i + 8]` for i < `lanes`. The same
/// sums in the same order lane by lane, so bit for bit `reduce_into`'s, in a form the compiler
/// turns into vector adds across the strip (a texel alone is a chain of f64 adds).
#[inline(always)]
pub fn reduce_strip<const L: usize>(
    reduce: crate::params::Reduce,
    bins: &[[f32; L]],
    lanes: usize,
    out: &mut [f32],
) {
    let b = bins.len();
    let step = b / 8;
    let mut ch = [[0.0f32; L]; 8];
    match reduce {
        crate::params::Reduce::Average => {
            let half = b / 16;
            let inv = 1.0 / (step + 1) as f64;
            for (c, o) in ch.iter_mut().enumerate() {
                let mut i = (c * step + b - half) % b;
                let mut sum = [0.0f64; L];
                for _ in 0..=2 * half {
                    for (s, &v) in sum.iter_mut().zip(&bins[i]) {
                        *s += v as f64;
                    }
                    i = if i + 1 == b { 0 } else { i + 1 };
                }
                for (o, s) in o.iter_mut().zip(sum) {
                    *o = (s * inv) as f32;
                }
            }
        }
        crate::params::Reduce::Point => {
            for (c, o) in ch.iter_mut().enumerate() {
                *o = bins[c * step];
            }
        }
    }
    for (i, t) in out.chunks_exact_mut(8).take(lanes).enumerate() {
        for (c, v) in t.iter_mut().enumerate() {
            *v = ch[c][i];
        }
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

/// One flag per texel, 64 to a word: the masks a kernel keeps for the whole bake (a `Vec<bool>`
/// took a byte a texel, 67 MB at 8192²).
#[derive(Clone, Debug, Default)]
pub(crate) struct Flags {
    words: Vec<u64>,
}

impl Flags {
    /// `len` flags, all clear.
    pub(crate) fn new(len: usize) -> Flags {
        Flags { words: vec![0; len.div_ceil(64)] }
    }

    #[inline]
    pub(crate) fn get(&self, i: usize) -> bool {
        self.words[i >> 6] >> (i & 63) & 1 == 1
    }

    #[inline]
    pub(crate) fn set(&mut self, i: usize) {
        self.words[i >> 6] |= 1 << (i & 63);
    }

    /// Whether any flag of `r` is set.
    #[inline]
    pub(crate) fn any(&self, r: std::ops::Range<usize>) -> bool {
        r.into_iter().any(|i| self.get(i))
    }
}

/// Per texel: whether a hole lies within Chebyshev distance `r` (wrapped or clipped at the
/// map's sides): a row pass and a column pass of sliding-window counts, O(W·H) whatever `r`.
pub(crate) fn near_holes(holes: &[bool], w: usize, h: usize, r: usize, wrap: bool) -> Flags {
    // One line of `len` flags, `stride` apart from `start`, dilated by `r` (`set(i)` for
    // each flag of the line that is set).
    fn dilate(
        at: impl Fn(usize) -> bool,
        mut set: impl FnMut(usize),
        len: usize,
        r: usize,
        wrap: bool,
    ) {
        let mut prefix = vec![0u32; len + 1];
        for i in 0..len {
            prefix[i + 1] = prefix[i] + u32::from(at(i));
        }
        let count = |a: usize, b: usize| prefix[b] - prefix[a]; // flags in a..b
        for i in 0..len {
            let any = if wrap && 2 * r + 1 >= len {
                prefix[len] > 0
            } else if wrap {
                let (a, b) = (i as i64 - r as i64, i as i64 + r as i64 + 1);
                let n = len as i64;
                if a < 0 {
                    count(0, b as usize) + count((a + n) as usize, len) > 0
                } else if b > n {
                    count(a as usize, len) + count(0, (b - n) as usize) > 0
                } else {
                    count(a as usize, b as usize) > 0
                }
            } else {
                count(i.saturating_sub(r), (i + r + 1).min(len)) > 0
            };
            if any {
                set(i);
            }
        }
    }
    let mut across = Flags::new(w * h);
    for y in 0..h {
        dilate(|i| holes[y * w + i], |i| across.set(y * w + i), w, r, wrap);
    }
    let mut near = Flags::new(w * h);
    for x in 0..w {
        dilate(|i| across.get(i * w + x), |i| near.set(i * w + x), h, r, wrap);
    }
    near
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The channel means against SPEC §3.1's definition written out with `rem_euclid`, bit
    /// for bit, for every bin count up to 64 (the window wraps at both ends).
    #[test]
    fn reduce_average_is_the_wrapped_window_mean() {
        let mut seed = 5u64;
        for b in 1..=64usize {
            let bins: Vec<f32> = (0..b)
                .map(|_| {
                    seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                    (seed >> 40) as f32 / (1u64 << 24) as f32
                })
                .collect();
            let mut got = [0.0f32; 8];
            reduce_average(&bins, &mut got);
            let (step, half) = (b / 8, (b / 16) as i64);
            for (c, &g) in got.iter().enumerate() {
                let sum: f64 = (-half..=half)
                    .map(|k| bins[((c * step) as i64 + k).rem_euclid(b as i64) as usize] as f64)
                    .sum();
                let want = (sum * (1.0 / (step + 1) as f64)) as f32;
                assert_eq!(g.to_bits(), want.to_bits(), "{b} bins, channel {c}");
            }
        }
    }

    /// The strip form against the texel form, bit for bit, for every bin count up to 64, both
    /// reductions, and a strip shorter than its lanes.
    #[test]
    fn reduce_strip_is_reduce_into_lane_by_lane() {
        let mut seed = 11u64;
        for b in 1..=64usize {
            let bins: Vec<[f32; 16]> = (0..b)
                .map(|_| {
                    std::array::from_fn(|_| {
                        seed = seed
                            .wrapping_mul(6364136223846793005)
                            .wrapping_add(1442695040888963407);
                        (seed >> 40) as f32 / (1u64 << 20) as f32
                    })
                })
                .collect();
            for reduce in [crate::params::Reduce::Average, crate::params::Reduce::Point] {
                for lanes in [16, 5] {
                    let mut got = vec![-1.0f32; 16 * 8];
                    reduce_strip(reduce, &bins, lanes, &mut got);
                    for i in 0..16 {
                        let texel: Vec<f32> = bins.iter().map(|v| v[i]).collect();
                        let mut want = [-1.0f32; 8];
                        if i < lanes {
                            reduce_into(reduce, &texel, &mut want);
                        }
                        for c in 0..8 {
                            assert_eq!(
                                got[i * 8 + c].to_bits(),
                                want[c].to_bits(),
                                "{b} bins, {reduce:?}, {lanes} lanes, texel {i} channel {c}"
                            );
                        }
                    }
                }
            }
        }
    }

    /// A kernel that only reports its size and cost.
    struct Costed(usize, usize, f64);
    impl HorizonRows for Costed {
        fn width(&self) -> usize {
            self.0
        }
        fn height(&self) -> usize {
            self.1
        }
        fn bins(&self) -> usize {
            32
        }
        fn rows(&self, _: usize, _: &mut [f32], _: Option<&mut [f32]>) {}
        fn texel_cost(&self) -> f64 {
            self.2
        }
    }

    #[test]
    fn bands_shrink_with_texel_cost_down_to_one_row() {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(2).build().unwrap();
        pool.install(|| {
            // Default cost: balance decides (2048 / (2 · 16) = 64 rows of 2048 texels).
            assert_eq!(band_rows_for(&Costed(2048, 2048, 1.0)), 64);
            assert_eq!(band_rows(2048, 2048), 64);
            // R = 128 costs 64×: 262144 / 64 / 2048 = 2 rows, the same work as 128 cheap rows.
            assert_eq!(band_rows_for(&Costed(2048, 2048, 64.0)), 2);
            // Anything dearer still makes progress a row at a time.
            assert_eq!(band_rows_for(&Costed(8192, 8192, 4096.0)), 1);
            // Costs below 1 never make bands larger than the default.
            assert_eq!(band_rows_for(&Costed(2048, 2048, 0.01)), 64);
        });
    }

    #[test]
    fn lengyel_cost_grows_with_the_disc() {
        let h = vec![0f32; 64 * 64];
        let g = Grid::new(64, 64, &h, Edge::Wrap, YAxis::Up);
        let cost = |r, b| lengyel::LengyelFast::new(g, r, b).texel_cost();
        assert_eq!(cost(16, 32), 1.0);
        assert_eq!(cost(64, 32), 16.0);
        assert_eq!(cost(128, 64), 128.0);
    }
}
