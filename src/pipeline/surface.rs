//! The surface maps of a bake (SPEC §3.8): `normal.png`, `ao.png` and `bent_normal.png` from
//! [`bake::bake_surface`], and what they hold, for bake.json.

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
    progress: &Progress,
) -> Result<(Vec<OutFile>, ResolvedRadius, serde_json::Value)> {
    let (m, radius) = bake::bake_surface(map, params, progress)?;
    progress.start(Stage::Encode, 1);
    let (files, info) = surface_pngs(&m, params, progress)?;
    Ok((files, radius, info))
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
