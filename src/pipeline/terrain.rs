//! The terrain products of a bake (SPEC §3.7): the horizon angles and sky-view factor as
//! GeoTIFFs with the input's georeferencing, their band descriptions, and the sun shadow of
//! `shadow` and its preview.

use super::*;
use crate::terrain::sun::{SunAzimuth, SunQuery};

/// Bakes the terrain products `params.outputs` asks for into GeoTIFFs (SPEC §3.7): `angles.tif`
/// (one band per bin) and `svf.tif`, with the input's georeferencing; and what they hold, for
/// bake.json. `heights`: the map's heights scaled, when the caller took them out of the map
/// ([`bake::bake_terrain_from`]); else they are scaled from a copy.
///
/// # Errors
/// Whatever the bake or the GeoTIFF encoder fails with.
pub fn terrain_files(
    map: &HeightMap,
    heights: Option<Vec<f32>>,
    params: &BakeParams,
    progress: &Progress,
) -> Result<(Vec<OutFile>, ResolvedRadius, serde_json::Value)> {
    let (mut files, spooled, radius, info) = terrain_parts(map, heights, params, progress)?;
    if let Some(s) = spooled {
        let name = s.name;
        files.insert(0, OutFile { name, bytes: s.write_to(Vec::new())? });
    }
    Ok((files, radius, info))
}

/// A GeoTIFF made band by band as the bake went (`sweep`'s `angles`), its tiles in a
/// temporary file: [`SpooledTiff::write_to`] writes the file.
pub struct SpooledTiff {
    pub name: &'static str,
    spool: crate::encode::geotiff::Spool,
    descriptions: Vec<String>,
    georef: Option<crate::heightmap::georef::Georef>,
}

impl SpooledTiff {
    /// Writes the whole file into `out` and hands it back.
    ///
    /// # Errors
    /// The spool's and `out`'s I/O errors.
    pub fn write_to<W: std::io::Write>(self, out: W) -> Result<W> {
        let names: Vec<&str> = self.descriptions.iter().map(String::as_str).collect();
        self.spool.finish(out, &names, self.georef.as_ref())
    }
}

/// [`terrain_files`], with `angles.tif` spooled rather than in memory where the bake streams
/// its bands ([`bake::streams_angles`]: one plane per bin in flight, so any bins fit at any
/// size); the caller writes it ([`SpooledTiff::write_to`]).
///
/// # Errors
/// As [`terrain_files`]; [`Error::Io`] when no temporary file can be made in the progress's
/// scratch directory.
pub fn terrain_parts(
    map: &HeightMap,
    heights: Option<Vec<f32>>,
    params: &BakeParams,
    progress: &Progress,
) -> Result<(Vec<OutFile>, Option<SpooledTiff>, ResolvedRadius, serde_json::Value)> {
    use crate::encode::geotiff;
    let georef = map.terrain.georef.as_ref();
    let (p, radius, spool) = if bake::streams_angles(map, params) {
        let nodata = map.terrain.nodata.map_or(f32::NAN, |v| v as f32);
        let (w, h, nb) = (map.width, map.height, params.bins as usize);
        let mut spool = geotiff::Spool::new(&progress.scratch_dir(), w, h, nb, nodata)?;
        let heights = heights.unwrap_or_else(|| map.scaled(params.height_scale));
        let put: bake::AngleBands<'_> = &mut |band, row| spool.put(band, row);
        let (p, r) = bake::bake_terrain_streamed(map, heights, params, progress, put)?;
        (p, r, Some(spool))
    } else {
        let (p, r) = match heights {
            Some(heights) => bake::bake_terrain_from(map, heights, params, progress)?,
            None => bake::bake_terrain(map, params, progress)?,
        };
        (p, r, None)
    };
    progress.start(Stage::Encode, 1);
    let plane = p.width * p.height;
    let mut files = Vec::new();
    let mut spooled = None;
    let mut info = serde_json::Map::new();
    let nodata = serde_json::json!(geotiff::nodata_text(p.nodata));
    let true_north = p.north.as_ref().is_some_and(|n| n.reference == "true");
    let north = serde_json::to_value(&p.north).unwrap_or_default();
    if p.angles.is_some() || spool.is_some() {
        let (from, unit) = (azimuth_from_name(params), angle_unit_name(params));
        let azimuths: Vec<f64> =
            (0..p.bins).map(|n| crate::terrain::angles::band_azimuth_deg(n, p.bins)).collect();
        let descriptions = angle_descriptions(params, p.bins, true_north);
        if progress.is_canceled() {
            return Err(Error::Canceled);
        }
        if let Some(a) = &p.angles {
            let bands: Vec<geotiff::Band<'_>> = a
                .chunks_exact(plane)
                .zip(descriptions.iter().cloned())
                .map(|(plane, description)| geotiff::Band { plane, description })
                .collect();
            let bytes = geotiff::encode(p.width, p.height, &bands, georef, p.nodata)?;
            files.push(OutFile { name: "angles.tif", bytes });
        } else if let Some(spool) = spool {
            let georef = georef.cloned();
            let descriptions = descriptions.clone();
            spooled = Some(SpooledTiff { name: "angles.tif", spool, descriptions, georef });
        }
        info.insert(
            "angles.tif".into(),
            serde_json::json!({
                "bands": descriptions,
                "azimuths_deg": azimuths,
                "azimuth_from": from,
                "north": north_of(params, true_north),
                "unit": unit,
                "nodata": nodata,
            }),
        );
    }
    if let Some(v) = &p.svf {
        let model = svf_model_name(params);
        let description = svf_description(params, p.bins);
        let bands = [geotiff::Band { plane: v, description: description.clone() }];
        let bytes = geotiff::encode(p.width, p.height, &bands, georef, p.nodata)?;
        files.push(OutFile { name: "svf.tif", bytes });
        info.insert(
            "svf.tif".into(),
            serde_json::json!({
                "bands": [description],
                "model": model,
                "unit": "fraction of the sky",
                "nodata": nodata,
            }),
        );
    }
    if let Some(d) = &p.distance {
        let unit = distance_unit(map.terrain.georef.as_ref(), params);
        let descriptions = distance_descriptions(params, p.bins, &unit, true_north);
        let bands: Vec<geotiff::Band<'_>> = d
            .chunks_exact(plane)
            .zip(descriptions)
            .map(|(plane, description)| geotiff::Band { plane, description })
            .collect();
        if progress.is_canceled() {
            return Err(Error::Canceled);
        }
        let bytes = geotiff::encode(p.width, p.height, &bands, georef, p.nodata)?;
        files.push(OutFile { name: "horizon_distance.tif", bytes });
        let azimuths: Vec<f64> =
            (0..p.bins).map(|n| crate::terrain::angles::band_azimuth_deg(n, p.bins)).collect();
        info.insert(
            "horizon_distance.tif".into(),
            serde_json::json!({
                "bands": bands.iter().map(|b| b.description.clone()).collect::<Vec<_>>(),
                "azimuths_deg": azimuths,
                "azimuth_from": azimuth_from_name(params),
                "north": north_of(params, true_north),
                "unit": unit,
                "value": "horizontal distance to the point that sets the horizon (exact ray); \
                          nodata where the horizon is 0",
                "nodata": nodata,
            }),
        );
    }
    if let Some([pos, neg]) = &p.openness {
        for (name, plane, sign) in
            [("openness_positive.tif", pos, "positive"), ("openness_negative.tif", neg, "negative")]
        {
            if progress.is_canceled() {
                return Err(Error::Canceled);
            }
            let description = openness_description(sign, p.bins, radius.texels);
            let bands = [geotiff::Band { plane, description: description.clone() }];
            let bytes = geotiff::encode(p.width, p.height, &bands, georef, p.nodata)?;
            files.push(OutFile { name, bytes });
            info.insert(
                name.into(),
                serde_json::json!({
                    "bands": [description],
                    "unit": "degrees",
                    "value": format!("mean over the azimuths of 90° − the signed maximum \
                        elevation angle {}(Yokoyama et al. 2002)",
                        if sign == "negative" { "of the inverted surface " } else { "" }),
                    "nodata": nodata,
                }),
            );
        }
    }
    let sun =
        [("sun_hours.tif", &p.sun_hours, "hours"), ("insolation.tif", &p.insolation, "Wh/m²")];
    for (name, plane, unit) in sun {
        let Some(plane) = plane else { continue };
        if progress.is_canceled() {
            return Err(Error::Canceled);
        }
        let step = params.time_step_minutes.unwrap_or(crate::params::DEFAULT_TIME_STEP_MINUTES);
        let (from, to) = (params.date_from.as_deref(), params.date_to.as_deref());
        let (from, to) = (from.unwrap_or_default(), to.unwrap_or_default());
        let description = sun_description(params, name == "insolation.tif");
        let bands = [geotiff::Band { plane, description: description.clone() }];
        let bytes = geotiff::encode(p.width, p.height, &bands, georef, p.nodata)?;
        files.push(OutFile { name, bytes });
        let place = match (params.latitude, params.longitude) {
            (Some(a), Some(o)) => {
                serde_json::json!({"latitude": a, "longitude": o, "from": "given"})
            }
            _ => match bake::centre_lat_lon(map) {
                Some((a, o)) => serde_json::json!({
                    "latitude": (a * 1e6).round() / 1e6,
                    "longitude": (o * 1e6).round() / 1e6,
                    "from": "the DEM's centre",
                }),
                None => serde_json::Value::Null,
            },
        };
        info.insert(
            name.into(),
            serde_json::json!({
                "bands": [description],
                "unit": unit,
                "date_from": from,
                "date_to": to,
                "time_step_minutes": step,
                "sun": "NREL SPA (solar-positioning crate), apparent elevation; local mean \
                        solar days; the midpoint of each step",
                "place": place,
                "clear_sky": if name == "insolation.tif" {
                    "simplified Solis (Ineichen 2008) with pvlib's defaults: aod700 0.1, \
                     precipitable water 1 cm, I0 1364 W/m², pressure of the texel's altitude \
                     (pvlib alt2pres); direct beam only, times the cosine of incidence on the \
                     surface"
                } else {
                    "none: a step counts where the sun is above 0° and above the horizon at \
                     its own azimuth"
                },
                "north": north,
                "nodata": nodata,
            }),
        );
    }
    Ok((files, spooled, radius, serde_json::Value::Object(info)))
}

/// The band description of `openness_{sign}.tif`.
pub fn openness_description(sign: &str, bins: usize, radius: u32) -> String {
    format!("{sign} openness, degrees ({bins} azimuths within {radius} texels)")
}

/// The band description of `sun_hours.tif` (or, `insolation`, of `insolation.tif`).
pub fn sun_description(params: &BakeParams, insolation: bool) -> String {
    let (what, unit) = if insolation {
        ("clear-sky direct beam on the surface", "Wh/m²")
    } else {
        ("hours of direct sun", "hours")
    };
    let step = params.time_step_minutes.unwrap_or(crate::params::DEFAULT_TIME_STEP_MINUTES);
    let from = params.date_from.as_deref().unwrap_or_default();
    let to = params.date_to.as_deref().unwrap_or_default();
    let days = if from == to { from.to_owned() } else { format!("{from} to {to}") };
    format!("{what}, {unit}, {days}, every {step} min")
}

/// What a product's azimuths count from, for bake.json: `east_ccw` is the grid's x axis;
/// `north_cw` is true north where the map's projection gives it, else grid north.
fn north_of(params: &BakeParams, true_north: bool) -> &'static str {
    match (params.azimuth_from, true_north) {
        (crate::params::AzimuthFrom::EastCcw, _) => "grid (x axis)",
        (crate::params::AzimuthFrom::NorthCw, true) => "true",
        (crate::params::AzimuthFrom::NorthCw, false) => "grid",
    }
}

/// The azimuth convention of a band description: `east_ccw`, or `north_cw` with which north.
fn band_from(params: &BakeParams, true_north: bool) -> &'static str {
    match (params.azimuth_from, true_north) {
        (crate::params::AzimuthFrom::EastCcw, _) => "east_ccw",
        (crate::params::AzimuthFrom::NorthCw, true) => "north_cw, true north",
        (crate::params::AzimuthFrom::NorthCw, false) => "north_cw",
    }
}

/// The unit of `horizon_distance.tif`: the CRS's linear unit when `cell_size` came from it (or
/// was given), texels otherwise.
pub fn distance_unit(
    georef: Option<&crate::heightmap::georef::Georef>,
    params: &BakeParams,
) -> String {
    match (params.cell_size, georef) {
        (Some(c), Some(g)) => g.report(Some(c)).units.unwrap_or_else(|| "map units".to_owned()),
        (Some(_), None) => "map units (cell_size)".to_owned(),
        (None, _) => "texels".to_owned(),
    }
}

/// The band descriptions of `horizon_distance.tif` at `bins` azimuths.
pub fn distance_descriptions(
    params: &BakeParams,
    bins: usize,
    unit: &str,
    true_north: bool,
) -> Vec<String> {
    let from = band_from(params, true_north);
    (0..bins)
        .map(|n| {
            let az = crate::terrain::angles::band_azimuth_deg(n, bins);
            format!("distance to the horizon at azimuth {az}° ({from}), {unit}")
        })
        .collect()
}

fn azimuth_from_name(params: &BakeParams) -> &'static str {
    match params.azimuth_from {
        crate::params::AzimuthFrom::EastCcw => "east_ccw",
        crate::params::AzimuthFrom::NorthCw => "north_cw",
    }
}

fn angle_unit_name(params: &BakeParams) -> &'static str {
    match params.angle_unit {
        crate::params::AngleUnit::Degrees => "degrees",
        crate::params::AngleUnit::Radians => "radians",
        crate::params::AngleUnit::Sin => "sin",
    }
}

fn svf_model_name(params: &BakeParams) -> &'static str {
    match params.svf_model {
        crate::params::SvfModel::Radiative => "radiative",
        crate::params::SvfModel::Visual => "visual",
        crate::params::SvfModel::Tilted => "tilted",
    }
}

/// The band descriptions of `angles.tif` at `bins` azimuths (as [`terrain_files`] writes them).
/// `true_north`: compass bands are true azimuths (SPEC §3.7 "True and grid north").
pub fn angle_descriptions(params: &BakeParams, bins: usize, true_north: bool) -> Vec<String> {
    let (from, unit) = (band_from(params, true_north), angle_unit_name(params));
    (0..bins)
        .map(|n| {
            let az = crate::terrain::angles::band_azimuth_deg(n, bins);
            format!("horizon {unit} at azimuth {az}° ({from})")
        })
        .collect()
}

/// The band description of `svf.tif` (as [`terrain_files`] writes it).
pub fn svf_description(params: &BakeParams, bins: usize) -> String {
    format!("sky-view factor ({}, {bins} azimuths)", svf_model_name(params))
}

/// The sun shadow (SPEC §3.7) of `map` as `shadow.tif`: uint8, 1 lit, 0 shadowed, 255 at holes
/// (its GDAL_NODATA), with the input's georeferencing.
///
/// # Errors
/// Whatever [`bake::shadow`] or the GeoTIFF encoder fails with.
pub fn shadow_tif(
    map: &HeightMap,
    params: &BakeParams,
    sun: &SunQuery,
    progress: &Progress,
) -> Result<Vec<u8>> {
    let (azimuth, elevation_deg, _) = sun.resolve(bake::centre_lat_lon(map))?;
    let plane = bake::shadow(map, params, azimuth, elevation_deg, progress)?;
    let (compass, _) = bake::compass_of(map, params);
    let from = match (azimuth, compass.is_true()) {
        (SunAzimuth::Grid(_), _) => "east_ccw: counter-clockwise from the grid's x axis",
        (SunAzimuth::True(_), true) => "north_cw: clockwise from true north",
        (SunAzimuth::True(_), false) => "north_cw: clockwise from grid north",
    };
    let description = format!(
        "sun shadow at azimuth {}° ({from}), elevation {elevation_deg}° (1 lit, 0 shadow)",
        azimuth.degrees()
    );
    encode::geotiff::encode_u8(
        map.width,
        map.height,
        &plane,
        &description,
        map.terrain.georef.as_ref(),
        crate::terrain::shadow::NODATA,
    )
}

/// The sun shadow of [`shadow_tif`] as an 8-bit grey + alpha PNG a browser can show: lit 255,
/// shadowed 0, holes transparent (SPEC §3.7, `format=png`).
///
/// # Errors
/// Whatever [`bake::shadow`] or the PNG encoder fails with.
pub fn shadow_png(
    map: &HeightMap,
    params: &BakeParams,
    sun: &SunQuery,
    progress: &Progress,
) -> Result<Vec<u8>> {
    let (azimuth, elevation_deg, _) = sun.resolve(bake::centre_lat_lon(map))?;
    let plane = bake::shadow(map, params, azimuth, elevation_deg, progress)?;
    png::encode8(map.width, map.height, png::PngColor::GrayAlpha, &shadow_grey(&plane))
}

/// Grey + alpha samples of a shadow plane (1 lit, 0 shadowed, [`NODATA`](crate::terrain::shadow::NODATA)
/// a hole): lit (255, 255), shadowed (0, 255), hole (0, 0).
pub fn shadow_grey(plane: &[u8]) -> Vec<u8> {
    plane
        .iter()
        .flat_map(|&s| match s {
            crate::terrain::shadow::NODATA => [0, 0],
            0 => [0, 255],
            _ => [255, 255],
        })
        .collect()
}

/// A stored `svf.tif` (as [`terrain_files`] writes it) as an 8-bit grey + alpha PNG a browser
/// can show: the sky-view factor 0..1 quantised to 0..255 as every 8-bit output is (SPEC §2),
/// holes (the file's GDAL_NODATA) transparent (SPEC §3.7, `format=png`).
///
/// # Errors
/// [`Error::Decode`] when the bytes are not a one-band float GeoTIFF; the PNG encoder's errors.
pub fn svf_png(svf_tif: &[u8]) -> Result<Vec<u8>> {
    let limits = crate::heightmap::Limits {
        max_dim: u32::MAX,
        max_texels: u64::MAX,
        max_bytes: u64::MAX,
        max_decode_bytes: u64::MAX,
    };
    let (map, _) = crate::heightmap::decode(svf_tif, crate::params::Channel::Luma, &limits)?;
    let holes = map.terrain.holes.as_deref();
    let grey = svf_grey(&map.values, holes);
    png::encode8(map.width, map.height, png::PngColor::GrayAlpha, &grey)
}

/// Grey + alpha samples of sky-view factors: (floor(v·255 + 0.5), 255), a hole (0, 0).
pub fn svf_grey(values: &[f32], holes: Option<&[bool]>) -> Vec<u8> {
    values
        .iter()
        .enumerate()
        .flat_map(|(k, &v)| {
            if holes.is_some_and(|h| h[k]) || !v.is_finite() {
                [0, 0]
            } else {
                [encode::quantize8(v), 255]
            }
        })
        .collect()
}
