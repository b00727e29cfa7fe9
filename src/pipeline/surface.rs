//! The surface maps of a bake (SPEC §3.8): `normal`, `ao` and `bent_normal` from
//! [`bake::bake_surface`], in the formats of the horizon layers: 8- or 16-bit PNG
//! (`normal.png`, …, as `png8`/`png16` says), EXR (`normal.exr`, …, float or half as
//! `exr_precision` says, the same [0, 1] values unquantised), and KTX2/DDS 2D textures
//! ([`surface_textures`]: the horizon layers' texture options, mips and block compression
//! through the same `encode::texture::build`); and what each holds, for bake.json.

use super::*;

/// Bakes the surface maps `params.outputs` asks for into the files of `formats`
/// ([`surface_outputs`]): `normal.png` (RGB), `ao.png` (grey), `bent_normal.png` (RGB; `rg`
/// with blue 0, PNG having no two-channel colour type; RGBA with the AO in alpha for
/// `rgb_ao`), their EXR and texture files; and what they hold, for bake.json.
///
/// # Errors
/// Whatever the bake or the PNG encoder fails with.
pub fn surface_files(
    map: &HeightMap,
    params: &BakeParams,
    formats: &Formats,
    progress: &Progress,
) -> Result<(Vec<OutFile>, ResolvedRadius, serde_json::Value)> {
    let keep = super::surface_keep(params, formats);
    let (m, radius) = bake::bake_surface_as(map, params, keep, progress)?;
    progress.start(Stage::Encode, 1);
    let (files, info) = surface_outputs(&m, params, formats, progress)?;
    Ok((files, radius, info))
}

/// The files of surface maps baked with `params` for `formats`, as the horizon layers get
/// them: 8-bit PNGs with `png8`, 16-bit PNGs (the same names) with `png16`, EXR with `exr`
/// (these two from [`bake::SurfaceMaps::values`]), and the KTX2/DDS textures `formats` asks
/// ([`surface_textures`]); what each holds, for bake.json.
///
/// # Errors
/// [`Error::Canceled`], [`Error::Internal`] when a 16-bit or float file is asked of maps
/// baked without their values, the encoders' errors.
pub fn surface_outputs(
    m: &bake::SurfaceMaps,
    params: &BakeParams,
    formats: &Formats,
    progress: &Progress,
) -> Result<(Vec<OutFile>, serde_json::Value)> {
    let (mut files, mut info) = if formats.png8 || formats.png16 {
        surface_pngs(m, params, formats.png16, progress)?
    } else {
        (Vec::new(), serde_json::Value::Object(Default::default()))
    };
    if formats.exr {
        let (exr, exr_info) = surface_exrs(m, params, formats.exr_precision, progress)?;
        files.extend(exr);
        if let (Some(to), serde_json::Value::Object(from)) = (info.as_object_mut(), exr_info) {
            to.extend(from);
        }
    }
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

/// The KTX2/DDS files of the surface maps, as `formats` asks: `normal.ktx2`, `ao.ktx2`,
/// `bent_normal.ktx2` (and `.dds`), each one 2D texture (layerCount 0) with the horizon layers'
/// options: RGBA8 (`unorm8`: the PNG's channels, alpha 255 where it has none, the AO in r, g
/// and b), RGBA16 (`unorm16`, the 16-bit PNG's samples) or RGBA32F (`float32`, the EXR's
/// values), alpha 1 where the map has none; BC7 blocks of the bytes, or `bc5`: BC5 of the first
/// two channels (the normal's and bent normal's x and y, z rebuilt as engines do for BC5 normal
/// maps; the AO in r). Mips as asked, box-filtered when `mip_filter=rebake` (a surface map has
/// no horizons to bake again); zstd for the KTX2.
///
/// # Errors
/// [`Error::Canceled`], [`Error::Internal`] for a 16-bit or float texture of maps baked
/// without their values, the encoders' errors.
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
    let mut opts = formats.texture;
    opts.layout = TextureLayout::Separate;
    if opts.mip_filter == MipFilter::Rebake {
        opts.mip_filter = MipFilter::Box;
    }
    let bc5 = opts.precision == crate::encode::TexturePrecision::Bc5;
    let bent_ch = bake::SurfaceMaps::bent_channels(params.bent_normal_encoding);
    // (content, KTX2 name, DDS name, samples, channels per texel)
    type Map<'m> = (
        &'static str,
        &'static str,
        &'static str,
        Option<&'m Vec<u8>>,
        Option<&'m Vec<f32>>,
        usize,
    );
    let v = m.values.as_ref();
    let maps: [Map<'_>; 3] = [
        (
            "normal",
            "normal.ktx2",
            "normal.dds",
            m.normal.as_ref(),
            v.and_then(|v| v.normal.as_ref()),
            3,
        ),
        ("ao", "ao.ktx2", "ao.dds", m.ao.as_ref(), v.and_then(|v| v.ao.as_ref()), 1),
        (
            "bent_normal",
            "bent_normal.ktx2",
            "bent_normal.dds",
            m.bent_normal.as_ref(),
            v.and_then(|v| v.bent_normal.as_ref()),
            bent_ch,
        ),
    ];
    use crate::encode::TexturePrecision as P;
    let wide = matches!(opts.precision, P::Unorm16 | P::Float32);
    let mut out = Vec::new();
    for (what, ktx_name, dds_name, data, values, ch) in maps {
        let Some(data) = data else { continue };
        if progress.is_canceled() {
            return Err(Error::Canceled);
        }
        // RGBA of the map's channels: grey in r, g and b, alpha 1 where it has none.
        fn rgba<V: Copy>(t: &[V], one: V) -> [V; 4] {
            match t.len() {
                1 => [t[0], t[0], t[0], one],
                3 => [t[0], t[1], t[2], one],
                _ => [t[0], t[1], t[2], t[3]],
            }
        }
        let (bytes, shorts, floats): (Vec<u8>, Vec<u16>, Vec<f32>) = match (opts.precision, values)
        {
            (P::Unorm16, Some(v)) => {
                let q = v.iter().map(|&x| crate::terrain::surface::encode_unorm16(x));
                let q: Vec<u16> = q.collect();
                (
                    Vec::new(),
                    q.chunks_exact(ch).flat_map(|t| rgba(t, u16::MAX)).collect(),
                    Vec::new(),
                )
            }
            (P::Float32, Some(v)) => {
                (Vec::new(), Vec::new(), v.chunks_exact(ch).flat_map(|t| rgba(t, 1.0)).collect())
            }
            (_, None) if wide => {
                return Err(Error::Internal(
                    "a 16-bit or float texture of surface maps baked without their values".into(),
                ))
            }
            _ => {
                (data.chunks_exact(ch).flat_map(|t| rgba(t, 255)).collect(), Vec::new(), Vec::new())
            }
        };
        let texels = match opts.precision {
            P::Unorm16 => Texels::Unorm16(&shorts),
            P::Float32 => Texels::Float32(&floats),
            _ => Texels::Unorm8(&bytes),
        };
        // `separate` gives one texture per layer: RGBA and BC7 one, BC5 two RG layers, of
        // which the first holds channels 0 and 1.
        let built = texture::build(m.width, m.height, Shape::Array(1), &[texels], &opts, progress)?;
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

/// What each surface map's files hold, for bake.json: its name stem, its channels in the
/// file's words, and the rest of its description.
fn surface_info(params: &BakeParams) -> [(&'static str, &'static str, serde_json::Value); 3] {
    use crate::params::BentNormalEncoding as E;
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
    let bent = match params.bent_normal_encoding {
        E::Rgb => "rgb",
        E::Rg => "rg (blue 0; z = sqrt(1 - x² - y²))",
        E::RgbAo => "rgb + ao in alpha",
    };
    [
        (
            "normal",
            "rgb",
            serde_json::json!({
                "value": "(n + 1) / 2", "convention": convention, "y_axis": y_axis, "holes": 0,
            }),
        ),
        (
            "ao",
            "grey",
            serde_json::json!({
                "value": "cosine-weighted visible sky above the horizon, 1 = open and flat",
                "horizons": from, "holes": 0,
            }),
        ),
        (
            "bent_normal",
            bent,
            serde_json::json!({
                "value": "(b + 1) / 2", "convention": convention, "y_axis": y_axis,
                "horizons": from, "holes": 0,
            }),
        ),
    ]
}

/// `info` with `channels` first and `depth`, as bake.json lists a file.
fn described(channels: &str, depth: &str, info: &serde_json::Value) -> serde_json::Value {
    let mut m = serde_json::Map::new();
    m.insert("channels".into(), channels.into());
    m.insert("depth".into(), depth.into());
    if let Some(rest) = info.as_object() {
        m.extend(rest.clone());
    }
    serde_json::Value::Object(m)
}

/// The PNGs of surface maps baked with `params`, 8-bit, or 16-bit (floor(v·65535 + 0.5) of
/// [`bake::SurfaceMaps::values`]) with `sixteen`, and what they hold, for bake.json.
///
/// # Errors
/// [`Error::Canceled`], [`Error::Internal`] for 16 bits of maps baked without their values,
/// the PNG encoder's errors.
pub fn surface_pngs(
    m: &bake::SurfaceMaps,
    params: &BakeParams,
    sixteen: bool,
    progress: &Progress,
) -> Result<(Vec<OutFile>, serde_json::Value)> {
    use crate::params::BentNormalEncoding as E;
    let (w, h) = (m.width, m.height);
    let values = m.values.as_ref();
    if sixteen && values.is_none() {
        return Err(Error::Internal("16-bit surface maps of a bake without their values".into()));
    }
    let bent_color = match params.bent_normal_encoding {
        // RG has no PNG colour type of its own (grey + alpha would sample as x, x, x, y): x and
        // y in red and green, blue 0, so `.rg` reads them.
        E::Rgb | E::Rg => png::PngColor::Rgb,
        E::RgbAo => png::PngColor::Rgba,
    };
    let [ni, ai, bi] = surface_info(params);
    let maps = [
        ("normal.png", png::PngColor::Rgb, &m.normal, values.and_then(|v| v.normal.as_ref()), ()),
        ("ao.png", png::PngColor::Gray, &m.ao, values.and_then(|v| v.ao.as_ref()), ()),
        (
            "bent_normal.png",
            bent_color,
            &m.bent_normal,
            values.and_then(|v| v.bent_normal.as_ref()),
            (),
        ),
    ];
    // The maps side by side on the pool: each encoder waits for its slowest piece at every
    // batch, so one at a time left a core idle at each batch's end.
    use rayon::prelude::*;
    let encoded: Vec<Result<Option<(OutFile, &str)>>> = maps
        .into_par_iter()
        .map(|(name, color, bytes, vals, _)| {
            let Some(bytes) = bytes else { return Ok(None) };
            if progress.is_canceled() {
                return Err(Error::Canceled);
            }
            let (png, depth) = match vals.filter(|_| sixteen) {
                Some(v) => {
                    let q: Vec<u16> =
                        v.iter().map(|&x| crate::terrain::surface::encode_unorm16(x)).collect();
                    (png::encode16(w, h, color, &q)?, "16-bit")
                }
                None => (png::encode8(w, h, color, bytes)?, "8-bit"),
            };
            Ok(Some((OutFile { name, bytes: png }, depth)))
        })
        .collect();
    let mut files = Vec::new();
    let mut info = serde_json::Map::new();
    for (done, (_, channels, rest)) in encoded.into_iter().zip([ni, ai, bi]) {
        let Some((file, depth)) = done? else { continue };
        info.insert(file.name.into(), described(channels, depth, &rest));
        files.push(file);
    }
    Ok((files, serde_json::Value::Object(info)))
}

/// The EXR files of surface maps baked with their values: `normal.exr` (R, G, B),
/// `ao.exr` (Y), `bent_normal.exr` (R, G, B, and A for `rgb_ao`), the [0, 1] values the PNGs
/// quantise, in `precision`; and what they hold, for bake.json.
///
/// # Errors
/// [`Error::Canceled`], [`Error::Internal`] for maps baked without their values, the encoder's
/// errors.
pub fn surface_exrs(
    m: &bake::SurfaceMaps,
    params: &BakeParams,
    precision: crate::encode::exr::ExrPrecision,
    progress: &Progress,
) -> Result<(Vec<OutFile>, serde_json::Value)> {
    let Some(values) = m.values.as_ref() else {
        return Err(Error::Internal("EXR surface maps of a bake without their values".into()));
    };
    let bent_ch = bake::SurfaceMaps::bent_channels(params.bent_normal_encoding);
    let [ni, ai, bi] = surface_info(params);
    let maps = [
        ("normal.exr", 3, values.normal.as_ref(), ni),
        ("ao.exr", 1, values.ao.as_ref(), ai),
        ("bent_normal.exr", bent_ch, values.bent_normal.as_ref(), bi),
    ];
    let depth = match precision {
        crate::encode::exr::ExrPrecision::Float => "float32",
        crate::encode::exr::ExrPrecision::Half => "half",
    };
    let mut files = Vec::new();
    let mut info = serde_json::Map::new();
    for (name, ch, vals, (_, channels, rest)) in maps {
        let Some(v) = vals else { continue };
        if progress.is_canceled() {
            return Err(Error::Canceled);
        }
        let bytes = crate::encode::exr::encode_channels(m.width, m.height, ch, v, precision)?;
        files.push(OutFile { name, bytes });
        let channels = if ch == 1 { "grey (Y)" } else { channels };
        info.insert(name.into(), described(channels, depth, &rest));
    }
    Ok((files, serde_json::Value::Object(info)))
}
