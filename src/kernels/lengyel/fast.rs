//! The Lengyel/Max horizon map, fast: the same function as the oracle in [`super::oracle`],
//! vectorised across texels (SPEC §3.1).
//!
//! The oracle loops texel → neighbour → bin, which is branchy scalar work. Here the loop is
//! turned inside out so that the hot loop is "load, subtract, multiply, max" over contiguous
//! memory, which LLVM vectorises:
//! - once per kernel, every neighbour offset is assigned the bins it touches, computed in f64
//!   exactly as the oracle does (so both agree on which neighbour feeds which bin), and offsets
//!   with the same range of bins form a group;
//! - each band of rows is copied into a padded tile (wrapped, or filled with `f32::MIN` for
//!   `edge=none`, which never occludes), so the hot loop never clamps or wraps;
//! - for a strip of consecutive texels ([`lanes`]): group → offset → lane, keeping max(tan) with
//!   tan = (h − h0)/r from 0, so each neighbour is evaluated once, not once per bin it touches;
//!   max(tan, 0)² is exactly the oracle's value, in any merge order;
//! - groups sharing a first bin form a run with one running maximum, snapshotted after each
//!   group, and bins are finished in order while their snapshots are still in L1; the finish
//!   (sin α, the channel averages, the packing) is vectorised too.
//!
//! The hot function is compiled three times (AVX-512, AVX2+FMA, baseline) and the variant is
//! chosen once per kernel at run time, so the release binary needs no `-C target-cpu`.
//!
//! Precision: tan is computed in f32 (relative error a few ulp), the oracle works in f64; the
//! results agree within ~1e-6, so the 8-bit outputs only differ where the oracle's value sits
//! on a rounding tie. When the padded tile would exceed [`MAX_TILE`] floats (a radius of
//! thousands of texels) the kernel falls back to the oracle, correct and bounded in memory.
//! docs/lengyel.md has the full account and the measurements behind each step.

use super::LengyelNaive;
use crate::kernels::isa::Isa;
use crate::kernels::{Grid, HorizonRows};
use crate::params::Edge;
use crate::progress::Progress;
use std::cell::RefCell;
use std::f64::consts::PI;

/// The widest strip of any variant ([`lanes`]): the tile keeps this many spare columns
/// and every strip's window is checked against it.
pub const STRIP: usize = 128;

/// Largest padded tile (floats, per thread) before falling back to the oracle (64 MiB).
pub const MAX_TILE: usize = 1 << 24;

/// Height used outside the map with `edge=none`: h − h0 ≤ 0 for every finite h0, so it never
/// raises a bin, and it never makes NaN (unlike −∞ − −∞ in the discarded lanes).
const LOW: f32 = f32::MIN;

/// Texels per strip in this variant's hot loop; chosen by measurement (docs/lengyel.md,
/// "Constants").
const fn lanes(isa: Isa) -> usize {
    match isa {
        Isa::Avx512 => 128,
        Isa::Avx2 => 64,
        Isa::Baseline => 16,
    }
}

/// Neighbours that touch the same run of bins `lo ..= lo + span − 1` (mod B): their maximum
/// tan is computed once and then merged into each of those bins.
#[derive(Debug, Clone, Copy)]
struct Group {
    lo: usize,
    span: usize,
    /// `entries[start..end]`.
    start: usize,
    end: usize,
    /// Whether the previous group has the same `lo` (and a wider span): the running maximum
    /// carries on from it.
    continues: bool,
}

/// Per-(radius, bins, edge, y_axis, map size) tables: the neighbours, grouped by bin range.
#[derive(Debug, Clone)]
struct Tables {
    groups: Vec<Group>,
    /// (offset from the strip's top-left corner in the padded tile, 1/r), grouped.
    entries: Vec<(u32, f32)>,
    /// For each channel, the B/8 + 1 bins it averages.
    average: Vec<u32>,
    /// Where each group's snapshot is kept, `0..slots`.
    slot: Vec<u32>,
    slots: usize,
    /// `cover[cover_start[n]..cover_start[n + 1]]`: the slots of the snapshots bin n merges,
    /// one per run covering it.
    cover_start: Vec<usize>,
    cover: Vec<u32>,
    /// `groups[..ready[n]]` are every group bin n (and every earlier bin) reads.
    ready: Vec<usize>,
    /// Largest entry offset + STRIP: the window of the tile one strip reads.
    reach: usize,
    /// Padding columns on each side and rows above/below.
    pad_x: usize,
    pad_y: usize,
    /// Row stride of the padded tile: W + 2·pad_x + STRIP (room for the last strip's lanes).
    stride: usize,
    /// Rows per tile so it stays under MAX_TILE.
    max_rows: usize,
}

#[derive(Debug, Clone)]
enum Mode<'a> {
    Fast(Tables),
    /// Radius too large for a padded tile: the oracle, slow but bounded in memory.
    Oracle(LengyelNaive<'a>),
}

/// The fast Lengyel kernel for one grid.
#[derive(Debug, Clone)]
pub struct LengyelFast<'a> {
    grid: Grid<'a>,
    radius: usize,
    bins: usize,
    isa: Isa,
    mode: Mode<'a>,
    /// Watched between strips: a band is one row at large radii, and one row can still take
    /// seconds (R ≈ 700 on an 8192-wide map).
    cancel: Option<Progress>,
}

impl<'a> LengyelFast<'a> {
    /// Prepares the kernel, choosing the CPU variant at run time. `radius ≥ 1`, `bins` a
    /// multiple of 16 (validated by `params`).
    pub fn new(grid: Grid<'a>, radius: u32, bins: u32) -> Self {
        Self::with_isa(grid, radius, bins, Isa::detect())
    }

    /// Prepares the kernel with a given variant (tests and benches compare them). A variant the
    /// CPU lacks is replaced by the best one it has.
    pub fn with_isa(grid: Grid<'a>, radius: u32, bins: u32, isa: Isa) -> Self {
        let isa = isa.or_detected();
        let b = bins.max(1) as usize;
        let r = radius.max(1) as usize;
        let (w, h) = (grid.width, grid.height);
        // With edge=none an offset reaching past the whole map never finds a neighbour: drop
        // it and pad less. With wrap every offset is real and the padding wraps as needed.
        let (pad_x, pad_y) = match grid.edge {
            Edge::Wrap => (r - 1, r - 1),
            Edge::None => ((r - 1).min(w.saturating_sub(1)), (r - 1).min(h.saturating_sub(1))),
        };
        let stride = w + 2 * pad_x + STRIP;
        let one_row = stride.saturating_mul(2 * pad_y + 1);
        let mode = if one_row > MAX_TILE {
            Mode::Oracle(LengyelNaive::new(grid, radius, bins))
        } else {
            let max_rows = (MAX_TILE / stride - 2 * pad_y).max(1);
            Mode::Fast(build_tables(r, b, pad_x, pad_y, stride, max_rows, grid.row_step()))
        };
        LengyelFast { grid, radius: r, bins: b, isa, mode, cancel: None }
    }

    /// Makes [`HorizonRows::rows`] return early (leaving the rest of its rows unspecified) once
    /// `progress` is canceled, checking between strips of one row (and between neighbour rows
    /// on the oracle fallback); the band driver then discards the band.
    pub fn with_cancel(mut self, progress: &Progress) -> Self {
        self.mode = match self.mode {
            Mode::Oracle(k) => Mode::Oracle(k.with_cancel(progress)),
            fast => fast,
        };
        self.cancel = Some(progress.clone());
        self
    }

    /// The CPU variant in use.
    pub fn isa(&self) -> Isa {
        self.isa
    }

    /// Whether the radius forced the oracle fallback.
    pub fn is_fallback(&self) -> bool {
        matches!(self.mode, Mode::Oracle(_))
    }
}

/// Builds the per-bin neighbour lists. θ, δ and the bin range are computed in f64 with the
/// oracle's exact expressions, so the same neighbours feed the same bins.
fn build_tables(
    r: usize,
    b: usize,
    pad_x: usize,
    pad_y: usize,
    stride: usize,
    max_rows: usize,
    row_step: i64,
) -> Tables {
    let r = r as i64;
    let scale = b as f64 / (2.0 * PI);
    let mut per_offset: Vec<(u32, f32, i64, i64)> = Vec::new();
    for j in (1 - r)..r {
        for i in (1 - r)..r {
            let d2 = (i * i + j * j) as f64;
            if d2 == 0.0 || d2 >= (r * r) as f64 {
                continue;
            }
            if i.unsigned_abs() as usize > pad_x || j.unsigned_abs() as usize > pad_y {
                continue; // edge=none, beyond the whole map
            }
            let theta = (j as f64).atan2(i as f64);
            let delta = (2f64.sqrt() / (2.0 * d2.sqrt())).atan();
            let lo = ((theta - delta) * scale).floor() as i64;
            let hi = ((theta + delta) * scale).ceil() as i64;
            let row = (pad_y as i64 + j * row_step) as usize;
            let col = (pad_x as i64 + i) as usize;
            // Fits: the tile is at most MAX_TILE < 2^32 floats.
            let off = (row * stride + col) as u32;
            per_offset.push((off, (1.0 / d2.sqrt()) as f32, lo, hi));
        }
    }
    // Group by (first bin mod B, number of bins); a range as wide as 2π covers every bin once.
    // Every offset lands in exactly one group, so the hot loop evaluates it once, instead of
    // once per bin it touches (2.2–3.6 times on average): a max over the same values, merged in
    // another order, so the result is identical.
    let mut keyed: Vec<(usize, usize, u32, f32)> = per_offset
        .iter()
        .map(|&(off, inv, lo, hi)| {
            let span = ((hi - lo + 1) as usize).min(b);
            let lo = if span == b { 0 } else { lo.rem_euclid(b as i64) as usize };
            (lo, span, off, inv)
        })
        .collect();
    // Groups with the same first bin form a run, widest first: the hot loop carries one
    // running maximum through a run and snapshots it at the end of each group, so a snapshot
    // is the maximum over every neighbour covering bins lo .. lo + span − 1 of that run. A bin
    // then merges one snapshot per run instead of one per group (R=16, B=32: 164 merges per
    // strip instead of 368).
    let mut widest = vec![0usize; b];
    for &(lo, span, _, _) in &keyed {
        widest[lo] = widest[lo].max(span);
    }
    // Runs that wrap past bin B−1 first (bin 0 needs them), then by first bin: the hot loop
    // computes runs just before the first bin that needs them, so their snapshots are still in
    // L1 when read. Stable: within a group, offsets stay in row-major order (memory locality).
    keyed.sort_by_key(|&(lo, span, _, _)| (lo + widest[lo] <= b, lo, std::cmp::Reverse(span)));
    let mut groups: Vec<Group> = Vec::new();
    let mut entries = Vec::with_capacity(keyed.len());
    for (k, &(lo, span, off, inv)) in keyed.iter().enumerate() {
        match groups.last_mut() {
            Some(g) if g.lo == lo && g.span == span => g.end = k + 1,
            last => {
                let continues = last.is_some_and(|g| g.lo == lo);
                groups.push(Group { lo, span, start: k, end: k + 1, continues })
            }
        }
        entries.push((off, inv));
    }
    let reach = entries.iter().map(|&(off, _)| off as usize).max().unwrap_or(0) + STRIP;
    // The snapshot bin n reads from each run: that of the narrowest group still covering n,
    // i.e. group k covers bins lo + (span of group k + 1) .. lo + span − 1 for its run.
    let own = |gi: usize| {
        let g = &groups[gi];
        let next = groups.get(gi + 1).filter(|h| h.continues).map_or(0, |h| h.span);
        (next..g.span).map(move |k| (g.lo + k) % b)
    };
    let mut cover_start = vec![0usize; b + 1];
    for gi in 0..groups.len() {
        for n in own(gi) {
            cover_start[n + 1] += 1;
        }
    }
    for n in 0..b {
        cover_start[n + 1] += cover_start[n];
    }
    let mut fill = cover_start.clone();
    let mut cover = vec![0u32; cover_start[b]];
    for gi in 0..groups.len() {
        for n in own(gi) {
            cover[fill[n]] = gi as u32;
            fill[n] += 1;
        }
    }
    // Groups in that order needed by bins 0 ..= n: the wrapping runs and those starting ≤ n.
    let ready: Vec<usize> = (0..b)
        .map(|n| groups.iter().filter(|g| g.lo + widest[g.lo] > b || g.lo <= n).count())
        .collect();
    // Snapshot slots, reused once the last bin reading a snapshot is done: one slot per group
    // would make the strip's snapshots 52 KB at 128 lanes, beside a 32 KB L1; live snapshots are
    // a fraction of them (R=16, B=32: 20 slots for 104 groups).
    let last_read = |gi: usize| own(gi).max().unwrap_or(0);
    let mut slot = vec![0u32; groups.len()];
    let mut free: Vec<u32> = Vec::new();
    let mut slots = 0u32;
    let mut made = 0;
    for (n, &rdy) in ready.iter().enumerate() {
        for (gi, sl) in slot.iter_mut().enumerate().take(rdy).skip(made) {
            *sl = free.pop().unwrap_or_else(|| {
                slots += 1;
                slots - 1
            });
            debug_assert!(last_read(gi) >= n);
        }
        made = made.max(rdy);
        free.extend((0..made).filter(|&gi| last_read(gi) == n).map(|gi| slot[gi]));
    }
    for c in &mut cover {
        *c = slot[*c as usize];
    }
    // Channel c averages the B/8 + 1 bins centred on bin c·B/8 (mod B).
    let (step, half) = (b / 8, b / 16);
    let average = (0..8)
        .flat_map(|c| (0..=2 * half).map(move |k| ((c * step + b + k - half) % b) as u32))
        .collect();
    Tables {
        average,
        groups,
        slot,
        slots: slots as usize,
        entries,
        cover_start,
        cover,
        ready,
        reach,
        pad_x,
        pad_y,
        stride,
        max_rows,
    }
}

impl HorizonRows for LengyelFast<'_> {
    fn width(&self) -> usize {
        self.grid.width
    }
    fn height(&self) -> usize {
        self.grid.height
    }
    fn bins(&self) -> usize {
        self.bins
    }
    fn texel_cost(&self) -> f64 {
        // The work per texel grows with the neighbours in the disc (∝ R²) and, past 32, with
        // the bins each spans; the oracle fallback does the same work without SIMD (~100×).
        let r = self.radius as f64 / 16.0;
        let cost = r * r * (self.bins as f64 / 32.0).max(1.0);
        match self.mode {
            Mode::Fast(_) => cost,
            Mode::Oracle(_) => cost * 100.0,
        }
    }
    fn rows(&self, y0: usize, channels: &mut [f32], mut bins_out: Option<&mut [f32]>) {
        let t = match &self.mode {
            Mode::Oracle(k) => return k.rows(y0, channels, bins_out),
            Mode::Fast(t) => t,
        };
        let w = self.grid.width;
        let b = self.bins;
        let n = channels.len() / (w * 8).max(1);
        SCRATCH.with(|cell| {
            let mut fresh = Scratch::default();
            let mut guard = cell.try_borrow_mut();
            let scratch = match guard.as_deref_mut() {
                Ok(s) => s,
                Err(_) => &mut fresh,
            };
            let mut r0 = 0;
            while r0 < n {
                let m = t.max_rows.min(n - r0);
                if self.cancel.as_ref().is_some_and(Progress::is_canceled) {
                    return;
                }
                fill_tile(&self.grid, t, y0 + r0, m, &mut scratch.tile);
                // Per-bin results, then per-group maxima.
                scratch.acc.resize((b + t.slots) * lanes(self.isa), 0.0);
                let ch = &mut channels[r0 * w * 8..(r0 + m) * w * 8];
                let bo = bins_out.as_deref_mut().map(|bo| &mut bo[r0 * w * b..(r0 + m) * w * b]);
                let job = Job {
                    t,
                    tile: &scratch.tile,
                    rows: m,
                    width: w,
                    bins: b,
                    cancel: self.cancel.as_ref(),
                };
                run_job(self.isa, &job, &mut scratch.acc, ch, bo);
                r0 += m;
            }
        });
    }
}

/// Per-thread buffers reused across bands, so the band loop does not allocate.
#[derive(Default)]
struct Scratch {
    tile: Vec<f32>,
    /// `bins` per-bin results followed by the snapshot slots, each one strip wide.
    acc: Vec<f32>,
}

thread_local! {
    static SCRATCH: RefCell<Scratch> = RefCell::new(Scratch::default());
}

/// Copies image rows `y0 .. y0 + m` and their padding into `tile` (`(m + 2·pad_y) · stride`).
fn fill_tile(g: &Grid<'_>, t: &Tables, y0: usize, m: usize, tile: &mut Vec<f32>) {
    let (w, h) = (g.width as i64, g.height as i64);
    let rows = m + 2 * t.pad_y;
    tile.clear();
    tile.resize(rows * t.stride, LOW);
    // Tile row 0 is image row y0 − pad_y; offsets were laid out with the y-axis sign already.
    for (tr, dst) in tile.chunks_exact_mut(t.stride).enumerate() {
        let iy = y0 as i64 + tr as i64 - t.pad_y as i64;
        let src_row = match g.edge {
            Edge::Wrap => iy.rem_euclid(h),
            Edge::None if iy < 0 || iy >= h => continue, // stays LOW
            Edge::None => iy,
        } as usize;
        let src = &g.heights[src_row * g.width..(src_row + 1) * g.width];
        let px = t.pad_x;
        dst[px..px + g.width].copy_from_slice(src);
        if g.edge == Edge::Wrap {
            // Only the padding columns: a test per column of the whole row cost ~1.5%.
            let (left, right) = dst.split_at_mut(px);
            let right = &mut right[g.width..];
            for (tc, d) in left.iter_mut().enumerate() {
                *d = src[(tc as i64 - px as i64).rem_euclid(w) as usize];
            }
            for (tc, d) in right.iter_mut().enumerate() {
                *d = src[((g.width + tc) as i64).rem_euclid(w) as usize];
            }
        }
    }
}

/// One tile's worth of work for the hot loop.
struct Job<'a> {
    t: &'a Tables,
    tile: &'a [f32],
    rows: usize,
    width: usize,
    bins: usize,
    cancel: Option<&'a Progress>,
}

/// Runs the variant of [`job_body`] compiled for `isa`.
fn run_job(
    isa: Isa,
    job: &Job<'_>,
    acc: &mut [f32],
    channels: &mut [f32],
    bins_out: Option<&mut [f32]>,
) {
    #[cfg(target_arch = "x86_64")]
    {
        match isa {
            // SAFETY: a kernel holds Avx512 / Avx2 only when `Isa::supported` saw those features
            // on this CPU (`with_isa` replaces anything else), which is the one requirement of
            // calling a `#[target_feature]` function.
            Isa::Avx512 => return unsafe { job_avx512(job, acc, channels, bins_out) },
            Isa::Avx2 => return unsafe { job_avx2(job, acc, channels, bins_out) },
            Isa::Baseline => {}
        }
    }
    let _ = isa;
    // SAFETY: `Portable` uses no CPU feature beyond the compile target's.
    unsafe { job_body::<{ lanes(Isa::Baseline) }, Portable>(job, acc, channels, bins_out) }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
fn job_avx512(job: &Job<'_>, acc: &mut [f32], channels: &mut [f32], bins_out: Option<&mut [f32]>) {
    // SAFETY: this function only runs where avx512f is present, which `Avx512` needs.
    unsafe { job_body::<{ lanes(Isa::Avx512) }, Avx512>(job, acc, channels, bins_out) }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn job_avx2(job: &Job<'_>, acc: &mut [f32], channels: &mut [f32], bins_out: Option<&mut [f32]>) {
    // SAFETY: `Avx2` uses no CPU feature beyond those of `job_avx2`.
    unsafe { job_body::<{ lanes(Isa::Avx2) }, Avx2>(job, acc, channels, bins_out) }
}

/// What differs between the compiled variants besides the instruction set LLVM targets.
trait Variant {
    /// Keep one running maximum per group rather than two interleaved ones: enough when a
    /// strip is 8 or more vectors wide (that many independent max() chains), and the second
    /// set would not fit in the registers.
    const ONE_MAX: bool = false;
    /// Take maxima as signed integers over the f32 bits (see [`raise`]); a constant, so the
    /// choice folds away in each variant.
    const INT_MAX: bool;
    /// Turns a bin's max(tan) lanes into s = t/√(t²+1); correctly rounded unless a variant
    /// has something faster.
    ///
    /// # Safety
    /// The running CPU must have the features the implementation uses.
    #[inline(always)]
    unsafe fn finish<const L: usize>(a: &mut [f32; L]) {
        finish_exact(a)
    }
    /// Whether the variant's features include AVX, for the transposing [`Variant::pack`].
    const AVX: bool = false;
    /// Writes channel-major `ch` texel-major into `dst` (8 floats per texel, up to L texels).
    ///
    /// # Safety
    /// The running CPU must have the features the implementation uses.
    #[inline(always)]
    unsafe fn pack<const L: usize>(ch: &[[f32; L]; 8], dst: &mut [f32]) {
        #[cfg(target_arch = "x86_64")]
        if Self::AVX {
            // SAFETY: `AVX` is only set by variants whose features include AVX, and the
            // caller guarantees those features (this trait's contract).
            unsafe { pack_avx(ch, dst) };
            return;
        }
        pack_scalar(ch, dst, 0)
    }
}

/// [`Variant::pack`] from texel `from` on, one float at a time.
#[inline(always)]
fn pack_scalar<const L: usize>(ch: &[[f32; L]; 8], dst: &mut [f32], from: usize) {
    for (k, d) in dst.chunks_exact_mut(8).enumerate().skip(from) {
        for (c, v) in d.iter_mut().enumerate() {
            *v = ch[c][k];
        }
    }
}

/// [`Variant::pack`] with 8×8 AVX transposes (24 shuffles per 8 texels): done one float at a
/// time, LLVM emitted 64 scalar loads and stores per 8 texels, ~5% of the kernel.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx")]
#[inline]
fn pack_avx<const L: usize>(ch: &[[f32; L]; 8], dst: &mut [f32]) {
    use std::arch::x86_64::*;
    let full = dst.len() / 64;
    for (blk, out) in dst.chunks_exact_mut(64).enumerate().take(full) {
        let k = blk * 8;
        // SAFETY: k + 8 ≤ dst.len() / 8 ≤ L, so each row's 8 floats at k are in bounds.
        let r: [__m256; 8] =
            std::array::from_fn(|c| unsafe { _mm256_loadu_ps(ch[c][k..].as_ptr()) });
        let t0 = _mm256_unpacklo_ps(r[0], r[1]);
        let t1 = _mm256_unpackhi_ps(r[0], r[1]);
        let t2 = _mm256_unpacklo_ps(r[2], r[3]);
        let t3 = _mm256_unpackhi_ps(r[2], r[3]);
        let t4 = _mm256_unpacklo_ps(r[4], r[5]);
        let t5 = _mm256_unpackhi_ps(r[4], r[5]);
        let t6 = _mm256_unpacklo_ps(r[6], r[7]);
        let t7 = _mm256_unpackhi_ps(r[6], r[7]);
        let u0 = _mm256_shuffle_ps::<0x44>(t0, t2);
        let u1 = _mm256_shuffle_ps::<0xEE>(t0, t2);
        let u2 = _mm256_shuffle_ps::<0x44>(t1, t3);
        let u3 = _mm256_shuffle_ps::<0xEE>(t1, t3);
        let u4 = _mm256_shuffle_ps::<0x44>(t4, t6);
        let u5 = _mm256_shuffle_ps::<0xEE>(t4, t6);
        let u6 = _mm256_shuffle_ps::<0x44>(t5, t7);
        let u7 = _mm256_shuffle_ps::<0xEE>(t5, t7);
        let o = [
            _mm256_permute2f128_ps::<0x20>(u0, u4),
            _mm256_permute2f128_ps::<0x20>(u1, u5),
            _mm256_permute2f128_ps::<0x20>(u2, u6),
            _mm256_permute2f128_ps::<0x20>(u3, u7),
            _mm256_permute2f128_ps::<0x31>(u0, u4),
            _mm256_permute2f128_ps::<0x31>(u1, u5),
            _mm256_permute2f128_ps::<0x31>(u2, u6),
            _mm256_permute2f128_ps::<0x31>(u3, u7),
        ];
        for (d, v) in out.chunks_exact_mut(8).zip(o) {
            // SAFETY: `d` holds exactly 8 floats.
            unsafe { _mm256_storeu_ps(d.as_mut_ptr(), v) };
        }
    }
    pack_scalar(ch, dst, full * 8);
}

/// SSE2: float maxima (it has no 32-bit integer max), correctly rounded square root and
/// divide.
struct Portable;

impl Variant for Portable {
    const INT_MAX: bool = false;
}

/// AVX2: integer maxima, correctly rounded square root and divide.
struct Avx2;

impl Variant for Avx2 {
    const INT_MAX: bool = true;
    const ONE_MAX: bool = true;
    const AVX: bool = true;
}

/// AVX-512: integer maxima, 14-bit reciprocal square root and one Newton step.
struct Avx512;

impl Variant for Avx512 {
    const INT_MAX: bool = true;
    const ONE_MAX: bool = true;
    const AVX: bool = true;
    #[inline(always)]
    unsafe fn finish<const L: usize>(a: &mut [f32; L]) {
        #[cfg(target_arch = "x86_64")]
        // SAFETY: the caller guarantees avx512f (this trait's contract).
        unsafe {
            finish_rsqrt14(a)
        }
        #[cfg(not(target_arch = "x86_64"))]
        finish_exact(a)
    }
}

/// s = t/√(t²+1) with t capped so t² stays finite (s is 1.0 in f32 long before 1e18).
#[inline(always)]
fn finish_exact<const L: usize>(a: &mut [f32; L]) {
    for v in a.iter_mut() {
        let tt = v.min(1e18);
        *v = tt / (tt * tt + 1.0).sqrt();
    }
}

/// `*acc = max(*acc, v)` where the accumulator starts at +0 and only its final value if
/// positive matters. With `int` the f32 bits are compared as i32: for non-negative floats
/// (+∞ included) that is the same order, and every negative float is a negative integer, so
/// it never beats the +0 start, as in max(·, 0). That matters on Zen 4: float max shares the
/// two add pipes with the subtraction (2 cycles per 512-bit neighbour), integer max issues on
/// any of the four (measured ~1.4× on the three-operation chain). NaN cannot occur: heights
/// are finite, so h − h0 is finite or ±∞ and 1/r is finite and positive.
#[inline(always)]
fn raise(int: bool, acc: &mut f32, v: f32) {
    if int {
        *acc = f32::from_bits((acc.to_bits() as i32).max(v.to_bits() as i32) as u32);
    } else {
        *acc = if v > *acc { v } else { *acc };
    }
}

/// s = t·rsqrt(t² + 1): a divide and a square root cost ~20% of the kernel on Zen 4 (their
/// 512-bit forms issue every 5–6 cycles), this costs six pipelined operations. The 14-bit
/// estimate after one Newton step is within ~2^-22 relative, far inside the 1e-5 the results
/// promise, and is clamped so s never exceeds 1.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
#[inline]
fn finish_rsqrt14<const L: usize>(a: &mut [f32; L]) {
    use std::arch::x86_64::*;
    let (one, half, three_halves, cap) =
        (_mm512_set1_ps(1.0), _mm512_set1_ps(0.5), _mm512_set1_ps(1.5), _mm512_set1_ps(1e18));
    for c in a.chunks_exact_mut(16) {
        // SAFETY: `c` holds exactly 16 floats; unaligned loads and stores.
        let t = _mm512_min_ps(unsafe { _mm512_loadu_ps(c.as_ptr()) }, cap);
        let x = _mm512_fmadd_ps(t, t, one);
        let y = _mm512_rsqrt14_ps(x);
        let y = _mm512_mul_ps(
            y,
            _mm512_fnmadd_ps(_mm512_mul_ps(x, half), _mm512_mul_ps(y, y), three_halves),
        );
        let s = _mm512_min_ps(_mm512_mul_ps(t, y), one);
        unsafe { _mm512_storeu_ps(c.as_mut_ptr(), s) };
    }
}

/// The hot loop over one padded tile, for strips of `L` texels, inlined into each
/// `#[target_feature]` variant so LLVM vectorises it for that instruction set.
///
/// # Safety
/// The running CPU must have the features `V` uses.
#[inline(always)]
unsafe fn job_body<const L: usize, V: Variant>(
    job: &Job<'_>,
    acc: &mut [f32],
    channels: &mut [f32],
    mut bins_out: Option<&mut [f32]>,
) {
    let Job { t, tile, rows, width: w, bins: b, cancel } = *job;
    let centre = t.pad_y * t.stride + t.pad_x;
    let step = b / 8;
    let inv_count = 1.0 / (step + 1) as f32;
    let (acc, gmax) = acc.as_chunks_mut::<L>().0.split_at_mut(b);
    for r in 0..rows {
        for x0 in (0..w).step_by(L) {
            // One relaxed load per strip, against L·πR² neighbours of work.
            if cancel.is_some_and(Progress::is_canceled) {
                return;
            }
            let base = r * t.stride + x0;
            let Some(h0) = tile.get(base + centre..).and_then(<[f32]>::first_chunk::<L>) else {
                continue; // unreachable: the tile has STRIP ≥ L spare columns
            };
            // The strip's whole neighbourhood, checked once here so the hot loop need not.
            let Some(win) = tile.get(base..base + t.reach) else {
                continue; // unreachable: the tile holds every strip's neighbourhood
            };
            let mut done = 0;
            let mut run = [[0f32; L]; 2];
            for (n, out) in acc.iter_mut().enumerate() {
                // The groups bin n is the first to need, just before it reads them.
                for (g, &sl) in t.groups[done..t.ready[n]].iter().zip(&t.slot[done..]) {
                    let gm = &mut gmax[sl as usize];
                    if !g.continues {
                        run = [[0f32; L]; 2];
                    }
                    // SAFETY: `win.len() == t.reach` and every entry's offset + STRIP ≤ t.reach
                    // (`reach` is that maximum, computed in `build_tables`), with L ≤ STRIP.
                    unsafe {
                        accumulate(
                            V::INT_MAX,
                            V::ONE_MAX,
                            win,
                            h0,
                            &t.entries[g.start..g.end],
                            &mut run,
                        )
                    };
                    *gm = run[0];
                    if !V::ONE_MAX {
                        for (m, &y) in gm.iter_mut().zip(&run[1]) {
                            raise(V::INT_MAX, m, y);
                        }
                    }
                }
                done = done.max(t.ready[n]);
                // Each bin is the max over the groups covering it, gathered into a register
                // accumulator: scattering each group into its bins instead made LLVM emit masked
                // read-modify-write stores, ~20% of the kernel's time (perf, Zen 4).
                let mut a = [0f32; L];
                for &sl in &t.cover[t.cover_start[n]..t.cover_start[n + 1]] {
                    let m = &gmax[sl as usize];
                    for (x, &y) in a.iter_mut().zip(m) {
                        raise(V::INT_MAX, x, y);
                    }
                }
                // SAFETY: the caller guarantees V's features.
                unsafe { V::finish(&mut a) };
                *out = a;
            }
            let lanes = L.min(w - x0);
            let mut ch = [[0f32; L]; 8];
            for (chc, bins) in ch.iter_mut().zip(t.average.chunks_exact(step + 1)) {
                // Summed in a local so it stays in registers: summed in place, each add waited
                // on the store of the previous one (~6% of the kernel).
                let mut sum = [0f32; L];
                for &n in bins {
                    for (o, &s) in sum.iter_mut().zip(&acc[n as usize]) {
                        *o += s;
                    }
                }
                for (o, s) in chc.iter_mut().zip(sum) {
                    *o = s * inv_count;
                }
            }
            let row0 = (r * w + x0) * 8;
            // SAFETY: the caller guarantees V's features.
            unsafe { V::pack(&ch, &mut channels[row0..row0 + lanes * 8]) };
            if let Some(bo) = bins_out.as_deref_mut() {
                let row0 = (r * w + x0) * b;
                for (k, dst) in bo[row0..row0 + lanes * b].chunks_exact_mut(b).enumerate() {
                    for (n, d) in dst.iter_mut().enumerate() {
                        *d = acc[n][k];
                    }
                }
            }
        }
    }
}

/// Raises `acc` (two interleaved partial maxima, or only the first with `one`) to the
/// max of (h − h0)·(1/r) over `entries` for the L texels whose neighbourhood is `win`. Two
/// accumulators for narrow strips so consecutive max() operations do not wait on each other.
///
/// # Safety
/// Every entry's offset + L must be ≤ `win.len()`. The loads are unchecked because the
/// two bounds checks per neighbour (and the register they cost) took ~10% of the kernel's time;
/// the caller checks the whole window once per strip instead.
#[inline(always)]
unsafe fn accumulate<const L: usize>(
    int: bool,
    one: bool,
    win: &[f32],
    h0: &[f32; L],
    entries: &[(u32, f32)],
    acc: &mut [[f32; L]; 2],
) {
    debug_assert!(entries.iter().all(|&(off, _)| off as usize + L <= win.len()));
    let load = |off: u32| -> &[f32; L] {
        // SAFETY: off + L ≤ win.len() (this function's contract), so the L floats
        // starting at `off` are inside `win`; [f32; L] has the alignment of f32.
        unsafe { &*win.as_ptr().add(off as usize).cast::<[f32; L]>() }
    };
    let [a0, a1] = acc;
    if one {
        // Eight or more vectors per neighbour already make enough independent max() chains;
        // a second set of accumulators would not fit in the registers.
        for &(off, inv) in entries {
            let s0 = load(off);
            for k in 0..L {
                let v0 = (s0[k] - h0[k]) * inv;
                raise(int, &mut a0[k], v0);
            }
        }
        return;
    }
    let mut pairs = entries.chunks_exact(2);
    for p in &mut pairs {
        let (s0, s1) = (load(p[0].0), load(p[1].0));
        let (i0, i1) = (p[0].1, p[1].1);
        for k in 0..L {
            let v0 = (s0[k] - h0[k]) * i0;
            let v1 = (s1[k] - h0[k]) * i1;
            raise(int, &mut a0[k], v0);
            raise(int, &mut a1[k], v1);
        }
    }
    for &(off, inv) in pairs.remainder() {
        let s0 = load(off);
        for k in 0..L {
            let v0 = (s0[k] - h0[k]) * inv;
            raise(int, &mut a0[k], v0);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kernels::compute_all;
    use crate::params::YAxis;
    use crate::progress::Progress;

    #[test]
    fn single_wall_east_of_texel_matches_hand_value() {
        let mut h = vec![0.0f32; 9];
        h[2] = 2.0;
        let g = Grid::new(9, 1, &h, Edge::None, YAxis::Up);
        let k = LengyelFast::new(g, 4, 32);
        let mut ch = vec![0.0f32; 9 * 8];
        let mut bins = vec![0.0f32; 9 * 32];
        k.rows(0, &mut ch, Some(&mut bins));
        // tan = 1 → s = √½ on bins 30, 31, 0, 1, 2 (δ ≈ 0.34 rad); nothing elsewhere.
        let expect = (0.5f64).sqrt() as f32;
        for n in [30usize, 31, 0, 1, 2] {
            assert!((bins[n] - expect).abs() < 1e-6, "bin {n}: {}", bins[n]);
        }
        assert_eq!(bins[3], 0.0);
        assert_eq!(bins[16], 0.0);
        // Channel 0 averages bins 30..=2, all √½.
        assert!((ch[0] - expect).abs() < 1e-6);
        assert_eq!(ch[4], 0.0);
    }

    #[test]
    fn every_isa_agrees_with_the_oracle() {
        let (w, h) = (45, 7);
        let hs: Vec<f32> = (0..w * h).map(|k| ((k * 7919) % 101) as f32 * 0.13).collect();
        let g = Grid::new(w, h, &hs, Edge::Wrap, YAxis::Down);
        let want = compute_all(&LengyelNaive::new(g, 9, 48), &Progress::new()).unwrap();
        for isa in [Isa::Baseline, Isa::Avx2, Isa::Avx512] {
            let got = compute_all(&LengyelFast::with_isa(g, 9, 48, isa), &Progress::new()).unwrap();
            let worst = got.iter().zip(&want).map(|(a, b)| (a - b).abs()).fold(0.0, f32::max);
            assert!(worst < 1e-5, "{isa:?}: {worst}");
        }
    }

    #[test]
    fn bands_split_into_several_tiles_match_the_oracle() {
        // A radius of thousands of texels splits a band into tiles of a few rows; shrink the
        // limit instead so the oracle stays quick.
        let (w, h) = (23, 17);
        let hs: Vec<f32> = (0..w * h).map(|k| ((k * 31) % 17) as f32 * 0.4).collect();
        for edge in [Edge::Wrap, Edge::None] {
            let g = Grid::new(w, h, &hs, edge, YAxis::Up);
            let mut k = LengyelFast::new(g, 7, 32);
            if let Mode::Fast(t) = &mut k.mode {
                t.max_rows = 3;
            }
            let want = compute_all(&LengyelNaive::new(g, 7, 32), &Progress::new()).unwrap();
            let mut got = vec![0.0f32; w * h * 8];
            k.rows(0, &mut got, None);
            let worst = got.iter().zip(&want).map(|(a, b)| (a - b).abs()).fold(0.0, f32::max);
            assert!(worst < 1e-5, "{edge:?}: {worst}");
        }
    }

    #[test]
    fn huge_radius_falls_back_to_the_oracle() {
        let hs = vec![0.0f32, 1.0, 0.5, 2.0];
        let g = Grid::new(2, 2, &hs, Edge::Wrap, YAxis::Up);
        let k = LengyelFast::new(g, 4000, 16);
        assert!(k.is_fallback());
        let small = LengyelFast::new(g, 40, 16);
        assert!(!small.is_fallback());
        let want = compute_all(&LengyelNaive::new(g, 40, 16), &Progress::new()).unwrap();
        let got = compute_all(&small, &Progress::new()).unwrap();
        for (a, b) in got.iter().zip(&want) {
            assert!((a - b).abs() < 1e-5);
        }
    }
    /// Runs `k.rows` over its whole map on this thread, cancels from another after 50 ms, and
    /// asserts that `rows` returned within 3 s with the last texel left unwritten.
    fn assert_cancel_stops_mid_band(k: &LengyelFast<'_>, progress: &Progress) {
        let mut ch = vec![f32::NAN; k.width() * k.height() * 8];
        let p = progress.clone();
        let canceller = std::thread::spawn(move || {
            std::thread::sleep(std::time::Duration::from_millis(50));
            p.cancel();
        });
        let t = std::time::Instant::now();
        k.rows(0, &mut ch, None);
        let took = t.elapsed();
        canceller.join().unwrap();
        assert!(ch.last().unwrap().is_nan(), "the band ran to its end despite the cancel");
        assert!(took.as_secs_f64() < 3.0, "cancel took {took:?}");
    }

    #[test]
    fn a_cancel_stops_a_band_between_strips() {
        // R = 600 on a 4096-wide map: ~90 µs per texel, so the 32-row band is ~10 s of one
        // thread and a single row ~0.4 s; the check between strips of 128 texels answers in ms.
        let (w, h) = (4096, 32);
        let hs: Vec<f32> = (0..w * h).map(|k| ((k * 7919) % 101) as f32 * 0.13).collect();
        let g = Grid::new(w, h, &hs, Edge::Wrap, YAxis::Up);
        let progress = Progress::new();
        let k = LengyelFast::new(g, 600, 32).with_cancel(&progress);
        assert!(!k.is_fallback());
        assert_cancel_stops_mid_band(&k, &progress);
    }

    #[test]
    fn a_cancel_stops_the_oracle_fallback_inside_a_texel() {
        // R = 4000 forces the oracle: (2R)² = 64 M neighbours, about a second per texel.
        let (w, h) = (64, 4);
        let hs: Vec<f32> = (0..w * h).map(|k| ((k * 31) % 17) as f32 * 0.4).collect();
        let g = Grid::new(w, h, &hs, Edge::Wrap, YAxis::Up);
        let progress = Progress::new();
        let k = LengyelFast::new(g, 4000, 32).with_cancel(&progress);
        assert!(k.is_fallback());
        assert_cancel_stops_mid_band(&k, &progress);
    }
}
