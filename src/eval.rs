//! Accuracy against time (SPEC §4): how much each horizon model gives up for its speed.
//!
//! For every map of a corpus the ground truth is the exact line-of-sight horizon (SPEC §3.2) at
//! `radius=unlimited`, computed once at [`TRUTH_BINS`] = 192 azimuths: 192 is a multiple of both
//! 24 and 64, so the 24 shadow-test azimuths (every 15°) and the 64 horizon-test azimuths (every
//! 5.625°) are bin centres and the truth is never interpolated.
//!
//! Each model is then baked the way a user would bake it (`bake::make_kernel` +
//! `bake::run_into_layers`, timed in this same process, on this machine) and decoded the way a
//! shader does: the stored layer values are turned back into s (v/255, v/65535 or v²), and the
//! channel-factor blend s = Σ max(f,0)·layer0 + max(−f,0)·layer1 (SPEC §3.3) is taken with the
//! factors of the light direction, either exact ([`Factors::Exact`]) or read from a UNORM8 cube
//! map of a given face size ([`Factors::Cube`], nearest or bilinear within the face, as a GPU
//! without seamless filtering samples it). Fourier models (SPEC §3.4) are baked with
//! `bake::bake_fourier` and decoded with `kernels::fourier` (coefficients from the stored bytes,
//! then Σ C_k·b_k(φ) at the light's azimuth). Models that differ only in how they are decoded
//! share one bake, and so one time.
//!
//! - shadow error: fraction of texels where (L_z > s) differs from (L_z > s_true), per light
//!   elevation (mean over the 24 azimuths) and overall (mean over all 144 lights);
//! - horizon error: mean |asin(s) − asin(s_true)| in degrees over 64 azimuths and every texel;
//!   for cube-map rows the cube is sampled in the direction of the true horizon, where the shadow
//!   boundary of that azimuth lies.
//!
//! [`report`] turns the rows into Markdown, CSV and JSON, [`plot`] draws error against time with
//! the Pareto front, and [`dump`] writes the files an independent script needs to recompute the
//! default model's numbers.

pub mod corpus;
pub mod dump;
pub mod plot;
pub mod report;

use crate::bake::{self, HorizonLayers, Precisions};
use crate::error::{Error, Result};
use crate::heightmap::HeightMap;
use crate::kernels::fourier::{self, FourierLayers, MAX_TERMS};
use crate::kernels::{self, cubemap, Grid};
use crate::params::{BakeParams, Edge, Encoding, FourierRange, Method, Radius, Reduce, YAxis};
use crate::progress::Progress;
use corpus::Map;
use rayon::prelude::*;
use serde::Serialize;
use std::f64::consts::PI;
use std::time::Instant;

/// Light elevations of the shadow error (SPEC §4), degrees.
pub const ELEVATIONS_DEG: [f64; 6] = [5.0, 10.0, 20.0, 30.0, 45.0, 60.0];
/// Light azimuths of the shadow error: 0°, 15°, …, 345°.
pub const SHADOW_AZIMUTHS: usize = 24;
/// Azimuths of the horizon error.
pub const HORIZON_AZIMUTHS: usize = 64;
/// Azimuth bins of the ground truth: lcm(24, 64), so every test azimuth is a bin centre.
pub const TRUTH_BINS: usize = 192;

/// How a model's layers are stored (and so decoded).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Storage {
    /// 8-bit UNORM of s (the default `png8`).
    U8,
    /// 16-bit UNORM of s (`png16`).
    U16,
    /// 8-bit UNORM of √s (`encoding=sqrt`).
    Sqrt8,
    /// 16-bit UNORM of √s.
    Sqrt16,
    /// f32 s (`exr`).
    F32,
}

impl Storage {
    fn encoding(self) -> Encoding {
        match self {
            Storage::Sqrt8 | Storage::Sqrt16 => Encoding::Sqrt,
            _ => Encoding::Linear,
        }
    }
    fn precisions(self) -> Precisions {
        match self {
            Storage::U8 | Storage::Sqrt8 => Precisions::U8,
            Storage::U16 | Storage::Sqrt16 => Precisions { u8: false, u16: true, f32: false },
            Storage::F32 => Precisions { u8: false, u16: false, f32: true },
        }
    }
    /// Short name used in model names and tables.
    pub fn label(self) -> &'static str {
        match self {
            Storage::U8 => "u8",
            Storage::U16 => "u16",
            Storage::Sqrt8 => "sqrt8",
            Storage::Sqrt16 => "sqrt16",
            Storage::F32 => "f32",
        }
    }
}

/// Where the channel factors of a light direction come from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize)]
#[serde(tag = "kind", rename_all = "lowercase")]
pub enum Factors {
    /// SPEC §3.3 computed exactly from the azimuth.
    Exact,
    /// A UNORM8 cube map with `size`² faces, sampled nearest or bilinear within the face.
    Cube { size: usize, bilinear: bool },
}

impl Factors {
    /// Short name used in model names and tables.
    pub fn label(self) -> String {
        match self {
            Factors::Exact => "exact".into(),
            Factors::Cube { size, bilinear } => {
                format!("cube{size} {}", if bilinear { "bilinear" } else { "nearest" })
            }
        }
    }
}

/// One model of the grid: bake parameters, storage and decoding.
#[derive(Debug, Clone, PartialEq)]
pub struct ModelSpec {
    /// Unique, human-readable (`lengyel R16 B32`, `exact Runlimited point`, …).
    pub name: String,
    /// Group in the tables and colour in the plot: `lengyel`, `exact`, `auto`, `storage`,
    /// `cubemap`, `fourier`.
    pub family: &'static str,
    pub params: BakeParams,
    pub storage: Storage,
    pub factors: Factors,
    /// Baked and decoded as Fourier coefficients (`params.fourier_terms`, `fourier_range`)
    /// instead of 8 channels.
    pub fourier: bool,
}

impl ModelSpec {
    fn new(name: String, family: &'static str, params: BakeParams) -> Self {
        ModelSpec {
            name,
            family,
            params,
            storage: Storage::U8,
            factors: Factors::Exact,
            fourier: false,
        }
    }
    /// The key of the bake this model needs: models with equal keys share one timed bake.
    fn bake_key(&self) -> String {
        let mut k: String =
            self.params.to_pairs().iter().map(|(a, b)| format!("{a}={b};")).collect();
        k.push_str(self.storage.label());
        if self.fourier {
            k.push_str(";fourier");
        }
        k
    }
}

/// The name of the default model (SPEC defaults, 8-bit layers, exact factors).
pub const DEFAULT_MODEL: &str = "lengyel R16 B32";

fn params(method: Method, radius: Radius, bins: u32, reduce: Reduce) -> BakeParams {
    BakeParams { method, radius, bins, reduce, ..BakeParams::default() }
}

/// The grid of models. `quick` keeps one representative of each family (for CI).
pub fn models(quick: bool) -> Vec<ModelSpec> {
    let mut out = Vec::new();
    let (radii, binss): (&[u32], &[u32]) =
        if quick { (&[4, 16], &[32]) } else { (&[4, 8, 16, 32, 64], &[16, 32, 64]) };
    for &r in radii {
        for &b in binss {
            out.push(ModelSpec::new(
                format!("lengyel R{r} B{b}"),
                "lengyel",
                params(Method::Lengyel, Radius::Texels(r), b, Reduce::Average),
            ));
        }
    }
    let exact_radii: &[Radius] = if quick {
        &[Radius::Texels(16), Radius::Unlimited]
    } else {
        &[Radius::Texels(16), Radius::Texels(64), Radius::Unlimited]
    };
    let reduces: &[Reduce] =
        if quick { &[Reduce::Average] } else { &[Reduce::Average, Reduce::Point] };
    for &r in exact_radii {
        for &red in reduces {
            let rn = match red {
                Reduce::Average => "average",
                Reduce::Point => "point",
            };
            out.push(ModelSpec::new(
                format!("exact R{r} {rn}"),
                "exact",
                params(Method::Exact, r, 32, red),
            ));
        }
    }
    // The fast approximation of exact at finite radii (SPEC §3.2a), beside exact at R16/R64.
    let march_radii: &[u32] = if quick { &[16] } else { &[16, 32, 64] };
    for &r in march_radii {
        out.push(ModelSpec::new(
            format!("march R{r} average"),
            "march",
            params(Method::March, Radius::Texels(r), 32, Reduce::Average),
        ));
    }
    // The radius-independent approximation (SPEC §3.2a), at several radii and unlimited.
    let sweep_radii: &[Radius] = if quick {
        &[Radius::Unlimited]
    } else {
        &[Radius::Texels(16), Radius::Texels(64), Radius::Unlimited]
    };
    for &r in sweep_radii {
        out.push(ModelSpec::new(
            format!("sweep R{r} average"),
            "sweep",
            params(Method::Sweep, r, 32, Reduce::Average),
        ));
    }
    let thetas: &[f64] = if quick { &[10.0] } else { &[5.0, 10.0, 20.0, 30.0] };
    for &t in thetas {
        let mut p = params(Method::Exact, Radius::Auto, 32, Reduce::Average);
        p.min_elevation_deg = t;
        out.push(ModelSpec::new(format!("exact auto {t}° average"), "auto", p));
    }
    let default = params(Method::Lengyel, Radius::Texels(16), 32, Reduce::Average);
    let exact_unl = params(Method::Exact, Radius::Unlimited, 32, Reduce::Average);
    let storages: &[Storage] = if quick {
        &[Storage::U16, Storage::Sqrt8]
    } else {
        &[Storage::U16, Storage::Sqrt8, Storage::Sqrt16, Storage::F32]
    };
    for (base, base_name) in [(&default, DEFAULT_MODEL), (&exact_unl, "exact Runlimited average")] {
        for &s in storages {
            let mut m =
                ModelSpec::new(format!("{base_name} {}", s.label()), "storage", base.clone());
            m.storage = s;
            if s == Storage::Sqrt8 || s == Storage::Sqrt16 {
                m.params.encoding = Encoding::Sqrt;
            }
            out.push(m);
        }
        if quick {
            break;
        }
    }
    let sizes: &[usize] = if quick { &[8] } else { &[4, 8, 16, 32] };
    for &size in sizes {
        for bilinear in [false, true] {
            let f = Factors::Cube { size, bilinear };
            let mut m = ModelSpec::new(
                format!("{DEFAULT_MODEL} {}", f.label()),
                "cubemap",
                default.clone(),
            );
            m.factors = f;
            out.push(m);
        }
    }
    let fourier_terms: &[u32] = if quick { &[5] } else { &[3, 5, 7, 9] };
    let ranges: &[FourierRange] = if quick {
        &[FourierRange::Standard]
    } else {
        &[FourierRange::Standard, FourierRange::Expanded]
    };
    let fourier_bases: &[(&BakeParams, &str)] = if quick {
        &[(&default, DEFAULT_MODEL)]
    } else {
        &[(&default, DEFAULT_MODEL), (&exact_unl, "exact Runlimited")]
    };
    for &(base, base_name) in fourier_bases {
        for &terms in fourier_terms {
            for &range in ranges {
                let rn = match range {
                    FourierRange::Standard => "standard",
                    FourierRange::Expanded => "expanded",
                };
                // The exact base only at the standard range: the range is a storage detail
                // already measured on the Lengyel base.
                if base.method == Method::Exact && range == FourierRange::Expanded {
                    continue;
                }
                let mut p = base.clone();
                p.fourier_terms = terms;
                p.fourier_range = range;
                let mut m =
                    ModelSpec::new(format!("fourier{terms} {rn} ({base_name})"), "fourier", p);
                m.fourier = true;
                out.push(m);
            }
        }
    }
    out
}

/// Errors of one model on one map.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Default)]
pub struct Metrics {
    /// Shadow error per light elevation ([`ELEVATIONS_DEG`]), fraction of texels.
    pub shadow_by_elevation: [f64; 6],
    /// Mean of `shadow_by_elevation` (= mean over all 144 lights).
    pub shadow_error: f64,
    /// Mean absolute horizon-angle error, degrees.
    pub horizon_error_deg: f64,
}

/// One model on one map, with the time of its bake.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Row {
    pub model: String,
    pub family: String,
    pub map: String,
    pub width: usize,
    pub height: usize,
    pub method: String,
    pub radius: String,
    /// The radius the kernel used (what `auto` and `unlimited` resolved to).
    pub resolved_radius: u32,
    pub bins: u32,
    pub reduce: String,
    pub min_elevation_deg: Option<f64>,
    pub storage: Storage,
    pub factors: String,
    /// Terms and range of a Fourier model.
    pub fourier_terms: Option<u32>,
    pub fourier_range: Option<FourierRange>,
    /// Bake time (kernel preparation + kernel + quantisation), best of the repeats.
    pub ms: f64,
    pub mtexel_per_s: f64,
    #[serde(flatten)]
    pub metrics: Metrics,
}

/// What a whole eval produced.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct EvalResult {
    /// One per model and map.
    pub rows: Vec<Row>,
    /// Time of each map's ground truth (exact, unlimited, 192 bins), ms.
    pub truth_ms: Vec<(String, f64)>,
    /// Threads of the rayon pool the times were measured with.
    pub threads: usize,
    pub quick: bool,
}

/// Options of [`run`].
#[derive(Debug, Clone)]
pub struct Options {
    pub quick: bool,
    /// Side of the generated maps.
    pub size: usize,
    /// Extra maps (e.g. the real-terrain excerpt).
    pub extra: Vec<(Map, Edge)>,
    /// Stop repeating a bake for its time once this much was spent on it (ms).
    pub repeat_budget_ms: f64,
    /// Where to write the files for the independent recomputation, if anywhere.
    pub dump: Option<std::path::PathBuf>,
    /// Progress lines on stderr.
    pub verbose: bool,
}

impl Default for Options {
    fn default() -> Self {
        Options {
            quick: false,
            size: 128,
            extra: Vec::new(),
            repeat_budget_ms: 300.0,
            dump: None,
            verbose: false,
        }
    }
}

/// The ground truth of a map: exact, unlimited radius, [`TRUTH_BINS`] azimuths,
/// `H·W·TRUTH_BINS` values of s.
///
/// # Errors
/// [`Error::Canceled`] never in practice (no one cancels); kept for the driver's signature.
pub fn ground_truth(map: &Map, edge: Edge) -> Result<Vec<f32>> {
    let p = BakeParams {
        method: Method::Exact,
        radius: Radius::Unlimited,
        bins: TRUTH_BINS as u32,
        edge,
        ..BakeParams::default()
    };
    let r = bake::resolve_radius(&p, map.width, map.height, &map.heights);
    let grid = Grid::new(map.width, map.height, &map.heights, edge, YAxis::Up);
    let kernel = bake::make_kernel(&p, grid, r.texels, &Progress::new());
    let (w, h) = (map.width, map.height);
    let mut out = vec![0.0f32; w * h * TRUTH_BINS];
    let band = kernels::band_rows_for(kernel.as_ref());
    let chunks: Vec<std::sync::Mutex<&mut [f32]>> =
        out.chunks_mut(band * w * TRUTH_BINS).map(std::sync::Mutex::new).collect();
    kernels::run_bands(kernel.as_ref(), band, true, &Progress::new(), |b, band| {
        if let (Ok(mut dst), Some(bins)) = (chunks[b].lock(), band.bins) {
            dst.copy_from_slice(bins);
        }
    })?;
    drop(chunks);
    Ok(out)
}

/// Light direction for azimuth/elevation in radians (SPEC §2 "Light").
fn light(az: f64, el: f64) -> [f64; 3] {
    [el.cos() * az.cos(), el.cos() * az.sin(), el.sin()]
}

/// A UNORM8 cube map of channel factors, decoded back to f64 as a shader reads it.
struct Cube {
    size: usize,
    texels: Vec<[f64; 4]>,
}

impl Cube {
    fn new(size: usize) -> Self {
        let f = cubemap::cube_factors_shared(size);
        let texels = f
            .chunks_exact(4)
            .map(|t| {
                let d = |v: f32| cubemap::unorm8(v) as f64 / 255.0 * 2.0 - 1.0;
                [d(t[0]), d(t[1]), d(t[2]), d(t[3])]
            })
            .collect();
        Cube { size, texels }
    }

    fn texel(&self, face: usize, u: i64, v: i64) -> [f64; 4] {
        let n = self.size as i64;
        let (u, v) = (u.clamp(0, n - 1) as usize, v.clamp(0, n - 1) as usize);
        self.texels[(face * self.size + v) * self.size + u]
    }

    /// Samples the face the direction selects: nearest, or bilinear with clamp-to-edge.
    fn sample(&self, d: [f64; 3], bilinear: bool) -> [f64; 4] {
        let (face, s, t) = cubemap::select_face(d);
        let n = self.size as f64;
        if !bilinear {
            return self.texel(face, (s * n).floor() as i64, (t * n).floor() as i64);
        }
        let (x, y) = (s * n - 0.5, t * n - 0.5);
        let (x0, y0) = (x.floor(), y.floor());
        let (fx, fy) = (x - x0, y - y0);
        let (x0, y0) = (x0 as i64, y0 as i64);
        let mut out = [0.0; 4];
        for (dx, dy, w) in [
            (0, 0, (1.0 - fx) * (1.0 - fy)),
            (1, 0, fx * (1.0 - fy)),
            (0, 1, (1.0 - fx) * fy),
            (1, 1, fx * fy),
        ] {
            let t = self.texel(face, x0 + dx, y0 + dy);
            for k in 0..4 {
                out[k] += w * t[k];
            }
        }
        out
    }
}

/// How a model turns its stored data back into s for a light direction, as a shader would.
/// `prepare` does the per-light work once (factors, basis values); `s` is the per-texel part.
pub trait Decoder: Sync {
    /// What `prepare` computes for one light direction.
    type Light: Sync;
    /// The per-light part of decoding, for a (not necessarily normalised) direction.
    fn prepare(&self, d: [f64; 3]) -> Self::Light;
    /// s of texel `t` for a prepared light.
    fn s(&self, light: &Self::Light, t: usize) -> f64;
}

/// 8 decoded channels per texel, blended with exact or cube-map factors.
pub struct ChannelDecoder<'a> {
    /// `H·W·8` values of s.
    pub ch: &'a [f64],
    factors: Factors,
    cube: Option<Cube>,
}

impl<'a> ChannelDecoder<'a> {
    /// A decoder over `ch` (`H·W·8`) reading factors from `factors`.
    pub fn new(ch: &'a [f64], factors: Factors) -> Self {
        let cube = match factors {
            Factors::Cube { size, .. } => Some(Cube::new(size)),
            Factors::Exact => None,
        };
        ChannelDecoder { ch, factors, cube }
    }
}

impl Decoder for ChannelDecoder<'_> {
    type Light = [f64; 4];
    fn prepare(&self, d: [f64; 3]) -> [f64; 4] {
        match (self.factors, &self.cube) {
            (Factors::Cube { bilinear, .. }, Some(c)) => c.sample(d, bilinear),
            _ => cubemap::factors_for_direction(d).map(|v| v as f64),
        }
    }
    #[inline]
    fn s(&self, f: &[f64; 4], t: usize) -> f64 {
        blend(f, &self.ch[t * 8..t * 8 + 8])
    }
}

/// Fourier coefficients per texel, evaluated at the light's azimuth (SPEC §3.4).
pub struct FourierDecoder {
    coeffs: Vec<[f64; MAX_TERMS]>,
    terms: usize,
}

impl FourierDecoder {
    /// Decodes the stored bytes of `layers` into coefficients, as a shader reads them
    /// (t = byte/255, then `fourier::decode_texel`).
    pub fn new(layers: &FourierLayers) -> Self {
        let n = layers.width * layers.height;
        let u = |b: u8| b as f64 / 255.0;
        let coeffs = (0..n)
            .map(|t| {
                let q = |v: &[u8]| [u(v[t * 4]), u(v[t * 4 + 1]), u(v[t * 4 + 2]), u(v[t * 4 + 3])];
                let high = layers.high.as_deref().map(q).unwrap_or([0.5; 4]);
                fourier::decode_texel(
                    q(&layers.bands),
                    u(layers.constant[t]),
                    high,
                    layers.terms,
                    layers.range,
                )
            })
            .collect();
        FourierDecoder { coeffs, terms: layers.terms }
    }
}

impl Decoder for FourierDecoder {
    type Light = [f64; MAX_TERMS];
    fn prepare(&self, d: [f64; 3]) -> [f64; MAX_TERMS] {
        let phi = d[1].atan2(d[0]);
        fourier::basis(phi.cos(), phi.sin())
    }
    #[inline]
    fn s(&self, b: &[f64; MAX_TERMS], t: usize) -> f64 {
        self.coeffs[t].iter().zip(b).take(self.terms).map(|(c, b)| c * b).sum()
    }
}

/// The channel-factor blend of SPEC §3.3 on one texel's 8 decoded channels.
#[inline]
pub fn blend(f: &[f64; 4], ch: &[f64]) -> f64 {
    f.iter()
        .zip(&ch[..4])
        .zip(&ch[4..8])
        .map(|((f, a), b)| f.max(0.0) * a + (-f).max(0.0) * b)
        .sum()
}

/// Decodes baked layers into `H·W·8` channel values of s, as a shader would read them.
pub fn decode_layers(layers: &HorizonLayers, storage: Storage) -> Vec<f64> {
    let n = layers.width * layers.height;
    let mut out = vec![0.0f64; n * 8];
    let sqrt = matches!(storage, Storage::Sqrt8 | Storage::Sqrt16);
    let fin = |v: f64| if sqrt { v * v } else { v };
    for layer in 0..2 {
        for t in 0..n {
            for k in 0..4 {
                let i = t * 4 + k;
                let v = if let Some(l) = &layers.u8 {
                    l[layer][i] as f64 / 255.0
                } else if let Some(l) = &layers.u16 {
                    l[layer][i] as f64 / 65535.0
                } else if let Some(l) = &layers.f32 {
                    l[layer][i] as f64
                } else {
                    0.0
                };
                out[t * 8 + layer * 4 + k] = fin(v);
            }
        }
    }
    out
}

/// Shadow and horizon error of decoded channels `ch` (`H·W·8`) against `truth`
/// (`H·W·TRUTH_BINS`), with the factors of `factors`.
pub fn metrics(ch: &[f64], truth: &[f32], factors: Factors) -> Metrics {
    metrics_of(&ChannelDecoder::new(ch, factors), truth)
}

/// Shadow and horizon error of any decoder against `truth` (`H·W·TRUTH_BINS`).
pub fn metrics_of<D: Decoder>(dec: &D, truth: &[f32]) -> Metrics {
    let texels = truth.len() / TRUTH_BINS;
    let mut m = Metrics::default();
    for (e, &el_deg) in ELEVATIONS_DEG.iter().enumerate() {
        let el = el_deg.to_radians();
        let lz = el.sin();
        let mut wrong = 0usize;
        for a in 0..SHADOW_AZIMUTHS {
            let az = a as f64 * 2.0 * PI / SHADOW_AZIMUTHS as f64;
            let l = dec.prepare(light(az, el));
            let bin = a * (TRUTH_BINS / SHADOW_AZIMUTHS);
            wrong += (0..texels)
                .into_par_iter()
                .filter(|&t| (lz > dec.s(&l, t)) != (lz > truth[t * TRUTH_BINS + bin] as f64))
                .count();
        }
        m.shadow_by_elevation[e] = wrong as f64 / (texels * SHADOW_AZIMUTHS) as f64;
    }
    m.shadow_error = m.shadow_by_elevation.iter().sum::<f64>() / ELEVATIONS_DEG.len() as f64;
    let step = TRUTH_BINS / HORIZON_AZIMUTHS;
    let sum: f64 = (0..texels)
        .into_par_iter()
        .map(|t| {
            let mut acc = 0.0;
            for a in 0..HORIZON_AZIMUTHS {
                let az = a as f64 * 2.0 * PI / HORIZON_AZIMUTHS as f64;
                let alpha = (truth[t * TRUTH_BINS + a * step] as f64).clamp(0.0, 1.0).asin();
                // Decoded in the direction of the true horizon, where the shadow boundary of
                // this azimuth lies (only the cube-map rows depend on the elevation).
                let s = dec.s(&dec.prepare(light(az, alpha)), t).clamp(0.0, 1.0);
                acc += (s.asin() - alpha).abs();
            }
            acc
        })
        .sum();
    m.horizon_error_deg = (sum / (texels * HORIZON_AZIMUTHS) as f64).to_degrees();
    m
}

/// Runs `f` once, then again while the total stays under `budget_ms` (at most 5 runs), and
/// returns the first result with the fastest time: short bakes are noisy, long ones are not.
fn timed<T>(budget_ms: f64, mut f: impl FnMut() -> Result<T>) -> Result<(T, f64)> {
    let t0 = Instant::now();
    let first = f()?;
    let mut best = t0.elapsed().as_secs_f64() * 1e3;
    let mut spent = best;
    let mut runs = 1;
    while spent + best < budget_ms && runs < 5 {
        let t = Instant::now();
        drop(f()?);
        let ms = t.elapsed().as_secs_f64() * 1e3;
        best = best.min(ms);
        spent += ms;
        runs += 1;
    }
    Ok((first, best))
}

/// One timed bake of `spec` on `map`: the layers and the resolved radius.
/// What one bake produced.
enum Baked {
    Layers(HorizonLayers),
    Fourier(FourierLayers),
}

fn bake_model(spec: &ModelSpec, map: &Map, edge: Edge) -> Result<(Baked, bake::ResolvedRadius)> {
    let mut p = spec.params.clone();
    p.edge = edge;
    if spec.fourier {
        // The corpus is already in texels: a height map of those values with height_scale 1.
        // The copy is part of the timed bake, as decoding is part of a user's.
        p.height_scale = 1.0;
        let hm = HeightMap::from_values(map.width, map.height, map.heights.clone())?;
        let (layers, r) = bake::bake_fourier(&hm, &p, &Progress::new())?;
        return Ok((Baked::Fourier(layers), r));
    }
    let r = bake::resolve_radius(&p, map.width, map.height, &map.heights);
    let grid = Grid::new(map.width, map.height, &map.heights, edge, YAxis::Up);
    let progress = Progress::new();
    let kernel = bake::make_kernel(&p, grid, r.texels, &progress);
    let layers = bake::run_into_layers(
        kernel.as_ref(),
        spec.storage.encoding(),
        spec.storage.precisions(),
        &progress,
    )?;
    Ok((Baked::Layers(layers), r))
}

/// Runs the whole eval: every model of [`models`] on every map.
///
/// # Errors
/// Whatever a bake or the dump fails with.
pub fn run(opts: &Options) -> Result<EvalResult> {
    if opts.size < 8 {
        return Err(Error::param("size", "the eval's maps must be at least 8 texels wide"));
    }
    let mut maps: Vec<(Map, Edge)> =
        corpus::generated(opts.size).into_iter().map(|m| (m, Edge::Wrap)).collect();
    if opts.quick {
        maps.truncate(2);
    }
    maps.extend(opts.extra.iter().cloned());
    let specs = models(opts.quick);
    let mut rows = Vec::new();
    let mut truth_ms = Vec::new();
    for (map, edge) in &maps {
        let t0 = Instant::now();
        let truth = ground_truth(map, *edge)?;
        let tms = t0.elapsed().as_secs_f64() * 1e3;
        if opts.verbose {
            eprintln!(
                "eval: {} {}×{}: ground truth in {tms:.0} ms",
                map.name, map.width, map.height
            );
        }
        truth_ms.push((map.name.clone(), tms));
        // Models sharing a bake are decoded from the same layers, timed once.
        let mut done: Vec<(String, Baked, bake::ResolvedRadius, f64)> = Vec::new();
        for spec in &specs {
            let key = spec.bake_key();
            let idx = match done.iter().position(|d| d.0 == key) {
                Some(i) => i,
                None => {
                    let ((layers, r), ms) =
                        timed(opts.repeat_budget_ms, || bake_model(spec, map, *edge))?;
                    done.push((key, layers, r, ms));
                    done.len() - 1
                }
            };
            let (_, baked, r, ms) = &done[idx];
            let metrics = match baked {
                Baked::Layers(layers) => {
                    let ch = decode_layers(layers, spec.storage);
                    let metrics = metrics(&ch, &truth, spec.factors);
                    if let (Some(dir), true) = (&opts.dump, spec.name == DEFAULT_MODEL) {
                        dump::write_map(dir, map, *edge, &truth, layers, &metrics)?;
                    }
                    metrics
                }
                Baked::Fourier(layers) => metrics_of(&FourierDecoder::new(layers), &truth),
            };
            if opts.verbose {
                eprintln!(
                    "eval: {:>8} {:<40} {:>9.1} ms  shadow {:>6.3}%  horizon {:>6.3}°",
                    map.name,
                    spec.name,
                    ms,
                    metrics.shadow_error * 100.0,
                    metrics.horizon_error_deg
                );
            }
            let texels = (map.width * map.height) as f64;
            rows.push(Row {
                model: spec.name.clone(),
                family: spec.family.into(),
                map: map.name.clone(),
                width: map.width,
                height: map.height,
                method: format!("{:?}", spec.params.method).to_lowercase(),
                radius: spec.params.radius.to_string(),
                resolved_radius: r.texels,
                bins: spec.params.bins,
                reduce: format!("{:?}", spec.params.reduce).to_lowercase(),
                min_elevation_deg: (spec.params.radius == Radius::Auto)
                    .then_some(spec.params.min_elevation_deg),
                storage: spec.storage,
                factors: if spec.fourier { "fourier".into() } else { spec.factors.label() },
                fourier_terms: spec.fourier.then_some(spec.params.fourier_terms),
                fourier_range: spec.fourier.then_some(spec.params.fourier_range),
                ms: *ms,
                mtexel_per_s: texels / (ms * 1e3).max(1e-9),
                metrics,
            });
        }
    }
    Ok(EvalResult { rows, truth_ms, threads: rayon::current_num_threads(), quick: opts.quick })
}
