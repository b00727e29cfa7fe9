//! The surface maps of a bake (SPEC §3.8): `normal.png`, `ao.png` and `bent_normal.png` from
//! [`bake::bake_surface`], as KTX2/DDS 2D textures too when the bake asks those containers
//! ([`surface_textures`]: the horizon layers' texture options, mips and block compression
//! through the same `encode::texture::build`), and what they hold, for bake.json.

use super::*;

/// Bakes the surface maps `params.outputs` asks for into PNGs: `normal.png` (RGB8), `ao.png`
/// (grey8), `bent_normal.png` (RGB8; `rg` with blue 0, PNG having no two-channel colour type;
/// RGBA8 with the AO in alpha for `rgb_ao`); and what they hold, for bake.json.
///
/// # Errors
/// Whatever the bake or the PNG encoder fails with.
pub fn surface_files(
    map: &HeightMap,
    params: &BakeParams,
    formats: &Formats,
    progress: &Progress,
) -> Result<(Vec<OutFile>, ResolvedRadius, serde_json::Value)> {
    let (m, radius) = bake::bake_surface(map, params, progress)?;
    progress.start(Stage::Encode, 1);
    let (files, info) = surface_outputs(&m, params, formats, progress)?;
    Ok((files, radius, info))
}

/// The files of surface maps baked with `params` for `formats`: the PNGs when `formats` has a
/// PNG or no texture container (an EXR-only bake still gets them), and the KTX2/DDS textures
/// `formats` asks ([`surface_textures`]); what each holds, for bake.json.
///
/// # Errors
/// [`Error::Canceled`], [`check_surface_formats`]' refusal, the encoders' errors.
pub fn surface_outputs(
    m: &bake::SurfaceMaps,
    params: &BakeParams,
    formats: &Formats,
    progress: &Progress,
) -> Result<(Vec<OutFile>, serde_json::Value)> {
    let pngs = formats.png8 || formats.png16 || !(formats.ktx2 || formats.dds);
    let (mut files, mut info) = if pngs {
        surface_pngs(m, params, progress)?
    } else {
        (Vec::new(), serde_json::Value::Object(Default::default()))
    };
    let textures = surface_textures(m, params, formats, progress)?;
    if let Some(map) = info.as_object_mut() {
        for f in &textures {
            map.insert(
                f.name.to_owned(),
                serde_json::json!({
                    "texture": if f.name.ends_with(".ktx2") { "ktx2" } else { "dds" },
                    "texture_precision": formats.texture.precision.name(),
                    "mips": if formats.texture.mips { "full" } else { "none" },
                    "channels": if formats.texture.precision == crate::encode::TexturePrecision::Bc5 {
                        "rg: the PNG's first two channels (x and y; the ao in r)"
                    } else {
                        "rgba: the PNG's channels, alpha 1 where the PNG has none (the ao in r, g and b)"
                    },
                }),
            );
        }
    }
    files.extend(textures);
    Ok((files, info))
}

/// Refuses, before anything is baked, texture options the surface maps cannot honour: they
/// are 8-bit, so with `normal`, `ao` or `bent_normal` in `outputs` a KTX2/DDS bake takes
/// `texture_precision` `unorm8`, `bc7` or `bc5`.
///
/// # Errors
/// [`Error::Param`] naming `texture_precision`.
pub fn check_surface_formats(params: &BakeParams, formats: &Formats) -> Result<()> {
    use crate::encode::TexturePrecision as P;
    let eight_bit = matches!(formats.texture.precision, P::Unorm8 | P::Bc7 | P::Bc5);
    if params.outputs.surface() && (formats.ktx2 || formats.dds) && !eight_bit {
        return Err(Error::param(
            "texture_precision",
            format!(
                "the surface maps (normal, ao, bent_normal) are 8-bit: with them, KTX2/DDS \
                 files take unorm8, bc7 or bc5, not {}",
                formats.texture.precision.name()
            ),
        ));
    }
    Ok(())
}

/// The KTX2/DDS files of the surface maps, as `formats` asks: `normal.ktx2`, `ao.ktx2`,
/// `bent_normal.ktx2` (and `.dds`), each one 2D texture (layerCount 0) with the horizon layers'
/// options: RGBA8 (`unorm8`: the PNG's channels, alpha 255 where it has none, the AO in r, g
/// and b), BC7 blocks of those, or `bc5`: BC5 of the first two channels (the normal's and bent
/// normal's x and y, z rebuilt as engines do for BC5 normal maps; the AO in r). Mips as asked,
/// box-filtered when `mip_filter=rebake` (a surface map has no horizons to bake again); zstd
/// for the KTX2.
///
/// # Errors
/// [`Error::Canceled`], [`check_surface_formats`]' refusal, the encoders' errors.
pub fn surface_textures(
    m: &bake::SurfaceMaps,
    params: &BakeParams,
    formats: &Formats,
    progress: &Progress,
) -> Result<Vec<OutFile>> {
    use crate::encode::{dds, ktx2, texture, MipFilter, Shape, Texels, TextureLayout};
    if !(formats.ktx2 || formats.dds) {
        return Ok(Vec::new());
    }
    check_surface_formats(params, formats)?;
    let mut opts = formats.texture;
    opts.layout = TextureLayout::Separate;
    if opts.mip_filter == MipFilter::Rebake {
        opts.mip_filter = MipFilter::Box;
    }
    let bc5 = opts.precision == crate::encode::TexturePrecision::Bc5;
    let bent_ch = bake::SurfaceMaps::bent_channels(params.bent_normal_encoding);
    // (content, KTX2 name, DDS name, samples, channels per texel)
    type Map<'m> = (&'static str, &'static str, &'static str, Option<&'m Vec<u8>>, usize);
    let maps: [Map<'_>; 3] = [
        ("normal", "normal.ktx2", "normal.dds", m.normal.as_ref(), 3),
        ("ao", "ao.ktx2", "ao.dds", m.ao.as_ref(), 1),
        ("bent_normal", "bent_normal.ktx2", "bent_normal.dds", m.bent_normal.as_ref(), bent_ch),
    ];
    let mut out = Vec::new();
    for (what, ktx_name, dds_name, data, ch) in maps {
        let Some(data) = data else { continue };
        if progress.is_canceled() {
            return Err(Error::Canceled);
        }
        let rgba: Vec<u8> = data
            .chunks_exact(ch)
            .flat_map(|t| match t.len() {
                1 => [t[0], t[0], t[0], 255],
                3 => [t[0], t[1], t[2], 255],
                _ => [t[0], t[1], t[2], t[3]],
            })
            .collect();
        // `separate` gives one texture per layer: RGBA8 and BC7 one, BC5 two RG layers, of
        // which the first holds channels 0 and 1.
        let built = texture::build(
            m.width,
            m.height,
            Shape::Array(1),
            &[Texels::Unorm8(&rgba)],
            &opts,
            progress,
        )?;
        let t = built.into_iter().next().ok_or_else(|| Error::Internal("no texture".into()))?;
        let conventions = serde_json::json!({
            "content": what,
            "y_axis": if params.y_axis == crate::params::YAxis::Down { "down" } else { "up" },
            "normal_convention": match params.normal_convention {
                crate::params::NormalConvention::OpenGl => "opengl",
                crate::params::NormalConvention::DirectX => "directx",
            },
            "value": if what == "ao" { "ao" } else { "(v + 1) / 2" },
            "channels": if bc5 { "rg" } else { "rgba" },
        })
        .to_string();
        if formats.ktx2 {
            out.push(OutFile {
                name: ktx_name,
                bytes: ktx2::write(&t, opts.zstd_level, &conventions)?,
            });
        }
        if formats.dds {
            out.push(OutFile { name: dds_name, bytes: dds::write(&t, opts.dds_header)? });
        }
    }
    Ok(out)
}

/// The PNGs of surface maps baked with `params` and what they hold, for bake.json.
///
/// # Errors
/// [`Error::Canceled`], the PNG encoder's errors.
pub fn surface_pngs(
    m: &bake::SurfaceMaps,
    params: &BakeParams,
    progress: &Progress,
) -> Result<(Vec<OutFile>, serde_json::Value)> {
    use crate::params::BentNormalEncoding as E;
    let (w, h) = (m.width, m.height);
    let convention = match params.normal_convention {
        crate::params::NormalConvention::OpenGl => "opengl",
        crate::params::NormalConvention::DirectX => "directx",
    };
    let y_axis = match params.y_axis {
        crate::params::YAxis::Up => "up",
        crate::params::YAxis::Down => "down",
    };
    let lengyel = params.method == crate::params::Method::Lengyel;
    let from = if lengyel { "the 8 channel directions (lengyel)" } else { "every bin" };
    let mut files = Vec::new();
    let mut info = serde_json::Map::new();
    if let Some(n) = &m.normal {
        files.push(OutFile {
            name: "normal.png",
            bytes: png::encode8(w, h, png::PngColor::Rgb, n)?,
        });
        info.insert(
            "normal.png".into(),
            serde_json::json!({
                "channels": "rgb", "value": "(n + 1) / 2", "convention": convention,
                "y_axis": y_axis, "holes": 0,
            }),
        );
    }
    if let Some(a) = &m.ao {
        files.push(OutFile { name: "ao.png", bytes: png::encode8(w, h, png::PngColor::Gray, a)? });
        info.insert(
            "ao.png".into(),
            serde_json::json!({
                "channels": "grey", "value": "cosine-weighted visible sky above the horizon, \
                 1 = open and flat", "horizons": from, "holes": 0,
            }),
        );
    }
    if let Some(b) = &m.bent_normal {
        if progress.is_canceled() {
            return Err(Error::Canceled);
        }
        // RG has no PNG colour type of its own (grey + alpha would sample as x, x, x, y): x and
        // y in red and green, blue 0, so `.rg` reads them.
        let (color, channels) = match params.bent_normal_encoding {
            E::Rgb => (png::PngColor::Rgb, "rgb"),
            E::Rg => (png::PngColor::Rgb, "rg (blue 0; z = sqrt(1 - x² - y²))"),
            E::RgbAo => (png::PngColor::Rgba, "rgb + ao in alpha"),
        };
        files.push(OutFile { name: "bent_normal.png", bytes: png::encode8(w, h, color, b)? });
        info.insert(
            "bent_normal.png".into(),
            serde_json::json!({
                "channels": channels, "value": "(b + 1) / 2", "convention": convention,
                "y_axis": y_axis, "horizons": from, "holes": 0,
            }),
        );
    }
    Ok((files, serde_json::Value::Object(info)))
}
