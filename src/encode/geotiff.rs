//! GeoTIFF writer for the terrain products (SPEC §3.7): float32 samples, one band per plane
//! (PlanarConfiguration 2), tiled 512×512, DEFLATE (Adobe, code 8) with the floating-point
//! predictor (3), and the input's georeferencing tags copied verbatim from
//! [`crate::heightmap::georef::Georef`] with a GDAL_NODATA tag, so GDAL and QGIS place the
//! outputs exactly where the DEM was.
//!
//! Written by hand (classic little-endian TIFF, a header, the tiles, one IFD): the `tiff` crate
//! writes neither tiles nor predictor 3. The layout follows libtiff: predictor 3 works per tile
//! row, first spreading each sample's bytes into planes, most significant byte first, then
//! differencing the bytes left to right (`fpDiff` in libtiff's tif_predict.c). Proven by GDAL
//! itself (rasterio) in tests/terrain.

use crate::error::{Error, Result};
use crate::heightmap::georef::{self, Georef};
use rayon::prelude::*;
use std::io::Write;

/// Tile edge in texels.
pub const TILE: usize = 512;

/// DEFLATE level of the float32 tiles. Float samples barely compress (their low mantissa bits
/// are noise, predictor or not), so a higher level buys little and costs most of a terrain
/// bake: a 1024² DEM's 32-band `angles.tif` (134 MB raw) came out at 114.3 MB in a bake of
/// 8.3 s at level 4 (half of it in the compressor) and at 118.5 MB in 1.8 s at level 1.
const FLOAT_LEVEL: u32 = 1;

/// One band: its plane (`width × height`, row-major) and its description (GDAL band
/// description, e.g. "azimuth 45").
pub struct Band<'a> {
    pub plane: &'a [f32],
    pub description: String,
}

const SHORT: u16 = 3;
const LONG: u16 = 4;
const ASCII: u16 = 2;
const DOUBLE: u16 = 12;
const LONG8: u16 = 16;

struct Entry {
    tag: u16,
    kind: u16,
    count: u32,
    data: Vec<u8>,
}

fn shorts(tag: u16, v: &[u16]) -> Entry {
    Entry {
        tag,
        kind: SHORT,
        count: v.len() as u32,
        data: v.iter().flat_map(|x| x.to_le_bytes()).collect(),
    }
}

fn longs(tag: u16, v: &[u32]) -> Entry {
    Entry {
        tag,
        kind: LONG,
        count: v.len() as u32,
        data: v.iter().flat_map(|x| x.to_le_bytes()).collect(),
    }
}

fn long8s(tag: u16, v: &[u64]) -> Entry {
    Entry {
        tag,
        kind: LONG8,
        count: v.len() as u32,
        data: v.iter().flat_map(|x| x.to_le_bytes()).collect(),
    }
}

fn doubles(tag: u16, v: &[f64]) -> Entry {
    Entry {
        tag,
        kind: DOUBLE,
        count: v.len() as u32,
        data: v.iter().flat_map(|x| x.to_le_bytes()).collect(),
    }
}

fn ascii(tag: u16, s: &str) -> Entry {
    let mut data: Vec<u8> = s.trim_end_matches('\0').bytes().collect();
    data.push(0);
    Entry { tag, kind: ASCII, count: data.len() as u32, data }
}

/// GDAL_NODATA text for `v` ("nan" for NaN, as GDAL writes it).
pub fn nodata_text(v: f32) -> String {
    if v.is_nan() {
        "nan".into()
    } else {
        format!("{}", v as f64)
    }
}

/// Predictor 3 on one tile row of f32 samples, into `out` (4 × row length bytes).
fn fp_predict(row: &[f32], out: &mut [u8]) {
    let n = row.len();
    for (i, v) in row.iter().enumerate() {
        let b = v.to_le_bytes();
        for (byte, &x) in b.iter().enumerate() {
            out[(3 - byte) * n + i] = x;
        }
    }
    for j in (1..out.len()).rev() {
        out[j] = out[j].wrapping_sub(out[j - 1]);
    }
}

/// One compressed tile of `plane`: tile (tx, ty), padded with `fill` past the map's edge.
pub(crate) fn tile_bytes(
    plane: &[f32],
    width: usize,
    height: usize,
    tx: usize,
    ty: usize,
    fill: f32,
) -> Vec<u8> {
    tile_of(&|y| &plane[y * width..(y + 1) * width], width, height, tx, ty, fill)
}

/// [`tile_bytes`] of the plane whose row y is `row(y)`.
fn tile_of<'p>(
    row_of: &(dyn Fn(usize) -> &'p [f32] + 'p),
    width: usize,
    height: usize,
    tx: usize,
    ty: usize,
    fill: f32,
) -> Vec<u8> {
    let mut row = vec![fill; TILE];
    let mut bytes = vec![0u8; TILE * 4];
    let mut z = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::new(FLOAT_LEVEL));
    for r in 0..TILE {
        let y = ty * TILE + r;
        row.fill(fill);
        if y < height {
            let x0 = tx * TILE;
            let n = TILE.min(width - x0);
            row[..n].copy_from_slice(&row_of(y)[x0..x0 + n]);
        }
        fp_predict(&row, &mut bytes);
        // Writing into a Vec cannot fail.
        let _ = z.write_all(&bytes);
    }
    z.finish().unwrap_or_default()
}

/// XML of GDAL's GDAL_METADATA tag (42112) carrying the band descriptions.
fn gdal_metadata(descriptions: &[&str]) -> String {
    let esc = |s: &str| s.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;");
    let mut x = String::from("<GDALMetadata>\n");
    for (i, d) in descriptions.iter().enumerate() {
        x.push_str(&format!(
            "  <Item name=\"DESCRIPTION\" sample=\"{i}\" role=\"description\">{}</Item>\n",
            esc(d)
        ));
    }
    x.push_str("</GDALMetadata>");
    x
}

/// Encodes `bands` (each `width × height`) as a tiled float32 GeoTIFF with `georef`'s tags
/// and GDAL_NODATA = `nodata`.
///
/// # Errors
/// [`Error::Internal`] for a band of the wrong size or a file beyond 4 GiB (classic TIFF).
pub fn encode(
    width: usize,
    height: usize,
    bands: &[Band<'_>],
    georef: Option<&Georef>,
    nodata: f32,
) -> Result<Vec<u8>> {
    if bands.is_empty() || bands.iter().any(|b| b.plane.len() != width * height) {
        return Err(Error::Internal("GeoTIFF bands do not match the map size".into()));
    }
    let (tx, ty) = (width.div_ceil(TILE), height.div_ceil(TILE));
    let per_band = tx * ty;
    let tiles: Vec<Vec<u8>> = (0..bands.len() * per_band)
        .into_par_iter()
        .map(|i| {
            let (b, t) = (i / per_band, i % per_band);
            tile_bytes(bands[b].plane, width, height, t % tx, t / tx, nodata)
        })
        .collect();
    let descriptions: Vec<&str> = bands.iter().map(|b| b.description.as_str()).collect();
    assemble(width, height, tiles, &descriptions, FLOAT32, georef, &nodata_text(nodata))
}

/// Encodes one uint8 band (`shadow.tif`: 1 lit, 0 shadowed) as a tiled GeoTIFF, DEFLATE with
/// horizontal differencing (predictor 2), with `georef`'s tags and GDAL_NODATA = `nodata`.
///
/// # Errors
/// As [`encode`].
pub fn encode_u8(
    width: usize,
    height: usize,
    plane: &[u8],
    description: &str,
    georef: Option<&Georef>,
    nodata: u8,
) -> Result<Vec<u8>> {
    if plane.len() != width * height || plane.is_empty() {
        return Err(Error::Internal("GeoTIFF band does not match the map size".into()));
    }
    let (tx, ty) = (width.div_ceil(TILE), height.div_ceil(TILE));
    let tiles: Vec<Vec<u8>> = (0..tx * ty)
        .into_par_iter()
        .map(|t| {
            let (x0, y0) = ((t % tx) * TILE, (t / tx) * TILE);
            let mut z = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::new(4));
            let mut row = vec![nodata; TILE];
            for r in 0..TILE {
                row.fill(nodata);
                if y0 + r < height {
                    let n = TILE.min(width - x0);
                    let at = (y0 + r) * width + x0;
                    row[..n].copy_from_slice(&plane[at..at + n]);
                }
                for j in (1..TILE).rev() {
                    row[j] = row[j].wrapping_sub(row[j - 1]);
                }
                let _ = z.write_all(&row);
            }
            z.finish().unwrap_or_default()
        })
        .collect();
    let layout = Layout { bits: 8, sample_format: 1, predictor: 2 };
    assemble(width, height, tiles, &[description], layout, georef, &nodata.to_string())
}

/// Sample layout of a file: bits per sample, SampleFormat (1 uint, 3 float), Predictor.
#[derive(Clone, Copy)]
pub(crate) struct Layout {
    bits: u16,
    sample_format: u16,
    predictor: u16,
}

/// The layout of the float32 files of [`encode`].
pub(crate) const FLOAT32: Layout = Layout { bits: 32, sample_format: 3, predictor: 3 };

/// Largest file a classic TIFF holds here (offsets are u32; 1 MiB kept for the IFD).
pub(crate) const MAX_CLASSIC: u64 = u32::MAX as u64 - (1 << 20);

/// The file around compressed `tiles` (band-major, row-major within a band).
fn assemble(
    width: usize,
    height: usize,
    tiles: Vec<Vec<u8>>,
    descriptions: &[&str],
    layout: Layout,
    georef: Option<&Georef>,
    nodata: &str,
) -> Result<Vec<u8>> {
    let mut out: Vec<u8> = Vec::with_capacity(8 + tiles.iter().map(Vec::len).sum::<usize>());
    out.extend_from_slice(b"II*\0");
    out.extend_from_slice(&[0; 4]);
    let mut offsets = Vec::with_capacity(tiles.len());
    let mut counts = Vec::with_capacity(tiles.len());
    for t in &tiles {
        offsets.push(out.len() as u64);
        counts.push(t.len() as u32);
        out.extend_from_slice(t);
    }
    drop(tiles);
    if out.len() as u64 > MAX_CLASSIC {
        return Err(Error::Internal("a GeoTIFF beyond 4 GiB needs BigTIFF, not written".into()));
    }
    // The IFD, word-aligned.
    if out.len() % 2 == 1 {
        out.push(0);
    }
    let ifd = out.len();
    out[4..8].copy_from_slice(&(ifd as u32).to_le_bytes());
    let at = IfdAt { ifd, offsets: &offsets, counts: &counts, big: false };
    out.extend(ifd_bytes(width, height, &at, descriptions, layout, georef, nodata));
    Ok(out)
}

/// Where the tiles of a file went: the IFD's offset, each tile's offset and byte count, and
/// whether the file is a BigTIFF (64-bit offsets: [`header`]).
pub(crate) struct IfdAt<'a> {
    pub ifd: usize,
    pub offsets: &'a [u64],
    pub counts: &'a [u32],
    pub big: bool,
}

/// The header of a file whose IFD is at `ifd`: classic TIFF (8 bytes), or BigTIFF (16 bytes:
/// version 43, 8-byte offsets), which GDAL and libtiff read, for a file past [`MAX_CLASSIC`].
pub(crate) fn header(ifd: u64, big: bool) -> Vec<u8> {
    let mut head = Vec::with_capacity(16);
    if big {
        head.extend_from_slice(b"II+\0");
        head.extend_from_slice(&8u16.to_le_bytes());
        head.extend_from_slice(&0u16.to_le_bytes());
        head.extend_from_slice(&ifd.to_le_bytes());
    } else {
        head.extend_from_slice(b"II*\0");
        head.extend_from_slice(&(ifd as u32).to_le_bytes());
    }
    head
}

/// Bytes of [`header`]: where the first tile starts.
pub(crate) fn header_len(big: bool) -> u64 {
    if big {
        16
    } else {
        8
    }
}

/// The IFD at `at.ifd` (word-aligned) and the values that do not fit in its entries, for tiles
/// at `at.offsets` (band-major, row-major within a band): the end of the file.
pub(crate) fn ifd_bytes(
    width: usize,
    height: usize,
    at: &IfdAt<'_>,
    descriptions: &[&str],
    layout: Layout,
    georef: Option<&Georef>,
    nodata: &str,
) -> Vec<u8> {
    let (offsets, counts) = (at.offsets, at.counts);
    let spp = descriptions.len() as u16;
    let mut e = vec![
        longs(256, &[width as u32]),
        longs(257, &[height as u32]),
        shorts(258, &vec![layout.bits; spp as usize]),
        shorts(259, &[8]),
        shorts(262, &[1]),
        shorts(277, &[spp]),
        shorts(284, &[if spp > 1 { 2 } else { 1 }]),
        shorts(317, &[layout.predictor]),
        longs(322, &[TILE as u32]),
        longs(323, &[TILE as u32]),
        if at.big {
            long8s(324, offsets)
        } else {
            longs(324, &offsets.iter().map(|&o| o as u32).collect::<Vec<_>>())
        },
        longs(325, counts),
        shorts(339, &vec![layout.sample_format; spp as usize]),
        ascii(42112, &gdal_metadata(descriptions)),
        ascii(georef::TAG_GDAL_NODATA, nodata),
    ];
    if spp > 1 {
        e.push(shorts(338, &vec![0; spp as usize - 1]));
    }
    if let Some(g) = georef {
        if let Some(v) = &g.pixel_scale {
            e.push(doubles(georef::TAG_MODEL_PIXEL_SCALE, v));
        }
        if let Some(v) = &g.tiepoints {
            e.push(doubles(georef::TAG_MODEL_TIEPOINT, v));
        }
        if let Some(v) = &g.transformation {
            e.push(doubles(georef::TAG_MODEL_TRANSFORMATION, v));
        }
        if let Some(v) = &g.geo_keys {
            e.push(shorts(georef::TAG_GEO_KEY_DIRECTORY, v));
        }
        if let Some(v) = &g.geo_doubles {
            e.push(doubles(georef::TAG_GEO_DOUBLE_PARAMS, v));
        }
        if let Some(v) = &g.geo_ascii {
            e.push(ascii(georef::TAG_GEO_ASCII_PARAMS, v));
        }
    }
    e.sort_by_key(|x| x.tag);
    let ifd = at.ifd;
    // Classic: a 2-byte entry count, 12-byte entries (4-byte count and value), a 4-byte next
    // offset; BigTIFF: 8, 20 (8 and 8) and 8.
    let (head, entry, word) = if at.big { (8, 20, 8) } else { (2, 12, 4) };
    let mut out = Vec::with_capacity(head + entry * e.len() + word);
    let mut extra = ifd + head + entry * e.len() + word;
    let mut tail: Vec<u8> = Vec::new();
    let word_of =
        |v: u64| if at.big { v.to_le_bytes().to_vec() } else { (v as u32).to_le_bytes().to_vec() };
    if at.big {
        out.extend_from_slice(&(e.len() as u64).to_le_bytes());
    } else {
        out.extend_from_slice(&(e.len() as u16).to_le_bytes());
    }
    for x in &e {
        out.extend_from_slice(&x.tag.to_le_bytes());
        out.extend_from_slice(&x.kind.to_le_bytes());
        out.extend(word_of(u64::from(x.count)));
        if x.data.len() <= word {
            let mut v = vec![0u8; word];
            v[..x.data.len()].copy_from_slice(&x.data);
            out.extend_from_slice(&v);
        } else {
            out.extend(word_of(extra as u64));
            tail.extend_from_slice(&x.data);
            extra += x.data.len();
            if x.data.len() % 2 == 1 {
                tail.push(0);
                extra += 1;
            }
        }
    }
    out.extend(word_of(0));
    out.extend_from_slice(&tail);
    out
}

/// A float32 GeoTIFF written band by band in any order (`sweep`'s planes give the bins one
/// after another), each band's tiles compressed as it comes and spooled to a temporary file, so
/// no more than one band is ever in memory; [`Spool::finish`] writes header, tiles and IFD to
/// any writer (the header names the IFD, which follows the tiles). Classic TIFF up to
/// [`MAX_CLASSIC`], BigTIFF beyond; bands put in their order give the bytes of [`encode`].
pub struct Spool {
    tmp: std::io::BufWriter<std::fs::File>,
    width: usize,
    height: usize,
    /// Per tile (band-major), its offset from the first tile's (`u64::MAX`: not put) and its
    /// compressed bytes.
    offsets: Vec<u64>,
    counts: Vec<u32>,
    at: u64,
    nodata: f32,
    /// Made BigTIFF whatever the size (tests).
    force_big: bool,
}

impl Spool {
    /// A spool for `bands` bands of `width` × `height`, its temporary file in `dir` (unlinked:
    /// gone with the spool, or with the process).
    ///
    /// # Errors
    /// [`Error::Io`] when no temporary file can be made in `dir`.
    pub fn new(
        dir: &std::path::Path,
        width: usize,
        height: usize,
        bands: usize,
        nodata: f32,
    ) -> Result<Spool> {
        if bands == 0 || width == 0 || height == 0 {
            return Err(Error::Internal("a GeoTIFF with no band or no texel".into()));
        }
        std::fs::create_dir_all(dir)?;
        let file = tempfile::tempfile_in(dir).map_err(|e| {
            Error::Io(std::io::Error::new(
                e.kind(),
                format!("cannot create a temporary file in {}: {e}", dir.display()),
            ))
        })?;
        let tiles = bands * width.div_ceil(TILE) * height.div_ceil(TILE);
        Ok(Spool {
            tmp: std::io::BufWriter::with_capacity(1 << 20, file),
            width,
            height,
            offsets: vec![u64::MAX; tiles],
            counts: vec![0; tiles],
            at: 0,
            nodata,
            force_big: false,
        })
    }

    /// Makes the file a BigTIFF whatever its size (so tests can read one back small).
    pub fn force_big(mut self) -> Spool {
        self.force_big = true;
        self
    }

    /// Band `band`, its row y being `row(y)` (`width` values), compressed on the pool and
    /// appended.
    ///
    /// # Errors
    /// [`Error::Internal`] for a band out of range or put twice; [`Error::Io`].
    pub fn put<'p>(
        &mut self,
        band: usize,
        row: &(dyn Fn(usize) -> &'p [f32] + Sync + 'p),
    ) -> Result<()> {
        let (w, h) = (self.width, self.height);
        let (tx, ty) = (w.div_ceil(TILE), h.div_ceil(TILE));
        let first = band * tx * ty;
        if first >= self.offsets.len() || self.offsets[first] != u64::MAX {
            return Err(Error::Internal(format!("GeoTIFF band {band} out of range or put twice")));
        }
        let nodata = self.nodata;
        for r in 0..ty {
            let tiles: Vec<Vec<u8>> =
                (0..tx).into_par_iter().map(|t| tile_of(row, w, h, t, r, nodata)).collect();
            for (t, bytes) in tiles.into_iter().enumerate() {
                self.offsets[first + r * tx + t] = self.at;
                self.counts[first + r * tx + t] = bytes.len() as u32;
                self.at += bytes.len() as u64;
                self.tmp.write_all(&bytes)?;
            }
        }
        Ok(())
    }

    /// Writes the file into `out`: header, the spooled tiles, the IFD with `descriptions` (one
    /// per band), `georef`'s tags and GDAL_NODATA.
    ///
    /// # Errors
    /// [`Error::Internal`] when a band was never put; [`Error::Io`].
    pub fn finish<W: Write>(
        self,
        mut out: W,
        descriptions: &[&str],
        georef: Option<&Georef>,
    ) -> Result<W> {
        use std::io::{Seek, SeekFrom};
        let tiles_per = self.offsets.len() / descriptions.len().max(1);
        if descriptions.len() * tiles_per != self.offsets.len() || self.offsets.contains(&u64::MAX)
        {
            return Err(Error::Internal("a GeoTIFF band was never written".into()));
        }
        let text = nodata_text(self.nodata);
        // Classic while the whole file, IFD and its values included, has 32-bit offsets: the
        // IFD's length does not depend on where it or the tiles are (720 bands of a 65 536²
        // map carry 94 MB of tile offsets and counts), so it is measured with the tiles' own.
        let at = IfdAt { ifd: 0, offsets: &self.offsets, counts: &self.counts, big: false };
        let ifd_len = ifd_bytes(self.width, self.height, &at, descriptions, FLOAT32, georef, &text)
            .len() as u64;
        let big = self.force_big || 8 + self.at + 1 + ifd_len > u64::from(u32::MAX);
        let start = header_len(big);
        let end = start + self.at;
        let ifd = end + end % 2;
        let mut tmp = self.tmp.into_inner().map_err(|e| Error::Io(e.into_error()))?;
        out.write_all(&header(ifd, big))?;
        tmp.seek(SeekFrom::Start(0))?;
        std::io::copy(&mut tmp, &mut out)?;
        if end % 2 == 1 {
            out.write_all(&[0])?;
        }
        let offsets: Vec<u64> = self.offsets.iter().map(|o| o + start).collect();
        let at = IfdAt { ifd: ifd as usize, offsets: &offsets, counts: &self.counts, big };
        out.write_all(&ifd_bytes(
            self.width,
            self.height,
            &at,
            descriptions,
            FLOAT32,
            georef,
            &text,
        ))?;
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn predictor_spreads_bytes_then_differences() {
        let row = [1.0f32, 1.0];
        let mut out = [0u8; 8];
        fp_predict(&row, &mut out);
        // 1.0 = 0x3F800000: planes [3F 3F][80 80][00 00][00 00], then byte differences.
        assert_eq!(out, [0x3F, 0, 0x80u8.wrapping_sub(0x3F), 0, 0x80u8.wrapping_neg(), 0, 0, 0]);
    }

    /// A spool given its bands in order writes the bytes of `encode`; given them out of order,
    /// the same tiles where the IFD says; BigTIFF (forced, so small) reads back with the `tiff`
    /// crate pixel for pixel; a band put twice or never is refused.
    #[test]
    fn a_spool_writes_what_encode_does_in_any_order_and_as_bigtiff() {
        let (w, h) = (700, 530);
        let planes: Vec<Vec<f32>> = (0..3)
            .map(|b| (0..w * h).map(|i| ((i * (b + 3)) % 977) as f32 * 0.37 - b as f32).collect())
            .collect();
        let names = ["a", "b", "c"];
        let bands: Vec<Band<'_>> = planes
            .iter()
            .zip(names)
            .map(|(p, n)| Band { plane: p, description: n.into() })
            .collect();
        let want = encode(w, h, &bands, None, -9999.0).unwrap();
        let dir = tempfile::tempdir().unwrap();
        let spooled = |order: &[usize], big: bool| {
            let mut s = Spool::new(dir.path(), w, h, 3, -9999.0).unwrap();
            if big {
                s = s.force_big();
            }
            for &b in order {
                let p = &planes[b];
                s.put(b, &|y| &p[y * w..(y + 1) * w]).unwrap();
            }
            s.finish(Vec::new(), &names, None).unwrap()
        };
        assert_eq!(spooled(&[0, 1, 2], false), want);
        // Out of order: the same tiles at other offsets, so the same length.
        let shuffled = spooled(&[2, 0, 1], false);
        assert_ne!(shuffled, want);
        assert_eq!(shuffled.len(), want.len());
        // A single band as BigTIFF, read back by the `tiff` crate.
        let one = |big: bool| {
            let mut s = Spool::new(dir.path(), w, h, 1, f32::NAN).unwrap();
            if big {
                s = s.force_big();
            }
            let p = &planes[1];
            s.put(0, &|y| &p[y * w..(y + 1) * w]).unwrap();
            s.finish(Vec::new(), &["b"], None).unwrap()
        };
        let big = one(true);
        assert_eq!(&big[..4], b"II+\0");
        assert_eq!(&one(false)[..4], b"II*\0");
        let mut dec = tiff::decoder::Decoder::new(std::io::Cursor::new(&big)).unwrap();
        assert_eq!(dec.dimensions().unwrap(), (w as u32, h as u32));
        let tiff::decoder::DecodingResult::F32(got) = dec.read_image().unwrap() else {
            panic!("not float32");
        };
        assert_eq!(got, planes[1]);
        let mut s = Spool::new(dir.path(), w, h, 2, 0.0).unwrap();
        let p = &planes[0];
        s.put(1, &|y| &p[y * w..(y + 1) * w]).unwrap();
        assert!(s.put(1, &|y| &p[y * w..(y + 1) * w]).is_err(), "a band put twice");
        assert!(s.put(2, &|y| &p[y * w..(y + 1) * w]).is_err(), "a band out of range");
        assert!(s.finish(Vec::new(), &["x", "y"], None).is_err(), "band 0 was never put");
    }

    #[test]
    fn reads_back_with_the_tiff_crate() {
        let (w, h) = (600, 70);
        let a: Vec<f32> = (0..w * h).map(|i| i as f32 * 0.25).collect();
        let b: Vec<f32> = (0..w * h).map(|i| -(i as f32)).collect();
        let bands = [
            Band { plane: &a, description: "a".into() },
            Band { plane: &b, description: "b".into() },
        ];
        let bytes = encode(w, h, &bands, None, f32::NAN).unwrap();
        let mut dec = tiff::decoder::Decoder::new(std::io::Cursor::new(&bytes)).unwrap();
        assert_eq!(dec.dimensions().unwrap(), (w as u32, h as u32));
        let nd = dec.get_tag_ascii_string(tiff::tags::Tag::Unknown(42113)).unwrap();
        assert_eq!(nd.trim_end_matches('\0'), "nan");
        let pred = dec.get_tag_u32(tiff::tags::Tag::Predictor).unwrap();
        assert_eq!(pred, 3);
    }
}
