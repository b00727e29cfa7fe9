//! The single-stream writer this crate used before the parallel one in [`super::PngRowWriter`]:
//! one zlib stream whose 256 KiB pieces are each sync-flushed (or stored), compressed on the
//! calling thread only. Kept as the oracle the tests decode against and the baseline of
//! `cargo bench --bench png_encode`; nothing in the product writes with it.

use super::{
    check_rows, filter_row, png_error, store_blocks, write_chunk, write_header, write_trailer,
    Adler32, PngColor, PngSample, PIECE, SMALL_IMAGE_TEXELS, STREAM_CHUNK,
};
use crate::error::{Error, Result};

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
pub struct SingleStreamWriter<W: std::io::Write, T: PngSample> {
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

impl<W: std::io::Write, T: PngSample> SingleStreamWriter<W, T> {
    /// Writes the PNG signature and header of a `width × height` image to `out`.
    ///
    /// # Errors
    /// [`Error::Io`] when `out` fails; [`Error::Internal`] for a 0-sized or oversized image.
    pub fn new(mut out: W, width: usize, height: usize, color: PngColor) -> Result<Self> {
        write_header::<W, T>(&mut out, width, height, color)?;
        let small = width.saturating_mul(height) <= SMALL_IMAGE_TEXELS;
        let level =
            if small { flate2::Compression::default() } else { flate2::Compression::new(1) };
        let row_samples = width * color.channels();
        let row_bytes = row_samples * usize::from(T::BITS / 8);
        // The zlib header: deflate, 32 KiB window, no dictionary (0x78 0x01 is a valid check).
        let mut idat = Vec::with_capacity(STREAM_CHUNK.min(row_bytes * height + 64) + PIECE);
        idat.extend_from_slice(&[0x78, 0x01]);
        Ok(SingleStreamWriter {
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
        check_rows(rows.len(), self.row_samples, self.rows_left)?;
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
            // The compressor's window holds the same bytes either way.
            store_blocks(&self.pending, &mut self.idat);
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
        write_trailer(&mut self.out, &mut self.idat, self.adler)?;
        Ok(self.out)
    }
}
