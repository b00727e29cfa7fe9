//! Streamed decode of a large input into tile-sized height blobs (SPEC §7.1, issue 23).
//!
//! A map larger than `--tile-above` is never decoded whole: a PNG is read row by row and a TIFF
//! strip by strip (or one row of TIFF tiles at a time), each row normalised and channel-picked
//! exactly as [`super::decode_with`] does (the same `samples`/`tiff_values` code), and the rows
//! are cut into the windows a tile plan asks for (tile + halo, wrapped modulo the map size).
//! In the same pass it computes what the bake needs from the whole map: the hole count, the
//! height range (radius=auto), the hole fill value and the first offending texel (so a refusal
//! says what the whole decode says).
//!
//! Memory: a band of map rows as tall as the tallest window (rows are dropped as soon as no
//! window still to be emitted needs them), the decoder's own row or strip buffer, and the blob
//! being built. For `edge=wrap`, a window whose halo crosses the bottom edge is completed from
//! the first rows of the map, kept from the start of the pass (halo rows × width); a window
//! whose halo crosses the top edge is completed by a **second pass** that decodes the first
//! rows again, its bottom rows kept from the end of the first pass. A 65 536-wide map cut in
//! 2048 tiles with a halo of 17 holds 2082 × 65 536 × 4 bytes = 546 MB of rows (+ a byte per
//! texel for the hole mask when `nodata` is in effect); 16 384 wide, 136 MB.
//!
//! The hole fill depends on the whole map's range, known only at the end of the pass, so a
//! tile blob carries the raw values and a hole mask; [`TileHeights::into_map`] fills the holes
//! with [`MapStats::fill`], which gives exactly the crop of the whole-map [`HeightMap`].

use super::{
    check_dimensions, contained, nonfinite_error, png_dimensions, range_error, samples, sniff,
    tiff_error, tiff_meta, tiff_values, Format, HeightMap, InputInfo, Limits, Terrain, TiffMeta,
    MAX_ABS_HEIGHT,
};
use crate::error::{Error, LimitError, Result};
use crate::heightmap::georef::Georef;
use crate::params::{Channel, NoData};
use serde::{Deserialize, Serialize};
use std::collections::VecDeque;
use std::io::{BufReader, Read, Seek, SeekFrom};

/// A window of the map in texels: columns `x0..x0 + width`, rows `y0..y0 + height`, each taken
/// modulo the map size (`rem_euclid`), so a wrap halo is `x0 < 0` or `x0 + width > W` (and the
/// same for rows). For `edge=none`, windows are clipped to the map and nothing wraps.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Window {
    pub x0: i64,
    pub y0: i64,
    pub width: u32,
    pub height: u32,
}

/// What the whole map gives the bake, computed in the pass that cuts the tiles.
#[derive(Debug, Clone, PartialEq)]
pub struct MapStats {
    /// Width, height, format, colour, bit depth, content hash (the input blob's).
    pub info: InputInfo,
    /// The georeferencing as the whole decode reads it.
    pub georef: Option<Georef>,
    /// The nodata value in effect (NaN for `nan`).
    pub nodata: Option<f64>,
    /// Hole texels in the whole map.
    pub holes: u64,
    /// Range of the whole-map [`HeightMap::values`] (unscaled, holes filled: with holes, `min`
    /// is the fill value).
    pub min: f32,
    pub max: f32,
    /// The value holes are filled with, when there is any.
    pub fill: Option<f32>,
}

impl MapStats {
    /// (min, max) of the scaled heights `(v as f64 · height_scale) as f32`, what
    /// `radius=auto` sees of the whole map.
    pub fn scaled_range(&self, height_scale: f64) -> (f32, f32) {
        let a = (self.min as f64 * height_scale) as f32;
        let b = (self.max as f64 * height_scale) as f32;
        (a.min(b), a.max(b))
    }

    /// The stats as JSON, to keep beside a tiled bake (NaN nodata as the string `"nan"`).
    pub fn to_json(&self) -> serde_json::Value {
        let g = self.georef.as_ref().map(|g| GeorefWire {
            pixel_scale: g.pixel_scale.clone(),
            tiepoints: g.tiepoints.clone(),
            transformation: g.transformation.clone(),
            geo_keys: g.geo_keys.clone(),
            geo_doubles: g.geo_doubles.clone(),
            geo_ascii: g.geo_ascii.clone(),
            gdal_nodata: g.gdal_nodata.clone(),
            gdal_metadata: g.gdal_metadata.clone(),
        });
        serde_json::json!({
            "info": self.info,
            "georef": g,
            "nodata": self.nodata.map(|v| if v.is_nan() { serde_json::json!("nan") } else { serde_json::json!(v) }),
            "holes": self.holes,
            "min": self.min,
            "max": self.max,
            "fill": self.fill,
        })
    }

    /// Reads [`MapStats::to_json`]'s output back.
    ///
    /// # Errors
    /// [`Error::Internal`] for JSON that is not such stats.
    pub fn from_json(v: &serde_json::Value) -> Result<Self> {
        let bad = |what: &str| Error::Internal(format!("tile map stats: bad `{what}`"));
        let info: InputInfo = serde_json::from_value(v["info"].clone()).map_err(|_| bad("info"))?;
        let georef = match &v["georef"] {
            serde_json::Value::Null => None,
            g => {
                let w: GeorefWire = serde_json::from_value(g.clone()).map_err(|_| bad("georef"))?;
                Some(Georef {
                    pixel_scale: w.pixel_scale,
                    tiepoints: w.tiepoints,
                    transformation: w.transformation,
                    geo_keys: w.geo_keys,
                    geo_doubles: w.geo_doubles,
                    geo_ascii: w.geo_ascii,
                    gdal_nodata: w.gdal_nodata,
                    gdal_metadata: w.gdal_metadata,
                })
            }
        };
        let nodata = match &v["nodata"] {
            serde_json::Value::Null => None,
            serde_json::Value::String(s) if s == "nan" => Some(f64::NAN),
            n => Some(n.as_f64().ok_or_else(|| bad("nodata"))?),
        };
        let f = |k: &str| v[k].as_f64().map(|x| x as f32).ok_or_else(|| bad(k));
        Ok(MapStats {
            info,
            georef,
            nodata,
            holes: v["holes"].as_u64().ok_or_else(|| bad("holes"))?,
            min: f("min")?,
            max: f("max")?,
            fill: if v["fill"].is_null() { None } else { Some(f("fill")?) },
        })
    }
}

/// [`Georef`] as JSON (the type itself carries no serde: it belongs to the decoder).
#[derive(Serialize, Deserialize)]
struct GeorefWire {
    pixel_scale: Option<Vec<f64>>,
    tiepoints: Option<Vec<f64>>,
    transformation: Option<Vec<f64>>,
    geo_keys: Option<Vec<u16>>,
    geo_doubles: Option<Vec<f64>>,
    geo_ascii: Option<String>,
    gdal_nodata: Option<String>,
    #[serde(default)]
    gdal_metadata: Option<String>,
}

/// The heights of one window, as a tile blob carries them (see [`TileHeights::encode`]).
#[derive(Debug, Clone, PartialEq)]
pub struct TileHeights {
    pub window: Window,
    /// Row-major, unscaled, as decoded (hole texels hold their stored value, not the fill).
    pub values: Vec<f32>,
    /// `true` for a hole texel; `None` when the window holds none.
    pub holes: Option<Vec<bool>>,
}

/// Magic of a tile height blob.
pub const TILE_MAGIC: &[u8; 4] = b"HBH1";
/// Bytes before the values of a tile height blob.
pub const TILE_HEADER: usize = 32;
/// Flag: a hole mask follows the values.
const HAS_HOLES: u32 = 1;
/// Flag: the values are u16 samples k of a 16-bit image, each value `(k / 65535) as f32` in
/// f64 (the decoder's own normalisation).
const NORM16: u32 = 2;
/// Flag: the values are u16 integers k, each value `k as f32` (an unsigned integer DEM).
const INT16: u32 = 4;
/// Flag: the values are i16 integers k (stored as their two's-complement bits), each value
/// `k as f32` (a signed integer DEM: land below sea level, or a nodata of −32768).
const SINT16: u32 = 8;

/// A 2-byte form of a window's values: its flag, the value a stored u16 stands for, and the
/// u16 a value would be stored as if it is one of those (checked against `value`).
struct Narrow {
    flag: u32,
    value: fn(u16) -> f32,
    guess: fn(f32) -> u16,
}

/// The 2-byte forms, tried in this order; at most one flag is set in a blob.
const NARROW: [Narrow; 3] = [
    Narrow {
        flag: NORM16,
        value: |k| (f64::from(k) / 65535.0) as f32,
        guess: |v| (f64::from(v) * 65535.0).round() as u16,
    },
    Narrow { flag: INT16, value: f32::from, guess: |v| v as u16 },
    Narrow { flag: SINT16, value: |k| f32::from(k as i16), guess: |v| v as i16 as u16 },
];

impl Narrow {
    /// The u16 that stands for `v` exactly (bit for bit: not −0 for 0, not NaN, no fraction).
    fn of(&self, v: f32) -> Option<u16> {
        let k = (self.guess)(v);
        ((self.value)(k).to_bits() == v.to_bits()).then_some(k)
    }
}

impl TileHeights {
    /// The blob: `HBH1`, u32 width, u32 height, i64 x0, i64 y0, u32 flags, the values
    /// (row-major), then the hole bits (LSB first, row-major) if flag 1 says so; all
    /// little-endian. The values take 2 bytes each when every one of them is a 16-bit sample
    /// as the decoder normalises it (flag 2: a 16-bit PNG or TIFF, the common case of a huge
    /// map) or a u16 or i16 integer (flags 4 and 8: an integer DEM), else 4 (f32): half the
    /// bytes through the blob store for the same values, bit for bit (each is checked on the
    /// way in, see [`Narrow::of`]).
    pub fn encode(&self) -> Vec<u8> {
        let n = self.values.len();
        let narrow = NARROW.iter().find(|f| self.values.iter().all(|&v| f.of(v).is_some()));
        let size = if narrow.is_some() { 2 } else { 4 };
        let mut out = Vec::with_capacity(TILE_HEADER + size * n + n.div_ceil(8));
        out.extend_from_slice(TILE_MAGIC);
        out.extend_from_slice(&self.window.width.to_le_bytes());
        out.extend_from_slice(&self.window.height.to_le_bytes());
        out.extend_from_slice(&self.window.x0.to_le_bytes());
        out.extend_from_slice(&self.window.y0.to_le_bytes());
        let holes = if self.holes.is_some() { HAS_HOLES } else { 0 };
        out.extend_from_slice(&(holes | narrow.map_or(0, |f| f.flag)).to_le_bytes());
        match narrow {
            Some(f) => {
                for &v in &self.values {
                    out.extend_from_slice(&f.of(v).unwrap_or(0).to_le_bytes());
                }
            }
            None => {
                for v in &self.values {
                    out.extend_from_slice(&v.to_le_bytes());
                }
            }
        }
        if let Some(h) = &self.holes {
            out.extend(pack_bits(h));
        }
        out
    }

    /// Reads a blob written by [`TileHeights::encode`].
    ///
    /// # Errors
    /// [`Error::Internal`] for bytes that are not such a blob.
    pub fn decode(bytes: &[u8]) -> Result<TileHeights> {
        let bad = || Error::Internal("not a tile height blob (HBH1)".into());
        if bytes.len() < TILE_HEADER || &bytes[..4] != TILE_MAGIC {
            return Err(bad());
        }
        let u32_at = |o: usize| u32::from_le_bytes(bytes[o..o + 4].try_into().unwrap_or([0; 4]));
        let i64_at = |o: usize| i64::from_le_bytes(bytes[o..o + 8].try_into().unwrap_or([0; 8]));
        let window = Window { width: u32_at(4), height: u32_at(8), x0: i64_at(12), y0: i64_at(20) };
        let flags = u32_at(28);
        let mut forms = NARROW.iter().filter(|f| flags & f.flag != 0);
        let narrow = forms.next();
        if flags & !(HAS_HOLES | NORM16 | INT16 | SINT16) != 0 || forms.next().is_some() {
            return Err(bad());
        }
        let n = (window.width as usize).checked_mul(window.height as usize).ok_or_else(bad)?;
        let size = if narrow.is_some() { 2 } else { 4 };
        let end = n.checked_mul(size).and_then(|b| b.checked_add(TILE_HEADER)).ok_or_else(bad)?;
        let want = end + if flags & HAS_HOLES != 0 { n.div_ceil(8) } else { 0 };
        if bytes.len() != want {
            return Err(bad());
        }
        let vals = &bytes[TILE_HEADER..end];
        let values = match narrow {
            Some(f) => {
                vals.chunks_exact(2).map(|c| (f.value)(u16::from_le_bytes([c[0], c[1]]))).collect()
            }
            None => {
                vals.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect()
            }
        };
        let holes = (flags & HAS_HOLES != 0).then(|| unpack_bits(&bytes[end..], n));
        Ok(TileHeights { window, values, holes })
    }

    /// The window's [`HeightMap`]: holes filled with `stats.fill`, the map's georeferencing and
    /// nodata, and a hole mask whenever the whole map has holes. Equal, value for value, to the
    /// same window cut from the whole-map decode.
    pub fn into_map(self, stats: &MapStats) -> HeightMap {
        let n = self.values.len();
        let mut values = self.values;
        let holes = if stats.holes > 0 {
            let mask = self.holes.unwrap_or_else(|| vec![false; n]);
            if let Some(fill) = stats.fill {
                for (v, &h) in values.iter_mut().zip(&mask) {
                    if h {
                        *v = fill;
                    }
                }
            }
            Some(mask)
        } else {
            None
        };
        HeightMap {
            width: self.window.width as usize,
            height: self.window.height as usize,
            values,
            terrain: Terrain { georef: stats.georef.clone(), nodata: stats.nodata, holes },
        }
    }
}

fn pack_bits(bits: &[bool]) -> Vec<u8> {
    bits.chunks(8)
        .map(|c| c.iter().enumerate().fold(0u8, |b, (i, &x)| b | (u8::from(x) << i)))
        .collect()
}

fn unpack_bits(bytes: &[u8], n: usize) -> Vec<bool> {
    (0..n).map(|k| bytes.get(k / 8).is_some_and(|b| (b >> (k % 8)) & 1 == 1)).collect()
}

/// Reads only the header of `input`: its format name and dimensions, checked against `limits`
/// (and its length against `limits.max_bytes`). PNG reads 24 bytes; TIFF its IFD; OpenEXR its
/// header. No pixel buffer is allocated.
///
/// # Errors
/// As [`super::probe`].
pub fn probe_reader<R: Read + Seek>(
    mut input: R,
    limits: &Limits,
) -> Result<(&'static str, u32, u32)> {
    let len = input.seek(SeekFrom::End(0))?;
    if len > limits.max_bytes {
        return Err(Error::Limits(LimitError::Bytes { bytes: len, max_bytes: limits.max_bytes }));
    }
    input.seek(SeekFrom::Start(0))?;
    let mut head = Vec::with_capacity(64);
    (&mut input).take(64).read_to_end(&mut head)?;
    let fmt = sniff(&head)?;
    input.seek(SeekFrom::Start(0))?;
    let (w, h) = match fmt {
        Format::Png => png_dimensions(&head)?,
        Format::Tiff => contained("TIFF", || {
            let mut dec = tiff::decoder::Decoder::new(&mut input).map_err(tiff_error)?;
            let (w, h) = dec.dimensions().map_err(tiff_error)?;
            Ok((w as u64, h as u64))
        })?,
        Format::Exr => contained("OpenEXR", || {
            let meta = exr::meta::MetaData::read_from_buffered(BufReader::new(&mut input), false)
                .map_err(super::exr_error)?;
            let header = meta
                .headers
                .first()
                .ok_or_else(|| Error::Decode("the OpenEXR file has no layers".into()))?;
            Ok((header.layer_size.0 as u64, header.layer_size.1 as u64))
        })?,
    };
    check_dimensions(w, h, limits)?;
    Ok((fmt.name(), w as u32, h as u32))
}

/// What [`probe_for`] reads: (format name, width, height) and the georeferencing report.
pub type ProbedFor = ((&'static str, u32, u32), Option<super::georef::GeorefReport>);

/// [`probe_reader`] for a submission with `params`, as
/// [`super::check_submission_for`] without decoding the values: the header's format and size,
/// a TIFF's georeferencing with the DEM defaults of SPEC §2 applied to `params`, and the
/// georeferencing report. For an input too large to hold (its values are checked when the
/// bake decodes it).
///
/// # Errors
/// As [`probe_reader`]; a TIFF's compression we do not read, colour types we do not read, and
/// the refusals of the DEM defaults.
pub fn probe_for<R: Read + Seek>(
    mut input: R,
    params: &mut crate::params::BakeParams,
    limits: &Limits,
) -> Result<ProbedFor> {
    let probed = probe_reader(&mut input, limits)?;
    let georef = if probed.0 == "tiff" {
        input.seek(SeekFrom::Start(0))?;
        contained("TIFF", || {
            let mut dec = tiff::decoder::Decoder::new(&mut input).map_err(tiff_error)?;
            Ok(tiff_meta(&mut dec)?.georef)
        })?
    } else {
        None
    };
    super::georef::apply_dem_defaults(params, georef.as_ref())?;
    let report = georef.as_ref().map(|g| g.report(params.cell_size));
    Ok((probed, report))
}

/// Whether `input` can be decoded in row bands ([`decode_tiles`]), checked from its header (and
/// a TIFF's first strip or tile), for a submission that will be tiled to refuse now what would
/// fail the bake later: OpenEXR, an interlaced PNG, a TIFF with separate colour planes or with
/// strips or tiles too large to decode one at a time.
///
/// # Errors
/// [`Error::Unsupported`] or [`Error::InvalidInput`] saying which and how to fix it; the
/// header's refusals.
pub fn check_streamable<R: Read + Seek>(
    mut input: R,
    channel: Channel,
    limits: &Limits,
) -> Result<()> {
    contained("streamed", || open_rows(&mut input, channel, limits).map(|_| ()))
}

/// Decoded rows of heights, a band at a time.
trait Rows {
    /// Replaces `out` with the next band of rows (`width` values each); returns how many rows,
    /// 0 at the end of the image.
    fn next_band(&mut self, out: &mut Vec<f32>) -> Result<usize>;
}

/// What a decoder knows of its samples after its header (and, for TIFF, its first chunk).
#[derive(Debug, Clone)]
struct Kind {
    color: &'static str,
    bit_depth: u8,
    float: bool,
    /// Stored value = value × `stored`.
    stored: f64,
}

fn png_err(e: png::DecodingError) -> Error {
    match e {
        png::DecodingError::IoError(io) if io.kind() == std::io::ErrorKind::UnexpectedEof => {
            Error::Decode("the image data is truncated".into())
        }
        png::DecodingError::LimitsExceeded => {
            Error::InvalidInput("the image exceeds the decoder's limits".into())
        }
        other => Error::Decode(other.to_string()),
    }
}

/// A PNG read row by row by the `png` crate with the transformations the `image` crate's PNG
/// decoder asks for (`EXPAND`: palette to RGB(A), low bit depths to 8, tRNS to alpha), so the
/// samples are the ones the whole decode sees.
struct PngRows<R: Read + Seek> {
    reader: png::Reader<BufReader<R>>,
    n: usize,
    sixteen: bool,
    channel: Channel,
    row16: Vec<u16>,
}

impl<R: Read + Seek> PngRows<R> {
    fn open(input: R, channel: Channel, limits: &Limits) -> Result<(Self, Kind)> {
        let mut dec = png::Decoder::new_with_limits(
            BufReader::with_capacity(1 << 16, input),
            png::Limits { bytes: 64 << 20 },
        );
        dec.set_ignore_text_chunk(false);
        let info = dec.read_header_info().map_err(png_err)?;
        check_dimensions(info.width as u64, info.height as u64, limits)?;
        if info.interlaced {
            return Err(Error::Unsupported(
                "an interlaced (Adam7) PNG cannot be decoded in row bands for a tiled bake; \
                 save it without interlacing"
                    .into(),
            ));
        }
        dec.set_transformations(png::Transformations::EXPAND);
        let reader = dec.read_info().map_err(png_err)?;
        let (ct, bits) = reader.output_color_type();
        let (n, color) = match ct {
            png::ColorType::Grayscale => (1, "gray"),
            png::ColorType::GrayscaleAlpha => (2, "gray_alpha"),
            png::ColorType::Rgb => (3, "rgb"),
            png::ColorType::Rgba => (4, "rgba"),
            png::ColorType::Indexed => {
                return Err(Error::Unsupported("an indexed PNG that does not expand".into()))
            }
        };
        let sixteen = match bits {
            png::BitDepth::Eight => false,
            png::BitDepth::Sixteen => true,
            other => {
                return Err(Error::Unsupported(format!("PNG of {} bits per sample", other as u8)))
            }
        };
        let kind = Kind {
            color,
            bit_depth: if sixteen { 16 } else { 8 },
            float: false,
            stored: if sixteen { 65535.0 } else { 255.0 },
        };
        Ok((PngRows { reader, n, sixteen, channel, row16: Vec::new() }, kind))
    }
}

impl<R: Read + Seek> Rows for PngRows<R> {
    fn next_band(&mut self, out: &mut Vec<f32>) -> Result<usize> {
        let Some(row) = self.reader.next_row().map_err(png_err)? else { return Ok(0) };
        let data = row.data();
        *out = if self.sixteen {
            self.row16.clear();
            self.row16.extend(data.chunks_exact(2).map(|c| u16::from_be_bytes([c[0], c[1]])));
            samples(&self.row16, self.n, self.channel, |v: u16| (v as f64 / 65535.0) as f32)
        } else {
            samples(data, self.n, self.channel, |v: u8| v as f32 / 255.0)
        };
        Ok(1)
    }
}

/// Bit depth, float, stored scale of decoded TIFF samples.
type SampleKind = (u8, bool, f64);

/// Largest TIFF strip or tile we decode at once: a file written as one strip of a huge map
/// would be the whole map.
const MAX_CHUNK_BYTES: u64 = 512 << 20;

/// A TIFF read strip by strip, or one row of tiles at a time, each chunk converted by
/// [`tiff_values`]: the streamed decode's reader, and the whole decode's
/// ([`super::decode_tiff`]), which appends the bands to the map's heights.
pub(super) struct TiffRows<R: Read + Seek> {
    dec: tiff::decoder::Decoder<R>,
    pub(super) meta: TiffMeta,
    pub(super) channel: Channel,
    pub(super) width: usize,
    pub(super) height: usize,
    tiled: bool,
    chunk: (usize, usize),
    /// The next strip, or the next row of tiles.
    next: usize,
    rows_done: usize,
}

impl<R: Read + Seek> TiffRows<R> {
    fn open(input: R, limits: &Limits) -> Result<(Self, Option<Georef>)> {
        Self::open_with(input, limits, MAX_CHUNK_BYTES)
    }

    /// [`TiffRows::open`] with chunks of up to `max_chunk` bytes (at 8 bytes a sample): the
    /// whole decode takes a file written as one strip, which its memory estimate counts.
    pub(super) fn open_with(
        input: R,
        limits: &Limits,
        max_chunk: u64,
    ) -> Result<(Self, Option<Georef>)> {
        let mut tl = tiff::decoder::Limits::default();
        let cap = usize::try_from(max_chunk).unwrap_or(usize::MAX);
        tl.decoding_buffer_size = cap;
        tl.intermediate_buffer_size = cap;
        let mut dec = tiff::decoder::Decoder::new(input).map_err(tiff_error)?.with_limits(tl);
        let (w, h) = dec.dimensions().map_err(tiff_error)?;
        check_dimensions(w as u64, h as u64, limits)?;
        let meta = tiff_meta(&mut dec)?;
        let planar = dec
            .find_tag_unsigned::<u16>(tiff::tags::Tag::PlanarConfiguration)
            .map_err(tiff_error)?
            .unwrap_or(1);
        if planar == 2 && meta.n > 1 {
            return Err(Error::Unsupported(
                "a TIFF with separate colour planes (PlanarConfiguration 2); rewrite it \
                 pixel-interleaved (`gdal_translate -co INTERLEAVE=PIXEL`)"
                    .into(),
            ));
        }
        let tiled = dec.get_chunk_type() == tiff::decoder::ChunkType::Tile;
        let (cw, ch) = dec.chunk_dimensions();
        let chunk_bytes = cw as u64 * ch as u64 * meta.n as u64 * 8;
        if chunk_bytes > max_chunk {
            return Err(Error::InvalidInput(format!(
                "the TIFF's {} are {cw}×{ch} texels, too large to decode in bands; rewrite it \
                 tiled (`gdal_translate -co TILED=YES in.tif out.tif`)",
                if tiled { "tiles" } else { "strips" }
            )));
        }
        let georef = meta.georef.clone();
        let rows = TiffRows {
            dec,
            meta,
            channel: Channel::R,
            width: w as usize,
            height: h as usize,
            tiled,
            chunk: (cw as usize, ch as usize),
            next: 0,
            rows_done: 0,
        };
        Ok((rows, georef))
    }

    /// The next band and the sample kind of its chunks.
    pub(super) fn band(&mut self, out: &mut Vec<f32>) -> Result<(usize, Option<SampleKind>)> {
        if self.rows_done >= self.height {
            return Ok((0, None));
        }
        let idx = u32::try_from(self.next).map_err(|_| Error::Decode("TIFF chunk index".into()))?;
        if !self.tiled {
            let res = self.dec.read_chunk(idx).map_err(tiff_error)?;
            let (vals, bd, fl, st) = tiff_values(&res, &self.meta, self.channel)?;
            let rows = vals.len() / self.width.max(1);
            if rows == 0 || vals.len() != rows * self.width {
                return Err(Error::Decode(format!(
                    "TIFF strip {idx} holds {} samples for rows {} texels wide",
                    vals.len(),
                    self.width
                )));
            }
            *out = vals;
            self.next += 1;
            self.rows_done += rows;
            return Ok((rows, Some((bd, fl, st))));
        }
        let (cw, ch) = self.chunk;
        let across = self.width.div_ceil(cw);
        let rows = ch.min(self.height - self.rows_done);
        out.clear();
        out.resize(rows * self.width, 0.0);
        let mut kind = None;
        for t in 0..across {
            let i = u32::try_from(self.next * across + t)
                .map_err(|_| Error::Decode("TIFF tile index".into()))?;
            let res = self.dec.read_chunk(i).map_err(tiff_error)?;
            let (vals, bd, fl, st) = tiff_values(&res, &self.meta, self.channel)?;
            let dw = cw.min(self.width - t * cw);
            if vals.len() < dw * rows {
                return Err(Error::Decode(format!("TIFF tile {i} is short")));
            }
            // A chunk's data is its data dimensions, `dw` wide (or the full tile width).
            let stride = vals.len() / rows.max(1);
            for r in 0..rows {
                out[r * self.width + t * cw..r * self.width + t * cw + dw]
                    .copy_from_slice(&vals[r * stride..r * stride + dw]);
            }
            kind = Some((bd, fl, st));
        }
        self.next += 1;
        self.rows_done += rows;
        Ok((rows, kind))
    }
}

impl<R: Read + Seek> Rows for TiffRows<R> {
    fn next_band(&mut self, out: &mut Vec<f32>) -> Result<usize> {
        Ok(self.band(out)?.0)
    }
}

/// Opens a band reader over `input` (rewound), and says what it reads.
/// A band reader just opened: what it reads, and (TIFF) its first band, read to learn the
/// sample kind.
struct Opened<'r> {
    rows: Box<dyn Rows + 'r>,
    kind: Kind,
    fmt: Format,
    georef: Option<Georef>,
    first: Vec<f32>,
    first_rows: usize,
}

fn open_rows<'r, R: Read + Seek + 'r>(
    mut input: R,
    channel: Channel,
    limits: &Limits,
) -> Result<Opened<'r>> {
    input.seek(SeekFrom::Start(0))?;
    let mut head = Vec::with_capacity(64);
    (&mut input).take(64).read_to_end(&mut head)?;
    let fmt = sniff(&head)?;
    input.seek(SeekFrom::Start(0))?;
    match fmt {
        Format::Png => {
            let (rows, kind) = PngRows::open(input, channel, limits)?;
            Ok(Opened {
                rows: Box::new(rows),
                kind,
                fmt,
                georef: None,
                first: Vec::new(),
                first_rows: 0,
            })
        }
        Format::Tiff => {
            let (mut rows, georef) = TiffRows::open(input, limits)?;
            rows.channel = channel;
            // The sample kind comes with the first chunk, read here.
            let mut first = Vec::new();
            let (n, k) = rows.band(&mut first)?;
            let (bit_depth, float, stored) =
                k.ok_or_else(|| Error::Decode("the TIFF holds no image data".into()))?;
            let kind = Kind { color: rows.meta.color, bit_depth, float, stored };
            Ok(Opened { rows: Box::new(rows), kind, fmt, georef, first, first_rows: n })
        }
        Format::Exr => Err(Error::Unsupported(
            "an OpenEXR input cannot be decoded in row bands for a tiled bake; convert it to a \
             float TIFF (`gdal_translate -ot Float32 in.exr out.tif`)"
                .into(),
        )),
    }
}

/// One row of the map as kept: values and, when nodata is in effect, hole flags.
#[derive(Clone)]
struct Row {
    values: Vec<f32>,
    holes: Option<Vec<bool>>,
}

/// Where each window's rows come from (see the module docs).
struct Schedule {
    /// Windows emitted in the first pass: (index, first map row, row at which it is complete).
    first: Vec<(usize, usize, usize)>,
    /// Windows emitted in the second pass: (index, row of the second pass at which it is
    /// complete).
    second: Vec<(usize, usize)>,
    /// Rows 0..head kept from the first pass for bottom-wrapping windows.
    head: usize,
    /// Rows tail..H kept from the first pass for top-wrapping windows.
    tail: usize,
    /// Rows the second pass decodes.
    second_rows: usize,
}

fn schedule(windows: &[Window], h: usize) -> Result<Schedule> {
    let mut s =
        Schedule { first: Vec::new(), second: Vec::new(), head: 0, tail: h, second_rows: 0 };
    for (i, win) in windows.iter().enumerate() {
        if win.width == 0 || win.height == 0 {
            return Err(Error::Internal(format!("tile window {i} is empty")));
        }
        let ys = win.y0.rem_euclid(h as i64) as usize;
        let end = ys + win.height as usize;
        if end <= h {
            s.first.push((i, ys, end - 1));
            continue;
        }
        // Rows ys..H, then rows from 0 again (all of them if the window is taller than the map).
        let from_top = (end - h).min(h);
        let from_bottom = h - ys;
        if from_top <= from_bottom {
            s.head = s.head.max(from_top);
            s.first.push((i, ys, h - 1));
        } else {
            s.tail = s.tail.min(ys);
            s.second_rows = s.second_rows.max(from_top);
            s.second.push((i, from_top - 1));
        }
    }
    s.first.sort_by_key(|&(i, _, last)| (last, i));
    s.second.sort_by_key(|&(i, last)| (last, i));
    Ok(s)
}

/// The texel checks of the whole decode, run as rows arrive.
struct Checks {
    width: usize,
    nodata: Option<f64>,
    stored: f64,
    holes: u64,
    texels: u64,
    /// Range over the texels that are not holes.
    lo: f32,
    hi: f32,
    first_nonfinite: Option<(u64, f32)>,
    first_range: Option<(u64, f32)>,
    first_bad_valid: Option<(u64, f32)>,
}

impl Checks {
    #[inline]
    fn is_hole(&self, nd: f64, v: f32) -> bool {
        if nd.is_nan() {
            v.is_nan()
        } else if self.stored != 1.0 {
            (v as f64 * self.stored).round() == nd
        } else {
            v == nd as f32 || v as f64 == nd
        }
    }

    /// Checks a row; returns its hole flags when nodata is in effect. A non-finite texel with
    /// no nodata in effect is the whole decode's error right away (nothing later precedes it).
    fn row(&mut self, values: &[f32]) -> Result<Option<Vec<bool>>> {
        let holes = self.nodata.map(|nd| values.iter().map(|&v| self.is_hole(nd, v)).collect());
        for (i, &v) in values.iter().enumerate() {
            let k = self.texels + i as u64;
            let hole = holes.as_ref().is_some_and(|h: &Vec<bool>| h[i]);
            let finite = v.is_finite();
            let in_range = finite && v.abs() <= MAX_ABS_HEIGHT;
            if !finite && self.first_nonfinite.is_none() {
                self.first_nonfinite = Some((k, v));
                if self.nodata.is_none() {
                    return Err(nonfinite_error(k as usize, self.width, v));
                }
            }
            if finite && !in_range && self.first_range.is_none() {
                self.first_range = Some((k, v));
            }
            if hole {
                self.holes += 1;
            } else if in_range {
                self.lo = self.lo.min(v);
                self.hi = self.hi.max(v);
            } else if self.first_bad_valid.is_none() {
                self.first_bad_valid = Some((k, v));
            }
        }
        self.texels += values.len() as u64;
        Ok(holes)
    }

    /// The whole decode's verdict, once every texel was seen: (min, max, fill).
    fn finish(&self) -> Result<(f32, f32, Option<f32>)> {
        let w = self.width;
        if self.holes > 0 {
            if self.holes == self.texels {
                let nd = self.nodata.unwrap_or(f64::NAN);
                return Err(Error::InvalidInput(format!(
                    "every texel is nodata ({nd}): the map has no height left to bake"
                )));
            }
            if let Some((k, v)) = self.first_bad_valid {
                return Err(super::bad_texel_error(k as usize, w, v));
            }
            let fill = super::hole_fill(self.lo, self.hi);
            return Ok((fill, self.hi, Some(fill)));
        }
        if let Some((k, v)) = self.first_nonfinite {
            return Err(nonfinite_error(k as usize, w, v));
        }
        if let Some((k, v)) = self.first_range {
            return Err(range_error(k as usize, w, v));
        }
        Ok((self.lo, self.hi, None))
    }
}

/// The rows a pass keeps: a contiguous run starting at `lo`.
struct Ring {
    lo: usize,
    rows: VecDeque<Row>,
}

impl Ring {
    fn get(&self, y: usize) -> Option<&Row> {
        y.checked_sub(self.lo).and_then(|i| self.rows.get(i))
    }
    fn trim_below(&mut self, y: usize) {
        while self.lo < y && !self.rows.is_empty() {
            self.rows.pop_front();
            self.lo += 1;
        }
    }
}

/// Cuts window `win` out of the map (rows by `row`), as a tile height blob.
fn cut<'a>(
    win: &Window,
    w: usize,
    h: usize,
    row: impl Fn(usize) -> Option<&'a Row>,
) -> Result<Vec<u8>> {
    let (ww, wh) = (win.width as usize, win.height as usize);
    let xs = win.x0.rem_euclid(w as i64) as usize;
    let ys = win.y0.rem_euclid(h as i64) as usize;
    let mut t = TileHeights { window: *win, values: Vec::with_capacity(ww * wh), holes: None };
    let mut mask: Vec<bool> = Vec::new();
    let mut any_hole = false;
    for j in 0..wh {
        let y = (ys + j) % h;
        let r = row(y).ok_or_else(|| {
            Error::Internal(format!("tile cut: map row {y} was not kept (a scheduling bug)"))
        })?;
        // Columns xs.., wrapping as often as the window is wide.
        let mut x = xs;
        let mut left = ww;
        while left > 0 {
            let n = left.min(w - x);
            t.values.extend_from_slice(&r.values[x..x + n]);
            if let Some(hr) = &r.holes {
                let part = &hr[x..x + n];
                any_hole |= part.iter().any(|&b| b);
                mask.extend_from_slice(part);
            }
            left -= n;
            x = 0;
        }
    }
    if any_hole {
        t.holes = Some(mask);
    }
    Ok(t.encode())
}

/// Decodes `input` (PNG or TIFF) band by band and hands `sink` one tile height blob
/// ([`TileHeights::encode`]) per window of `windows`, with the window's index, never holding
/// the whole map (see the module docs for the memory and the order: rows top to bottom,
/// windows whose halo crosses the top edge last, after a second pass over the first rows).
/// `content_hash` is the input's BLAKE3 (the blob store's name for it), reported as is.
///
/// The values in the blobs are bitwise those of [`super::decode_with`] on the same bytes with
/// the same `channel` and `nodata`; a refusal is the whole decode's (same message, same
/// texel), though blobs may have gone to `sink` before it.
///
/// # Errors
/// As [`super::decode_with`]; [`Error::Unsupported`] for OpenEXR, interlaced PNG and planar
/// colour TIFF; the sink's errors.
pub fn decode_tiles<R: Read + Seek>(
    mut input: R,
    content_hash: &str,
    channel: Channel,
    nodata: NoData,
    limits: &Limits,
    windows: &[Window],
    sink: &mut dyn FnMut(usize, Vec<u8>) -> Result<()>,
) -> Result<MapStats> {
    let len = input.seek(SeekFrom::End(0))?;
    if len > limits.max_bytes {
        return Err(Error::Limits(LimitError::Bytes { bytes: len, max_bytes: limits.max_bytes }));
    }
    contained("streamed", || {
        decode_tiles_inner(&mut input, content_hash, channel, nodata, limits, windows, sink)
    })
}

fn decode_tiles_inner<R: Read + Seek>(
    input: &mut R,
    content_hash: &str,
    channel: Channel,
    nodata: NoData,
    limits: &Limits,
    windows: &[Window],
    sink: &mut dyn FnMut(usize, Vec<u8>) -> Result<()>,
) -> Result<MapStats> {
    let (w, h) = {
        let (_, w, h) = probe_reader(&mut *input, limits)?;
        (w as usize, h as usize)
    };
    let plan = schedule(windows, h)?;
    let Opened { mut rows, kind, fmt, georef, first: mut band, first_rows: mut band_rows } =
        open_rows(&mut *input, channel, limits)?;
    let nodata = match nodata {
        NoData::Auto => georef.as_ref().and_then(|g| g.nodata()),
        NoData::None => None,
        NoData::Nan => Some(f64::NAN),
        NoData::Value(v) => Some(v),
    };
    let mut checks = Checks {
        width: w,
        nodata,
        stored: kind.stored,
        holes: 0,
        texels: 0,
        lo: f32::INFINITY,
        hi: f32::NEG_INFINITY,
        first_nonfinite: None,
        first_range: None,
        first_bad_valid: None,
    };
    // First pass.
    let mut ring = Ring { lo: 0, rows: VecDeque::new() };
    let mut head: Vec<Row> = Vec::with_capacity(plan.head);
    let mut tail: Vec<Row> = Vec::with_capacity(h - plan.tail);
    let mut next = 0; // next window of plan.first
    let mut y = 0;
    loop {
        if band_rows == 0 {
            band_rows = rows.next_band(&mut band)?;
            if band_rows == 0 {
                break;
            }
        }
        if band.len() != band_rows * w {
            return Err(Error::Decode(format!(
                "decoded {} samples for {band_rows} rows {w} texels wide",
                band.len()
            )));
        }
        for r in 0..band_rows {
            if y >= h {
                return Err(Error::Decode(format!("the image holds more than {h} rows")));
            }
            let values = band[r * w..(r + 1) * w].to_vec();
            let holes = checks.row(&values)?;
            let row = Row { values, holes };
            if y < plan.head {
                head.push(row.clone());
            }
            if y >= plan.tail {
                tail.push(row.clone());
            }
            ring.rows.push_back(row);
            while let Some(&(i, _, last)) = plan.first.get(next) {
                if last != y {
                    break;
                }
                let blob = cut(&windows[i], w, h, |yy| {
                    ring.get(yy).or_else(|| (yy < head.len()).then(|| &head[yy]))
                })?;
                sink(i, blob)?;
                next += 1;
            }
            // Rows no window still to come in this pass needs.
            let keep = plan.first[next..].iter().map(|&(_, first, _)| first).min().unwrap_or(y + 1);
            ring.trim_below(keep.min(y + 1));
            y += 1;
        }
        band_rows = 0;
    }
    if y != h {
        return Err(Error::Decode(format!("the image data is truncated: {y} of {h} rows decoded")));
    }
    drop(ring);
    drop(head);
    let (min, max, fill) = checks.finish()?;
    // Second pass: the first rows again, for the windows that cross the top edge.
    if !plan.second.is_empty() {
        drop(rows);
        let again = open_rows(&mut *input, channel, limits)?;
        let (mut rows2, mut band2, mut n2) = (again.rows, again.first, again.first_rows);
        let mut ring = Ring { lo: 0, rows: VecDeque::new() };
        let mut next = 0;
        let mut y = 0;
        let tail_at = plan.tail;
        while y < plan.second_rows {
            if n2 == 0 {
                n2 = rows2.next_band(&mut band2)?;
                if n2 == 0 {
                    break;
                }
            }
            for r in 0..n2 {
                if y >= plan.second_rows {
                    break;
                }
                let values = band2[r * w..(r + 1) * w].to_vec();
                let holes =
                    nodata.map(|nd| values.iter().map(|&v| checks.is_hole(nd, v)).collect());
                ring.rows.push_back(Row { values, holes });
                while let Some(&(i, last)) = plan.second.get(next) {
                    if last != y {
                        break;
                    }
                    let blob = cut(&windows[i], w, h, |yy| {
                        if yy >= tail_at {
                            tail.get(yy - tail_at)
                        } else {
                            ring.get(yy)
                        }
                    })?;
                    sink(i, blob)?;
                    next += 1;
                }
                y += 1;
            }
            n2 = 0;
        }
        if next != plan.second.len() {
            return Err(Error::Decode("the image changed between the two passes".into()));
        }
    }
    let info = InputInfo {
        width: w as u32,
        height: h as u32,
        format: fmt.name().into(),
        color: kind.color.into(),
        bit_depth: kind.bit_depth,
        float: kind.float,
        content_hash: content_hash.to_string(),
    };
    Ok(MapStats { info, georef, nodata, holes: checks.holes, min, max, fill })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn blob(values: Vec<f32>, holes: Option<Vec<bool>>) -> (TileHeights, Vec<u8>) {
        let window = Window { x0: -3, y0: 7, width: 5, height: values.len() as u32 / 5 };
        let t = TileHeights { window, values, holes };
        let b = t.encode();
        (t, b)
    }

    fn same_bits(a: &[f32], b: &[f32]) -> bool {
        a.len() == b.len() && a.iter().zip(b).all(|(x, y)| x.to_bits() == y.to_bits())
    }

    #[test]
    fn sixteen_bit_samples_travel_in_two_bytes_and_come_back_bit_for_bit() {
        // As the PNG decoder normalises them, the extremes included.
        let ks = [0u16, 1, 2, 255, 256, 32767, 32768, 65534, 65535, 12345];
        let values: Vec<f32> = ks.iter().map(|&k| (f64::from(k) / 65535.0) as f32).collect();
        let holes = Some((0..10).map(|i| i % 3 == 0).collect::<Vec<_>>());
        let (t, b) = blob(values, holes);
        assert_eq!(b.len(), TILE_HEADER + 2 * 10 + 2);
        let back = TileHeights::decode(&b).unwrap();
        assert!(same_bits(&back.values, &t.values));
        assert_eq!(back.holes, t.holes);
        assert_eq!(back.window, t.window);
        // Every 16-bit sample survives, not only those.
        for k in 0..=u16::MAX {
            let v = (f64::from(k) / 65535.0) as f32;
            assert_eq!(NARROW[0].of(v), Some(k), "sample {k}");
        }
    }

    #[test]
    fn integer_dems_travel_in_two_bytes() {
        let values: Vec<f32> = vec![0.0, 1.0, 2.0, 3000.0, 65535.0, 17.0, 4.0, 8.0, 9.0, 10.0];
        let signed: Vec<f32> = vec![0.0, -1.0, 2.0, -32768.0, 32767.0, 17.0, 4.0, -8.0, 9.0, 1.0];
        for values in [values, signed] {
            let (t, b) = blob(values, None);
            assert_eq!(b.len(), TILE_HEADER + 2 * 10);
            assert!(same_bits(&TileHeights::decode(&b).unwrap().values, &t.values));
        }
    }

    #[test]
    fn any_other_value_keeps_the_whole_window_in_f32() {
        let eighth = (f64::from(100u16) / 65535.0) as f32;
        for odd in [0.5f32, -0.0, -1.0, 65536.0, f32::NAN, 1e-9, 123.25, -32769.0] {
            // A normalised sample next to an integer and the odd one: no narrow form holds all.
            let values = vec![eighth, 3.0, odd, 0.0, 1.0];
            let (t, b) = blob(values, None);
            assert_eq!(b.len(), TILE_HEADER + 4 * 5, "{odd}");
            assert!(same_bits(&TileHeights::decode(&b).unwrap().values, &t.values), "{odd}");
        }
    }

    #[test]
    fn a_blob_cut_short_or_with_unknown_flags_is_refused() {
        let values: Vec<f32> = (0..10).map(|k| (f64::from(k) / 65535.0) as f32).collect();
        let (_, b) = blob(values, None);
        assert!(TileHeights::decode(&b[..b.len() - 1]).is_err());
        let mut odd = b.clone();
        odd[28] |= 8;
        assert!(TileHeights::decode(&odd).is_err());
        let mut odd = b.clone();
        odd[28] |= 16;
        assert!(TileHeights::decode(&odd).is_err());
        for f in [INT16, SINT16] {
            let mut both = b.clone();
            both[28] |= f as u8;
            assert!(TileHeights::decode(&both).is_err());
        }
    }
}
