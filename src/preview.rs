//! The CPU preview (SPEC §3.5): the lit surface as a shader would draw it, and a contact sheet of
//! several light azimuths, as PNG.
//!
//! A preview is a pure function of the height map, the bake parameters, the preview parameters
//! ([`PreviewParams`]) and the baked layers it decodes ([`Baked`]). Everything that does not
//! depend on the pixel — scaled heights, normals, the UNORM8 cube map, the light's cube-map
//! factors — is prepared once in a [`Scene`]; pixels are then shaded in parallel over output rows.
//!
//! Per pixel:
//! 1. the pixel centre maps to texel coordinates (texel centres at integers), so at the native
//!    size every pixel is a texel; `size` scales the image and every texture is then sampled
//!    bilinearly at the pixel centre, as a GPU would (no separate resampling pass);
//! 2. `parallax` displaces that coordinate along the view direction
//!    ([`crate::kernels::parallax`]);
//! 3. the normal is the bilinear sample of the per-texel central-difference normals,
//!    renormalised;
//! 4. colour = albedo·(ambient + F·max(N·L, 0)) + (F·ks·(N·H)^n + env)·HO, with H the Blinn half
//!    vector, env a uniform environment seen in the mirror direction, HO = saturate(1 +
//!    fade·R.z) the horizon occlusion of the reflection R = reflect(−V, N) against the geometric
//!    normal (0, 0, 1) (it darkens the reflection where a bent normal sends R below the surface),
//!    and F from `shading`:
//!    - `horizon`: the baked 8- or 16-bit layers decoded through the UNORM8 cube map exactly as
//!      in [`crate::kernels::shade`] (the zero offset included), F of SPEC §3.3;
//!    - `fourier`: the Fourier layers decoded as in [`crate::kernels::fourier`], F likewise;
//!    - `raytraced`: the exact horizon at the light's azimuth on the bilinear surface, unlimited
//!      radius, F likewise (ground truth);
//!    - `none`: F = 1 (normal mapping only);
//!    - `difference`: grey where `horizon` and `raytraced` agree on lit (L_z > s) vs shadowed,
//!      red where the horizon map shadows a lit texel, blue where it lights a shadowed one.
//! 5. linear → sRGB, 8-bit.

use crate::bake::{self, HorizonLayers, Precisions};
use crate::error::{Error, Result};
use crate::heightmap::HeightMap;
use crate::kernels::fourier::{self, FourierLayers};
use crate::kernels::parallax::{self, Parallax, ParallaxSettings};
use crate::kernels::shade::{self, CubeMap, Samples, Surface, Texture};
use crate::kernels::Grid;
use crate::params::{BakeParams, Edge, Encoding};
use crate::progress::Progress;
use rayon::prelude::*;

/// What the preview shows as the illumination factor F.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Shading {
    Horizon,
    Fourier,
    Raytraced,
    None,
    Difference,
}

/// Largest output side in pixels.
pub const MAX_SIZE: u32 = 4096;
/// Most output pixels of one preview or contact sheet (all tiles together): 64 Mpixel, 256 MB.
pub const MAX_PIXELS: u64 = 1 << 26;
/// Most tiles on a contact sheet.
pub const MAX_TILES: u32 = 64;
/// Longest side of a contact-sheet tile when `size` is not given: a sheet is for comparing
/// lights at a glance, and native tiles of a 2048² map made a 6160×6226, 131 MB image.
pub const SHEET_TILE: u32 = 512;
/// Most parallax layers / bisections.
pub const MAX_PARALLAX_STEPS: u32 = 1024;
/// Largest cube-map face.
pub const MAX_CUBE_SIZE: u32 = 1024;

/// Every preview parameter (SPEC §3.5), with its default.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct PreviewParams {
    pub shading: Shading,
    /// Light azimuth in degrees from +x toward +y (used unless `light` is set).
    pub azimuth: f64,
    /// Light elevation in degrees above the tangent plane.
    pub elevation: f64,
    /// An explicit tangent-space light vector (normalised); when given it wins over
    /// azimuth/elevation whatever order they arrive in (query strings have no reliable order).
    pub light: Option<[f64; 3]>,
    /// k in F = clamp(k·(L_z − s) + 1, 0, 1).
    pub hardness: f64,
    pub view_azimuth: f64,
    /// 90 = straight down (no parallax shift).
    pub view_elevation: f64,
    /// An explicit view vector (surface → eye, z > 0); wins over view_azimuth/view_elevation.
    pub view: Option<[f64; 3]>,
    pub parallax: Parallax,
    pub parallax_steps: u32,
    pub parallax_search_steps: u32,
    pub parallax_strength: f64,
    /// Fade of the horizon occlusion of the specular reflection (0 = off).
    pub horizon_occlusion: f64,
    /// Longer output side in pixels; `None` = one pixel per texel.
    pub size: Option<u32>,
    /// Which baked horizon precision `horizon` decodes: 8 or 16 bits.
    pub precision: u8,
    /// Face size of the channel-factor cube map `horizon` samples.
    pub cube_size: u32,
    /// Number of tiles of a contact sheet (0 = a single image).
    pub contact_sheet: u32,
    /// Half the azimuth span of a contact sheet, in degrees (tiles cover azimuth ± spread).
    pub sheet_spread: f64,
    /// `baked`: the ambient and environment terms are multiplied by the bake's ambient
    /// occlusion (`ao.png`, SPEC §3.8), as an engine applies an AO map; `none` (default).
    pub ambient_occlusion: bool,
}

impl Default for PreviewParams {
    fn default() -> Self {
        PreviewParams {
            shading: Shading::Horizon,
            azimuth: 135.0,
            elevation: 30.0,
            light: None,
            hardness: shade::DEFAULT_HARDNESS,
            view_azimuth: 0.0,
            view_elevation: 90.0,
            view: None,
            parallax: Parallax::None,
            parallax_steps: 32,
            parallax_search_steps: 8,
            parallax_strength: 1.0,
            horizon_occlusion: 1.0,
            size: None,
            precision: 8,
            cube_size: 16,
            contact_sheet: 0,
            sheet_spread: 60.0,
            ambient_occlusion: false,
        }
    }
}

/// The names [`PreviewParams::set`] accepts.
pub const PREVIEW_PARAM_NAMES: &[&str] = &[
    "shading",
    "azimuth",
    "elevation",
    "light",
    "hardness",
    "view_azimuth",
    "view_elevation",
    "view",
    "parallax",
    "parallax_steps",
    "parallax_search_steps",
    "parallax_strength",
    "horizon_occlusion",
    "size",
    "precision",
    "cube_size",
    "contact_sheet",
    "sheet_spread",
    "ambient_occlusion",
];

use crate::params::parse_f64 as num;

/// A whole number in `lo ..= hi`, or a parameter error naming `field`.
fn whole(field: &str, value: &str, lo: u32, hi: u32) -> Result<u32> {
    let v = crate::params::parse_u32(field, value)?;
    if (lo..=hi).contains(&v) {
        Ok(v)
    } else {
        Err(Error::param(field, format!("must be between {lo} and {hi}, got {v}")))
    }
}

/// Parses "x,y,z" into a unit vector.
fn vector(field: &str, value: &str) -> Result<[f64; 3]> {
    let parts: Vec<&str> = value.split(',').map(str::trim).collect();
    if parts.len() != 3 {
        return Err(Error::param(field, format!("`{value}` is not three comma-separated numbers")));
    }
    let mut v = [0.0; 3];
    for (o, p) in v.iter_mut().zip(&parts) {
        *o = num(field, p)?;
    }
    let len = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    if !(len.is_finite() && len > 0.0) {
        return Err(Error::param(field, "must be a non-zero finite vector"));
    }
    Ok([v[0] / len, v[1] / len, v[2] / len])
}

impl PreviewParams {
    /// Whether `key` is a preview parameter (the rest of a query string are bake parameters).
    pub fn is_preview_key(key: &str) -> bool {
        PREVIEW_PARAM_NAMES.contains(&key)
    }

    /// Sets one parameter from its textual value, validating it.
    ///
    /// # Errors
    /// [`Error::Param`] naming `key` when the key is unknown or the value is invalid.
    pub fn set(&mut self, key: &str, value: &str) -> Result<()> {
        let lower = value.trim().to_ascii_lowercase();
        match key {
            "shading" => {
                self.shading = match lower.as_str() {
                    "horizon" => Shading::Horizon,
                    "fourier" => Shading::Fourier,
                    "raytraced" => Shading::Raytraced,
                    "none" => Shading::None,
                    "difference" => Shading::Difference,
                    _ => {
                        return Err(Error::param(
                            key,
                            format!("`{value}` is not one of horizon, fourier, raytraced, none, difference"),
                        ))
                    }
                }
            }
            "azimuth" => {
                self.azimuth = num(key, value)?;
            }
            "elevation" => {
                let e = num(key, value)?;
                if !(-90.0..=90.0).contains(&e) {
                    return Err(Error::param(key, "must be between -90 and 90 degrees"));
                }
                self.elevation = e;
            }
            "light" => self.light = Some(vector(key, value)?),
            "hardness" => {
                let k = num(key, value)?;
                if !(k > 0.0 && k <= 1e6) {
                    return Err(Error::param(key, "must be greater than 0 and at most 1e6"));
                }
                self.hardness = k;
            }
            "view_azimuth" => {
                self.view_azimuth = num(key, value)?;
            }
            "view_elevation" => {
                let e = num(key, value)?;
                if !(e > 0.0 && e <= 90.0) {
                    return Err(Error::param(key, "must be greater than 0 and at most 90 degrees"));
                }
                self.view_elevation = e;
            }
            "view" => {
                let v = vector(key, value)?;
                if v[2] <= 0.0 {
                    return Err(Error::param(key, "must point above the surface (z > 0)"));
                }
                self.view = Some(v);
            }
            "parallax" => {
                self.parallax = match lower.as_str() {
                    "none" => Parallax::None,
                    "offset" => Parallax::Offset,
                    "offset_limited" => Parallax::OffsetLimited,
                    "steep" => Parallax::Steep,
                    "interpolated" => Parallax::Interpolated,
                    "relief" => Parallax::Relief,
                    _ => {
                        return Err(Error::param(
                            key,
                            format!(
                                "`{value}` is not one of none, offset, offset_limited, steep, interpolated, relief"
                            ),
                        ))
                    }
                }
            }
            "parallax_steps" => self.parallax_steps = whole(key, value, 1, MAX_PARALLAX_STEPS)?,
            "parallax_search_steps" => {
                self.parallax_search_steps = whole(key, value, 0, MAX_PARALLAX_STEPS)?
            }
            "parallax_strength" => {
                let s = num(key, value)?;
                if !(0.0..=1000.0).contains(&s) {
                    return Err(Error::param(key, "must be between 0 and 1000"));
                }
                self.parallax_strength = s;
            }
            "ambient_occlusion" => {
                self.ambient_occlusion = match lower.as_str() {
                    "none" => false,
                    "baked" => true,
                    _ => return Err(Error::param(key, format!("`{value}` is not one of none, baked"))),
                }
            }
            "horizon_occlusion" => {
                let f = num(key, value)?;
                if !(0.0..=1000.0).contains(&f) {
                    return Err(Error::param(key, "must be between 0 and 1000"));
                }
                self.horizon_occlusion = f;
            }
            "size" => {
                self.size = if lower == "native" || lower == "0" {
                    None
                } else {
                    Some(whole(key, value, 1, MAX_SIZE)?)
                }
            }
            "precision" => {
                self.precision = match lower.as_str() {
                    "8" => 8,
                    "16" => 16,
                    _ => return Err(Error::param(key, format!("`{value}` is not 8 or 16"))),
                }
            }
            "cube_size" => self.cube_size = whole(key, value, 1, MAX_CUBE_SIZE)?,
            "contact_sheet" => self.contact_sheet = whole(key, value, 0, MAX_TILES)?,
            "sheet_spread" => {
                let s = num(key, value)?;
                if !(0.0..=180.0).contains(&s) {
                    return Err(Error::param(key, "must be between 0 and 180 degrees"));
                }
                self.sheet_spread = s;
            }
            _ => {
                return Err(Error::param(
                    key,
                    format!("unknown parameter; known ones are {}", PREVIEW_PARAM_NAMES.join(", ")),
                ))
            }
        }
        Ok(())
    }

    /// Builds parameters from key/value pairs, defaults elsewhere.
    ///
    /// # Errors
    /// The first invalid or unknown pair, as [`Error::Param`].
    pub fn from_pairs<'a, I>(pairs: I) -> Result<Self>
    where
        I: IntoIterator<Item = (&'a str, &'a str)>,
    {
        let mut p = PreviewParams::default();
        for (k, v) in pairs {
            p.set(k, v)?;
        }
        Ok(p)
    }

    /// The unit tangent-space light vector.
    pub fn light_dir(&self) -> [f64; 3] {
        self.light.unwrap_or_else(|| from_angles(self.azimuth, self.elevation))
    }

    /// The unit tangent-space view vector (surface → eye).
    pub fn view_dir(&self) -> [f64; 3] {
        self.view.unwrap_or_else(|| from_angles(self.view_azimuth, self.view_elevation))
    }

    /// The light's azimuth in degrees (of `light` when set).
    pub fn light_azimuth(&self) -> f64 {
        match self.light {
            Some(l) => l[1].atan2(l[0]).to_degrees(),
            None => self.azimuth,
        }
    }
}

/// (cos e cos a, cos e sin a, sin e) from degrees.
pub fn from_angles(azimuth: f64, elevation: f64) -> [f64; 3] {
    let (a, e) = (azimuth.to_radians(), elevation.to_radians());
    [e.cos() * a.cos(), e.cos() * a.sin(), e.sin()]
}

/// The baked layers a preview decodes; what its `shading` needs must be present.
#[derive(Debug, Clone, Copy, Default)]
pub struct Baked<'a> {
    pub horizon: Option<&'a HorizonLayers>,
    pub fourier: Option<&'a FourierLayers>,
    /// `ao.png`'s values (SPEC §3.8), one per texel, for `ambient_occlusion=baked`.
    pub ao: Option<&'a [u8]>,
}

/// An 8-bit sRGB RGBA image (alpha always 255), row-major from the top.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Image {
    pub width: usize,
    pub height: usize,
    pub rgba: Vec<u8>,
}

impl Image {
    /// PNG bytes.
    ///
    /// # Errors
    /// [`Error::Internal`] if the encoder fails.
    pub fn to_png(&self) -> Result<Vec<u8>> {
        crate::encode::png::encode8(
            self.width,
            self.height,
            crate::encode::png::PngColor::Rgba,
            &self.rgba,
        )
    }

    /// The pixel at (`x`, `y`) as RGB.
    pub fn rgb(&self, x: usize, y: usize) -> [u8; 3] {
        let i = (y * self.width + x) * 4;
        [self.rgba[i], self.rgba[i + 1], self.rgba[i + 2]]
    }
}

/// Output dimensions: native, or the longer side scaled to `size` (the shorter rounded, ≥ 1).
pub fn output_size(width: usize, height: usize, size: Option<u32>) -> (usize, usize) {
    match size {
        None => (width, height),
        Some(s) => {
            let s = s as f64;
            let long = width.max(height) as f64;
            let w = ((width as f64 * s / long).round() as usize).max(1);
            let h = ((height as f64 * s / long).round() as usize).max(1);
            (w, h)
        }
    }
}

// Material constants of the preview (linear RGB).
const ALBEDO: f64 = 0.8;
const AMBIENT: f64 = 0.12;
const SPECULAR: f64 = 0.3;
const SHININESS: i32 = 24;
/// A uniform environment seen in the mirror direction (both hemispheres, as a cube-map lookup
/// would return): the reflection horizon occlusion exists to fade where R dips below the surface.
const ENV_REFLECTION: f64 = 0.06;
const FALSE_SHADOW: [f64; 3] = [0.9, 0.12, 0.08];
const MISSED_SHADOW: [f64; 3] = [0.08, 0.3, 0.95];

/// Linear [0, 1] → sRGB byte.
#[inline]
pub fn srgb8(v: f64) -> u8 {
    let v = if v.is_nan() { 0.0 } else { v.clamp(0.0, 1.0) };
    let s = if v <= 0.003_130_8 { 12.92 * v } else { 1.055 * v.powf(1.0 / 2.4) - 0.055 };
    (s * 255.0 + 0.5).floor().clamp(0.0, 255.0) as u8
}

#[inline]
fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

#[inline]
fn normalize(v: [f64; 3]) -> [f64; 3] {
    let l = dot(v, v).sqrt();
    if l > 0.0 && l.is_finite() {
        [v[0] / l, v[1] / l, v[2] / l]
    } else {
        [0.0, 0.0, 1.0]
    }
}

/// Everything a preview needs that does not depend on the pixel or the light.
pub struct Scene<'a> {
    width: usize,
    height: usize,
    heights: Vec<f32>,
    normals: Vec<f32>,
    hmin: f64,
    hmax: f64,
    edge: Edge,
    y_axis: crate::params::YAxis,
    encoding: Encoding,
    horizon: Option<[Texture<'a>; 2]>,
    fourier:
        Option<(Texture<'a>, Texture<'a>, Option<Texture<'a>>, usize, crate::params::FourierRange)>,
    cube: CubeMap,
    /// The ambient occlusion as a one-channel texture (`ambient_occlusion=baked`).
    ao: Option<Texture<'a>>,
    params: PreviewParams,
}

impl<'a> Scene<'a> {
    /// Prepares a scene.
    ///
    /// # Errors
    /// [`Error::Param`] (`shading`, `precision`) when the layers that `shading` decodes are
    /// missing or of another size than the map.
    pub fn new(
        map: &HeightMap,
        bake: &BakeParams,
        params: &PreviewParams,
        baked: Baked<'a>,
    ) -> Result<Self> {
        let heights = map.scaled(bake.height_scale);
        let grid = Grid::new(map.width, map.height, &heights, bake.edge, bake.y_axis);
        let normals = shade::normals(&grid);
        let (lo, hi) = grid.range();
        let wrap = bake.edge == Edge::Wrap;
        let needs_horizon = matches!(params.shading, Shading::Horizon | Shading::Difference);
        let horizon = if needs_horizon {
            let l = baked
                .horizon
                .ok_or_else(|| Error::param("shading", "the horizon layers were not baked"))?;
            if l.width != map.width || l.height != map.height {
                return Err(Error::param(
                    "shading",
                    "the horizon layers do not match the height map's size",
                ));
            }
            let tex = |s: Samples<'a>| Texture {
                width: l.width,
                height: l.height,
                channels: 4,
                samples: s,
                wrap,
            };
            Some(match params.precision {
                16 => {
                    let [a, b] = l.u16.as_ref().ok_or_else(|| {
                        Error::param("precision", "no 16-bit horizon layers were baked")
                    })?;
                    [tex(Samples::U16(a)), tex(Samples::U16(b))]
                }
                _ => {
                    let [a, b] = l.u8.as_ref().ok_or_else(|| {
                        Error::param("precision", "no 8-bit horizon layers were baked")
                    })?;
                    [tex(Samples::U8(a)), tex(Samples::U8(b))]
                }
            })
        } else {
            None
        };
        let fourier = if params.shading == Shading::Fourier {
            let f = baked
                .fourier
                .ok_or_else(|| Error::param("shading", "the Fourier layers were not baked"))?;
            if f.width != map.width || f.height != map.height {
                return Err(Error::param(
                    "shading",
                    "the Fourier layers do not match the height map's size",
                ));
            }
            let tex = |data: &'a [u8], channels: usize| Texture {
                width: f.width,
                height: f.height,
                channels,
                samples: Samples::U8(data),
                wrap,
            };
            Some((
                tex(&f.bands, 4),
                tex(&f.constant, 1),
                f.high.as_deref().map(|h| tex(h, 4)),
                f.terms,
                f.range,
            ))
        } else {
            None
        };
        let ao = if params.ambient_occlusion {
            let a = baked.ao.ok_or_else(|| {
                Error::param("ambient_occlusion", "the ambient occlusion was not baked")
            })?;
            if a.len() != map.width * map.height {
                return Err(Error::param(
                    "ambient_occlusion",
                    "the ambient occlusion does not match the height map's size",
                ));
            }
            Some(Texture {
                width: map.width,
                height: map.height,
                channels: 1,
                samples: Samples::U8(a),
                wrap,
            })
        } else {
            None
        };
        Ok(Scene {
            width: map.width,
            height: map.height,
            ao,
            hmin: lo as f64,
            hmax: hi as f64,
            normals,
            edge: bake.edge,
            y_axis: bake.y_axis,
            encoding: bake.encoding,
            horizon,
            fourier,
            cube: CubeMap::new(params.cube_size as usize),
            params: params.clone(),
            heights,
        })
    }

    fn grid(&self) -> Grid<'_> {
        Grid::new(self.width, self.height, &self.heights, self.edge, self.y_axis)
    }

    /// Bilinear normal at texel coordinates.
    #[inline]
    fn normal(&self, x: f64, r: f64) -> [f64; 3] {
        let (w, h) = (self.width as i64, self.height as i64);
        let idx = |c: i64, rr: i64| -> usize {
            let (c, rr) = match self.edge {
                Edge::Wrap => (c.rem_euclid(w), rr.rem_euclid(h)),
                Edge::None => (c.clamp(0, w - 1), rr.clamp(0, h - 1)),
            };
            (rr * w + c) as usize * 3
        };
        let (x0, r0) = (x.floor(), r.floor());
        let (fx, fr) = (x - x0, r - r0);
        let (c, rr) = (x0 as i64, r0 as i64);
        let (i00, i10, i01, i11) = (idx(c, rr), idx(c + 1, rr), idx(c, rr + 1), idx(c + 1, rr + 1));
        let n = &self.normals;
        let mut out = [0.0; 3];
        for (k, o) in out.iter_mut().enumerate() {
            let a = n[i00 + k] as f64 + (n[i10 + k] as f64 - n[i00 + k] as f64) * fx;
            let b = n[i01 + k] as f64 + (n[i11 + k] as f64 - n[i01 + k] as f64) * fx;
            *o = a + (b - a) * fr;
        }
        normalize(out)
    }

    /// Decoded horizon value s of the baked layers at texel coordinates, for cube factors `f`.
    #[inline]
    fn horizon_s(&self, x: f64, r: f64, f: [f32; 4]) -> f64 {
        let Some([t0, t1]) = &self.horizon else { return 0.0 };
        let (mut h0, mut h1) = ([0.0f32; 4], [0.0f32; 4]);
        t0.sample(x, r, &mut h0);
        t1.sample(x, r, &mut h1);
        if self.encoding == Encoding::Sqrt {
            for v in h0.iter_mut().chain(h1.iter_mut()) {
                *v *= *v;
            }
        }
        shade::horizon_s(f, h0, h1) as f64
    }

    /// Decoded Fourier horizon at texel coordinates, for the light's tangent-plane (cos, sin).
    #[inline]
    fn fourier_s(&self, x: f64, r: f64, cs: (f64, f64)) -> f64 {
        let Some((bands, constant, high, terms, range)) = &self.fourier else { return 0.0 };
        let (mut b, mut c, mut h) = ([0.0f32; 4], [0.0f32; 4], [0.5f32; 4]);
        bands.sample(x, r, &mut b);
        constant.sample(x, r, &mut c);
        if let Some(t) = high {
            t.sample(x, r, &mut h);
        }
        let f64x4 = |v: [f32; 4]| [v[0] as f64, v[1] as f64, v[2] as f64, v[3] as f64];
        let coeffs = fourier::decode_texel(f64x4(b), c[0] as f64, f64x4(h), *terms, *range);
        fourier::evaluate_xy(&coeffs, *terms, cs.0, cs.1)
    }

    /// Renders the scene for tangent-space light `l` (unit).
    pub fn render(&self, l: [f64; 3]) -> Image {
        match self.render_cancelable(l, &Progress::new()) {
            Ok(img) => img,
            // A fresh Progress is never canceled.
            Err(_) => Image { width: 0, height: 0, rgba: Vec::new() },
        }
    }

    /// As [`Scene::render`], checking `progress` for cancellation before every output row.
    ///
    /// # Errors
    /// [`Error::Canceled`] when `progress` asks for it.
    pub fn render_cancelable(&self, l: [f64; 3], progress: &Progress) -> Result<Image> {
        let p = &self.params;
        let (ow, oh) = output_size(self.width, self.height, p.size);
        let mut rgba = vec![255u8; ow * oh * 4];
        let grid = self.grid();
        let surface = Surface::new(grid);
        let row_step = grid.row_step() as f64;
        let v = p.view_dir();
        let v_img = [v[0], v[1] * row_step, v[2]];
        let settings = ParallaxSettings {
            method: p.parallax,
            steps: p.parallax_steps,
            search_steps: p.parallax_search_steps,
            strength: p.parallax_strength,
        };
        let factors = self.cube.factors(l);
        let hl = (l[0] * l[0] + l[1] * l[1]).sqrt();
        let cs = if hl > 0.0 { (l[0] / hl, l[1] / hl) } else { (1.0, 0.0) };
        let half = normalize([l[0] + v[0], l[1] + v[1], l[2] + v[2]]);
        let k = p.hardness;
        let (sx, sy) = (self.width as f64 / ow as f64, self.height as f64 / oh as f64);
        rgba.par_chunks_mut(ow * 4).enumerate().try_for_each(|(py, row)| {
            if progress.is_canceled() {
                return Err(Error::Canceled);
            }
            let r0 = (py as f64 + 0.5) * sy - 0.5;
            for (px, out) in row.chunks_exact_mut(4).enumerate() {
                let x0 = (px as f64 + 0.5) * sx - 0.5;
                let (x, r) = parallax::displace(
                    |a, b| surface.height(a, b),
                    self.hmin,
                    self.hmax,
                    (x0, r0),
                    v_img,
                    &settings,
                );
                let n = self.normal(x, r);
                let ndl = dot(n, l).max(0.0);
                let spec =
                    if ndl > 0.0 { SPECULAR * dot(n, half).max(0.0).powi(SHININESS) } else { 0.0 };
                let nv = dot(n, v);
                let refl_z = 2.0 * nv * n[2] - v[2];
                let ho = (1.0 + p.horizon_occlusion * refl_z).clamp(0.0, 1.0);
                // An AO map darkens the light that comes from everywhere (ambient and the
                // environment's reflection), not the sun's, which F already shadows.
                let occ = self.ao.as_ref().map_or(1.0, |t| {
                    let mut a = [0f32; 4];
                    t.sample(x, r, &mut a);
                    a[0] as f64
                });
                let lit = |f: f64| {
                    ALBEDO * (AMBIENT * occ + f * ndl) + (f * spec + ENV_REFLECTION * occ) * ho
                };
                let rgb = match p.shading {
                    Shading::None => [lit(1.0); 3],
                    Shading::Horizon => {
                        [lit(shade::illumination(l[2], self.horizon_s(x, r, factors), k)); 3]
                    }
                    Shading::Fourier => {
                        [lit(shade::illumination(l[2], self.fourier_s(x, r, cs), k)); 3]
                    }
                    Shading::Raytraced => {
                        let s = surface.horizon_sin_for_light(x, r, l, k);
                        [lit(shade::illumination(l[2], s, k)); 3]
                    }
                    Shading::Difference => {
                        let s_h = self.horizon_s(x, r, factors);
                        let lit_h = l[2] > s_h;
                        let lit_t = !surface.shadowed(x, r, l);
                        let g = ALBEDO * (AMBIENT + if lit_t { ndl } else { 0.0 }) * 0.7;
                        match (lit_h, lit_t) {
                            (false, true) => FALSE_SHADOW,
                            (true, false) => MISSED_SHADOW,
                            _ => [g; 3],
                        }
                    }
                };
                out[0] = srgb8(rgb[0]);
                out[1] = srgb8(rgb[1]);
                out[2] = srgb8(rgb[2]);
            }
            Ok(())
        })?;
        Ok(Image { width: ow, height: oh, rgba })
    }
}

/// Renders one preview (or, with `contact_sheet` > 0, the contact sheet) from baked layers.
///
/// # Errors
/// [`Error::Param`] when the layers `shading` needs are missing (see [`Scene::new`]), or
/// (`size`) when the output would exceed [`MAX_PIXELS`].
pub fn render(
    map: &HeightMap,
    bake: &BakeParams,
    params: &PreviewParams,
    baked: Baked<'_>,
) -> Result<Image> {
    render_cancelable(map, bake, params, baked, &Progress::new())
}

/// As [`render`], checking `progress` for cancellation between output rows (a service can
/// abandon a preview it no longer needs).
///
/// # Errors
/// As [`render`], and [`Error::Canceled`].
pub fn render_cancelable(
    map: &HeightMap,
    bake: &BakeParams,
    params: &PreviewParams,
    baked: Baked<'_>,
    progress: &Progress,
) -> Result<Image> {
    let capped;
    let params = if params.contact_sheet > 0
        && params.size.is_none()
        && map.width.max(map.height) > SHEET_TILE as usize
    {
        capped = PreviewParams { size: Some(SHEET_TILE), ..params.clone() };
        &capped
    } else {
        params
    };
    let (ow, oh) = output_size(map.width, map.height, params.size);
    let pixels = ow as u64 * oh as u64 * params.contact_sheet.max(1) as u64;
    if pixels > MAX_PIXELS {
        return Err(Error::param(
            "size",
            format!("the preview would have {pixels} pixels, at most {MAX_PIXELS} are allowed"),
        ));
    }
    let scene = Scene::new(map, bake, params, baked)?;
    if params.contact_sheet > 0 {
        return sheet(&scene, params, progress);
    }
    scene.render_cancelable(params.light_dir(), progress)
}

/// Bakes what `params.shading` decodes (horizon layers at the asked precision, or the Fourier
/// layers), then renders.
///
/// # Errors
/// [`Error::Canceled`] from the bake or the render; parameter errors as [`render`].
pub fn render_baking(
    map: &HeightMap,
    bake: &BakeParams,
    params: &PreviewParams,
    progress: &Progress,
) -> Result<Image> {
    let horizon = match params.shading {
        Shading::Horizon | Shading::Difference => {
            let prec = if params.precision == 16 {
                Precisions { u8: false, u16: true, f32: false }
            } else {
                Precisions::U8
            };
            Some(bake::bake_horizon(map, bake, prec, progress)?.0)
        }
        _ => None,
    };
    let fourier = match params.shading {
        Shading::Fourier => Some(bake::bake_fourier(map, bake, progress)?.0),
        _ => None,
    };
    let ao = if params.ambient_occlusion {
        // The bake's own AO map (SPEC §3.8), from the same method, radius and bins.
        let mut p = bake.clone();
        p.outputs = crate::params::Outputs { ao: true, ..crate::params::Outputs::NONE };
        bake::bake_surface(map, &p, progress)?.0.ao
    } else {
        None
    };
    let baked = Baked { horizon: horizon.as_ref(), fourier: fourier.as_ref(), ao: ao.as_deref() };
    render_cancelable(map, bake, params, baked, progress)
}

/// The light azimuths (degrees) of an `n`-tile contact sheet centred on `azimuth`: evenly from
/// azimuth − spread to azimuth + spread (Lengyel's figure 5.3 uses 9 tiles over ±60°).
pub fn sheet_azimuths(azimuth: f64, spread: f64, n: usize) -> Vec<f64> {
    match n {
        0 => Vec::new(),
        1 => vec![azimuth],
        _ => (0..n).map(|i| azimuth - spread + 2.0 * spread * i as f64 / (n - 1) as f64).collect(),
    }
}

/// Gap between tiles and around the sheet, pixels.
const GAP: usize = 4;

/// The label of a tile: its azimuth in whole degrees, normalised to (−180, 180].
pub fn tile_label(azimuth: f64) -> String {
    let mut a = azimuth.rem_euclid(360.0);
    if a > 180.0 {
        a -= 360.0;
    }
    let r = a.round();
    format!("AZ {}°", if r == 0.0 { 0.0 } else { r })
}

fn sheet(scene: &Scene<'_>, params: &PreviewParams, progress: &Progress) -> Result<Image> {
    let n = params.contact_sheet as usize;
    let base_az = params.light_azimuth();
    let elev = match params.light {
        Some(l) => l[2].clamp(-1.0, 1.0).asin().to_degrees(),
        None => params.elevation,
    };
    let azs = sheet_azimuths(base_az, params.sheet_spread, n);
    let tiles = azs
        .iter()
        .map(|&a| scene.render_cancelable(from_angles(a, elev), progress))
        .collect::<Result<Vec<Image>>>()?;
    let (tw, th) = (tiles[0].width, tiles[0].height);
    let cols = (n as f64).sqrt().ceil() as usize;
    let rows = n.div_ceil(cols);
    // Labels grow with the tile: 7 px glyphs on tiles under 128 px, 7·⌊w/64⌋ px above (56 px
    // on a 512 px tile), so "AZ -180°" spans at most 3/4 of the tile's width.
    let scale = label_scale(tw);
    let label_h = font::HEIGHT * scale + 2 * GAP;
    let cell_w = tw + GAP;
    let cell_h = th + label_h + GAP;
    let (w, h) = (GAP + cols * cell_w, GAP + rows * cell_h);
    let mut img = Image { width: w, height: h, rgba: [24u8, 24, 24, 255].repeat(w * h) };
    for (i, (tile, &az)) in tiles.iter().zip(&azs).enumerate() {
        let (x0, y0) = (GAP + (i % cols) * cell_w, GAP + (i / cols) * cell_h);
        for y in 0..th {
            let src = &tile.rgba[y * tw * 4..(y + 1) * tw * 4];
            let d = ((y0 + y) * w + x0) * 4;
            img.rgba[d..d + tw * 4].copy_from_slice(src);
        }
        font::draw(&mut img, x0, y0 + th + GAP, tw, &tile_label(az), scale, [240, 240, 240]);
    }
    Ok(img)
}

/// The pixel size of a font pixel in the label of a contact-sheet tile `tile_w` pixels wide.
pub fn label_scale(tile_w: usize) -> usize {
    (tile_w / 64).max(1)
}

/// A tiny embedded 5×7 bitmap font for contact-sheet labels (no font crates).
pub mod font {
    use super::Image;

    /// Glyph width and height in font pixels (plus one column of spacing per glyph).
    pub const WIDTH: usize = 5;
    pub const HEIGHT: usize = 7;

    /// The rows of a glyph, 5 bits each (bit 4 = leftmost); `None` for characters we lack.
    pub fn glyph(c: char) -> Option<[u8; 7]> {
        Some(match c {
            '0' => [0b01110, 0b10001, 0b10011, 0b10101, 0b11001, 0b10001, 0b01110],
            '1' => [0b00100, 0b01100, 0b00100, 0b00100, 0b00100, 0b00100, 0b01110],
            '2' => [0b01110, 0b10001, 0b00001, 0b00010, 0b00100, 0b01000, 0b11111],
            '3' => [0b11111, 0b00010, 0b00100, 0b00010, 0b00001, 0b10001, 0b01110],
            '4' => [0b00010, 0b00110, 0b01010, 0b10010, 0b11111, 0b00010, 0b00010],
            '5' => [0b11111, 0b10000, 0b11110, 0b00001, 0b00001, 0b10001, 0b01110],
            '6' => [0b00110, 0b01000, 0b10000, 0b11110, 0b10001, 0b10001, 0b01110],
            '7' => [0b11111, 0b00001, 0b00010, 0b00100, 0b01000, 0b01000, 0b01000],
            '8' => [0b01110, 0b10001, 0b10001, 0b01110, 0b10001, 0b10001, 0b01110],
            '9' => [0b01110, 0b10001, 0b10001, 0b01111, 0b00001, 0b00010, 0b01100],
            '-' => [0, 0, 0, 0b11111, 0, 0, 0],
            '+' => [0, 0b00100, 0b00100, 0b11111, 0b00100, 0b00100, 0],
            '.' => [0, 0, 0, 0, 0, 0b01100, 0b01100],
            ':' => [0, 0b01100, 0b01100, 0, 0b01100, 0b01100, 0],
            '°' => [0b01100, 0b10010, 0b10010, 0b01100, 0, 0, 0],
            'A' => [0b01110, 0b10001, 0b10001, 0b11111, 0b10001, 0b10001, 0b10001],
            'E' => [0b11111, 0b10000, 0b10000, 0b11110, 0b10000, 0b10000, 0b11111],
            'L' => [0b10000, 0b10000, 0b10000, 0b10000, 0b10000, 0b10000, 0b11111],
            'Z' => [0b11111, 0b00001, 0b00010, 0b00100, 0b01000, 0b10000, 0b11111],
            ' ' => [0; 7],
            _ => return None,
        })
    }

    /// Width in image pixels of `text` at `scale`.
    pub fn text_width(text: &str, scale: usize) -> usize {
        text.chars().count() * (WIDTH + 1) * scale
    }

    /// Draws `text` at (`x0`, `y0`) in `color`, clipped to `max_w` pixels and the image; unknown
    /// characters are blank.
    pub fn draw(
        img: &mut Image,
        x0: usize,
        y0: usize,
        max_w: usize,
        text: &str,
        scale: usize,
        color: [u8; 3],
    ) {
        for (i, c) in text.chars().enumerate() {
            let Some(g) = glyph(c) else { continue };
            for (gy, bits) in g.iter().enumerate() {
                for gx in 0..WIDTH {
                    if bits & (1 << (WIDTH - 1 - gx)) == 0 {
                        continue;
                    }
                    for dy in 0..scale {
                        for dx in 0..scale {
                            let lx = (i * (WIDTH + 1) + gx) * scale + dx;
                            let (x, y) = (x0 + lx, y0 + gy * scale + dy);
                            if lx >= max_w || x >= img.width || y >= img.height {
                                continue;
                            }
                            let k = (y * img.width + x) * 4;
                            img.rgba[k..k + 3].copy_from_slice(&color);
                        }
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn params_errors_name_the_field() {
        let cases = [
            ("shading", "phong"),
            ("azimuth", "NaN"),
            ("elevation", "91"),
            ("light", "0,0,0"),
            ("light", "1,2"),
            ("light", "1,inf,0"),
            ("hardness", "0"),
            ("view", "1,0,0"),
            ("view_elevation", "0"),
            ("parallax", "pom"),
            ("parallax_steps", "0"),
            ("size", "-3"),
            ("precision", "12"),
            ("contact_sheet", "1000"),
            ("bogus", "1"),
        ];
        for (k, v) in cases {
            match PreviewParams::from_pairs([(k, v)]) {
                Err(Error::Param { field, .. }) => assert_eq!(field, k, "{k}={v}"),
                other => panic!("{k}={v}: expected a parameter error, got {other:?}"),
            }
        }
    }

    #[test]
    fn light_from_angles_and_vector() {
        let p = PreviewParams::from_pairs([("azimuth", "90"), ("elevation", "30")]).unwrap();
        let l = p.light_dir();
        assert!(
            l[0].abs() < 1e-12
                && (l[1] - 0.75f64.sqrt()).abs() < 1e-12
                && (l[2] - 0.5).abs() < 1e-12
        );
        let p = PreviewParams::from_pairs([("light", "3,0,4")]).unwrap();
        assert_eq!(p.light_dir(), [0.6, 0.0, 0.8]);
        let p = PreviewParams::from_pairs([("light", "3,0,4"), ("azimuth", "10")]).unwrap();
        assert_eq!(p.light_dir(), [0.6, 0.0, 0.8]);
    }

    #[test]
    fn sizes_and_labels() {
        assert_eq!(output_size(64, 32, None), (64, 32));
        assert_eq!(output_size(64, 32, Some(128)), (128, 64));
        assert_eq!(output_size(1, 300, Some(30)), (1, 30));
        assert_eq!(
            sheet_azimuths(90.0, 60.0, 9),
            vec![30.0, 45.0, 60.0, 75.0, 90.0, 105.0, 120.0, 135.0, 150.0]
        );
        assert_eq!(tile_label(-15.2), "AZ -15°");
        assert_eq!(tile_label(350.0), "AZ -10°");
        assert_eq!(tile_label(-0.3), "AZ 0°");
    }

    #[test]
    fn srgb_endpoints() {
        assert_eq!(srgb8(0.0), 0);
        assert_eq!(srgb8(1.0), 255);
        assert_eq!(srgb8(0.5), 188);
        assert_eq!(srgb8(f64::NAN), 0);
    }

    #[test]
    fn font_draws_the_glyph_bits() {
        let mut img = Image { width: 12, height: 7, rgba: vec![0; 12 * 7 * 4] };
        font::draw(&mut img, 0, 0, 12, "1-", 1, [255, 255, 255]);
        let on = |x: usize, y: usize| img.rgba[(y * 12 + x) * 4] == 255;
        // '1': column 2 of every row is on; row 0 only has column 2.
        for y in 0..7 {
            assert!(on(2, y));
        }
        assert!(!on(1, 0) && on(1, 1) && !on(0, 0));
        // '-' starts at x = 6: row 3 fully on, row 2 off.
        for x in 6..11 {
            assert!(on(x, 3) && !on(x, 2));
        }
        let lit = img.rgba.chunks_exact(4).filter(|p| p[0] == 255).count();
        assert_eq!(lit, 10 + 5); // "1" has 10 bits, "-" has 5
    }
}
