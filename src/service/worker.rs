//! Running bakes: the dispatcher that takes ids off the queue, at most N at once, and the job
//! that runs one bake on the dedicated rayon pool.
//!
//! The async side never computes: it marks the record `running`, hands the bake to the pool with
//! `ThreadPool::spawn`, and awaits the outcome on a oneshot channel. The pool side decodes,
//! bakes, encodes and stores the results, inside `catch_unwind` so a panicking bake becomes a
//! `failed` record instead of an aborted process (rayon's default on a panic in `spawn`).
//! Cancellation goes through [`Progress::cancel`], which the kernel polls between bands.

use crate::bake::{self, Precisions};
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

/// Names of the horizon results a bake stores (each an immutable blob); with
/// `outputs=fourier` it also stores `fourier_0.png`, `fourier_1.png` (and `fourier_2.png` for
/// 7 or 9 terms), as the CLI names them. Every format is encoded once, when the bake finishes, by the same function the CLI uses
/// ([`encode::horizon_files`]), so a download is a file read with a content-hash ETag and is
/// byte-identical to `horizon-bake bake --format …` (KTX2/DDS at the CLI's default `unorm8`).
pub const HORIZON_RESULTS: [&str; 8] = [
    "horizon_0.png8",
    "horizon_1.png8",
    "horizon_0.png16",
    "horizon_1.png16",
    "horizon_0.exr",
    "horizon_1.exr",
    "horizon.ktx2",
    "horizon.dds",
];

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
                    tracing::error!(bake = %id, error = %e, "bake failed");
                    "an internal error occurred; it has been logged".to_owned()
                }
                _ => e.to_string(),
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

/// One bake, on the bake pool: decode → bake → encode → store, then the record is committed as
/// `succeeded`. Returns the stored record.
fn execute(st: &AppState, mut rec: BakeRecord, progress: &Progress) -> Result<BakeRecord> {
    let t_total = Instant::now();
    let params = params_of(&rec)?;

    progress.start(Stage::Decode, 1);
    let t = Instant::now();
    let bytes =
        st.0.blobs
            .get(&rec.input_blob)?
            .ok_or_else(|| Error::Internal(format!("input blob {} is missing", rec.input_blob)))?;
    let (map, info) = heightmap::decode(&bytes, params.channel, &st.0.config.limits)?;
    drop(bytes);
    progress.advance(1);
    let decode_ms = ms(t);

    let t = Instant::now();
    let mut encoded: Vec<(String, Vec<u8>)> = Vec::with_capacity(HORIZON_RESULTS.len() + 3);
    let mut radius = None;
    let mut encode_ms = 0.0;
    if params.outputs.horizon {
        let (layers, r) = bake::bake_horizon(&map, &params, Precisions::ALL, progress)?;
        radius = Some(r);
        let te = Instant::now();
        progress.start(Stage::Encode, 2);
        // png8 and png16 share a file name in the CLI's scheme, so they are two calls.
        let main_formats = Formats {
            png8: true,
            png16: false,
            exr: true,
            ktx2: true,
            dds: true,
            texture_precision: TexturePrecision::Unorm8,
        };
        let wide = Formats {
            png8: false,
            png16: true,
            exr: false,
            ktx2: false,
            dds: false,
            ..main_formats
        };
        for (formats, png_suffix) in [(main_formats, "png8"), (wide, "png16")] {
            if progress.is_canceled() {
                return Err(Error::Canceled);
            }
            for f in encode::horizon_files(&layers, &formats)? {
                let name = match f.name.strip_suffix(".png") {
                    Some(stem) => format!("{stem}.{png_suffix}"),
                    None => f.name.to_owned(),
                };
                encoded.push((name, f.bytes));
            }
            progress.advance(1);
        }
        encode_ms += ms(te);
    }
    if params.outputs.fourier {
        // The CLI's own function: the same files `horizon-bake bake --outputs fourier` writes.
        let (files, r) = crate::bake::fourier_files(&map, &params, progress)?;
        radius.get_or_insert(r);
        for f in files {
            encoded.push((f.name.to_owned(), f.bytes));
        }
    }
    drop(map);
    let bake_ms = ms(t) - encode_ms;
    let radius = radius.ok_or_else(|| Error::Internal("a bake with no outputs".into()))?;

    if progress.is_canceled() {
        return Err(Error::Canceled);
    }
    progress.start(Stage::Store, encoded.len() as u64 + 1);
    let t = Instant::now();
    // Hold the sweep lock from the first blob write to the record commit, so a concurrent
    // retention sweep never removes a blob this record is about to reference.
    let _gc = st.0.gc_lock.read().unwrap_or_else(|e| e.into_inner());
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
