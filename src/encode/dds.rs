//! DDS writer for the horizon array texture and the cube map, written by hand: the header is
//! 148 bytes and every field matters to some reader.
//!
//! **DX10 (default).** Magic `DDS `, the 124-byte header, then the 20-byte DX10 header (DXGI
//! format, TEXTURE2D, the cube flag, array size, alpha mode). The legacy pixel format carries
//! only DDPF_FOURCC (0x4) with FourCC `DX10` and zero bit count and masks: a reader that also
//! sees DDPF_RGB (as the `ddsfile` crate's writer set it) reads the zero masks instead of the
//! DXGI format (Pillow then decoded 1.9% of a layer right). The mip count is always filled
//! (DDSD_MIPMAPCOUNT), pitch or linear size of level 0 as DirectXTex writes them.
//!
//! **Legacy** (`dds_header=legacy`, SPEC §8): no DX10 header, for loaders that read none; one 2D
//! texture or a cube map: FourCC `ATI2` for BC5, DDPF_RGB | DDPF_ALPHAPIXELS with R, G, B, A
//! masks for RGBA8, DDPF_BUMPDUDV masks for SNORM8 (D3DFMT_Q8W8V8U8), FourCC 36 for RGBA16 and
//! 116 for f32 (the D3DFMT numbers), as DirectXTex writes them.
//!
//! Data order (DDS): for each array element (or cube face +X, −X, +Y, −Y, +Z, −Z), every mip
//! level from the largest, rows (of texels or 4×4 blocks) from the top, samples little-endian.

use super::texture::{DdsHeader, PixelFormat, Texture};
use super::{Shape, Texels};
use crate::error::{Error, Result};

const DDSD_CAPS: u32 = 0x1;
const DDSD_HEIGHT: u32 = 0x2;
const DDSD_WIDTH: u32 = 0x4;
const DDSD_PITCH: u32 = 0x8;
const DDSD_PIXELFORMAT: u32 = 0x1000;
const DDSD_MIPMAPCOUNT: u32 = 0x20000;
const DDSD_LINEARSIZE: u32 = 0x80000;
const DDPF_ALPHAPIXELS: u32 = 0x1;
const DDPF_FOURCC: u32 = 0x4;
const DDPF_RGB: u32 = 0x40;
const DDPF_BUMPDUDV: u32 = 0x80000;
const DDSCAPS_COMPLEX: u32 = 0x8;
const DDSCAPS_TEXTURE: u32 = 0x1000;
const DDSCAPS_MIPMAP: u32 = 0x40_0000;
/// DDSCAPS2_CUBEMAP and all six DDSCAPS2_CUBEMAP_* faces.
const DDSCAPS2_CUBEMAP_ALLFACES: u32 = 0xFE00;
const DDS_RESOURCE_MISC_TEXTURECUBE: u32 = 0x4;
const D3D10_RESOURCE_DIMENSION_TEXTURE2D: u32 = 3;
/// DDS_ALPHA_MODE_STRAIGHT / UNKNOWN.
const ALPHA_STRAIGHT: u32 = 1;
const ALPHA_UNKNOWN: u32 = 0;

/// The DXGI format number of a pixel format.
pub fn dxgi_format(f: PixelFormat) -> u32 {
    match f {
        PixelFormat::Rgba8Unorm => 28,  // R8G8B8A8_UNORM
        PixelFormat::Rgba8Snorm => 31,  // R8G8B8A8_SNORM
        PixelFormat::Rgba16Unorm => 11, // R16G16B16A16_UNORM
        PixelFormat::Rgba32Float => 2,  // R32G32B32A32_FLOAT
        PixelFormat::Bc5Unorm => 83,    // BC5_UNORM
        PixelFormat::Bc7Unorm => 98,    // BC7_UNORM
    }
}

/// The legacy pixel format: (flags, FourCC, bit count, R, G, B, A masks).
fn legacy_pixel_format(f: PixelFormat) -> Result<(u32, [u8; 4], u32, [u32; 4])> {
    const RGBA: [u32; 4] = [0xFF, 0xFF00, 0xFF_0000, 0xFF00_0000];
    Ok(match f {
        PixelFormat::Rgba8Unorm => (DDPF_RGB | DDPF_ALPHAPIXELS, [0; 4], 32, RGBA),
        PixelFormat::Rgba8Snorm => (DDPF_BUMPDUDV, [0; 4], 32, RGBA),
        PixelFormat::Rgba16Unorm => (DDPF_FOURCC, 36u32.to_le_bytes(), 0, [0; 4]),
        PixelFormat::Rgba32Float => (DDPF_FOURCC, 116u32.to_le_bytes(), 0, [0; 4]),
        PixelFormat::Bc5Unorm => (DDPF_FOURCC, *b"ATI2", 0, [0; 4]),
        PixelFormat::Bc7Unorm => {
            return Err(Error::param("dds_header", "BC7 has no legacy FourCC; use dds_header=dx10"))
        }
    })
}

/// The DDS header (and DX10 extension) of `t`: its format, size, shape and level count
/// (`t.levels` is only counted, not read), everything before the data. [`write`] appends the
/// images; the streamed writer of `encode::assemble` writes level 0 band by band after it.
///
/// # Errors
/// As [`write`].
pub(crate) fn header_bytes(t: &Texture, header: DdsHeader) -> Result<Vec<u8>> {
    let (w, h) = (t.width as u32, t.height as u32);
    let mips = t.levels.len() as u32;
    let cube = t.shape == Shape::Cube;
    let legacy = header == DdsHeader::Legacy;
    if legacy && t.shape != Shape::Array(1) && !cube {
        return Err(Error::param(
            "dds_header",
            "a legacy DDS header holds no array; add texture_layout=separate",
        ));
    }
    let mut out = Vec::with_capacity(4 + 124 + 20);
    let put = |out: &mut Vec<u8>, v: u32| out.extend(v.to_le_bytes());

    out.extend(b"DDS ");
    put(&mut out, 124);
    let block = t.format.is_block();
    let mut flags = DDSD_CAPS | DDSD_HEIGHT | DDSD_WIDTH | DDSD_PIXELFORMAT | DDSD_MIPMAPCOUNT;
    flags |= if block { DDSD_LINEARSIZE } else { DDSD_PITCH };
    put(&mut out, flags);
    put(&mut out, h);
    put(&mut out, w);
    let pitch = if block {
        t.format.image_bytes(t.width, t.height)
    } else {
        t.width * t.format.block_bytes()
    };
    put(&mut out, pitch as u32);
    put(&mut out, 0); // depth
    put(&mut out, mips);
    out.extend([0u8; 44]); // reserved1[11]
    put(&mut out, 32); // pixel format size
    let (pf_flags, fourcc, bits, masks) =
        if legacy { legacy_pixel_format(t.format)? } else { (DDPF_FOURCC, *b"DX10", 0, [0; 4]) };
    put(&mut out, pf_flags);
    out.extend(fourcc);
    put(&mut out, bits);
    for m in masks {
        put(&mut out, m);
    }
    let mut caps = DDSCAPS_TEXTURE;
    if mips > 1 {
        caps |= DDSCAPS_COMPLEX | DDSCAPS_MIPMAP;
    }
    if cube {
        caps |= DDSCAPS_COMPLEX;
    }
    put(&mut out, caps);
    put(&mut out, if cube { DDSCAPS2_CUBEMAP_ALLFACES } else { 0 });
    out.extend([0u8; 12]); // caps3, caps4, reserved2
    if !legacy {
        put(&mut out, dxgi_format(t.format));
        put(&mut out, D3D10_RESOURCE_DIMENSION_TEXTURE2D);
        put(&mut out, if cube { DDS_RESOURCE_MISC_TEXTURECUBE } else { 0 });
        // A cube counts one cube; an array its layers.
        put(&mut out, if cube { 1 } else { t.images() as u32 });
        put(
            &mut out,
            if t.format == PixelFormat::Bc5Unorm { ALPHA_UNKNOWN } else { ALPHA_STRAIGHT },
        );
    }
    Ok(out)
}

/// Writes `t` as a DDS file with the header `header` asks for.
///
/// # Errors
/// [`Error::Param`] (`dds_header`) for what a legacy header cannot hold (BC7, an array of more
/// than one layer); [`Error::Internal`] for a texture whose levels do not fit its size.
pub fn write(t: &Texture, header: DdsHeader) -> Result<Vec<u8>> {
    t.check()?;
    let mut out = header_bytes(t, header)?;
    out.reserve(t.levels.iter().flatten().map(Vec::len).sum());
    for image in 0..t.images() {
        for level in &t.levels {
            out.extend(&level[image]);
        }
    }
    Ok(out)
}

/// Encodes a single-level, uncompressed array texture (`Shape::Array(n)`) or cube map
/// (`Shape::Cube`) with a DX10 header.
///
/// # Errors
/// [`Error::Internal`] when the images do not fit `width × height` RGBA or `shape`.
pub fn encode(width: usize, height: usize, shape: Shape, images: &[Texels<'_>]) -> Result<Vec<u8>> {
    write(&Texture::single(width, height, shape, images)?, DdsHeader::Dx10)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn legacy_headers() {
        let px = [1u8, 2, 3, 4];
        let t = Texture::single(1, 1, Shape::Array(1), &[Texels::Unorm8(&px)]).unwrap();
        let b = write(&t, DdsHeader::Legacy).unwrap();
        assert_eq!(b.len(), 128 + 4);
        assert_eq!(u32::from_le_bytes(b[80..84].try_into().unwrap()), 0x41);
        assert_eq!(u32::from_le_bytes(b[88..92].try_into().unwrap()), 32);
        assert_eq!(u32::from_le_bytes(b[92..96].try_into().unwrap()), 0xFF);
        assert_eq!(&b[128..], &px);
        let two =
            Texture::single(1, 1, Shape::Array(2), &[Texels::Unorm8(&px), Texels::Unorm8(&px)])
                .unwrap();
        assert!(matches!(write(&two, DdsHeader::Legacy), Err(Error::Param { .. })));
        let bc7 = Texture { format: PixelFormat::Bc7Unorm, levels: vec![vec![vec![0; 16]]], ..t };
        assert!(matches!(write(&bc7, DdsHeader::Legacy), Err(Error::Param { .. })));
        let bc5 = Texture { format: PixelFormat::Bc5Unorm, ..bc7 };
        let b = write(&bc5, DdsHeader::Legacy).unwrap();
        assert_eq!(&b[84..88], b"ATI2");
        assert_eq!(u32::from_le_bytes(b[20..24].try_into().unwrap()), 16, "linear size");
    }
}
