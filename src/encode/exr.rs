//! OpenEXR writer: one RGBA image of a horizon layer, in float (f32) or half (f16) samples,
//! uncompressed, written directly (see [`encode_rgba_as`]; the `exr` crate reads them back in
//! the tests).
//!
//! No compression pays for itself on horizon layers. Measured on both layers of a 2048² bake
//! (test profile, this 2-core machine, bake of the f32 layers 0.94 s): float ZIP16 27.0 s for
//! 133.1 MB against 134.3 MB raw (sin α has noisy low mantissa bits), float RLE 3.2 s for no
//! gain, float uncompressed 0.84 s; half ZIP16 20.7 s for 58.7 MB against 67.2 MB raw, half PIZ
//! 12.9 s for 58.5 MB, half RLE 0.82 s for no gain, half uncompressed 0.59 s. So both are written
//! uncompressed (float reads back bit for bit), and `half` is the way to halve the size: 10
//! mantissa bits are plenty for sin α in [0, 1] shown on 8- or 10-bit displays.

use crate::error::{Error, Result};
use exr::prelude::f16;

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
/// An uncompressed scanline file is a header, a table of chunk offsets and one chunk per row
/// (its y, its byte count, then each channel's row of samples, channels in name order A, B, G,
/// R), so it is written here directly, rows in parallel, into one buffer of the final size. The
/// `exr` crate's writer (which reads the tests' files back) went through a per-pixel closure
/// and a block pipeline: 0.84 s for both float layers of a 2048² bake, about the bake's own
/// time; this is a transposition at memory speed.
///
/// # Errors
/// [`Error::Internal`] on a size mismatch or a size the format cannot describe.
pub fn encode_rgba_as(
    width: usize,
    height: usize,
    data: &[f32],
    precision: ExrPrecision,
) -> Result<Vec<u8>> {
    encode_channels(width, height, 4, data, precision)
}

/// The channel names of an image of `channels` components per pixel, in the components'
/// order: Y (grey), R G B, or R G B A.
fn channel_names(channels: usize) -> Option<&'static [&'static str]> {
    match channels {
        1 => Some(&["Y"]),
        3 => Some(&["R", "G", "B"]),
        4 => Some(&["R", "G", "B", "A"]),
        _ => None,
    }
}

/// Encodes `width · height · channels` f32 samples (1: Y, 3: RGB, 4: RGBA, interleaved,
/// row-major from the top row) as OpenEXR in `precision`, as [`encode_rgba_as`] writes RGBA.
///
/// # Errors
/// [`Error::Internal`] on a size mismatch, another channel count or a size the format cannot
/// describe.
pub fn encode_channels(
    width: usize,
    height: usize,
    channels: usize,
    data: &[f32],
    precision: ExrPrecision,
) -> Result<Vec<u8>> {
    use rayon::prelude::*;
    let Some(names) = channel_names(channels) else {
        return Err(Error::Internal(format!("exr: {channels} channels")));
    };
    if width == 0 || height == 0 || data.len() != width * height * channels {
        return Err(Error::Internal("exr: buffer size mismatch".into()));
    }
    // The file lists channels by name (A, B, G, R; or Y), each row's planes in that order.
    let mut order: Vec<(&str, usize)> = names.iter().copied().zip(0..).collect();
    order.sort_by_key(|&(n, _)| n);
    let sample = match precision {
        ExrPrecision::Half => 2,
        ExrPrecision::Float => 4,
    };
    let row_bytes = width * channels * sample;
    let (Ok(w), Ok(h), Ok(row_len)) =
        (i32::try_from(width), i32::try_from(height), i32::try_from(row_bytes))
    else {
        return Err(Error::Internal(format!("exr: {width}×{height} is too large")));
    };
    let sorted: Vec<&str> = order.iter().map(|&(n, _)| n).collect();
    let header = scanline_header(w, h, &sorted, precision);
    let chunk = 8 + row_bytes;
    let first = header.len() + 8 * height;
    let mut out = vec![0u8; first + chunk * height];
    out[..header.len()].copy_from_slice(&header);
    for (y, slot) in out[header.len()..first].chunks_exact_mut(8).enumerate() {
        slot.copy_from_slice(&((first + y * chunk) as u64).to_le_bytes());
    }
    out[first..].par_chunks_mut(chunk).zip(data.par_chunks(width * channels)).enumerate().for_each(
        |(y, (dst, src))| {
            dst[..4].copy_from_slice(&(y as i32).to_le_bytes());
            dst[4..8].copy_from_slice(&row_len.to_le_bytes());
            let planes = &mut dst[8..];
            // Channels in name order (RGBA: A, B, G, R = components 3, 2, 1, 0).
            for (plane, &(_, c)) in planes.chunks_exact_mut(width * sample).zip(&order) {
                match precision {
                    ExrPrecision::Float => {
                        for (d, px) in plane.chunks_exact_mut(4).zip(src.chunks_exact(channels)) {
                            d.copy_from_slice(&px[c].to_le_bytes());
                        }
                    }
                    ExrPrecision::Half => {
                        for (d, px) in plane.chunks_exact_mut(2).zip(src.chunks_exact(channels)) {
                            d.copy_from_slice(&f16::from_f32(px[c]).to_bits().to_le_bytes());
                        }
                    }
                }
            }
        },
    );
    Ok(out)
}

/// The magic number, version 2 (single-part scanline), and the required attributes of a
/// `width × height` image of the channels `names` (sorted) without compression, increasing y.
fn scanline_header(width: i32, height: i32, names: &[&str], precision: ExrPrecision) -> Vec<u8> {
    fn attr(out: &mut Vec<u8>, name: &str, kind: &str, value: &[u8]) {
        out.extend_from_slice(name.as_bytes());
        out.push(0);
        out.extend_from_slice(kind.as_bytes());
        out.push(0);
        out.extend_from_slice(&(value.len() as i32).to_le_bytes());
        out.extend_from_slice(value);
    }
    let pixel_type: i32 = match precision {
        ExrPrecision::Half => 1,
        ExrPrecision::Float => 2,
    };
    let mut chlist = Vec::new();
    for name in names {
        chlist.extend_from_slice(name.as_bytes());
        chlist.push(0);
        chlist.extend_from_slice(&pixel_type.to_le_bytes());
        chlist.extend_from_slice(&[0, 0, 0, 0]); // pLinear, reserved
        chlist.extend_from_slice(&1i32.to_le_bytes()); // x sampling
        chlist.extend_from_slice(&1i32.to_le_bytes()); // y sampling
    }
    chlist.push(0);
    let mut window = Vec::new();
    for v in [0, 0, width - 1, height - 1] {
        window.extend_from_slice(&v.to_le_bytes());
    }
    let mut out = vec![0x76, 0x2f, 0x31, 0x01, 2, 0, 0, 0];
    attr(&mut out, "channels", "chlist", &chlist);
    attr(&mut out, "compression", "compression", &[0]);
    attr(&mut out, "dataWindow", "box2i", &window);
    attr(&mut out, "displayWindow", "box2i", &window);
    attr(&mut out, "lineOrder", "lineOrder", &[0]);
    attr(&mut out, "pixelAspectRatio", "float", &1f32.to_le_bytes());
    let mut centre = 0f32.to_le_bytes().to_vec();
    centre.extend_from_slice(&0f32.to_le_bytes());
    attr(&mut out, "screenWindowCenter", "v2f", &centre);
    attr(&mut out, "screenWindowWidth", "float", &1f32.to_le_bytes());
    out.push(0);
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use exr::prelude::*;
    use std::io::Cursor;

    #[test]
    fn odd_sizes_and_half_read_back_with_the_exr_crate() {
        for (w, h) in [(1usize, 1usize), (7, 3), (130, 67)] {
            let data: Vec<f32> =
                (0..w * h * 4).map(|k| ((k * 7919) % 1000) as f32 / 997.0).collect();
            let img = read_any(&encode_rgba_as(w, h, &data, ExrPrecision::Float).unwrap());
            assert_eq!(img.len(), 4);
            for (name, c) in [("R", 0), ("G", 1), ("B", 2), ("A", 3)] {
                let FlatSamples::F32(got) = &img.iter().find(|(n, _)| n == name).unwrap().1 else {
                    panic!("{name} is not f32")
                };
                let want: Vec<f32> = data.chunks_exact(4).map(|p| p[c]).collect();
                assert_eq!(got, &want, "{w}×{h} {name}");
            }
            let img = read_any(&encode_rgba_as(w, h, &data, ExrPrecision::Half).unwrap());
            for (name, c) in [("R", 0), ("G", 1), ("B", 2), ("A", 3)] {
                let FlatSamples::F16(got) = &img.iter().find(|(n, _)| n == name).unwrap().1 else {
                    panic!("{name} is not f16")
                };
                let want: Vec<f16> = data.chunks_exact(4).map(|p| f16::from_f32(p[c])).collect();
                assert_eq!(got, &want, "{w}×{h} half {name}");
            }
        }
    }

    /// Grey and RGB images (the surface maps, SPEC §3.8) read back with their channels' names
    /// and values; other counts are refused.
    #[test]
    fn grey_and_rgb_read_back_with_the_exr_crate() {
        let (w, h) = (5usize, 3usize);
        for (ch, names) in [(1usize, &["Y"][..]), (3, &["R", "G", "B"][..])] {
            let data: Vec<f32> = (0..w * h * ch).map(|k| k as f32 / 7.0).collect();
            let img = read_any(&encode_channels(w, h, ch, &data, ExrPrecision::Float).unwrap());
            assert_eq!(img.len(), ch);
            for (c, name) in names.iter().enumerate() {
                let FlatSamples::F32(got) = &img.iter().find(|(n, _)| n == name).unwrap().1 else {
                    panic!("{name} is not f32")
                };
                let want: Vec<f32> = data.chunks_exact(ch).map(|p| p[c]).collect();
                assert_eq!(got, &want, "{ch} channels, {name}");
            }
        }
        assert!(encode_channels(w, h, 2, &vec![0.0; w * h * 2], ExrPrecision::Float).is_err());
        assert!(encode_channels(w, h, 3, &vec![0.0; w * h], ExrPrecision::Float).is_err());
    }

    fn read_any(bytes: &[u8]) -> Vec<(String, FlatSamples)> {
        let img = read()
            .no_deep_data()
            .largest_resolution_level()
            .all_channels()
            .first_valid_layer()
            .all_attributes()
            .from_buffered(Cursor::new(bytes))
            .unwrap();
        img.layer_data
            .channel_data
            .list
            .into_iter()
            .map(|c| (c.name.to_string(), c.sample_data))
            .collect()
    }

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
