//! PNG writers (8-bit and 16-bit, gray or RGBA), via the `png` crate directly so 16-bit samples
//! are written big-endian as the format requires without an intermediate image type.

use crate::error::{Error, Result};

/// PNG colour layouts we write.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PngColor {
    Gray,
    Rgba,
}

impl PngColor {
    fn channels(self) -> usize {
        match self {
            PngColor::Gray => 1,
            PngColor::Rgba => 4,
        }
    }
    fn png(self) -> png::ColorType {
        match self {
            PngColor::Gray => png::ColorType::Grayscale,
            PngColor::Rgba => png::ColorType::Rgba,
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

/// The output of a [`PngRowWriter`] and the first I/O error seen on it. The `png` crate drops the
/// errors of its last writes (the final IDAT flush and IEND happen in destructors) and keeps the
/// writer it was given, so both live here, shared, for [`PngRowWriter::finish`] to check and
/// hand back.
struct Shared<W> {
    out: W,
    error: Option<std::io::Error>,
}

type SharedOut<W> = std::sync::Arc<std::sync::Mutex<Shared<W>>>;

/// The `io::Write` the `png` crate writes to.
struct Latch<W>(SharedOut<W>);

impl<W: std::io::Write> Latch<W> {
    fn with<T>(&self, f: impl FnOnce(&mut W) -> std::io::Result<T>) -> std::io::Result<T> {
        let mut s = self.0.lock().map_err(|_| std::io::Error::other("png output poisoned"))?;
        let r = f(&mut s.out);
        if let (Err(e), None) = (&r, &s.error) {
            s.error = Some(std::io::Error::new(e.kind(), e.to_string()));
        }
        r
    }
}

impl<W: std::io::Write> std::io::Write for Latch<W> {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.with(|w| w.write(buf))
    }
    fn flush(&mut self) -> std::io::Result<()> {
        self.with(|w| w.flush())
    }
}

/// IDAT chunk size of streamed PNGs (the `png` default of 4 KiB adds a chunk header per 4 KiB).
const STREAM_CHUNK: usize = 1 << 20;

/// Images up to this many texels are streamed with zlib's default level, larger ones with its
/// level 1 (see [`PngRowWriter::new`]).
const SMALL_IMAGE_TEXELS: usize = 512 * 512;

/// Writes a PNG row by row to any [`std::io::Write`] (a file, usually), so neither the samples
/// nor the encoded image need to be in memory whole: 16-bit rows are converted to big-endian one
/// call at a time. Same colour and depth as [`encode8`] / [`encode16`]; the bytes may differ
/// (whole images may differ in how zlib splits blocks), the samples never do. Every deflate
/// block falls back to stored when compression does not pay, so a layer is never larger than
/// its samples plus the framing (a filter byte per row, 5 bytes per block, 12 per chunk).
pub struct PngRowWriter<W: std::io::Write + 'static, T: PngSample> {
    stream: png::StreamWriter<'static, Latch<W>>,
    shared: SharedOut<W>,
    row_samples: usize,
    rows_left: usize,
    be: Vec<u8>,
    _sample: std::marker::PhantomData<T>,
}

fn png_error(what: &str, e: impl std::fmt::Display) -> Error {
    Error::Internal(format!("png {what}: {e}"))
}

/// The I/O error the output saw, if any (it explains a png error better than png does).
fn take_io<W>(shared: &SharedOut<W>) -> Option<Error> {
    shared.lock().ok().and_then(|mut s| s.error.take()).map(Error::Io)
}

impl<W: std::io::Write + 'static, T: PngSample> PngRowWriter<W, T> {
    /// Writes the PNG header of a `width × height` image to `out`.
    ///
    /// # Errors
    /// [`Error::Io`] when `out` fails; [`Error::Internal`] for a 0-sized or oversized image.
    pub fn new(out: W, width: usize, height: usize, color: PngColor) -> Result<Self> {
        let (Ok(w32), Ok(h32)) = (u32::try_from(width), u32::try_from(height)) else {
            return Err(Error::Internal(format!("png: {width}×{height} is too large")));
        };
        if width == 0 || height == 0 {
            return Err(Error::Internal(format!("png: {width}×{height} has no pixels")));
        }
        let shared = std::sync::Arc::new(std::sync::Mutex::new(Shared { out, error: None }));
        let mut enc = png::Encoder::new(Latch(shared.clone()), w32, h32);
        enc.set_color(color.png());
        enc.set_depth(if T::BITS == 16 { png::BitDepth::Sixteen } else { png::BitDepth::Eight });
        // fdeflate's `Fast` streams with one fixed Huffman table and no fallback, so on
        // incompressible rows (the layers of a rough map are close to noise) it writes more
        // than the raw samples: 555 KB for a 256² 16-bit layer of 524 KB, 18.4 MB for a 2048²
        // 8-bit layer of 16.8 MB. zlib (miniz_oxide) decides per deflate block (at most 64 KiB
        // of input) between its Huffman codes and a stored block, so no band of rows is ever
        // written larger than its samples plus 5 bytes per block. Small images use its default
        // level; large ones level 1, its fastest that still searches matches.
        let small = width.saturating_mul(height) <= SMALL_IMAGE_TEXELS;
        enc.set_compression(png::Compression::Balanced);
        if !small {
            enc.set_deflate_compression(png::DeflateCompression::Level(1));
        }
        let stream = enc.write_header().and_then(|w| w.into_stream_writer_with_size(STREAM_CHUNK));
        match stream {
            Ok(stream) => Ok(PngRowWriter {
                stream,
                shared,
                row_samples: width * color.channels(),
                rows_left: height,
                be: Vec::new(),
                _sample: std::marker::PhantomData,
            }),
            Err(e) => Err(take_io(&shared).unwrap_or_else(|| png_error("header", e))),
        }
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
        self.be.clear();
        T::extend_be(rows, &mut self.be);
        let r = std::io::Write::write_all(&mut self.stream, &self.be);
        r.map_err(|e| take_io(&self.shared).unwrap_or_else(|| png_error("data", e)))?;
        self.rows_left -= n;
        Ok(())
    }

    /// Ends the image (last IDAT, IEND) once every row was written, and hands the output back.
    ///
    /// # Errors
    /// [`Error::Internal`] when rows are missing; [`Error::Io`] when any write failed.
    pub fn finish(self) -> Result<W> {
        if self.rows_left != 0 {
            return Err(Error::Internal(format!("png: {} rows never written", self.rows_left)));
        }
        let PngRowWriter { stream, shared, .. } = self;
        // The stream writer writes the last IDAT and IEND as it drops, ignoring errors; the
        // latch has seen them.
        let r = stream.finish();
        let inner = std::sync::Arc::try_unwrap(shared)
            .map_err(|_| Error::Internal("png: output still shared after finish".into()))?
            .into_inner()
            .map_err(|_| Error::Internal("png: output poisoned".into()))?;
        match (inner.error, r) {
            (Some(e), _) => Err(Error::Io(e)),
            (None, Err(e)) => Err(png_error("finish", e)),
            (None, Ok(())) => Ok(inner.out),
        }
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
