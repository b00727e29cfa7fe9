//! One bake pipeline, from a decoded height map to encoded files in a [`Sink`], shared by the
//! CLI (`horizon-bake bake`, into a staging directory) and the service's worker (into the blob
//! store), so both produce the same bytes by the same steps.
//!
//! It is the one module that joins the kernels' output ([`crate::bake`]) to the encoders
//! ([`crate::encode`]): neither imports the other.
//! - PNG-only horizon outputs stream: the kernel's bands go in row order into PNG row writers
//!   over the sink's writers, so no layer and no encoded image is ever whole in memory.
//! - Anything else (EXR, KTX2, DDS) bakes whole layers at the precisions the formats need, then
//!   encodes them.
//! - Fourier outputs are baked before the streamed horizon layers, which consume the map, and
//!   so are the terrain products ([`terrain`]) and the surface maps ([`surface`]).
//!
//! Beside it: [`terrain`] (the GeoTIFF products), [`job`] (a stored bake record run through
//! this pipeline into the blob store: what the jobs core runs for the service) and [`tiled`]
//! (a map above `--tile-above`: split, a tile's bake, assembly). The service only wires them.

use crate::bake::{self, LayerRows, ResolvedRadius, Sample};
use crate::encode::{self, png, Formats, OutFile};
use crate::error::{Error, Result};
use crate::heightmap::HeightMap;
use crate::params::BakeParams;
use crate::progress::{Progress, Stage};
use std::time::Instant;

pub mod job;
pub mod surface;
pub mod terrain;
pub mod tiled;

pub use terrain::{
    angle_descriptions, distance_descriptions, distance_unit, openness_description, shadow_grey,
    shadow_png, shadow_tif, sun_description, svf_description, svf_grey, svf_png, terrain_files,
};

/// Where a bake's files go.
pub trait Sink {
    /// A file being streamed.
    type Writer: std::io::Write + Send + 'static;
    /// Starts streaming file `name`.
    ///
    /// # Errors
    /// The sink's failure.
    fn writer(&mut self, name: &'static str) -> Result<Self::Writer>;
    /// Keeps the two streamed horizon files, written completely.
    ///
    /// # Errors
    /// The sink's failure.
    fn finish(&mut self, files: [(&'static str, Self::Writer); 2]) -> Result<()>;
    /// Keeps a file encoded whole.
    ///
    /// # Errors
    /// The sink's failure.
    fn put(&mut self, file: OutFile) -> Result<()>;
    /// Keeps one streamed file, written completely (a spooled `angles.tif`).
    ///
    /// # Errors
    /// The sink's failure.
    fn finish_one(&mut self, name: &'static str, file: Self::Writer) -> Result<()>;
}

/// What [`produce`] made.
#[derive(Debug, Clone)]
pub struct Produced {
    /// The files, in the order they were kept.
    pub names: Vec<&'static str>,
    pub radius: ResolvedRadius,
    /// Kernel time (with the PNG encoding it overlaps when streaming), ms.
    pub bake_ms: f64,
    /// Encoding that does not overlap the kernel (whole-layer formats, Fourier PNGs), ms.
    pub encode_ms: f64,
    /// Handing files to the sink after they were encoded (flushes, uploads), ms.
    pub store_ms: f64,
    /// What each terrain product file holds (bands, units, conventions), for bake.json;
    /// `null` without terrain outputs.
    pub products: serde_json::Value,
}

/// The cube-map files for face size `size` (SPEC §4): the channel factors from the kernel,
/// encoded as `formats` asks.
///
/// # Errors
/// As [`encode::cube_files`].
pub fn cube_files(size: usize, formats: encode::CubeFormats) -> Result<Vec<OutFile>> {
    encode::cube_files(size, &crate::kernels::cubemap::cube_factors_shared(size), formats)
}

/// The conventions of `params`' horizon layers that the KTX2 files state (SPEC §8).
pub fn conventions(params: &BakeParams) -> encode::LayerConventions {
    encode::LayerConventions {
        y_axis_down: params.y_axis == crate::params::YAxis::Down,
        sqrt: params.encoding == crate::params::Encoding::Sqrt,
    }
}

/// Milliseconds since `t`, to the microsecond.
pub fn ms(t: Instant) -> f64 {
    (t.elapsed().as_secs_f64() * 1e6).round() / 1e3
}

/// Whether the horizon files can be streamed: only PNGs asked for (EXR, KTX2 and DDS need whole
/// layers).
pub fn streamable(formats: &Formats) -> bool {
    (formats.png8 || formats.png16) && !(formats.exr || formats.ktx2 || formats.dds)
}

/// What of the surface maps a bake with `params` must keep for `formats`: their values too
/// where a 16-bit PNG, an EXR or a 16-bit or float texture of them is written (SPEC §3.8: the
/// formats of the layers).
pub fn surface_keep(params: &BakeParams, formats: &Formats) -> bake::Surface {
    if !params.outputs.surface() {
        bake::Surface::None
    } else if formats.png16
        || formats.exr
        || ((formats.ktx2 || formats.dds)
            && matches!(
                formats.texture.precision,
                crate::encode::TexturePrecision::Unorm16 | crate::encode::TexturePrecision::Float32
            ))
    {
        bake::Surface::Values
    } else {
        bake::Surface::Bytes
    }
}

/// Bakes `map` with `params` into the files `formats` and `params.outputs` ask for, into `sink`.
///
/// # Errors
/// [`Error::Canceled`] when `progress` is canceled, the kernels', encoders' and sink's errors.
pub fn produce<S: Sink>(
    mut map: HeightMap,
    params: &BakeParams,
    formats: &Formats,
    progress: &Progress,
    sink: &mut S,
) -> Result<Produced> {
    let formats = &Formats { conventions: conventions(params), ..*formats };
    let mut names: Vec<&'static str> = Vec::new();
    let mut store_ms = 0.0;
    // Terrain products first: the streamed horizon layers below consume the map.
    let mut terrain = None;
    if params.outputs.terrain() {
        let t = Instant::now();
        // Nothing after the terrain products reads the map's values when they are the only
        // outputs: the bake takes them, scaled in place (one copy of the map, not two). The
        // sun products read them in metres.
        let o = params.outputs;
        let sole = !(o.horizon || o.fourier || o.surface() || o.sun());
        let heights = sole.then(|| map.take_scaled(params.height_scale));
        let (files, spooled, r, products) =
            terrain::terrain_parts(&map, heights, params, progress)?;
        let bake_ms = ms(t);
        if let Some(s) = spooled {
            // The streamed angles first, where the whole file used to come.
            let t = Instant::now();
            let name = s.name;
            let w = s.write_to(sink.writer(name)?)?;
            sink.finish_one(name, w)?;
            names.push(name);
            store_ms += ms(t);
        }
        store_ms += keep(sink, files, &mut names)?;
        terrain = Some((r, products, bake_ms));
    }
    // Surface maps (SPEC §3.8) next, for the same reason (their description joins the terrain
    // products' in bake.json), unless they come from the streamed horizon layers' own pass.
    let streams = params.outputs.horizon && streamable(formats);
    if params.outputs.surface() && !streams {
        let t = Instant::now();
        let (files, r, products) = surface::surface_files(&map, params, formats, progress)?;
        let bake_ms = ms(t);
        store_ms += keep(sink, files, &mut names)?;
        terrain = Some(match terrain {
            None => (r, products, bake_ms),
            Some((r0, mut p0, ms0)) => {
                join_products(&mut p0, products);
                (r0, p0, ms0 + bake_ms)
            }
        });
    }
    let products = terrain.as_ref().map_or(serde_json::Value::Null, |t| t.1.clone());
    let terrain_ms = terrain.as_ref().map_or(0.0, |t| t.2);
    if !params.outputs.horizon && !params.outputs.fourier {
        let (radius, products, bake_ms) =
            terrain.ok_or_else(|| Error::Internal("a bake with no outputs".into()))?;
        return Ok(Produced { names, radius, bake_ms, encode_ms: 0.0, store_ms, products });
    }
    let out = if streams {
        let t = Instant::now();
        let mut radius = None;
        if params.outputs.fourier {
            let (files, r) = fourier_files(&map, params, progress)?;
            store_ms += keep(sink, files, &mut names)?;
            radius = Some(r);
        }
        let fourier_ms = ms(t);
        let t = Instant::now();
        let kept = surface_keep(params, formats);
        let (writers, r, surface) = if formats.png16 {
            stream_into::<u16, S>(map, params, kept, progress, sink)?
        } else {
            stream_into::<u8, S>(map, params, kept, progress, sink)?
        };
        let bake_ms = ms(t);
        let mut products = products.clone();
        if let Some(m) = surface {
            let (files, info) = surface::surface_outputs(&m, params, formats, progress)?;
            store_ms += keep(sink, files, &mut names)?;
            join_products(&mut products, info);
        }
        let t = Instant::now();
        sink.finish(writers)?;
        store_ms += ms(t);
        names.extend(["horizon_0.png", "horizon_1.png"]);
        // Both kernels resolve the radius alike; the horizon's is reported.
        drop(radius);
        Produced {
            names: Vec::new(),
            radius: r,
            bake_ms: bake_ms + terrain_ms,
            encode_ms: fourier_ms,
            store_ms: 0.0,
            products,
        }
    } else {
        let t = Instant::now();
        let layers = if params.outputs.horizon {
            Some(bake::bake_horizon(&map, params, formats.precisions(), progress)?)
        } else {
            None
        };
        let bake_ms = ms(t);
        let t = Instant::now();
        progress.start(Stage::Encode, 1);
        let mut radius = None;
        let mut files = match &layers {
            Some((l, r)) => {
                radius = Some(r.clone());
                encode_each(l, Some((&map, params)), formats, progress)?
            }
            None => Vec::new(),
        };
        drop(layers);
        if params.outputs.fourier {
            let (fourier, r) = fourier_files(&map, params, progress)?;
            files.extend(fourier);
            radius.get_or_insert(r);
        }
        let encode_ms = ms(t);
        store_ms += keep(sink, files, &mut names)?;
        let radius = radius.ok_or_else(|| Error::Internal("a bake with no outputs".into()))?;
        Produced {
            names: Vec::new(),
            radius,
            bake_ms: bake_ms + terrain_ms,
            encode_ms,
            store_ms: 0.0,
            products: products.clone(),
        }
    };
    if progress.is_canceled() {
        return Err(Error::Canceled);
    }
    Ok(Produced { names, store_ms, ..out })
}

/// Encodes whole layers into the files of `formats`, one format at a time with a cancel check
/// before each, so a canceled bake does not wait for every encoder (an 8192² float EXR pair
/// alone takes seconds).
///
/// # Errors
/// [`Error::Canceled`], and the encoders' errors.
///
/// KTX2/DDS with `mips=full` and `mip_filter=rebake` bake their levels again
/// ([`rebake_levels`]) from `heights`, the map and parameters `layers` were baked from (once for
/// both containers); without it they are an [`Error::Param`] naming `mip_filter`.
pub fn encode_each(
    layers: &bake::HorizonLayers,
    heights: Option<(&HeightMap, &BakeParams)>,
    formats: &Formats,
    progress: &Progress,
) -> Result<Vec<OutFile>> {
    let below = match heights {
        Some((map, params))
            if (formats.ktx2 || formats.dds) && encode::texture::rebakes(&formats.texture) =>
        {
            let below = rebake_levels(map, params, formats.precisions(), progress)?;
            progress.start(Stage::Encode, 1);
            below
        }
        _ => Vec::new(),
    };
    let none =
        Formats { png8: false, png16: false, exr: false, ktx2: false, dds: false, ..*formats };
    let each = [
        Formats { png8: formats.png8, ..none },
        Formats { png16: formats.png16, ..none },
        Formats { exr: formats.exr, ..none },
        Formats { ktx2: formats.ktx2, ..none },
        Formats { dds: formats.dds, ..none },
    ];
    let mut files = Vec::new();
    for one in each.iter().filter(|f| **f != none) {
        if progress.is_canceled() {
            return Err(Error::Canceled);
        }
        files.extend(encode::horizon_files_levels(layers, &below, one, progress)?);
    }
    Ok(files)
}

/// The map of the mip level below: heights box-filtered by [`encode::mips::box_heights`], a
/// hole wherever a parent texel is one ([`encode::mips::any_holes`]), the nodata value kept
/// and the georeferencing dropped (its pixel size is the full map's).
pub fn level_map(map: &HeightMap) -> HeightMap {
    let (w, h) = (map.width, map.height);
    HeightMap {
        width: encode::mips::next_size(w),
        height: encode::mips::next_size(h),
        values: encode::mips::box_heights(&map.values, w, h),
        terrain: crate::heightmap::Terrain {
            georef: None,
            nodata: map.terrain.nodata,
            holes: map.terrain.holes.as_ref().map(|m| encode::mips::any_holes(m, w, h)),
        },
    }
}

/// The radius, in texels, that `mip_filter=rebake` bakes level `level` with: the radius of
/// level 0 resolved on the full map (`unlimited` to max(W, H), `auto` from its height range,
/// `max_distance` from the cell size), halved per level, at least 1.
pub fn rebake_radius(level0: &ResolvedRadius, level: usize) -> u32 {
    (level0.texels.checked_shr(level as u32).unwrap_or(0)).max(1)
}

/// The levels 1.. of a full mip chain for `mip_filter=rebake` (SPEC §8): level `l` is the bake
/// of `map` box-filtered `l` times ([`level_map`], so `max(1, W >> l) × max(1, H >> l)`), with
/// `params` except the radius, [`rebake_radius`]; quantised at `precisions` as level 0 is.
/// Each level costs a quarter of the one above: the chain about a third of the bake.
///
/// # Errors
/// [`Error::Canceled`], and the kernels' errors.
pub fn rebake_levels(
    map: &HeightMap,
    params: &BakeParams,
    precisions: crate::layers::Precisions,
    progress: &Progress,
) -> Result<Vec<bake::HorizonLayers>> {
    let r0 = bake::resolve_radius(params, map.width, map.height, &map.scaled(params.height_scale));
    let n = encode::mips::full_levels(map.width, map.height);
    let mut out = Vec::with_capacity(n.saturating_sub(1));
    let mut level = std::borrow::Cow::Borrowed(map);
    for l in 1..n {
        if progress.is_canceled() {
            return Err(Error::Canceled);
        }
        level = std::borrow::Cow::Owned(level_map(&level));
        let p = BakeParams {
            radius: crate::params::Radius::Texels(rebake_radius(&r0, l)),
            max_distance: None,
            ..params.clone()
        };
        out.push(bake::bake_horizon(&level, &p, precisions, progress)?.0);
    }
    Ok(out)
}

/// The two streamed horizon files, named, before the sink keeps them.
type Streamed<S> = [(&'static str, <S as Sink>::Writer); 2];

/// Adds the file descriptions `more` to bake.json's `products` (`null` until a product is
/// described).
fn join_products(into: &mut serde_json::Value, more: serde_json::Value) {
    match (into, more) {
        (serde_json::Value::Object(a), serde_json::Value::Object(b)) => a.extend(b),
        (into @ serde_json::Value::Null, more) => *into = more,
        _ => {}
    }
}

/// Hands whole files to the sink; returns the time it took, ms.
fn keep<S: Sink>(sink: &mut S, files: Vec<OutFile>, names: &mut Vec<&'static str>) -> Result<f64> {
    let t = Instant::now();
    for f in files {
        names.push(f.name);
        sink.put(f)?;
    }
    Ok(ms(t))
}

/// The streamed horizon PNGs into `sink`'s writers, and the surface maps `params` asks for
/// from the same kernel pass.
fn stream_into<T: Sample + png::PngSample, S: Sink>(
    map: HeightMap,
    params: &BakeParams,
    surface: bake::Surface,
    progress: &Progress,
    sink: &mut S,
) -> Result<(Streamed<S>, ResolvedRadius, Option<bake::SurfaceMaps>)> {
    const NAMES: [&str; 2] = ["horizon_0.png", "horizon_1.png"];
    let outs = [sink.writer(NAMES[0])?, sink.writer(NAMES[1])?];
    let ([a, b], radius, maps) =
        stream_horizon_pngs_tapped::<T, _>(map, params, surface, progress, outs)?;
    Ok(([(NAMES[0], a), (NAMES[1], b)], radius, maps))
}

/// Bakes `map` into two PNGs (layers 0 and 1, 8- or 16-bit RGBA as `T` says), written to `outs`
/// band by band in row order ([`bake::stream_horizon`] into [`png::PngRowWriter`]s): no whole
/// layer and, with files as `outs`, no whole encoded image is ever in memory.
///
/// # Errors
/// [`Error::Canceled`] when `progress` is canceled (checked between bands), [`Error::Io`] from
/// `outs`, [`Error::Internal`] from the encoder.
pub fn stream_horizon_pngs<T, W>(
    map: HeightMap,
    params: &BakeParams,
    progress: &Progress,
    outs: [W; 2],
) -> Result<([W; 2], ResolvedRadius)>
where
    T: Sample + png::PngSample,
    W: std::io::Write + Send + 'static,
{
    let (files, radius, _) =
        stream_horizon_pngs_tapped::<T, W>(map, params, bake::Surface::None, progress, outs)?;
    Ok((files, radius))
}

/// [`stream_horizon_pngs`], and the surface maps `surface` keeps from the same kernel pass
/// ([`bake::stream_horizon_tapped`]).
///
/// # Errors
/// As [`stream_horizon_pngs`].
pub fn stream_horizon_pngs_tapped<T, W>(
    map: HeightMap,
    params: &BakeParams,
    surface: bake::Surface,
    progress: &Progress,
    outs: [W; 2],
) -> Result<([W; 2], ResolvedRadius, Option<bake::SurfaceMaps>)>
where
    T: Sample + png::PngSample,
    W: std::io::Write + Send + 'static,
{
    let (w, h) = (map.width, map.height);
    let [o0, o1] = outs;
    let mut writers = [
        png::PngRowWriter::<W, T>::new(o0, w, h, png::PngColor::Rgba)?,
        png::PngRowWriter::<W, T>::new(o1, w, h, png::PngColor::Rgba)?,
    ];
    let (radius, maps) =
        bake::stream_horizon_tapped(map, params, surface, progress, |rows: LayerRows<'_, T>| {
            // The two layers side by side; each writer also deflates its pieces on the pool.
            let [w0, w1] = &mut writers;
            let (a, b) =
                rayon::join(|| w0.write_rows(rows.layers[0]), || w1.write_rows(rows.layers[1]));
            a.and(b)
        })?;
    let [w0, w1] = writers;
    Ok(([w0.finish()?, w1.finish()?], radius, maps))
}

/// Bakes the Fourier coefficients (SPEC §3.4) into `fourier_0.png`, `fourier_1.png` and, with
/// 7 or 9 terms, `fourier_2.png`.
///
/// # Errors
/// Whatever the bake or the PNG encoder fails with.
pub fn fourier_files(
    map: &HeightMap,
    params: &BakeParams,
    progress: &Progress,
) -> Result<(Vec<OutFile>, ResolvedRadius)> {
    const NAMES: [&str; 3] = ["fourier_0.png", "fourier_1.png", "fourier_2.png"];
    let (layers, radius) = bake::bake_fourier(map, params, progress)?;
    let files = (0..layers.layer_count())
        .map(|i| Ok(OutFile { name: NAMES[i], bytes: encode::fourier_png(&layers, i)? }))
        .collect::<Result<Vec<_>>>()?;
    Ok((files, radius))
}
