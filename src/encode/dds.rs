//! DDS writer (DX10 header, DXGI formats) for the horizon array texture and the cube map, via the
//! `ddsfile` crate. Images are stored in array-layer order (cube faces +X, −X, +Y, −Y, +Z, −Z),
//! one mip level, rows from the top, samples little-endian. The cube map sets the DX10 cube flag
//! and counts one cube (the crate derives both from `is_cubemap` and 6 layers).

use super::{check_images, Shape, Texels};
use crate::error::{Error, Result};
use ddsfile::{AlphaMode, Caps2, D3D10ResourceDimension, Dds, DxgiFormat, NewDxgiParams};

/// The DXGI format of a sample type.
pub fn dxgi_format(t: &Texels<'_>) -> DxgiFormat {
    match t {
        Texels::Unorm8(_) => DxgiFormat::R8G8B8A8_UNorm,
        Texels::Snorm8(_) => DxgiFormat::R8G8B8A8_SNorm,
        Texels::Unorm16(_) => DxgiFormat::R16G16B16A16_UNorm,
        Texels::Float32(_) => DxgiFormat::R32G32B32A32_Float,
    }
}

/// Encodes a single-level array texture (`Shape::Array(n)`) or cube map (`Shape::Cube`).
///
/// # Errors
/// [`Error::Internal`] when the images do not fit `width × height` RGBA or `shape`, or the DDS
/// writer refuses.
pub fn encode(width: usize, height: usize, shape: Shape, images: &[Texels<'_>]) -> Result<Vec<u8>> {
    check_images(width, height, shape, images)?;
    let (layers, is_cubemap) = match shape {
        Shape::Array(n) => (n, false),
        Shape::Cube => (6, true),
    };
    let mut dds = Dds::new_dxgi(NewDxgiParams {
        height: height as u32,
        width: width as u32,
        depth: None,
        format: dxgi_format(&images[0]),
        mipmap_levels: None,
        array_layers: Some(layers),
        // Legacy readers look for the cube in caps2, DX10 readers in the misc flag (set by the
        // crate from `is_cubemap`): set both.
        caps2: is_cubemap.then_some(Caps2::CUBEMAP | Caps2::CUBEMAP_ALLFACES),
        is_cubemap,
        resource_dimension: D3D10ResourceDimension::Texture2D,
        alpha_mode: AlphaMode::Straight,
    })
    .map_err(|e| Error::Internal(format!("dds: {e}")))?;
    let mut data = Vec::with_capacity(dds.data.len());
    for img in images {
        img.extend_le(&mut data);
    }
    if data.len() != dds.data.len() {
        return Err(Error::Internal(format!(
            "dds: {} data bytes for a {}-byte surface",
            data.len(),
            dds.data.len()
        )));
    }
    dds.data = data;
    let mut out = Vec::with_capacity(dds.data.len() + 256);
    dds.write(&mut out).map_err(|e| Error::Internal(format!("dds: {e}")))?;
    Ok(out)
}
