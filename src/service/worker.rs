//! Running bakes: the dispatcher that takes ids off the queue, at most N at once, and the job
//! that runs one bake on the dedicated rayon pool.
//!
//! The async side never computes: it marks the record `running`, hands the bake to the pool with
//! `ThreadPool::spawn`, and awaits the outcome on a oneshot channel. The pool side decodes,
//! bakes, encodes and stores the results, inside `catch_unwind` so a panicking bake becomes a
//! `failed` record instead of an aborted process (rayon's default on a panic in `spawn`).
//! Cancellation goes through [`Progress::cancel`], which the kernel polls between bands.

use crate::bake;
use crate::encode::exr::ExrPrecision;
use crate::encode::{self, Formats, TexturePrecision};
use crate::error::{Error, Result};
use crate::heightmap;
use crate::params::BakeParams;
use crate::progress::{Progress, Stage};
use crate::service::queue::Live;
use crate::service::store::{now_ms, BakeFailure, BakeRecord, RadiusInfo, Status, Timings};
use crate::service::AppState;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::atomic::Ordering;
use std::time::Instant;

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

/// The results one on-request encode produces together (both layers of a layered format).
pub fn result_group(name: &str) -> Option<&'static [&'static str]> {
    Some(match name {
        "horizon_0.png8" | "horizon_1.png8" => &HORIZON_RESULTS[0..2],
        "horizon_0.png16" | "horizon_1.png16" => &HORIZON_RESULTS[2..4],
        "horizon_0.exr" | "horizon_1.exr" => &HORIZON_RESULTS[4..6],
        "horizon_0.half.exr" | "horizon_1.half.exr" => &HORIZON_RESULTS[6..8],
        "horizon.ktx2" => &HORIZON_RESULTS[8..9],
        "horizon.dds" => &HORIZON_RESULTS[9..10],
        _ => return None,
    })
}

/// Encodes the result group of `name` for the succeeded bake `rec` (on the calling thread: the
/// preview pool), stores it and records it in the bake's record. Returns the blob hash of
/// `name`, or None when the bake was removed meanwhile.
///
/// The input is decoded and baked again (bakes are deterministic, and re-baking costs about what
/// keeping every precision of the layers would cost in memory and disk for every bake, asked
/// or not); only the precision the format needs is produced.
///
/// # Errors
/// Decode, bake, encode and store failures.
pub fn encode_on_request(
    st: &AppState,
    rec: &BakeRecord,
    name: &str,
    progress: &Progress,
) -> Result<Option<String>> {
    let group = result_group(name)
        .ok_or_else(|| Error::Internal(format!("`{name}` is not an on-request result")))?;
    let params = params_of(rec)?;
    let (map, _) = decode_input(st, rec, &params)?;
    let files: Vec<Vec<u8>> = match group[0] {
        "horizon_0.png8" => {
            let (pngs, _) = encode::stream_horizon_pngs::<u8, _>(
                map,
                &params,
                progress,
                [Vec::new(), Vec::new()],
            )?;
            pngs.into()
        }
        "horizon_0.png16" => {
            let (pngs, _) = encode::stream_horizon_pngs::<u16, _>(
                map,
                &params,
                progress,
                [Vec::new(), Vec::new()],
            )?;
            pngs.into()
        }
        first => {
            let half = first == "horizon_0.half.exr";
            let formats = Formats {
                png8: false,
                png16: false,
                exr: half || first == "horizon_0.exr",
                ktx2: first == "horizon.ktx2",
                dds: first == "horizon.dds",
                texture_precision: TexturePrecision::Unorm8,
                exr_precision: if half { ExrPrecision::Half } else { ExrPrecision::Float },
            };
            let (layers, _) = bake::bake_horizon(&map, &params, formats.precisions(), progress)?;
            drop(map);
            if progress.is_canceled() {
                return Err(Error::Canceled);
            }
            encode::horizon_files(&layers, &formats)?.into_iter().map(|f| f.bytes).collect()
        }
    };
    if files.len() != group.len() {
        return Err(Error::Internal(format!("{} files encoded for {group:?}", files.len())));
    }
    // Under the sweep lock, so a removal cannot run between the re-read and the write (which
    // would bring a deleted bake back).
    let _gc = st.0.gc_lock.read().unwrap_or_else(|e| e.into_inner());
    let Some(mut current) = st.0.bakes.get(&rec.id)? else {
        return Ok(None);
    };
    for (n, bytes) in group.iter().zip(&files) {
        let hash = st.0.blobs.put(bytes)?;
        current.results.insert((*n).to_owned(), hash);
        st.0.metrics.encoded_on_request();
    }
    st.0.bakes.put(&current)?;
    Ok(current.results.get(name).cloned())
}

/// The parameters stored in a record.
///
/// # Errors
/// [`Error::Param`] if the stored pairs no longer parse (a record from an incompatible version).
pub fn params_of(rec: &BakeRecord) -> Result<BakeParams> {
    BakeParams::from_pairs(rec.params.iter().map(|(k, v)| (k.as_str(), v.as_str())))
}

/// Takes bakes off the queue while slots are free, until `stop` is canceled.
pub async fn dispatch(st: AppState) {
    let slots = st.0.slots.clone();
    loop {
        let permit = tokio::select! {
            p = slots.clone().acquire_owned() => match p { Ok(p) => p, Err(_) => return },
            _ = st.0.stop.cancelled() => return,
        };
        let (id, live) = tokio::select! {
            x = st.0.queue.next() => x,
            _ = st.0.stop.cancelled() => return,
        };
        let job_state = st.clone();
        st.0.tracker.spawn(async move {
            run_job(job_state, id, live).await;
            drop(permit);
        });
    }
}

/// Runs a blocking closure off the async workers.
///
/// # Errors
/// The closure's error, or [`Error::Internal`] if it panicked.
pub async fn blocking<T, F>(f: F) -> Result<T>
where
    T: Send + 'static,
    F: FnOnce() -> Result<T> + Send + 'static,
{
    tokio::task::spawn_blocking(f)
        .await
        .map_err(|e| Error::Internal(format!("blocking task failed: {e}")))?
}

async fn run_job(st: AppState, id: String, live: Live) {
    let store = st.0.bakes.clone();
    let lookup = id.clone();
    let rec = match blocking(move || store.get(&lookup)).await {
        Ok(Some(r)) if !r.status.is_terminal() => r,
        Ok(_) => {
            st.0.queue.finish(&id);
            return;
        }
        Err(e) => {
            tracing::error!(bake = %id, error = %e, "cannot load a queued bake; leaving it queued");
            st.0.queue.finish(&id);
            return;
        }
    };
    let mut running = rec.clone();
    running.status = Status::Running;
    running.started_ms = Some(now_ms());
    running.attempts += 1;
    let store = st.0.bakes.clone();
    let to_store = running.clone();
    if let Err(e) = blocking(move || store.put(&to_store)).await {
        tracing::error!(bake = %id, error = %e, "cannot mark a bake running; leaving it queued");
        st.0.queue.finish(&id);
        return;
    }
    st.notify(&id);

    let started = Instant::now();
    let (tx, rx) = tokio::sync::oneshot::channel();
    let pool_state = st.clone();
    let progress = live.progress.clone();
    let job = running.clone();
    st.0.pool.spawn(move || {
        let out = catch_unwind(AssertUnwindSafe(|| execute(&pool_state, job, &progress)));
        let _ = tx.send(out);
    });
    let outcome = rx.await;
    let seconds = started.elapsed().as_secs_f64();
    let texels = running.width as u64 * running.height as u64;

    let mut rec = running;
    let status = match outcome {
        Ok(Ok(Ok(_stored))) => Status::Succeeded,
        Ok(Ok(Err(Error::Canceled))) if live.requeue.load(Ordering::Relaxed) => Status::Queued,
        Ok(Ok(Err(Error::Canceled))) => Status::Canceled,
        Ok(Ok(Err(e))) => {
            let message = match &e {
                Error::Io(_) | Error::Internal(_) => {
                    tracing::error!(bake = %id, code = e.code(), error = %e, "bake failed");
                    "an internal error occurred; it has been logged".to_owned()
                }
                _ => {
                    // The input's fault, not ours: one line so an operator can still find it.
                    tracing::warn!(bake = %id, code = e.code(), error = %e, "bake failed");
                    e.to_string()
                }
            };
            rec.error = Some(BakeFailure { code: e.code().to_owned(), message });
            Status::Failed
        }
        Ok(Err(_)) | Err(_) => {
            tracing::error!(bake = %id, "bake panicked");
            rec.error = Some(BakeFailure {
                code: "internal".into(),
                message: "an internal error occurred; it has been logged".into(),
            });
            Status::Failed
        }
    };
    if status != Status::Succeeded {
        rec.status = status;
        if status == Status::Queued {
            // Shutdown: leave it for the next start, which re-queues it.
            rec.started_ms = None;
        } else {
            rec.finished_ms = Some(now_ms());
        }
        let store = st.0.bakes.clone();
        let to_store = rec.clone();
        if let Err(e) = blocking(move || store.put(&to_store)).await {
            tracing::error!(bake = %id, error = %e, "cannot record a bake's outcome");
        }
    }
    if status.is_terminal() {
        st.0.metrics.finished(status, seconds, texels);
    }
    st.0.queue.finish(&id);
    st.notify(&id);
}

fn ms(t: Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}

/// The bake's stored input, decoded with its `channel` (unscaled heights): what a bake, an
/// on-request encode, a preview and the heights route all start from. The encoded bytes are
/// dropped before the caller allocates anything else.
///
/// # Errors
/// A missing input blob ([`Error::Internal`]), store and decode failures.
pub fn decode_input(
    st: &AppState,
    rec: &BakeRecord,
    params: &BakeParams,
) -> Result<(heightmap::HeightMap, heightmap::InputInfo)> {
    let bytes =
        st.0.blobs
            .get(&rec.input_blob)?
            .ok_or_else(|| Error::Internal(format!("input blob {} is missing", rec.input_blob)))?;
    heightmap::decode(&bytes, params.channel, &st.0.config.limits)
}

/// One bake, on the bake pool: decode → bake → encode → store, then the record is committed as
/// `succeeded`. Returns the stored record.
fn execute(st: &AppState, mut rec: BakeRecord, progress: &Progress) -> Result<BakeRecord> {
    let t_total = Instant::now();
    let params = params_of(&rec)?;

    progress.start(Stage::Decode, 1);
    let t = Instant::now();
    let (map, info) = decode_input(st, &rec, &params)?;
    progress.advance(1);
    let decode_ms = ms(t);

    let t = Instant::now();
    let mut encoded: Vec<(String, Vec<u8>)> = Vec::with_capacity(5);
    let mut radius = None;
    if params.outputs.fourier {
        // The CLI's own function: the same files `horizon-bake bake --outputs fourier` writes.
        // Before the horizon layers, which consume the map as they stream.
        let (files, r) = crate::bake::fourier_files(&map, &params, progress)?;
        radius = Some(r);
        for f in files {
            encoded.push((f.name.to_owned(), f.bytes));
        }
    }
    let mut streamed = None;
    if params.outputs.horizon {
        // Kernel and PNG encoder overlap band by band, as in the CLI, so `bake` covers both and
        // no whole layer exists; the PNGs go straight into blob writers (temporary files), so
        // no whole encoded image exists either. Every other format waits for its first request.
        let outs = [st.0.blobs.writer()?, st.0.blobs.writer()?];
        let (writers, r) = encode::stream_horizon_pngs::<u8, _>(map, &params, progress, outs)?;
        radius = Some(r);
        streamed = Some(writers);
    } else {
        drop(map);
    }
    let bake_ms = ms(t);
    let encode_ms = 0.0;
    let radius = radius.ok_or_else(|| Error::Internal("a bake with no outputs".into()))?;

    if progress.is_canceled() {
        return Err(Error::Canceled);
    }
    progress.start(Stage::Store, encoded.len() as u64 + 3);
    let t = Instant::now();
    // Hold the sweep lock from the first blob write to the record commit, so a concurrent
    // retention sweep never removes a blob this record is about to reference.
    let _gc = st.0.gc_lock.read().unwrap_or_else(|e| e.into_inner());
    if let Some([w0, w1]) = streamed {
        // Both files are written already; committing is an fsync and a rename each, side by
        // side.
        let (h0, h1) = rayon::join(|| w0.commit(), || w1.commit());
        rec.results.insert(HORIZON_RESULTS[0].to_owned(), h0?);
        rec.results.insert(HORIZON_RESULTS[1].to_owned(), h1?);
        progress.advance(2);
    }
    for (name, bytes) in &encoded {
        let hash = st.0.blobs.put(bytes)?;
        rec.results.insert(name.clone(), hash);
        progress.advance(1);
    }
    rec.status = Status::Succeeded;
    rec.input = Some(info);
    rec.radius = Some(RadiusInfo { texels: radius.texels, reason: radius.reason });
    rec.finished_ms = Some(now_ms());
    rec.error = None;
    let store_ms = ms(t);
    let queued = rec.started_ms.unwrap_or(rec.created_ms).saturating_sub(rec.created_ms) as f64;
    rec.timings_ms = Some(Timings {
        queued,
        decode: decode_ms,
        bake: bake_ms,
        encode: encode_ms,
        store: store_ms,
        total: ms(t_total),
    });
    st.0.bakes.put(&rec)?;
    progress.start(Stage::Done, 1);
    progress.advance(1);
    Ok(rec)
}
