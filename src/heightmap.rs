//! Decoding an input image into a height map (SPEC §2 "Heights").
//!
//! Inputs come from untrusted uploads, so the order of operations matters: sniff the format from
//! the magic bytes, read the dimensions from the header, check them against [`Limits`], and only
//! then let a decoder allocate pixel buffers. Integer images are normalised to [0, 1] (v/255,
//! v/65535); float images are used as they are; RGB(A) images pick a channel or luma on the
//! stored (non-linearised) values. Non-finite heights are rejected.

use crate::error::{Error, LimitError, Result};
use crate::params::Channel;
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
}

impl Default for Limits {
    fn default() -> Self {
        Limits { max_dim: 16384, max_texels: 8192 * 8192, max_bytes: 512 * 1024 * 1024 }
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
}

impl HeightMap {
    /// Heights in texel units: value × `height_scale`.
    pub fn scaled(&self, height_scale: f64) -> Vec<f32> {
        self.values.iter().map(|&v| (v as f64 * height_scale) as f32).collect()
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
        Ok(HeightMap { width, height, values })
    }
}

fn check_finite(values: &[f32], width: usize) -> Result<()> {
    if let Some(k) = values.iter().position(|v| !v.is_finite()) {
        return Err(Error::InvalidInput(format!(
            "height at column {}, row {} is {} (heights must be finite)",
            k % width.max(1),
            k / width.max(1),
            values[k]
        )));
    }
    Ok(())
}

/// The input formats we read, sniffed from magic bytes (never from a name or a header).
fn sniff(bytes: &[u8]) -> Result<image::ImageFormat> {
    if bytes.is_empty() {
        return Err(Error::Unsupported("the input is empty".into()));
    }
    let fmt = image::guess_format(bytes).map_err(|_| {
        Error::Unsupported("not a PNG, TIFF or OpenEXR image (unrecognised signature)".into())
    })?;
    match fmt {
        image::ImageFormat::Png | image::ImageFormat::Tiff | image::ImageFormat::OpenExr => Ok(fmt),
        other => Err(Error::Unsupported(format!(
            "{} images are not supported; use PNG, TIFF or OpenEXR",
            other.extensions_str().first().copied().unwrap_or("this kind of").to_uppercase()
        ))),
    }
}

fn format_name(f: image::ImageFormat) -> &'static str {
    match f {
        image::ImageFormat::Png => "png",
        image::ImageFormat::Tiff => "tiff",
        _ => "exr",
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
        other => Error::Decode(other.to_string()),
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

/// Reads only the header: format and dimensions, checked against `limits`.
///
/// # Errors
/// As [`decode`], without touching pixel data.
pub fn probe(bytes: &[u8], limits: &Limits) -> Result<(image::ImageFormat, u32, u32)> {
    if bytes.len() as u64 > limits.max_bytes {
        return Err(Error::Limits(LimitError::Bytes {
            bytes: bytes.len() as u64,
            max_bytes: limits.max_bytes,
        }));
    }
    let fmt = sniff(bytes)?;
    let reader = image::ImageReader::with_format(Cursor::new(bytes), fmt);
    let (w, h) = reader.into_dimensions().map_err(image_error)?;
    check_dimensions(w as u64, h as u64, limits)?;
    Ok((fmt, w, h))
}

/// Decodes `bytes` into a height map, picking `channel` from colour images.
///
/// # Errors
/// [`Error::Unsupported`] (not an image we read), [`Error::Limits`] (too large, checked from the
/// header before decoding), [`Error::Decode`] (broken data), [`Error::InvalidInput`] (0×0,
/// non-finite heights).
pub fn decode(bytes: &[u8], channel: Channel, limits: &Limits) -> Result<(HeightMap, InputInfo)> {
    let (fmt, w, h) = probe(bytes, limits)?;
    let mut reader = image::ImageReader::with_format(Cursor::new(bytes), fmt);
    let mut il = image::Limits::default();
    il.max_image_width = Some(limits.max_dim);
    il.max_image_height = Some(limits.max_dim);
    // Room for the decoded image at up to 4 × f32 per texel plus the decoder's own buffers.
    il.max_alloc = Some(limits.max_texels.saturating_mul(16).saturating_add(64 << 20));
    reader.limits(il);
    let img = reader.decode().map_err(image_error)?;
    let (values, color, bit_depth, float) = extract(&img, channel);
    let info = InputInfo {
        width: w,
        height: h,
        format: format_name(fmt).into(),
        color: color.into(),
        bit_depth,
        float,
        content_hash: blake3::hash(bytes).to_hex().to_string(),
    };
    check_finite(&values, w as usize)?;
    Ok((HeightMap { width: w as usize, height: h as usize, values }, info))
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

fn extract(img: &image::DynamicImage, channel: Channel) -> (Vec<f32>, &'static str, u8, bool) {
    use image::DynamicImage as D;
    fn gray<T: Copy>(buf: &[T], step: usize, f: impl Fn(T) -> f32) -> Vec<f32> {
        buf.iter().step_by(step).map(|&v| f(v)).collect()
    }
    fn color<T: Copy>(buf: &[T], n: usize, channel: Channel, f: impl Fn(T) -> f32) -> Vec<f32> {
        buf.chunks_exact(n)
            .map(|p| {
                let px = [f(p[0]), f(p[1]), f(p[2]), if n == 4 { f(p[3]) } else { 1.0 }];
                pick(px, channel)
            })
            .collect()
    }
    let n8 = |v: u8| v as f32 / 255.0;
    let n16 = |v: u16| (v as f64 / 65535.0) as f32;
    let id = |v: f32| v;
    match img {
        D::ImageLuma8(b) => (gray(b.as_raw(), 1, n8), "gray", 8, false),
        D::ImageLumaA8(b) => (gray(b.as_raw(), 2, n8), "gray_alpha", 8, false),
        D::ImageRgb8(b) => (color(b.as_raw(), 3, channel, n8), "rgb", 8, false),
        D::ImageRgba8(b) => (color(b.as_raw(), 4, channel, n8), "rgba", 8, false),
        D::ImageLuma16(b) => (gray(b.as_raw(), 1, n16), "gray", 16, false),
        D::ImageLumaA16(b) => (gray(b.as_raw(), 2, n16), "gray_alpha", 16, false),
        D::ImageRgb16(b) => (color(b.as_raw(), 3, channel, n16), "rgb", 16, false),
        D::ImageRgba16(b) => (color(b.as_raw(), 4, channel, n16), "rgba", 16, false),
        D::ImageRgb32F(b) => (color(b.as_raw(), 3, channel, id), "rgb", 32, true),
        D::ImageRgba32F(b) => (color(b.as_raw(), 4, channel, id), "rgba", 32, true),
        other => {
            let b = other.to_rgba32f();
            (color(b.as_raw(), 4, channel, id), "rgba", 32, true)
        }
    }
}
