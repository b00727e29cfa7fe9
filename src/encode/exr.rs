//! OpenEXR writer: one RGBA image of a horizon layer, via the `exr` crate, in float (f32) or
//! half (f16) samples, uncompressed.
//!
//! No compression pays for itself on horizon layers. Measured on both layers of a 2048² bake
//! (test profile, this 2-core machine, bake of the f32 layers 0.94 s): float ZIP16 27.0 s for
//! 133.1 MB against 134.3 MB raw (sin α has noisy low mantissa bits), float RLE 3.2 s for no
//! gain, float uncompressed 0.84 s; half ZIP16 20.7 s for 58.7 MB against 67.2 MB raw, half PIZ
//! 12.9 s for 58.5 MB, half RLE 0.82 s for no gain, half uncompressed 0.59 s. So both are written
//! uncompressed (float reads back bit for bit), and `half` is the way to halve the size: 10
//! mantissa bits are plenty for sin α in [0, 1] shown on 8- or 10-bit displays.

use crate::error::{Error, Result};
use exr::prelude::*;
use std::io::Cursor;

/// Sample type of an EXR result.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum ExrPrecision {
    /// 16-bit half floats: half the size, ~3 significant decimal digits.
    Half,
    /// 32-bit floats, bit-exact (the default).
    #[default]
    Float,
}

impl ExrPrecision {
    /// Parses `half` or `float`.
    ///
    /// # Errors
    /// [`Error::Param`] naming `field`.
    pub fn parse(field: &str, value: &str) -> Result<Self> {
        crate::params::parse_enum(
            field,
            value,
            &[("half", ExrPrecision::Half), ("float", ExrPrecision::Float)],
        )
    }

    /// The API spelling.
    pub fn as_str(self) -> &'static str {
        match self {
            ExrPrecision::Half => "half",
            ExrPrecision::Float => "float",
        }
    }
}

/// Encodes `width · height · 4` f32 samples (RGBA, row-major from the top row) as OpenEXR with
/// float R, G, B, A channels, uncompressed (see the module documentation for why).
///
/// # Errors
/// [`Error::Internal`] on a size mismatch or an encoder failure.
pub fn encode_rgba(width: usize, height: usize, data: &[f32]) -> Result<Vec<u8>> {
    encode_rgba_as(width, height, data, ExrPrecision::Float)
}

/// Encodes `width · height · 4` f32 samples (RGBA, row-major from the top row) as OpenEXR in
/// `precision`.
///
/// # Errors
/// [`Error::Internal`] on a size mismatch or an encoder failure.
pub fn encode_rgba_as(
    width: usize,
    height: usize,
    data: &[f32],
    precision: ExrPrecision,
) -> Result<Vec<u8>> {
    if width == 0 || height == 0 || data.len() != width * height * 4 {
        return Err(Error::Internal("exr: buffer size mismatch".into()));
    }
    let mut out = Cursor::new(Vec::new());
    let written = match precision {
        ExrPrecision::Float => {
            let channels = SpecificChannels::rgba(|p: Vec2<usize>| {
                let k = (p.y() * width + p.x()) * 4;
                (data[k], data[k + 1], data[k + 2], data[k + 3])
            });
            let layer = Layer::new(
                (width, height),
                LayerAttributes::default(),
                exr::prelude::Encoding::UNCOMPRESSED,
                channels,
            );
            Image::from_layer(layer).write().to_buffered(&mut out)
        }
        ExrPrecision::Half => {
            let channels = SpecificChannels::rgba(|p: Vec2<usize>| {
                let k = (p.y() * width + p.x()) * 4;
                let h = f16::from_f32;
                (h(data[k]), h(data[k + 1]), h(data[k + 2]), h(data[k + 3]))
            });
            let layer = Layer::new(
                (width, height),
                LayerAttributes::default(),
                exr::prelude::Encoding::UNCOMPRESSED,
                channels,
            );
            Image::from_layer(layer).write().to_buffered(&mut out)
        }
    };
    written.map_err(|e| Error::Internal(format!("exr: {e}")))?;
    Ok(out.into_inner())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_bit_exact() {
        let (w, h) = (3, 2);
        let data: Vec<f32> = (0..w * h * 4).map(|k| k as f32 * 0.037 + 1e-7).collect();
        let bytes = encode_rgba(w, h, &data).unwrap();
        let img = read_first_rgba_layer_from_file_bytes(&bytes);
        assert_eq!(img, data);
        assert!(encode_rgba(3, 3, &data).is_err());
    }

    fn read_first_rgba_layer_from_file_bytes(bytes: &[u8]) -> Vec<f32> {
        let img = read()
            .no_deep_data()
            .largest_resolution_level()
            .rgba_channels(
                |res, _| vec![0f32; res.width() * res.height() * 4],
                |buf: &mut Vec<f32>, p: Vec2<usize>, (r, g, b, a): (f32, f32, f32, f32)| {
                    let k = (p.y() * 3 + p.x()) * 4;
                    buf[k..k + 4].copy_from_slice(&[r, g, b, a]);
                },
            )
            .first_valid_layer()
            .all_attributes()
            .from_buffered(Cursor::new(bytes))
            .unwrap();
        img.layer_data.channel_data.pixels
    }
}
