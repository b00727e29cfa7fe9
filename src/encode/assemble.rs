//! Results of a tiled bake assembled as streams (SPEC §7.1, issue 23): no process holds a whole
//! layer. Each tile's bake leaves a tile result blob ([`write_tile_result`]: its interior's
//! layers and terrain bands, plane by plane); the writers here pull rows of the whole map band
//! by band from a row source ([`TileRows`] reads them from the tile blobs by ranged reads) and
//! write the same bytes the untiled bake writes:
//! - PNG through the same [`PngRowWriter`], whose output does not depend on how the rows are
//!   split into calls;
//! - KTX2 and DDS level 0 after the header the whole-texture writers build
//!   ([`super::ktx2::prefix`], [`super::dds::header_bytes`]); mips, BC7/BC5 and zstd are refused
//!   for tiled bakes ([`check_tiled_texture`]);
//! - GeoTIFF one row of 512² TIFF tiles at a time, compressed by the whole writer's
//!   [`super::geotiff::tile_bytes`], spooled to a temporary file (the IFD offset in the header
//!   needs the compressed size), then header, tiles and [`super::geotiff::ifd_bytes`].
//!
//! Memory: a band of rows of the output (at most [`BAND_BYTES`], at least one row), the tile
//! blobs' headers, and for GeoTIFF one row of TIFF tiles (512 rows) per band.

use super::geotiff::{self, IfdAt, TILE};
use super::png::{PngColor, PngRowWriter, PngSample};
use super::texture::{DdsHeader, PixelFormat, Texture, TextureOptions, TexturePrecision};
use super::{dds, ktx2, Shape};
use crate::error::{Error, Result};
use crate::heightmap::georef::Georef;
use rayon::prelude::*;
use std::io::{Seek, SeekFrom, Write};

/// A row band of an assembled output holds about this many bytes.
pub const BAND_BYTES: usize = 16 << 20;

/// Rows per band for rows of `row_bytes`: [`BAND_BYTES`] worth, at least 1, at most 512.
pub fn band_rows(row_bytes: usize) -> usize {
    (BAND_BYTES / row_bytes.max(1)).clamp(1, 512)
}

/// A sample of a tile result plane: `u8`, `u16` or `f32`, little-endian in blobs.
pub trait LeSample: Copy + Default + Send + Sync + 'static {
    /// Bytes per sample.
    const BYTES: usize;
    /// The kind byte of a tile result section (1, 2 or 4).
    const KIND: u8;
    /// Reads one sample.
    fn from_le(b: &[u8]) -> Self;
    /// Appends samples, little-endian.
    fn extend_le(s: &[Self], out: &mut Vec<u8>);
}

impl LeSample for u8 {
    const BYTES: usize = 1;
    const KIND: u8 = 1;
    fn from_le(b: &[u8]) -> Self {
        b[0]
    }
    fn extend_le(s: &[Self], out: &mut Vec<u8>) {
        out.extend_from_slice(s);
    }
}

impl LeSample for u16 {
    const BYTES: usize = 2;
    const KIND: u8 = 2;
    fn from_le(b: &[u8]) -> Self {
        u16::from_le_bytes([b[0], b[1]])
    }
    fn extend_le(s: &[Self], out: &mut Vec<u8>) {
        out.extend(s.iter().flat_map(|v| v.to_le_bytes()));
    }
}

impl LeSample for f32 {
    const BYTES: usize = 4;
    const KIND: u8 = 4;
    fn from_le(b: &[u8]) -> Self {
        f32::from_le_bytes([b[0], b[1], b[2], b[3]])
    }
    fn extend_le(s: &[Self], out: &mut Vec<u8>) {
        out.extend(s.iter().flat_map(|v| v.to_le_bytes()));
    }
}

/// Tags of the sections of a tile result blob.
pub mod tag {
    /// Horizon layers quantised to 8 bits: 2 planes (layer 0, 1), 4 channels (RGBA).
    pub const HORIZON_U8: u32 = 1;
    /// Horizon layers at 16 bits: 2 planes, 4 channels.
    pub const HORIZON_U16: u32 = 2;
    /// Horizon layers as f32: 2 planes, 4 channels.
    pub const HORIZON_F32: u32 = 3;
    /// Terrain `angles`: one plane per bin, 1 channel, f32.
    pub const ANGLES: u32 = 10;
    /// Terrain `svf`: 1 plane, 1 channel, f32.
    pub const SVF: u32 = 11;
    /// Terrain `horizon_distance`: one plane per bin, 1 channel, f32.
    pub const DISTANCE: u32 = 12;
    /// Terrain `openness`: positive and negative, 1 plane each, f32.
    pub const OPENNESS_POSITIVE: u32 = 13;
    pub const OPENNESS_NEGATIVE: u32 = 14;
    /// Terrain `sun_hours` and `insolation`: 1 plane each, f32.
    pub const SUN_HOURS: u32 = 15;
    pub const INSOLATION: u32 = 16;
}

/// One plane of a tile result section.
#[derive(Debug, Clone, Copy)]
pub enum Plane<'a> {
    U8(&'a [u8]),
    U16(&'a [u16]),
    F32(&'a [f32]),
}

impl Plane<'_> {
    fn kind(&self) -> u8 {
        match self {
            Plane::U8(_) => 1,
            Plane::U16(_) => 2,
            Plane::F32(_) => 4,
        }
    }
    fn len(&self) -> usize {
        match self {
            Plane::U8(v) => v.len(),
            Plane::U16(v) => v.len(),
            Plane::F32(v) => v.len(),
        }
    }
}

/// A section of a tile result: planes of one sample type and channel count.
#[derive(Debug, Clone)]
pub struct Section<'a> {
    pub tag: u32,
    pub channels: u32,
    pub planes: Vec<Plane<'a>>,
}

/// Magic of a tile result blob.
pub const RESULT_MAGIC: &[u8; 4] = b"HBR1";

/// Writes a tile result blob of a `width × height` interior to `out`: `HBR1`, u32 width, u32
/// height, u32 section count, then per section 16 bytes (u8 kind 1/2/4, 3 zero bytes, u32
/// planes, u32 channels, u32 tag), then the planes, section by section, each
/// `width · height · channels` samples row-major; all little-endian.
///
/// # Errors
/// [`Error::Internal`] for a plane of the wrong size or mixed sample types; `out`'s errors.
pub fn write_tile_result<W: Write>(
    mut out: W,
    width: u32,
    height: u32,
    sections: &[Section<'_>],
) -> Result<W> {
    let texels = width as usize * height as usize;
    let mut head = Vec::with_capacity(16 + 16 * sections.len());
    head.extend_from_slice(RESULT_MAGIC);
    for v in [width, height, sections.len() as u32] {
        head.extend_from_slice(&v.to_le_bytes());
    }
    for s in sections {
        let kind = s.planes.first().map_or(4, Plane::kind);
        if s.planes.iter().any(|p| p.kind() != kind || p.len() != texels * s.channels as usize) {
            return Err(Error::Internal(format!("tile result section {}: plane mismatch", s.tag)));
        }
        head.extend_from_slice(&[kind, 0, 0, 0]);
        for v in [s.planes.len() as u32, s.channels, s.tag] {
            head.extend_from_slice(&v.to_le_bytes());
        }
    }
    out.write_all(&head)?;
    let mut buf = Vec::with_capacity(1 << 20);
    for s in sections {
        for p in &s.planes {
            // In pieces, so no second copy of a plane is made.
            let step = 1 << 18;
            for k in (0..p.len()).step_by(step) {
                buf.clear();
                let end = (k + step).min(p.len());
                match p {
                    Plane::U8(v) => u8::extend_le(&v[k..end], &mut buf),
                    Plane::U16(v) => u16::extend_le(&v[k..end], &mut buf),
                    Plane::F32(v) => f32::extend_le(&v[k..end], &mut buf),
                }
                out.write_all(&buf)?;
            }
        }
    }
    Ok(out)
}

/// Where a tile's interior lies in the map, and its result blob.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TilePiece {
    pub x0: u32,
    pub y0: u32,
    pub width: u32,
    pub height: u32,
    pub hash: String,
}

/// A section's place in a tile result blob.
#[derive(Debug, Clone, Copy)]
struct SectionAt {
    tag: u32,
    kind: u8,
    planes: u32,
    channels: u32,
    /// Byte offset of its first plane.
    start: u64,
}

/// The parsed header of a tile result blob.
#[derive(Debug, Clone)]
struct ResultIndex {
    width: u32,
    height: u32,
    sections: Vec<SectionAt>,
}

impl ResultIndex {
    fn parse(head: &[u8], more: impl FnOnce(usize) -> Result<Vec<u8>>) -> Result<Self> {
        let bad = || Error::Internal("not a tile result blob (HBR1)".into());
        if head.len() < 16 || &head[..4] != RESULT_MAGIC {
            return Err(bad());
        }
        let u = |b: &[u8], o: usize| u32::from_le_bytes([b[o], b[o + 1], b[o + 2], b[o + 3]]);
        let (width, height, n) = (u(head, 4), u(head, 8), u(head, 12) as usize);
        if n > 4096 {
            return Err(bad());
        }
        let table = more(16 * n)?;
        if table.len() != 16 * n {
            return Err(bad());
        }
        let texels = width as u64 * height as u64;
        let mut start = 16 + 16 * n as u64;
        let mut sections = Vec::with_capacity(n);
        for k in 0..n {
            let t = &table[16 * k..16 * k + 16];
            let s =
                SectionAt { kind: t[0], planes: u(t, 4), channels: u(t, 8), tag: u(t, 12), start };
            start += texels * s.channels as u64 * s.planes as u64 * s.kind as u64;
            sections.push(s);
        }
        Ok(ResultIndex { width, height, sections })
    }
}

/// Reads `len` bytes from byte `start` of the blob named `hash` (over a blob store:
/// `jobs::blob::read_range`; encode does not import the jobs core). Called from several
/// threads at once: the tiles a band crosses are read side by side.
pub type ReadRange = std::sync::Arc<dyn Fn(&str, u64, usize) -> Result<Vec<u8>> + Send + Sync>;

/// Rows of the whole map read from tile result blobs: for each band, one ranged read per tile
/// that the band crosses, so memory is the band and the reads.
pub struct TileRows {
    read: ReadRange,
    pieces: Vec<TilePiece>,
    index: Vec<Option<ResultIndex>>,
    width: usize,
    height: usize,
}

impl TileRows {
    /// A row source over `pieces`, which must cover the `width × height` map exactly once.
    ///
    /// # Errors
    /// [`Error::Internal`] for pieces outside the map or not covering it.
    pub fn new(
        read: ReadRange,
        pieces: Vec<TilePiece>,
        width: usize,
        height: usize,
    ) -> Result<Self> {
        let mut area = 0u64;
        for p in &pieces {
            if p.x0 as usize + p.width as usize > width
                || p.y0 as usize + p.height as usize > height
            {
                return Err(Error::Internal(format!("tile piece {p:?} is outside the map")));
            }
            area += p.width as u64 * p.height as u64;
        }
        if area != width as u64 * height as u64 {
            return Err(Error::Internal("the tile pieces do not cover the map once".into()));
        }
        let index = vec![None; pieces.len()];
        Ok(TileRows { read, pieces, index, width, height })
    }

    fn read_range(&mut self, hash: &str, start: u64, len: usize) -> Result<Vec<u8>> {
        checked_read(&self.read, hash, start, len)
    }

    fn index_of(&mut self, i: usize) -> Result<ResultIndex> {
        if let Some(ix) = &self.index[i] {
            return Ok(ix.clone());
        }
        let hash = self.pieces[i].hash.clone();
        let head = self.read_range(&hash, 0, 16)?;
        let ix = ResultIndex::parse(&head, |n| self.read_range(&hash, 16, n))?;
        let p = &self.pieces[i];
        if (ix.width, ix.height) != (p.width, p.height) {
            return Err(Error::Internal(format!(
                "tile result {hash} is {}×{}, its piece {}×{}",
                ix.width, ix.height, p.width, p.height
            )));
        }
        self.index[i] = Some(ix.clone());
        Ok(ix)
    }

    /// Fills `out` with rows `y0..y0 + n` (n = `out.len() / (width · channels)`) of plane
    /// `plane` of section `tag`, read from the tiles those rows cross.
    ///
    /// # Errors
    /// [`Error::Internal`] when a tile lacks the section or its sample type differs from `T`;
    /// the store's errors.
    pub fn read<T: LeSample>(
        &mut self,
        tag: u32,
        plane: usize,
        y0: usize,
        out: &mut [T],
    ) -> Result<()> {
        let w = self.width;
        let mut channels = 0;
        // Where each crossed tile's rows lie: (piece, first row, rows, byte start, row bytes).
        let mut wanted = Vec::new();
        for i in 0..self.pieces.len() {
            let (py0, ph) = (self.pieces[i].y0 as usize, self.pieces[i].height as usize);
            let ix = self.index_of(i)?;
            let s = ix.sections.iter().find(|s| s.tag == tag).copied().ok_or_else(|| {
                Error::Internal(format!("tile result {} has no section {tag}", self.pieces[i].hash))
            })?;
            if s.kind as usize != T::BYTES || plane >= s.planes as usize {
                return Err(Error::Internal(format!(
                    "tile result section {tag}: kind {} planes {}, asked {}-byte plane {plane}",
                    s.kind,
                    s.planes,
                    T::BYTES
                )));
            }
            let ch = s.channels as usize;
            channels = ch;
            let n = out.len() / (w * ch).max(1);
            if n * w * ch != out.len() || y0 + n > self.height {
                return Err(Error::Internal(format!("rows {y0}+{n} of a {w}-wide map")));
            }
            let (a, b) = (y0.max(py0), (y0 + n).min(py0 + ph));
            if a >= b {
                continue;
            }
            let row_bytes = self.pieces[i].width as usize * ch * T::BYTES;
            let plane_bytes = (ph * row_bytes) as u64;
            let start = s.start + plane as u64 * plane_bytes + ((a - py0) * row_bytes) as u64;
            wanted.push((i, a, b - a, start, row_bytes));
        }
        // The ranges side by side (each a network round trip on a remote store), then copied
        // into place in tile order.
        let read = &self.read;
        let pieces = &self.pieces;
        let got: Vec<Result<Vec<u8>>> = std::thread::scope(|scope| {
            let jobs: Vec<_> = wanted
                .iter()
                .map(|&(i, _, rows, start, row_bytes)| {
                    let hash = pieces[i].hash.as_str();
                    scope.spawn(move || checked_read(read, hash, start, rows * row_bytes))
                })
                .collect();
            jobs.into_iter()
                .map(|j| {
                    j.join().unwrap_or_else(|_| Err(Error::Internal("a tile read panicked".into())))
                })
                .collect()
        });
        for (&(i, a, _, _, row_bytes), bytes) in wanted.iter().zip(got) {
            let bytes = bytes?;
            let (px0, pw, ch) = (pieces[i].x0 as usize, pieces[i].width as usize, channels);
            for (r, src) in bytes.chunks_exact(row_bytes).enumerate() {
                let at = ((a - y0 + r) * w + px0) * ch;
                for (o, c) in out[at..at + pw * ch].iter_mut().zip(src.chunks_exact(T::BYTES)) {
                    *o = T::from_le(c);
                }
            }
        }
        if channels == 0 && !out.is_empty() {
            return Err(Error::Internal("no tile pieces".into()));
        }
        Ok(())
    }
}

fn checked_read(read: &ReadRange, hash: &str, start: u64, len: usize) -> Result<Vec<u8>> {
    let out = read(hash, start, len)?;
    if out.len() != len {
        return Err(Error::Internal(format!("tile result blob {hash} is short")));
    }
    Ok(out)
}

/// A source of rows: `(plane, y0, out)` fills `out` with whole rows from `y0` of `plane`.
pub type RowSource<'a, T> = dyn FnMut(usize, usize, &mut [T]) -> Result<()> + 'a;

/// Writes a `width × height` PNG of `color` (8- or 16-bit as `T`) from the rows of plane
/// `plane` of `rows`, band by band: the same bytes as [`super::png::encode8`]/`encode16` of
/// the whole image.
///
/// # Errors
/// The row source's, the encoder's and `out`'s errors.
pub fn write_png<T: PngSample + LeSample, W: Write + Send>(
    out: W,
    width: usize,
    height: usize,
    color: PngColor,
    plane: usize,
    rows: &mut RowSource<'_, T>,
) -> Result<W> {
    let ch = color.channels();
    let w = PngRowWriter::<W, T>::new(out, width, height, color)?;
    let band = band_rows(width * ch * T::BYTES);
    // The encoder on its own thread, a band behind the reads: while one band is filtered and
    // deflated the next is read (from a remote store, mostly waiting on the network). Bands
    // go over a channel of one and come back to be refilled: at most three are alive.
    std::thread::scope(|scope| {
        let (full, bands) = std::sync::mpsc::sync_channel::<Vec<T>>(1);
        let (empty, spare) = std::sync::mpsc::channel::<Vec<T>>();
        let encoder = scope.spawn(move || -> Result<W> {
            let mut w = w;
            for b in bands {
                w.write_rows(&b)?;
                let _ = empty.send(b);
            }
            w.finish()
        });
        let mut read = Ok(());
        for y0 in (0..height).step_by(band) {
            let n = band.min(height - y0);
            let mut b = spare.try_recv().unwrap_or_default();
            b.resize(n * width * ch, T::default());
            read = rows(plane, y0, &mut b);
            if read.is_err() || full.send(b).is_err() {
                break;
            }
        }
        drop(full);
        let written = encoder
            .join()
            .unwrap_or_else(|_| Err(Error::Internal("the PNG encoder panicked".into())));
        read?;
        written
    })
}

/// Refuses the texture options a tiled bake cannot stream: `mips=full`, `bc7`/`bc5`,
/// `supercompression=zstd` (each needs a whole level, or a size known only after compressing
/// it, before the first byte of the file).
///
/// # Errors
/// [`Error::Param`] naming the option.
pub fn check_tiled_texture(opts: &TextureOptions) -> Result<()> {
    const WHY: &str = "is not available for a tiled bake (a map above --tile-above): its \
                       textures are written level 0 only, uncompressed, as a stream";
    if opts.mips {
        return Err(Error::param("mips", format!("`full` {WHY}; use mips=none")));
    }
    if opts.precision.block().is_some() {
        return Err(Error::param(
            "texture_precision",
            format!("`{}` {WHY}; use unorm8, unorm16 or float32", opts.precision.name()),
        ));
    }
    if opts.zstd_level.is_some() {
        return Err(Error::param("supercompression", format!("`zstd` {WHY}; use none")));
    }
    Ok(())
}

/// The pixel format of an uncompressed horizon texture at `precision`.
fn pixel_format(precision: TexturePrecision) -> Result<PixelFormat> {
    match precision {
        TexturePrecision::Unorm8 => Ok(PixelFormat::Rgba8Unorm),
        TexturePrecision::Unorm16 => Ok(PixelFormat::Rgba16Unorm),
        TexturePrecision::Float32 => Ok(PixelFormat::Rgba32Float),
        other => Err(Error::param(
            "texture_precision",
            format!("`{}` is not available for a tiled bake", other.name()),
        )),
    }
}

/// A texture of `images` RGBA images whose levels are only counted by the header writers.
fn shell(format: PixelFormat, width: usize, height: usize, images: usize) -> Texture {
    Texture {
        format,
        width,
        height,
        shape: Shape::Array(images as u32),
        levels: vec![vec![Vec::new(); images]],
    }
}

/// Streams the images `planes` (in order) of `rows`, RGBA samples, little-endian, band by band.
fn stream_images<T: LeSample, W: Write>(
    out: &mut W,
    width: usize,
    height: usize,
    planes: &[usize],
    rows: &mut RowSource<'_, T>,
) -> Result<()> {
    let band = band_rows(width * 4 * T::BYTES);
    let mut buf = vec![T::default(); band * width * 4];
    let mut bytes = Vec::with_capacity(buf.len() * T::BYTES);
    for &p in planes {
        for y0 in (0..height).step_by(band) {
            let n = band.min(height - y0);
            let b = &mut buf[..n * width * 4];
            rows(p, y0, b)?;
            bytes.clear();
            T::extend_le(b, &mut bytes);
            out.write_all(&bytes)?;
        }
    }
    Ok(())
}

fn precision_of<T: LeSample>() -> TexturePrecision {
    match T::BYTES {
        1 => TexturePrecision::Unorm8,
        2 => TexturePrecision::Unorm16,
        _ => TexturePrecision::Float32,
    }
}

/// Writes a KTX2 array texture of the RGBA planes `planes` of `rows` (one layer each, in
/// order), level 0 only, uncompressed at `T`'s precision, stating `conventions` (SPEC §8): the
/// same bytes as [`super::ktx2::write`] of that texture built whole.
///
/// # Errors
/// The row source's and `out`'s errors.
pub fn write_ktx2<T: LeSample, W: Write>(
    mut out: W,
    width: usize,
    height: usize,
    planes: &[usize],
    conventions: &str,
    rows: &mut RowSource<'_, T>,
) -> Result<W> {
    let format = pixel_format(precision_of::<T>())?;
    let t = shell(format, width, height, planes.len());
    let image = format.image_bytes(width, height);
    let len = image * planes.len();
    let (mut head, offsets) =
        ktx2::prefix(&t, &[(len, len)], format.block_bytes(), false, conventions);
    head.resize(offsets[0], 0);
    out.write_all(&head)?;
    stream_images(&mut out, width, height, planes, rows)?;
    Ok(out)
}

/// Writes a DDS array texture of the RGBA planes `planes` of `rows`, level 0 only,
/// uncompressed at `T`'s precision, with `header`: the same bytes as [`super::dds::write`].
///
/// # Errors
/// [`Error::Param`] for a legacy header on more than one plane; the row source's and `out`'s
/// errors.
pub fn write_dds<T: LeSample, W: Write>(
    mut out: W,
    width: usize,
    height: usize,
    planes: &[usize],
    header: DdsHeader,
    rows: &mut RowSource<'_, T>,
) -> Result<W> {
    let format = pixel_format(precision_of::<T>())?;
    let t = shell(format, width, height, planes.len());
    out.write_all(&dds::header_bytes(&t, header)?)?;
    stream_images(&mut out, width, height, planes, rows)?;
    Ok(out)
}

/// Writes a float32 GeoTIFF of `descriptions.len()` bands (band `b` from plane `b` of `rows`,
/// one channel) with `georef`'s tags and GDAL_NODATA `nodata`: the same bytes as
/// [`super::geotiff::encode`] of the whole bands. Bands are read one row of 512² TIFF tiles at
/// a time; the compressed tiles are spooled to a temporary file in `spool` (the system's
/// temporary directory when `None`), since the header names the IFD that follows them.
///
/// # Errors
/// [`Error::Internal`] for a file beyond 4 GiB; the row source's, the spool's and `out`'s
/// errors.
#[allow(clippy::too_many_arguments)]
pub fn write_geotiff<W: Write>(
    mut out: W,
    width: usize,
    height: usize,
    descriptions: &[String],
    georef: Option<&Georef>,
    nodata: f32,
    spool: Option<&std::path::Path>,
    rows: &mut RowSource<'_, f32>,
) -> Result<W> {
    if descriptions.is_empty() || width == 0 || height == 0 {
        return Err(Error::Internal("a GeoTIFF with no band or no texel".into()));
    }
    let mut tmp = match spool {
        Some(dir) => tempfile::tempfile_in(dir)?,
        None => tempfile::tempfile()?,
    };
    let (tx, ty) = (width.div_ceil(TILE), height.div_ceil(TILE));
    let mut offsets = Vec::with_capacity(descriptions.len() * tx * ty);
    let mut counts = Vec::with_capacity(descriptions.len() * tx * ty);
    let mut at = 8u64;
    let mut band = vec![0f32; TILE * width];
    {
        let mut w = std::io::BufWriter::with_capacity(1 << 20, &mut tmp);
        for b in 0..descriptions.len() {
            for row in 0..ty {
                let y0 = row * TILE;
                let n = TILE.min(height - y0);
                let plane = &mut band[..n * width];
                rows(b, y0, plane)?;
                let plane = &*plane;
                let tiles: Vec<Vec<u8>> = (0..tx)
                    .into_par_iter()
                    .map(|t| geotiff::tile_bytes(plane, width, n, t, 0, nodata))
                    .collect();
                for t in tiles {
                    offsets.push(at);
                    counts.push(t.len() as u32);
                    at += t.len() as u64;
                    w.write_all(&t)?;
                }
                if at > geotiff::MAX_CLASSIC {
                    return Err(Error::Internal(
                        "a GeoTIFF beyond 4 GiB needs BigTIFF, not written".into(),
                    ));
                }
            }
        }
        w.flush()?;
    }
    let ifd = (at + at % 2) as usize;
    out.write_all(&geotiff::header(ifd as u64, false))?;
    tmp.seek(SeekFrom::Start(0))?;
    std::io::copy(&mut tmp, &mut out)?;
    if at % 2 == 1 {
        out.write_all(&[0])?;
    }
    let names: Vec<&str> = descriptions.iter().map(String::as_str).collect();
    let place = IfdAt { ifd, offsets: &offsets, counts: &counts, big: false };
    let text = geotiff::nodata_text(nodata);
    out.write_all(&geotiff::ifd_bytes(
        width,
        height,
        &place,
        &names,
        geotiff::FLOAT32,
        georef,
        &text,
    ))?;
    Ok(out)
}

/// File names of the horizon textures, as [`super::horizon_files`] names them.
const KTX2_NAMES: [&str; 2] = ["horizon_0.ktx2", "horizon_1.ktx2"];
const DDS_NAMES: [&str; 2] = ["horizon_0.dds", "horizon_1.dds"];

/// Writes the KTX2 and DDS horizon files `formats` asks for, level 0 streamed from the horizon
/// sections of `rows` at the texture precision (`tag::HORIZON_U8`, `HORIZON_U16` or
/// `HORIZON_F32`): `horizon.ktx2` / `horizon.dds` (one 2-layer array), or with
/// `texture_layout=separate` one file per layer, the same bytes and names as
/// [`super::horizon_files`]. Each file goes into the writer `open(name)` gives and is handed
/// to `keep(name, writer)` once written.
///
/// # Errors
/// [`check_tiled_texture`]'s refusals; the row source's and the writers' errors.
pub fn write_textures<W: Write>(
    rows: &mut TileRows,
    width: usize,
    height: usize,
    formats: &super::Formats,
    open: &mut dyn FnMut(&'static str) -> Result<W>,
    keep: &mut dyn FnMut(&'static str, W) -> Result<()>,
) -> Result<()> {
    if !(formats.ktx2 || formats.dds) {
        return Ok(());
    }
    let opts = &formats.texture;
    check_tiled_texture(opts)?;
    let separate = opts.layout == super::texture::TextureLayout::Separate;
    let sets: Vec<(&[usize], &'static str, &'static str)> = if separate {
        vec![(&[0], KTX2_NAMES[0], DDS_NAMES[0]), (&[1], KTX2_NAMES[1], DDS_NAMES[1])]
    } else {
        vec![(&[0, 1], "horizon.ktx2", "horizon.dds")]
    };
    fn one<T: LeSample, W: Write>(
        rows: &mut TileRows,
        tag: u32,
        (width, height): (usize, usize),
        (planes, name, ktx, meta): (&[usize], &'static str, bool, &str),
        header: DdsHeader,
        open: &mut dyn FnMut(&'static str) -> Result<W>,
        keep: &mut dyn FnMut(&'static str, W) -> Result<()>,
    ) -> Result<()> {
        let mut src = |p: usize, y: usize, out: &mut [T]| rows.read(tag, p, y, out);
        let out = open(name)?;
        let out = if ktx {
            write_ktx2(out, width, height, planes, meta, &mut src)?
        } else {
            write_dds(out, width, height, planes, header, &mut src)?
        };
        keep(name, out)
    }
    let size = (width, height);
    // KTX2 files first, then DDS, as horizon_files orders them.
    for (wanted, ktx) in [(formats.ktx2, true), (formats.dds, false)] {
        if !wanted {
            continue;
        }
        for &(planes, ktx_name, dds_name) in &sets {
            let name = if ktx { ktx_name } else { dds_name };
            let meta = formats.conventions.ktx2_json(opts, separate.then_some(planes[0]));
            let job = (planes, name, ktx, meta.as_str());
            let header = opts.dds_header;
            match opts.precision {
                TexturePrecision::Unorm8 => {
                    one::<u8, W>(rows, tag::HORIZON_U8, size, job, header, open, keep)?
                }
                TexturePrecision::Unorm16 => {
                    one::<u16, W>(rows, tag::HORIZON_U16, size, job, header, open, keep)?
                }
                _ => one::<f32, W>(rows, tag::HORIZON_F32, size, job, header, open, keep)?,
            }
        }
    }
    Ok(())
}
