//! KTX2 writer for RGBA and BC7/BC5 array textures and cube maps, with mip levels and Zstandard
//! supercompression (Khronos KTX 2.0 spec).
//!
//! No Rust crate both writes KTX2 and builds offline (NOTES.md), and the container is small, so
//! it is written here by hand: identifier, header, the level index, a basic data format descriptor
//! (DFD), the key/value data ([`key_values`]: `KTXorientation` and `KTXwriter`, which engines'
//! loaders and `ktx validate` read, and `horizon-bake`: the data's conventions as JSON, SPEC §8),
//! then the levels smallest first. `tests/encode/encode.rs` proves it by reading
//! every texel back with the independent `ktx2` crate and comparing the DFD with the one that
//! crate generates for the same format.
//!
//! Layout (all little-endian): 12-byte identifier, 9 × u32 header, the index (DFD and KVD offset
//! and length as u32, SGD offset and length as u64), the level index (offset, length,
//! uncompressed length as u64, level 0 first), the DFD, the KVD, then the level data, smallest
//! level first, each aligned to lcm(texel or block size, 4) (to 1 when supercompressed). One
//! image (a layer of `texture_layout=separate`) is a 2D texture, layerCount 0: libktx and
//! Godot's loader take layerCount 1 for an array.
//! Within the level, images follow in layer order, then face order (+X, −X, +Y, −Y, +Z, −Z),
//! each row-major from the top row.

use super::texture::{PixelFormat, Texture};
use super::{Shape, Texels};
use crate::error::Result;
use rayon::prelude::*;

/// The KTX2 file identifier «KTX 20»\r\n\x1A\n.
pub const IDENTIFIER: [u8; 12] =
    [0xAB, 0x4B, 0x54, 0x58, 0x20, 0x32, 0x30, 0xBB, 0x0D, 0x0A, 0x1A, 0x0A];

/// VkFormat values of the formats we write.
pub const VK_FORMAT_R8G8B8A8_UNORM: u32 = 37;
/// SNORM 8-bit RGBA (the cube map: 0 is exact).
pub const VK_FORMAT_R8G8B8A8_SNORM: u32 = 38;
/// UNORM 16-bit RGBA.
pub const VK_FORMAT_R16G16B16A16_UNORM: u32 = 91;
/// IEEE f32 RGBA.
pub const VK_FORMAT_R32G32B32A32_SFLOAT: u32 = 109;
/// BC5 (RG) blocks.
pub const VK_FORMAT_BC5_UNORM_BLOCK: u32 = 141;
/// BC7 blocks.
pub const VK_FORMAT_BC7_UNORM_BLOCK: u32 = 145;
/// supercompressionScheme of Zstandard.
pub const SUPERCOMPRESSION_ZSTD: u32 = 2;

/// The key/value data every file carries, sorted by key as KTX2 §3.11 requires (by bytes: the
/// upper-case `KTX` keys first): the data's orientation (rows from the top, texels left to
/// right: "rd", which three.js and engines read to decide whether to flip), who wrote it, and
/// under `horizon-bake` the `conventions` of the data (a JSON object: what the texels hold and
/// how to decode them, so a file read without its bake.json still says so). Each entry: its
/// byte length (u32), the key, NUL, the value with its NUL, padded to 4 bytes.
pub fn key_values(conventions: &str) -> Vec<u8> {
    let writer = format!("horizon-bake {}", env!("CARGO_PKG_VERSION"));
    let mut out = Vec::new();
    for (key, value) in
        [("KTXorientation", "rd"), ("KTXwriter", writer.as_str()), ("horizon-bake", conventions)]
    {
        let len = key.len() + 1 + value.len() + 1;
        out.extend((len as u32).to_le_bytes());
        out.extend(key.as_bytes());
        out.push(0);
        out.extend(value.as_bytes());
        out.push(0);
        out.resize(out.len().div_ceil(4) * 4, 0);
    }
    out
}

/// (vkFormat, typeSize, sample flags, lower, upper) of a pixel format.
fn describe(f: PixelFormat) -> (u32, u32, u8, u32, u32) {
    // Channel-type qualifier bits of a DFD sample: 0x80 float, 0x40 signed.
    match f {
        PixelFormat::Rgba8Unorm => (VK_FORMAT_R8G8B8A8_UNORM, 1, 0, 0, 255),
        PixelFormat::Rgba8Snorm => (VK_FORMAT_R8G8B8A8_SNORM, 1, 0x40, (-127i32) as u32, 127),
        PixelFormat::Rgba16Unorm => (VK_FORMAT_R16G16B16A16_UNORM, 2, 0, 0, 65535),
        PixelFormat::Rgba32Float => {
            (VK_FORMAT_R32G32B32A32_SFLOAT, 4, 0xC0, (-1.0f32).to_bits(), 1.0f32.to_bits())
        }
        PixelFormat::Bc5Unorm => (VK_FORMAT_BC5_UNORM_BLOCK, 1, 0, 0, u32::MAX),
        PixelFormat::Bc7Unorm => (VK_FORMAT_BC7_UNORM_BLOCK, 1, 0, 0, u32::MAX),
    }
}

/// A DFD sample: bitOffset, bitLength, channel id.
type Sample = (u32, u32, u8);

/// The DFD: its total size, then one basic block (BT.709 primaries, linear transfer, straight
/// alpha). Uncompressed: the RGBSDA model with four samples R, G, B, A. BC7: its model, 4×4
/// blocks of 16 bytes, one 128-bit sample; BC5: two 64-bit samples, red then green.
fn dfd(f: PixelFormat) -> Vec<u8> {
    let (_, type_size, flags, lower, upper) = describe(f);
    // (bitOffset, bitLength, channel id) of each sample.
    let (model, dims, bytes_plane, samples): (u8, [u8; 4], u32, Vec<Sample>) = match f {
        PixelFormat::Bc7Unorm => (134, [3, 3, 0, 0], 16, vec![(0, 128, 0)]),
        PixelFormat::Bc5Unorm => (132, [3, 3, 0, 0], 16, vec![(0, 64, 0), (64, 64, 1)]),
        _ => {
            let bits = type_size * 8;
            let s =
                [0u8, 1, 2, 15].into_iter().enumerate().map(|(k, c)| (k as u32 * bits, bits, c));
            (1, [0, 0, 0, 0], 4 * type_size, s.collect())
        }
    };
    let block_size = 24 + 16 * samples.len() as u32;
    let mut d = Vec::with_capacity(4 + block_size as usize);
    d.extend((4 + block_size).to_le_bytes());
    d.extend(0u32.to_le_bytes()); // vendorId 0 (Khronos), descriptorType 0 (basic)
    d.extend(2u16.to_le_bytes()); // versionNumber
    d.extend((block_size as u16).to_le_bytes());
    d.extend([model, 1, 1, 0]); // colorModel, primaries BT709, transfer linear, flags straight
    d.extend(dims); // texelBlockDimension0..3 (stored minus one)
    d.extend([bytes_plane as u8, 0, 0, 0, 0, 0, 0, 0]); // bytesPlane0..7
    for (offset, len, channel_id) in samples {
        d.extend((offset as u16).to_le_bytes()); // bitOffset
        d.push((len - 1) as u8); // bitLength − 1
        d.push(channel_id | flags);
        d.extend([0, 0, 0, 0]); // samplePosition0..3
        d.extend(lower.to_le_bytes());
        d.extend(upper.to_le_bytes());
    }
    d
}

/// Writes `t` as KTX2: `Shape::Array(n)` as layerCount = n (0 for one image: a 2D texture),
/// `Shape::Cube` as faceCount = 6
/// (layerCount 0); every level of `t`; with `zstd_level`, supercompressionScheme 2 (Zstandard),
/// each level compressed on its own as KTX-Software's `ktxTexture2_DeflateZstd` does (level
/// alignment then 1, the DFD unchanged, uncompressedByteLength the raw level size).
///
/// # Errors
/// [`crate::Error::Internal`] when the levels do not fit the texture's size, or zstd fails.
pub fn write(t: &Texture, zstd_level: Option<i32>, conventions: &str) -> Result<Vec<u8>> {
    t.check()?;
    let levels = t.levels.len();
    // Raw level data: images in layer/face order, each level on its own.
    let raw: Vec<Vec<u8>> = t.levels.iter().map(|l| l.concat()).collect();
    // Each level compressed on its own (independent: side by side on rayon).
    let compressed: Option<Vec<Vec<u8>>> = match zstd_level {
        None => None,
        Some(level) => Some(
            raw.par_iter()
                .map(|r| {
                    zstd::bulk::compress(r, level)
                        .map_err(|e| crate::Error::Internal(format!("zstd: {e}")))
                })
                .collect::<Result<Vec<_>>>()?,
        ),
    };
    let (stored, align): (Vec<&[u8]>, usize) = match &compressed {
        Some(c) => (c.iter().map(Vec::as_slice).collect(), 1),
        None => (raw.iter().map(Vec::as_slice).collect(), t.format.block_bytes()),
    };
    let lens: Vec<(usize, usize)> =
        stored.iter().zip(&raw).map(|(s, r)| (s.len(), r.len())).collect();
    let (mut out, offsets) = prefix(t, &lens, align, zstd_level.is_some(), conventions);
    for l in (0..levels).rev() {
        out.resize(offsets[l], 0);
        out.extend_from_slice(stored[l]);
    }
    Ok(out)
}

/// Everything of a KTX2 file before its level data, for `t`'s format, size, shape and level
/// count (`t.levels` is only counted), with levels of `lens[l]` = (stored, uncompressed) bytes
/// aligned to `align`, and the `horizon-bake` key's `conventions`: the bytes and each level's
/// offset. [`write`] appends the levels; the streamed writer of `encode::assemble` writes level
/// 0 band by band after the same bytes.
pub(crate) fn prefix(
    t: &Texture,
    lens: &[(usize, usize)],
    align: usize,
    zstd: bool,
    conventions: &str,
) -> (Vec<u8>, Vec<usize>) {
    let (vk_format, type_size, ..) = describe(t.format);
    let (layer_count, face_count) = match t.shape {
        // One image is a 2D texture, not an array of one (see the module doc).
        Shape::Array(1) => (0, 1u32),
        Shape::Array(n) => (n, 1u32),
        Shape::Cube => (0, 6),
    };
    let levels = lens.len();
    let dfd = dfd(t.format);
    let kvd = key_values(conventions);
    let header_len = 12 + 9 * 4 + 4 * 4 + 2 * 8;
    let dfd_offset = header_len + levels * 3 * 8;
    // The DFD's length is a multiple of 4, so the KVD that follows it is 4-aligned.
    let kvd_offset = dfd_offset + dfd.len();
    // Levels are stored smallest first (KTX2 §3.9), each aligned to lcm(block size, 4) when not
    // supercompressed (block sizes here are 4, 8 or 16: multiples of 4).
    let mut offsets = vec![0usize; levels];
    let mut end = kvd_offset + kvd.len();
    for l in (0..levels).rev() {
        end = end.div_ceil(align) * align;
        offsets[l] = end;
        end += lens[l].0;
    }
    let mut out = Vec::with_capacity(end);
    out.extend(IDENTIFIER);
    for v in [
        vk_format,
        type_size,
        t.width as u32,
        t.height as u32,
        0, // pixelDepth: 2D
        layer_count,
        face_count,
        levels as u32,
        if zstd { SUPERCOMPRESSION_ZSTD } else { 0 },
    ] {
        out.extend(v.to_le_bytes());
    }
    out.extend((dfd_offset as u32).to_le_bytes());
    out.extend((dfd.len() as u32).to_le_bytes());
    out.extend((kvd_offset as u32).to_le_bytes());
    out.extend((kvd.len() as u32).to_le_bytes());
    out.extend(0u64.to_le_bytes()); // sgdByteOffset
    out.extend(0u64.to_le_bytes()); // sgdByteLength
    for l in 0..levels {
        out.extend((offsets[l] as u64).to_le_bytes());
        out.extend((lens[l].0 as u64).to_le_bytes());
        out.extend((lens[l].1 as u64).to_le_bytes());
    }
    out.extend(&dfd);
    out.extend(&kvd);
    (out, offsets)
}

/// Encodes one single-level, uncompressed texture: `Shape::Array(n)` with `n` images, or
/// `Shape::Cube` with 6 faces. The vkFormat follows the sample type of `images`:
/// R8G8B8A8_UNORM, R8G8B8A8_SNORM, R16G16B16A16_UNORM or R32G32B32A32_SFLOAT. Its
/// `horizon-bake` key is `{}`: these texels carry no convention of ours.
///
/// # Errors
/// [`crate::Error::Internal`] when the images do not fit `width × height` RGBA or `shape`.
pub fn encode(width: usize, height: usize, shape: Shape, images: &[Texels<'_>]) -> Result<Vec<u8>> {
    write(&Texture::single(width, height, shape, images)?, None, "{}")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn header_fields_and_alignment() {
        let a = [0.25f32; 2 * 3 * 4];
        let b = [0.5f32; 2 * 3 * 4];
        let bytes =
            encode(2, 3, Shape::Array(2), &[Texels::Float32(&a), Texels::Float32(&b)]).unwrap();
        assert_eq!(&bytes[..12], &IDENTIFIER);
        let u32_at =
            |o: usize| u32::from_le_bytes([bytes[o], bytes[o + 1], bytes[o + 2], bytes[o + 3]]);
        assert_eq!(u32_at(12), VK_FORMAT_R32G32B32A32_SFLOAT);
        assert_eq!(u32_at(16), 4);
        assert_eq!((u32_at(20), u32_at(24), u32_at(32), u32_at(36)), (2, 3, 2, 1));
        let off = u64::from_le_bytes(bytes[80..88].try_into().unwrap()) as usize;
        assert_eq!(off % 16, 0);
        assert_eq!(bytes.len(), off + 2 * 2 * 3 * 16);
        assert_eq!(f32::from_le_bytes(bytes[off..off + 4].try_into().unwrap()), 0.25);
        assert!(encode(2, 3, Shape::Cube, &[Texels::Float32(&a)]).is_err());
    }

    /// One image is a 2D texture (layerCount 0), two an array of 2, a cube layerCount 0 with six
    /// faces; every file's key/value data holds the orientation and the writer, sorted by key,
    /// as the independent `ktx2` reader parses them.
    #[test]
    fn one_image_is_2d_and_every_file_says_its_orientation_and_writer() {
        let a = [0.5f32; 2 * 2 * 4];
        let one = encode(2, 2, Shape::Array(1), &[Texels::Float32(&a)]).unwrap();
        let two = encode(2, 2, Shape::Array(2), &[Texels::Float32(&a), Texels::Float32(&a)]);
        let cube = encode(2, 2, Shape::Cube, &[Texels::Float32(&a); 6]).unwrap();
        for (bytes, layers, faces) in [(&one, 0, 1), (&two.unwrap(), 2, 1), (&cube, 0, 6)] {
            let r = ktx2::Reader::new(&bytes[..]).unwrap();
            let h = r.header();
            assert_eq!((h.layer_count, h.face_count), (layers, faces));
            let kv: Vec<(String, Vec<u8>)> =
                r.key_value_data().map(|(k, v)| (k.to_owned(), v.to_vec())).collect();
            let writer = format!("horizon-bake {}\0", env!("CARGO_PKG_VERSION"));
            assert_eq!(
                kv,
                [
                    ("KTXorientation".to_owned(), b"rd\0".to_vec()),
                    ("KTXwriter".to_owned(), writer.into_bytes()),
                    ("horizon-bake".to_owned(), b"{}\0".to_vec())
                ]
            );
            let level = r.levels().next().unwrap();
            assert_eq!(f32::from_le_bytes(level.data[..4].try_into().unwrap()), 0.5);
        }
    }
}
