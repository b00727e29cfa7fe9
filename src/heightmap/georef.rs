//! GeoTIFF georeferencing (SPEC §2 "Georeferenced input"): the tags a DEM carries, read once at
//! decode and carried as one value to the GeoTIFF writer, which copies them unchanged; and the
//! DEM defaults (`cell_size`, `height_scale`, `edge`, `earth_curvature`), decided here and
//! nowhere else.
//!
//! Tags (GeoTIFF 1.1, GDAL): ModelPixelScale 33550, ModelTiepoint 33922, ModelTransformation
//! 34264, GeoKeyDirectory 34735 (+ GeoDoubleParams 34736, GeoAsciiParams 34737) and GDAL's
//! GDAL_NODATA 42113 (ASCII), and GDAL_METADATA 42112 for the band's scale and offset. Only what
//! the defaults and bake.json need is interpreted: the model type, the EPSG code, the linear and
//! vertical units, the band scale and the affine transform; everything else travels verbatim
//! (GDAL_METADATA excepted: the outputs' values are not the input's scaled heights).

use crate::error::{Error, Result};
use crate::params::{BakeParams, EarthCurvature, Edge};
use serde::Serialize;

pub const TAG_MODEL_PIXEL_SCALE: u16 = 33550;
pub const TAG_MODEL_TIEPOINT: u16 = 33922;
pub const TAG_MODEL_TRANSFORMATION: u16 = 34264;
pub const TAG_GEO_KEY_DIRECTORY: u16 = 34735;
pub const TAG_GEO_DOUBLE_PARAMS: u16 = 34736;
pub const TAG_GEO_ASCII_PARAMS: u16 = 34737;
pub const TAG_GDAL_NODATA: u16 = 42113;
pub const TAG_GDAL_METADATA: u16 = 42112;

/// GeoKeys this module reads.
const KEY_MODEL_TYPE: u16 = 1024;
const KEY_RASTER_TYPE: u16 = 1025;
const KEY_GEOGRAPHIC_TYPE: u16 = 2048;
const KEY_PROJECTED_CS_TYPE: u16 = 3072;
const KEY_PROJ_LINEAR_UNITS: u16 = 3076;
const KEY_VERTICAL_CS_TYPE: u16 = 4096;
const KEY_VERTICAL_UNITS: u16 = 4099;

/// Vertical CRSs whose heights are in metres (EPSG), the ones DEMs are shipped in: EGM96,
/// EGM2008, NAVD88, MSL, ODN, DHHN92, DHHN2016, LN02, LHN95, NN2000, AHD, Baltic 1977.
const VERTICAL_METRE_CRS: [u16; 12] =
    [5773, 3855, 5703, 5714, 5701, 5783, 7837, 5728, 5729, 5941, 5711, 5705];
/// Vertical CRSs in international feet, and in US survey feet (EPSG).
const VERTICAL_FOOT_CRS: [u16; 2] = [8228, 8051];
const VERTICAL_US_FOOT_CRS: [u16; 3] = [6360, 5702, 6357];

/// The georeferencing tags of a TIFF, as stored.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Georef {
    pub pixel_scale: Option<Vec<f64>>,
    pub tiepoints: Option<Vec<f64>>,
    pub transformation: Option<Vec<f64>>,
    pub geo_keys: Option<Vec<u16>>,
    pub geo_doubles: Option<Vec<f64>>,
    pub geo_ascii: Option<String>,
    /// GDAL_NODATA as written (ASCII, e.g. "-32768" or "nan").
    pub gdal_nodata: Option<String>,
    /// GDAL_METADATA (XML) as written: read for the band's scale and offset, never copied to
    /// outputs (their values are angles, not the input's scaled heights).
    pub gdal_metadata: Option<String>,
}

/// What bake.json (and the service's bake resource) reports of the georeferencing.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct GeorefReport {
    /// `projected`, `geographic` or `unknown` (GTModelTypeGeoKey).
    pub model: &'static str,
    /// EPSG code of the CRS, when the keys name one.
    pub epsg: Option<u16>,
    /// The CRS citation of GeoAsciiParams (for user-defined CRSs).
    pub citation: Option<String>,
    /// GDAL geotransform: [x0, pixel width, row rotation, y0, column rotation, pixel height],
    /// of the top-left corner of the top-left texel.
    pub transform: Option<[f64; 6]>,
    /// Map units per texel the bake used (`cell_size`).
    pub cell_size: Option<f64>,
    /// `metre`, `foot`, `us_survey_foot`, `degree` or the EPSG unit code.
    pub units: Option<String>,
    /// What the input looks like it means but does not say (SPEC §2: an undeclared nodata, a
    /// degree grid given one cell size): baked as it is, said here and on the CLI's stderr.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub warnings: Vec<String>,
}

/// The coordinate model of a CRS given outside a TIFF (the Python package's `crs`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CrsModel {
    Projected,
    Geographic,
}

impl Georef {
    /// The georeferencing a GeoTIFF with this GDAL geotransform and CRS would carry: the
    /// tags [`Georef::read`] would return for it (pixel scale and tie point for a north-up
    /// grid, a model transformation otherwise; the model, EPSG code and linear unit as
    /// GeoKeys). For arrays that come with a transform and a CRS instead of TIFF tags (rasterio,
    /// xarray), so the DEM defaults and refusals of SPEC §2 apply to them alike.
    /// `model` `None` is a transform without a CRS (no GeoKeys: a DEM only with `cell_size`
    /// given); `epsg` 0 is a user-defined CRS; `linear_unit` is the EPSG unit code (9001 metre,
    /// 9002 foot, 9003 US survey foot) of a projected CRS; `nodata` becomes GDAL_NODATA.
    pub fn from_gdal(
        transform: [f64; 6],
        model: Option<CrsModel>,
        epsg: u16,
        linear_unit: u16,
        nodata: Option<f64>,
    ) -> Georef {
        let t = transform;
        let (pixel_scale, tiepoints, transformation) = if t[2] == 0.0 && t[4] == 0.0 {
            (Some(vec![t[1], -t[5], 0.0]), Some(vec![0.0, 0.0, 0.0, t[0], t[3], 0.0]), None)
        } else {
            let m = vec![
                t[1], t[2], 0.0, t[0], t[4], t[5], 0.0, t[3], 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0,
                1.0,
            ];
            (None, None, Some(m))
        };
        let code = if epsg == 0 { 32767 } else { epsg };
        let mut keys: Vec<[u16; 4]> = vec![[KEY_RASTER_TYPE, 0, 1, 1]];
        match model {
            None => {}
            Some(CrsModel::Projected) => {
                keys.insert(0, [KEY_MODEL_TYPE, 0, 1, 1]);
                keys.push([KEY_PROJECTED_CS_TYPE, 0, 1, code]);
                keys.push([KEY_PROJ_LINEAR_UNITS, 0, 1, linear_unit]);
            }
            Some(CrsModel::Geographic) => {
                keys.insert(0, [KEY_MODEL_TYPE, 0, 1, 2]);
                keys.push([KEY_GEOGRAPHIC_TYPE, 0, 1, code]);
            }
        }
        let mut geo_keys = vec![1, 1, 0, keys.len() as u16];
        geo_keys.extend(keys.into_iter().flatten());
        let gdal_nodata = nodata.map(|v| if v.is_nan() { "nan".to_owned() } else { v.to_string() });
        Georef {
            pixel_scale,
            tiepoints,
            transformation,
            geo_keys: model.map(|_| geo_keys),
            gdal_nodata,
            ..Georef::default()
        }
    }

    /// Reads the georeferencing tags of the current image of `dec` (all absent: `None`).
    ///
    /// # Errors
    /// A tag present with the wrong type is a decode error.
    pub fn read<R: std::io::Read + std::io::Seek>(
        dec: &mut tiff::decoder::Decoder<R>,
    ) -> Result<Option<Georef>> {
        use tiff::tags::Tag;
        let bad = |what: &str, e: tiff::TiffError| {
            Error::Decode(format!("the TIFF's {what} tag cannot be read: {e}"))
        };
        let f64s = |dec: &mut tiff::decoder::Decoder<R>, tag: u16, what: &str| match dec
            .find_tag(Tag::Unknown(tag))
            .map_err(|e| bad(what, e))?
        {
            None => Ok(None),
            Some(v) => v.into_f64_vec().map(Some).map_err(|e| bad(what, e)),
        };
        let g = Georef {
            pixel_scale: f64s(dec, TAG_MODEL_PIXEL_SCALE, "ModelPixelScale")?,
            tiepoints: f64s(dec, TAG_MODEL_TIEPOINT, "ModelTiepoint")?,
            transformation: f64s(dec, TAG_MODEL_TRANSFORMATION, "ModelTransformation")?,
            geo_keys: match dec
                .find_tag(Tag::Unknown(TAG_GEO_KEY_DIRECTORY))
                .map_err(|e| bad("GeoKeyDirectory", e))?
            {
                None => None,
                Some(v) => Some(
                    v.into_u64_vec()
                        .map_err(|e| bad("GeoKeyDirectory", e))?
                        .into_iter()
                        .map(|k| k as u16)
                        .collect(),
                ),
            },
            geo_doubles: f64s(dec, TAG_GEO_DOUBLE_PARAMS, "GeoDoubleParams")?,
            geo_ascii: match dec
                .find_tag(Tag::Unknown(TAG_GEO_ASCII_PARAMS))
                .map_err(|e| bad("GeoAsciiParams", e))?
            {
                None => None,
                Some(v) => Some(v.into_string().map_err(|e| bad("GeoAsciiParams", e))?),
            },
            gdal_nodata: match dec
                .find_tag(Tag::Unknown(TAG_GDAL_NODATA))
                .map_err(|e| bad("GDAL_NODATA", e))?
            {
                None => None,
                Some(v) => Some(v.into_string().map_err(|e| bad("GDAL_NODATA", e))?),
            },
            // Unreadable metadata is only metadata: the heights decode without it.
            gdal_metadata: dec
                .find_tag(Tag::Unknown(TAG_GDAL_METADATA))
                .ok()
                .flatten()
                .and_then(|v| v.into_string().ok()),
        };
        g.check()?;
        Ok((g != Georef::default()).then_some(g))
    }

    /// Refuses tags no reader could use: a transform with a non-finite number (it would reach
    /// bake.json as `null` and the outputs' GeoTIFF tags as NaN), and a GDAL_NODATA that is no
    /// number (`abc`) or overflows (`1e400`, which parses to infinity); `nan`, `inf` and `-inf`
    /// spelled out are GDAL's own spellings and stay.
    ///
    /// # Errors
    /// [`Error::Decode`] naming the tag.
    fn check(&self) -> Result<()> {
        let tags = [
            ("ModelPixelScale", &self.pixel_scale),
            ("ModelTiepoint", &self.tiepoints),
            ("ModelTransformation", &self.transformation),
        ];
        for (what, values) in tags {
            if values.iter().flatten().any(|v| !v.is_finite()) {
                return Err(Error::Decode(format!(
                    "the TIFF's {what} tag holds a value that is not a finite number"
                )));
            }
        }
        if let Some(raw) = &self.gdal_nodata {
            let t = raw.trim().trim_end_matches('\0').trim();
            let spelled = ["nan", "inf", "-inf", "+inf", "infinity", "-infinity"]
                .iter()
                .any(|s| t.eq_ignore_ascii_case(s));
            if !spelled && !t.parse::<f64>().is_ok_and(f64::is_finite) {
                return Err(Error::Decode(format!(
                    "the TIFF's GDAL_NODATA tag `{}` is not a number this reader can use; \
                     fix the file's nodata (gdal_edit.py -a_nodata VALUE, or -unsetnodata)",
                    t.escape_debug()
                )));
            }
        }
        Ok(())
    }

    /// Whether this is a DEM by SPEC §2: a GeoKeyDirectory and a model transform.
    pub fn is_dem(&self) -> bool {
        self.geo_keys.is_some()
            && (self.transformation.is_some()
                || (self.pixel_scale.is_some() && self.tiepoints.is_some()))
    }

    /// The short value of GeoKey `id` (stored in the directory itself), if present.
    pub fn key(&self, id: u16) -> Option<u16> {
        let k = self.geo_keys.as_ref()?;
        let n = *k.get(3)? as usize;
        (0..n).find_map(|i| {
            let e = k.get(4 + 4 * i..8 + 4 * i)?;
            (e[0] == id && e[1] == 0).then_some(e[3])
        })
    }

    /// The GDAL_NODATA value, parsed (`nan` as NaN).
    pub fn nodata(&self) -> Option<f64> {
        let t = self.gdal_nodata.as_deref()?.trim().trim_end_matches('\0').trim();
        if t.eq_ignore_ascii_case("nan") {
            return Some(f64::NAN);
        }
        t.parse().ok()
    }

    /// The band's GDAL scale (`<Item name="SCALE" sample="0" role="scale">`), when given.
    pub fn band_scale(&self) -> Option<f64> {
        self.metadata_item("scale")
    }

    /// The band's GDAL offset, when given.
    pub fn band_offset(&self) -> Option<f64> {
        self.metadata_item("offset")
    }

    fn metadata_item(&self, role: &str) -> Option<f64> {
        let xml = self.gdal_metadata.as_deref()?;
        let tag = format!("role=\"{role}\"");
        xml.split("<Item").find_map(|item| {
            let (head, rest) = item.split_once('>')?;
            let first_band = !head.contains("sample=") || head.contains("sample=\"0\"");
            if !head.contains(&tag) || !first_band {
                return None;
            }
            rest.split('<').next()?.trim().parse().ok()
        })
    }

    /// The unit of the heights when the keys say (VerticalUnitsGeoKey, or a vertical CRS this
    /// reader knows), as `(name, metres per unit)`; `Err(code)` for a vertical CRS it does not
    /// know; `Ok(None)` when the keys are silent (heights in the CRS's linear unit).
    pub fn vertical_unit(&self) -> std::result::Result<Option<(&'static str, f64)>, u16> {
        let unit = |code: u16| match code {
            9001 => Some(("metre", 1.0)),
            9002 => Some(("foot", 0.3048)),
            9003 => Some(("us_survey_foot", 1200.0 / 3937.0)),
            _ => None,
        };
        if let Some(u) = self.key(KEY_VERTICAL_UNITS).filter(|&u| u != 0 && u != 32767) {
            return unit(u).map(Some).ok_or(u);
        }
        match self.key(KEY_VERTICAL_CS_TYPE).filter(|&c| c != 0 && c != 32767) {
            None => Ok(None),
            Some(c) if VERTICAL_METRE_CRS.contains(&c) => Ok(unit(9001)),
            Some(c) if VERTICAL_FOOT_CRS.contains(&c) => Ok(unit(9002)),
            Some(c) if VERTICAL_US_FOOT_CRS.contains(&c) => Ok(unit(9003)),
            Some(c) => Err(c),
        }
    }

    /// `projected`, `geographic` or `unknown`.
    pub fn model(&self) -> &'static str {
        match self.key(KEY_MODEL_TYPE) {
            Some(1) => "projected",
            Some(2) => "geographic",
            Some(3) => "geocentric",
            _ => "unknown",
        }
    }

    /// The EPSG code of the CRS (projected or geographic), when one is named.
    pub fn epsg(&self) -> Option<u16> {
        let code = match self.model() {
            "geographic" => self.key(KEY_GEOGRAPHIC_TYPE),
            _ => self.key(KEY_PROJECTED_CS_TYPE).or_else(|| self.key(KEY_GEOGRAPHIC_TYPE)),
        }?;
        (code != 0 && code != 32767).then_some(code)
    }

    /// Metres per map unit of a projected CRS (ProjLinearUnitsGeoKey; silent keys: metre, as
    /// GeoTIFF 1.1 writers leave it to the EPSG code; 1 for any other model, whose `cell_size`
    /// is given in metres).
    pub fn linear_unit_m(&self) -> f64 {
        if self.model() != "projected" {
            return 1.0;
        }
        match self.key(KEY_PROJ_LINEAR_UNITS) {
            Some(9002) => 0.3048,
            Some(9003) => 1200.0 / 3937.0,
            _ => 1.0,
        }
    }

    /// Refuses a DEM whose stored values are not heights in its map unit, unless `height_scale`
    /// says how to read them (SPEC §2 "Units of a DEM"): a GDAL band scale other than 1, or
    /// heights in another unit than the cells (a compound CRS with heights in feet over metres).
    /// The drop of `earth_curvature=on` assumes heights in the cells' unit, so a given
    /// `height_scale` needs it off. A band offset moves every height alike and is ignored.
    ///
    /// # Errors
    /// [`Error::InvalidInput`] naming the fix, or [`Error::Param`] naming `earth_curvature`.
    fn check_units(&self, given: crate::params::Explicit, curved: bool, cell: f64) -> Result<()> {
        let scale = self.band_scale().unwrap_or(1.0);
        let lin = self.linear_unit_m();
        let (what, ratio) = match self.vertical_unit() {
            Ok(None) => (None, scale),
            Ok(Some((name, m))) => ((m != lin).then(|| name.to_string()), scale * m / lin),
            Err(code) => {
                if given.has("height_scale") {
                    (Some(format!("the unit of vertical CRS EPSG:{code}")), f64::NAN)
                } else {
                    return Err(Error::InvalidInput(format!(
                        "the DEM's heights are in vertical CRS EPSG:{code}, whose unit this \
                         reader does not know; convert them to the cells' unit (`gdalwarp \
                         -t_srs` to a CRS with heights in metres) or give height_scale (texels \
                         per stored height unit = metres per unit / cell size) with \
                         earth_curvature=off"
                    )));
                }
            }
        };
        if what.is_none() && scale == 1.0 {
            return Ok(());
        }
        if given.has("height_scale") {
            if curved {
                return Err(Error::param(
                    "earth_curvature",
                    "the DEM's stored values are not heights in its map unit (a band scale or \
                     a vertical unit of their own) and height_scale reads them: give \
                     earth_curvature=off with it, or convert the file so the drop is in metres",
                ));
            }
            return Ok(());
        }
        let suggest = ratio / cell;
        Err(Error::InvalidInput(match what {
            Some(unit) => format!(
                "the DEM's heights are in {unit} and its cells in metre (or the CRS's unit); \
                 convert the heights (`gdal_calc.py -A in.tif --outfile out.tif --calc \
                 \"A*{m}\"`) or give height_scale={suggest} (metres per height unit {m} × \
                 band scale {scale} / cell size {cell}) with earth_curvature=off",
                m = ratio / scale * lin
            ),
            None => format!(
                "the DEM's band has a GDAL scale of {scale} (offset {}), so its stored values \
                 are not heights; apply it (`gdal_translate -unscale -ot Float32 in.tif \
                 out.tif`) or give height_scale={suggest} (scale {scale} / cell size {cell}) \
                 with earth_curvature=off",
                self.band_offset().unwrap_or(0.0)
            ),
        }))
    }

    fn units(&self) -> Option<String> {
        if self.model() == "geographic" {
            return Some("degree".into());
        }
        Some(match self.key(KEY_PROJ_LINEAR_UNITS)? {
            9001 => "metre".into(),
            9002 => "foot".into(),
            9003 => "us_survey_foot".into(),
            other => format!("EPSG:{other}"),
        })
    }

    /// For a geographic DEM of `height` rows: the latitude of its centre row and the ratio of
    /// a cell's east–west to its north–south extent there (cos φ for square degree cells),
    /// which a single `cell_size` cannot hold.
    pub fn geographic_squeeze(&self, height: usize) -> Option<(f64, f64)> {
        if self.model() != "geographic" {
            return None;
        }
        let t = self.transform()?;
        let lat = t[3] + t[5] * height as f64 / 2.0;
        let ratio = lat.to_radians().cos() * (t[1] / t[5]).abs();
        (lat.abs() <= 90.0).then_some((lat, ratio))
    }

    /// The GDAL geotransform (PixelIsPoint shifted by half a texel, as GDAL does).
    pub fn transform(&self) -> Option<[f64; 6]> {
        let mut t = if let Some(m) = self.transformation.as_ref().filter(|m| m.len() >= 8) {
            [m[3], m[0], m[1], m[7], m[4], m[5]]
        } else {
            let s = self.pixel_scale.as_ref().filter(|s| s.len() >= 2)?;
            let p = self.tiepoints.as_ref().filter(|p| p.len() >= 6)?;
            [p[3] - p[0] * s[0], s[0], 0.0, p[4] + p[1] * s[1], 0.0, -s[1]]
        };
        if self.key(KEY_RASTER_TYPE) == Some(2) {
            t[0] -= 0.5 * t[1] + 0.5 * t[2];
            t[3] -= 0.5 * t[4] + 0.5 * t[5];
        }
        Some(t)
    }

    /// The report for bake.json, with the cell size the bake used.
    pub fn report(&self, cell_size: Option<f64>) -> GeorefReport {
        GeorefReport {
            model: self.model(),
            epsg: self.epsg(),
            citation: self.geo_ascii.as_ref().map(|s| s.trim_end_matches(['|', '\0']).to_owned()),
            transform: self.transform(),
            cell_size,
            units: self.units(),
            warnings: Vec::new(),
        }
    }

    /// The cell size in map units of a DEM, or the 422 SPEC §2 asks for: a geographic CRS, a
    /// rotated grid and non-square cells each name their fix.
    ///
    /// # Errors
    /// [`Error::InvalidInput`] as above.
    pub fn cell_size(&self) -> Result<f64> {
        let t = self.transform().ok_or_else(|| {
            Error::InvalidInput("the GeoTIFF has GeoKeys but no pixel scale or transform".into())
        })?;
        if self.model() == "geographic" {
            let code = self.epsg().map_or("a geographic CRS".into(), |c| format!("EPSG:{c}"));
            return Err(Error::InvalidInput(format!(
                "the DEM is in {code} (degrees), so its cells have no size in metres; reproject it \
                 to a projected CRS (e.g. `gdalwarp -t_srs EPSG:32632 -r bilinear in.tif out.tif`, \
                 the UTM zone of the area) or give `cell_size` in metres"
            )));
        }
        if t[2] != 0.0 || t[4] != 0.0 {
            return Err(Error::InvalidInput(format!(
                "the DEM's grid is rotated (transform {t:?}); resample it to a north-up grid \
                 (`gdalwarp in.tif out.tif`) or give `cell_size`"
            )));
        }
        let (sx, sy) = (t[1].abs(), t[5].abs());
        if !(sx > 0.0 && sx.is_finite()) || (sx - sy).abs() > 1e-6 * sx.max(sy) {
            return Err(Error::InvalidInput(format!(
                "the DEM's cells are not square ({sx} × {sy} map units); resample it \
                 (`gdalwarp -tr {s} {s} in.tif out.tif`) or give `cell_size`",
                s = sx.min(sy)
            )));
        }
        Ok(sx)
    }
}

/// Applies the DEM defaults of SPEC §2 to the parameters not given explicitly: `method=sweep`
/// (and, with it, `radius=unlimited` unless `radius` or `max_distance` is given), `cell_size` =
/// the pixel scale, `height_scale` = 1 / `cell_size`, `edge=none`, `earth_curvature=on` (with a
/// ray method). Then the full [`BakeParams::check`]. For a plain image only `cell_size` given
/// by hand makes `max_distance` and the curvature usable.
/// Idempotent: parameters already resolved (and so explicit) stay as they are.
///
/// # Errors
/// The refusals of [`Georef::cell_size`] (unless `cell_size` is given, which overrides the
/// georeferencing); `max_distance` or `earth_curvature=on` without a cell size.
pub fn apply_dem_defaults(params: &mut BakeParams, georef: Option<&Georef>) -> Result<()> {
    use crate::params::{Method, Radius};
    let ex = params.explicit;
    if let Some(t) = georef.filter(|g| !g.is_dem()).and_then(Georef::transform) {
        // A map transform without a CRS: GIS data whose cell size and units are unknown, not a
        // texture; with `cell_size` it is baked as a DEM.
        if !ex.has("cell_size") {
            return Err(Error::InvalidInput(format!(
                "the TIFF has a map transform but no CRS (no GeoKeyDirectory), so its cell size \
                 and units are unknown; give cell_size (the transform says {} map units per \
                 texel) to bake it as a DEM, or assign its CRS (`gdal_edit.py -a_srs EPSG:XXXX \
                 in.tif`)",
                t[1].abs()
            )));
        }
    }
    // The sun's place (SPEC §3.7): the DEM's centre through its projection, else given.
    if params.outputs.sun()
        && params.latitude.is_none()
        && georef.filter(|g| g.is_dem()).is_none_or(|g| super::north::Geodesy::of(g).is_err())
    {
        return Err(Error::param(
            "latitude",
            "sun_hours and insolation need the sun's place: give latitude and longitude (this \
             map has no projection that places its centre)",
        ));
    }
    let dem = georef.filter(|g| g.is_dem() || (g.transform().is_some() && ex.has("cell_size")));
    if dem.is_some() && !ex.has("method") {
        // A line of sight, to the edge unless a reach is given (SPEC §2). Left unmarked, so
        // [`crate::bake::fit_method`] may still trade `sweep` for `exact` on a map `sweep`
        // cannot take, and the resolved pair is what the bake stores.
        params.method = Method::Sweep;
        if !ex.has("radius") && !ex.has("max_distance") {
            params.radius = Radius::Unlimited;
        }
    }
    // The drop is in metres, the map in its CRS's unit (SPEC §2): always from the input, as
    // it is no parameter the stored pairs could carry.
    params.linear_unit_m = dem.map_or(1.0, Georef::linear_unit_m);
    // The methods that cast rays, and so can lower far points (lengyel has no ray).
    let rays = matches!(params.method, Method::Exact | Method::March | Method::Sweep);
    if let Some(g) = dem {
        let cell = match params.cell_size {
            Some(c) => c,
            None => g.cell_size()?,
        };
        let mut set = |k: &str, v: String| -> Result<()> {
            if !ex.has(k) {
                params.set(k, &v)?;
            }
            Ok(())
        };
        set("cell_size", cell.to_string())?;
        set("height_scale", (1.0 / cell).to_string())?;
        set("edge", "none".into())?;
        // Only the ray methods model the drop: the others keep it off by default (and refuse
        // it when asked, below).
        if rays {
            set("earth_curvature", "on".into())?;
        }
        g.check_units(ex, params.earth_curvature == EarthCurvature::On, cell)?;
    }
    if params.earth_curvature == EarthCurvature::On && !rays {
        return Err(Error::param(
            "earth_curvature",
            "is modelled by the ray methods (exact, march, sweep) only; use one of them or \
             earth_curvature=off",
        ));
    }
    if params.cell_size.is_none() {
        if params.max_distance.is_some() {
            return Err(Error::param(
                "max_distance",
                "needs a cell size: a georeferenced (GeoTIFF) input or `cell_size`",
            ));
        }
        if params.earth_curvature == EarthCurvature::On {
            return Err(Error::param(
                "earth_curvature",
                "needs a cell size: a georeferenced (GeoTIFF) input or `cell_size`",
            ));
        }
    }
    debug_assert!(dem.is_none() || params.edge == Edge::None || ex.has("edge"));
    // The rules that waited for the method (`bins` and `reduce` with `lengyel`).
    params.check()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn with(f: impl FnOnce(&mut Georef)) -> Result<()> {
        let mut g = Georef {
            pixel_scale: Some(vec![30.0, 30.0, 0.0]),
            tiepoints: Some(vec![0.0, 0.0, 0.0, 500_000.0, 4_000_000.0, 0.0]),
            ..Georef::default()
        };
        f(&mut g);
        g.check()
    }

    /// A non-finite tie point, scale or transform, and a GDAL_NODATA that is no number or
    /// overflows, are decode errors naming the tag; GDAL's spellings of NaN and infinity stay.
    #[test]
    fn unusable_tags_are_refused_by_name() {
        assert!(with(|_| ()).is_ok());
        let msg = |r: Result<()>| match r {
            Err(Error::Decode(m)) => m,
            other => panic!("not refused: {other:?}"),
        };
        let m = msg(with(|g| g.tiepoints.as_mut().unwrap()[3] = f64::NAN));
        assert!(m.contains("ModelTiepoint"), "{m}");
        let m = msg(with(|g| g.pixel_scale.as_mut().unwrap()[0] = f64::INFINITY));
        assert!(m.contains("ModelPixelScale"), "{m}");
        let m = msg(with(|g| g.transformation = Some(vec![f64::NAN; 16])));
        assert!(m.contains("ModelTransformation"), "{m}");
        for bad in ["abc", "1e400", "-1e999", ""] {
            let m = msg(with(|g| g.gdal_nodata = Some(bad.into())));
            assert!(m.contains("GDAL_NODATA") && m.contains("-a_nodata"), "{bad}: {m}");
        }
        for good in ["-32768", "nan", "-inf", "3.4028234663852886e+38", "-9999\0"] {
            assert!(with(|g| g.gdal_nodata = Some(good.into())).is_ok(), "{good}");
        }
    }

    /// GDAL's band scale and offset are read from GDAL_METADATA for the first band only; the
    /// vertical unit comes from VerticalUnitsGeoKey, else a vertical CRS this reader knows, and
    /// an unknown one is named by code.
    #[test]
    fn band_scale_and_vertical_units_are_read_from_the_tags() {
        let xml = r#"<GDALMetadata>
  <Item name="STATISTICS_MEAN" sample="0">12.5</Item>
  <Item name="OFFSET" sample="0" role="offset">10</Item>
  <Item name="SCALE" sample="1" role="scale">7</Item>
  <Item name="SCALE" sample="0" role="scale">0.20000000000000001</Item>
</GDALMetadata>"#;
        let g = Georef { gdal_metadata: Some(xml.into()), ..Georef::default() };
        assert_eq!((g.band_scale(), g.band_offset()), (Some(0.2), Some(10.0)));
        assert_eq!(Georef::default().band_scale(), None);
        let keys = |extra: &[u16]| {
            let mut k = vec![1, 1, 1, 2, 1024, 0, 1, 1, 3072, 0, 1, 2056];
            k.extend_from_slice(extra);
            k[3] = ((k.len() - 4) / 4) as u16;
            Georef { geo_keys: Some(k), ..Georef::default() }
        };
        assert_eq!(keys(&[]).vertical_unit(), Ok(None));
        assert_eq!(keys(&[4096, 0, 1, 8228]).vertical_unit(), Ok(Some(("foot", 0.3048))));
        assert_eq!(keys(&[4096, 0, 1, 5703]).vertical_unit(), Ok(Some(("metre", 1.0))));
        let us = keys(&[4096, 0, 1, 5703, 4099, 0, 1, 9003]).vertical_unit();
        assert_eq!(us, Ok(Some(("us_survey_foot", 1200.0 / 3937.0))));
        assert_eq!(keys(&[4096, 0, 1, 1234]).vertical_unit(), Err(1234));
    }

    /// A geotransform and CRS given outside a TIFF read back as the same transform, model,
    /// EPSG code, unit and nodata, and pass the checks a decoded GeoTIFF passes.
    #[test]
    fn from_gdal_round_trips_the_transform_and_crs() {
        let t = [500_000.0, 20.0, 0.0, 4_000_000.0, 0.0, -20.0];
        let g = Georef::from_gdal(t, Some(CrsModel::Projected), 32633, 9002, Some(-9999.0));
        assert!(g.is_dem());
        assert!(g.check().is_ok());
        assert_eq!(g.transform(), Some(t));
        assert_eq!((g.model(), g.epsg(), g.linear_unit_m()), ("projected", Some(32633), 0.3048));
        assert_eq!(g.nodata(), Some(-9999.0));
        assert_eq!(g.cell_size().ok(), Some(20.0));
        let rotated = [10.0, 1.0, 0.5, 20.0, 0.5, -1.0];
        let g = Georef::from_gdal(rotated, Some(CrsModel::Geographic), 4326, 9001, Some(f64::NAN));
        assert_eq!(g.transform(), Some(rotated));
        assert_eq!((g.model(), g.epsg()), ("geographic", Some(4326)));
        assert!(g.nodata().is_some_and(f64::is_nan));
        assert!(matches!(g.cell_size(), Err(Error::InvalidInput(m)) if m.contains("EPSG:4326")));
        let custom = Georef::from_gdal(t, Some(CrsModel::Projected), 0, 9001, None);
        assert_eq!((custom.epsg(), custom.nodata()), (None, None));
        let bare = Georef::from_gdal(t, None, 0, 0, None);
        assert!(!bare.is_dem());
        assert_eq!(bare.transform(), Some(t));
    }
}
