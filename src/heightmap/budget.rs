//! What a decode will hold, known from the header before anything is allocated (issue 43), and
//! the process-wide budget the service's decodes reserve it from.
//!
//! A compressed input says nothing about its decoded size: a 261 KB deflated TIFF of one value
//! decodes to 256 MiB. [`estimate`] reads the header only (dimensions, samples per texel, bits
//! per sample, a TIFF's strip or tile size, an OpenEXR's channels) and returns the bytes the
//! decode path of [`super::decode_with`] holds at its peak, modelled on that code:
//!
//! - TIFF, read chunk by chunk ([`super::decode_tiff`]): the f32 heights (4 B a texel), one
//!   chunk's raw samples and its f32 conversion, and for a tiled TIFF one row of tiles as f32
//!   (the band [`super::stream`]'s reader assembles); a TIFF that is one strip (or one row of
//!   tiles) becomes the heights without a copy.
//! - PNG, through the `image` crate: the whole raw image (samples × bytes a sample after
//!   palette and low bit depths are expanded) and the f32 heights.
//! - OpenEXR, through the `exr` crate: every channel as stored (the reader takes them all), the
//!   picked channels converted to f32 (4 B a texel each, a float channel copied), and for an
//!   RGB(A) image the f32 heights besides.
//! - With nodata in effect, the hole mask (1 B a texel).
//!
//! Plus [`SLACK`] for the decoders' own state. The unit tests hold the estimate against the peak
//! resident memory a child process really reaches decoding each kind of file.
//!
//! [`MemoryBudget`] is a byte count shared by a process's decodes: a decode reserves its
//! estimate before it allocates and gets a [`Reservation`], an RAII guard that gives the bytes
//! back when dropped (with the decoded map), or part of them at once with
//! [`Reservation::shrink_to`] (a bake keeps only the heights). A std mutex and condition
//! variable, not an async semaphore: decodes run on blocking threads and rayon pools.

use super::{sniff, tiff_decoder, tiff_error, tiff_meta, Format};
use crate::error::{Error, LimitError, Result};
use crate::params::NoData;
use std::io::Cursor;
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

/// Bytes a decoder keeps besides the buffers the estimate counts (zlib state and windows, IFD
/// arrays, the `exr` crate's blocks in flight on its threads), rounded up from the largest
/// excess the unit tests measured.
pub const SLACK: u64 = 8 << 20;

/// What one decode holds, in bytes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Estimate {
    /// At its peak, [`SLACK`] included.
    pub peak: u64,
    /// Once decoded: the heights and the hole mask, what a caller holding the map keeps.
    pub kept: u64,
}

/// The estimate of a TIFF read chunk by chunk: `n` samples of `bits` per texel, chunks of
/// `cw`×`ch` texels (strips are `width` wide), `tiled` for tiles, `holes` when nodata is in
/// effect.
pub fn tiff_estimate(
    (width, height): (u64, u64),
    n: u64,
    bits: u64,
    (cw, ch): (u64, u64),
    tiled: bool,
    holes: bool,
) -> Estimate {
    // In u128: a hostile header's sizes must saturate, not overflow.
    let (width, height, n, bits, cw, ch) =
        (width as u128, height as u128, n as u128, bits as u128, cw as u128, ch as u128);
    let texels = width * height;
    let heights = 4 * texels;
    let sample = n * bits.div_ceil(8);
    let rows = ch.min(height).max(1);
    let chunk = if tiled { cw.min(width) * rows } else { width * rows };
    // While a chunk is converted: its raw samples and its f32 values are both alive.
    let convert = chunk * (sample + 4);
    let one_band = rows >= height;
    let peak = match (tiled, one_band) {
        // The single band is the heights: raw + f32 of the whole image.
        (false, true) => texels * sample + heights,
        // Heights filling up, the chunk being converted.
        (false, false) => heights + convert,
        // A row of tiles as f32 (moved into the heights when it is the whole image).
        (true, true) => heights + convert,
        (true, false) => heights + 4 * width * rows + convert,
    };
    let mask = if holes { texels } else { 0 };
    Estimate { peak: sat(peak + mask + SLACK as u128), kept: sat(heights + mask) }
}

fn sat(v: u128) -> u64 {
    u64::try_from(v).unwrap_or(u64::MAX)
}

/// The estimate of a PNG decoded whole by the `image` crate: `n` samples of `bits` per texel as
/// the decoder expands them (palette to RGB(A), low bit depths to 8).
pub fn png_estimate((width, height): (u64, u64), n: u64, bits: u64, holes: bool) -> Estimate {
    let (texels, n) = (width as u128 * height as u128, n as u128);
    let raw = texels * n * if bits == 16 { 2 } else { 1 };
    let mask = if holes { texels } else { 0 };
    Estimate { peak: sat(raw + 4 * texels + mask + SLACK as u128), kept: sat(4 * texels + mask) }
}

/// The estimate of an OpenEXR decoded by the `exr` crate: `stored` bytes a texel over all its
/// channels, `picked` channels converted to f32, `rgb` when the heights are computed from them
/// (else the one converted channel is the heights).
pub fn exr_estimate(
    (width, height): (u64, u64),
    stored: u64,
    picked: u64,
    rgb: bool,
    holes: bool,
) -> Estimate {
    let texels = width as u128 * height as u128;
    let heights = 4 * texels;
    let converted = 4 * picked as u128 * texels + if rgb { heights } else { 0 };
    let mask = if holes { texels } else { 0 };
    let peak = stored as u128 * texels + converted + mask + SLACK as u128;
    Estimate { peak: sat(peak), kept: sat(heights + mask) }
}

/// The bytes decoding `bytes` with [`super::decode_with`] holds (see the module docs), from the
/// header alone; `nodata` as the decode is given it (`auto` takes a GeoTIFF's GDAL_NODATA).
///
/// # Errors
/// The header's refusals ([`super::probe`]'s, a TIFF's unread colour type or compression).
pub fn estimate(bytes: &[u8], nodata: NoData) -> Result<Estimate> {
    let declared = !matches!(nodata, NoData::Auto | NoData::None);
    match sniff(bytes)? {
        Format::Png => {
            let (w, h) = super::png_dimensions(bytes)?;
            let (Some(&bits), Some(&color)) = (bytes.get(24), bytes.get(25)) else {
                return Err(Error::Decode("the PNG is truncated in its IHDR header chunk".into()));
            };
            let trns = png_has_trns(bytes);
            let n = match color {
                0 => 1 + u64::from(trns),
                2 => 3 + u64::from(trns),
                3 => 3 + u64::from(trns),
                4 => 2,
                _ => 4,
            };
            Ok(png_estimate((w, h), n, u64::from(bits.max(8)), declared))
        }
        Format::Tiff => super::contained("TIFF", || {
            let mut dec = tiff_decoder(bytes)?;
            let (w, h) = dec.dimensions().map_err(tiff_error)?;
            let meta = tiff_meta(&mut dec)?;
            let holes = declared
                || (matches!(nodata, NoData::Auto)
                    && meta.georef.as_ref().and_then(|g| g.nodata()).is_some());
            let tiled = dec.get_chunk_type() == tiff::decoder::ChunkType::Tile;
            let (cw, ch) = dec.chunk_dimensions();
            Ok(tiff_estimate(
                (u64::from(w), u64::from(h)),
                meta.n as u64,
                u64::from(meta.ct.bit_depth()),
                (u64::from(cw), u64::from(ch)),
                tiled,
                holes,
            ))
        }),
        Format::Exr => super::contained("OpenEXR", || {
            let meta = exr::meta::MetaData::read_from_buffered(Cursor::new(bytes), false)
                .map_err(super::exr_error)?;
            let header = meta
                .headers
                .first()
                .ok_or_else(|| Error::Decode("the OpenEXR file has no layers".into()))?;
            let list = &header.channels.list;
            let stored: u64 = list.iter().map(|c| c.sample_type.bytes_per_sample() as u64).sum();
            let has = |name: &str| list.iter().any(|c| c.name == *name);
            let (picked, rgb) = if has("R") && has("G") && has("B") {
                (3 + u64::from(has("A")), true)
            } else {
                (1, false)
            };
            let size = (header.layer_size.0 as u64, header.layer_size.1 as u64);
            Ok(exr_estimate(size, stored, picked, rgb, declared))
        }),
    }
}

/// Whether a tRNS chunk precedes the first IDAT (the decoder then adds an alpha sample).
fn png_has_trns(bytes: &[u8]) -> bool {
    let mut at = 8;
    while let Some(head) = bytes.get(at..at + 8) {
        let len = u32::from_be_bytes([head[0], head[1], head[2], head[3]]) as usize;
        match &head[4..8] {
            b"tRNS" => return true,
            b"IDAT" | b"IEND" => return false,
            _ => at = at.saturating_add(12).saturating_add(len),
        }
    }
    false
}

/// Refuses an estimate over the per-request budget `max_decode_bytes`.
///
/// # Errors
/// [`Error::Limits`] with [`LimitError::DecodeBytes`].
pub fn check(est: &Estimate, max_decode_bytes: u64) -> Result<()> {
    if est.peak > max_decode_bytes {
        return Err(Error::Limits(LimitError::DecodeBytes {
            estimate: est.peak,
            max_decode_bytes,
        }));
    }
    Ok(())
}

/// Where a decode reserves its memory: the process's budget and how long it may wait for it
/// (`None`: as long as it takes).
#[derive(Debug, Clone, Copy)]
pub struct Admit<'a> {
    pub budget: &'a Arc<MemoryBudget>,
    pub wait: Option<Duration>,
}

/// Bytes shared by every decode of a process (see the module docs).
#[derive(Debug)]
pub struct MemoryBudget {
    total: u64,
    used: Mutex<u64>,
    freed: Condvar,
}

impl MemoryBudget {
    /// A budget of `total` bytes.
    pub fn new(total: u64) -> Arc<Self> {
        Arc::new(MemoryBudget { total, used: Mutex::new(0), freed: Condvar::new() })
    }

    /// The budget's size in bytes.
    pub fn total(&self) -> u64 {
        self.total
    }

    /// Bytes reserved now.
    pub fn in_use(&self) -> u64 {
        *self.used.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Reserves `bytes`, waiting for other reservations to be released for at most `wait`
    /// (`None`: as long as it takes, for work already accepted, such as a queued bake).
    ///
    /// # Errors
    /// [`Error::MemoryBusy`] when `wait` passes first; [`Error::Limits`] for more bytes than
    /// the whole budget, which no wait could give.
    pub fn reserve(self: &Arc<Self>, bytes: u64, wait: Option<Duration>) -> Result<Reservation> {
        if bytes > self.total {
            return Err(Error::Limits(LimitError::DecodeBytes {
                estimate: bytes,
                max_decode_bytes: self.total,
            }));
        }
        let deadline = wait.map(|w| Instant::now() + w);
        let mut used = self.used.lock().unwrap_or_else(|e| e.into_inner());
        while *used + bytes > self.total {
            used = match deadline {
                None => self.freed.wait(used).unwrap_or_else(|e| e.into_inner()),
                Some(d) => {
                    let left = d.saturating_duration_since(Instant::now());
                    if left.is_zero() {
                        return Err(Error::MemoryBusy {
                            needed: bytes,
                            in_use: *used,
                            budget: self.total,
                        });
                    }
                    self.freed.wait_timeout(used, left).unwrap_or_else(|e| e.into_inner()).0
                }
            };
        }
        *used += bytes;
        Ok(Reservation { budget: Some(self.clone()), bytes })
    }

    fn release(&self, bytes: u64) {
        let mut used = self.used.lock().unwrap_or_else(|e| e.into_inner());
        *used = used.saturating_sub(bytes);
        self.freed.notify_all();
    }
}

/// Bytes held from a [`MemoryBudget`], given back when dropped.
#[derive(Debug, Default)]
pub struct Reservation {
    budget: Option<Arc<MemoryBudget>>,
    bytes: u64,
}

impl Reservation {
    /// A reservation of nothing from no budget (a decode outside the service).
    pub fn none() -> Self {
        Reservation::default()
    }

    /// Bytes held.
    pub fn bytes(&self) -> u64 {
        self.bytes
    }

    /// Gives back all but `bytes` (a decode done keeps only what its map holds).
    pub fn shrink_to(&mut self, bytes: u64) {
        if bytes < self.bytes {
            if let Some(b) = &self.budget {
                b.release(self.bytes - bytes);
            }
            self.bytes = bytes;
        }
    }
}

impl Drop for Reservation {
    fn drop(&mut self) {
        if let Some(b) = self.budget.take() {
            b.release(self.bytes);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::params::Channel;

    #[test]
    fn a_reservation_waits_for_a_release_and_times_out_without_one() {
        let b = MemoryBudget::new(100);
        let mut first = b.reserve(60, Some(Duration::ZERO)).unwrap();
        assert_eq!(b.in_use(), 60);
        match b.reserve(50, Some(Duration::from_millis(20))) {
            Err(Error::MemoryBusy { needed: 50, in_use: 60, budget: 100 }) => {}
            other => panic!("expected MemoryBusy, got {other:?}"),
        }
        // More than the whole budget is refused at once, not waited for.
        assert!(matches!(b.reserve(101, None), Err(Error::Limits(_))));
        let b2 = b.clone();
        let waiter = std::thread::spawn(move || b2.reserve(50, Some(Duration::from_secs(10))));
        std::thread::sleep(Duration::from_millis(30));
        first.shrink_to(40);
        let second = waiter.join().unwrap().unwrap();
        assert_eq!(b.in_use(), 90);
        drop(first);
        drop(second);
        assert_eq!(b.in_use(), 0);
    }

    /// Found by tests/service/fuzz.rs: a PNG cut inside its IHDR (after the dimensions, before
    /// the bit depth) panicked the estimate instead of being refused; and a hostile header's
    /// sizes saturate instead of overflowing.
    #[test]
    fn a_truncated_header_is_refused_and_huge_sizes_saturate() {
        let png = gray16_png(4, 4);
        assert!(matches!(estimate(&png[..24], NoData::None), Err(Error::Decode(_))));
        let e = tiff_estimate((u32::MAX as u64, u32::MAX as u64), 4, 64, (1, 1), true, true);
        assert_eq!(e.peak, u64::MAX);
    }

    /// A deflated float TIFF of one value: small on disk, `w`×`h`×4 bytes decoded.
    pub(crate) fn float_tiff(w: u32, h: u32, rows_per_strip: Option<u32>) -> Vec<u8> {
        use tiff::encoder::{colortype::Gray32Float, compression::DeflateLevel, Compression};
        let mut out = Cursor::new(Vec::new());
        let mut enc = tiff::encoder::TiffEncoder::new(&mut out)
            .unwrap()
            .with_compression(Compression::Deflate(DeflateLevel::default()));
        let mut img = enc.new_image::<Gray32Float>(w, h).unwrap();
        if let Some(r) = rows_per_strip {
            img.rows_per_strip(r).unwrap();
        }
        // `write_data` (not `write_strip`, which skips the compressor) with the whole image.
        img.write_data(&vec![0.5f32; w as usize * h as usize]).unwrap();
        out.into_inner()
    }

    fn gray16_png(w: u32, h: u32) -> Vec<u8> {
        let mut out = Vec::new();
        let mut enc = png::Encoder::new(&mut out, w, h);
        enc.set_color(png::ColorType::Grayscale);
        enc.set_depth(png::BitDepth::Sixteen);
        let mut wr = enc.write_header().unwrap();
        wr.write_image_data(&vec![7u8; (w * h * 2) as usize]).unwrap();
        wr.finish().unwrap();
        out
    }

    fn exr(w: usize, h: usize, rgba: bool) -> Vec<u8> {
        use exr::prelude::*;
        let mut out = Cursor::new(Vec::new());
        if rgba {
            let img = Image::from_channels(
                (w, h),
                SpecificChannels::rgba(|_: Vec2<usize>| (0.5f32, 0.25f32, 0.125f32, 1.0f32)),
            );
            img.write().to_buffered(&mut out).unwrap();
        } else {
            let ch = AnyChannel::new("Y", FlatSamples::F32(vec![0.5f32; w * h]));
            let img = Image::from_layer(Layer::new(
                (w, h),
                LayerAttributes::default(),
                Encoding::SMALL_LOSSLESS,
                AnyChannels::sort(SmallVec::from_vec(vec![ch])),
            ));
            img.write().to_buffered(&mut out).unwrap();
        }
        out.into_inner()
    }

    /// The inputs measured: (name, bytes, nodata).
    fn case(name: &str) -> (Vec<u8>, NoData) {
        match name {
            "tiff_strips" => (float_tiff(4096, 4096, None), NoData::None),
            "tiff_strips_nodata" => (float_tiff(4096, 4096, None), NoData::Value(-1.0)),
            "tiff_one_strip" => (float_tiff(3072, 3072, Some(3072)), NoData::None),
            "png16" => (gray16_png(4096, 4096), NoData::None),
            "exr_gray" => (exr(3072, 3072, false), NoData::None),
            "exr_rgba" => (exr(2048, 2048, true), NoData::None),
            other => panic!("no case {other}"),
        }
    }

    fn status_kib(key: &str) -> u64 {
        let s = std::fs::read_to_string("/proc/self/status").unwrap();
        let line = s.lines().find(|l| l.starts_with(key)).unwrap();
        line.split_whitespace().nth(1).unwrap().parse().unwrap()
    }

    /// Run by [`the_estimate_bounds_the_measured_peak_closely`] in a child process: decodes the
    /// case named by `HB_BUDGET_CASE` and prints how far its resident memory rose.
    #[test]
    #[ignore = "a child of the_estimate_bounds_the_measured_peak_closely"]
    fn decode_peak_child() {
        let Ok(name) = std::env::var("HB_BUDGET_CASE") else { return };
        let (bytes, nodata) = case(&name);
        // Writing 5 to clear_refs resets VmHWM to the current resident size (Linux ≥ 4.0).
        std::fs::write("/proc/self/clear_refs", "5").unwrap();
        let base = status_kib("VmRSS:");
        let limits = super::super::Limits {
            max_dim: 65536,
            max_texels: u64::MAX,
            max_bytes: u64::MAX,
            max_decode_bytes: u64::MAX,
        };
        let (map, _) = super::super::decode_with(&bytes, Channel::Luma, nodata, &limits).unwrap();
        let peak = status_kib("VmHWM:");
        assert!(!map.values.is_empty());
        println!("PEAK_DELTA_BYTES={}", (peak.saturating_sub(base)) * 1024);
    }

    /// The estimate is never below what a decode really reaches (resident memory of a child
    /// process, from its start to its peak), and not far above it: within 10% + [`SLACK`].
    #[test]
    fn the_estimate_bounds_the_measured_peak_closely() {
        let exe = std::env::current_exe().unwrap();
        for name in
            ["tiff_strips", "tiff_strips_nodata", "tiff_one_strip", "png16", "exr_gray", "exr_rgba"]
        {
            let (bytes, nodata) = case(name);
            let est = estimate(&bytes, nodata).unwrap();
            let out = std::process::Command::new(&exe)
                .args([
                    "heightmap::budget::tests::decode_peak_child",
                    "--exact",
                    "--ignored",
                    "--nocapture",
                    "--test-threads=1",
                ])
                .env("HB_BUDGET_CASE", name)
                .output()
                .unwrap();
            let text = String::from_utf8_lossy(&out.stdout);
            let measured: u64 = text
                .split("PEAK_DELTA_BYTES=")
                .nth(1)
                .and_then(|t| t.split_whitespace().next()?.parse().ok())
                .unwrap_or_else(|| panic!("{name}: no measurement in {text}"));
            eprintln!(
                "{name}: estimate {} MiB, measured {} MiB",
                crate::error::mib(est.peak),
                crate::error::mib(measured)
            );
            assert!(measured <= est.peak, "{name}: measured {measured} > estimate {}", est.peak);
            assert!(
                est.peak <= measured + measured / 10 + SLACK,
                "{name}: estimate {} far above measured {measured}",
                est.peak
            );
        }
    }
}
