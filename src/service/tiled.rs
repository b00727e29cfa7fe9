//! What a tiled bake computes for the service (SPEC §7.1): the [`Tiler`] the jobs core runs for
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
//! The blob layouts are tilestream's (TILES.md): `HBH1` tile heights and `HBR1` tile results.
//! Until its streaming decoder lands, the split decodes the input whole (a stand-in behind the
//! same layout).

use crate::bake;
use crate::encode::{png, Formats};
use crate::error::{Error, Result};
use crate::heightmap::{self, HeightMap, Limits};
use crate::jobs::store::{now_ms, BakeRecord, BlobStore, RadiusInfo, Status, Timings};
use crate::jobs::tiles::{self, TileContext, TilePlan, TileRecord};
use crate::jobs::{Blobs, Tiler};
use crate::params::{BakeParams, Radius};
use crate::pipeline::ms;
use crate::progress::{Progress, Stage};
use crate::service::worker::{formats_of, params_of, HORIZON_RESULTS};
use std::collections::BTreeMap;
use std::io::{Read, Write};
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
    let by_distance = params.max_distance.is_some() && params.cell_size.is_some();
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
    if params.outputs.fourier || params.outputs.terrain() {
        return Err(Error::param(
            "outputs",
            "a tiled bake (map above --tile-above) produces the horizon layers only; ask for \
             outputs=horizon",
        ));
    }
    if formats.exr || formats.ktx2 || formats.dds {
        return Err(Error::param(
            "formats",
            "a tiled bake (map above --tile-above) is assembled as png8 or png16 layers",
        ));
    }
    if params.radius != Radius::Auto || by_distance {
        let r = bake::resolve_radius_in(params, width as usize, height as usize, || (0.0, 0.0));
        TilePlan::new(width, height, s.tile_size, tiles::halo_for(r.texels), params.edge)?;
    }
    Ok(())
}

/// The service's [`Tiler`].
pub struct ServiceTiler {
    pub limits: Limits,
    pub settings: TileSettings,
    pub store: Arc<dyn BlobStore>,
}

impl Tiler for ServiceTiler {
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
        let mut params = params_of(rec)?;
        progress.start(Stage::Decode, 1);
        let bytes = blobs
            .get(&rec.input_blob)?
            .ok_or_else(|| Error::Internal(format!("input blob {} is missing", rec.input_blob)))?;
        let (map, info) = heightmap::decode_for(&bytes, &mut params, &self.limits)?;
        drop(bytes);
        let pieces = split_map(&map, &params, self.settings.tile_size)?;
        drop(map);
        let split_ms = ms(t);
        let mut out = Vec::with_capacity(pieces.len());
        for (mut ctx, index, blob) in pieces {
            if progress.is_canceled() {
                return Err(Error::Canceled);
            }
            ctx.input = Some(info.clone());
            ctx.split_ms = split_ms;
            let hash = blobs.put(&blob)?;
            out.push(TileRecord::new(&rec.id, index, hash, ctx));
        }
        progress.advance(1);
        Ok(out)
    }

    fn bake_tile(
        &self,
        rec: &BakeRecord,
        tile: &TileRecord,
        progress: &Progress,
        blobs: &Blobs,
    ) -> Result<BTreeMap<String, String>> {
        let params = params_of(rec)?;
        let formats = formats_of(rec)?;
        let bytes = blobs
            .get(&tile.input_blob)?
            .ok_or_else(|| Error::Internal(format!("tile blob {} is missing", tile.input_blob)))?;
        let window = decode_heights(&bytes)?;
        drop(bytes);
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
                let h =
                    t.results.get("tile").cloned().ok_or_else(|| {
                        Error::Internal(format!("tile {} has no result", t.index))
                    })?;
                Ok((t.geom(), h))
            })
            .collect::<Result<_>>()?;
        let outs = [blobs.writer()?, blobs.writer()?];
        let read = |hash: &str, start: u64, buf: &mut [u8]| -> Result<()> {
            let mut r = self
                .store
                .open_range(hash, start, start + buf.len() as u64)?
                .ok_or_else(|| Error::Internal(format!("tile result {hash} is missing")))?;
            r.read_exact(buf)?;
            Ok(())
        };
        let [a, b] = if formats.png16 {
            assemble_pngs::<u16, _>(&ctx.plan, &pieces, read, progress, outs)?
        } else {
            assemble_pngs::<u8, _>(&ctx.plan, &pieces, read, progress, outs)?
        };
        let (h0, h1) = (a.commit()?, b.commit()?);
        let (n0, n1) = if formats.png16 {
            (HORIZON_RESULTS[2], HORIZON_RESULTS[3])
        } else {
            (HORIZON_RESULTS[0], HORIZON_RESULTS[1])
        };
        let mut done = rec.clone();
        done.results.insert(n0.to_owned(), h0);
        done.results.insert(n1.to_owned(), h1);
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

/// Cuts a decoded map into the windows of its tile plan: for each tile its context (the whole
/// map's range and radius), its index and its `HBH1` heights blob.
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
    let radius = bake::resolve_radius_in(params, map.width, map.height, || (lo, hi));
    if params.radius == Radius::Unlimited && params.max_distance.is_none() {
        return Err(Error::param("radius", "radius=unlimited needs the whole map: not tiled"));
    }
    let plan = TilePlan::new(w, h, tile_size, tiles::halo_for(radius.texels), params.edge)?;
    let ctx = TileContext {
        plan,
        range: (lo, hi),
        radius: radius.texels,
        radius_reason: radius.reason,
        input: None,
        split_ms: 0.0,
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
            let blob = encode_heights(&g, &values, hole.as_deref());
            (ctx.clone(), g.index, blob)
        })
        .collect())
}

/// The `HBH1` blob of a window (TILES.md §1): magic, width, height, x0, y0, flags, f32 values,
/// then hole bits (LSB first) when there are holes.
fn encode_heights(g: &tiles::TileGeom, values: &[f32], holes: Option<&[bool]>) -> Vec<u8> {
    let mut out = Vec::with_capacity(32 + values.len() * 4);
    out.extend_from_slice(b"HBH1");
    out.extend_from_slice(&g.window_w.to_le_bytes());
    out.extend_from_slice(&g.window_h.to_le_bytes());
    out.extend_from_slice(&g.window_x.to_le_bytes());
    out.extend_from_slice(&g.window_y.to_le_bytes());
    out.extend_from_slice(&(holes.is_some() as u32).to_le_bytes());
    for v in values {
        out.extend_from_slice(&v.to_le_bytes());
    }
    if let Some(holes) = holes {
        let mut bits = vec![0u8; holes.len().div_ceil(8)];
        for (k, _) in holes.iter().enumerate().filter(|(_, &h)| h) {
            bits[k / 8] |= 1 << (k % 8);
        }
        out.extend_from_slice(&bits);
    }
    out
}

/// The window a `HBH1` blob holds, as a height map (holes kept; their fill is in the values).
fn decode_heights(bytes: &[u8]) -> Result<HeightMap> {
    let bad = || Error::Internal("a tile heights blob is corrupt".into());
    if bytes.len() < 32 || &bytes[..4] != b"HBH1" {
        return Err(bad());
    }
    let u32_at = |o: usize| u32::from_le_bytes(bytes[o..o + 4].try_into().unwrap_or([0; 4]));
    let (w, h, flags) = (u32_at(4) as usize, u32_at(8) as usize, u32_at(28));
    let n = w * h;
    let body = bytes.get(32..32 + 4 * n).ok_or_else(bad)?;
    let values: Vec<f32> =
        body.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect();
    let holes = if flags & 1 == 1 {
        let bits = bytes.get(32 + 4 * n..32 + 4 * n + n.div_ceil(8)).ok_or_else(bad)?;
        Some((0..n).map(|k| bits[k / 8] & (1 << (k % 8)) != 0).collect())
    } else {
        None
    };
    Ok(HeightMap {
        width: w,
        height: h,
        values,
        terrain: heightmap::Terrain { georef: None, nodata: None, holes },
    })
}

/// A quantised sample as tile results store it (little-endian).
trait LeSample: bake::Sample + png::PngSample {
    const SIZE: usize;
    const TAG: u32;
    fn put(self, out: &mut Vec<u8>);
    fn get(b: &[u8]) -> Self;
}

impl LeSample for u8 {
    const SIZE: usize = 1;
    const TAG: u32 = 1;
    fn put(self, out: &mut Vec<u8>) {
        out.push(self);
    }
    fn get(b: &[u8]) -> Self {
        b[0]
    }
}

impl LeSample for u16 {
    const SIZE: usize = 2;
    const TAG: u32 = 2;
    fn put(self, out: &mut Vec<u8>) {
        out.extend_from_slice(&self.to_le_bytes());
    }
    fn get(b: &[u8]) -> Self {
        u16::from_le_bytes([b[0], b[1]])
    }
}

/// Bytes before a `HBR1` result's data: header (16) + one section descriptor (16).
const RESULT_HEADER: u64 = 32;

/// Bakes a tile's window and writes its interior as a `HBR1` result (TILES.md §2: one section,
/// the horizon layers at the precision `formats` asks for, layer 0 then layer 1, RGBA rows).
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
    let precisions = bake::Precisions { u8: !formats.png16, u16: formats.png16, f32: false };
    let layers =
        bake::bake_window(window, params, interior, ctx.range, ctx.radius, precisions, progress)?;
    fn write<T: LeSample, W: Write>(
        out: &mut W,
        g: &tiles::TileGeom,
        ls: &[Vec<T>; 2],
    ) -> Result<()> {
        let mut head = Vec::with_capacity(RESULT_HEADER as usize);
        head.extend_from_slice(b"HBR1");
        head.extend_from_slice(&g.interior.w.to_le_bytes());
        head.extend_from_slice(&g.interior.h.to_le_bytes());
        head.extend_from_slice(&1u32.to_le_bytes());
        head.extend_from_slice(&[T::SIZE as u8, 0, 0, 0]);
        head.extend_from_slice(&2u32.to_le_bytes());
        head.extend_from_slice(&4u32.to_le_bytes());
        head.extend_from_slice(&T::TAG.to_le_bytes());
        out.write_all(&head)?;
        let mut buf = Vec::with_capacity(ls[0].len() * T::SIZE);
        for l in ls {
            buf.clear();
            for &v in l {
                v.put(&mut buf);
            }
            out.write_all(&buf)?;
        }
        Ok(())
    }
    match (&layers.u8, &layers.u16) {
        (_, Some(l)) if formats.png16 => write(out, &g, l),
        (Some(l), _) => write(out, &g, l),
        _ => Err(Error::Internal("a tile baked no layer".into())),
    }
}

/// Rows per band of the assembly (each band reads one range of each tile of its tile row).
const BAND: u32 = 64;

/// Streams the two PNG layers of a tiled bake into `outs`, band by band in row order, reading
/// each tile's rows of the band by range through `read(hash, offset, buf)`: memory is one band
/// of both layers, whatever the map size.
///
/// # Errors
/// [`Error::Canceled`], `read`'s and the encoder's errors.
fn assemble_pngs<T: LeSample, W: Write + Send + 'static>(
    plan: &TilePlan,
    pieces: &[(tiles::TileGeom, String)],
    read: impl Fn(&str, u64, &mut [u8]) -> Result<()>,
    progress: &Progress,
    outs: [W; 2],
) -> Result<[W; 2]> {
    let (w, h) = (plan.width as usize, plan.height as usize);
    let [o0, o1] = outs;
    let mut writers = [
        png::PngRowWriter::<W, T>::new(o0, w, h, png::PngColor::Rgba)?,
        png::PngRowWriter::<W, T>::new(o1, w, h, png::PngColor::Rgba)?,
    ];
    progress.start(Stage::Encode, h as u64);
    let mut rows: [Vec<T>; 2] = [Vec::new(), Vec::new()];
    let mut raw = Vec::new();
    for tr in 0..plan.rows {
        let row_tiles: Vec<&(tiles::TileGeom, String)> =
            pieces.iter().filter(|(g, _)| g.row == tr).collect();
        let (y_start, th) = match row_tiles.first() {
            Some((g, _)) => (g.interior.y, g.interior.h),
            None => return Err(Error::Internal(format!("tile row {tr} is empty"))),
        };
        let mut y = 0;
        while y < th {
            if progress.is_canceled() {
                return Err(Error::Canceled);
            }
            let n = BAND.min(th - y);
            for (layer, buf) in rows.iter_mut().enumerate() {
                buf.clear();
                buf.resize(n as usize * w * 4, T::default());
                for (g, hash) in &row_tiles {
                    let (tw, tht) = (g.interior.w as usize, g.interior.h as usize);
                    let plane = (tw * tht * 4 * T::SIZE) as u64;
                    let row_bytes = tw * 4 * T::SIZE;
                    let start = RESULT_HEADER + layer as u64 * plane + y as u64 * row_bytes as u64;
                    raw.resize(n as usize * row_bytes, 0);
                    read(hash, start, &mut raw)?;
                    for r in 0..n as usize {
                        let dst = &mut buf[(r * w + g.interior.x as usize) * 4..][..tw * 4];
                        let src = &raw[r * row_bytes..(r + 1) * row_bytes];
                        for (d, s) in dst.iter_mut().zip(src.chunks_exact(T::SIZE)) {
                            *d = T::get(s);
                        }
                    }
                }
            }
            let [w0, w1] = &mut writers;
            let (a, b) = rayon::join(|| w0.write_rows(&rows[0]), || w1.write_rows(&rows[1]));
            a.and(b)?;
            progress.advance(n as u64);
            y += n;
        }
        let _ = y_start;
    }
    let [w0, w1] = writers;
    Ok([w0.finish()?, w1.finish()?])
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
        let window = decode_heights(blob)?;
        let mut out = Vec::new();
        bake_tile_into(window, params, formats, ctx, *index, &progress, &mut out)?;
        let key = format!("tile{index}");
        results.insert(key.clone(), out);
        geoms.push((plan.tile(*index), key));
    }
    let read = |k: &str, start: u64, buf: &mut [u8]| -> Result<()> {
        let b = results.get(k).ok_or_else(|| Error::Internal(k.to_owned()))?;
        let s = start as usize;
        buf.copy_from_slice(b.get(s..s + buf.len()).ok_or_else(|| Error::Internal(k.to_owned()))?);
        Ok(())
    };
    if formats.png16 {
        assemble_pngs::<u16, _>(&plan, &geoms, read, &progress, [Vec::new(), Vec::new()])
    } else {
        assemble_pngs::<u8, _>(&plan, &geoms, read, &progress, [Vec::new(), Vec::new()])
    }
}
