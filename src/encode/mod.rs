//! Output encoders: PNG 8/16-bit, OpenEXR f32, KTX2 and DDS array textures and cube maps, the
//! latter with the SPEC §8 options ([`texture`]: mip chains from [`mips`], BC7/BC5 blocks from
//! [`bcn`], KTX2 zstd supercompression, separate layers, legacy DDS headers).
//!
//! Encoders take finished, quantised buffers and return bytes; they never compute. Quantisation
//! lives here too ([`quantize8`], [`quantize16`]) so every producer rounds the same way
//! (SPEC §2: floor(v·255 + 0.5), floor(v·65535 + 0.5)).
//!
//! [`horizon_files`] turns baked [`HorizonLayers`] into the files SPEC §6 names, so the CLI and
//! the service produce byte-identical outputs from one place; [`Formats`] says which files a
//! caller asked for and which layer precisions the bake must therefore produce.

pub mod assemble;
pub mod bcn;
pub mod dds;
pub mod exr;
pub mod geotiff;
pub mod ktx2;
pub mod mips;
pub mod png;
pub mod texture;

use crate::error::{Error, Result};
use crate::layers::{HorizonLayers, Precisions};

pub use crate::layers::{quantize16, quantize8};
pub use mips::MipFilter;
pub use texture::{DdsHeader, TextureLayout, TextureOptions, TexturePrecision};

/// One image (a layer or a cube face) of RGBA texels, `width · height · 4` samples row-major from
/// the top row, in one of the sample types the texture containers carry.
#[derive(Debug, Clone, Copy)]
pub enum Texels<'a> {
    /// UNORM 8-bit.
    Unorm8(&'a [u8]),
    /// SNORM 8-bit (0 exact; ±127 = ±1).
    Snorm8(&'a [i8]),
    /// UNORM 16-bit.
    Unorm16(&'a [u16]),
    /// IEEE f32.
    Float32(&'a [f32]),
}

impl Texels<'_> {
    /// Number of samples.
    pub fn len(&self) -> usize {
        match self {
            Texels::Unorm8(d) => d.len(),
            Texels::Snorm8(d) => d.len(),
            Texels::Unorm16(d) => d.len(),
            Texels::Float32(d) => d.len(),
        }
    }

    /// Whether there are no samples.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Bytes per sample.
    pub fn sample_bytes(&self) -> usize {
        match self {
            Texels::Unorm8(_) | Texels::Snorm8(_) => 1,
            Texels::Unorm16(_) => 2,
            Texels::Float32(_) => 4,
        }
    }

    /// Whether `other` has the same sample type.
    pub fn same_kind(&self, other: &Texels<'_>) -> bool {
        std::mem::discriminant(self) == std::mem::discriminant(other)
    }

    /// Appends the samples little-endian (the byte order of KTX2 and DDS).
    pub fn extend_le(&self, out: &mut Vec<u8>) {
        match self {
            Texels::Unorm8(d) => out.extend_from_slice(d),
            Texels::Snorm8(d) => out.extend(d.iter().map(|&v| v as u8)),
            Texels::Unorm16(d) => out.extend(d.iter().flat_map(|v| v.to_le_bytes())),
            Texels::Float32(d) => out.extend(d.iter().flat_map(|v| v.to_le_bytes())),
        }
    }
}

/// How a texture container (KTX2, DDS) arranges its images.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Shape {
    /// A 2D array texture with this many layers (the horizon map: 2).
    Array(u32),
    /// A cube map: six faces +X, −X, +Y, −Y, +Z, −Z.
    Cube,
}

/// Checks that `images` fit `width × height` RGBA, agree on the sample type and match `shape`.
fn check_images(width: usize, height: usize, shape: Shape, images: &[Texels<'_>]) -> Result<()> {
    let want = match shape {
        Shape::Array(n) => n as usize,
        Shape::Cube => 6,
    };
    if width == 0 || height == 0 {
        return Err(Error::Internal(format!("texture of {width}×{height} texels")));
    }
    if images.len() != want {
        return Err(Error::Internal(format!(
            "{shape:?} needs {want} images, got {}",
            images.len()
        )));
    }
    for (k, img) in images.iter().enumerate() {
        if img.len() != width * height * 4 {
            return Err(Error::Internal(format!(
                "image {k}: {} samples for {width}×{height} RGBA",
                img.len()
            )));
        }
        if !img.same_kind(&images[0]) {
            return Err(Error::Internal("images of one texture must share a sample type".into()));
        }
    }
    Ok(())
}

/// Which horizon files to write (SPEC §6 `--format`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
pub struct Formats {
    pub png8: bool,
    pub png16: bool,
    pub exr: bool,
    pub ktx2: bool,
    pub dds: bool,
    /// Precision, mips, supercompression, layout and DDS header of the KTX2/DDS files
    /// (serialised as their own keys: `texture_precision`, `mips`, …).
    #[serde(flatten)]
    pub texture: TextureOptions,
    /// Sample type of `horizon_0.exr` / `horizon_1.exr` (float unless asked otherwise).
    pub exr_precision: exr::ExrPrecision,
    /// What the layers' values mean, stated in every KTX2 file (SPEC §8): set from the bake's
    /// parameters where the layers are encoded; not a choice of format, so not serialised.
    #[serde(skip)]
    pub conventions: LayerConventions,
}

/// The bake parameters a horizon layer's texels depend on for their meaning, which every KTX2
/// file states under its `horizon-bake` key (SPEC §8) with the layout and the channels it holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct LayerConventions {
    /// `y_axis=down`: tangent-space +y toward the bottom of the image.
    pub y_axis_down: bool,
    /// `encoding=sqrt`: the texels hold √s.
    pub sqrt: bool,
}

impl LayerConventions {
    /// The `horizon-bake` value of one KTX2 horizon file: what its texels hold, `y_axis`,
    /// `encoding`, `layout`, and per layer the horizon channels in its components (channel c at
    /// azimuth c·45° from +x toward +y). `file` is the index of a `separate` file, None for the
    /// array.
    pub fn ktx2_json(self, opts: &TextureOptions, file: Option<usize>) -> String {
        let all: Vec<Vec<u8>> = if opts.precision == TexturePrecision::Bc5 {
            (0..4).map(|l| vec![2 * l, 2 * l + 1]).collect()
        } else {
            (0..2).map(|l| (4 * l..4 * l + 4).collect()).collect()
        };
        let channels = match file {
            Some(i) => all.get(i).map(|c| vec![c.clone()]).unwrap_or_default(),
            None => all,
        };
        serde_json::json!({
            "content": "horizon",
            "value": if self.sqrt { "sqrt(sin(horizon elevation))" } else { "sin(horizon elevation)" },
            "y_axis": if self.y_axis_down { "down" } else { "up" },
            "encoding": if self.sqrt { "sqrt" } else { "linear" },
            "layout": if opts.layout == TextureLayout::Separate { "separate" } else { "array" },
            "channels": channels,
        })
        .to_string()
    }
}

impl Default for Formats {
    fn default() -> Self {
        Formats {
            png8: true,
            png16: false,
            exr: false,
            ktx2: false,
            dds: false,
            texture: TextureOptions::default(),
            exr_precision: exr::ExrPrecision::Float,
            conventions: LayerConventions::default(),
        }
    }
}

impl Formats {
    /// Parses a comma list of `png8`, `png16`, `exr`, `ktx2`, `dds`.
    ///
    /// `png8` and `png16` both name `horizon_0.png`, so asking for both is an error rather than
    /// a silent pick.
    ///
    /// # Errors
    /// [`Error::Param`] naming `format`.
    pub fn parse(list: &str, texture_precision: TexturePrecision) -> Result<Self> {
        let mut f = Formats {
            png8: false,
            png16: false,
            exr: false,
            ktx2: false,
            dds: false,
            texture: TextureOptions { precision: texture_precision, ..Default::default() },
            exr_precision: exr::ExrPrecision::Float,
            conventions: LayerConventions::default(),
        };
        for part in list.split(',').map(str::trim).filter(|p| !p.is_empty()) {
            match part.to_ascii_lowercase().as_str() {
                "png8" => f.png8 = true,
                "png16" => f.png16 = true,
                "exr" => f.exr = true,
                "ktx2" => f.ktx2 = true,
                "dds" => f.dds = true,
                _ => {
                    return Err(Error::param(
                        "format",
                        format!("`{part}` is not one of png8, png16, exr, ktx2, dds"),
                    ))
                }
            }
        }
        if f.png8 && f.png16 {
            return Err(Error::param(
                "format",
                "png8 and png16 both write horizon_0.png/horizon_1.png; ask for one of them",
            ));
        }
        if !(f.png8 || f.png16 || f.exr || f.ktx2 || f.dds) {
            return Err(Error::param(
                "format",
                "must name at least one of png8, png16, exr, ktx2, dds",
            ));
        }
        Ok(f)
    }

    /// The layer precisions a bake must produce for these files.
    pub fn precisions(&self) -> Precisions {
        let tex = (self.ktx2 || self.dds).then_some(self.texture.precision);
        let eight = matches!(
            tex,
            Some(TexturePrecision::Unorm8 | TexturePrecision::Bc7 | TexturePrecision::Bc5)
        );
        Precisions {
            u8: self.png8 || eight,
            u16: self.png16 || tex == Some(TexturePrecision::Unorm16),
            f32: self.exr || tex == Some(TexturePrecision::Float32),
        }
    }
}

/// A named output file.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct OutFile {
    /// File name as SPEC §6 spells it.
    pub name: &'static str,
    pub bytes: Vec<u8>,
}

fn missing(what: &str) -> Error {
    Error::Internal(format!("the bake did not produce the {what} layers an output needs"))
}

/// The two layers of `layers` in the samples a texture of `precision` is made from.
fn layer_images(layers: &HorizonLayers, precision: TexturePrecision) -> Result<Vec<Texels<'_>>> {
    Ok(match precision {
        TexturePrecision::Unorm8 | TexturePrecision::Bc7 | TexturePrecision::Bc5 => {
            let l = layers.u8.as_ref().ok_or_else(|| missing("8-bit"))?;
            vec![Texels::Unorm8(&l[0]), Texels::Unorm8(&l[1])]
        }
        TexturePrecision::Unorm16 => {
            let l = layers.u16.as_ref().ok_or_else(|| missing("16-bit"))?;
            vec![Texels::Unorm16(&l[0]), Texels::Unorm16(&l[1])]
        }
        TexturePrecision::Float32 => {
            let l = layers.f32.as_ref().ok_or_else(|| missing("f32"))?;
            vec![Texels::Float32(&l[0]), Texels::Float32(&l[1])]
        }
    })
}

/// File names of the `separate` layout (SPEC §8): one 2D texture per layer, 2 or 4 (`bc5`).
const SEPARATE_KTX2: [&str; 4] =
    ["horizon_0.ktx2", "horizon_1.ktx2", "horizon_2.ktx2", "horizon_3.ktx2"];
const SEPARATE_DDS: [&str; 4] =
    ["horizon_0.dds", "horizon_1.dds", "horizon_2.dds", "horizon_3.dds"];

/// Encodes the horizon layers into the files `formats` asks for (SPEC §6, §8): `horizon_0.png`
/// and `horizon_1.png` (8- or 16-bit RGBA), `horizon_0.exr` and `horizon_1.exr` (f32 RGBA),
/// `horizon.ktx2` and `horizon.dds` (one array texture; `horizon_{i}.ktx2`/`.dds` per layer with
/// `texture_layout=separate`).
///
/// # Errors
/// [`Error::Internal`] when `layers` lacks a precision `formats` needs (bake with
/// [`Formats::precisions`]) or an encoder fails; [`Error::Param`] for texture options that
/// cannot apply (see [`TextureOptions::check_for`]).
pub fn horizon_files(layers: &HorizonLayers, formats: &Formats) -> Result<Vec<OutFile>> {
    horizon_files_with(layers, formats, &crate::progress::Progress::new())
}

/// [`horizon_files`], checking `progress` for cancellation between texture levels and layers.
///
/// # Errors
/// As [`horizon_files`], and [`Error::Canceled`].
pub fn horizon_files_with(
    layers: &HorizonLayers,
    formats: &Formats,
    progress: &crate::progress::Progress,
) -> Result<Vec<OutFile>> {
    horizon_files_levels(layers, &[], formats, progress)
}

/// [`horizon_files_with`] with the levels below `layers` baked again (`below[l − 1]` is level
/// `l`, every level of a full chain), which KTX2/DDS files with `mips=full` and
/// `mip_filter=rebake` need (`pipeline::rebake_levels` bakes them); empty otherwise.
///
/// # Errors
/// As [`horizon_files_with`]; [`Error::Param`] naming `mip_filter` for `rebake` without the
/// levels (only a caller holding the heights can bake them).
pub fn horizon_files_levels(
    layers: &HorizonLayers,
    below: &[HorizonLayers],
    formats: &Formats,
    progress: &crate::progress::Progress,
) -> Result<Vec<OutFile>> {
    let (w, h) = (layers.width, layers.height);
    let mut out = Vec::new();
    if formats.png8 {
        let l = layers.u8.as_ref().ok_or_else(|| missing("8-bit"))?;
        out.push(OutFile {
            name: "horizon_0.png",
            bytes: png::encode8(w, h, png::PngColor::Rgba, &l[0])?,
        });
        // A whole PNG layer is the longest step of an encode: DELETE waits for one, not two.
        if progress.is_canceled() {
            return Err(Error::Canceled);
        }
        out.push(OutFile {
            name: "horizon_1.png",
            bytes: png::encode8(w, h, png::PngColor::Rgba, &l[1])?,
        });
    }
    if formats.png16 {
        let l = layers.u16.as_ref().ok_or_else(|| missing("16-bit"))?;
        out.push(OutFile {
            name: "horizon_0.png",
            bytes: png::encode16(w, h, png::PngColor::Rgba, &l[0])?,
        });
        // A whole PNG layer is the longest step of an encode: DELETE waits for one, not two.
        if progress.is_canceled() {
            return Err(Error::Canceled);
        }
        out.push(OutFile {
            name: "horizon_1.png",
            bytes: png::encode16(w, h, png::PngColor::Rgba, &l[1])?,
        });
    }
    if formats.exr {
        let l = layers.f32.as_ref().ok_or_else(|| missing("f32"))?;
        // The two layers are independent: encode them side by side.
        let p = formats.exr_precision;
        let (a, b) = rayon::join(
            || exr::encode_rgba_as(w, h, &l[0], p),
            || exr::encode_rgba_as(w, h, &l[1], p),
        );
        out.push(OutFile { name: "horizon_0.exr", bytes: a? });
        out.push(OutFile { name: "horizon_1.exr", bytes: b? });
    }
    if formats.ktx2 || formats.dds {
        let opts = &formats.texture;
        // The caller checked the options against every container it asked for (zstd is for
        // KTX2 alone); a call per container (pipeline::encode_each) ignores the other's options.
        opts.check_for(true, true, false)?;
        let images = |layers| layer_images(layers, opts.precision);
        let mut levels = vec![images(layers)?];
        if texture::rebakes(opts) {
            if below.is_empty() && mips::full_levels(w, h) > 1 {
                return Err(Error::param(
                    "mip_filter",
                    "`rebake` bakes each level again from the heights: encode through \
                     pipeline::encode_each with the height map",
                ));
            }
            for l in below {
                levels.push(images(l)?);
            }
        }
        let textures = texture::build_levels(w, h, Shape::Array(2), &levels, opts, progress)?;
        let separate = opts.layout == TextureLayout::Separate;
        if formats.ktx2 {
            for (i, t) in textures.iter().enumerate() {
                let name = if separate { SEPARATE_KTX2[i] } else { "horizon.ktx2" };
                let meta = formats.conventions.ktx2_json(opts, separate.then_some(i));
                out.push(OutFile { name, bytes: ktx2::write(t, opts.zstd_level, &meta)? });
            }
        }
        if formats.dds {
            for (i, t) in textures.iter().enumerate() {
                let name = if separate { SEPARATE_DDS[i] } else { "horizon.dds" };
                out.push(OutFile { name, bytes: dds::write(t, opts.dds_header)? });
            }
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn formats_parse_and_precisions() {
        let f = Formats::parse("png16, exr,ktx2", TexturePrecision::Unorm8).unwrap();
        assert!(f.png16 && f.exr && f.ktx2 && !f.png8 && !f.dds);
        assert_eq!(f.precisions(), Precisions { u8: true, u16: true, f32: true });
        let f = Formats::parse("dds", TexturePrecision::Float32).unwrap();
        assert_eq!(f.precisions(), Precisions { u8: false, u16: false, f32: true });
        for bad in ["png8,png16", "jpeg", ""] {
            match Formats::parse(bad, TexturePrecision::Unorm8) {
                Err(Error::Param { field, .. }) => assert_eq!(field, "format", "{bad}"),
                other => panic!("{bad}: {other:?}"),
            }
        }
        assert!(TexturePrecision::parse("unorm12").is_err());
    }

    #[test]
    fn missing_precision_is_an_error_not_a_panic() {
        let layers = HorizonLayers { width: 1, height: 1, ..Default::default() };
        assert!(horizon_files(&layers, &Formats::default()).is_err());
    }
}

/// Largest face size accepted: the factors of a 2048² cube already take 400 MB as f32, far more
/// than a 2-texel-wide blend ever needs (the default is 16).
pub const MAX_CUBE_SIZE: u32 = 2048;

/// Which cube-map files to write.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct CubeFormats {
    pub png8: bool,
    pub ktx2: bool,
    pub dds: bool,
    /// Mips, supercompression and DDS header of `cubemap.ktx2`/`cubemap.dds` (SPEC §8; the
    /// cube map stays one cube texture, RGBA8 SNORM or, with `texture_precision=bc7`, BC7
    /// blocks of its UNORM faces).
    pub texture: TextureOptions,
}

/// The cube-map files of the channel factors `factors` (six faces of `size`² texels × 4, in
/// the cube map's face order): PNG faces, KTX2 and DDS as `formats` asks.
///
/// # Errors
/// [`Error::Param`] for texture options the cube map does not take; an encoder failure.
pub fn cube_files(size: usize, factors: &[f32], formats: CubeFormats) -> Result<Vec<OutFile>> {
    const NAMES: [&str; 6] =
        ["cube_0.png", "cube_1.png", "cube_2.png", "cube_3.png", "cube_4.png", "cube_5.png"];
    let face_len = size * size * 4;
    let mut out = Vec::new();
    if formats.png8 {
        for (face, name) in NAMES.into_iter().enumerate() {
            let bytes: Vec<u8> = factors[face * face_len..(face + 1) * face_len]
                .iter()
                .map(|&f| crate::kernels::cubemap::unorm8(f))
                .collect();
            out.push(OutFile {
                name,
                bytes: png::encode8(size, size, png::PngColor::Rgba, &bytes)?,
            });
        }
    }
    if formats.ktx2 || formats.dds {
        let opts = &formats.texture;
        opts.check_for(formats.ktx2, formats.dds, true)?;
        // SNORM keeps a zero factor exact; `bc7` (for loaders that read no uncompressed cube,
        // such as three.js) compresses the UNORM faces of the PNGs, f = 2t − 1 as for them.
        let bc7 = opts.precision == TexturePrecision::Bc7;
        let (snorm, unorm): (Vec<i8>, Vec<u8>) = if bc7 {
            (Vec::new(), factors.iter().map(|&f| crate::kernels::cubemap::unorm8(f)).collect())
        } else {
            (factors.iter().map(|&f| crate::kernels::cubemap::snorm8(f)).collect(), Vec::new())
        };
        let faces: Vec<Texels<'_>> = if bc7 {
            unorm.chunks_exact(face_len).map(Texels::Unorm8).collect()
        } else {
            snorm.chunks_exact(face_len).map(Texels::Snorm8).collect()
        };
        let progress = crate::progress::Progress::new();
        let cube = texture::build(size, size, Shape::Cube, &faces, opts, &progress)?;
        if formats.ktx2 {
            let meta = serde_json::json!({
                "content": "cube_factors",
                "faces": ["+x", "-x", "+y", "-y", "+z", "-z"],
                "row0": "t = -1",
                "factors": if bc7 { "unorm: f = 2t - 1" } else { "snorm: f = t" },
                "slots": "channel c in slot c % 4, negated for c >= 4",
            })
            .to_string();
            out.push(OutFile {
                name: "cubemap.ktx2",
                bytes: ktx2::write(&cube[0], opts.zstd_level, &meta)?,
            });
        }
        if formats.dds {
            out.push(OutFile {
                name: "cubemap.dds",
                bytes: dds::write(&cube[0], opts.dds_header)?,
            });
        }
    }
    Ok(out)
}

/// Fourier layer `i` as PNG bytes (`fourier_{i}.png`): 0 and 2 RGBA, 1 gray.
///
/// # Errors
/// [`Error::Param`] (`layer`) for a layer this bake does not have; [`Error::Internal`] if the
/// encoder fails.
pub fn fourier_png(f: &crate::kernels::fourier::FourierLayers, i: usize) -> Result<Vec<u8>> {
    use png::{encode8, PngColor};
    match (i, &f.high) {
        (0, _) => encode8(f.width, f.height, PngColor::Rgba, &f.bands),
        (1, _) => encode8(f.width, f.height, PngColor::Gray, &f.constant),
        (2, Some(h)) => encode8(f.width, f.height, PngColor::Rgba, h),
        _ => Err(Error::param(
            "layer",
            format!("this bake has Fourier layers 0..{}", f.layer_count() - 1),
        )),
    }
}
