//! Bake parameters: parsing, validation and defaults (SPEC §2, §3, §5).
//!
//! Parameters arrive three ways: as a JSON object (multipart `params` part), as a query string
//! (raw-body upload) and as CLI flags. All three go through one string-keyed setter,
//! [`BakeParams::set`], so a value means the same thing and fails with the same message whichever
//! way it came in, and every error names the field as the API spells it.

use crate::error::{Error, Result};
use serde::{Deserialize, Serialize};
use std::fmt;

/// Which channel of an RGB(A) image holds the height (gray images ignore it).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Hash)]
#[serde(rename_all = "lowercase")]
pub enum Channel {
    R,
    G,
    B,
    A,
    /// 0.2126 R + 0.7152 G + 0.0722 B on the normalised stored values.
    Luma,
}

/// What lies beyond the map's border.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Hash)]
#[serde(rename_all = "lowercase")]
pub enum Edge {
    /// The map tiles.
    Wrap,
    /// Nothing outside the map occludes.
    None,
}

/// Orientation of tangent-space +y relative to the image rows.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Hash)]
#[serde(rename_all = "lowercase")]
pub enum YAxis {
    /// +y toward the top of the image (OpenGL, "Y+").
    Up,
    /// +y toward the bottom of the image (DirectX, "Y−").
    Down,
}

/// Which horizon kernel computes the bake.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Hash)]
#[serde(rename_all = "lowercase")]
pub enum Method {
    /// Lengyel/Max 32-bin splat with 5-bin averaging (SPEC §3.1).
    Lengyel,
    /// Exact line-of-sight horizon on the bilinear surface (SPEC §3.2).
    Exact,
    /// The §3.2 horizon sampled at grid-line crossings, vectorised (SPEC §3.2a).
    March,
    /// Exact near field plus convex-hull line sweeps, any radius at a cost independent of it
    /// (SPEC §3.2a).
    Sweep,
}

/// Every `method` by name, in the order a user is offered them.
pub const METHODS: &[(&str, Method)] = &[
    ("lengyel", Method::Lengyel),
    ("exact", Method::Exact),
    ("march", Method::March),
    ("sweep", Method::Sweep),
];

/// How far occluders are searched.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Radius {
    /// A fixed radius in texels.
    Texels(u32),
    /// To the edge of the map (or max(W, H) texels when wrapping).
    Unlimited,
    /// Derived from the map's height range and `min_elevation_deg` (SPEC §3.6).
    Auto,
}

impl fmt::Display for Radius {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Radius::Texels(r) => write!(f, "{r}"),
            Radius::Unlimited => f.write_str("unlimited"),
            Radius::Auto => f.write_str("auto"),
        }
    }
}

impl Serialize for Radius {
    fn serialize<S: serde::Serializer>(&self, s: S) -> std::result::Result<S::Ok, S::Error> {
        match self {
            Radius::Texels(r) => s.serialize_u32(*r),
            other => s.serialize_str(&other.to_string()),
        }
    }
}

/// How the `bins` azimuth samples of `method=exact` are reduced to 8 channels.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Hash)]
#[serde(rename_all = "lowercase")]
pub enum Reduce {
    /// Mean over the B/8+1 bins centred on each channel, as Lengyel's kernel does.
    Average,
    /// The bin at the channel's azimuth.
    Point,
}

/// How a horizon value s is stored.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Hash)]
#[serde(rename_all = "lowercase")]
pub enum Encoding {
    /// s itself.
    Linear,
    /// √s (decode with v²): more precision near grazing angles.
    Sqrt,
}

/// Range mapping of the companded Fourier coefficients (SPEC §3.4).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Hash)]
#[serde(rename_all = "lowercase")]
pub enum FourierRange {
    Standard,
    /// Uses the ±2/π coefficient bound to spread the stored range.
    Expanded,
}

/// Which results a bake computes. Only what is asked for is computed and encoded.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Hash)]
pub struct Outputs {
    pub horizon: bool,
    pub fourier: bool,
    /// Horizon angles at every bin, no channel reduction (SPEC §3.7), as `angles.tif`.
    #[serde(default)]
    pub angles: bool,
    /// The sky-view factor (SPEC §3.7), as `svf.tif`.
    #[serde(default)]
    pub svf: bool,
    /// The tangent-space normal map (SPEC §3.8), as `normal.png`.
    #[serde(default)]
    pub normal: bool,
    /// Ambient occlusion from the horizons (SPEC §3.8), as `ao.png`.
    #[serde(default)]
    pub ao: bool,
    /// The bent normal (SPEC §3.8), as `bent_normal.png`.
    #[serde(default)]
    pub bent_normal: bool,
    /// The distance to the point that sets each bin's horizon (SPEC §3.7), as
    /// `horizon_distance.tif`.
    #[serde(default)]
    pub horizon_distance: bool,
    /// Positive and negative openness (SPEC §3.7), as `openness_positive.tif` and
    /// `openness_negative.tif`.
    #[serde(default)]
    pub openness: bool,
    /// Hours of direct sun over `date_from`..`date_to` (SPEC §3.7), as `sun_hours.tif`.
    #[serde(default)]
    pub sun_hours: bool,
    /// The clear-sky direct beam on the tilted surface over the same days, Wh/m², as
    /// `insolation.tif`.
    #[serde(default)]
    pub insolation: bool,
}

impl Outputs {
    /// Nothing asked for: what `outputs=` parses into before its names.
    pub const NONE: Outputs = Outputs {
        horizon: false,
        fourier: false,
        angles: false,
        svf: false,
        normal: false,
        ao: false,
        bent_normal: false,
        horizon_distance: false,
        openness: false,
        sun_hours: false,
        insolation: false,
    };

    /// Whether a terrain product (SPEC §3.7) is asked for.
    pub fn terrain(&self) -> bool {
        self.angles || self.svf || self.horizon_distance || self.openness || self.sun()
    }

    /// Whether a product of the sun over days (SPEC §3.7 `sun_hours`, `insolation`) is asked.
    pub fn sun(&self) -> bool {
        self.sun_hours || self.insolation
    }

    /// Whether a surface map (SPEC §3.8) is asked for.
    pub fn surface(&self) -> bool {
        self.normal || self.ao || self.bent_normal
    }
}

impl Default for Outputs {
    fn default() -> Self {
        Outputs { horizon: true, ..Outputs::NONE }
    }
}

impl fmt::Display for Outputs {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let mut parts = Vec::new();
        if self.horizon {
            parts.push("horizon");
        }
        if self.fourier {
            parts.push("fourier");
        }
        if self.angles {
            parts.push("angles");
        }
        if self.svf {
            parts.push("svf");
        }
        if self.normal {
            parts.push("normal");
        }
        if self.ao {
            parts.push("ao");
        }
        if self.bent_normal {
            parts.push("bent_normal");
        }
        if self.horizon_distance {
            parts.push("horizon_distance");
        }
        if self.openness {
            parts.push("openness");
        }
        if self.sun_hours {
            parts.push("sun_hours");
        }
        if self.insolation {
            parts.push("insolation");
        }
        f.write_str(&parts.join(","))
    }
}

/// Unit of the horizon angles in `angles.tif` (SPEC §3.7).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Hash)]
#[serde(rename_all = "lowercase")]
pub enum AngleUnit {
    Degrees,
    Radians,
    /// sin α, as the horizon layers store it.
    Sin,
}

/// How the bands of `angles.tif` count azimuths (SPEC §3.7).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Hash)]
#[serde(rename_all = "snake_case")]
pub enum AzimuthFrom {
    /// φ of SPEC §2: counter-clockwise from +x (east on a north-up map), as GRASS counts.
    EastCcw,
    /// Compass: clockwise from north (+y with `y_axis=up`), as Whitebox and PVGIS count.
    NorthCw,
}

/// Which sky-view factor (SPEC §3.7).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Hash)]
#[serde(rename_all = "lowercase")]
pub enum SvfModel {
    /// mean cos² α: the share of isotropic diffuse light on a horizontal surface.
    Radiative,
    /// 1 − mean sin α (Zakšek et al. 2011, RVT).
    Visual,
    /// The share of isotropic diffuse light on the tilted surface itself (Dozier & Frew 1990
    /// for a slope): the sky above both the horizon and the surface's own plane, cosine-weighted
    /// about its normal.
    Tilted,
}

/// How `normal.png` stores the normal's y (SPEC §3.8).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Hash, Default)]
#[serde(rename_all = "lowercase")]
pub enum NormalConvention {
    /// Y+ (Godot, Blender, Unity): the stored y points up the image, whatever `y_axis`.
    #[default]
    OpenGl,
    /// Y− (Unreal): the stored y points down the image.
    DirectX,
}

/// What `bent_normal.png` holds (SPEC §3.8).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Hash, Default)]
#[serde(rename_all = "snake_case")]
pub enum BentNormalEncoding {
    /// x, y, z as (v + 1) / 2.
    #[default]
    Rgb,
    /// x, y only (z rebuilt from them: Godot's `bent_normal_texture`).
    Rg,
    /// x, y, z and the ambient occlusion in alpha (as Knald packs it).
    RgbAo,
}

/// Whether far terrain drops with the earth's curvature (SPEC §3.7).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Hash)]
#[serde(rename_all = "lowercase")]
pub enum EarthCurvature {
    Off,
    On,
}

/// Which input value is a hole (SPEC §2 "Nodata").
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum NoData {
    /// The file's GDAL_NODATA tag, if any (default).
    Auto,
    /// No value is a hole, whatever the file says.
    None,
    /// Texels holding NaN.
    Nan,
    /// Texels holding this value (as stored in the file).
    Value(f64),
}

impl Serialize for NoData {
    fn serialize<S: serde::Serializer>(&self, s: S) -> std::result::Result<S::Ok, S::Error> {
        match self {
            NoData::Value(v) => s.serialize_f64(*v),
            other => s.serialize_str(&other.to_string()),
        }
    }
}

impl fmt::Display for NoData {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            NoData::Auto => f.write_str("auto"),
            NoData::None => f.write_str("none"),
            NoData::Nan => f.write_str("nan"),
            NoData::Value(v) => write!(f, "{v}"),
        }
    }
}

/// Which parameters were set explicitly (by name, as a bit per [`PARAM_NAMES`] index), so the
/// DEM defaults of SPEC §2 apply only to the others. It is bookkeeping, not a parameter: two
/// parameter sets compare equal whatever was explicit.
#[derive(Debug, Clone, Copy, Default)]
pub struct Explicit(u64);

impl PartialEq for Explicit {
    fn eq(&self, _: &Self) -> bool {
        true
    }
}

impl Explicit {
    fn mark(&mut self, key: &str) {
        if let Some(i) = PARAM_NAMES.iter().position(|n| *n == key) {
            self.0 |= 1 << i;
        }
    }

    /// Whether `key` was given.
    pub fn has(&self, key: &str) -> bool {
        PARAM_NAMES.iter().position(|n| *n == key).is_some_and(|i| self.0 & (1 << i) != 0)
    }
}

/// Upper bounds that keep a single bake's cost finite; each is documented in the README.
pub const MAX_BINS: u32 = 256;
/// Most azimuths of `angles`/`svf` with a ray method (SPEC §3.7).
pub const MAX_TERRAIN_BINS: u32 = 720;
/// Largest fixed radius accepted (the Lengyel splat costs O(R²) per texel).
pub const MAX_RADIUS: u32 = 4096;
/// Largest absolute `height_scale` accepted.
pub const MAX_HEIGHT_SCALE: f64 = 1e9;

/// Every parameter of a bake (SPEC §5), with its default.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct BakeParams {
    /// Height in texels = normalised value × `height_scale`.
    pub height_scale: f64,
    pub channel: Channel,
    pub edge: Edge,
    pub y_axis: YAxis,
    pub method: Method,
    pub radius: Radius,
    pub bins: u32,
    pub reduce: Reduce,
    /// Lowest light elevation the scene uses, in degrees; drives `radius=auto`.
    pub min_elevation_deg: f64,
    pub encoding: Encoding,
    pub outputs: Outputs,
    pub fourier_terms: u32,
    pub fourier_range: FourierRange,
    /// Which value is a hole (SPEC §2).
    pub nodata: NoData,
    /// Map units per texel; `None`: from the georeferencing, if any.
    pub cell_size: Option<f64>,
    /// The radius in map units; resolves to ceil(max_distance / cell_size) texels and then
    /// takes the place of `radius`.
    pub max_distance: Option<f64>,
    /// Off by default; on for georeferenced input unless given (SPEC §2).
    pub earth_curvature: EarthCurvature,
    /// Refraction coefficient of the curvature drop (R_e = 6 371 km / (1 − refraction)).
    pub refraction: f64,
    pub angle_unit: AngleUnit,
    pub azimuth_from: AzimuthFrom,
    pub svf_model: SvfModel,
    pub normal_convention: NormalConvention,
    pub bent_normal_encoding: BentNormalEncoding,
    /// The band (sample) of a multi-band TIFF the heights are read from, 1-based; `None`:
    /// `channel` decides (a DEM with several bands then needs it, SPEC §2).
    pub band: Option<u8>,
    /// The first and last local solar day (`YYYY-MM-DD`, `date` sets both) of `sun_hours` and
    /// `insolation` (SPEC §3.7).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub date_from: Option<String>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub date_to: Option<String>,
    /// Minutes between the sun positions sampled over a day (`None`: 10).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub time_step_minutes: Option<u32>,
    /// The place of the sun's position, degrees (`None`: the DEM's centre).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub latitude: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub longitude: Option<f64>,
    /// Metres per map unit of the input's CRS (1 for metre CRSs, cell sizes given in metres and
    /// plain images): read from the input with the DEM defaults, never a parameter; the
    /// curvature drop is in metres.
    #[serde(skip)]
    pub linear_unit_m: f64,
    /// Which of the above were given (the rest may take the DEM defaults).
    #[serde(skip)]
    pub explicit: Explicit,
}

impl Default for BakeParams {
    fn default() -> Self {
        BakeParams {
            height_scale: 8.0,
            channel: Channel::Luma,
            edge: Edge::Wrap,
            y_axis: YAxis::Up,
            method: Method::Lengyel,
            radius: Radius::Texels(16),
            bins: 32,
            reduce: Reduce::Average,
            min_elevation_deg: 5.0,
            encoding: Encoding::Linear,
            outputs: Outputs::default(),
            fourier_terms: 5,
            fourier_range: FourierRange::Standard,
            nodata: NoData::Auto,
            cell_size: None,
            max_distance: None,
            earth_curvature: EarthCurvature::Off,
            refraction: 0.0,
            angle_unit: AngleUnit::Degrees,
            azimuth_from: AzimuthFrom::EastCcw,
            svf_model: SvfModel::Radiative,
            normal_convention: NormalConvention::OpenGl,
            bent_normal_encoding: BentNormalEncoding::Rgb,
            band: None,
            date_from: None,
            date_to: None,
            time_step_minutes: None,
            latitude: None,
            longitude: None,
            linear_unit_m: 1.0,
            explicit: Explicit::default(),
        }
    }
}

/// The names `set` accepts, in SPEC order.
pub const PARAM_NAMES: &[&str] = &[
    "height_scale",
    "channel",
    "edge",
    "y_axis",
    "method",
    "radius",
    "bins",
    "reduce",
    "min_elevation_deg",
    "encoding",
    "outputs",
    "fourier_terms",
    "fourier_range",
    "nodata",
    "cell_size",
    "max_distance",
    "earth_curvature",
    "refraction",
    "angle_unit",
    "azimuth_from",
    "svf_model",
    "band",
    "normal_convention",
    "bent_normal_encoding",
    "date",
    "date_from",
    "date_to",
    "time_step_minutes",
    "latitude",
    "longitude",
];

/// The default of `time_step_minutes`.
pub const DEFAULT_TIME_STEP_MINUTES: u32 = 10;
/// Most days one `sun_hours`/`insolation` bake spans (a year and a day).
pub const MAX_SUN_DAYS: i64 = 366;

/// (year, month, day) of a `YYYY-MM-DD` date, or a parameter error naming `field`.
pub fn parse_date(field: &str, value: &str) -> Result<(i32, u32, u32)> {
    let bad = || Error::param(field, format!("`{value}` is not a date YYYY-MM-DD"));
    let mut it = value.trim().splitn(3, '-');
    let y: i32 = it.next().and_then(|v| v.parse().ok()).ok_or_else(bad)?;
    let m: u32 = it.next().and_then(|v| v.parse().ok()).ok_or_else(bad)?;
    let d: u32 = it.next().and_then(|v| v.parse().ok()).ok_or_else(bad)?;
    let leap = (y % 4 == 0 && y % 100 != 0) || y % 400 == 0;
    let days = [31, if leap { 29 } else { 28 }, 31, 30, 31, 30, 31, 31, 30, 31, 30, 31];
    if !(1..=9999).contains(&y) || !(1..=12).contains(&m) || d < 1 || d > days[m as usize - 1] {
        return Err(bad());
    }
    Ok((y, m, d))
}

/// Days since 1970-01-01 of a civil date (Howard Hinnant's `days_from_civil`).
pub fn days_from_civil((y, m, d): (i32, u32, u32)) -> i64 {
    let y = i64::from(y) - i64::from(m <= 2);
    let era = y.div_euclid(400);
    let yoe = y - era * 400;
    let mp = (i64::from(m) + 9) % 12;
    let doy = (153 * mp + 2) / 5 + i64::from(d) - 1;
    era * 146_097 + yoe * 365 + yoe / 4 - yoe / 100 + doy - 719_468
}

pub(crate) fn parse_enum<T: Copy>(field: &str, value: &str, options: &[(&str, T)]) -> Result<T> {
    let v = value.trim().to_ascii_lowercase();
    options.iter().find(|(name, _)| *name == v).map(|(_, t)| *t).ok_or_else(|| {
        let names: Vec<&str> = options.iter().map(|(n, _)| *n).collect();
        Error::param(field, format!("`{value}` is not one of {}", names.join(", ")))
    })
}

/// A finite number, or a parameter error naming `field`.
pub(crate) fn parse_f64(field: &str, value: &str) -> Result<f64> {
    let v: f64 = value
        .trim()
        .parse()
        .map_err(|_| Error::param(field, format!("`{value}` is not a number")))?;
    if !v.is_finite() {
        return Err(Error::param(field, "must be a finite number"));
    }
    Ok(v)
}

/// A non-negative whole number ("16.0" accepted), or a parameter error naming `field`.
pub(crate) fn parse_u32(field: &str, value: &str) -> Result<u32> {
    let t = value.trim();
    // Accept "16.0" from JSON clients that only have doubles, but not "16.5".
    if let Ok(v) = t.parse::<u32>() {
        return Ok(v);
    }
    match t.parse::<f64>() {
        Ok(f) if f.fract() == 0.0 && (0.0..=u32::MAX as f64).contains(&f) => Ok(f as u32),
        _ => Err(Error::param(field, format!("`{value}` is not a non-negative whole number"))),
    }
}

/// Most members a `params` JSON object may have: every bake and delivery parameter fits many
/// times over, and the bound keeps a hostile object from costing more than its first members.
pub const MAX_JSON_MEMBERS: usize = 256;

/// Most bytes of a multipart `params` part (64 KiB), read before it is parsed: a 413 beyond.
pub const MAX_PARAMS_BYTES: usize = 64 << 10;

/// The members of a JSON object in document order, refusing a key given twice (serde_json would
/// silently keep the last one; SPEC-wise a duplicate is a 422 naming the key, as in a query).
/// Linear in the text: keys are checked against a set, and at most [`MAX_JSON_MEMBERS`] are
/// read.
///
/// # Errors
/// [`Error::Param`] naming `params` for text that is not a JSON object or has more than
/// [`MAX_JSON_MEMBERS`] members, or naming the duplicated key.
pub fn json_object_pairs(text: &[u8]) -> Result<Vec<(String, serde_json::Value)>> {
    use serde::de::{Deserializer as _, MapAccess, Visitor};
    struct Pairs;
    impl<'de> Visitor<'de> for Pairs {
        type Value = Vec<(String, serde_json::Value)>;
        fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
            f.write_str("a JSON object")
        }
        fn visit_map<A: MapAccess<'de>>(
            self,
            mut map: A,
        ) -> std::result::Result<Self::Value, A::Error> {
            let mut out: Vec<(String, serde_json::Value)> = Vec::new();
            let mut seen = std::collections::HashSet::new();
            while let Some(k) = map.next_key::<String>()? {
                // Counted before the value is read, so a body of a million members stops at
                // the first one past the bound.
                if out.len() == MAX_JSON_MEMBERS {
                    return Err(serde::de::Error::custom(TooMany));
                }
                if !seen.insert(k.clone()) {
                    return Err(serde::de::Error::custom(DuplicateKey(k)));
                }
                let v = map.next_value::<serde_json::Value>()?;
                out.push((k, v));
            }
            Ok(out)
        }
    }
    /// Marks the member-count refusal in serde's error text.
    struct TooMany;
    impl std::fmt::Display for TooMany {
        fn fmt(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
            f.write_str("\u{2}")
        }
    }
    /// Carries the duplicated key through serde's error text.
    struct DuplicateKey(String);
    impl std::fmt::Display for DuplicateKey {
        fn fmt(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
            write!(f, "\u{1}{}\u{1}", self.0)
        }
    }
    let mut de = serde_json::Deserializer::from_slice(text);
    let pairs = de.deserialize_map(Pairs).and_then(|p| de.end().map(|()| p));
    pairs.map_err(|e| {
        let msg = e.to_string();
        let mut parts = msg.split('\u{1}');
        match (parts.next(), parts.next()) {
            _ if msg.contains('\u{2}') => Error::param(
                "params",
                format!("has more than {MAX_JSON_MEMBERS} members; a bake takes far fewer"),
            ),
            (Some(_), Some(key)) => Error::param(key, "given more than once"),
            _ if e.is_data() => Error::param("params", "must be a JSON object"),
            _ => Error::param("params", format!("not valid JSON: {e}")),
        }
    })
}

/// The textual value of one JSON member (None for `null`, meaning the default).
///
/// # Errors
/// [`Error::Param`] naming `key` for a boolean, an object or a non-string array item.
pub fn json_value_text(key: &str, v: &serde_json::Value) -> Result<Option<String>> {
    Ok(Some(match v {
        serde_json::Value::Null => return Ok(None),
        serde_json::Value::String(s) => s.clone(),
        serde_json::Value::Number(n) => n.to_string(),
        serde_json::Value::Bool(_) | serde_json::Value::Object(_) => {
            return Err(Error::param(key, "must be a number or a string"))
        }
        serde_json::Value::Array(items) => {
            let mut parts = Vec::new();
            for it in items {
                match it {
                    serde_json::Value::String(s) => parts.push(s.clone()),
                    _ => return Err(Error::param(key, "array items must be strings")),
                }
            }
            parts.join(",")
        }
    }))
}

impl BakeParams {
    /// Sets one parameter from its textual value, validating it.
    ///
    /// # Errors
    /// [`Error::Param`] naming `key` when the key is unknown or the value is invalid.
    pub fn set(&mut self, key: &str, value: &str) -> Result<()> {
        match key {
            "height_scale" => {
                let v = parse_f64(key, value)?;
                if v < 0.0 {
                    return Err(Error::param(key, "must not be negative"));
                }
                if v > MAX_HEIGHT_SCALE {
                    return Err(Error::param(key, format!("must be at most {MAX_HEIGHT_SCALE:e}")));
                }
                self.height_scale = v;
            }
            "channel" => {
                self.channel = parse_enum(
                    key,
                    value,
                    &[
                        ("r", Channel::R),
                        ("g", Channel::G),
                        ("b", Channel::B),
                        ("a", Channel::A),
                        ("luma", Channel::Luma),
                    ],
                )?
            }
            "edge" => {
                self.edge = parse_enum(key, value, &[("wrap", Edge::Wrap), ("none", Edge::None)])?
            }
            "y_axis" => {
                self.y_axis = parse_enum(key, value, &[("up", YAxis::Up), ("down", YAxis::Down)])?
            }
            "method" => self.method = parse_enum(key, value, METHODS)?,
            "radius" => {
                self.radius = match value.trim().to_ascii_lowercase().as_str() {
                    "unlimited" => Radius::Unlimited,
                    "auto" => Radius::Auto,
                    _ => {
                        let r = parse_u32(key, value).map_err(|_| {
                            Error::param(
                                key,
                                format!(
                                    "`{value}` is not a positive whole number, `unlimited` or `auto`"
                                ),
                            )
                        })?;
                        if r == 0 {
                            return Err(Error::param(key, "must be at least 1 texel"));
                        }
                        if r > MAX_RADIUS {
                            return Err(Error::param(
                                key,
                                format!("must be at most {MAX_RADIUS} (use `unlimited`)"),
                            ));
                        }
                        Radius::Texels(r)
                    }
                }
            }
            "bins" => {
                // The multiple-of-16 rule depends on `method` and `outputs`: see `check`.
                let b = parse_u32(key, value)?;
                if b == 0 || b > MAX_TERRAIN_BINS {
                    return Err(Error::param(
                        key,
                        format!("must be between 1 and {MAX_TERRAIN_BINS}, got {b}"),
                    ));
                }
                self.bins = b;
            }
            "reduce" => {
                self.reduce = parse_enum(
                    key,
                    value,
                    &[("average", Reduce::Average), ("point", Reduce::Point)],
                )?
            }
            "min_elevation_deg" => {
                let v = parse_f64(key, value)?;
                if !(v > 0.0 && v < 90.0) {
                    return Err(Error::param(key, "must be strictly between 0 and 90 degrees"));
                }
                self.min_elevation_deg = v;
            }
            "encoding" => {
                self.encoding = parse_enum(
                    key,
                    value,
                    &[("linear", Encoding::Linear), ("sqrt", Encoding::Sqrt)],
                )?
            }
            "outputs" => {
                const NAMES: &str =
                    "horizon, fourier, angles, svf, normal, ao, bent_normal, horizon_distance, \
                     openness, sun_hours, insolation";
                let mut o = Outputs::NONE;
                for part in value.split(',').map(str::trim).filter(|p| !p.is_empty()) {
                    match part.to_ascii_lowercase().as_str() {
                        "horizon" => o.horizon = true,
                        "fourier" => o.fourier = true,
                        "angles" => o.angles = true,
                        "svf" => o.svf = true,
                        "normal" => o.normal = true,
                        "ao" => o.ao = true,
                        "bent_normal" => o.bent_normal = true,
                        "horizon_distance" => o.horizon_distance = true,
                        "openness" => o.openness = true,
                        "sun_hours" => o.sun_hours = true,
                        "insolation" => o.insolation = true,
                        _ => {
                            return Err(Error::param(
                                key,
                                format!("`{part}` is not one of {NAMES}"),
                            ))
                        }
                    }
                }
                if !o.horizon && !o.fourier && !o.terrain() && !o.surface() {
                    return Err(Error::param(key, format!("must name at least one of {NAMES}")));
                }
                self.outputs = o;
            }
            "fourier_terms" => {
                let t = parse_u32(key, value)?;
                if ![3, 5, 7, 9].contains(&t) {
                    return Err(Error::param(key, format!("must be 3, 5, 7 or 9, got {t}")));
                }
                self.fourier_terms = t;
            }
            "fourier_range" => {
                self.fourier_range = parse_enum(
                    key,
                    value,
                    &[("standard", FourierRange::Standard), ("expanded", FourierRange::Expanded)],
                )?
            }
            "band" => {
                self.band = match value.trim().to_ascii_lowercase().as_str() {
                    "auto" | "" => None,
                    v => match v.parse::<u8>() {
                        Ok(b @ 1..=4) => Some(b),
                        _ => {
                            return Err(Error::param(
                                key,
                                format!("`{value}` is not a band of a TIFF: 1 to 4, or auto"),
                            ))
                        }
                    },
                }
            }
            "nodata" => {
                self.nodata = match value.trim().to_ascii_lowercase().as_str() {
                    "auto" | "" => NoData::Auto,
                    "none" => NoData::None,
                    "nan" => NoData::Nan,
                    _ => NoData::Value(parse_f64(key, value).map_err(|_| {
                        Error::param(
                            key,
                            format!("`{value}` is not a number, `nan`, `none` or `auto`"),
                        )
                    })?),
                }
            }
            "cell_size" | "max_distance" => {
                let v = match value.trim().to_ascii_lowercase().as_str() {
                    "auto" | "" => None,
                    _ => {
                        let v = parse_f64(key, value)?;
                        if !(v > 0.0 && v < 1e12) {
                            return Err(Error::param(
                                key,
                                "must be a positive number of map units (below 1e12)",
                            ));
                        }
                        Some(v)
                    }
                };
                if key == "cell_size" {
                    self.cell_size = v;
                } else {
                    self.max_distance = v;
                }
            }
            "earth_curvature" => {
                self.earth_curvature = parse_enum(
                    key,
                    value,
                    &[("off", EarthCurvature::Off), ("on", EarthCurvature::On)],
                )?
            }
            "refraction" => {
                let v = parse_f64(key, value)?;
                if !(0.0..1.0).contains(&v) {
                    return Err(Error::param(key, "must be at least 0 and below 1"));
                }
                self.refraction = v;
            }
            "angle_unit" => {
                self.angle_unit = parse_enum(
                    key,
                    value,
                    &[
                        ("degrees", AngleUnit::Degrees),
                        ("radians", AngleUnit::Radians),
                        ("sin", AngleUnit::Sin),
                    ],
                )?
            }
            "azimuth_from" => {
                self.azimuth_from = parse_enum(
                    key,
                    value,
                    &[("east_ccw", AzimuthFrom::EastCcw), ("north_cw", AzimuthFrom::NorthCw)],
                )?
            }
            "svf_model" => {
                self.svf_model = parse_enum(
                    key,
                    value,
                    &[
                        ("radiative", SvfModel::Radiative),
                        ("visual", SvfModel::Visual),
                        ("tilted", SvfModel::Tilted),
                    ],
                )?
            }
            "date" | "date_from" | "date_to" => {
                let v = match value.trim() {
                    "" | "auto" => None,
                    v => {
                        let (y, m, d) = parse_date(key, v)?;
                        Some(format!("{y:04}-{m:02}-{d:02}"))
                    }
                };
                if key != "date_to" {
                    self.date_from = v.clone();
                }
                if key != "date_from" {
                    self.date_to = v;
                }
            }
            "time_step_minutes" => {
                self.time_step_minutes = match value.trim() {
                    "" | "auto" => None,
                    _ => {
                        let t = parse_u32(key, value)?;
                        if t == 0 || t > 1440 || 1440 % t != 0 {
                            return Err(Error::param(
                                key,
                                format!("must divide a day of 1440 minutes (1, 5, 10, 15, 30, 60, …), got {t}"),
                            ));
                        }
                        Some(t)
                    }
                }
            }
            "latitude" | "longitude" => {
                let v = match value.trim() {
                    "" | "auto" => None,
                    _ => {
                        let v = parse_f64(key, value)?;
                        let lim = if key == "latitude" { 90.0 } else { 180.0 };
                        if !(-lim..=lim).contains(&v) {
                            return Err(Error::param(
                                key,
                                format!("must be between -{lim} and {lim} degrees"),
                            ));
                        }
                        Some(v)
                    }
                };
                if key == "latitude" {
                    self.latitude = v;
                } else {
                    self.longitude = v;
                }
            }
            "normal_convention" => {
                self.normal_convention = parse_enum(
                    key,
                    value,
                    &[("opengl", NormalConvention::OpenGl), ("directx", NormalConvention::DirectX)],
                )?
            }
            "bent_normal_encoding" => {
                self.bent_normal_encoding = parse_enum(
                    key,
                    value,
                    &[
                        ("rgb", BentNormalEncoding::Rgb),
                        ("rg", BentNormalEncoding::Rg),
                        ("rgb_ao", BentNormalEncoding::RgbAo),
                    ],
                )?
            }
            _ => {
                return Err(Error::param(
                    key,
                    format!("unknown parameter; known ones are {}", PARAM_NAMES.join(", ")),
                ))
            }
        }
        self.explicit.mark(key);
        Ok(())
    }

    /// The channel the decoder reads: `band` N as the N-th sample of a texel, else `channel`.
    pub fn decode_channel(&self) -> Channel {
        match self.band {
            Some(1) => Channel::R,
            Some(2) => Channel::G,
            Some(3) => Channel::B,
            Some(4) => Channel::A,
            _ => self.channel,
        }
    }

    /// Rules that join several parameters, checked once all are set.
    ///
    /// # Errors
    /// [`Error::Param`] naming the field to change.
    pub fn check(&self) -> Result<()> {
        self.check_with(true)
    }

    /// The days of `sun_hours`/`insolation`: both ends given, in order, at most
    /// [`MAX_SUN_DAYS`]; `latitude` and `longitude` together or not at all.
    fn check_sun(&self) -> Result<()> {
        let (Some(from), Some(to)) = (&self.date_from, &self.date_to) else {
            return Err(Error::param(
                "date",
                "sun_hours and insolation are sums over days: give date (YYYY-MM-DD), or \
                 date_from and date_to",
            ));
        };
        let days = days_from_civil(parse_date("date_to", to)?)
            - days_from_civil(parse_date("date_from", from)?)
            + 1;
        if days < 1 {
            return Err(Error::param("date_to", format!("{to} is before date_from {from}")));
        }
        if days > MAX_SUN_DAYS {
            return Err(Error::param(
                "date_to",
                format!("{days} days from {from} to {to}: at most {MAX_SUN_DAYS}"),
            ));
        }
        if self.latitude.is_some() != self.longitude.is_some() {
            let missing = if self.latitude.is_none() { "latitude" } else { "longitude" };
            return Err(Error::param(
                missing,
                "give latitude and longitude together (or neither: the DEM's centre)",
            ));
        }
        Ok(())
    }

    /// [`BakeParams::check`] before the input is read: a method not given may still become a
    /// ray method by the DEM defaults (SPEC §2, [`crate::heightmap::georef::apply_dem_defaults`],
    /// which checks again once it has resolved them), so the rules of `lengyel` wait for it.
    ///
    /// # Errors
    /// [`Error::Param`] naming the field to change.
    pub fn check_before_input(&self) -> Result<()> {
        self.check_with(false)
    }

    fn check_with(&self, settled: bool) -> Result<()> {
        let b = self.bins;
        // Openness is measured within a distance (SPEC §3.7, RVT's radius): to the edge of the
        // map it would mostly measure the map's size. (A DEM's default radius is `unlimited`.)
        if self.outputs.openness
            && self.radius == Radius::Unlimited
            && self.max_distance.is_none()
            && (settled || self.explicit.has("radius"))
        {
            return Err(Error::param(
                "max_distance",
                "openness is measured within a distance: give max_distance (metres, with a cell \
                 size) or a finite radius (texels)",
            ));
        }
        if self.outputs.sun() {
            self.check_sun()?;
        }
        let ray = matches!(self.method, Method::Exact | Method::March | Method::Sweep)
            || !(settled || self.explicit.has("method"));
        let layers = self.outputs.horizon || self.outputs.fourier;
        if (layers || !ray) && (b < 16 || !b.is_multiple_of(16) || b > MAX_BINS) {
            let why =
                if ray { "with the horizon or fourier outputs" } else { "with method=lengyel" };
            return Err(Error::param(
                "bins",
                format!(
                    "must be a multiple of 16 between 16 and {MAX_BINS} {why}, got {b} \
                     (any 1..{MAX_TERRAIN_BINS} for outputs=angles,svf with method=exact, march or sweep)"
                ),
            ));
        }
        if self.outputs.terrain()
            && self.azimuth_from == AzimuthFrom::NorthCw
            && !b.is_multiple_of(4)
        {
            return Err(Error::param(
                "azimuth_from",
                format!(
                    "north_cw needs bins divisible by 4 (so north is one of the bins), got {b}"
                ),
            ));
        }
        // `lengyel` splats and always averages 5 bins (SPEC §3.1), so `reduce=point` with it
        // would be a separate bake with the same bytes: refused, naming `reduce`.
        if !ray && self.reduce == Reduce::Point {
            return Err(Error::param(
                "reduce",
                "`point` applies to the ray methods (exact, march, sweep); method=lengyel always \
                 averages its bins (SPEC §3.1): drop `reduce` or pick another method",
            ));
        }
        Ok(())
    }

    /// Builds parameters from key/value pairs (a query string, CLI flags), defaults elsewhere,
    /// and checks the rules joining several keys ([`BakeParams::check`]).
    ///
    /// # Errors
    /// The first invalid or unknown pair, or a key given twice, as [`Error::Param`] naming it.
    pub fn from_pairs<'a, I>(pairs: I) -> Result<Self>
    where
        I: IntoIterator<Item = (&'a str, &'a str)>,
    {
        let p = Self::from_pairs_unchecked(pairs)?;
        p.check()?;
        Ok(p)
    }

    /// [`BakeParams::from_pairs`] without [`BakeParams::check`]: for a query that may hold half
    /// of a combination whose other half comes in a multipart `params` JSON part. The caller
    /// checks once every key is set.
    ///
    /// # Errors
    /// The first invalid or unknown pair, or a key given twice, as [`Error::Param`] naming it.
    pub fn from_pairs_unchecked<'a, I>(pairs: I) -> Result<Self>
    where
        I: IntoIterator<Item = (&'a str, &'a str)>,
    {
        let mut p = BakeParams::default();
        let mut seen: Vec<&str> = Vec::new();
        for (k, v) in pairs {
            if seen.contains(&k) {
                return Err(Error::param(k, "given more than once"));
            }
            p.set(k, v)?;
            seen.push(k);
        }
        Ok(p)
    }

    /// Builds parameters from a JSON object. Numbers, strings and (for `outputs`) arrays of
    /// strings are accepted; `null` means "the default".
    ///
    /// # Errors
    /// [`Error::Param`] naming the field; `params` itself when the value is not an object.
    pub fn from_json(value: &serde_json::Value) -> Result<Self> {
        let obj =
            value.as_object().ok_or_else(|| Error::param("params", "must be a JSON object"))?;
        let mut p = BakeParams::default();
        for (k, v) in obj {
            if let Some(text) = json_value_text(k, v)? {
                p.set(k, &text)?;
            }
        }
        p.check()?;
        Ok(p)
    }

    /// The parameters as textual key/value pairs, the inverse of [`BakeParams::from_pairs`].
    pub fn to_pairs(&self) -> Vec<(&'static str, String)> {
        fn name<T: Serialize>(t: &T) -> String {
            serde_json::to_value(t)
                .ok()
                .and_then(|v| v.as_str().map(str::to_owned))
                .unwrap_or_default()
        }
        let mut pairs = vec![
            ("height_scale", self.height_scale.to_string()),
            ("channel", name(&self.channel)),
            ("edge", name(&self.edge)),
            ("y_axis", name(&self.y_axis)),
            ("method", name(&self.method)),
            ("radius", self.radius.to_string()),
            ("bins", self.bins.to_string()),
            ("reduce", name(&self.reduce)),
            ("min_elevation_deg", self.min_elevation_deg.to_string()),
            ("encoding", name(&self.encoding)),
            ("outputs", self.outputs.to_string()),
            ("fourier_terms", self.fourier_terms.to_string()),
            ("fourier_range", name(&self.fourier_range)),
            ("nodata", self.nodata.to_string()),
            ("cell_size", self.cell_size.map_or("auto".into(), |v| v.to_string())),
            ("max_distance", self.max_distance.map_or("auto".into(), |v| v.to_string())),
            ("earth_curvature", name(&self.earth_curvature)),
            ("refraction", self.refraction.to_string()),
            ("angle_unit", name(&self.angle_unit)),
            ("azimuth_from", name(&self.azimuth_from)),
            ("svf_model", name(&self.svf_model)),
            ("band", self.band.map_or("auto".into(), |b| b.to_string())),
            ("normal_convention", name(&self.normal_convention)),
            ("bent_normal_encoding", name(&self.bent_normal_encoding)),
        ];
        // The days of the sun's products are parameters of those alone: a bake without them
        // keeps the pairs (and the dedup key) it had before they existed.
        if self.outputs.sun() {
            let opt = |v: &Option<String>| v.clone().unwrap_or_else(|| "auto".into());
            let num = |v: Option<f64>| v.map_or("auto".into(), |v| v.to_string());
            pairs.push(("date_from", opt(&self.date_from)));
            pairs.push(("date_to", opt(&self.date_to)));
            let step = self.time_step_minutes.unwrap_or(DEFAULT_TIME_STEP_MINUTES);
            pairs.push(("time_step_minutes", step.to_string()));
            pairs.push(("latitude", num(self.latitude)));
            pairs.push(("longitude", num(self.longitude)));
        }
        pairs
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A `params` object is read in one pass with a bound on its members: 256 distinct keys
    /// are read (in order), one more is a 422 naming `params` rather than a scan of every key
    /// seen so far for each new one, and a duplicate is still named.
    #[test]
    fn json_members_are_bounded_and_duplicates_named() {
        let object = |n: usize| {
            let members: Vec<String> = (0..n).map(|i| format!("\"k{i}\": {i}")).collect();
            format!("{{{}}}", members.join(","))
        };
        let pairs = json_object_pairs(object(MAX_JSON_MEMBERS).as_bytes()).unwrap();
        assert_eq!(pairs.len(), MAX_JSON_MEMBERS);
        assert_eq!(pairs[255].0, "k255");
        match json_object_pairs(object(40_000).as_bytes()) {
            Err(Error::Param { field, message }) => {
                assert_eq!(field, "params");
                assert!(message.contains("more than 256 members"), "{message}");
            }
            other => panic!("not refused: {other:?}"),
        }
        match json_object_pairs(br#"{"radius": 4, "bins": 16, "radius": 5}"#) {
            Err(Error::Param { field, .. }) => assert_eq!(field, "radius"),
            other => panic!("duplicate not named: {other:?}"),
        }
    }

    #[test]
    fn defaults_match_spec() {
        let p = BakeParams::default();
        assert_eq!(p.radius, Radius::Texels(16));
        assert_eq!(p.bins, 32);
        assert_eq!(p.edge, Edge::Wrap);
        assert_eq!(p.y_axis, YAxis::Up);
        assert_eq!(p.method, Method::Lengyel);
        assert_eq!(p.fourier_terms, 5);
    }

    #[test]
    fn errors_name_the_field() {
        let cases = [
            ("height_scale", "-1"),
            ("bins", "24"),
            ("bins", "0"),
            ("radius", "0"),
            ("radius", "abc"),
            ("edge", "clamp"),
            ("fourier_terms", "4"),
            ("min_elevation_deg", "90"),
            ("height_scale", "NaN"),
            ("outputs", "normals"),
            ("bogus", "1"),
        ];
        for (k, v) in cases {
            match BakeParams::from_pairs([(k, v)]) {
                Err(Error::Param { field, .. }) => assert_eq!(field, k, "{k}={v}"),
                other => panic!("{k}={v}: expected a parameter error, got {other:?}"),
            }
        }
    }

    #[test]
    fn point_reduction_is_refused_with_lengyel_only() {
        let bad = BakeParams::from_pairs_unchecked([("reduce", "point")]).unwrap();
        match bad.check() {
            Err(Error::Param { field, .. }) => assert_eq!(field, "reduce"),
            other => panic!("lengyel + point: {other:?}"),
        }
        for m in ["exact", "march"] {
            let p = BakeParams::from_pairs([("method", m), ("reduce", "point")]).unwrap();
            assert!(p.check().is_ok(), "{m}");
        }
        assert!(BakeParams::default().check().is_ok());
        let json = serde_json::json!({"method": "lengyel", "reduce": "point"});
        assert!(matches!(BakeParams::from_json(&json), Err(Error::Param { .. })));
    }

    #[test]
    fn pairs_round_trip() {
        let p = BakeParams::from_pairs([
            ("radius", "unlimited"),
            ("bins", "64"),
            ("outputs", "horizon,fourier"),
            ("encoding", "sqrt"),
            ("y_axis", "down"),
        ])
        .unwrap();
        let pairs = p.to_pairs();
        let q = BakeParams::from_pairs(pairs.iter().map(|(k, v)| (*k, v.as_str()))).unwrap();
        assert_eq!(p, q);
    }

    #[test]
    fn json_accepts_numbers_strings_and_arrays() {
        let v =
            serde_json::json!({"radius": 8, "bins": "48", "outputs": ["fourier"], "edge": null});
        let p = BakeParams::from_json(&v).unwrap();
        assert_eq!(p.radius, Radius::Texels(8));
        assert_eq!(p.bins, 48);
        assert!(p.outputs.fourier && !p.outputs.horizon);
        assert!(BakeParams::from_json(&serde_json::json!({"bins": true})).is_err());
        assert!(BakeParams::from_json(&serde_json::json!([1])).is_err());
    }
}
