//! What a tiled bake computes (SPEC §7.1): the [`Tiler`] the jobs core runs for
//! each step of a bake whose map is above `--tile-above` texels, and the checks that refuse at
//! submission what a tiled bake cannot do.
//!
//! - **split**: decode the input, compute what the kernels derive from the whole map (the
//!   scaled height range, hence `radius=auto`'s radius and the kernels' reference height), cut
//!   the map into tile windows ([`crate::jobs::tiles::TilePlan`]) and store each as a blob.
//! - **tile**: bake a window with the whole map's range and radius ([`bake::bake_window`]),
//!   keep its interior, store it as a blob (both layers at the precision the formats need).
//! - **assemble**: stream the PNG layers band by band from the tiles' blobs, reading each tile's
//!   rows by range: no whole layer is ever in memory.
//!
//! The blobs are [`crate::heightmap::stream`]'s `HBH1` tile heights (decoded from the input
//! in row bands, never whole) and [`crate::encode::assemble`]'s `HBR1` tile results (read back
//! by range, one band at a time).

use super::job::{formats_of, params_of, result_name, HORIZON_RESULTS};
use super::ms;
use crate::bake;
use crate::encode::assemble::{self, Plane, Section, TilePiece, TileRows};
use crate::encode::{png, Formats};
use crate::error::{Error, Result};
use crate::heightmap::stream::{self, MapStats, TileHeights, Window};
use crate::heightmap::{self, HeightMap, Limits};
use crate::jobs::blob::{read_range, BlobSeekReader, BlobStore};
use crate::jobs::record::{now_ms, BakeRecord, RadiusInfo, Status, Timings};
use crate::jobs::record::{TileContext, TileRecord};
use crate::jobs::tiles::{self, TilePlan};
use crate::jobs::{Blobs, Tiler};
use crate::params::{BakeParams, Radius};
use crate::progress::{Progress, Stage};
use std::collections::BTreeMap;
use std::io::Write;
use std::sync::Arc;
use std::time::Instant;

/// When and how bakes are tiled (`--tile-above`, `--tile-size`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TileSettings {
    /// Maps with more texels than this are tiled.
    pub tile_above: u64,
    pub tile_size: u32,
}

impl TileSettings {
    /// Whether a `width` × `height` map is tiled.
    pub fn tiles(&self, width: u32, height: u32) -> bool {
        tiles::is_tiled(width, height, self.tile_above)
    }
}

/// Refuses at submission what a tiled bake cannot do (a 422 naming the parameter): nothing for
/// a map at or below `--tile-above`.
///
/// # Errors
/// [`Error::Param`]: `radius` for `unlimited` (it needs the whole map) or a halo larger than the
/// map, `tile_size` for a tile smaller than its halo, `outputs` / `formats` for what tiled bakes
/// do not assemble.
pub fn check(
    params: &BakeParams,
    formats: &Formats,
    width: u32,
    height: u32,
    s: &TileSettings,
) -> Result<()> {
    if !s.tiles(width, height) {
        return Ok(());
    }
    if params.method == crate::params::Method::Sweep {
        // Its far field spans the whole map (and is not yet proven crop-invariant).
        return Err(Error::param(
            "method",
            format!(
                "method=sweep bakes a whole map at once, and this {width}×{height} map is above \
                 --tile-above ({} texels), so it is baked in tiles; use method=march or exact \
                 with a finite radius, radius=auto or max_distance",
                s.tile_above
            ),
        ));
    }
    let by_distance = params.max_distance.is_some() && params.cell_size.is_some();
    if params.radius == Radius::Unlimited && !by_distance && !params.explicit.has("radius") {
        // The DEM defaults' unlimited reach (SPEC §2) on a map that tiles cannot take whole.
        return Err(Error::param(
            "radius",
            format!(
                "a DEM without `radius` is baked to the map's edge (radius=unlimited), which \
                 needs the whole map, and this {width}×{height} map is above --tile-above ({} \
                 texels), so it is baked in tiles that each read only their neighbourhood; \
                 give the reach: max_distance (map units, e.g. max_distance=10000) or radius",
                s.tile_above
            ),
        ));
    }
    if params.radius == Radius::Unlimited && !by_distance {
        return Err(Error::param(
            "radius",
            format!(
                "radius=unlimited needs the whole map, and this {width}×{height} map is above \
                 --tile-above ({} texels), so it is baked in tiles that each read only their \
                 neighbourhood; use radius=auto (with min_elevation_deg) or max_distance (with \
                 cell_size), or a finite radius",
                s.tile_above
            ),
        ));
    }
    let o = params.outputs;
    // horizon_distance is the walk's arg max, which a tile's window can pick differently from
    // the whole map's where two points of a ray tie to the last bit (the walk's positions are
    // the window's, their rounding too): not byte-identical, so not tiled.
    if o.fourier || o.surface() || o.horizon_distance {
        return Err(Error::param(
            "outputs",
            "a tiled bake (map above --tile-above) produces the horizon layers and the terrain \
             products angles, svf, openness, sun_hours and insolation; not fourier, \
             horizon_distance, nor yet the surface maps (normal, ao, bent_normal)",
        ));
    }
    // Each terrain product is one classic GeoTIFF, assembled tile by tile: the untiled bake's
    // limit on its values holds (the file's 4 GiB offsets), not on memory.
    let texels = width as u64 * height as u64;
    let nb = params.bins as u64;
    if params.outputs.angles && texels * nb > bake::MAX_ANGLE_VALUES {
        return Err(Error::param(
            "bins",
            format!(
                "angles of a {width}×{height} map at {nb} bins are {} values, above the limit \
                 of {}; use fewer bins or a smaller map",
                texels * nb,
                bake::MAX_ANGLE_VALUES
            ),
        ));
    }
    if params.outputs.svf && texels > bake::MAX_ANGLE_VALUES {
        return Err(Error::param(
            "outputs",
            format!(
                "svf of a {width}×{height} map is {texels} values, above the limit of {} for \
                 one GeoTIFF; ask for outputs=horizon or use a smaller map",
                bake::MAX_ANGLE_VALUES
            ),
        ));
    }
    if formats.exr {
        return Err(Error::param(
            "formats",
            "a tiled bake (map above --tile-above) is assembled as png8, png16, ktx2 or dds \
             (level 0, uncompressed); not exr",
        ));
    }
    if formats.ktx2 || formats.dds {
        assemble::check_tiled_texture(&formats.texture)?;
    }
    if params.radius != Radius::Auto || by_distance {
        let r = bake::resolve_radius_in(params, width as usize, height as usize, || (0.0, 0.0));
        TilePlan::new(width, height, s.tile_size, tiles::halo_for(r.texels), params.edge)?;
    }
    Ok(())
}

/// The service's [`Tiler`].
pub struct PipelineTiler {
    pub limits: Limits,
    pub settings: TileSettings,
    pub store: Arc<dyn BlobStore>,
}

impl Tiler for PipelineTiler {
    fn is_tiled(&self, rec: &BakeRecord) -> bool {
        self.settings.tiles(rec.width, rec.height)
    }

    fn split(
        &self,
        rec: &BakeRecord,
        progress: &Progress,
        blobs: &Blobs,
    ) -> Result<Vec<TileRecord>> {
        let t = Instant::now();
        let params = params_of(rec)?;
        progress.start(Stage::Decode, 1);
        let decode = |windows: &[Window], sink: &mut dyn FnMut(usize, Vec<u8>) -> Result<()>| {
            let input =
                BlobSeekReader::open(self.store.clone(), &rec.input_blob)?.ok_or_else(|| {
                    Error::Internal(format!("input blob {} is missing", rec.input_blob))
                })?;
            stream::decode_tiles(
                input,
                &rec.input_blob,
                params.decode_channel(),
                params.nodata,
                &self.limits,
                windows,
                sink,
            )
        };
        // `radius=auto` needs the whole map's height range before the halo is known: one pass
        // for the statistics alone, then the pass that cuts the tiles.
        let by_distance = params.max_distance.is_some() && params.cell_size.is_some();
        let first = if params.radius == Radius::Auto && !by_distance {
            Some(decode(&[], &mut |_, _| Ok(()))?)
        } else {
            None
        };
        if params.radius == Radius::Unlimited && !by_distance {
            return Err(Error::param("radius", "radius=unlimited needs the whole map: not tiled"));
        }
        let (w, h) = (rec.width, rec.height);
        let radius = bake::resolve_radius_in(&params, w as usize, h as usize, || {
            first.as_ref().map_or((0.0, 0.0), |s| s.scaled_range(params.height_scale))
        });
        let halo = tiles::halo_for(radius.texels);
        let plan = TilePlan::new(w, h, self.settings.tile_size, halo, params.edge)?;
        let windows: Vec<Window> = plan.tiles().map(|g| window_of(&g)).collect();
        let mut hashes = vec![String::new(); windows.len()];
        // The windows are stored on their own thread while the decode goes on (a put is a
        // network transfer: the decoder need not wait for it); two wait their turn at most.
        let (stats, stored) = std::thread::scope(|scope| {
            let (tx, rx) = std::sync::mpsc::sync_channel::<(usize, Vec<u8>)>(2);
            let putter = scope.spawn(move || -> Result<Vec<(usize, String)>> {
                rx.into_iter().map(|(i, blob)| Ok((i, blobs.put(&blob)?))).collect()
            });
            let stats = decode(&windows, &mut |i, blob| {
                if progress.is_canceled() {
                    return Err(Error::Canceled);
                }
                // A closed channel means the putter failed: its error is the one reported.
                tx.send((i, blob)).map_err(|_| Error::Internal("the tile store stopped".into()))
            });
            drop(tx);
            let stored = putter
                .join()
                .unwrap_or_else(|_| Err(Error::Internal("storing a tile panicked".into())));
            (stats, stored)
        });
        for (i, hash) in stored? {
            hashes[i] = hash;
        }
        let stats = stats?;
        let range = stats.scaled_range(params.height_scale);
        bake::check_scaled(&[range.0, range.1])?;
        let ctx = TileContext {
            plan,
            range,
            radius: radius.texels,
            radius_reason: radius.reason,
            input: Some(stats.info.clone()),
            split_ms: ms(t),
            stats: stats.to_json(),
        };
        progress.advance(1);
        Ok(hashes
            .into_iter()
            .enumerate()
            .map(|(i, hash)| TileRecord::new(&rec.id, i as u32, hash, ctx.clone()))
            .collect())
    }

    fn bake_tile(
        &self,
        rec: &BakeRecord,
        tile: &TileRecord,
        progress: &Progress,
        blobs: &Blobs,
    ) -> Result<BTreeMap<String, String>> {
        let mut params = params_of(rec)?;
        let formats = formats_of(rec)?;
        let bytes = blobs
            .get(&tile.input_blob)?
            .ok_or_else(|| Error::Internal(format!("tile blob {} is missing", tile.input_blob)))?;
        let heights = TileHeights::decode(&bytes)?;
        drop(bytes);
        let window = if tile.context.stats.is_null() {
            raw_window(heights)
        } else {
            let stats = MapStats::from_json(&tile.context.stats)?;
            // What the untiled bake reads from the input with the DEM defaults.
            let dem = stats.georef.as_ref().filter(|g| g.is_dem());
            params.linear_unit_m = dem.map_or(1.0, |g| g.linear_unit_m());
            heights.into_map(&stats)
        };
        let mut w = blobs.writer()?;
        bake_tile_into(window, &params, &formats, &tile.context, tile.index, progress, &mut w)?;
        let hash = w.commit()?;
        Ok(BTreeMap::from([("tile".to_owned(), hash)]))
    }

    fn assemble(
        &self,
        rec: &BakeRecord,
        tiles: &[TileRecord],
        progress: &Progress,
        blobs: &Blobs,
    ) -> Result<BakeRecord> {
        let t = Instant::now();
        let formats = formats_of(rec)?;
        let first =
            tiles.first().ok_or_else(|| Error::Internal("a tiled bake without tiles".into()))?;
        let ctx = &first.context;
        let pieces: Vec<(tiles::TileGeom, String)> = tiles
            .iter()
            .map(|t| {
                let h = t.results.get("tile").cloned();
                let h = h.ok_or_else(|| Error::Internal(format!("tile {} has no result", t.index)));
                Ok((t.geom(), h?))
            })
            .collect::<Result<_>>()?;
        let read = || -> assemble::ReadRange {
            let store = self.store.clone();
            Arc::new(move |hash: &str, start, len| read_range(store.as_ref(), hash, start, len))
        };
        let params = params_of(rec)?;
        let formats = Formats { conventions: crate::pipeline::conventions(&params), ..formats };
        let mut done = rec.clone();
        let (w, h) = (ctx.plan.width as usize, ctx.plan.height as usize);
        if params.outputs.terrain() {
            // As the untiled bake: its georeferencing and nodata, its band descriptions.
            let stats = match &ctx.stats {
                serde_json::Value::Null => None,
                j => Some(MapStats::from_json(j)?),
            };
            let georef = stats.as_ref().and_then(|s| s.georef.clone());
            let nodata = stats.as_ref().and_then(|s| s.nodata).map_or(f32::NAN, |v| v as f32);
            let nb = params.bins as usize;
            let o = params.outputs;
            use assemble::tag;
            let files = [
                (o.angles, "angles.tif", tag::ANGLES),
                (o.svf, "svf.tif", tag::SVF),
                (o.horizon_distance, "horizon_distance.tif", tag::DISTANCE),
                (o.openness, "openness_positive.tif", tag::OPENNESS_POSITIVE),
                (o.openness, "openness_negative.tif", tag::OPENNESS_NEGATIVE),
                (o.sun_hours, "sun_hours.tif", tag::SUN_HOURS),
                (o.insolation, "insolation.tif", tag::INSOLATION),
            ];
            progress.start(Stage::Encode, files.iter().filter(|f| f.0).count() as u64);
            let (compass, _) = crate::heightmap::north::compass(
                georef.as_ref(),
                (0, 0),
                (w, h),
                (w, h),
                params.y_axis,
            );
            let true_north = compass.is_true();
            for (wanted, name, tag) in files {
                if !wanted {
                    continue;
                }
                // The untiled bake's band descriptions (pipeline::terrain_files).
                let names = match tag {
                    tag::ANGLES => crate::pipeline::angle_descriptions(&params, nb, true_north),
                    tag::SVF => vec![crate::pipeline::svf_description(&params, nb)],
                    tag::DISTANCE => {
                        let unit = crate::pipeline::distance_unit(georef.as_ref(), &params);
                        crate::pipeline::distance_descriptions(&params, nb, &unit, true_north)
                    }
                    tag::OPENNESS_POSITIVE | tag::OPENNESS_NEGATIVE => {
                        let sign =
                            if tag == tag::OPENNESS_POSITIVE { "positive" } else { "negative" };
                        vec![crate::pipeline::openness_description(sign, nb, ctx.radius)]
                    }
                    _ => vec![crate::pipeline::sun_description(&params, tag == tag::INSOLATION)],
                };
                let mut rows = TileRows::new(read(), pieces_of(&pieces), w, h)?;
                let mut src = |b: usize, y: usize, out: &mut [f32]| {
                    if progress.is_canceled() {
                        return Err(Error::Canceled);
                    }
                    rows.read(tag, b, y, out)
                };
                let out = assemble::write_geotiff(
                    blobs.writer()?,
                    w,
                    h,
                    &names,
                    georef.as_ref(),
                    nodata,
                    None,
                    &mut src,
                )?;
                done.results.insert(name.to_owned(), out.commit()?);
                progress.advance(1);
            }
        }
        let textures = params.outputs.horizon && (formats.ktx2 || formats.dds);
        if params.outputs.horizon && (formats.png8 || formats.png16 || !textures) {
            let outs = [blobs.writer()?, blobs.writer()?];
            let [a, b] = if formats.png16 {
                assemble_pngs::<u16, _>(&ctx.plan, &pieces, &read, progress, outs)?
            } else {
                assemble_pngs::<u8, _>(&ctx.plan, &pieces, &read, progress, outs)?
            };
            let (h0, h1) = (a.commit()?, b.commit()?);
            let (n0, n1) = if formats.png16 {
                (HORIZON_RESULTS[2], HORIZON_RESULTS[3])
            } else {
                (HORIZON_RESULTS[0], HORIZON_RESULTS[1])
            };
            done.results.insert(n0.to_owned(), h0);
            done.results.insert(n1.to_owned(), h1);
        }
        if textures {
            let mut rows = TileRows::new(read(), pieces_of(&pieces), w, h)?;
            let mut kept = Vec::new();
            assemble::write_textures(
                &mut rows,
                w,
                h,
                &formats,
                &mut |_| blobs.writer(),
                &mut |name, writer| {
                    kept.push((result_name(&formats, name), writer.commit()?));
                    Ok(())
                },
            )?;
            done.results.extend(kept);
        }
        done.status = Status::Succeeded;
        done.input = ctx.input.clone();
        done.radius = Some(RadiusInfo { texels: ctx.radius, reason: ctx.radius_reason.clone() });
        let now = now_ms();
        done.finished_ms = Some(now);
        done.error = None;
        let started = rec.started_ms.unwrap_or(rec.created_ms);
        let total = now.saturating_sub(started) as f64;
        let encode = ms(t);
        done.timings_ms = Some(Timings {
            queued: started.saturating_sub(rec.created_ms) as f64,
            decode: ctx.split_ms,
            bake: (total - ctx.split_ms - encode).max(0.0),
            encode,
            store: 0.0,
            total,
        });
        progress.start(Stage::Done, 1);
        progress.advance(1);
        Ok(done)
    }
}

/// The window of a tile, as the streamed decode cuts it.
fn window_of(g: &tiles::TileGeom) -> Window {
    Window { x0: g.window_x, y0: g.window_y, width: g.window_w, height: g.window_h }
}

/// Cuts a decoded map into the windows of its tile plan: for each tile its context (the whole
/// map's range and radius), its index and its `HBH1` heights blob (values already filled).
///
/// # Errors
/// [`Error::Param`] for heights beyond f32 (`height_scale`), `radius=unlimited`, and the plan's
/// refusals ([`TilePlan::new`]).
pub fn split_map(
    map: &HeightMap,
    params: &BakeParams,
    tile_size: u32,
) -> Result<Vec<(TileContext, u32, Vec<u8>)>> {
    let (w, h) = (map.width as u32, map.height as u32);
    let hs = params.height_scale;
    let (lo, hi) = map.values.iter().fold((f32::INFINITY, f32::NEG_INFINITY), |(l, u), &v| {
        let s = (v as f64 * hs) as f32;
        (l.min(s), u.max(s))
    });
    bake::check_scaled(&[lo, hi])?;
    if params.radius == Radius::Unlimited && params.max_distance.is_none() {
        return Err(Error::param("radius", "radius=unlimited needs the whole map: not tiled"));
    }
    let radius = bake::resolve_radius_in(params, map.width, map.height, || (lo, hi));
    let plan = TilePlan::new(w, h, tile_size, tiles::halo_for(radius.texels), params.edge)?;
    let ctx = TileContext {
        plan,
        range: (lo, hi),
        radius: radius.texels,
        radius_reason: radius.reason,
        input: None,
        split_ms: 0.0,
        stats: serde_json::Value::Null,
    };
    let holes = map.terrain.holes.as_deref();
    Ok(plan
        .tiles()
        .map(|g| {
            let n = g.window_w as usize * g.window_h as usize;
            let mut values = Vec::with_capacity(n);
            let mut hole = holes.map(|_| Vec::with_capacity(n));
            for r in 0..g.window_h {
                let y = g.map_row(r, h) as usize;
                for c in 0..g.window_w {
                    let k = y * map.width + g.map_col(c, w) as usize;
                    values.push(map.values[k]);
                    if let (Some(dst), Some(src)) = (hole.as_mut(), holes) {
                        dst.push(src[k]);
                    }
                }
            }
            let blob = TileHeights { window: window_of(&g), values, holes: hole }.encode();
            (ctx.clone(), g.index, blob)
        })
        .collect())
}

/// A window whose heights were stored already filled (the in-memory split of a decoded map).
fn raw_window(t: TileHeights) -> HeightMap {
    HeightMap {
        width: t.window.width as usize,
        height: t.window.height as usize,
        values: t.values,
        terrain: heightmap::Terrain { georef: None, nodata: None, holes: t.holes },
    }
}

/// Bakes a tile's window and writes its interior as a `HBR1` tile result
/// ([`assemble::write_tile_result`]: one section, the horizon layers at the precision `formats`
/// asks for).
///
/// # Errors
/// [`Error::Canceled`], the writer's errors.
pub fn bake_tile_into<W: Write>(
    window: HeightMap,
    params: &BakeParams,
    formats: &Formats,
    ctx: &TileContext,
    index: u32,
    progress: &Progress,
    out: &mut W,
) -> Result<()> {
    let g = ctx.plan.tile(index);
    if (window.width, window.height) != (g.window_w as usize, g.window_h as usize) {
        return Err(Error::Internal(format!("tile {index}'s heights do not fit its window")));
    }
    let (ox, oy) = g.interior_offset();
    let interior = (ox as usize, oy as usize, g.interior.w as usize, g.interior.h as usize);
    // The terrain products first (as the untiled bake does): the horizon bake consumes the window.
    let (range, radius) = (ctx.range, ctx.radius);
    // Where the window lies in the map its georeferencing describes (compass bands, SPEC §3.7).
    let origin = Some(bake::WindowPlace {
        origin: (g.window_x as usize, g.window_y as usize),
        map: (ctx.plan.width as usize, ctx.plan.height as usize),
    });
    let mut window = Some(window);
    let terrain = if params.outputs.terrain() {
        let w = if params.outputs.horizon { window.clone() } else { window.take() };
        let w = w.ok_or_else(|| Error::Internal("no window".into()))?;
        Some(bake::bake_terrain_window(w, params, interior, origin, range, radius, progress)?)
    } else {
        None
    };
    let mut precisions = formats.precisions();
    if !(precisions.u8 || precisions.u16 || precisions.f32) {
        precisions.u8 = true;
    }
    let layers = match window {
        Some(w) => bake::bake_window(w, params, interior, range, radius, precisions, progress)?,
        None => crate::layers::HorizonLayers::default(),
    };
    // One section per precision the formats need (PNGs and textures read their own), one per
    // terrain product (GeoTIFFs read theirs).
    let mut sections = Vec::new();
    if let Some(t) = &terrain {
        let plane = t.width * t.height;
        if let Some(a) = &t.angles {
            let planes = a.chunks_exact(plane).map(Plane::F32).collect();
            sections.push(Section { tag: assemble::tag::ANGLES, channels: 1, planes });
        }
        if let Some(v) = &t.svf {
            let planes = vec![Plane::F32(v)];
            sections.push(Section { tag: assemble::tag::SVF, channels: 1, planes });
        }
        if let Some(d) = &t.distance {
            let planes = d.chunks_exact(plane).map(Plane::F32).collect();
            sections.push(Section { tag: assemble::tag::DISTANCE, channels: 1, planes });
        }
        let singles = [
            (t.openness.as_ref().map(|o| &o[0]), assemble::tag::OPENNESS_POSITIVE),
            (t.openness.as_ref().map(|o| &o[1]), assemble::tag::OPENNESS_NEGATIVE),
            (t.sun_hours.as_ref(), assemble::tag::SUN_HOURS),
            (t.insolation.as_ref(), assemble::tag::INSOLATION),
        ];
        for (v, tag) in singles {
            if let Some(v) = v {
                sections.push(Section { tag, channels: 1, planes: vec![Plane::F32(v)] });
            }
        }
    }
    if let Some([l0, l1]) = &layers.u8 {
        let planes = vec![Plane::U8(l0), Plane::U8(l1)];
        sections.push(Section { tag: assemble::tag::HORIZON_U8, channels: 4, planes });
    }
    if let Some([l0, l1]) = &layers.u16 {
        let planes = vec![Plane::U16(l0), Plane::U16(l1)];
        sections.push(Section { tag: assemble::tag::HORIZON_U16, channels: 4, planes });
    }
    if let Some([l0, l1]) = &layers.f32 {
        let planes = vec![Plane::F32(l0), Plane::F32(l1)];
        sections.push(Section { tag: assemble::tag::HORIZON_F32, channels: 4, planes });
    }
    if sections.is_empty() {
        return Err(Error::Internal("a tile baked no layer".into()));
    }
    assemble::write_tile_result(out, g.interior.w, g.interior.h, &sections)?;
    Ok(())
}

/// A horizon sample of the assembled PNGs, with the tile result section that holds it.
trait Layered: bake::Sample + png::PngSample + assemble::LeSample {
    const TAG: u32;
}

impl Layered for u8 {
    const TAG: u32 = assemble::tag::HORIZON_U8;
}

impl Layered for u16 {
    const TAG: u32 = assemble::tag::HORIZON_U16;
}

/// Where each tile's interior lies in the map, and its result blob.
fn pieces_of(pieces: &[(tiles::TileGeom, String)]) -> Vec<TilePiece> {
    pieces
        .iter()
        .map(|(g, hash)| TilePiece {
            x0: g.interior.x,
            y0: g.interior.y,
            width: g.interior.w,
            height: g.interior.h,
            hash: hash.clone(),
        })
        .collect()
}

/// Streams the two PNG layers of a tiled bake into `outs`, band by band in row order, each band
/// read by range from the tiles it crosses ([`TileRows`], one per layer over readers made by
/// `read`): the two layers are encoded side by side, as the untiled bake does (each writer
/// deflates a batch of pieces on several threads too), and memory is one band and one batch
/// per layer, whatever the map size.
///
/// # Errors
/// [`Error::Canceled`], the reads', the encoder's and the writers' errors.
fn assemble_pngs<T: Layered, W: Write + Send>(
    plan: &TilePlan,
    pieces: &[(tiles::TileGeom, String)],
    read: &(dyn Fn() -> assemble::ReadRange + Sync),
    progress: &Progress,
    outs: [W; 2],
) -> Result<[W; 2]> {
    let (w, h) = (plan.width as usize, plan.height as usize);
    let pieces = pieces_of(pieces);
    let rows = [TileRows::new(read(), pieces.clone(), w, h)?, TileRows::new(read(), pieces, w, h)?];
    progress.start(Stage::Encode, 2 * h as u64);
    let layer = |plane: usize, mut rows: TileRows, out: W| -> Result<W> {
        let mut source = |p: usize, y0: usize, buf: &mut [T]| -> Result<()> {
            if progress.is_canceled() {
                return Err(Error::Canceled);
            }
            rows.read(T::TAG, p, y0, buf)?;
            progress.advance((buf.len() / (w * 4)) as u64);
            Ok(())
        };
        assemble::write_png::<T, W>(out, w, h, png::PngColor::Rgba, plane, &mut source)
    };
    let [r0, r1] = rows;
    let [o0, o1] = outs;
    let (a, b) = rayon::join(|| layer(0, r0, o0), || layer(1, r1, o1));
    Ok([a?, b?])
}

/// A tiled bake of `map` done in memory, step by step as the service does it across workers:
/// split, every tile, assembly. The two PNG layers (8- or 16-bit as `formats` says). For tests
/// that hold it against the untiled bake.
///
/// # Errors
/// Whatever a step fails with.
pub fn bake_tiled_in_memory(
    map: &HeightMap,
    params: &BakeParams,
    formats: &Formats,
    tile_size: u32,
) -> Result<[Vec<u8>; 2]> {
    let progress = Progress::new();
    let pieces = split_map(map, params, tile_size)?;
    let plan = pieces.first().map(|p| p.0.plan).ok_or_else(|| Error::Internal("no tile".into()))?;
    let mut results: BTreeMap<String, Vec<u8>> = BTreeMap::new();
    let mut geoms = Vec::new();
    for (ctx, index, blob) in &pieces {
        let window = raw_window(TileHeights::decode(blob)?);
        let mut out = Vec::new();
        bake_tile_into(window, params, formats, ctx, *index, &progress, &mut out)?;
        let key = format!("tile{index}");
        results.insert(key.clone(), out);
        geoms.push((plan.tile(*index), key));
    }
    let results = Arc::new(results);
    let read = || -> assemble::ReadRange {
        let results = results.clone();
        Arc::new(move |k: &str, start, len| {
            let b = results.get(k).ok_or_else(|| Error::Internal(k.to_owned()))?;
            let s = start as usize;
            Ok(b.get(s..s + len).ok_or_else(|| Error::Internal(k.to_owned()))?.to_vec())
        })
    };
    let outs = [Vec::new(), Vec::new()];
    if formats.png16 {
        assemble_pngs::<u16, _>(&plan, &geoms, &read, &progress, outs)
    } else {
        assemble_pngs::<u8, _>(&plan, &geoms, &read, &progress, outs)
    }
}
