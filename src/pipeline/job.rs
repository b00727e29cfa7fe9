//! A stored bake record run through the pipeline: the [`Runner`] the jobs core runs on the bake
//! pool for each claimed bake (decode → bake → encode → store), the results encoded on their
//! first request, and what a record's fields mean to the pipeline (parameters, formats, result
//! names).
//!
//! The jobs core owns the lifecycle (claims, heartbeats, cancel, completion, `catch_unwind`);
//! this module only turns a record into results. Cancellation goes through
//! [`Progress::cancel`], which the kernel polls between bands.

use crate::bake;
use crate::encode::exr::ExrPrecision;
use crate::encode::{Formats, TextureLayout, TextureOptions, TexturePrecision};
use crate::error::{Error, Result};
use crate::heightmap;
use crate::heightmap::budget::{Admit, MemoryBudget, Reservation};
use crate::heightmap::Limits;
use crate::jobs::blob::BlobStore;
use crate::jobs::record::{now_ms, BakeRecord, RadiusInfo, Status, Timings};
use crate::jobs::Jobs;
use crate::jobs::{Blobs, Runner};
use crate::params::BakeParams;
use crate::pipeline::ms;
use crate::progress::{Progress, Stage};
use std::sync::Arc;
use std::time::Instant;

pub use crate::jobs::blocking;

/// Names of the horizon results (each an immutable, content-addressed blob). A bake stores only
/// `horizon_0.png8` and `horizon_1.png8` (plus `fourier_*.png` with `outputs=fourier`), streamed
/// band by band into the PNG encoder as the CLI's `bake --format png8` does, so a bake costs what
/// the CLI's does and holds no whole layer in memory. Every other format is encoded on its first
/// request ([`encode_on_request`]) and kept: pay only for what is asked. All of them come from the
/// CLI's own functions, so each download is byte-identical to `horizon-bake bake --format …`
/// (png8 / png16 alone; KTX2/DDS at the CLI's default `unorm8`).
pub const HORIZON_RESULTS: [&str; 10] = [
    "horizon_0.png8",
    "horizon_1.png8",
    "horizon_0.png16",
    "horizon_1.png16",
    "horizon_0.exr",
    "horizon_1.exr",
    "horizon_0.half.exr",
    "horizon_1.half.exr",
    "horizon.ktx2",
    "horizon.dds",
];

/// The results one on-request encode produces together (both layers of a layered format; every
/// file of a `texture_layout=separate` texture variant).
pub fn result_group(name: &str) -> Option<Vec<String>> {
    let fixed: &[&str] = match name {
        "horizon_0.png8" | "horizon_1.png8" => &HORIZON_RESULTS[0..2],
        "horizon_0.png16" | "horizon_1.png16" => &HORIZON_RESULTS[2..4],
        // Every precision of a format from one re-bake: the f32 layers give both EXRs.
        "horizon_0.exr" | "horizon_1.exr" | "horizon_0.half.exr" | "horizon_1.half.exr" => {
            &HORIZON_RESULTS[4..8]
        }
        "horizon.ktx2" => &HORIZON_RESULTS[8..9],
        "horizon.dds" => &HORIZON_RESULTS[9..10],
        _ => {
            let (ext, opts) = texture_variant(name)?;
            return Some(texture_group(ext, &opts));
        }
    };
    Some(fixed.iter().map(|n| (*n).to_owned()).collect())
}

/// The result name of a texture variant (SPEC §8 options other than the defaults): the file
/// name, then `?` and the options in canonical order, e.g.
/// `horizon.ktx2?texture_precision=bc7&mips=full`; the defaults are `horizon.ktx2` itself.
/// `layer` picks a file of the `separate` layout (`horizon_1.ktx2?texture_layout=separate`).
pub fn texture_result_name(ext: &str, opts: &TextureOptions, layer: Option<usize>) -> String {
    let file = match layer {
        Some(i) => format!("horizon_{i}.{ext}"),
        None => format!("horizon.{ext}"),
    };
    let pairs: Vec<String> = opts.pairs().into_iter().map(|(k, v)| format!("{k}={v}")).collect();
    if pairs.is_empty() {
        file
    } else {
        format!("{file}?{}", pairs.join("&"))
    }
}

/// Every result name one encode of the texture variant `opts` produces.
fn texture_group(ext: &str, opts: &TextureOptions) -> Vec<String> {
    if opts.layout == TextureLayout::Separate {
        let n = if opts.precision == TexturePrecision::Bc5 { 4 } else { 2 };
        (0..n).map(|i| texture_result_name(ext, opts, Some(i))).collect()
    } else {
        vec![texture_result_name(ext, opts, None)]
    }
}

/// The extension (`ktx2` or `dds`) and options of a texture variant's result name.
fn texture_variant(name: &str) -> Option<(&'static str, TextureOptions)> {
    let (file, query) = name.split_once('?').unwrap_or((name, ""));
    let ext = if file.ends_with(".ktx2") {
        "ktx2"
    } else if file.ends_with(".dds") {
        "dds"
    } else {
        return None;
    };
    let pairs =
        query.split('&').filter(|p| !p.is_empty()).map(|p| p.split_once('=').unwrap_or((p, "")));
    let opts = TextureOptions::from_pairs(pairs).ok()?;
    (texture_result_name(ext, &opts, None) == name
        || texture_group(ext, &opts).iter().any(|n| n == name))
    .then_some((ext, opts))
}

/// Encodes the result group of `name` for the succeeded bake `rec` (on the calling thread: the
/// preview pool, started in the background by the first download that asks for it), stores it
/// and records it in the bake's record. EXR float and half come from one re-bake. Returns the blob hash of
/// `name`, or None when the bake was removed meanwhile.
///
/// The input is decoded and baked again (bakes are deterministic, and re-baking costs about what
/// keeping every precision of the layers would cost in memory and disk for every bake, asked
/// or not); only the precision the format needs is produced.
///
/// # Errors
/// Decode, bake, encode and store failures.
pub fn encode_on_request(
    jobs: &Jobs,
    limits: &Limits,
    admit: Option<Admit<'_>>,
    rec: &BakeRecord,
    name: &str,
    progress: &Progress,
    on_stored: &dyn Fn(),
) -> Result<Option<String>> {
    let group = result_group(name)
        .ok_or_else(|| Error::Internal(format!("`{name}` is not an on-request result")))?;
    let params = params_of(rec)?;
    let (map, _, _held) = decode_input(jobs.blob_store().as_ref(), rec, &params, limits, admit)?;
    let files: Vec<Vec<u8>> = match group[0].as_str() {
        "horizon_0.png8" => {
            let (pngs, _) = crate::pipeline::stream_horizon_pngs::<u8, _>(
                map,
                &params,
                progress,
                [Vec::new(), Vec::new()],
            )?;
            pngs.into()
        }
        "horizon_0.png16" => {
            let (pngs, _) = crate::pipeline::stream_horizon_pngs::<u16, _>(
                map,
                &params,
                progress,
                [Vec::new(), Vec::new()],
            )?;
            pngs.into()
        }
        "horizon_0.exr" => {
            // One f32 bake, both precisions: float then half, layer 0 then 1 (the group's order).
            let exr = |exr_precision| Formats {
                png8: false,
                png16: false,
                exr: true,
                ktx2: false,
                dds: false,
                texture: Default::default(),
                exr_precision,
                conventions: Default::default(),
            };
            let float = exr(ExrPrecision::Float);
            let (layers, _) = bake::bake_horizon(&map, &params, float.precisions(), progress)?;
            drop(map);
            let mut files = Vec::with_capacity(4);
            for f in [float, exr(ExrPrecision::Half)] {
                files.extend(
                    crate::pipeline::encode_each(&layers, None, &f, progress)?
                        .into_iter()
                        .map(|f| f.bytes),
                );
            }
            files
        }
        first => {
            let texture = texture_variant(first);
            let formats = Formats {
                png8: false,
                png16: false,
                exr: false,
                ktx2: texture.is_some_and(|(e, _)| e == "ktx2"),
                dds: texture.is_some_and(|(e, _)| e == "dds"),
                texture: texture.map(|(_, o)| o).unwrap_or_default(),
                exr_precision: ExrPrecision::Float,
                conventions: crate::pipeline::conventions(&params),
            };
            let (layers, _) = bake::bake_horizon(&map, &params, formats.precisions(), progress)?;
            // `mip_filter=rebake` bakes the levels again from the map.
            crate::pipeline::encode_each(&layers, Some((&map, &params)), &formats, progress)?
                .into_iter()
                .map(|f| f.bytes)
                .collect()
        }
    };
    if files.len() != group.len() {
        return Err(Error::Internal(format!("{} files encoded for {group:?}", files.len())));
    }
    // Each blob is pinned for this encode until the record references it, so a concurrent
    // removal of an identical result elsewhere cannot take it away in between.
    let owner = format!("encode/{}/{}/{}", rec.id, group[0], now_ms());
    let blobs = jobs.blobs_for(owner.clone());
    let mut stored = Vec::with_capacity(group.len());
    for (n, bytes) in group.iter().zip(&files) {
        stored.push((n.clone(), blobs.put(bytes)?));
        on_stored();
    }
    let added = jobs.block_on(jobs.add_results(&rec.id, &stored, &owner))?;
    if !added {
        return Ok(None);
    }
    Ok(stored.into_iter().find(|(n, _)| n == name).map(|(_, h)| h))
}

/// The record's spelling of the formats a submission asked to encode with the bake: the CLI's
/// `--format` list in its canonical order, plus `half` for half-float EXR, then the texture
/// options that differ from the defaults as a query (`ktx2,dds?texture_precision=bc7&mips=full`,
/// [`TextureOptions::pairs`]).
pub fn formats_field(f: &Formats) -> String {
    let mut parts: Vec<&str> = [
        (f.png8, "png8"),
        (f.png16, "png16"),
        (f.exr, "exr"),
        (f.exr && f.exr_precision == ExrPrecision::Half, "half"),
        (f.ktx2, "ktx2"),
        (f.dds, "dds"),
    ]
    .into_iter()
    .filter_map(|(on, name)| on.then_some(name))
    .collect();
    if parts.is_empty() {
        parts.push("png8");
    }
    let list = parts.join(",");
    let pairs = f.texture.pairs();
    if (f.ktx2 || f.dds) && !pairs.is_empty() {
        let q: Vec<String> = pairs.into_iter().map(|(k, v)| format!("{k}={v}")).collect();
        format!("{list}?{}", q.join("&"))
    } else {
        list
    }
}

/// The formats a record's bake encodes (see [`formats_field`]; None is `png8`).
///
/// # Errors
/// [`Error::Internal`] for a value this version does not write.
pub fn formats_of(rec: &BakeRecord) -> Result<Formats> {
    let field = rec.formats.as_deref().unwrap_or("png8");
    let (list, query) = field.split_once('?').unwrap_or((field, ""));
    let half = list.split(',').any(|p| p == "half");
    let names: Vec<&str> = list.split(',').filter(|p| *p != "half").collect();
    let stored = |e: Error| Error::Internal(format!("stored formats `{field}`: {e}"));
    let mut f = Formats::parse(&names.join(","), TexturePrecision::Unorm8).map_err(stored)?;
    if half {
        f.exr_precision = ExrPrecision::Half;
    }
    let pairs =
        query.split('&').filter(|p| !p.is_empty()).map(|p| p.split_once('=').unwrap_or((p, "")));
    f.texture = TextureOptions::from_pairs(pairs).map_err(stored)?;
    Ok(f)
}

/// The parameters stored in a record.
///
/// # Errors
/// [`Error::Param`] if the stored pairs no longer parse (a record from an incompatible version).
pub fn params_of(rec: &BakeRecord) -> Result<BakeParams> {
    BakeParams::from_pairs(rec.params.iter().map(|(k, v)| (k.as_str(), v.as_str())))
}

/// The runner the jobs core calls for each claimed bake, with the service's input limits and
/// its decode budget (a bake waits for its share as long as it takes: it was accepted, and
/// the decodes ahead of it finish).
pub fn runner(limits: Limits, budget: Arc<MemoryBudget>) -> Runner {
    Arc::new(move |rec: &BakeRecord, progress: &Progress, blobs: &Blobs| {
        let admit = Admit { budget: &budget, wait: None };
        execute(&limits, Some(admit), rec.clone(), progress, blobs)
    })
}

/// The worker's [`crate::pipeline::Sink`]: each file becomes a blob, pinned for the claim until
/// its record references it, under its result name (`horizon_0.png` is `horizon_0.png8`).
struct BlobSink<'a> {
    blobs: &'a Blobs,
    results: Vec<(String, String)>,
    /// The formats being produced, which say what the CLI's file names stand for here.
    formats: Formats,
}

impl BlobSink<'_> {
    /// The result name of the CLI's file `file`: `horizon_0.png` is png8 or png16 as asked, an
    /// EXR is `.half.exr` at half precision, a KTX2/DDS file the name of its variant
    /// ([`texture_result_name`], the name its download looks up).
    fn result_name(&self, file: &str) -> String {
        result_name(&self.formats, file)
    }
}

/// The result name of the CLI's file `file` when `formats` are produced: `horizon_0.png` is
/// png8 or png16 as asked, an EXR is `.half.exr` at half precision, a KTX2/DDS file the name of
/// its variant ([`texture_result_name`], the name its download looks up).
pub fn result_name(formats: &Formats, file: &str) -> String {
    // The horizon textures' names carry their variant; the surface maps' (`normal.ktx2`, …)
    // are stored as they are: they have no variants encoded on request.
    let horizon = file.starts_with("horizon");
    if let Some((stem, ext)) =
        file.rsplit_once('.').filter(|(_, e)| horizon && (*e == "ktx2" || *e == "dds"))
    {
        let layer = stem.strip_prefix("horizon_").and_then(|i| i.parse::<usize>().ok());
        let ext = if ext == "ktx2" { "ktx2" } else { "dds" };
        let opts = formats.texture.for_container(ext == "ktx2");
        return texture_result_name(ext, &opts, layer);
    }
    // A 16-bit surface map is `{map}.png16` (the CLI's `normal.png` in either depth), so that
    // its download answers for the depth it has.
    if formats.png16 {
        if let Some(stem) = ["normal.png", "ao.png", "bent_normal.png"]
            .iter()
            .find(|n| **n == file)
            .and_then(|n| n.strip_suffix(".png"))
        {
            return format!("{stem}.png16");
        }
    }
    let half = formats.exr_precision == ExrPrecision::Half;
    let pick = match file {
        "horizon_0.png" if formats.png16 => 2,
        "horizon_1.png" if formats.png16 => 3,
        "horizon_0.png" => 0,
        "horizon_1.png" => 1,
        "horizon_0.exr" if half => 6,
        "horizon_1.exr" if half => 7,
        other => return other.to_owned(),
    };
    HORIZON_RESULTS[pick].to_owned()
}

impl crate::pipeline::Sink for BlobSink<'_> {
    type Writer = crate::jobs::PinnedWriter;

    fn writer(&mut self, _name: &'static str) -> Result<Self::Writer> {
        self.blobs.writer()
    }

    fn finish(&mut self, files: [(&'static str, Self::Writer); 2]) -> Result<()> {
        // Both files are written already: commit them side by side (an fsync and a rename
        // each, or the last part of an upload).
        let [(n0, w0), (n1, w1)] = files;
        let (h0, h1) = rayon::join(|| w0.commit(), || w1.commit());
        let (r0, r1) = (self.result_name(n0), self.result_name(n1));
        self.results.push((r0, h0?));
        self.results.push((r1, h1?));
        Ok(())
    }

    fn finish_one(&mut self, name: &'static str, file: Self::Writer) -> Result<()> {
        let hash = file.commit()?;
        let name = self.result_name(name);
        self.results.push((name, hash));
        Ok(())
    }

    fn put(&mut self, file: crate::encode::OutFile) -> Result<()> {
        let hash = self.blobs.put(&file.bytes)?;
        let name = self.result_name(file.name);
        self.results.push((name, hash));
        Ok(())
    }
}

/// The bake's stored input, decoded with its `channel` (unscaled heights): what a bake, an
/// on-request encode, a preview and the heights route all start from. The encoded bytes are
/// dropped before the caller allocates anything else. The decode's memory is reserved from
/// `admit`'s budget; keep the returned reservation as long as the map.
///
/// # Errors
/// A missing input blob ([`Error::Internal`]), store and decode failures.
pub fn decode_input(
    blobs: &dyn BlobStore,
    rec: &BakeRecord,
    params: &BakeParams,
    limits: &Limits,
    admit: Option<Admit<'_>>,
) -> Result<(heightmap::HeightMap, heightmap::InputInfo, Reservation)> {
    if rec.tiles.is_some() {
        // Its map is above --tile-above: no process decodes it whole (SPEC §7.1).
        return Err(Error::InvalidInput(
            "this bake was baked in tiles (its map is above --tile-above): only the layers it \
             was submitted with exist, and its map is never decoded whole again; submit it \
             again with the formats you need (png8 or png16)"
                .into(),
        ));
    }
    let bytes = blobs
        .get(&rec.input_blob)?
        .ok_or_else(|| Error::Internal(format!("input blob {} is missing", rec.input_blob)))?;
    let mut params = params.clone();
    let (map, info, held) = heightmap::decode_for_in(&bytes, &mut params, limits, admit)?;
    bake::check_method_fits(&params, map.width as u32, map.height as u32)?;
    Ok((map, info, held))
}

/// One bake, on the bake pool: decode → bake → encode → store, then the record is committed as
/// `succeeded`. Returns the stored record.
fn execute(
    limits: &Limits,
    admit: Option<Admit<'_>>,
    mut rec: BakeRecord,
    progress: &Progress,
    blobs: &Blobs,
) -> Result<BakeRecord> {
    let t_total = Instant::now();
    let mut params = params_of(&rec)?;

    progress.start(Stage::Decode, 1);
    let t = Instant::now();
    let bytes = blobs
        .get(&rec.input_blob)?
        .ok_or_else(|| Error::Internal(format!("input blob {} is missing", rec.input_blob)))?;
    // Held until the bake is done with the heights (the end of this function).
    let (map, info, _held) = heightmap::decode_for_in(&bytes, &mut params, limits, admit)?;
    bake::check_method_fits(&params, map.width as u32, map.height as u32)?;
    drop(bytes);
    progress.advance(1);
    let decode_ms = ms(t);

    // The CLI's own pipeline with the formats the submission asked for (the CLI's default,
    // png8, unless told): a bake costs what `horizon-bake bake --format …` costs, and every
    // other format waits for its first request. With png8 or png16 alone the kernel and the PNG
    // encoders overlap band by band and the PNGs stream into blob writers, so no whole layer
    // and no whole encoded image exists; EXR, KTX2 and DDS need whole layers, as in the CLI.
    let formats = formats_of(&rec)?;
    let mut sink = BlobSink { blobs, results: Vec::new(), formats };
    let produced = crate::pipeline::produce(map, &params, &formats, progress, &mut sink)?;
    progress.start(Stage::Store, 1);
    for (name, hash) in sink.results {
        rec.results.insert(name, hash);
    }
    let radius = produced.radius;
    let (bake_ms, encode_ms, store_ms) = (produced.bake_ms, produced.encode_ms, produced.store_ms);
    rec.status = Status::Succeeded;
    rec.input = Some(info);
    rec.radius = Some(RadiusInfo { texels: radius.texels, reason: radius.reason });
    rec.finished_ms = Some(now_ms());
    rec.error = None;
    let queued = rec.started_ms.unwrap_or(rec.created_ms).saturating_sub(rec.created_ms) as f64;
    rec.timings_ms = Some(Timings {
        queued,
        decode: decode_ms,
        bake: bake_ms,
        encode: encode_ms,
        store: store_ms,
        total: ms(t_total),
    });
    progress.start(Stage::Done, 1);
    progress.advance(1);
    Ok(rec)
}
