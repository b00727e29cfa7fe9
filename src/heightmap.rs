//! Decoding an input image into a height map (SPEC §2 "Heights").
//!
//! Inputs come from untrusted uploads, so the order of operations matters: sniff the format from
//! the magic bytes, read the dimensions from the header, check them against [`Limits`], and only
//! then let a decoder allocate pixel buffers. Integer images are normalised to [0, 1] (v/255,
//! v/65535); float images are used as they are; RGB(A) images pick a channel or luma on the
//! stored (non-linearised) values. Non-finite heights are rejected unless they are nodata.
//!
//! A GeoTIFF DEM ([`georef`]) keeps its samples as they are (metres, any sample type) and carries
//! its georeferencing and nodata holes in [`Terrain`] to the bake and the GeoTIFF writer.
//! Holes (SPEC §2 "Nodata") are marked in [`Terrain::holes`] and filled here with a height far
//! below the map, [`HOLE_DEPTH`] × the map's height range under its lowest texel. `exact` skips
//! the cells touching a hole outright (see `kernels::exact`); for the other kernels the fill makes
//! a cell with a hole corner lie below every observer except within about 1/[`HOLE_DEPTH`] of a
//! texel of its valid edges, so a hole occludes nothing. Every output of a hole texel is masked
//! to nodata by the bake.

pub mod budget;
pub mod georef;
pub mod north;
pub mod stream;

use crate::error::{Error, LimitError, Result};
use crate::params::{BakeParams, Channel, NoData};
use serde::{Deserialize, Serialize};
use std::io::Cursor;

/// Bounds on what an input may be; checked before decoding allocates.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Limits {
    /// Largest width or height in texels.
    pub max_dim: u32,
    /// Largest width × height.
    pub max_texels: u64,
    /// Largest encoded input in bytes.
    pub max_bytes: u64,
    /// Most bytes one decode may hold at its peak, as [`budget::estimate`] reads it from the
    /// header (the service's `--max-decode-bytes`; unbounded for the CLI, which decodes one
    /// input and would rather try than refuse).
    pub max_decode_bytes: u64,
}

impl Default for Limits {
    fn default() -> Self {
        Limits {
            max_dim: 16384,
            max_texels: 8192 * 8192,
            max_bytes: 512 * 1024 * 1024,
            max_decode_bytes: u64::MAX,
        }
    }
}

/// What the input was, as reported with a bake.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct InputInfo {
    pub width: u32,
    pub height: u32,
    /// `png`, `tiff` or `exr`.
    pub format: String,
    /// `gray`, `gray_alpha`, `rgb` or `rgba`.
    pub color: String,
    /// Bits per sample of the stored image (8, 16 or 32).
    pub bit_depth: u8,
    /// Whether samples are floating point.
    pub float: bool,
    /// BLAKE3 of the input bytes, hex.
    pub content_hash: String,
}

/// Heights as stored in the image, normalised (integers) or as-is (floats); not yet scaled.
#[derive(Debug, Clone, PartialEq)]
pub struct HeightMap {
    pub width: usize,
    pub height: usize,
    /// Row-major from the top image row.
    pub values: Vec<f32>,
    /// Georeferencing and nodata holes (empty for a plain image).
    pub terrain: Terrain,
}

/// What a DEM carries beside its heights, from decode to encode as one value.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Terrain {
    /// The GeoTIFF tags, copied into GeoTIFF outputs.
    pub georef: Option<georef::Georef>,
    /// The nodata value in effect (NaN for `nan`), written as GDAL_NODATA of the outputs.
    pub nodata: Option<f64>,
    /// `true` for a hole texel (row-major), when there is any hole.
    pub holes: Option<Vec<bool>>,
}

/// How far below the map holes are filled, in map height ranges (see the module docs).
pub const HOLE_DEPTH: f32 = 1000.0;

impl HeightMap {
    /// The warnings of SPEC §2 for this map as decoded: an undeclared nodata (see
    /// [`HeightMap::suspected_nodata`]) and a geographic grid's cells, cos φ as wide as tall,
    /// given one cell size.
    pub fn dem_warnings(&self) -> Vec<String> {
        let mut out = Vec::new();
        let g = self.terrain.georef.as_ref();
        let squeeze = g.and_then(|g| g.geographic_squeeze(self.height));
        if let Some((lat, ratio)) = squeeze.filter(|(_, r)| (r - 1.0).abs() > 0.01) {
            out.push(format!(
                "the DEM is in degrees: at {lat:.2}° its cells are {ratio:.3}× as wide as they \
                 are tall, which one cell_size (`--cell-size`) cannot hold (angles off \
                 east–west); reproject \
                 it (`gdalwarp -t_srs EPSG:<UTM zone> -r bilinear in.tif out.tif`)"
            ));
        }
        if let Some(v) = self.suspected_nodata() {
            out.push(format!(
                "the DEM declares no nodata, and {v} on its border looks like one; it is baked \
                 as a height (give nodata={v}, `--nodata {v}` on the CLI, to make it a hole)"
            ));
        }
        out
    }

    /// A value that looks like an undeclared nodata on a DEM with none declared: one of the
    /// sentinels GIS tools write (−9999, −32768, ±3.4028235e38 as f32::MAX) on the map's
    /// border, where warps and clips leave them (SPEC §2: baked as it is, with a warning).
    pub fn suspected_nodata(&self) -> Option<f32> {
        let dem = self.terrain.georef.as_ref().is_some_and(|g| g.is_dem());
        if !dem || self.terrain.nodata.is_some() || self.values.is_empty() {
            return None;
        }
        let (w, h) = (self.width, self.height);
        let border = (0..w)
            .flat_map(|x| [x, (h - 1) * w + x])
            .chain((0..h).flat_map(|y| [y * w, y * w + w - 1]));
        const SENTINELS: [f32; 4] = [-9999.0, -32768.0, f32::MAX, -f32::MAX];
        border.map(|i| self.values[i]).find(|v| SENTINELS.contains(v))
    }

    /// Heights in texel units: value × `height_scale`.
    pub fn scaled(&self, height_scale: f64) -> Vec<f32> {
        self.values.iter().map(|&v| (v as f64 * height_scale) as f32).collect()
    }

    /// Heights in texel units, scaled in place: the same values as [`HeightMap::scaled`] without
    /// a second full-size buffer (an 8192² map is 256 MiB of f32).
    pub fn into_scaled(mut self, height_scale: f64) -> Vec<f32> {
        self.take_scaled(height_scale)
    }

    /// [`HeightMap::into_scaled`] that keeps the rest of the map (its size, georeferencing,
    /// holes): the values are taken out, scaled in place and returned; `values` is left empty.
    pub fn take_scaled(&mut self, height_scale: f64) -> Vec<f32> {
        let mut values = std::mem::take(&mut self.values);
        for v in &mut values {
            *v = (*v as f64 * height_scale) as f32;
        }
        values
    }

    /// A height map from raw values (tests, synthetic inputs).
    ///
    /// # Errors
    /// [`Error::InvalidInput`] on a size mismatch, an empty map or a non-finite value.
    pub fn from_values(width: usize, height: usize, values: Vec<f32>) -> Result<Self> {
        if width == 0 || height == 0 || values.len() != width * height {
            return Err(Error::InvalidInput(format!(
                "{} values do not make a {width}×{height} map",
                values.len()
            )));
        }
        check_finite(&values, width)?;
        Ok(HeightMap { width, height, values, terrain: Terrain::default() })
    }

    /// A height map from decoded samples, as every decoder ends: `values` normalised as
    /// [`HeightMap`] holds them (`stored` = the integer scale they were divided by, 255 or
    /// 65535, or 1 for samples kept as-is), `nodata` resolved against `georef`'s GDAL_NODATA,
    /// its holes marked (compared as stored) and filled, the other values checked. The Python
    /// package builds arrays into maps through this, so an array and the same image in a file
    /// bake alike.
    ///
    /// # Errors
    /// [`Error::InvalidInput`] on a size mismatch, a map with no texel left, a non-finite or
    /// too-large value that is not nodata.
    pub fn from_samples(
        width: usize,
        height: usize,
        values: Vec<f32>,
        stored: f64,
        nodata: NoData,
        georef: Option<georef::Georef>,
    ) -> Result<Self> {
        Self::from_samples_filled(width, height, values, stored, nodata, georef, None)
    }

    /// [`HeightMap::from_samples`] of a window of a larger map whose holes are filled with
    /// `fill`, the whole map's [`hole_fill`] (`None`: this map's own), so the window holds
    /// exactly the whole map's values there, as a tiled bake's windows do.
    ///
    /// # Errors
    /// As [`HeightMap::from_samples`].
    pub fn from_samples_filled(
        width: usize,
        height: usize,
        mut values: Vec<f32>,
        stored: f64,
        nodata: NoData,
        georef: Option<georef::Georef>,
        fill: Option<f32>,
    ) -> Result<Self> {
        if width == 0 || height == 0 || values.len() != width * height {
            return Err(Error::InvalidInput(format!(
                "{} values do not make a {width}×{height} map",
                values.len()
            )));
        }
        let nodata = match nodata {
            NoData::Auto => georef.as_ref().and_then(|g| g.nodata()),
            NoData::None => None,
            NoData::Nan => Some(f64::NAN),
            NoData::Value(v) => Some(v),
        };
        let holes = nodata.map(|nd| mark_holes(&values, stored, nd)).transpose()?.flatten();
        match &holes {
            Some(holes) => fill_holes(&mut values, holes, width, fill)?,
            None => {
                check_finite(&values, width)?;
                check_range(&values, width)?;
            }
        }
        let terrain = Terrain { georef, nodata, holes };
        Ok(HeightMap { width, height, values, terrain })
    }
}

/// Largest absolute height value accepted (before `height_scale`). With `height_scale` at most
/// [`crate::params::MAX_HEIGHT_SCALE`] (1e9), scaled heights and their differences stay within
/// f32 (3.4e38), so a value beyond this is the input's fault, never the scale's.
pub const MAX_ABS_HEIGHT: f32 = 1e29;

fn check_finite(values: &[f32], width: usize) -> Result<()> {
    if let Some(k) = values.iter().position(|v| !v.is_finite()) {
        return Err(nonfinite_error(k, width, values[k]));
    }
    Ok(())
}

/// The refusal of non-finite texel `k` (row-major in a map `width` wide) holding `v`.
fn nonfinite_error(k: usize, width: usize, v: f32) -> Error {
    Error::InvalidInput(format!(
        "height at column {}, row {} is {} (heights must be finite; if it marks missing \
         data, declare it with `nodata={}`)",
        k % width.max(1),
        k / width.max(1),
        v,
        if v.is_nan() { "nan".to_string() } else { v.to_string() }
    ))
}

/// The refusal of texel `k` holding `v`, beyond ±[`MAX_ABS_HEIGHT`].
fn range_error(k: usize, width: usize, v: f32) -> Error {
    Error::InvalidInput(format!(
        "height at column {}, row {} is {:e}, beyond ±{MAX_ABS_HEIGHT:e}: the input's values \
         are out of range",
        k % width.max(1),
        k / width.max(1),
        v
    ))
}

/// The refusal of texel `k` holding `v` that is not a hole of a map with holes (non-finite or
/// out of range; [`fill_holes`]'s message).
fn bad_texel_error(k: usize, width: usize, v: f32) -> Error {
    if !v.is_finite() {
        return Error::InvalidInput(format!(
            "height at column {}, row {} is {v}: heights must be finite and within \
             ±{MAX_ABS_HEIGHT:e} (declare missing data with `nodata`)",
            k % width.max(1),
            k / width.max(1)
        ));
    }
    range_error(k, width, v)
}

/// Decoded input values must also be within ±[`MAX_ABS_HEIGHT`], so that an overflow is blamed
/// on the file rather than on `height_scale`. (Synthetic maps built with
/// [`HeightMap::from_values`] may go further: the kernels handle any finite value.)
fn check_range(values: &[f32], width: usize) -> Result<()> {
    if let Some(k) = values.iter().position(|v| v.abs() > MAX_ABS_HEIGHT) {
        return Err(range_error(k, width, values[k]));
    }
    Ok(())
}

/// The input formats we read.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Format {
    Png,
    Tiff,
    Exr,
}

impl Format {
    fn name(self) -> &'static str {
        match self {
            Format::Png => "png",
            Format::Tiff => "tiff",
            Format::Exr => "exr",
        }
    }
}

const PNG_MAGIC: &[u8] = b"\x89PNG\r\n\x1a\n";

/// Sniffs the format from magic bytes (never from a name or a declared content type).
fn sniff(bytes: &[u8]) -> Result<Format> {
    if bytes.is_empty() {
        return Err(Error::Unsupported("the input is empty (0 bytes)".into()));
    }
    if bytes.starts_with(PNG_MAGIC) {
        return Ok(Format::Png);
    }
    if bytes.starts_with(b"II*\0")
        || bytes.starts_with(b"MM\0*")
        || bytes.starts_with(b"II+\0")
        || bytes.starts_with(b"MM\0+")
    {
        return Ok(Format::Tiff);
    }
    if bytes.starts_with(&[0x76, 0x2f, 0x31, 0x01]) {
        return Ok(Format::Exr);
    }
    match image::guess_format(bytes) {
        Ok(other) => Err(Error::Unsupported(format!(
            "{} images are not supported; use PNG, TIFF or OpenEXR",
            other.extensions_str().first().copied().unwrap_or("this kind of").to_uppercase()
        ))),
        Err(_) => Err(Error::Unsupported(
            "not a PNG, TIFF or OpenEXR image (unrecognised signature)".into(),
        )),
    }
}

fn image_error(e: image::ImageError) -> Error {
    use image::ImageError as E;
    match e {
        E::Limits(l) => Error::InvalidInput(format!("the image exceeds the decoder's limits: {l}")),
        E::Unsupported(u) => Error::Unsupported(u.to_string()),
        E::IoError(io) if io.kind() == std::io::ErrorKind::UnexpectedEof => {
            Error::Decode("the image data is truncated".into())
        }
        E::Decoding(d) if d.to_string().contains("EOF") || d.to_string().contains("eof") => {
            Error::Decode(format!("the image data is truncated ({d})"))
        }
        other => Error::Decode(other.to_string()),
    }
}

fn tiff_error(e: tiff::TiffError) -> Error {
    use tiff::TiffError as T;
    match e {
        T::IoError(io) if io.kind() == std::io::ErrorKind::UnexpectedEof => {
            Error::Decode("the TIFF data is truncated".into())
        }
        T::UnsupportedError(u) => Error::Unsupported(format!("TIFF: {u}")),
        T::LimitsExceeded => {
            Error::InvalidInput("the TIFF exceeds the decoder's memory limits".into())
        }
        other => Error::Decode(format!("TIFF: {other}")),
    }
}

fn exr_error(e: exr::error::Error) -> Error {
    use exr::error::Error as X;
    match e {
        X::NotSupported(m) => Error::Unsupported(format!("OpenEXR: {m}")),
        X::Io(io) if io.kind() == std::io::ErrorKind::UnexpectedEof => {
            Error::Decode("the OpenEXR data is truncated".into())
        }
        other => Error::Decode(format!("OpenEXR: {other}")),
    }
}

/// Checks header dimensions against `limits`.
///
/// # Errors
/// [`Error::InvalidInput`] for a 0-sized image, [`Error::Limits`] over a limit.
pub fn check_dimensions(width: u64, height: u64, limits: &Limits) -> Result<()> {
    if width == 0 || height == 0 {
        return Err(Error::InvalidInput(format!("image is {width}×{height}; it has no texels")));
    }
    if width > limits.max_dim as u64 || height > limits.max_dim as u64 {
        return Err(Error::Limits(LimitError::Dimensions {
            width,
            height,
            max_dim: limits.max_dim,
        }));
    }
    let texels = width * height;
    if texels > limits.max_texels {
        return Err(Error::Limits(LimitError::Texels { texels, max_texels: limits.max_texels }));
    }
    Ok(())
}

/// Width and height from a PNG's IHDR chunk, read by hand: 16 bytes in, no decoder, no allocation,
/// so an absurd header is rejected in microseconds.
fn png_dimensions(bytes: &[u8]) -> Result<(u64, u64)> {
    let ihdr = bytes
        .get(8..24)
        .ok_or_else(|| Error::Decode("the PNG is truncated before its IHDR header chunk".into()))?;
    if &ihdr[4..8] != b"IHDR" {
        return Err(Error::Decode("the PNG does not start with an IHDR header chunk".into()));
    }
    let w = u32::from_be_bytes([ihdr[8], ihdr[9], ihdr[10], ihdr[11]]);
    let h = u32::from_be_bytes([ihdr[12], ihdr[13], ihdr[14], ihdr[15]]);
    Ok((w as u64, h as u64))
}

fn tiff_decoder(bytes: &[u8]) -> Result<tiff::decoder::Decoder<Cursor<&[u8]>>> {
    tiff::decoder::Decoder::new(Cursor::new(bytes)).map_err(tiff_error)
}

/// Runs a third-party decoder on untrusted bytes with its panics caught: a decoder bug on a
/// malformed file must be that file's 422, not a crashed worker or a 500.
fn contained<T>(what: &str, f: impl FnOnce() -> Result<T>) -> Result<T> {
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)).unwrap_or_else(|_| {
        Err(Error::Decode(format!("the {what} decoder could not read this input (malformed)")))
    })
}

/// Refuses an OpenEXR whose first header's `dataWindow` is inverted (xMax < xMin or
/// yMax < yMin): such a file describes no image, and the `exr` crate silently swaps the corners,
/// which would bake a different size than the file states. Walks the attribute list (name\0,
/// type\0, i32 size, value) of the first header; a list it cannot walk is left to the crate.
fn check_exr_data_window(bytes: &[u8]) -> Result<()> {
    let cstr = |at: usize| -> Option<(&[u8], usize)> {
        let len = bytes.get(at..)?.iter().take(256).position(|&b| b == 0)?;
        Some((&bytes[at..at + len], at + len + 1))
    };
    let i32_at = |at: usize| -> Option<i32> {
        Some(i32::from_le_bytes(bytes.get(at..at + 4)?.try_into().ok()?))
    };
    // Magic (4 bytes) and version (4), then the attributes.
    let mut at = 8;
    for _ in 0..1024 {
        let Some((name, next)) = cstr(at) else { return Ok(()) };
        if name.is_empty() {
            return Ok(());
        }
        let Some((kind, next)) = cstr(next) else { return Ok(()) };
        let Some(size) = i32_at(next).and_then(|v| usize::try_from(v).ok()) else {
            return Ok(());
        };
        let value = next + 4;
        if name == b"dataWindow" && kind == b"box2i" && size == 16 {
            let v = [0, 4, 8, 12].map(|o| i32_at(value + o));
            if let [Some(x0), Some(y0), Some(x1), Some(y1)] = v {
                if x1 < x0 || y1 < y0 {
                    return Err(Error::Decode(format!(
                        "the OpenEXR data window is inverted (min {x0},{y0}, max {x1},{y1}): \
                         it describes no image"
                    )));
                }
            }
            return Ok(());
        }
        at = value.saturating_add(size);
    }
    Ok(())
}

/// Reads only the header: format and dimensions, checked against `limits`.
fn probe_format(bytes: &[u8], limits: &Limits) -> Result<(Format, u32, u32)> {
    if bytes.len() as u64 > limits.max_bytes {
        return Err(Error::Limits(LimitError::Bytes {
            bytes: bytes.len() as u64,
            max_bytes: limits.max_bytes,
        }));
    }
    let fmt = sniff(bytes)?;
    let (w, h) = match fmt {
        Format::Png => png_dimensions(bytes)?,
        Format::Tiff => contained("TIFF", || {
            let (w, h) = tiff_decoder(bytes)?.dimensions().map_err(tiff_error)?;
            Ok((w as u64, h as u64))
        })?,
        Format::Exr => contained("OpenEXR", || {
            check_exr_data_window(bytes)?;
            let meta = exr::meta::MetaData::read_from_buffered(Cursor::new(bytes), false)
                .map_err(exr_error)?;
            let header = meta
                .headers
                .first()
                .ok_or_else(|| Error::Decode("the OpenEXR file has no layers".into()))?;
            Ok((header.layer_size.0 as u64, header.layer_size.1 as u64))
        })?,
    };
    check_dimensions(w, h, limits)?;
    // check_dimensions bounds both by `max_dim: u32`.
    Ok((fmt, w as u32, h as u32))
}

/// Reads only the header: format and dimensions, checked against `limits`. No pixel buffer is
/// allocated.
///
/// # Errors
/// As [`decode`], without touching pixel data.
pub fn probe(bytes: &[u8], limits: &Limits) -> Result<(image::ImageFormat, u32, u32)> {
    let (f, w, h) = probe_format(bytes, limits)?;
    let f = match f {
        Format::Png => image::ImageFormat::Png,
        Format::Tiff => image::ImageFormat::Tiff,
        Format::Exr => image::ImageFormat::OpenExr,
    };
    Ok((f, w, h))
}

/// What a service checks before accepting an upload: the header (format, dimensions against
/// `limits`, without allocating pixels), and for TIFF and OpenEXR the whole decode with
/// `channel`: those can hold float samples (NaN, infinities, values out of range) and sample
/// formats we do not read (32-bit integer, 16-bit float TIFF), which the header check alone
/// would only find when the bake runs. PNG holds integers only, so its header is enough.
///
/// # Errors
/// As [`decode`].
pub fn check_submission(
    bytes: &[u8],
    channel: Channel,
    limits: &Limits,
) -> Result<(image::ImageFormat, u32, u32)> {
    let probed = probe(bytes, limits)?;
    if probed.0 != image::ImageFormat::Png {
        decode(bytes, channel, limits)?;
    }
    Ok(probed)
}

/// [`check_submission`] for a bake with `params`: TIFF and OpenEXR (and any input with a
/// `nodata` declaration) are decoded whole with the bake's `channel` and `nodata`, and the DEM
/// defaults of SPEC §2 are applied to `params`, so a refusal (a geographic CRS, an all-nodata
/// map, NaN without nodata) is the submission's 422 and the stored parameters are the resolved
/// ones.
///
/// Returns the format and size, and the input's georeferencing as bake.json reports it (with
/// the resolved `cell_size`), for a bake resource to show before the bake runs.
///
/// # Errors
/// As [`decode_for`].
pub fn check_submission_for(
    bytes: &[u8],
    params: &mut BakeParams,
    limits: &Limits,
) -> Result<((image::ImageFormat, u32, u32), Option<georef::GeorefReport>)> {
    check_submission_for_in(bytes, params, limits, None)
}

/// [`check_submission_for`] with the decode's memory reserved from `admit`'s budget (and
/// given back before it returns).
///
/// # Errors
/// As [`decode_for_in`].
pub fn check_submission_for_in(
    bytes: &[u8],
    params: &mut BakeParams,
    limits: &Limits,
    admit: Option<budget::Admit<'_>>,
) -> Result<((image::ImageFormat, u32, u32), Option<georef::GeorefReport>)> {
    let probed = probe(bytes, limits)?;
    let mut report = None;
    if probed.0 != image::ImageFormat::Png || !matches!(params.nodata, NoData::Auto) {
        let (map, _, _held) = decode_for_in(bytes, params, limits, admit)?;
        report = map.terrain.georef.as_ref().map(|g| g.report(params.cell_size));
        if let Some(r) = &mut report {
            r.warnings = map.dem_warnings();
        }
    } else {
        georef::apply_dem_defaults(params, None)?;
    }
    Ok((probed, report))
}

/// [`check_submission_for`] for a map that will be baked in tiles (above `--tile-above`),
/// which no process decodes whole: the values are checked by the band decoder of the tiled
/// bake's split ([`stream::decode_tiles`] with no window), so the refusals are the same and
/// the memory is one band, not the map (nor its share of the decode budgets).
///
/// # Errors
/// As [`stream::decode_tiles`] and [`stream::probe_for`].
pub fn check_submission_streamed(
    bytes: &[u8],
    params: &mut BakeParams,
    limits: &Limits,
) -> Result<((image::ImageFormat, u32, u32), Option<georef::GeorefReport>)> {
    let probed = probe(bytes, limits)?;
    let (_, report) = stream::probe_for(Cursor::new(bytes), params, limits)?;
    if probed.0 != image::ImageFormat::Png || !matches!(params.nodata, NoData::Auto) {
        let (channel, nodata) = (params.decode_channel(), params.nodata);
        let mut none = |_: usize, _: Vec<u8>| Ok(());
        stream::decode_tiles(Cursor::new(bytes), "", channel, nodata, limits, &[], &mut none)?;
    }
    Ok((probed, report))
}

/// Samples decoded from an image, before the channel pick.
struct Decoded {
    values: Vec<f32>,
    color: &'static str,
    bit_depth: u8,
    float: bool,
    /// Stored value = value × `stored` (255 or 65535 for normalised integers, else 1).
    stored: f64,
    georef: Option<georef::Georef>,
}

/// Decodes `bytes` into a height map, picking `channel` from colour images.
///
/// # Errors
/// [`Error::Unsupported`] (not an image we read), [`Error::Limits`] (too large, checked from the
/// header before decoding), [`Error::Decode`] (broken data), [`Error::InvalidInput`] (0×0,
/// non-finite heights).
pub fn decode(bytes: &[u8], channel: Channel, limits: &Limits) -> Result<(HeightMap, InputInfo)> {
    decode_with(bytes, channel, NoData::Auto, limits)
}

/// Decodes `bytes` for a bake with `params`: the `channel` and `nodata` it asks for, then the
/// DEM defaults of SPEC §2 applied to `params` ([`georef::apply_dem_defaults`]).
///
/// # Errors
/// As [`decode_with`], and the refusals of the DEM defaults.
pub fn decode_for(
    bytes: &[u8],
    params: &mut BakeParams,
    limits: &Limits,
) -> Result<(HeightMap, InputInfo)> {
    let (map, info, _) = decode_for_in(bytes, params, limits, None)?;
    Ok((map, info))
}

/// [`decode_for`] with its memory reserved from `admit`'s budget first (see
/// [`decode_with_in`]); the reservation, holding what the map keeps, is returned beside it.
///
/// # Errors
/// As [`decode_with_in`], and the refusals of the DEM defaults.
pub fn decode_for_in(
    bytes: &[u8],
    params: &mut BakeParams,
    limits: &Limits,
    admit: Option<budget::Admit<'_>>,
) -> Result<(HeightMap, InputInfo, budget::Reservation)> {
    let (map, info, held) =
        decode_with_in(bytes, params.decode_channel(), params.nodata, limits, admit)?;
    georef::apply_dem_defaults(params, map.terrain.georef.as_ref())?;
    Ok((map, info, held))
}

/// [`decode`] with a nodata declaration: texels equal to it (as stored in the file) are holes.
///
/// # Errors
/// As [`decode`]; a map with no texel left, and a non-finite value that is not nodata, are
/// [`Error::InvalidInput`].
pub fn decode_with(
    bytes: &[u8],
    channel: Channel,
    nodata: NoData,
    limits: &Limits,
) -> Result<(HeightMap, InputInfo)> {
    let (map, info, _) = decode_with_in(bytes, channel, nodata, limits, None)?;
    Ok((map, info))
}

/// [`decode_with`] under memory budgets: the peak the decode will hold is estimated from the
/// header ([`budget::estimate`]) and refused over `limits.max_decode_bytes`, then reserved from
/// `admit`'s process-wide budget (waiting as it says) before any pixel buffer is allocated. The
/// returned reservation is shrunk to what the map keeps (its heights and hole mask); drop it
/// with the map.
///
/// # Errors
/// As [`decode_with`]; [`Error::Limits`] over the per-request budget, [`Error::MemoryBusy`]
/// when the process budget stays taken for `admit`'s wait.
pub fn decode_with_in(
    bytes: &[u8],
    channel: Channel,
    nodata: NoData,
    limits: &Limits,
    admit: Option<budget::Admit<'_>>,
) -> Result<(HeightMap, InputInfo, budget::Reservation)> {
    let (fmt, w, h) = probe_format(bytes, limits)?;
    let est = budget::estimate(bytes, nodata)?;
    budget::check(&est, limits.max_decode_bytes)?;
    let mut held = match admit {
        Some(a) => a.budget.reserve(est.peak, a.wait)?,
        None => budget::Reservation::none(),
    };
    // Room for the decoded image at up to 4 × f32 per texel plus the decoders' own buffers.
    let max_alloc = limits.max_texels.saturating_mul(16).saturating_add(64 << 20);
    let d = match fmt {
        Format::Png => contained("PNG", || decode_png(bytes, channel, limits, max_alloc))?,
        Format::Tiff => contained("TIFF", || decode_tiff(bytes, channel, limits, max_alloc))?,
        Format::Exr => contained("OpenEXR", || decode_exr(bytes, channel))?,
    };
    if d.values.len() != w as usize * h as usize {
        return Err(Error::Decode(format!(
            "decoded {} samples for a {w}×{h} image",
            d.values.len()
        )));
    }
    let info = InputInfo {
        width: w,
        height: h,
        format: fmt.name().into(),
        color: d.color.into(),
        bit_depth: d.bit_depth,
        float: d.float,
        content_hash: blake3::hash(bytes).to_hex().to_string(),
    };
    let map =
        HeightMap::from_samples(w as usize, h as usize, d.values, d.stored, nodata, d.georef)?;
    held.shrink_to(est.kept);
    Ok((map, info, held))
}

/// The hole mask for nodata value `nd` (NaN: NaN texels), `None` when no texel is a hole.
/// Normalised integer samples are compared as stored (value × `stored`, rounded).
fn mark_holes(values: &[f32], stored: f64, nd: f64) -> Result<Option<Vec<bool>>> {
    let holes: Vec<bool> = if nd.is_nan() {
        values.iter().map(|v| v.is_nan()).collect()
    } else if stored != 1.0 {
        values.iter().map(|&v| (v as f64 * stored).round() == nd).collect()
    } else {
        let nd32 = nd as f32;
        values.iter().map(|&v| v == nd32 || v as f64 == nd).collect()
    };
    if holes.iter().all(|&h| h) {
        return Err(Error::InvalidInput(format!(
            "every texel is nodata ({nd}): the map has no height left to bake"
        )));
    }
    Ok(holes.iter().any(|&h| h).then_some(holes))
}

/// The value the holes of a map whose other texels span `lo..=hi` are filled with:
/// [`HOLE_DEPTH`] map height ranges (at least 1) below the lowest.
pub fn hole_fill(lo: f32, hi: f32) -> f32 {
    lo - HOLE_DEPTH * (hi - lo).max(1.0)
}

/// Checks the texels that are not holes, and fills the holes with `fill`, or [`hole_fill`] of
/// the others' range when `None` (see the module docs).
fn fill_holes(values: &mut [f32], holes: &[bool], width: usize, fill: Option<f32>) -> Result<()> {
    let mut lo = f32::INFINITY;
    let mut hi = f32::NEG_INFINITY;
    for (k, (&v, &hole)) in values.iter().zip(holes).enumerate() {
        if hole {
            continue;
        }
        if !v.is_finite() || v.abs() > MAX_ABS_HEIGHT {
            return Err(bad_texel_error(k, width, v));
        }
        lo = lo.min(v);
        hi = hi.max(v);
    }
    let fill = fill.unwrap_or_else(|| hole_fill(lo, hi));
    for (v, &hole) in values.iter_mut().zip(holes) {
        if hole {
            *v = fill;
        }
    }
    Ok(())
}

fn decode_png(bytes: &[u8], channel: Channel, limits: &Limits, max_alloc: u64) -> Result<Decoded> {
    let mut reader = image::ImageReader::with_format(Cursor::new(bytes), image::ImageFormat::Png);
    let mut il = image::Limits::default();
    il.max_image_width = Some(limits.max_dim);
    il.max_image_height = Some(limits.max_dim);
    il.max_alloc = Some(max_alloc);
    reader.limits(il);
    let img = reader.decode().map_err(image_error)?;
    Ok(extract(&img, channel))
}

/// TIFF compressions the `tiff` crate decodes here (its default features).
const TIFF_COMPRESSIONS: &[u16] = &[1, 2, 3, 4, 5, 6, 7, 8, 32773, 32946];

/// The name of a TIFF compression code, for a refusal that says which one it was.
fn compression_name(c: u16) -> String {
    match c {
        34712 => "JPEG 2000 (34712)".into(),
        34887 => "LERC (34887)".into(),
        34925 => "LZMA (34925)".into(),
        50000 => "ZSTD (50000)".into(),
        50001 => "WebP (50001)".into(),
        50002 => "JPEG XL (50002)".into(),
        32809 => "ThunderScan (32809)".into(),
        other => format!("code {other}"),
    }
}

/// TIFF through the `tiff` crate directly: `image` has no gray-f32 type, and 32-bit float gray
/// is exactly what terrain tools export. Signed integers are used as they are (DEM convention),
/// and a georeferenced DEM keeps every sample type as it is (heights in metres).
///
/// Read strip by strip (or one row of tiles at a time) by [`stream`]'s band reader, each band
/// appended to the heights as it is converted: the decode holds the heights and one chunk,
/// not the whole image's raw samples besides them (a float TIFF peaked at twice its decoded
/// size when read whole). The values are the whole image's, converted by the same
/// [`tiff_values`].
fn decode_tiff(bytes: &[u8], channel: Channel, limits: &Limits, max_alloc: u64) -> Result<Decoded> {
    let (mut rows, georef) = stream::TiffRows::open_with(Cursor::new(bytes), limits, max_alloc)?;
    rows.channel = channel;
    let texels = rows.width * rows.height;
    let mut values: Vec<f32> = Vec::new();
    let mut kind = None;
    loop {
        let mut band = Vec::new();
        let (n, k) = rows.band(&mut band)?;
        if n == 0 {
            break;
        }
        kind = kind.or(k);
        if values.len() + band.len() > texels {
            return Err(Error::Decode(format!(
                "the TIFF holds more than the {texels} samples of its {}×{} image",
                rows.width, rows.height
            )));
        }
        if values.is_empty() && band.len() == texels {
            // One strip (or one row of tiles) is the whole image: it is the heights.
            values = band;
        } else {
            values.reserve_exact(texels - values.len());
            values.extend_from_slice(&band);
        }
    }
    let (bit_depth, float, stored) =
        kind.ok_or_else(|| Error::Decode("the TIFF holds no image data".into()))?;
    Ok(Decoded { values, color: rows.meta.color, bit_depth, float, stored, georef })
}

/// What a TIFF's header says about its samples (shared by the whole decode and the streamed
/// one in [`stream`], so both read a file the same way).
struct TiffMeta {
    georef: Option<georef::Georef>,
    /// A georeferenced DEM: every sample type used as it is.
    dem: bool,
    /// Samples per texel.
    n: usize,
    color: &'static str,
    ct: tiff::ColorType,
}

/// Checks the compression and colour type of the current image of `dec` and reads its
/// georeferencing.
fn tiff_meta<R: std::io::Read + std::io::Seek>(
    dec: &mut tiff::decoder::Decoder<R>,
) -> Result<TiffMeta> {
    use tiff::ColorType as C;
    let compression = dec
        .find_tag_unsigned::<u16>(tiff::tags::Tag::Compression)
        .map_err(tiff_error)?
        .unwrap_or(1);
    if !TIFF_COMPRESSIONS.contains(&compression) {
        return Err(Error::Unsupported(format!(
            "TIFF compression {} is not supported; rewrite the file with DEFLATE or LZW \
             (`gdal_translate -co COMPRESS=DEFLATE in.tif out.tif`)",
            compression_name(compression)
        )));
    }
    let georef = georef::Georef::read(dec)?;
    let dem = georef.as_ref().is_some_and(|g| g.is_dem());
    let ct = dec.colortype().map_err(tiff_error)?;
    let (n, color) = match ct {
        C::Gray(_) => (1, "gray"),
        C::GrayA(_) | C::Multiband { num_samples: 2, .. } => (2, "gray_alpha"),
        C::RGB(_) => (3, "rgb"),
        C::RGBA(_) => (4, "rgba"),
        other => {
            return Err(Error::Unsupported(format!(
                "TIFF colour type {other:?}; use gray, gray+alpha, RGB or RGBA"
            )))
        }
    };
    Ok(TiffMeta { georef, dem, n, color, ct })
}

/// The heights of decoded TIFF samples `img` (a whole image, or a strip or tile of one), with
/// `channel` picked: (values, bit depth, float, stored scale).
fn tiff_values(
    img: &tiff::decoder::DecodingResult,
    meta: &TiffMeta,
    channel: Channel,
) -> Result<(Vec<f32>, u8, bool, f64)> {
    use tiff::decoder::DecodingResult as R;
    let (dem, n) = (meta.dem, meta.n);
    let (s8, s16): (f64, f64) = if dem { (1.0, 1.0) } else { (255.0, 65535.0) };
    let n8 = |v: u8| if dem { v as f32 } else { v as f32 / 255.0 };
    let n16 = |v: u16| (v as f64 / s16) as f32;
    let id = |v: f32| v;
    // A DEM's samples are bands of heights, not colours: one is read, by `band` (SPEC §2).
    let band = if dem && n > 1 { Some(dem_band(n, meta.color, channel)?) } else { None };
    Ok(match img {
        R::U8(b) => (take(b, n, channel, band, n8), 8, false, s8),
        R::U16(b) => (take(b, n, channel, band, n16), 16, false, s16),
        R::I8(b) => (take(b, n, channel, band, |v: i8| v as f32), 8, false, 1.0),
        R::I16(b) => (take(b, n, channel, band, |v: i16| v as f32), 16, false, 1.0),
        R::I32(b) => (take(b, n, channel, band, |v: i32| v as f32), 32, false, 1.0),
        R::U32(b) if dem => (take(b, n, channel, band, |v: u32| v as f32), 32, false, 1.0),
        R::F32(b) => (take(b, n, channel, band, id), 32, true, 1.0),
        R::F64(b) => (take(b, n, channel, band, |v: f64| v as f32), 64, true, 1.0),
        _ => {
            return Err(Error::Unsupported(format!(
                "TIFF sample type of a {}-bit {} image; use 8/16-bit unsigned, \
                 8/16/32-bit signed integer or 32/64-bit float",
                meta.ct.bit_depth(),
                meta.color
            )))
        }
    })
}

/// OpenEXR through the `exr` crate directly: `image`'s decoder insists on R, G and B channels,
/// while height maps are usually a single `Y` (or arbitrarily named) channel.
fn decode_exr(bytes: &[u8], channel: Channel) -> Result<Decoded> {
    use exr::prelude::traits::*;
    use exr::prelude::{read, AnyChannel, FlatSamples};
    let img = read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .first_valid_layer()
        .all_attributes()
        .from_buffered(Cursor::new(bytes))
        .map_err(exr_error)?;
    let list = &img.layer_data.channel_data.list;
    let find = |name: &str| list.iter().find(|c| c.name == *name);
    let to_f32 = |c: &AnyChannel<FlatSamples>| -> Result<Vec<f32>> {
        match &c.sample_data {
            FlatSamples::F16(v) => Ok(v.iter().map(|x| x.to_f32()).collect()),
            FlatSamples::F32(v) => Ok(v.clone()),
            FlatSamples::U32(_) => Err(Error::Unsupported(format!(
                "OpenEXR channel `{}` holds 32-bit integers; heights must be half or float",
                c.name
            ))),
        }
    };
    // Half-float channels report 16 bits, as the file stores them.
    let depth = |cs: &[&AnyChannel<FlatSamples>]| -> u8 {
        if cs.iter().all(|c| matches!(c.sample_data, FlatSamples::F16(_))) {
            16
        } else {
            32
        }
    };
    let (r, g, b, a) = (find("R"), find("G"), find("B"), find("A"));
    if let (Some(r), Some(g), Some(b)) = (r, g, b) {
        let bit_depth = depth(&[r, g, b]);
        let (r, g, b) = (to_f32(r)?, to_f32(g)?, to_f32(b)?);
        let a = a.map(to_f32).transpose()?;
        let color = if a.is_some() { "rgba" } else { "rgb" };
        let values = (0..r.len())
            .map(|k| {
                let alpha = a.as_ref().and_then(|a| a.get(k)).copied().unwrap_or(1.0);
                pick(
                    [
                        r[k],
                        g.get(k).copied().unwrap_or(0.0),
                        b.get(k).copied().unwrap_or(0.0),
                        alpha,
                    ],
                    channel,
                )
            })
            .collect();
        return Ok(Decoded { values, color, bit_depth, float: true, stored: 1.0, georef: None });
    }
    // A gray map: `Y`, or the only channel whatever its name.
    let gray = find("Y").or(if list.len() == 1 { list.first() } else { None });
    match gray {
        Some(y) => {
            let color = if a.is_some() && list.len() == 2 { "gray_alpha" } else { "gray" };
            Ok(Decoded {
                values: to_f32(y)?,
                color,
                bit_depth: depth(&[y]),
                float: true,
                stored: 1.0,
                georef: None,
            })
        }
        None => {
            let names: Vec<String> = list.iter().map(|c| c.name.to_string()).collect();
            Err(Error::Unsupported(format!(
                "OpenEXR channels [{}]; expected Y, R/G/B(/A) or a single channel",
                names.join(", ")
            )))
        }
    }
}

/// [`samples`], or sample `band` of each texel when one is picked.
fn take<T: Copy>(
    buf: &[T],
    n: usize,
    channel: Channel,
    band: Option<usize>,
    f: impl Fn(T) -> f32,
) -> Vec<f32> {
    match band {
        Some(i) => buf.iter().skip(i).step_by(n).map(|&v| f(v)).collect(),
        None => samples(buf, n, channel, f),
    }
}

/// The sample (0-based) a DEM with `n` bands per texel is read from: `band` N (which reaches
/// the decoder as channel r, g, b or a); without it a 422 naming `band`, as reading colour
/// channels of heights (luma, or band 1 of two) would bake something no band holds.
///
/// # Errors
/// [`Error::Param`] naming `band`.
fn dem_band(n: usize, color: &str, channel: Channel) -> Result<usize> {
    let i = match channel {
        Channel::R => 0,
        Channel::G => 1,
        Channel::B => 2,
        Channel::A => 3,
        Channel::Luma => {
            return Err(Error::param(
                "band",
                format!(
                    "the DEM has {n} bands per texel ({color}) and heights are read from one: \
                     give band=1..{n} (`--band`), or extract it (`gdal_translate -b 1 in.tif \
                     dem.tif`)"
                ),
            ))
        }
    };
    if i >= n {
        return Err(Error::param(
            "band",
            format!("band {} asked, but the DEM has {n} bands per texel", i + 1),
        ));
    }
    Ok(i)
}

/// Picks the height from interleaved samples with `n` channels per texel (1 gray, 2 gray+alpha,
/// 3 RGB, 4 RGBA), after normalising each sample with `f`.
fn samples<T: Copy>(buf: &[T], n: usize, channel: Channel, f: impl Fn(T) -> f32) -> Vec<f32> {
    match n {
        1 | 2 => buf.iter().step_by(n).map(|&v| f(v)).collect(),
        _ => buf
            .chunks_exact(n)
            .map(|p| {
                let px = [f(p[0]), f(p[1]), f(p[2]), if n == 4 { f(p[3]) } else { 1.0 }];
                pick(px, channel)
            })
            .collect(),
    }
}

#[inline]
fn pick(px: [f32; 4], channel: Channel) -> f32 {
    match channel {
        Channel::R => px[0],
        Channel::G => px[1],
        Channel::B => px[2],
        Channel::A => px[3],
        Channel::Luma => {
            (0.2126 * px[0] as f64 + 0.7152 * px[1] as f64 + 0.0722 * px[2] as f64) as f32
        }
    }
}

fn extract(img: &image::DynamicImage, channel: Channel) -> Decoded {
    use image::DynamicImage as D;
    let n8 = |v: u8| v as f32 / 255.0;
    let n16 = |v: u16| (v as f64 / 65535.0) as f32;
    let id = |v: f32| v;
    let d = |values, color, bit_depth: u8, float| Decoded {
        values,
        color,
        bit_depth,
        float,
        stored: match (float, bit_depth) {
            (false, 8) => 255.0,
            (false, _) => 65535.0,
            _ => 1.0,
        },
        georef: None,
    };
    match img {
        D::ImageLuma8(b) => d(samples(b.as_raw(), 1, channel, n8), "gray", 8, false),
        D::ImageLumaA8(b) => d(samples(b.as_raw(), 2, channel, n8), "gray_alpha", 8, false),
        D::ImageRgb8(b) => d(samples(b.as_raw(), 3, channel, n8), "rgb", 8, false),
        D::ImageRgba8(b) => d(samples(b.as_raw(), 4, channel, n8), "rgba", 8, false),
        D::ImageLuma16(b) => d(samples(b.as_raw(), 1, channel, n16), "gray", 16, false),
        D::ImageLumaA16(b) => d(samples(b.as_raw(), 2, channel, n16), "gray_alpha", 16, false),
        D::ImageRgb16(b) => d(samples(b.as_raw(), 3, channel, n16), "rgb", 16, false),
        D::ImageRgba16(b) => d(samples(b.as_raw(), 4, channel, n16), "rgba", 16, false),
        D::ImageRgb32F(b) => d(samples(b.as_raw(), 3, channel, id), "rgb", 32, true),
        D::ImageRgba32F(b) => d(samples(b.as_raw(), 4, channel, id), "rgba", 32, true),
        other => {
            let b = other.to_rgba32f();
            d(samples(b.as_raw(), 4, channel, id), "rgba", 32, true)
        }
    }
}
