//! The bands: per row, bin and strip of 16 texels, the far field and the point at R as a floor
//! for the exact near field, then sin α and the channel sums (compiled for AVX-512 where the CPU
//! has it).

use super::*;

impl HorizonRows for Sweep<'_> {
    fn width(&self) -> usize {
        self.grid.width
    }
    fn height(&self) -> usize {
        self.grid.height
    }
    fn bins(&self) -> usize {
        self.bins
    }
    fn failure(&self) -> Option<crate::error::Error> {
        if !self.failed.load(Ordering::Relaxed) {
            return None;
        }
        let f = self.failure.lock().ok()?.clone();
        let (kind, message) = f.unwrap_or((std::io::ErrorKind::Other, "unknown".into()));
        Some(spill_error(std::io::Error::new(kind, message)))
    }
    fn rows(&self, y0: usize, channels: &mut [f32], bins_out: Option<&mut [f32]>) {
        // The join's per-strip loops over 16 lanes (the point at R, the max, sin α, the channel
        // sums) are one or two AVX-512 instructions each rather than four SSE ones (measured:
        // the join's own time was about a tenth of a bake); AVX2 gains nothing there.
        #[cfg(target_arch = "x86_64")]
        if self.wide {
            // SAFETY: `wide` only where the CPU has AVX-512F (see `Sweep::with_options`).
            return unsafe { self.rows_avx512(y0, channels, bins_out) };
        }
        self.join(y0, channels, bins_out);
    }
}

impl Sweep<'_> {
    /// [`Sweep::join`] compiled for AVX-512.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f")]
    unsafe fn rows_avx512(&self, y0: usize, channels: &mut [f32], bins_out: Option<&mut [f32]>) {
        self.join(y0, channels, bins_out);
    }

    /// The bands: per row, bin and strip of 16 texels, the far field and the point at R as a
    /// floor for the near field, then sin α; then per strip its bins to the channels (see the
    /// module doc).
    #[inline(always)]
    fn join(&self, y0: usize, channels: &mut [f32], mut bins_out: Option<&mut [f32]>) {
        let (w, h, nb) = (self.grid.width, self.grid.height, self.bins);
        let n_rows = channels.len() / (w * 8);
        // Bin-major (`strip[n][i]`: texel i's bin n), so the channel sums run across the strip.
        let mut strip = vec![[0.0f32; NEAR_LANES]; nb];
        // `reduce=point` reads one bin per channel: the others are not computed unless asked.
        let step =
            if self.reduce == Reduce::Point && bins_out.is_none() && nb >= 8 { nb / 8 } else { 1 };
        if self.failed.load(Ordering::Relaxed) {
            return;
        }
        // The band's far field: the table's rows, or every needed bin's rows read from the
        // spill store (`far[n · n_rows·W + r·W + x]` either way, with its own origin).
        let band;
        let (far, plane, origin): (&[f32], usize, usize) = match &self.far {
            Far::Memory(t) => (t, w * h, 0),
            Far::Spilled(store) => {
                let mut b = vec![0.0f32; nb * n_rows * w];
                for n in (0..nb).step_by(step) {
                    let out = &mut b[n * n_rows * w..][..n_rows * w];
                    if let Err(e) = store.get(n, y0 * w, out) {
                        record(&self.failure, &self.failed, e);
                        return;
                    }
                }
                band = b;
                (&band, n_rows * w, y0 * w)
            }
            Far::Deferred => {
                channels.fill(0.0);
                if let Some(bo) = bins_out {
                    bo.fill(0.0);
                }
                return;
            }
        };
        // A row's strips bin by bin, then each strip's bins to its channels: bin by bin the
        // points at R lie on two rows and the far field on one, read left to right, which the
        // prefetchers follow; strip by strip they were 64 and 32 streams at once.
        let ns = w.div_ceil(NEAR_LANES);
        let mut hs = vec![[0.0f32; NEAR_LANES]; ns];
        let mut h0 = vec![[0.0f32; NEAR_LANES]; ns];
        let mut sines = vec![[0.0f32; NEAR_LANES]; nb * ns];
        for r in 0..n_rows {
            let y = y0 + r;
            // The strips' heights, once for all bins: raw for the points at R, and as the
            // near field takes them.
            self.row_heights(y, &mut hs, &mut h0);
            for n in (0..nb).step_by(step) {
                if self.progress.as_ref().is_some_and(Progress::is_canceled) {
                    return;
                }
                let row = &far[n * plane + y * w - origin..][..w];
                self.row_bin(&self.near, n, y, row, &hs, &h0, |j, sn| sines[n * ns + j] = sn);
            }
            for j in 0..ns {
                let (x, lanes) = (j * NEAR_LANES, NEAR_LANES.min(w - j * NEAR_LANES));
                for n in (0..nb).step_by(step) {
                    strip[n] = sines[n * ns + j];
                }
                let k = r * w + x;
                reduce_strip(self.reduce, &strip, lanes, &mut channels[k * 8..(k + lanes) * 8]);
                if let Some(bo) = bins_out.as_deref_mut() {
                    for i in 0..lanes {
                        for (n, s) in strip.iter().enumerate() {
                            bo[(k + i) * nb + n] = s[i];
                        }
                    }
                }
            }
        }
    }

    /// The strips' heights of row `y`, once for all bins: raw (`hs`, for the points at R) and
    /// as the near field takes them (`h0`).
    #[inline(always)]
    pub(super) fn row_heights(
        &self,
        y: usize,
        hs: &mut [[f32; NEAR_LANES]],
        h0: &mut [[f32; NEAR_LANES]],
    ) {
        let w = self.grid.width;
        for (j, (hs, h0)) in hs.iter_mut().zip(h0).enumerate() {
            let (x, lanes) = (j * NEAR_LANES, NEAR_LANES.min(w - j * NEAR_LANES));
            hs[..lanes].copy_from_slice(&self.grid.heights[y * w + x..][..lanes]);
            *h0 = self.near.lanes_h0(x, y);
        }
    }

    /// Row `y` at bin `n`, strip by strip: the far field (`row`, the row's W values of the
    /// plane) and the point at R as a floor for the near field, then sin α, handed to
    /// `put(strip, sines)` (lanes past the row's end unspecified). `hs` and `h0` are the row's
    /// [`Sweep::row_heights`]; `near` the kernel's near field or a window of it holding row
    /// `y` ([`NearField::refill`]). What the bands and the azimuth-major planes
    /// ([`Sweep::planes`]) share, so both give the same bits.
    #[allow(clippy::too_many_arguments)] // the row, its bin, its inputs and where it goes
    #[inline(always)]
    pub(super) fn row_bin(
        &self,
        near: &NearField<'_>,
        n: usize,
        y: usize,
        row: &[f32],
        hs: &[[f32; NEAR_LANES]],
        h0: &[[f32; NEAR_LANES]],
        mut put: impl FnMut(usize, [f32; NEAR_LANES]),
    ) {
        let w = self.grid.width;
        let ns = w.div_ceil(NEAR_LANES);
        let mut best: [f32; NEAR_LANES];
        let mut ep = [0.0f32; NEAR_LANES];
        let mut sn = [0.0f32; NEAR_LANES];
        for j in 0..ns {
            let (x, lanes) = (j * NEAR_LANES, NEAR_LANES.min(w - j * NEAR_LANES));
            self.end_points(n, x, y, lanes, &hs[j], &mut ep);
            let fb = &row[x..x + lanes];
            // The far field and the point at R first: the near field then only solves
            // the pieces that could beat them (the max is the same but for the f32
            // rounding of a skipped piece's value).
            best = [0.0; NEAR_LANES];
            if let Ok(fb) = <&[f32; NEAR_LANES]>::try_from(fb) {
                // A whole strip: a loop of fixed length, which vectorises.
                for i in 0..NEAR_LANES {
                    best[i] = best[i].max(fb[i]).max(ep[i]);
                }
            } else {
                for i in 0..lanes {
                    best[i] = best[i].max(fb[i]).max(ep[i]);
                }
            }
            let floor = best;
            let k = y * w + x;
            // Near a hole: the vector near field honours the holes itself where it
            // walks by crossings (out to the reach `exact` would walk); elsewhere (axis
            // and diagonal bins, a strip whose rays leave an `edge=none` surface early)
            // the texels within reach of a hole take `exact`'s walk, and a strip whose
            // every texel does (or is a hole) skips the vector one.
            let (mut near_hole, mut scalar, mut replaced) = (false, false, false);
            if let Some(hl) = &self.holes {
                near_hole = hl.near.any(k..k + lanes);
                scalar = near_hole && !near.honours_holes(n, x, y);
                let exact_only = |t: usize| hl.mask[t] || (scalar && hl.near.get(t));
                replaced = near_hole && (k..k + lanes).all(exact_only);
            }
            if near_hole && !scalar {
                near.strip_near_holes(n, x, y, &h0[j], &mut best);
            } else if !replaced {
                near.strip_from(n, x, y, &h0[j], &mut best);
            }
            if let Some(hl) = self.holes.as_ref().filter(|_| near_hole) {
                for i in 0..lanes {
                    if hl.mask[k + i] {
                        best[i] = 0.0;
                    } else if scalar && hl.near.get(k + i) {
                        let seed = f64::from(floor[i]);
                        best[i] = hl.exact.tan_at(x + i, y, n, seed) as f32;
                    }
                }
            }
            for i in 0..NEAR_LANES {
                // sin α in f32 (tan α ≥ 0; a vertical horizon, ∞, gives 1).
                let t = best[i].min(1e15);
                sn[i] = t / (1.0 + t * t).sqrt();
            }
            put(j, sn);
        }
    }
}
