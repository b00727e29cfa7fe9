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
    Rgba,
}

impl PngColor {
    fn channels(self) -> usize {
        match self {
            PngColor::Gray => 1,
            PngColor::GrayAlpha => 2,
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

/// Filtered bytes deflated as one piece: each piece is compressed and flushed on its own, and
/// written as stored blocks instead when compression does not pay for it.
const PIECE: usize = 256 * 1024;

/// Images up to this many texels are deflated at zlib's default level, larger ones at level 1.
const SMALL_IMAGE_TEXELS: usize = 512 * 512;

/// Writes a PNG row by row to any [`std::io::Write`] (a file, usually), so neither the samples
/// nor the encoded image need to be in memory whole: rows are filtered (the filter each row
/// compresses best by the usual sum-of-magnitudes rule), then deflated in pieces of 256 KiB
/// of filtered bytes, each flushed to a byte boundary; a piece that deflate would make larger
/// is written as stored blocks instead (the compressor's window holds the same bytes either
/// way, so later pieces may still refer to it). So a PNG is never larger than its samples plus
/// the framing: a filter byte per row, 5 bytes per stored block of 64 KiB, 5 per piece, 12 per
/// 1 MiB IDAT chunk, and the 57 bytes of signature, IHDR, IEND and zlib header and checksum.
///
/// The `png` crate's streaming writer had no such fallback: fdeflate's fixed Huffman table
/// wrote a 2048² 8-bit layer close to noise as 18.4 MB for 16.8 MB of samples, and zlib behind
/// it cannot store a block once it spans more than its 32 KiB window. The output is one
/// function of the rows, however they are split into calls, so a layer streamed in bands and
/// one written whole are the same bytes.
pub struct PngRowWriter<W: std::io::Write, T: PngSample> {
    out: W,
    deflate: flate2::Compress,
    adler: Adler32,
    row_samples: usize,
    /// Bytes per pixel (filters look this far left).
    bpp: usize,
    rows_left: usize,
    /// The previous row, unfiltered, and this one (big-endian bytes).
    prev: Vec<u8>,
    cur: Vec<u8>,
    /// Scratch for the five filter candidates.
    cand: Vec<u8>,
    best: Vec<u8>,
    /// Filtered bytes not deflated yet, and deflate's output of a piece.
    pending: Vec<u8>,
    piece: Vec<u8>,
    /// The IDAT data not written yet.
    idat: Vec<u8>,
    _sample: std::marker::PhantomData<T>,
}

fn png_error(what: &str, e: impl std::fmt::Display) -> Error {
    Error::Internal(format!("png {what}: {e}"))
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
    out.iter().map(|&b| u64::from((b as i8).unsigned_abs())).sum()
}

impl<W: std::io::Write, T: PngSample> PngRowWriter<W, T> {
    /// Writes the PNG signature and header of a `width × height` image to `out`.
    ///
    /// # Errors
    /// [`Error::Io`] when `out` fails; [`Error::Internal`] for a 0-sized or oversized image.
    pub fn new(mut out: W, width: usize, height: usize, color: PngColor) -> Result<Self> {
        let (Ok(w32), Ok(h32)) = (u32::try_from(width), u32::try_from(height)) else {
            return Err(Error::Internal(format!("png: {width}×{height} is too large")));
        };
        if width == 0 || height == 0 || w32 > i32::MAX as u32 || h32 > i32::MAX as u32 {
            return Err(Error::Internal(format!(
                "png: {width}×{height} has no pixels or too many"
            )));
        }
        out.write_all(b"\x89PNG\r\n\x1a\n")?;
        let mut ihdr = Vec::with_capacity(13);
        ihdr.extend_from_slice(&w32.to_be_bytes());
        ihdr.extend_from_slice(&h32.to_be_bytes());
        let color_type = match color {
            PngColor::Gray => 0,
            PngColor::GrayAlpha => 4,
            PngColor::Rgba => 6,
        };
        ihdr.extend_from_slice(&[T::BITS, color_type, 0, 0, 0]);
        write_chunk(&mut out, b"IHDR", &ihdr)?;
        let small = width.saturating_mul(height) <= SMALL_IMAGE_TEXELS;
        let level =
            if small { flate2::Compression::default() } else { flate2::Compression::new(1) };
        let row_samples = width * color.channels();
        let row_bytes = row_samples * usize::from(T::BITS / 8);
        // The zlib header: deflate, 32 KiB window, no dictionary (0x78 0x01 is a valid check).
        let mut idat = Vec::with_capacity(STREAM_CHUNK.min(row_bytes * height + 64) + PIECE);
        idat.extend_from_slice(&[0x78, 0x01]);
        Ok(PngRowWriter {
            out,
            deflate: flate2::Compress::new(level, false),
            adler: Adler32::new(),
            row_samples,
            bpp: color.channels() * usize::from(T::BITS / 8),
            rows_left: height,
            prev: vec![0; row_bytes],
            cur: Vec::with_capacity(row_bytes),
            cand: vec![0; row_bytes],
            best: vec![0; row_bytes],
            pending: Vec::with_capacity(PIECE + row_bytes + 1),
            piece: Vec::new(),
            idat,
            _sample: std::marker::PhantomData,
        })
    }

    /// Appends whole rows (`rows.len()` a multiple of `width · channels`).
    ///
    /// # Errors
    /// [`Error::Internal`] for a partial row or more rows than the image has; [`Error::Io`].
    pub fn write_rows(&mut self, rows: &[T]) -> Result<()> {
        let n = rows.len() / self.row_samples;
        if !rows.len().is_multiple_of(self.row_samples) || n > self.rows_left {
            return Err(Error::Internal(format!(
                "png rows: {} samples are not whole rows of {} within the {} rows left",
                rows.len(),
                self.row_samples,
                self.rows_left
            )));
        }
        for row in rows.chunks_exact(self.row_samples) {
            self.cur.clear();
            T::extend_be(row, &mut self.cur);
            let mut best_sum = u64::MAX;
            let mut best_kind = 0;
            for kind in 0..5u8 {
                let sum = filter_row(kind, self.bpp, &self.prev, &self.cur, &mut self.cand);
                if sum < best_sum {
                    best_sum = sum;
                    best_kind = kind;
                    std::mem::swap(&mut self.best, &mut self.cand);
                }
            }
            self.pending.push(best_kind);
            self.pending.extend_from_slice(&self.best);
            std::mem::swap(&mut self.prev, &mut self.cur);
            self.rows_left -= 1;
            if self.pending.len() >= PIECE {
                self.deflate_pending()?;
            }
        }
        Ok(())
    }

    /// Deflates the pending bytes as one piece (flushed to a byte boundary), or stores them
    /// when that would not be smaller, and writes out whole IDAT chunks.
    fn deflate_pending(&mut self) -> Result<()> {
        if self.pending.is_empty() {
            return Ok(());
        }
        self.adler.update(&self.pending);
        self.piece.clear();
        let mut pos = 0;
        loop {
            self.piece.reserve((self.pending.len() - pos) + (self.pending.len() >> 6) + 4096);
            let before = self.deflate.total_in();
            self.deflate
                .compress_vec(&self.pending[pos..], &mut self.piece, flate2::FlushCompress::Sync)
                .map_err(|e| png_error("deflate", e))?;
            pos += (self.deflate.total_in() - before) as usize;
            if pos == self.pending.len() && self.piece.len() < self.piece.capacity() {
                break;
            }
        }
        let stored = self.pending.len() + 5 * self.pending.len().div_ceil(65535);
        if self.piece.len() <= stored {
            self.idat.extend_from_slice(&self.piece);
        } else {
            // Stored blocks (BFINAL 0, BTYPE 00; the stream is at a byte boundary after every
            // piece): the decoder's window receives the same bytes the compressor's holds.
            for block in self.pending.chunks(65535) {
                let len = block.len() as u16;
                self.idat.push(0);
                self.idat.extend_from_slice(&len.to_le_bytes());
                self.idat.extend_from_slice(&(!len).to_le_bytes());
                self.idat.extend_from_slice(block);
            }
        }
        self.pending.clear();
        while self.idat.len() >= STREAM_CHUNK {
            write_chunk(&mut self.out, b"IDAT", &self.idat[..STREAM_CHUNK])?;
            self.idat.drain(..STREAM_CHUNK);
        }
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
        self.deflate_pending()?;
        // A final empty stored block, then the checksum of everything deflated.
        self.idat.extend_from_slice(&[1, 0, 0, 0xff, 0xff]);
        self.idat.extend_from_slice(&self.adler.finish().to_be_bytes());
        for chunk in self.idat.chunks(STREAM_CHUNK) {
            write_chunk(&mut self.out, b"IDAT", chunk)?;
        }
        write_chunk(&mut self.out, b"IEND", &[])?;
        self.out.flush()?;
        Ok(self.out)
    }
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
        // the png crate writes in destructors): each must come back as Error::Io.
        let (w, h) = (64, 64);
        let rows = vec![7u16; w * h * 4];
        let full = {
            let mut wr = PngRowWriter::<_, u16>::new(Vec::new(), w, h, PngColor::Rgba).unwrap();
            wr.write_rows(&rows).unwrap();
            wr.finish().unwrap().len()
        };
        assert!(matches!(
            PngRowWriter::<_, u16>::new(Failing { budget: 10 }, w, h, PngColor::Rgba),
            Err(Error::Io(_))
        ));
        for budget in [100, full - 20, full - 1] {
            let res = PngRowWriter::<_, u16>::new(Failing { budget }, w, h, PngColor::Rgba)
                .and_then(|mut wr| {
                    wr.write_rows(&rows)?;
                    wr.finish().map(|_| ())
                });
            assert!(matches!(res, Err(Error::Io(_))), "budget {budget}: {:?}", res);
        }
        let ok = PngRowWriter::<_, u16>::new(Failing { budget: full }, w, h, PngColor::Rgba)
            .and_then(|mut wr| {
                wr.write_rows(&rows)?;
                wr.finish().map(|_| ())
            });
        assert!(ok.is_ok(), "{ok:?}");
    }
}
