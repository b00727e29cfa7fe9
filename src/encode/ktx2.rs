//! KTX2 writer for uncompressed RGBA array textures and cube maps (Khronos KTX 2.0 spec).
//!
//! No Rust crate both writes KTX2 and builds offline (NOTES.md), and the container is small, so
//! it is written here by hand: identifier, header, one level, a basic data format descriptor
//! (DFD), no key/value data and no supercompression. `tests/encode.rs` proves it by reading
//! every texel back with the independent `ktx2` crate and comparing the DFD with the one that
//! crate generates for the same format.
//!
//! Layout (all little-endian): 12-byte identifier, 9 × u32 header, the index (DFD and KVD offset
//! and length as u32, SGD offset and length as u64), the level index (offset, length,
//! uncompressed length as u64), the DFD, then the level data aligned to lcm(texel size, 4).
//! Within the level, images follow in layer order, then face order (+X, −X, +Y, −Y, +Z, −Z),
//! each row-major from the top row.

use super::{check_images, Shape, Texels};
use crate::error::Result;

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

/// (vkFormat, typeSize, sample flags, lower, upper) of a sample type.
fn describe(t: &Texels<'_>) -> (u32, u32, u8, u32, u32) {
    // Channel-type qualifier bits of a DFD sample: 0x80 float, 0x40 signed.
    match t {
        Texels::Unorm8(_) => (VK_FORMAT_R8G8B8A8_UNORM, 1, 0, 0, 255),
        Texels::Snorm8(_) => (VK_FORMAT_R8G8B8A8_SNORM, 1, 0x40, (-127i32) as u32, 127),
        Texels::Unorm16(_) => (VK_FORMAT_R16G16B16A16_UNORM, 2, 0, 0, 65535),
        Texels::Float32(_) => {
            (VK_FORMAT_R32G32B32A32_SFLOAT, 4, 0xC0, (-1.0f32).to_bits(), 1.0f32.to_bits())
        }
    }
}

/// The DFD: its total size, then one basic block (RGBSDA model, BT.709 primaries, linear
/// transfer, straight alpha) with four samples R, G, B, A.
fn dfd(t: &Texels<'_>) -> Vec<u8> {
    let (_, type_size, flags, lower, upper) = describe(t);
    let bits = type_size * 8;
    let block_size = 24 + 16 * 4u32;
    let mut d = Vec::with_capacity(4 + block_size as usize);
    d.extend((4 + block_size).to_le_bytes());
    d.extend(0u32.to_le_bytes()); // vendorId 0 (Khronos), descriptorType 0 (basic)
    d.extend(2u16.to_le_bytes()); // versionNumber
    d.extend((block_size as u16).to_le_bytes());
    d.extend([1, 1, 1, 0]); // colorModel RGBSDA, primaries BT709, transfer linear, flags straight
    d.extend([0, 0, 0, 0]); // texelBlockDimension0..3 (stored minus one)
    d.extend([(4 * type_size) as u8, 0, 0, 0, 0, 0, 0, 0]); // bytesPlane0..7
    for (k, channel_id) in [0u8, 1, 2, 15].into_iter().enumerate() {
        d.extend(((k as u32 * bits) as u16).to_le_bytes()); // bitOffset
        d.push((bits - 1) as u8); // bitLength − 1
        d.push(channel_id | flags);
        d.extend([0, 0, 0, 0]); // samplePosition0..3
        d.extend(lower.to_le_bytes());
        d.extend(upper.to_le_bytes());
    }
    d
}

/// Encodes one single-level texture: `Shape::Array(n)` with `n` images (layerCount = n), or
/// `Shape::Cube` with 6 faces (faceCount = 6, layerCount = 0). The vkFormat follows the sample
/// type of `images`: R8G8B8A8_UNORM, R8G8B8A8_SNORM, R16G16B16A16_UNORM or R32G32B32A32_SFLOAT.
///
/// # Errors
/// [`crate::Error::Internal`] when the images do not fit `width × height` RGBA or `shape`.
pub fn encode(width: usize, height: usize, shape: Shape, images: &[Texels<'_>]) -> Result<Vec<u8>> {
    check_images(width, height, shape, images)?;
    let first = &images[0];
    let (vk_format, type_size, ..) = describe(first);
    let (layer_count, face_count) = match shape {
        Shape::Array(n) => (n, 1u32),
        Shape::Cube => (0, 6),
    };
    let dfd = dfd(first);
    let header_len = 12 + 9 * 4 + 4 * 4 + 2 * 8;
    let level_index_len = 3 * 8;
    let dfd_offset = header_len + level_index_len;
    let texel_bytes = 4 * type_size as usize;
    // lcm(texel block size, 4): texel sizes here are 4, 8 or 16, all multiples of 4.
    let align = texel_bytes;
    let data_offset = (dfd_offset + dfd.len()).div_ceil(align) * align;
    let data_len = images.iter().map(|i| i.len() * i.sample_bytes()).sum::<usize>();

    let mut out = Vec::with_capacity(data_offset + data_len);
    out.extend(IDENTIFIER);
    for v in [
        vk_format,
        type_size,
        width as u32,
        height as u32,
        0, // pixelDepth: 2D
        layer_count,
        face_count,
        1, // levelCount
        0, // supercompressionScheme: none
    ] {
        out.extend(v.to_le_bytes());
    }
    out.extend((dfd_offset as u32).to_le_bytes());
    out.extend((dfd.len() as u32).to_le_bytes());
    out.extend(0u32.to_le_bytes()); // kvdByteOffset
    out.extend(0u32.to_le_bytes()); // kvdByteLength
    out.extend(0u64.to_le_bytes()); // sgdByteOffset
    out.extend(0u64.to_le_bytes()); // sgdByteLength
    out.extend((data_offset as u64).to_le_bytes());
    out.extend((data_len as u64).to_le_bytes());
    out.extend((data_len as u64).to_le_bytes());
    out.extend(&dfd);
    out.resize(data_offset, 0);
    for img in images {
        img.extend_le(&mut out);
    }
    Ok(out)
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
}
