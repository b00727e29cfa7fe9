//! Service configuration in two steps: clap reads raw flags and environment variables
//! ([`ServeArgs`]), then [`Config::from_args`] validates them into the one [`Config`] the server
//! state is built from. Every limit has a flag, an environment variable and an embedded default,
//! so `horizon-bake serve` starts with no configuration at all.

use crate::error::{Error, Result};
use crate::heightmap::Limits;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

/// `--max-decode-bytes` when not given (see its doc).
pub const DEFAULT_MAX_DECODE_BYTES: u64 = 1536 << 20;
/// `--decode-memory-bytes` when not given (see its doc).
pub const DEFAULT_DECODE_MEMORY_BYTES: u64 = 4 << 30;

/// Raw flags of `horizon-bake serve` (each also read from a `HORIZON_*` environment variable).
#[derive(Debug, Clone, clap::Args)]
pub struct ServeArgs {
    /// Address to listen on (`127.0.0.1:0` picks a free port).
    #[arg(long, env = "HORIZON_ADDR", default_value = "127.0.0.1:8080")]
    pub addr: String,
    /// Directory holding the bake records (redb) and the content-addressed result files.
    #[arg(long, env = "HORIZON_DATA_DIR", default_value = "./data")]
    pub data_dir: PathBuf,
    /// Write the bound address (`IP:PORT`) to this file once listening (for scripts and tests).
    #[arg(long, env = "HORIZON_ADDR_FILE")]
    pub addr_file: Option<PathBuf>,
    /// Largest accepted request body in bytes (an upload, multipart included).
    #[arg(long, env = "HORIZON_MAX_BODY_BYTES", default_value_t = 256 * 1024 * 1024)]
    pub max_body_bytes: u64,
    /// Largest width or height of an input, in texels (maps above --tile-above are tiled).
    #[arg(long, env = "HORIZON_MAX_DIM", default_value_t = 65536)]
    pub max_dim: u32,
    /// Largest width × height of an input (maps above --tile-above are tiled).
    #[arg(long, env = "HORIZON_MAX_TEXELS", default_value_t = 65536 * 65536)]
    pub max_texels: u64,
    /// Most bytes one decode of an input may hold at its peak, estimated from the header before
    /// anything is allocated (a deflated TIFF of 261 KB can decode to 256 MiB); over it, the
    /// submission is a 422. The default, 1.5 GiB, fits the largest ordinary input whole: a
    /// 16384² float32 TIFF holds its 1 GiB of heights, a strip, and with nodata a 256 MiB hole
    /// mask (1.25 GiB); maps above --tile-above are checked streamed at submission, never whole.
    #[arg(long, env = "HORIZON_MAX_DECODE_BYTES", default_value_t = DEFAULT_MAX_DECODE_BYTES)]
    pub max_decode_bytes: u64,
    /// Bytes every decode of this process shares (submissions, previews, heights, on-request
    /// encodes, bakes): a decode reserves its estimate first, and waits up to upload_wait_ms
    /// for it (bakes as long as it takes), else 503 with Retry-After. The default, 4 GiB, is a
    /// fixed size rather than a share of the machine's memory, which a container misreports:
    /// two of the largest decodes --max-decode-bytes allows, with room for the smaller ones.
    #[arg(long, env = "HORIZON_DECODE_MEMORY_BYTES", default_value_t = DEFAULT_DECODE_MEMORY_BYTES)]
    pub decode_memory_bytes: u64,
    /// Threads of the dedicated bake pool (0 = one per core).
    #[arg(long, env = "HORIZON_BAKE_THREADS", default_value_t = 0)]
    pub bake_threads: usize,
    /// Bakes running at the same time (they share the bake pool).
    #[arg(long, env = "HORIZON_MAX_CONCURRENT_BAKES", default_value_t = 1)]
    pub max_concurrent_bakes: usize,
    /// Bakes waiting in the queue before submissions get 429.
    #[arg(long, env = "HORIZON_QUEUE_CAPACITY", default_value_t = 64)]
    pub queue_capacity: usize,
    /// Uploads read at the same time; more wait up to `upload_wait_ms`, then get 429.
    #[arg(long, env = "HORIZON_MAX_INFLIGHT_UPLOADS", default_value_t = 16)]
    pub max_inflight_uploads: usize,
    /// How long an upload waits for a free upload slot before 429, in milliseconds.
    #[arg(long, env = "HORIZON_UPLOAD_WAIT_MS", default_value_t = 5000)]
    pub upload_wait_ms: u64,
    /// Seconds a finished bake (and its results) is kept before it is removed.
    #[arg(long, env = "HORIZON_RETENTION_SECS", default_value_t = 7 * 24 * 3600)]
    pub retention_secs: u64,
    /// Seconds between retention sweeps.
    #[arg(long, env = "HORIZON_SWEEP_INTERVAL_SECS", default_value_t = 60)]
    pub sweep_interval_secs: u64,
    /// On SIGTERM, seconds running bakes get to finish before they are put back in the queue.
    #[arg(long, env = "HORIZON_SHUTDOWN_GRACE_SECS", default_value_t = 30)]
    pub shutdown_grace_secs: u64,
    /// When set, every /v1 route needs `Authorization: Bearer <key>` (health stays open).
    #[arg(long, env = "HORIZON_API_KEY", hide_env_values = true)]
    pub api_key: Option<String>,
    /// Largest cube-map face size served by /v1/cubemap.
    #[arg(long, env = "HORIZON_MAX_CUBEMAP_SIZE", default_value_t = 1024)]
    pub max_cubemap_size: u32,
    /// Turn the web page at `/` off (the API is unchanged).
    #[arg(long, env = "HORIZON_NO_UI")]
    pub no_ui: bool,
    /// Serve the web page's files from this directory, re-read on every request, instead of the
    /// copies built into the binary (for working on the page without rebuilding).
    #[arg(long, env = "HORIZON_UI_DIR")]
    pub ui_dir: Option<PathBuf>,
    /// Seconds an upload may go without sending a byte of its body before it is answered 408
    /// and its upload slot freed (a client that announces a body and never sends it).
    #[arg(long, env = "HORIZON_BODY_TIMEOUT_SECS", default_value_t = 30)]
    pub body_timeout_secs: u64,
    /// Least bytes per second an upload's body must bring over each 10 s window, else 408 and
    /// its upload slot is freed (a client dripping a byte every few seconds; 0 = no minimum).
    #[arg(long, env = "HORIZON_MIN_UPLOAD_RATE", default_value_t = 1024)]
    pub min_upload_rate: u64,
    /// Seconds a connection gets to send a request's complete headers before it is closed.
    #[arg(long, env = "HORIZON_HEADER_TIMEOUT_SECS", default_value_t = 30)]
    pub header_timeout_secs: u64,
    /// Threads of the preview pool, separate from the bake pool so a preview never waits for a
    /// long bake (0 = half the cores, at least one).
    #[arg(long, env = "HORIZON_PREVIEW_THREADS", default_value_t = 0)]
    pub preview_threads: usize,
    /// Seconds a preview, shadow, profile or rendered image may compute before it is canceled
    /// and answered 503 `preview_timeout` (a 4096² relief preview with 1024 steps runs minutes).
    #[arg(long, env = "HORIZON_PREVIEW_TIMEOUT_SECS", default_value_t = 60)]
    pub preview_timeout_secs: u64,
    /// Longest request target (path and query) in bytes; longer ones get 414 (problem+json).
    #[arg(long, env = "HORIZON_MAX_URI_BYTES", default_value_t = 16 * 1024)]
    pub max_uri_bytes: usize,
    /// Most bytes of request headers (names and values); more get 431 (problem+json).
    #[arg(long, env = "HORIZON_MAX_HEADER_BYTES", default_value_t = 64 * 1024)]
    pub max_header_bytes: usize,
    /// What this process does (SPEC §7): `all` answers HTTP and bakes; `api` answers HTTP and
    /// bakes nothing; `worker` bakes and serves only /healthz, /readyz and /metrics. `api` and
    /// `worker` need the shared stores (--database-url and --s3-bucket).
    #[arg(long, env = "HORIZON_ROLE", default_value = "all")]
    pub role: String,
    /// PostgreSQL for records, queue, leases, progress, cancel and change notifications,
    /// instead of the embedded redb file (needs --s3-bucket too).
    #[arg(long, env = "HORIZON_DATABASE_URL", hide_env_values = true)]
    pub database_url: Option<String>,
    /// S3-compatible endpoint URL for inputs and results (e.g. http://127.0.0.1:8333).
    #[arg(long, env = "HORIZON_S3_ENDPOINT")]
    pub s3_endpoint: Option<String>,
    /// Bucket for inputs and results (needs --database-url too).
    #[arg(long, env = "HORIZON_S3_BUCKET")]
    pub s3_bucket: Option<String>,
    /// Region of the bucket.
    #[arg(long, env = "HORIZON_S3_REGION", default_value = "us-east-1")]
    pub s3_region: String,
    /// Key prefix inside the bucket (several deployments can share one bucket).
    #[arg(long, env = "HORIZON_S3_PREFIX", default_value = "")]
    pub s3_prefix: String,
    /// This worker's name in claims and logs (default: host name and process id).
    #[arg(long, env = "HORIZON_WORKER_ID")]
    pub worker_id: Option<String>,
    /// Seconds a claim lasts without a heartbeat before another worker may take the bake over.
    #[arg(long, env = "HORIZON_LEASE_SECS", default_value_t = 15)]
    pub lease_secs: u64,
    /// Milliseconds between a running bake's heartbeats (progress, lease, cancel).
    #[arg(long, env = "HORIZON_HEARTBEAT_MS", default_value_t = 1000)]
    pub heartbeat_ms: u64,
    /// Claims of one bake before a lost worker fails it (`worker_lost`).
    #[arg(long, env = "HORIZON_MAX_ATTEMPTS", default_value_t = 3)]
    pub max_attempts: u32,
    /// Maps with more texels than this (width × height) are baked in tiles, spread over every
    /// worker (SPEC §7.1).
    #[arg(long, env = "HORIZON_TILE_ABOVE", default_value_t = 4096 * 4096)]
    pub tile_above: u64,
    /// Interior size of a tile, in texels (each also reads a halo of the radius + 1 around it).
    #[arg(long, env = "HORIZON_TILE_SIZE", default_value_t = 2048)]
    pub tile_size: u32,
    /// Let pages served from this origin (`https://tools.example.com`, or `*`) call the API
    /// from a browser (CORS). Off by default: only the server's own page can.
    #[arg(long, env = "HORIZON_CORS_ORIGIN")]
    pub cors_origin: Option<String>,
}

impl Default for ServeArgs {
    /// The embedded defaults, independent of the environment (tests, benches, embedding).
    fn default() -> Self {
        ServeArgs {
            addr: "127.0.0.1:8080".into(),
            data_dir: PathBuf::from("./data"),
            addr_file: None,
            max_body_bytes: 256 * 1024 * 1024,
            max_dim: 65536,
            max_texels: 65536 * 65536,
            max_decode_bytes: DEFAULT_MAX_DECODE_BYTES,
            decode_memory_bytes: DEFAULT_DECODE_MEMORY_BYTES,
            bake_threads: 0,
            max_concurrent_bakes: 1,
            queue_capacity: 64,
            max_inflight_uploads: 16,
            upload_wait_ms: 5000,
            retention_secs: 7 * 24 * 3600,
            sweep_interval_secs: 60,
            shutdown_grace_secs: 30,
            api_key: None,
            max_cubemap_size: 1024,
            no_ui: false,
            ui_dir: None,
            body_timeout_secs: 30,
            min_upload_rate: 1024,
            header_timeout_secs: 30,
            preview_threads: 0,
            preview_timeout_secs: 60,
            max_uri_bytes: 16 * 1024,
            max_header_bytes: 64 * 1024,
            role: "all".into(),
            database_url: None,
            s3_endpoint: None,
            s3_bucket: None,
            s3_region: "us-east-1".into(),
            s3_prefix: String::new(),
            worker_id: None,
            lease_secs: 15,
            heartbeat_ms: 1000,
            max_attempts: 3,
            cors_origin: None,
            tile_above: 4096 * 4096,
            tile_size: 2048,
        }
    }
}

/// What a process does (SPEC §7).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Role {
    /// HTTP and bakes (the default).
    All,
    /// HTTP only; bakes nothing.
    Api,
    /// Bakes; HTTP only for health and metrics.
    Worker,
}

impl Role {
    /// Whether this process claims bakes.
    pub fn bakes(self) -> bool {
        self != Role::Api
    }

    /// Whether this process serves the API.
    pub fn serves_api(self) -> bool {
        self != Role::Worker
    }
}

/// Where records and blobs live.
#[derive(Debug, Clone)]
pub enum Backend {
    /// redb + files in the data directory.
    Embedded,
    /// PostgreSQL + an S3 bucket.
    Shared { database_url: String, s3: crate::jobs::blob::S3Config },
}

/// The validated service configuration.
#[derive(Debug, Clone)]
pub struct Config {
    pub addr: SocketAddr,
    pub data_dir: PathBuf,
    pub addr_file: Option<PathBuf>,
    pub max_body_bytes: u64,
    pub limits: Limits,
    /// The process-wide decode budget in bytes (`--decode-memory-bytes`).
    pub decode_memory_bytes: u64,
    pub bake_threads: usize,
    pub max_concurrent_bakes: usize,
    pub queue_capacity: usize,
    pub max_inflight_uploads: usize,
    pub upload_wait: Duration,
    pub retention: Duration,
    pub sweep_interval: Duration,
    pub shutdown_grace: Duration,
    /// The API key, trimmed of surrounding whitespace (a key pasted with a trailing newline or
    /// space is the key without it; inner whitespace is refused).
    pub api_key: Option<String>,
    pub max_cubemap_size: u32,
    pub no_ui: bool,
    pub ui_dir: Option<PathBuf>,
    /// Longest pause between two pieces of an upload's body.
    pub body_timeout: Duration,
    /// Least bytes per second of an upload's body over each [`crate::service::upload::RATE_WINDOW`].
    pub min_upload_rate: u64,
    /// Longest time to receive a request's headers.
    pub header_timeout: Duration,
    pub preview_threads: usize,
    /// Longest a request's computation on the preview pool may take.
    pub preview_timeout: Duration,
    pub max_uri_bytes: usize,
    pub max_header_bytes: usize,
    pub role: Role,
    pub backend: Backend,
    pub worker_id: String,
    pub lease: Duration,
    pub heartbeat: Duration,
    pub max_attempts: u32,
    /// The origin allowed to call the API from a browser (`--cors-origin`), if any.
    pub cors_origin: Option<String>,
    /// When and how maps are tiled (`--tile-above`, `--tile-size`).
    pub tiles: crate::pipeline::tiled::TileSettings,
}

fn at_least_one(field: &str, v: u64) -> Result<()> {
    if v == 0 {
        return Err(Error::param(field, "must be at least 1"));
    }
    Ok(())
}

impl Config {
    /// Validates raw flags.
    ///
    /// # Errors
    /// [`Error::Param`] naming the flag (snake_case) that is out of range or malformed.
    pub fn from_args(a: ServeArgs) -> Result<Self> {
        let addr: SocketAddr = a
            .addr
            .parse()
            .map_err(|_| Error::param("addr", format!("`{}` is not an IP:PORT address", a.addr)))?;
        at_least_one("max_body_bytes", a.max_body_bytes)?;
        at_least_one("max_dim", a.max_dim as u64)?;
        at_least_one("max_texels", a.max_texels)?;
        at_least_one("max_decode_bytes", a.max_decode_bytes)?;
        if a.max_decode_bytes > a.decode_memory_bytes {
            // A decode the per-request budget lets through must fit the shared one, or it would
            // wait for memory that never comes.
            return Err(Error::param(
                "max_decode_bytes",
                format!("must be at most --decode-memory-bytes ({})", a.decode_memory_bytes),
            ));
        }
        at_least_one("max_concurrent_bakes", a.max_concurrent_bakes as u64)?;
        at_least_one("queue_capacity", a.queue_capacity as u64)?;
        at_least_one("max_inflight_uploads", a.max_inflight_uploads as u64)?;
        at_least_one("sweep_interval_secs", a.sweep_interval_secs)?;
        at_least_one("max_cubemap_size", a.max_cubemap_size as u64)?;
        if a.max_cubemap_size > crate::encode::MAX_CUBE_SIZE {
            return Err(Error::param(
                "max_cubemap_size",
                format!("must be at most {}", crate::encode::MAX_CUBE_SIZE),
            ));
        }
        at_least_one("body_timeout_secs", a.body_timeout_secs)?;
        at_least_one("preview_timeout_secs", a.preview_timeout_secs)?;
        // hyper answers a head over its own buffer (set to 1 MiB in `service::serve`) with a
        // bare 431, and a target over 64 KiB with a bare 414; below those, ours are problem+json.
        if !(256..=60 * 1024).contains(&a.max_uri_bytes) {
            return Err(Error::param("max_uri_bytes", "must be from 256 to 61440"));
        }
        if !(1024..=512 * 1024).contains(&a.max_header_bytes) {
            return Err(Error::param("max_header_bytes", "must be from 1024 to 524288"));
        }
        at_least_one("header_timeout_secs", a.header_timeout_secs)?;
        // Environment variables and secret files often carry a trailing newline or space; a key
        // that cannot match any header value would lock every client out, so trim it, and refuse
        // whitespace inside (no `Authorization` value could carry it as one token).
        let api_key = match a.api_key.as_deref().map(str::trim) {
            None => None,
            Some("") => return Err(Error::param("api_key", "must not be empty when given")),
            Some(k) if k.chars().any(char::is_whitespace) => {
                return Err(Error::param("api_key", "must not contain whitespace"))
            }
            Some(k) => Some(k.to_owned()),
        };
        let cores = std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1);
        let preview_threads =
            if a.preview_threads == 0 { (cores / 2).max(1) } else { a.preview_threads };
        let bake_threads = if a.bake_threads == 0 { cores } else { a.bake_threads };
        let role = match a.role.as_str() {
            "all" => Role::All,
            "api" => Role::Api,
            "worker" => Role::Worker,
            other => {
                return Err(Error::param(
                    "role",
                    format!("`{other}` is not one of all, api, worker"),
                ))
            }
        };
        let backend = match (a.database_url, a.s3_bucket) {
            (None, None) => Backend::Embedded,
            (Some(_), None) => {
                return Err(Error::param("s3_bucket", "--database-url needs --s3-bucket too"))
            }
            (None, Some(_)) => {
                return Err(Error::param("database_url", "--s3-bucket needs --database-url too"))
            }
            (Some(database_url), Some(bucket)) => {
                let endpoint = a.s3_endpoint.ok_or_else(|| {
                    Error::param("s3_endpoint", "the shared stores need --s3-endpoint")
                })?;
                let env = |k: &str| std::env::var(k).ok().filter(|v| !v.is_empty());
                Backend::Shared {
                    database_url,
                    s3: crate::jobs::blob::S3Config {
                        endpoint,
                        bucket,
                        region: a.s3_region,
                        prefix: a.s3_prefix,
                        access_key: env("AWS_ACCESS_KEY_ID"),
                        secret_key: env("AWS_SECRET_ACCESS_KEY"),
                    },
                }
            }
        };
        if role != Role::All && matches!(backend, Backend::Embedded) {
            return Err(Error::param(
                "role",
                "`api` and `worker` share work through --database-url and --s3-bucket; \
                 the embedded store serves one process (role `all`)",
            ));
        }
        at_least_one("tile_size", a.tile_size as u64)?;
        at_least_one("lease_secs", a.lease_secs)?;
        at_least_one("heartbeat_ms", a.heartbeat_ms)?;
        at_least_one("max_attempts", a.max_attempts as u64)?;
        if a.heartbeat_ms >= a.lease_secs * 1000 {
            return Err(Error::param("heartbeat_ms", "must be shorter than the lease"));
        }
        let worker_id = match a.worker_id.map(|w| w.trim().to_owned()) {
            Some(w) if !w.is_empty() => w,
            _ => {
                let host = std::fs::read_to_string("/proc/sys/kernel/hostname")
                    .ok()
                    .map(|h| h.trim().to_owned())
                    .filter(|h| !h.is_empty())
                    .or_else(|| std::env::var("HOSTNAME").ok())
                    .unwrap_or_else(|| "host".into());
                format!("{host}-{}", std::process::id())
            }
        };
        let cors_origin = match a.cors_origin.as_deref().map(str::trim) {
            None | Some("") => None,
            Some("*") => Some("*".to_owned()),
            Some(o) => {
                let rest = o.strip_prefix("https://").or_else(|| o.strip_prefix("http://"));
                match rest {
                    Some(host)
                        if !host.is_empty()
                            && !host.contains('/')
                            && host.bytes().all(|b| b.is_ascii_graphic()) =>
                    {
                        Some(o.to_owned())
                    }
                    _ => {
                        return Err(Error::param(
                            "cors_origin",
                            format!(
                                "`{o}` is not an origin (scheme://host[:port], no path) or `*`"
                            ),
                        ))
                    }
                }
            }
        };
        Ok(Config {
            addr,
            data_dir: a.data_dir,
            addr_file: a.addr_file,
            max_body_bytes: a.max_body_bytes,
            limits: Limits {
                max_dim: a.max_dim,
                max_texels: a.max_texels,
                max_bytes: a.max_body_bytes,
                max_decode_bytes: a.max_decode_bytes,
            },
            decode_memory_bytes: a.decode_memory_bytes,
            bake_threads,
            max_concurrent_bakes: a.max_concurrent_bakes,
            queue_capacity: a.queue_capacity,
            max_inflight_uploads: a.max_inflight_uploads,
            upload_wait: Duration::from_millis(a.upload_wait_ms),
            retention: Duration::from_secs(a.retention_secs),
            sweep_interval: Duration::from_secs(a.sweep_interval_secs),
            shutdown_grace: Duration::from_secs(a.shutdown_grace_secs),
            api_key,
            max_cubemap_size: a.max_cubemap_size,
            no_ui: a.no_ui,
            ui_dir: a.ui_dir,
            body_timeout: Duration::from_secs(a.body_timeout_secs),
            min_upload_rate: a.min_upload_rate,
            header_timeout: Duration::from_secs(a.header_timeout_secs),
            preview_threads,
            preview_timeout: Duration::from_secs(a.preview_timeout_secs),
            max_uri_bytes: a.max_uri_bytes,
            max_header_bytes: a.max_header_bytes,
            role,
            backend,
            worker_id,
            lease: Duration::from_secs(a.lease_secs),
            heartbeat: Duration::from_millis(a.heartbeat_ms),
            max_attempts: a.max_attempts,
            cors_origin,
            tiles: crate::pipeline::tiled::TileSettings {
                tile_above: a.tile_above,
                tile_size: a.tile_size,
            },
        })
    }

    /// The embedded defaults with the data directory at `dir` and an ephemeral port on
    /// 127.0.0.1 (tests, benches, embedding); the environment is not read.
    ///
    /// # Errors
    /// None in practice: the embedded defaults are valid (a test checks it).
    pub fn for_dir(dir: impl Into<PathBuf>) -> Result<Self> {
        Config::from_args(ServeArgs {
            addr: "127.0.0.1:0".into(),
            data_dir: dir.into(),
            ..Default::default()
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_are_valid_and_bad_flags_name_themselves() {
        let c = Config::from_args(ServeArgs::default()).unwrap();
        assert_eq!(c.addr.port(), 8080);
        let d = Config::for_dir("/tmp/x").unwrap();
        assert_eq!(d.queue_capacity, c.queue_capacity);
        assert_eq!(d.limits, c.limits);
        assert_eq!(c.queue_capacity, 64);
        assert_eq!(c.limits.max_dim, 65536);
        assert_eq!((c.tiles.tile_above, c.tiles.tile_size), (4096 * 4096, 2048));
        assert!(c.bake_threads >= 1);
        let a = ServeArgs { queue_capacity: 0, ..Default::default() };
        match Config::from_args(a) {
            Err(Error::Param { field, .. }) => assert_eq!(field, "queue_capacity"),
            other => panic!("expected a parameter error, got {other:?}"),
        }
        assert_eq!((c.limits.max_decode_bytes, c.decode_memory_bytes), (1536 << 20, 4 << 30));
        let a = ServeArgs { max_decode_bytes: 5 << 30, ..Default::default() };
        match Config::from_args(a) {
            Err(Error::Param { field, .. }) => assert_eq!(field, "max_decode_bytes"),
            other => panic!("expected a parameter error, got {other:?}"),
        }
        let a = ServeArgs { addr: "nowhere".into(), ..Default::default() };
        match Config::from_args(a) {
            Err(Error::Param { field, .. }) => assert_eq!(field, "addr"),
            other => panic!("expected a parameter error, got {other:?}"),
        }
    }
}
