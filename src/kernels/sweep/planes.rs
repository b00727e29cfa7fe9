//! Azimuth-major: the kernel's horizons one bin's plane at a time, for callers that fold them
//! (the terrain products' sky-view factor and angle bands), so that no far-field table of
//! W·H·bins is ever held or spilled.
//!
//! The bands ([`HorizonRows::rows`]) need every bin of a few rows at once, and the far field is
//! made a whole plane per azimuth, so between the two the table must wait somewhere. A caller
//! that only sums over bins, or writes each bin to a plane of its own, does not need that: here
//! each azimuth is swept into a plane, the near field and the point at R are joined into it
//! band by band (the same [`Sweep::row_bin`] as the bands, so the same bits), and the sink gets
//! sin α for those rows before the next azimuth is swept. Memory: one plane and the sweep's
//! scratch per azimuth in flight (as many in flight as threads, while they fit in
//! [`SPILL_SWEEP_BYTES`]), whatever the bins; with one in flight (a big map), an azimuth swept
//! along x hands its rows on as it transposes them ([`Sweep::streamed_x`]), so that its plane
//! is never whole either.

use super::*;
use crate::error::{Error, Result};

impl Sweep<'_> {
    /// Whether the kernel was built azimuth-major ([`Options::azimuth_major`]): only
    /// [`Sweep::planes`] gives its horizons.
    pub fn is_azimuth_major(&self) -> bool {
        matches!(self.far, Far::Deferred)
    }

    /// How many bins [`Sweep::planes`] has in flight at once: its chunks of bins are 0 ..
    /// this, then the next as many, and so on. Up to 3 planes of W·H f32 per azimuth in
    /// flight (the plane, and the sweep's sums and its scratch), as for a spilled table, and
    /// no more than threads.
    pub fn planes_in_flight(&self) -> usize {
        let plane = self.grid.width * self.grid.height;
        (SPILL_SWEEP_BYTES / (3 * plane * 4).max(1)).clamp(1, rayon::current_num_threads().max(1))
    }

    /// Every bin's sin α, plane by plane: `sink(b, n, values)` gets band `b` (rows `b·band ..`,
    /// at most `band` of them) of bin `n`, `rows × W` values row-major, the per-bin values the
    /// bands give ([`HorizonRows::rows`]'s `bins_out`) bit for bit. Calls for one band come one
    /// after another (never two at once), each bin once, in the order 0, 1, … bins − 1, so a
    /// sink that sums over bins adds in the order the bands' callers do (the same bits).
    /// Calls for different bands run on the pool's threads at once. `progress` advances by a
    /// band's rows per bin (start it at H·bins); it and the kernel's own are checked for a
    /// cancel between azimuths and bands.
    ///
    /// # Errors
    /// [`Error::Canceled`] when canceled (some bins' planes then were never handed on).
    pub fn planes<S>(&self, band: usize, progress: &Progress, sink: S) -> Result<()>
    where
        S: Fn(usize, usize, &[f32]) + Sync,
    {
        self.planes_then(band, progress, sink, |_| Ok(()))
    }

    /// [`Sweep::planes`], and `done(bins)` once every band of `bins` has been handed to
    /// `sink`, on the calling thread while no sink call runs (so it may use the pool, e.g. to
    /// compress those bins' planes): each bin comes in exactly one `done`, in the order 0, 1, ….
    ///
    /// # Errors
    /// As [`Sweep::planes`], and what `done` fails with (nothing more is swept then).
    pub fn planes_then<S, D>(
        &self,
        band: usize,
        progress: &Progress,
        sink: S,
        mut done: D,
    ) -> Result<()>
    where
        S: Fn(usize, usize, &[f32]) + Sync,
        D: FnMut(&[usize]) -> Result<()>,
    {
        #[cfg(target_arch = "x86_64")]
        let out = if self.wide {
            // SAFETY: `wide` only where the CPU has AVX-512F (see `Sweep::with_options`).
            unsafe { self.planes_avx512(band, progress, &sink, &mut done) }
        } else {
            self.planes_body(band, progress, &sink, &mut done)
        };
        #[cfg(not(target_arch = "x86_64"))]
        let out = self.planes_body(band, progress, &sink, &mut done);
        self.windows.lock().unwrap_or_else(|e| e.into_inner()).clear();
        out
    }

    /// [`Sweep::planes_body`] compiled for AVX-512 (the join, as [`Sweep::rows`] is).
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f")]
    unsafe fn planes_avx512(
        &self,
        band: usize,
        progress: &Progress,
        sink: &(dyn Fn(usize, usize, &[f32]) + Sync),
        done: &mut dyn FnMut(&[usize]) -> Result<()>,
    ) -> Result<()> {
        self.planes_body(band, progress, sink, done)
    }

    #[inline(always)]
    fn planes_body(
        &self,
        band: usize,
        progress: &Progress,
        sink: &(dyn Fn(usize, usize, &[f32]) + Sync),
        done: &mut dyn FnMut(&[usize]) -> Result<()>,
    ) -> Result<()> {
        let (w, h, nb) = (self.grid.width, self.grid.height, self.bins);
        let canceled =
            || progress.is_canceled() || self.progress.as_ref().is_some_and(Progress::is_canceled);
        let band = band.clamp(1, h.max(1));
        let nbands = h.div_ceil(band);
        let plane = w * h;
        let slots = self.planes_in_flight();
        let mut work: Vec<(Vec<f32>, Scratch)> =
            (0..slots).map(|_| (Vec::new(), Scratch::default())).collect();
        // The padded lines of the axes the azimuths in flight sweep along: made when a chunk
        // first needs them; on a big map dropped when one no longer does (the bins run around
        // the circle, so an axis comes back at most twice, each time made again: about 0.07 s
        // of the pool at 2048², a tenth of a 32-bin bake's difference to the table when they
        // were dropped there too).
        let keep_both = 2 * plane * 4 <= PAIR_SCRATCH_BYTES;
        let mut majors: [Option<MajorLines>; 2] = [None, None];
        let order: Vec<usize> = (0..nb).collect();
        for chunk in order.chunks(slots) {
            if canceled() {
                return Err(Error::Canceled);
            }
            if self.wide {
                let used =
                    |a: usize| chunk.iter().any(|&n| usize::from(self.lines_of[n].major_x) == a);
                // The axis let go before the other is made, so that the two are never held at
                // once on a big map (5 bytes a texel each: 338 MB at 8192²).
                for (a, ml) in majors.iter_mut().enumerate() {
                    if !used(a) && !keep_both {
                        *ml = None;
                    }
                }
                for (a, ml) in majors.iter_mut().enumerate() {
                    if (used(a) || keep_both) && ml.is_none() {
                        *ml = Some(MajorLines::new(&self.grid, a == 1));
                    }
                }
            }
            // One azimuth at a time (a big map): a sweep along x hands its rows on as it
            // transposes them, so its plane in the image layout is never whole; along y its
            // sums are the plane itself, and the sums' scratch of the x sweeps is let go.
            if slots == 1 && self.wide {
                let n = chunk[0];
                let (out, sc) = &mut work[0];
                if let (true, Some(ml)) = (self.lines_of[n].major_x, &majors[1]) {
                    *out = Vec::new();
                    self.streamed_x(n, ml, sc, band, progress, sink, &canceled)?;
                    done(chunk)?;
                    continue;
                }
                sc.acc = Vec::new();
            }
            {
                let majors = &majors;
                chunk.par_iter().zip(work.par_iter_mut()).for_each(|(&n, (out, sc))| {
                    let lines = self.lines_of[n];
                    out.clear();
                    out.resize(plane, 0.0);
                    match &majors[usize::from(lines.major_x)] {
                        Some(ml) => far_field_fast(
                            &self.grid, ml, lines, self.reach, self.curv, out, sc, None, false,
                            None,
                        ),
                        None => {
                            far_field(&self.grid, lines, self.reach, self.curv, out, &mut sc.wsum)
                        }
                    }
                });
                if canceled() {
                    return Err(Error::Canceled);
                }
                let far: Vec<&[f32]> = work[..chunk.len()].iter().map(|(o, _)| &o[..]).collect();
                let far_rows = |k: usize, y0: usize, rows: usize| &far[k][y0 * w..][..rows * w];
                self.join_groups(chunk, 0..nbands, band, &far_rows, progress, sink, &canceled)?;
            }
            done(chunk)?;
        }
        Ok(())
    }

    /// Bands `bands` of every bin of `chunk` from their far-field rows (`far(k, y0, rows)`:
    /// rows `y0 ..` of `chunk[k]`'s plane), on the pool, handed to `sink` band by band and bin
    /// by bin in `chunk`'s order. The near field's tables are made per group of bands
    /// ([`Sweep::group_bands`]) for the rows it reads ([`NearField::refill`]), and let go after
    /// it: the kernel never holds the whole map's (12 bytes a texel).
    #[allow(clippy::too_many_arguments)] // the bins, the rows and where they go
    #[inline(always)]
    fn join_groups<'f>(
        &self,
        chunk: &[usize],
        bands: std::ops::Range<usize>,
        band: usize,
        far: &(dyn Fn(usize, usize, usize) -> &'f [f32] + Sync),
        progress: &Progress,
        sink: &(dyn Fn(usize, usize, &[f32]) + Sync),
        canceled: &(dyn Fn() -> bool + Sync),
    ) -> Result<()> {
        let (w, h) = (self.grid.width, self.grid.height);
        let ns = w.div_ceil(NEAR_LANES);
        let per = self.group_bands(band);
        let groups: Vec<std::ops::Range<usize>> =
            bands.clone().step_by(per).map(|g| g..(g + per).min(bands.end)).collect();
        groups.into_par_iter().try_for_each_init(
            || {
                let strips = vec![[0.0f32; NEAR_LANES]; ns];
                (strips.clone(), strips, vec![0.0f32; band * w])
            },
            |(hs, h0, out), g| {
                if canceled() {
                    return Err(Error::Canceled);
                }
                let pool = || self.windows.lock().unwrap_or_else(|e| e.into_inner());
                let mut near = pool().pop().unwrap_or_else(|| self.near.window());
                near.refill(g.start * band, (g.end * band).min(h));
                for b in g {
                    let y0 = b * band;
                    let rows = band.min(h - y0);
                    for (k, &n) in chunk.iter().enumerate() {
                        let out = &mut out[..rows * w];
                        self.join_band(&near, n, y0, far(k, y0, rows), hs, h0, out);
                        sink(b, n, out);
                        progress.advance(rows as u64);
                    }
                }
                pool().push(near);
                Ok(())
            },
        )
    }

    /// Bands per window of the near field ([`Sweep::join_groups`]): about [`NEAR_WINDOW_ROWS`]
    /// rows, fewer on a short map so that each thread still gets a few windows. A window
    /// reads 2·pad + 1 more rows than it joins (37 at the default 16 steps), made again for
    /// every azimuth.
    pub(super) fn group_bands(&self, band: usize) -> usize {
        let threads = rayon::current_num_threads().max(1);
        let rows = (self.grid.height / (4 * threads)).clamp(16, NEAR_WINDOW_ROWS);
        (rows / band.max(1)).max(1)
    }

    /// Band rows `y0 ..` of bin `n` from their far-field rows `far` (as many rows as `out`
    /// holds, row-major): the near field (`near`, holding those rows) and the point at R
    /// joined in ([`Sweep::row_bin`]).
    #[allow(clippy::too_many_arguments)] // the rows, their bin, their inputs and the output
    #[inline(always)]
    fn join_band(
        &self,
        near: &NearField<'_>,
        n: usize,
        y0: usize,
        far: &[f32],
        hs: &mut [[f32; NEAR_LANES]],
        h0: &mut [[f32; NEAR_LANES]],
        out: &mut [f32],
    ) {
        let w = self.grid.width;
        for (r, (dst, far)) in out.chunks_exact_mut(w).zip(far.chunks_exact(w)).enumerate() {
            let y = y0 + r;
            self.row_heights(y, hs, h0);
            self.row_bin(near, n, y, far, hs, h0, |j, sn| {
                let x = j * NEAR_LANES;
                let lanes = NEAR_LANES.min(w - x);
                dst[x..x + lanes].copy_from_slice(&sn[..lanes]);
            });
        }
    }

    /// Bin `n`, swept along x, with its rows handed on as the sweep transposes them
    /// (`far_field_fast`'s emit, 16 rows at a time, top to bottom): they wait in a buffer of
    /// a few bands per thread, and each time it holds whole bands those are joined on the
    /// pool and handed to `sink`, as [`Sweep::planes_body`] does from a whole plane.
    #[allow(clippy::too_many_arguments)] // the bin, its sweep's inputs and where it goes
    #[inline(always)]
    fn streamed_x(
        &self,
        n: usize,
        ml: &MajorLines,
        sc: &mut Scratch,
        band: usize,
        progress: &Progress,
        sink: &(dyn Fn(usize, usize, &[f32]) + Sync),
        canceled: &(dyn Fn() -> bool + Sync),
    ) -> Result<()> {
        let (w, h) = (self.grid.width, self.grid.height);
        // Whole windows of the near field at a time, two per thread.
        let window = self.group_bands(band) * band;
        let group = (2 * rayon::current_num_threads().max(1) * window).min(h);
        let mut buf = vec![0.0f32; (group + EMIT_ROWS) * w];
        // Rows held, and the first of them.
        let (mut held, mut first) = (0usize, 0usize);
        let mut stopped = false;
        let join = |buf: &[f32], first: usize, rows: usize| {
            let b0 = first / band;
            let far = |_: usize, y0: usize, rows: usize| &buf[(y0 - first) * w..][..rows * w];
            let bands = b0..b0 + rows.div_ceil(band);
            self.join_groups(&[n], bands, band, &far, progress, sink, canceled)
        };
        let mut emit = |start: usize, values: &[f32]| {
            if stopped {
                return;
            }
            debug_assert_eq!(start, (first + held) * w);
            let rows = values.len() / w;
            buf[held * w..(held + rows) * w].copy_from_slice(values);
            held += rows;
            let end = first + held == h;
            if held >= group || end {
                if canceled() {
                    stopped = true;
                    return;
                }
                // Whole windows only, but for the map's last.
                let whole = if end { held } else { held / window * window };
                if join(&buf[..whole * w], first, whole).is_err() {
                    stopped = true;
                    return;
                }
                buf.copy_within(whole * w..held * w, 0);
                (first, held) = (first + whole, held - whole);
            }
        };
        let lines = self.lines_of[n];
        far_field_fast(
            &self.grid,
            ml,
            lines,
            self.reach,
            self.curv,
            &mut [],
            sc,
            Some(&mut emit),
            false,
            None,
        );
        if stopped || canceled() {
            return Err(Error::Canceled);
        }
        Ok(())
    }
}
