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

fn write(
    width: usize,
    height: usize,
    color: PngColor,
    depth: png::BitDepth,
    data: &[u8],
) -> Result<Vec<u8>> {
    let mut out = Vec::with_capacity(data.len() / 2 + 1024);
    {
        let mut enc = png::Encoder::new(&mut out, width as u32, height as u32);
        enc.set_color(color.png());
        enc.set_depth(depth);
        enc.set_compression(png::Compression::Fast);
        let mut w = enc.write_header().map_err(|e| Error::Internal(format!("png header: {e}")))?;
        w.write_image_data(data).map_err(|e| Error::Internal(format!("png data: {e}")))?;
        w.finish().map_err(|e| Error::Internal(format!("png finish: {e}")))?;
    }
    Ok(out)
}

/// Encodes 8-bit samples (`width · height · channels` of them) as PNG.
///
/// # Errors
/// [`Error::Internal`] on a size mismatch or an encoder failure.
pub fn encode8(width: usize, height: usize, color: PngColor, data: &[u8]) -> Result<Vec<u8>> {
    if data.len() != width * height * color.channels() {
        return Err(Error::Internal("png8: buffer size mismatch".into()));
    }
    write(width, height, color, png::BitDepth::Eight, data)
}

/// Encodes 16-bit samples as PNG (big-endian on disk).
///
/// # Errors
/// [`Error::Internal`] on a size mismatch or an encoder failure.
pub fn encode16(width: usize, height: usize, color: PngColor, data: &[u16]) -> Result<Vec<u8>> {
    if data.len() != width * height * color.channels() {
        return Err(Error::Internal("png16: buffer size mismatch".into()));
    }
    let be: Vec<u8> = data.iter().flat_map(|v| v.to_be_bytes()).collect();
    write(width, height, color, png::BitDepth::Sixteen, &be)
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
}
