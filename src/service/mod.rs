//! The bake service: an HTTP job API over the library (SPEC §5) that never loses a job.
//!
//! # Shape
//! - [`config`]: flags and environment → one validated [`Config`].
//! - [`crate::jobs`]: the job lifecycle behind the repository and blob traits (embedded redb +
//!   files, or PostgreSQL + S3); the HTTP layer reaches storage only through it.
//! - [`worker`]: what a bake computes (the [`crate::jobs::Runner`] the jobs core runs on the
//!   bake pool) and the results encoded on request.
//! - [`handlers`]: thin axum handlers: validate, call the jobs core, answer.
//! - [`upload`]: an upload's body under the size limit and the idle timeout.
//! - [`problem`]: every failure as problem+json with a stable code.
//! - [`headers`]: security headers on every answer, CORS when `--cors-origin` allows it.
//! - [`metrics`]: Prometheus text.
//!
//! # Durability
//! A submission is answered 202 only after its input blob and its `queued` record are durable.
//! Embedded: at start, every record found `queued` or `running` is queued again (in creation
//! order), so a crash or a SIGKILL loses no accepted bake. Shared stores: a worker that stops
//! heartbeating loses its lease and another takes the bake over. A re-run is idempotent because
//! results are content-addressed. On SIGTERM the server stops taking work (`/readyz` and
//! submissions answer 503), lets running bakes finish within the grace period and hands the
//! others back to the queue.

pub mod config;
pub mod conn;
pub mod handlers;
pub mod headers;
pub mod metrics;
pub mod problem;
pub mod ui;
pub mod upload;

pub use config::{Config, ServeArgs};

use crate::error::{Error, Result};
use crate::jobs::blob::{BlobStore, FsBlobStore};
use crate::jobs::repo::EmbeddedRepo;
use crate::jobs::repo::JobRepo;
use crate::jobs::{Jobs, JobsConfig};
use crate::pipeline::{job, tiled};
use axum::extract::DefaultBodyLimit;
use axum::routing::{get, post};
use axum::Router;
use config::Backend;
use std::convert::Infallible;
use std::future::Future;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;
use tokio::sync::Semaphore;

/// Every route and its methods: the router below is built to match, and a test checks both
/// against `openapi.yaml`.
pub const ROUTES: &[(&str, &[&str])] = &[
    ("/v1/bakes", &["GET", "POST"]),
    ("/v1/bakes/{id}", &["GET", "DELETE"]),
    ("/v1/bakes/{id}/events", &["GET"]),
    ("/v1/bakes/{id}/horizon/{layer}", &["GET"]),
    ("/v1/bakes/{id}/horizon.ktx2", &["GET"]),
    ("/v1/bakes/{id}/horizon.dds", &["GET"]),
    ("/v1/bakes/{id}/fourier/{layer}", &["GET"]),
    ("/v1/bakes/{id}/angles", &["GET"]),
    ("/v1/bakes/{id}/normal", &["GET"]),
    ("/v1/bakes/{id}/ao", &["GET"]),
    ("/v1/bakes/{id}/bent_normal", &["GET"]),
    ("/v1/bakes/{id}/svf", &["GET"]),
    ("/v1/bakes/{id}/horizon_distance", &["GET"]),
    ("/v1/bakes/{id}/openness_positive", &["GET"]),
    ("/v1/bakes/{id}/openness_negative", &["GET"]),
    ("/v1/bakes/{id}/sun_hours", &["GET"]),
    ("/v1/bakes/{id}/insolation", &["GET"]),
    ("/v1/bakes/{id}/shadow", &["GET"]),
    ("/v1/bakes/{id}/profile", &["GET"]),
    ("/v1/bakes/{id}/preview", &["GET"]),
    ("/v1/bakes/{id}/heights", &["GET"]),
    ("/v1/cubemap/{face}", &["GET"]),
    ("/v1/cubemap.ktx2", &["GET"]),
    ("/v1/cubemap.dds", &["GET"]),
    ("/v1/shaders", &["GET"]),
    ("/v1/shaders/{file}", &["GET"]),
    ("/healthz", &["GET"]),
    ("/readyz", &["GET"]),
    ("/metrics", &["GET"]),
    ("/openapi.yaml", &["GET"]),
    ("/", &["GET"]),
    ("/ui/{asset}", &["GET"]),
];

/// Shared state of one server. Cheap to clone.
#[derive(Clone)]
pub struct AppState(pub Arc<Shared>);

/// Requests per thread of the preview and encode pools that may wait for or run on them.
pub const POOL_QUEUE: usize = 8;

/// What [`AppState`] holds.
pub struct Shared {
    pub config: Config,
    /// The job lifecycle: every state change of a bake goes through it.
    pub jobs: Jobs,
    /// Previews render here, not on the bake pool: a preview is a request someone is waiting
    /// for, and on the bake pool it would wait for the whole of a running bake (rayon workers
    /// busy in a bake's parallel loop only take new jobs when they run out of its work).
    pub preview_pool: rayon::ThreadPool,
    /// On-request encodes (a format's first download) run here, not on the preview pool, so a
    /// burst of them cannot hold up a preview, nor a long preview an encode.
    pub encode_pool: rayon::ThreadPool,
    /// Requests waiting for or running on each of those pools ([`POOL_QUEUE`] per thread): past
    /// that, 503 with Retry-After rather than an unbounded queue of decoded maps.
    pub preview_slots: Arc<Semaphore>,
    pub encode_slots: Arc<Semaphore>,
    /// Uploads read at once.
    pub uploads: Arc<Semaphore>,
    /// The bytes every decode of this process reserves from (`--decode-memory-bytes`).
    pub decode_budget: Arc<crate::heightmap::budget::MemoryBudget>,
    pub metrics: Arc<metrics::Metrics>,
    /// Set on shutdown: readyz and submissions answer 503.
    pub draining: AtomicBool,
    /// Result groups being encoded in the background after their first request, by
    /// `id/first result name`: concurrent first requests start one encode, and every request
    /// meanwhile is answered 202 with its progress (see `handlers::results`).
    pub encodes: std::sync::Mutex<std::collections::HashMap<String, handlers::EncodeJob>>,
}

impl AppState {
    /// How a request's decode reserves its memory: from the process budget, waiting up to
    /// `upload_wait` (as an upload waits for its slot), else 503 `decode_memory_busy`.
    pub fn admit(&self) -> crate::heightmap::budget::Admit<'_> {
        crate::heightmap::budget::Admit {
            budget: &self.0.decode_budget,
            wait: Some(self.0.config.upload_wait),
        }
    }

    /// Opens the embedded stores in the data directory. Call inside a tokio runtime.
    ///
    /// # Errors
    /// When the data directory or the store cannot be opened, or the pools cannot start.
    pub fn open(config: Config) -> Result<Self> {
        std::fs::create_dir_all(&config.data_dir).map_err(|e| {
            Error::Io(std::io::Error::new(
                e.kind(),
                format!("cannot create the data directory {}: {e}", config.data_dir.display()),
            ))
        })?;
        let repo = Arc::new(EmbeddedRepo::open(&config.data_dir.join("bakes.redb"))?);
        let blobs = Arc::new(FsBlobStore::open(&config.data_dir.join("blobs"))?);
        Self::with_stores(config, repo, blobs)
    }

    /// Opens the stores `config.backend` names: the embedded ones, or PostgreSQL (migrated at
    /// start) and the S3 bucket. Call inside a tokio runtime.
    ///
    /// # Errors
    /// When a store cannot be opened or reached.
    pub async fn connect(config: Config) -> Result<Self> {
        match config.backend.clone() {
            Backend::Embedded => Self::open(config),
            Backend::Shared { database_url, s3 } => {
                let repo = crate::jobs::repo::postgres::PgRepo::connect(
                    &database_url,
                    Duration::from_secs(30),
                    &config.worker_id,
                    config.lease,
                )
                .await?;
                let spool = config.data_dir.join("spool");
                let blobs = crate::jobs::blob::S3BlobStore::connect(&s3, &spool).await?;
                Self::with_stores(config, Arc::new(repo), Arc::new(blobs))
            }
        }
    }

    /// Builds the state on any stores. Call inside a tokio runtime.
    ///
    /// # Errors
    /// When a pool cannot start.
    pub fn with_stores(
        config: Config,
        repo: Arc<dyn JobRepo>,
        blobs: Arc<dyn BlobStore>,
    ) -> Result<Self> {
        let pool = |name: &'static str| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(config.preview_threads)
                .thread_name(move |i| format!("{name}-{i}"))
                .panic_handler(move |_| tracing::error!("a {name} thread panicked outside a job"))
                .build()
                .map_err(|e| Error::Internal(format!("cannot start the {name} pool: {e}")))
        };
        let (preview_pool, encode_pool) = (pool("preview")?, pool("encode")?);
        let queue = config.preview_threads * POOL_QUEUE;
        let slots = || Arc::new(Semaphore::new(queue));
        let metrics = Arc::new(metrics::Metrics::default());
        let shared = matches!(config.backend, Backend::Shared { .. });
        let jobs_cfg = JobsConfig {
            worker_id: config.worker_id.clone(),
            lease: config.lease,
            heartbeat: config.heartbeat,
            max_attempts: config.max_attempts,
            queue_capacity: config.queue_capacity,
            concurrency: if config.role.bakes() { config.max_concurrent_bakes } else { 0 },
            bake_threads: config.bake_threads,
            retention: config.retention,
            sweep_interval: config.sweep_interval,
            orphan_age: Duration::from_secs(3600),
            // Change notifications wake idle workers; polling only covers a lost notification
            // (a database restart). The embedded queue lives in this process and never misses.
            poll: if shared { Duration::from_secs(2) } else { Duration::from_secs(30) },
            // `sweep` spills big far fields next to the service's own files, where the operator
            // put the disk for them (embedded mode; a shared-mode node keeps none, so the
            // system's temporary directory).
            scratch_dir: (!shared).then(|| config.data_dir.join("tmp")),
        };
        let decode_budget = crate::heightmap::budget::MemoryBudget::new(config.decode_memory_bytes);
        let hook_metrics = metrics.clone();
        let jobs = Jobs::new(
            repo,
            blobs,
            jobs_cfg,
            job::runner(config.limits, decode_budget.clone()),
            Some(Arc::new(move |s, secs, texels| hook_metrics.finished(s, secs, texels))),
        )?;
        // Maps above --tile-above are baked in tiles across every worker (SPEC §7.1).
        let tile_metrics = metrics.clone();
        jobs.set_tiling(crate::jobs::Tiling {
            tiler: Arc::new(tiled::PipelineTiler {
                limits: config.limits,
                settings: config.tiles,
                store: jobs.blob_store().clone(),
            }),
            on_tile: Some(Arc::new(move |label| tile_metrics.tile(label))),
        });
        Ok(AppState(Arc::new(Shared {
            uploads: Arc::new(Semaphore::new(config.max_inflight_uploads)),
            decode_budget,
            config,
            jobs,
            preview_pool,
            encode_pool,
            preview_slots: slots(),
            encode_slots: slots(),
            metrics,
            draining: AtomicBool::new(false),
            encodes: Default::default(),
        })))
    }

    /// Recovers what a previous run left and starts the jobs core's background work.
    ///
    /// # Errors
    /// When the store cannot be read.
    pub async fn start(&self) -> Result<usize> {
        self.0.jobs.start().await
    }

    /// Stops taking work, lets running bakes finish within the grace period, hands the rest
    /// back to the queue, and ends long-lived responses.
    pub async fn drain(&self) {
        self.0.draining.store(true, Ordering::SeqCst);
        self.0.jobs.drain(self.0.config.shutdown_grace).await;
    }

    /// Whether the server is draining.
    pub fn is_draining(&self) -> bool {
        self.0.draining.load(Ordering::SeqCst)
    }
}

/// The router: every route of SPEC §5 that this build serves (see [`ROUTES`]).
pub fn app(st: AppState) -> Router {
    if !st.0.config.role.serves_api() {
        // A worker answers health and metrics only (SPEC §7).
        return Router::new()
            .route("/healthz", get(handlers::healthz))
            .route("/readyz", get(handlers::readyz))
            .route("/metrics", get(handlers::metrics))
            .route_layer(axum::middleware::from_fn_with_state(st.clone(), handlers::track))
            .fallback(handlers::fallback)
            .layer(axum::middleware::map_response(problem::normalize))
            .layer(axum::middleware::from_fn_with_state(st.clone(), headers::security))
            .with_state(st);
    }
    // The submit handler bounds the body itself (see `handlers::submit`): it must read and
    // discard an oversized body before answering 413, or the client, still sending, sees a reset
    // instead of the answer. A limit layer would answer at once, so none is set here.
    let submit = post(handlers::submit).layer::<_, Infallible>(DefaultBodyLimit::disable());
    let v1 = Router::new()
        .route("/v1/bakes", submit.get(handlers::list))
        .route("/v1/bakes/{id}", get(handlers::get_bake).delete(handlers::delete_bake))
        .route("/v1/bakes/{id}/events", get(handlers::events))
        .route("/v1/bakes/{id}/horizon/{layer}", get(handlers::horizon_layer))
        .route("/v1/bakes/{id}/horizon.ktx2", get(handlers::horizon_ktx2))
        .route("/v1/bakes/{id}/horizon.dds", get(handlers::horizon_dds))
        .route("/v1/bakes/{id}/fourier/{layer}", get(handlers::fourier_layer))
        .route("/v1/bakes/{id}/angles", get(handlers::angles))
        .route("/v1/bakes/{id}/normal", get(handlers::normal))
        .route("/v1/bakes/{id}/ao", get(handlers::ao))
        .route("/v1/bakes/{id}/bent_normal", get(handlers::bent_normal))
        .route("/v1/bakes/{id}/svf", get(handlers::svf))
        .route("/v1/bakes/{id}/horizon_distance", get(handlers::horizon_distance))
        .route("/v1/bakes/{id}/openness_positive", get(handlers::openness_positive))
        .route("/v1/bakes/{id}/openness_negative", get(handlers::openness_negative))
        .route("/v1/bakes/{id}/sun_hours", get(handlers::sun_hours))
        .route("/v1/bakes/{id}/insolation", get(handlers::insolation))
        .route("/v1/bakes/{id}/shadow", get(handlers::shadow))
        .route("/v1/bakes/{id}/profile", get(handlers::profile))
        .route("/v1/bakes/{id}/preview", get(handlers::preview))
        .route("/v1/bakes/{id}/heights", get(handlers::heights))
        .route("/v1/cubemap/{face}", get(handlers::cubemap_face))
        .route("/v1/cubemap.ktx2", get(handlers::cubemap_ktx2))
        .route("/v1/cubemap.dds", get(handlers::cubemap_dds))
        .route_layer(axum::middleware::from_fn_with_state(st.clone(), handlers::auth));
    Router::new()
        .merge(v1)
        .route("/healthz", get(handlers::healthz))
        .route("/readyz", get(handlers::readyz))
        .route("/metrics", get(handlers::metrics))
        .route("/openapi.yaml", get(handlers::openapi))
        // Shader includes hold no data; the page's viewer loads one before a key is entered.
        .route("/v1/shaders", get(handlers::shaders_list))
        .route("/v1/shaders/{file}", get(handlers::shader_file))
        // The page loads before anyone can type an API key into it; it holds no data.
        .route("/", get(ui::index))
        .route("/ui/{asset}", get(ui::asset))
        .route_layer(axum::middleware::from_fn_with_state(st.clone(), handlers::track))
        .fallback(handlers::fallback)
        .layer(axum::middleware::from_fn_with_state(st.clone(), handlers::head_limits))
        .layer(axum::middleware::map_response(problem::normalize))
        .layer(axum::middleware::from_fn_with_state(st.clone(), headers::security))
        .with_state(st)
}

/// Opens the store in `config.data_dir`, then serves on `listener` until `shutdown` resolves
/// (see [`serve`]).
///
/// # Errors
/// When the store cannot be opened or the listener fails.
pub async fn run(
    config: Config,
    listener: tokio::net::TcpListener,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> Result<()> {
    let st = AppState::connect(config).await?;
    serve(st, listener, shutdown).await
}

/// Serves `app(st)` on `listener` until `shutdown` resolves, then drains (see
/// [`AppState::drain`]) and lets open connections finish.
///
/// The accept loop is our own rather than `axum::serve`, which sets no timer on hyper and so
/// has no header read timeout: a client that opens a connection and never finishes its headers
/// would hold it forever. Here hyper closes such a connection after `header_timeout`.
///
/// # Errors
/// When the store cannot be read at start.
pub async fn serve(
    st: AppState,
    listener: tokio::net::TcpListener,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> Result<()> {
    use hyper::server::conn::http1;
    use hyper_util::rt::{TokioIo, TokioTimer};
    use hyper_util::server::graceful::GracefulShutdown;
    use hyper_util::service::TowerToHyperService;

    st.start().await?;
    let header_timeout = st.0.config.header_timeout;
    let router = app(st.clone());
    let graceful = GracefulShutdown::new();
    let mut builder = http1::Builder::new();
    // hyper's own limit on a request head answers a bare 431; set it well above ours
    // (`max_header_bytes`, checked by `handlers::head_limits`), so clients get problem+json.
    builder.timer(TokioTimer::new()).header_read_timeout(header_timeout).max_buf_size(1 << 20);
    let drain_state = st.clone();
    let mut shutdown = std::pin::pin!(async move {
        shutdown.await;
        tracing::info!("shutting down: draining");
        drain_state.drain().await;
    });
    loop {
        let (stream, _peer) = tokio::select! {
            _ = &mut shutdown => break,
            accepted = listener.accept() => match accepted {
                Ok(conn) => conn,
                Err(e) => {
                    // Out of file descriptors and the like: back off instead of spinning.
                    tracing::warn!(error = %e, "accept failed");
                    tokio::time::sleep(std::time::Duration::from_millis(50)).await;
                    continue;
                }
            },
        };
        let service = TowerToHyperService::new(router.clone());
        let io = TokioIo::new(conn::ProblemIo::new(stream));
        let conn = graceful.watch(builder.serve_connection(io, service));
        tokio::spawn(async move {
            if let Err(e) = conn.await {
                tracing::debug!(error = %e, "connection ended with an error");
            }
        });
    }
    // Connections still open after the bakes' drain get the grace period again, then are
    // closed: a request stuck in a handler cannot hold the process up for ever.
    let grace = st.0.config.shutdown_grace.max(std::time::Duration::from_secs(1));
    if tokio::time::timeout(grace, graceful.shutdown()).await.is_err() {
        tracing::warn!(?grace, "connections still open after the drain's deadline: closing them");
    }
    Ok(())
}
