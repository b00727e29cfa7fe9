//! OpenEXR writer: one RGBA image of f32 samples (a horizon layer), via the `exr` crate,
//! losslessly compressed (ZIP) so the f32 values read back bit for bit.

use crate::error::{Error, Result};
use exr::prelude::*;
use std::io::Cursor;

/// Encodes `width · height · 4` f32 samples (RGBA, row-major from the top row) as OpenEXR with
/// float R, G, B, A channels.
///
/// # Errors
/// [`Error::Internal`] on a size mismatch or an encoder failure.
pub fn encode_rgba(width: usize, height: usize, data: &[f32]) -> Result<Vec<u8>> {
    if width == 0 || height == 0 || data.len() != width * height * 4 {
        return Err(Error::Internal("exr: buffer size mismatch".into()));
    }
    let channels = SpecificChannels::rgba(|p: Vec2<usize>| {
        let k = (p.y() * width + p.x()) * 4;
        (data[k], data[k + 1], data[k + 2], data[k + 3])
    });
    let layer = Layer::new(
        (width, height),
        LayerAttributes::default(),
        exr::prelude::Encoding::SMALL_LOSSLESS,
        channels,
    );
    let image = Image::from_layer(layer);
    let mut out = Cursor::new(Vec::new());
    image.write().to_buffered(&mut out).map_err(|e| Error::Internal(format!("exr: {e}")))?;
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
