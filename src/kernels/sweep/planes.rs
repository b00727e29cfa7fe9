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
//! [`SPILL_SWEEP_BYTES`]), whatever the bins.

use super::*;
use crate::error::{Error, Result};

impl Sweep<'_> {
    /// Whether the kernel was built azimuth-major ([`Options::azimuth_major`]): only
    /// [`Sweep::planes`] gives its horizons.
    pub fn is_azimuth_major(&self) -> bool {
        matches!(self.far, Far::Deferred)
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
        #[cfg(target_arch = "x86_64")]
        if self.wide {
            // SAFETY: `wide` only where the CPU has AVX-512F (see `Sweep::with_options`).
            return unsafe { self.planes_avx512(band, progress, &sink) };
        }
        self.planes_body(band, progress, &sink)
    }

    /// [`Sweep::planes_body`] compiled for AVX-512 (the join, as [`Sweep::rows`] is).
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f")]
    unsafe fn planes_avx512(
        &self,
        band: usize,
        progress: &Progress,
        sink: &(dyn Fn(usize, usize, &[f32]) + Sync),
    ) -> Result<()> {
        self.planes_body(band, progress, sink)
    }

    #[inline(always)]
    fn planes_body(
        &self,
        band: usize,
        progress: &Progress,
        sink: &(dyn Fn(usize, usize, &[f32]) + Sync),
    ) -> Result<()> {
        let (w, h, nb) = (self.grid.width, self.grid.height, self.bins);
        let canceled =
            || progress.is_canceled() || self.progress.as_ref().is_some_and(Progress::is_canceled);
        let band = band.clamp(1, h.max(1));
        let nbands = h.div_ceil(band);
        // Up to 3 planes of W·H f32 per azimuth in flight (the plane, and the sweep's missing
        // weights and transposed sums), as for a spilled table.
        let plane = w * h;
        let slots = (SPILL_SWEEP_BYTES / (3 * plane * 4).max(1))
            .clamp(1, rayon::current_num_threads().max(1));
        let mut work: Vec<(Vec<f32>, Scratch)> =
            (0..slots).map(|_| (Vec::new(), Scratch::default())).collect();
        let ns = w.div_ceil(NEAR_LANES);
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
                for (a, ml) in majors.iter_mut().enumerate() {
                    let used = chunk.iter().any(|&n| usize::from(self.lines_of[n].major_x) == a);
                    if !used && !keep_both {
                        *ml = None;
                    } else if ml.is_none() {
                        *ml = Some(MajorLines::new(&self.grid, a == 1));
                    }
                }
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
                            far_field(&self.grid, lines, self.reach, self.curv, out, &mut sc.miss)
                        }
                    }
                });
                if canceled() {
                    return Err(Error::Canceled);
                }
                let far: Vec<&[f32]> = work[..chunk.len()].iter().map(|(o, _)| &o[..]).collect();
                (0..nbands).into_par_iter().try_for_each_init(
                    || {
                        let strips = vec![[0.0f32; NEAR_LANES]; ns];
                        (strips.clone(), strips, vec![0.0f32; band * w])
                    },
                    |(hs, h0, out), b| {
                        if canceled() {
                            return Err(Error::Canceled);
                        }
                        let y0 = b * band;
                        let rows = band.min(h - y0);
                        for (k, &n) in chunk.iter().enumerate() {
                            for r in 0..rows {
                                let y = y0 + r;
                                self.row_heights(y, hs, h0);
                                let dst = &mut out[r * w..][..w];
                                self.row_bin(n, y, &far[k][y * w..][..w], hs, h0, |j, sn| {
                                    let x = j * NEAR_LANES;
                                    let lanes = NEAR_LANES.min(w - x);
                                    dst[x..x + lanes].copy_from_slice(&sn[..lanes]);
                                });
                            }
                            sink(b, n, &out[..rows * w]);
                            progress.advance(rows as u64);
                        }
                        Ok(())
                    },
                )?;
            }
        }
        Ok(())
    }
}
