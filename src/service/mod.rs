//! The bake service: an HTTP job API over the library (SPEC §5) that never loses a job.
//!
//! # Shape
//! - [`config`]: flags and environment → one validated [`Config`].
//! - [`store`]: the [`store::BakeStore`] and [`store::BlobStore`] traits and their embedded
//!   implementations (redb file + content-addressed files in the data directory).
//! - [`queue`] and [`worker`]: a bounded FIFO of bake ids, a dispatcher that runs at most N
//!   bakes at once on a dedicated rayon pool, results back over a oneshot.
//! - [`handlers`]: thin axum handlers: validate, call the store or the queue, answer.
//! - [`upload`]: an upload's body under the size limit and the idle timeout.
//! - [`problem`]: every failure as problem+json with a stable code.
//! - [`metrics`]: Prometheus text.
//!
//! # Durability
//! A submission is answered 202 only after its input blob and its `queued` record are durable.
//! At start, every record found `queued` or `running` is queued again (in creation order), so a
//! crash or a SIGKILL loses no accepted bake; a re-run is idempotent because results are
//! content-addressed. On SIGTERM the server stops taking work (`/readyz` and submissions answer
//! 503), lets running bakes finish within the grace period and puts the others back to `queued`
//! for the next start.

pub mod config;
pub mod handlers;
pub mod metrics;
pub mod problem;
pub mod queue;
pub mod store;
pub mod ui;
pub mod upload;
pub mod worker;

pub use config::{Config, ServeArgs};

use crate::error::{Error, Result};
use axum::extract::DefaultBodyLimit;
use axum::routing::{get, post};
use axum::Router;
use std::convert::Infallible;
use std::future::Future;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use store::{BakeStore, BlobStore, FsBlobStore, RedbStore, Status};
use tokio::sync::{broadcast, Semaphore};
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;

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
    ("/v1/bakes/{id}/preview", &["GET"]),
    ("/v1/bakes/{id}/heights", &["GET"]),
    ("/v1/cubemap/{face}", &["GET"]),
    ("/v1/cubemap.ktx2", &["GET"]),
    ("/v1/cubemap.dds", &["GET"]),
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

/// What [`AppState`] holds.
pub struct Shared {
    pub config: Config,
    pub bakes: Arc<dyn BakeStore>,
    pub blobs: Arc<dyn BlobStore>,
    pub queue: queue::Queue,
    /// The dedicated pool bakes run on (never the async workers).
    pub pool: rayon::ThreadPool,
    /// Previews render here, not on `pool`: a preview is a request someone is waiting for, and
    /// on the bake pool it would wait for the whole of a running bake (rayon workers busy in a
    /// bake's parallel loop only take new jobs when they run out of its work).
    pub preview_pool: rayon::ThreadPool,
    /// At most `max_concurrent_bakes` permits.
    pub slots: Arc<Semaphore>,
    /// Uploads read at once.
    pub uploads: Arc<Semaphore>,
    pub metrics: metrics::Metrics,
    /// Set on shutdown: readyz and submissions answer 503.
    pub draining: AtomicBool,
    /// Stops the dispatcher.
    pub stop: CancellationToken,
    /// Ends long-lived responses (SSE) and background loops.
    pub closing: CancellationToken,
    /// Running jobs.
    pub tracker: TaskTracker,
    /// Serialises the dedup check and the insert of submissions.
    pub submit_lock: tokio::sync::Mutex<()>,
    /// Readers: anything writing blobs then a record referencing them. Writer: blob removal.
    pub gc_lock: std::sync::RwLock<()>,
    /// Ids of bakes whose state changed (wakes SSE streams).
    pub changes: broadcast::Sender<String>,
    /// One lock per result group being encoded on request (`id/first result name`), so
    /// concurrent first requests for a result encode it once and the others wait for it.
    pub encoding: std::sync::Mutex<std::collections::HashMap<String, Arc<tokio::sync::Mutex<()>>>>,
}

impl AppState {
    /// Opens the data directory with the embedded stores.
    ///
    /// # Errors
    /// When the data directory or the store cannot be opened, or the pool cannot start.
    pub fn open(config: Config) -> Result<Self> {
        std::fs::create_dir_all(&config.data_dir).map_err(|e| {
            Error::Io(std::io::Error::new(
                e.kind(),
                format!("cannot create the data directory {}: {e}", config.data_dir.display()),
            ))
        })?;
        let bakes = Arc::new(RedbStore::open(&config.data_dir.join("bakes.redb"))?);
        let blobs = Arc::new(FsBlobStore::open(&config.data_dir.join("blobs"))?);
        Self::with_stores(config, bakes, blobs)
    }

    /// Builds the state on any stores (a networked database, object storage).
    ///
    /// # Errors
    /// When the bake pool cannot start.
    pub fn with_stores(
        config: Config,
        bakes: Arc<dyn BakeStore>,
        blobs: Arc<dyn BlobStore>,
    ) -> Result<Self> {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(config.bake_threads)
            .thread_name(|i| format!("bake-{i}"))
            .panic_handler(|_| tracing::error!("a bake thread panicked outside a job"))
            .build()
            .map_err(|e| Error::Internal(format!("cannot start the bake pool: {e}")))?;
        let preview_pool = rayon::ThreadPoolBuilder::new()
            .num_threads(config.preview_threads)
            .thread_name(|i| format!("preview-{i}"))
            .panic_handler(|_| tracing::error!("a preview thread panicked outside a job"))
            .build()
            .map_err(|e| Error::Internal(format!("cannot start the preview pool: {e}")))?;
        let (changes, _) = broadcast::channel(1024);
        Ok(AppState(Arc::new(Shared {
            slots: Arc::new(Semaphore::new(config.max_concurrent_bakes)),
            uploads: Arc::new(Semaphore::new(config.max_inflight_uploads)),
            queue: queue::Queue::new(config.queue_capacity),
            config,
            bakes,
            blobs,
            pool,
            preview_pool,
            metrics: metrics::Metrics::default(),
            draining: AtomicBool::new(false),
            stop: CancellationToken::new(),
            closing: CancellationToken::new(),
            tracker: TaskTracker::new(),
            submit_lock: tokio::sync::Mutex::new(()),
            gc_lock: std::sync::RwLock::new(()),
            changes,
            encoding: Default::default(),
        })))
    }

    /// Tells SSE watchers that bake `id` changed.
    pub fn notify(&self, id: &str) {
        let _ = self.0.changes.send(id.to_owned());
    }

    /// Re-queues every bake found `queued` or `running` (in creation order) and starts the
    /// dispatcher and the retention sweeper. Call once, inside a tokio runtime.
    ///
    /// # Errors
    /// When the store cannot be read.
    pub async fn start(&self) -> Result<usize> {
        let store = self.0.bakes.clone();
        let unfinished = worker::blocking(move || {
            let mut out = Vec::new();
            let mut after: Option<String> = None;
            loop {
                let page = store.list(None, after.as_deref(), 1000)?;
                for mut r in page.items {
                    if r.status == Status::Running {
                        r.status = Status::Queued;
                        r.started_ms = None;
                        store.put(&r)?;
                    }
                    if r.status == Status::Queued {
                        out.push(r.id);
                    }
                }
                match page.next {
                    Some(n) => after = Some(n),
                    None => break,
                }
            }
            Ok(out)
        })
        .await?;
        for id in &unfinished {
            self.0.queue.push_recovered(id);
        }
        if !unfinished.is_empty() {
            tracing::info!(count = unfinished.len(), "re-queued unfinished bakes");
        }
        tokio::spawn(worker::dispatch(self.clone()));
        tokio::spawn(handlers::sweep_loop(self.clone()));
        Ok(unfinished.len())
    }

    /// Stops taking work, lets running bakes finish within the grace period, puts the rest back
    /// to `queued`, and ends long-lived responses.
    pub async fn drain(&self) {
        self.0.draining.store(true, Ordering::SeqCst);
        self.0.stop.cancel();
        self.0.tracker.close();
        let grace = self.0.config.shutdown_grace;
        if tokio::time::timeout(grace, self.0.tracker.wait()).await.is_err() {
            let ids = self.0.queue.running_ids();
            tracing::warn!(
                count = ids.len(),
                "grace period over: returning running bakes to the queue"
            );
            for id in ids {
                self.0.queue.cancel_running(&id, true);
            }
            self.0.tracker.wait().await;
        }
        self.0.closing.cancel();
    }

    /// Whether the server is draining.
    pub fn is_draining(&self) -> bool {
        self.0.draining.load(Ordering::SeqCst)
    }
}

/// The router: every route of SPEC §5 that this build serves (see [`ROUTES`]).
pub fn app(st: AppState) -> Router {
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
        // The page loads before anyone can type an API key into it; it holds no data.
        .route("/", get(ui::index))
        .route("/ui/{asset}", get(ui::asset))
        .route_layer(axum::middleware::from_fn_with_state(st.clone(), handlers::track))
        .fallback(handlers::fallback)
        .layer(axum::middleware::from_fn_with_state(st.clone(), handlers::head_limits))
        .layer(axum::middleware::map_response(problem::normalize))
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
    let st = AppState::open(config)?;
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
        let conn = graceful.watch(builder.serve_connection(TokioIo::new(stream), service));
        tokio::spawn(async move {
            if let Err(e) = conn.await {
                tracing::debug!(error = %e, "connection ended with an error");
            }
        });
    }
    graceful.shutdown().await;
    Ok(())
}
