//! PNG writers (8-bit and 16-bit, gray or RGBA), streamed row by row: our own chunk writer over
//! zlib (see [`PngRowWriter`] for why), 16-bit samples big-endian as the format requires, with
//! no intermediate image type. Read back in the tests by the `image` crate's PNG decoder.

use crate::error::{Error, Result};

/// PNG colour layouts we write.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PngColor {
    Gray,
    /// Grey and alpha (the terrain renderings: a hole is transparent).
    GrayAlpha,
    /// Three channels (the normal and bent-normal maps, SPEC §3.8).
    Rgb,
    Rgba,
}

impl PngColor {
    /// Samples per pixel.
    pub fn channels(self) -> usize {
        match self {
            PngColor::Gray => 1,
            PngColor::GrayAlpha => 2,
            PngColor::Rgb => 3,
            PngColor::Rgba => 4,
        }
    }
}

/// Encodes whole images through the same row writer the streaming bake uses, so a layer encoded
/// in one piece and one streamed band by band are the same bytes (the service's downloads and
/// the CLI's files are compared byte for byte).
fn encode_whole<T: PngSample>(
    width: usize,
    height: usize,
    color: PngColor,
    data: &[T],
) -> Result<Vec<u8>> {
    if data.len() != width * height * color.channels() {
        return Err(Error::Internal(format!("png{}: buffer size mismatch", T::BITS)));
    }
    let out = Vec::with_capacity(data.len() * T::BITS as usize / 16 + 1024);
    let mut w = PngRowWriter::<Vec<u8>, T>::new(out, width, height, color)?;
    w.write_rows(data)?;
    w.finish()
}

/// Encodes 8-bit samples (`width · height · channels` of them) as PNG.
///
/// # Errors
/// [`Error::Internal`] on a size mismatch or an encoder failure.
pub fn encode8(width: usize, height: usize, color: PngColor, data: &[u8]) -> Result<Vec<u8>> {
    encode_whole(width, height, color, data)
}

/// Encodes 16-bit samples as PNG (big-endian on disk).
///
/// # Errors
/// [`Error::Internal`] on a size mismatch or an encoder failure.
pub fn encode16(width: usize, height: usize, color: PngColor, data: &[u16]) -> Result<Vec<u8>> {
    encode_whole(width, height, color, data)
}

/// A sample type the row-streaming writer takes: `u8` (8-bit PNG) or `u16` (16-bit PNG).
pub trait PngSample: Copy {
    /// Bits per sample.
    const BITS: u8;
    /// Appends `rows` in PNG byte order (big-endian for 16-bit).
    fn extend_be(rows: &[Self], out: &mut Vec<u8>);
}

impl PngSample for u8 {
    const BITS: u8 = 8;
    fn extend_be(rows: &[u8], out: &mut Vec<u8>) {
        out.extend_from_slice(rows);
    }
}

impl PngSample for u16 {
    const BITS: u8 = 16;
    fn extend_be(rows: &[u16], out: &mut Vec<u8>) {
        out.extend(rows.iter().flat_map(|v| v.to_be_bytes()));
    }
}

/// IDAT chunk size of streamed PNGs.
const STREAM_CHUNK: usize = 1 << 20;

/// Filtered bytes deflated as one piece (whole rows, at least this many): each piece is
/// compressed on its own, and written as stored blocks instead when compression does not pay
/// for it.
const PIECE: usize = 256 * 1024;

/// Deflate's window: the pieces of small images are compressed with the 32 KiB of filtered
/// bytes before them as their dictionary, so matches across a piece boundary are found as in
/// one continuous stream.
const WINDOW: usize = 32 * 1024;

/// Images up to this many texels are deflated at zlib's default level, larger ones at level 1.
const SMALL_IMAGE_TEXELS: usize = 512 * 512;

#[doc(hidden)]
pub mod single_stream;

/// Writes a PNG row by row to any [`std::io::Write`] (a file, usually), so neither the samples
/// nor the encoded image need to be in memory whole, and deflates on every core: rows are
/// filtered (the filter each row compresses best by the usual sum-of-magnitudes rule), then
/// deflated in pieces of whole rows, at least 256 KiB of filtered bytes each, every piece by a
/// fresh compressor of its own (pigz's scheme) flushed to a byte boundary. A piece that deflate
/// would make larger is written as stored blocks instead. So a PNG is never larger than its
/// samples plus the framing: a filter byte per row, 5 bytes per stored block of 64 KiB, 5 per
/// piece, 12 per 1 MiB IDAT chunk, and the 57 bytes of signature, IHDR, IEND and zlib header
/// and checksum.
///
/// Small images (the default level, up to 512² texels) prime each piece's compressor with the
/// 32 KiB of filtered bytes before it, compressed and thrown away (miniz_oxide, flate2's
/// backend here, has no `set_dictionary`; a decoder holds those bytes in its window, so the
/// piece's matches may reach into them): without it a 512² smooth layer was 0.6 % larger.
/// Larger images (level 1) do not: priming cost 7–10 % more CPU and bought nothing at level 1
/// (a 4096² horizon layer 179 bytes smaller in 64.3 MB, a smooth one 0.03 % larger;
/// `cargo test --bench png_encode`).
///
/// Rows are buffered a batch of pieces at a time (4 per thread, at most 64), then the batch's
/// rows are filtered and its pieces deflated in parallel: on the rayon pool when the caller is
/// one of its threads (the caller takes part, so a pool busy elsewhere cannot stall it), on
/// scoped threads otherwise (as many as rayon's pool has; a plain thread never waits on pool
/// jobs that might themselves be waiting for it). The checksum is combined from the pieces'.
/// Each piece's bytes depend only on its rows (and the 32 KiB before them), and pieces start
/// every ⌈256 KiB / filtered row⌉ rows: the output is one function of the rows, whatever the
/// number of threads or how the rows are split into calls, so a layer written whole, streamed
/// band by band and assembled from tiles are the same bytes.
///
/// The `png` crate's streaming writer had no stored fallback: fdeflate's fixed Huffman table
/// wrote a 2048² 8-bit layer close to noise as 18.4 MB for 16.8 MB of samples, and zlib behind
/// it cannot store a block once it spans more than its 32 KiB window.
pub struct PngRowWriter<W: std::io::Write, T: PngSample> {
    out: W,
    /// zlib level (the default for small images, 1 above [`SMALL_IMAGE_TEXELS`]).
    level: u32,
    row_samples: usize,
    row_bytes: usize,
    /// Bytes per pixel (filters look this far left).
    bpp: usize,
    rows_left: usize,
    rows_per_piece: usize,
    pieces_per_batch: usize,
    /// Whether pieces are primed with the 32 KiB before them (small images only).
    dictionary: bool,
    /// The last row of the previous batch, unfiltered (zeros before the first row).
    prev: Vec<u8>,
    /// Rows of the current batch not filtered yet (big-endian bytes).
    raw: Vec<u8>,
    /// The last [`WINDOW`] filtered bytes deflated so far.
    tail: Vec<u8>,
    /// Per piece of a batch, its filtered bytes and its deflate data: kept from batch to batch
    /// (the pieces are filled on scoped threads that live for one batch; allocating anew in each
    /// would leave freed buffers in the arenas of threads long gone).
    filtered: Vec<Vec<u8>>,
    deflated: Vec<Vec<u8>>,
    /// Compressors (miniz_oxide's state is ~300 KiB to allocate), one per piece in flight.
    compressors: std::sync::Mutex<Vec<flate2::Compress>>,
    adler: Adler32,
    /// The IDAT data not written yet.
    idat: Vec<u8>,
    _sample: std::marker::PhantomData<T>,
}

fn png_error(what: &str, e: impl std::fmt::Display) -> Error {
    Error::Internal(format!("png {what}: {e}"))
}

/// Checks and writes the PNG signature and the IHDR chunk of a `width × height` image, the
/// same for both writers.
fn write_header<W: std::io::Write, T: PngSample>(
    out: &mut W,
    width: usize,
    height: usize,
    color: PngColor,
) -> Result<()> {
    let (Ok(w32), Ok(h32)) = (u32::try_from(width), u32::try_from(height)) else {
        return Err(Error::Internal(format!("png: {width}×{height} is too large")));
    };
    if width == 0 || height == 0 || w32 > i32::MAX as u32 || h32 > i32::MAX as u32 {
        return Err(Error::Internal(format!("png: {width}×{height} has no pixels or too many")));
    }
    out.write_all(b"\x89PNG\r\n\x1a\n")?;
    let mut ihdr = Vec::with_capacity(13);
    ihdr.extend_from_slice(&w32.to_be_bytes());
    ihdr.extend_from_slice(&h32.to_be_bytes());
    let color_type = match color {
        PngColor::Gray => 0,
        PngColor::GrayAlpha => 4,
        PngColor::Rgb => 2,
        PngColor::Rgba => 6,
    };
    ihdr.extend_from_slice(&[T::BITS, color_type, 0, 0, 0]);
    write_chunk(out, b"IHDR", &ihdr)
}

/// Refuses rows that are not whole rows of `row_samples` or more than the `rows_left`.
fn check_rows(len: usize, row_samples: usize, rows_left: usize) -> Result<()> {
    if !len.is_multiple_of(row_samples) || len / row_samples > rows_left {
        return Err(Error::Internal(format!(
            "png rows: {len} samples are not whole rows of {row_samples} within the {rows_left} \
             rows left"
        )));
    }
    Ok(())
}

/// Appends `data` to `out` as stored deflate blocks (BFINAL 0, BTYPE 00; the stream is at a
/// byte boundary after every piece, so the decoder's window receives the same bytes).
fn store_blocks(data: &[u8], out: &mut Vec<u8>) {
    for block in data.chunks(65535) {
        let len = block.len() as u16;
        out.push(0);
        out.extend_from_slice(&len.to_le_bytes());
        out.extend_from_slice(&(!len).to_le_bytes());
        out.extend_from_slice(block);
    }
}

/// Ends an image whose rows are all deflated into `idat`: a final empty stored block, the
/// checksum of everything deflated, the last IDAT chunks and IEND.
fn write_trailer<W: std::io::Write>(out: &mut W, idat: &mut Vec<u8>, adler: Adler32) -> Result<()> {
    idat.extend_from_slice(&[1, 0, 0, 0xff, 0xff]);
    idat.extend_from_slice(&adler.finish().to_be_bytes());
    for chunk in idat.chunks(STREAM_CHUNK) {
        write_chunk(out, b"IDAT", chunk)?;
    }
    write_chunk(out, b"IEND", &[])?;
    out.flush()?;
    Ok(())
}

/// Writes one chunk: length, type, data, CRC of type and data.
fn write_chunk<W: std::io::Write>(out: &mut W, kind: &[u8; 4], data: &[u8]) -> Result<()> {
    let mut crc = crc32fast::Hasher::new();
    crc.update(kind);
    crc.update(data);
    out.write_all(&(data.len() as u32).to_be_bytes())?;
    out.write_all(kind)?;
    out.write_all(data)?;
    out.write_all(&crc.finalize().to_be_bytes())?;
    Ok(())
}

/// The zlib checksum (RFC 1950), in blocks of 5552 bytes so the sums never overflow.
#[derive(Debug, Clone, Copy)]
struct Adler32 {
    a: u32,
    b: u32,
}

impl Adler32 {
    fn new() -> Self {
        Adler32 { a: 1, b: 0 }
    }
    fn update(&mut self, data: &[u8]) {
        const MOD: u32 = 65521;
        for block in data.chunks(5552) {
            let (mut a, mut b) = (self.a, self.b);
            for &x in block {
                a += u32::from(x);
                b += a;
            }
            self.a = a % MOD;
            self.b = b % MOD;
        }
    }
    fn finish(self) -> u32 {
        (self.b << 16) | self.a
    }
}

/// Paeth predictor of the PNG specification (pa = |b − c|, pb = |a − c|, pc = |a + b − 2c|),
/// written to compile to selects rather than branches.
#[inline(always)]
fn paeth(a: u8, b: u8, c: u8) -> u8 {
    let (a16, b16, c16) = (i16::from(a), i16::from(b), i16::from(c));
    let pa = (b16 - c16).abs();
    let pb = (a16 - c16).abs();
    let pc = (a16 + b16 - 2 * c16).abs();
    let bc = if pb <= pc { b } else { c };
    if pa <= pb && pa <= pc {
        a
    } else {
        bc
    }
}

/// Filters `cur` (above it: `prev`) with filter `kind` into `out`; returns the sum of the
/// output bytes read as signed magnitudes (the heuristic that picks the filter). Loops zip
/// slices, so no index is bounds-checked in them.
#[inline(always)]
fn filter_row(kind: u8, bpp: usize, prev: &[u8], cur: &[u8], out: &mut [u8]) -> u64 {
    let n = cur.len();
    let b = bpp.min(n);
    let (head, tail) = out.split_at_mut(b);
    match kind {
        0 => out.copy_from_slice(cur),
        1 => {
            head.copy_from_slice(&cur[..b]);
            for ((o, &c), &l) in tail.iter_mut().zip(&cur[b..]).zip(&cur[..n - b]) {
                *o = c.wrapping_sub(l);
            }
        }
        2 => {
            for ((o, &c), &p) in out.iter_mut().zip(cur).zip(prev) {
                *o = c.wrapping_sub(p);
            }
        }
        3 => {
            for ((o, &c), &p) in head.iter_mut().zip(&cur[..b]).zip(&prev[..b]) {
                *o = c.wrapping_sub(p >> 1);
            }
            for (((o, &c), &l), &p) in
                tail.iter_mut().zip(&cur[b..]).zip(&cur[..n - b]).zip(&prev[b..])
            {
                *o = c.wrapping_sub(((u16::from(l) + u16::from(p)) >> 1) as u8);
            }
        }
        _ => {
            for ((o, &c), &p) in head.iter_mut().zip(&cur[..b]).zip(&prev[..b]) {
                *o = c.wrapping_sub(p);
            }
            for ((((o, &c), &l), &p), &ul) in tail
                .iter_mut()
                .zip(&cur[b..])
                .zip(&cur[..n - b])
                .zip(&prev[b..])
                .zip(&prev[..n - b])
            {
                *o = c.wrapping_sub(paeth(l, p, ul));
            }
        }
    }
    // Summed in u32 lanes over chunks (a row's sum fits: at most 127 per byte, and a chunk
    // of 2^24 bytes), which vectorises; a sum widened to u64 per byte did not.
    out.chunks(1 << 24)
        .map(|c| u64::from(c.iter().map(|&b| u32::from((b as i8).unsigned_abs())).sum::<u32>()))
        .sum()
}

impl Adler32 {
    /// The checksum of this data followed by data whose own checksum is `next`, of `len` bytes
    /// (zlib's `adler32_combine`): a = a₁ + a₂ − 1, b = b₁ + b₂ + len·(a₁ − 1), modulo 65521.
    fn combine(self, next: Adler32, len: usize) -> Adler32 {
        const MOD: u64 = 65521;
        let rem = len as u64 % MOD;
        let (a1, b1) = (u64::from(self.a), u64::from(self.b));
        let (a2, b2) = (u64::from(next.a), u64::from(next.b));
        let a = (a1 + a2 + MOD - 1) % MOD;
        let b = (b1 + b2 + rem * ((a1 + MOD - 1) % MOD)) % MOD;
        Adler32 { a: a as u32, b: b as u32 }
    }
}

/// Filters `rows` (whole rows of `prev.len()` bytes; above the first: `prev`) into `out`, a
/// filter byte and the filtered row each, picking per row the filter with the least sum.
fn filter_rows(bpp: usize, prev: &[u8], rows: &[u8], out: &mut Vec<u8>) {
    #[cfg(target_arch = "x86_64")]
    if crate::kernels::isa::Isa::Avx2.supported() {
        // SAFETY: the CPU has AVX2 (checked above). Integer filters: the same bytes on every
        // variant.
        return unsafe { filter_rows_avx2(bpp, prev, rows, out) };
    }
    filter_rows_body(bpp, prev, rows, out);
}

/// [`filter_rows`] compiled for AVX2: the filters and their sums 32 bytes a vector.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn filter_rows_avx2(bpp: usize, prev: &[u8], rows: &[u8], out: &mut Vec<u8>) {
    filter_rows_body(bpp, prev, rows, out);
}

#[inline(always)]
fn filter_rows_body(bpp: usize, prev: &[u8], rows: &[u8], out: &mut Vec<u8>) {
    let n = prev.len();
    let mut cand = vec![0; n];
    let mut best = vec![0; n];
    let mut above = prev;
    for cur in rows.chunks_exact(n) {
        let mut best_sum = u64::MAX;
        let mut best_kind = 0;
        for kind in 0..5u8 {
            let sum = filter_row(kind, bpp, above, cur, &mut cand);
            if sum < best_sum {
                best_sum = sum;
                best_kind = kind;
                std::mem::swap(&mut best, &mut cand);
            }
        }
        out.push(best_kind);
        out.extend_from_slice(&best);
        above = cur;
    }
}

/// Locks `m`, also after a panic elsewhere (the data are scratch buffers, rewritten before use).
fn lock<T>(m: &std::sync::Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// Runs `data` through `deflate` with a sync flush (ending at a byte boundary), appending to
/// `out`.
fn deflate_sync(deflate: &mut flate2::Compress, data: &[u8], out: &mut Vec<u8>) -> Result<()> {
    let mut pos = 0;
    loop {
        out.reserve((data.len() - pos) + (data.len() >> 6) + 4096);
        let before = deflate.total_in();
        deflate
            .compress_vec(&data[pos..], out, flate2::FlushCompress::Sync)
            .map_err(|e| png_error("deflate", e))?;
        pos += (deflate.total_in() - before) as usize;
        if pos == data.len() && out.len() < out.capacity() {
            return Ok(());
        }
    }
}

/// One piece's deflate data: `data` compressed by `deflate` reset, primed with `dict` (the
/// bytes just before it in the stream; none when empty), flushed to a byte boundary; or stored
/// blocks when those are not larger. Appends to `out`. A reset compressor is a fresh one, so
/// which compressor (and thread) compresses a piece never shows in its bytes.
fn deflate_piece(
    deflate: &mut flate2::Compress,
    dict: &[u8],
    data: &[u8],
    out: &mut Vec<u8>,
) -> Result<()> {
    let start = out.len();
    deflate.reset();
    if !dict.is_empty() {
        let mut primed = Vec::with_capacity(dict.len() + 1024);
        deflate_sync(deflate, dict, &mut primed)?;
    }
    deflate_sync(deflate, data, out)?;
    let stored = data.len() + 5 * data.len().div_ceil(65535);
    if out.len() - start > stored {
        out.truncate(start);
        store_blocks(data, out);
    }
    Ok(())
}

/// `f(0), …, f(n − 1)` in parallel, in order: on the current rayon pool when called from one
/// of its threads (the caller runs jobs itself while it waits, so this finishes even when the
/// pool's other threads are busy or blocked), else on up to `threads` scoped threads, the
/// caller one of them (a plain thread never waits on pool jobs: the pool's threads may be
/// waiting on it).
fn par_map<R: Send>(n: usize, threads: usize, f: impl Fn(usize) -> R + Sync) -> Vec<R> {
    use rayon::prelude::*;
    if n <= 1 || threads <= 1 {
        return (0..n).map(f).collect();
    }
    if rayon::current_thread_index().is_some() {
        return (0..n).into_par_iter().with_max_len(1).map(&f).collect();
    }
    let next = std::sync::atomic::AtomicUsize::new(0);
    let work = || {
        let mut done = Vec::new();
        loop {
            let i = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            if i >= n {
                return done;
            }
            done.push((i, f(i)));
        }
    };
    let mut all: Vec<(usize, R)> = std::thread::scope(|s| {
        let helpers: Vec<_> = (1..threads.min(n)).map(|_| s.spawn(work)).collect();
        let mut all = work();
        for h in helpers {
            match h.join() {
                Ok(part) => all.extend(part),
                Err(panic) => std::panic::resume_unwind(panic),
            }
        }
        all
    });
    all.sort_unstable_by_key(|(i, _)| *i);
    all.into_iter().map(|(_, r)| r).collect()
}

impl<W: std::io::Write, T: PngSample> PngRowWriter<W, T> {
    /// Writes the PNG signature and header of a `width × height` image to `out`.
    ///
    /// # Errors
    /// [`Error::Io`] when `out` fails; [`Error::Internal`] for a 0-sized or oversized image.
    pub fn new(mut out: W, width: usize, height: usize, color: PngColor) -> Result<Self> {
        write_header::<W, T>(&mut out, width, height, color)?;
        let small = width.saturating_mul(height) <= SMALL_IMAGE_TEXELS;
        let level = if small { flate2::Compression::default().level() } else { 1 };
        let row_samples = width * color.channels();
        let row_bytes = row_samples * usize::from(T::BITS / 8);
        let rows_per_piece = PIECE.div_ceil(row_bytes + 1);
        let pieces_per_batch = (4 * rayon::current_num_threads()).clamp(4, 64);
        let batch_rows = (rows_per_piece * pieces_per_batch).min(height);
        // The zlib header: deflate, 32 KiB window, no dictionary (0x78 0x01 is a valid check).
        let mut idat = Vec::with_capacity(STREAM_CHUNK.min(row_bytes * height + 64) + PIECE);
        idat.extend_from_slice(&[0x78, 0x01]);
        Ok(PngRowWriter {
            out,
            level,
            row_samples,
            row_bytes,
            bpp: color.channels() * usize::from(T::BITS / 8),
            rows_left: height,
            rows_per_piece,
            pieces_per_batch,
            dictionary: small,
            prev: vec![0; row_bytes],
            raw: Vec::with_capacity(batch_rows * row_bytes),
            tail: Vec::new(),
            filtered: Vec::new(),
            deflated: Vec::new(),
            compressors: std::sync::Mutex::new(Vec::new()),
            adler: Adler32::new(),
            idat,
            _sample: std::marker::PhantomData,
        })
    }

    /// Primes every piece with the 32 KiB before it (`true`) or not, whatever the image size:
    /// only to measure what that buys (`cargo test --bench png_encode`); the output is still a
    /// valid PNG of the same samples, but not the same bytes.
    #[doc(hidden)]
    #[must_use]
    pub fn dictionary(mut self, on: bool) -> Self {
        self.dictionary = on;
        self
    }

    /// Appends whole rows (`rows.len()` a multiple of `width · channels`).
    ///
    /// # Errors
    /// [`Error::Internal`] for a partial row or more rows than the image has; [`Error::Io`].
    pub fn write_rows(&mut self, rows: &[T]) -> Result<()> {
        check_rows(rows.len(), self.row_samples, self.rows_left)?;
        let batch_rows = self.rows_per_piece * self.pieces_per_batch;
        let mut rest = rows;
        while !rest.is_empty() {
            let have = self.raw.len() / self.row_bytes;
            let take = (batch_rows - have).min(rest.len() / self.row_samples);
            let (now, later) = rest.split_at(take * self.row_samples);
            T::extend_be(now, &mut self.raw);
            self.rows_left -= take;
            rest = later;
            if have + take == batch_rows {
                self.deflate_batch()?;
            }
        }
        Ok(())
    }

    /// Filters and deflates the buffered rows, piece by piece in parallel, appends the pieces
    /// to the IDAT data in order and writes out whole IDAT chunks.
    fn deflate_batch(&mut self) -> Result<()> {
        if self.raw.is_empty() {
            return Ok(());
        }
        let (rb, bpp, level) = (self.row_bytes, self.bpp, self.level);
        let threads = rayon::current_num_threads();
        let piece_raw = self.rows_per_piece * rb;
        let pieces: Vec<&[u8]> = self.raw.chunks(piece_raw).collect();
        let n = pieces.len();
        let (raw, prev) = (&self.raw, &self.prev);
        let mut bufs = std::mem::take(&mut self.filtered);
        bufs.resize_with(n.max(bufs.len()), Vec::new);
        let slots: Vec<std::sync::Mutex<Vec<u8>>> =
            bufs.into_iter().map(std::sync::Mutex::new).collect();
        let adlers: Vec<Adler32> = par_map(n, threads, |k| {
            let above = if k == 0 { &prev[..] } else { &raw[k * piece_raw - rb..k * piece_raw] };
            let mut out = lock(&slots[k]);
            out.clear();
            filter_rows(bpp, above, pieces[k], &mut out);
            let mut adler = Adler32::new();
            adler.update(&out);
            adler
        });
        let filtered: Vec<Vec<u8>> = slots
            .into_iter()
            .map(|m| m.into_inner().unwrap_or_else(std::sync::PoisonError::into_inner))
            .collect();
        let (tail, dictionary, compressors) = (&self.tail, self.dictionary, &self.compressors);
        let mut bufs = std::mem::take(&mut self.deflated);
        bufs.resize_with(n.max(bufs.len()), Vec::new);
        let slots: Vec<std::sync::Mutex<Vec<u8>>> =
            bufs.into_iter().map(std::sync::Mutex::new).collect();
        let done: Vec<Result<()>> = par_map(n, threads, |k| {
            let dict = if !dictionary {
                Vec::new()
            } else {
                // The last WINDOW bytes before piece k (a whole piece is longer than WINDOW).
                let mut before: Vec<&[u8]> = vec![tail];
                before.extend(filtered[..k].iter().map(|f| &f[..]));
                last_bytes(&before, WINDOW)
            };
            let mut deflate = lock(compressors)
                .pop()
                .unwrap_or_else(|| flate2::Compress::new(flate2::Compression::new(level), false));
            let mut out = lock(&slots[k]);
            out.clear();
            let res = deflate_piece(&mut deflate, &dict, &filtered[k], &mut out);
            lock(compressors).push(deflate);
            res
        });
        let deflated: Vec<Vec<u8>> = slots
            .into_iter()
            .map(|m| m.into_inner().unwrap_or_else(std::sync::PoisonError::into_inner))
            .collect();
        for (k, res) in done.into_iter().enumerate() {
            res?;
            self.adler = self.adler.combine(adlers[k], filtered[k].len());
            self.idat.extend_from_slice(&deflated[k]);
        }
        let mut before: Vec<&[u8]> = vec![&self.tail];
        before.extend(filtered[..n].iter().map(|f| &f[..]));
        self.tail = last_bytes(&before, WINDOW);
        self.filtered = filtered;
        self.deflated = deflated;
        self.prev.copy_from_slice(&self.raw[self.raw.len() - rb..]);
        self.raw.clear();
        let mut written = 0;
        while self.idat.len() - written >= STREAM_CHUNK {
            write_chunk(&mut self.out, b"IDAT", &self.idat[written..written + STREAM_CHUNK])?;
            written += STREAM_CHUNK;
        }
        self.idat.drain(..written);
        Ok(())
    }

    /// Ends the image (last IDAT, IEND) once every row was written, and hands the output back.
    ///
    /// # Errors
    /// [`Error::Internal`] when rows are missing; [`Error::Io`] when any write failed.
    pub fn finish(mut self) -> Result<W> {
        if self.rows_left != 0 {
            return Err(Error::Internal(format!("png: {} rows never written", self.rows_left)));
        }
        self.deflate_batch()?;
        write_trailer(&mut self.out, &mut self.idat, self.adler)?;
        Ok(self.out)
    }
}

/// The last `n` bytes (or all, if fewer) of the concatenation of `parts`.
fn last_bytes(parts: &[&[u8]], n: usize) -> Vec<u8> {
    let mut need = n;
    let mut ends: Vec<&[u8]> = Vec::new();
    for p in parts.iter().rev() {
        if need == 0 {
            break;
        }
        let take = need.min(p.len());
        ends.push(&p[p.len() - take..]);
        need -= take;
    }
    ends.reverse();
    ends.concat()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_8_and_16() {
        let d8: Vec<u8> = (0..3 * 2 * 4).map(|v| (v * 10) as u8).collect();
        let png8 = encode8(3, 2, PngColor::Rgba, &d8).unwrap();
        let img = image::load_from_memory(&png8).unwrap().to_rgba8();
        assert_eq!(img.as_raw(), &d8);
        let d16: Vec<u16> = (0..3 * 2).map(|v| (v * 10001) as u16).collect();
        let png16 = encode16(3, 2, PngColor::Gray, &d16).unwrap();
        let img = image::load_from_memory(&png16).unwrap().to_luma16();
        assert_eq!(img.as_raw(), &d16);
        assert!(encode8(3, 3, PngColor::Rgba, &d8).is_err());
    }

    #[test]
    fn streamed_rows_are_the_same_bytes_as_one_piece() {
        // The service encodes whole layers, the CLI streams bands: downloads must equal files.
        let (w, h) = (7usize, 23usize);
        let d16: Vec<u16> =
            (0..w * h * 4).map(|v| (v as u64 * 2654435761 % 65536) as u16).collect();
        let whole = encode16(w, h, PngColor::Rgba, &d16).unwrap();
        let mut pw = PngRowWriter::<Vec<u8>, u16>::new(Vec::new(), w, h, PngColor::Rgba).unwrap();
        for rows in [3usize, 1, 8, 11] {
            let start = d16.len() - pw_rows_left(&pw) * w * 4;
            pw.write_rows(&d16[start..start + rows * w * 4]).unwrap();
        }
        assert_eq!(pw.finish().unwrap(), whole);
    }

    fn pw_rows_left<W: std::io::Write + 'static, T: PngSample>(pw: &PngRowWriter<W, T>) -> usize {
        pw.rows_left
    }

    /// A horizon-like RGBA8 layer: four channels of smooth ramps with a little noise, so its
    /// filtered rows compress but not to nothing.
    fn layer8(w: usize, h: usize, seed: u64) -> Vec<u8> {
        let mut s = seed;
        (0..w * h * 4)
            .map(|i| {
                s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                let (x, y, c) = ((i / 4) % w, i / 4 / w, i % 4);
                let smooth = ((x as f32 * 0.013 * (c + 1) as f32).sin() * 60.0
                    + (y as f32 * 0.007).cos() * 50.0
                    + 120.0) as i32;
                (smooth + ((s >> 61) as i32 - 4)).clamp(0, 255) as u8
            })
            .collect()
    }

    /// Encodes through [`PngRowWriter`] in calls of `bands` rows (cycled).
    fn streamed<T: PngSample>(
        w: usize,
        h: usize,
        c: PngColor,
        d: &[T],
        bands: &[usize],
    ) -> Vec<u8> {
        let mut pw = PngRowWriter::<Vec<u8>, T>::new(Vec::new(), w, h, c).unwrap();
        let row = w * c.channels();
        let (mut y, mut k) = (0, 0);
        while y < h {
            let n = bands[k % bands.len()].min(h - y);
            pw.write_rows(&d[y * row..(y + n) * row]).unwrap();
            y += n;
            k += 1;
        }
        pw.finish().unwrap()
    }

    fn oracle<T: PngSample>(w: usize, h: usize, c: PngColor, d: &[T]) -> Vec<u8> {
        let mut pw =
            single_stream::SingleStreamWriter::<Vec<u8>, T>::new(Vec::new(), w, h, c).unwrap();
        pw.write_rows(d).unwrap();
        pw.finish().unwrap()
    }

    /// The IDAT data inflated by a zlib decoder that checks the Adler-32 (the `image` crate's
    /// PNG decoder does not): the filtered rows.
    fn inflate_checked(png: &[u8]) -> Vec<u8> {
        use std::io::Read;
        let (mut i, mut z) = (8, Vec::new());
        while i < png.len() {
            let n = u32::from_be_bytes(png[i..i + 4].try_into().unwrap()) as usize;
            if &png[i + 4..i + 8] == b"IDAT" {
                z.extend_from_slice(&png[i + 8..i + 8 + n]);
            }
            i += 12 + n;
        }
        let mut out = Vec::new();
        flate2::read::ZlibDecoder::new(&z[..]).read_to_end(&mut out).unwrap();
        // A wrong checksum is an error above; a flipped one must be too.
        let last = z.len() - 1;
        z[last] ^= 1;
        assert!(flate2::read::ZlibDecoder::new(&z[..]).read_to_end(&mut Vec::new()).is_err());
        out
    }

    fn pool(n: usize) -> rayon::ThreadPool {
        rayon::ThreadPoolBuilder::new().num_threads(n).build().unwrap()
    }

    #[test]
    fn same_bytes_on_any_number_of_threads_and_any_split() {
        // 1100² RGBA8: level 1, 19 pieces of 59 rows, batches of 4 pieces on one thread and
        // 16 on four; 400×600 (under 512² texels): the default level, 4 pieces.
        for (w, h) in [(1100usize, 1100usize), (400, 600)] {
            let d = layer8(w, h, 7);
            let whole = pool(1).install(|| encode8(w, h, PngColor::Rgba, &d).unwrap());
            let four = pool(4).install(|| streamed(w, h, PngColor::Rgba, &d, &[37, 1, 200]));
            assert!(whole == four, "{w}×{h}: 1 thread whole vs 4 threads in bands");
            let d2 = d.clone();
            // A plain thread (not a pool's): the scoped-thread path.
            let plain = std::thread::spawn(move || streamed(w, h, PngColor::Rgba, &d2, &[59, 3]))
                .join()
                .unwrap();
            assert!(whole == plain, "{w}×{h}: plain thread in bands");
            let img = image::load_from_memory(&whole).unwrap().to_rgba8();
            assert!(img.as_raw() == &d, "{w}×{h}: decodes to the samples");
            assert_eq!(inflate_checked(&whole).len(), h * (w * 4 + 1), "{w}×{h}: checksum");
            let old = image::load_from_memory(&oracle(w, h, PngColor::Rgba, &d)).unwrap();
            assert!(old.to_rgba8().as_raw() == &d);
        }
        // 16-bit grey and alpha, rows of 3 KiB: pieces of 86 rows.
        let (w, h) = (769usize, 700usize);
        let d16: Vec<u16> = layer8(w, h, 3)
            .chunks(2)
            .map(|p| u16::from(p[0]) << 8 | u16::from(p[1] >> 3))
            .collect();
        let a = pool(1).install(|| streamed(w, h, PngColor::GrayAlpha, &d16, &[700]));
        let b = pool(4).install(|| streamed(w, h, PngColor::GrayAlpha, &d16, &[5, 86, 87]));
        assert!(a == b, "16-bit: 1 vs 4 threads");
        let img = image::load_from_memory(&a).unwrap();
        assert_eq!(img.color(), image::ColorType::La16);
        let got: Vec<u16> = img.to_luma_alpha16().into_raw();
        assert!(got == d16, "16-bit decodes to the samples");
        assert_eq!(inflate_checked(&a).len(), h * (w * 4 + 1));
    }

    #[test]
    fn noise_is_stored_and_the_dictionary_pays() {
        // Noise: never larger than the samples plus the framing, on 1 thread or 4.
        let (w, h) = (1024usize, 1024usize);
        let mut s = 11u64;
        let noise: Vec<u8> = (0..w * h * 4)
            .map(|_| {
                s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                (s >> 56) as u8
            })
            .collect();
        let raw = noise.len();
        let framing = h
            + 5 * (raw + h).div_ceil(65535)
            + 5 * (raw + h).div_ceil(PIECE)
            + 12 * (raw / STREAM_CHUNK + 1)
            + 57;
        for n in [1, 4] {
            let png = pool(n).install(|| streamed(w, h, PngColor::Rgba, &noise, &[100]));
            assert!(png.len() <= raw + framing, "{n} threads: {} for {raw}", png.len());
            let img = image::load_from_memory(&png).unwrap().to_rgba8();
            assert!(img.as_raw() == &noise);
            assert_eq!(inflate_checked(&png).len(), h * (w * 4 + 1));
        }
        // A repetitive layer (a 600-byte period, rows of 4400 bytes): with the 32 KiB before
        // each piece as its dictionary the pieces start with matches, without they cannot.
        let (w, h) = (1100usize, 1100usize);
        let d: Vec<u8> = (0..w * h * 4).map(|i| ((i % 600) * 7 % 251) as u8).collect();
        let with_dict = |on: bool| {
            let mut pw = PngRowWriter::<Vec<u8>, u8>::new(Vec::new(), w, h, PngColor::Rgba)
                .unwrap()
                .dictionary(on);
            pw.write_rows(&d).unwrap();
            pw.finish().unwrap()
        };
        let (with, without) = (with_dict(true), with_dict(false));
        assert!(without == encode8(w, h, PngColor::Rgba, &d).unwrap(), "level 1: no dictionary");
        assert!(with.len() < without.len(), "with {} without {}", with.len(), without.len());
        let img = image::load_from_memory(&with).unwrap().to_rgba8();
        assert!(img.as_raw() == &d);
        assert_eq!(inflate_checked(&with).len(), h * (w * 4 + 1));
    }

    #[test]
    fn adler_of_pieces_combines_to_the_adler_of_the_whole() {
        let data: Vec<u8> =
            (0..200_000u32).map(|i| (i.wrapping_mul(2654435761) >> 13) as u8).collect();
        let mut whole = Adler32::new();
        whole.update(&data);
        for cut in [0, 1, 5551, 5552, 65521, 65522, 131_043, 199_999, 200_000] {
            let (a, b) = data.split_at(cut);
            let (mut x, mut y) = (Adler32::new(), Adler32::new());
            x.update(a);
            y.update(b);
            assert_eq!(x.combine(y, b.len()).finish(), whole.finish(), "cut at {cut}");
        }
        // zlib's value for a known string.
        let mut w = Adler32::new();
        w.update(b"Wikipedia");
        assert_eq!(w.finish(), 0x11E6_0398);
    }
}

#[cfg(test)]
mod stream_tests {
    use super::*;

    /// Accepts `budget` bytes, then fails every write (a full disk).
    struct Failing {
        budget: usize,
    }
    impl std::io::Write for Failing {
        fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
            if buf.len() > self.budget {
                return Err(std::io::Error::new(std::io::ErrorKind::StorageFull, "disk full"));
            }
            self.budget -= buf.len();
            Ok(buf.len())
        }
        fn flush(&mut self) -> std::io::Result<()> {
            Ok(())
        }
    }

    #[test]
    fn rows_in_uneven_chunks_decode_to_the_samples() {
        let (w, h) = (5, 7);
        let d16: Vec<u16> = (0..w * h * 4).map(|v| (v * 977 % 65536) as u16).collect();
        let mut wr = PngRowWriter::<_, u16>::new(Vec::new(), w, h, PngColor::Rgba).unwrap();
        let row = w * 4;
        for (a, b) in [(0, 1), (1, 4), (4, 4), (4, 7)] {
            wr.write_rows(&d16[a * row..b * row]).unwrap();
        }
        let png = wr.finish().unwrap();
        let img = image::load_from_memory(&png).unwrap().to_rgba16();
        assert_eq!(img.as_raw(), &d16);

        let d8: Vec<u8> = (0..w * h).map(|v| (v * 37) as u8).collect();
        let mut wr = PngRowWriter::<_, u8>::new(Vec::new(), w, h, PngColor::Gray).unwrap();
        wr.write_rows(&d8[..2 * w]).unwrap();
        wr.write_rows(&d8[2 * w..]).unwrap();
        let png = wr.finish().unwrap();
        let img = image::load_from_memory(&png).unwrap();
        assert!(matches!(img, image::DynamicImage::ImageLuma8(_)));
        assert_eq!(img.to_luma8().as_raw(), &d8);
    }

    #[test]
    fn partial_extra_and_missing_rows_are_errors() {
        let mut wr = PngRowWriter::<_, u8>::new(Vec::new(), 3, 2, PngColor::Rgba).unwrap();
        assert!(matches!(wr.write_rows(&[0; 5]), Err(Error::Internal(_))));
        assert!(matches!(wr.write_rows(&[0; 36]), Err(Error::Internal(_))));
        wr.write_rows(&[0; 12]).unwrap();
        match wr.finish() {
            Err(Error::Internal(m)) => assert!(m.contains("1 rows never written"), "{m}"),
            other => panic!("{:?}", other.map(|_| ())),
        }
        assert!(PngRowWriter::<_, u8>::new(Vec::new(), 0, 2, PngColor::Rgba).is_err());
    }

    #[test]
    fn write_errors_surface_even_from_the_final_writes() {
        // Fails on the header, in the data, and only at the very end (last IDAT / IEND, which
        // the png crate writes in destructors): each must come back as the
        // writer's error (a full disk: Error::StorageFull).
        let (w, h) = (64, 64);
        let rows = vec![7u16; w * h * 4];
        let full = {
            let mut wr = PngRowWriter::<_, u16>::new(Vec::new(), w, h, PngColor::Rgba).unwrap();
            wr.write_rows(&rows).unwrap();
            wr.finish().unwrap().len()
        };
        assert!(matches!(
            PngRowWriter::<_, u16>::new(Failing { budget: 10 }, w, h, PngColor::Rgba),
            Err(Error::StorageFull { .. })
        ));
        for budget in [100, full - 20, full - 1] {
            let res = PngRowWriter::<_, u16>::new(Failing { budget }, w, h, PngColor::Rgba)
                .and_then(|mut wr| {
                    wr.write_rows(&rows)?;
                    wr.finish().map(|_| ())
                });
            assert!(matches!(res, Err(Error::StorageFull { .. })), "budget {budget}: {:?}", res);
        }
        let ok = PngRowWriter::<_, u16>::new(Failing { budget: full }, w, h, PngColor::Rgba)
            .and_then(|mut wr| {
                wr.write_rows(&rows)?;
                wr.finish().map(|_| ())
            });
        assert!(ok.is_ok(), "{ok:?}");
    }
}
