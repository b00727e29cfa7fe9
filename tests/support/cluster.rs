//! The real-engines cluster harness of the distributed tests (tests/cluster/distributed.rs,
//! tests/cluster/distributed_tiles.rs): PostgreSQL and an S3 server started by `scripts/engines.sh`
//! (named by the `HORIZON_TEST_*` variables it writes), and real `horizon-bake serve` processes
//! on them, so kill -9, SIGSTOP and SIGTERM are the real thing. Each [`Cluster`] gets its own
//! database and bucket prefix. Included with `#[path = "../support/cluster.rs"] mod cluster;` by
//! the cluster binary only (not through `support`, which every test binary compiles).
#![allow(dead_code)]

use serde_json::Value;
use std::collections::BTreeSet;
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// One lock for every test on the engines, whichever module it is in: one of them restarts
/// PostgreSQL (`distributed::postgres_restart_gives_503_then_recovers`), and the tests of
/// tests/distributed.rs and tests/tiles_distributed.rs, each with a lock of its own, never
/// overlapped only because they were two processes that cargo ran one after the other.
pub static SERIAL: tokio::sync::Mutex<()> = tokio::sync::Mutex::const_new(());

/// The binary under test.
pub const BIN: &str = env!("CARGO_BIN_EXE_horizon-bake");

/// Where the engines listen (the `HORIZON_TEST_*` variables).
pub struct Engines {
    pub admin_url: String,
    pub s3_endpoint: String,
    pub bucket: String,
    /// The engines' directory (`scripts/engines.sh pg-stop DIR` restarts PostgreSQL).
    pub dir: PathBuf,
}

/// The engines, or None (the tests pass, saying so) when they are not running, except under
/// `CI=true`, where that is a failure.
pub fn engines() -> Option<Engines> {
    let var = |k: &str| std::env::var(k).ok().filter(|v| !v.is_empty());
    match (
        var("HORIZON_TEST_DATABASE_URL"),
        var("HORIZON_TEST_S3_ENDPOINT"),
        var("HORIZON_TEST_S3_BUCKET"),
        var("HORIZON_TEST_ENGINES"),
    ) {
        (Some(admin_url), Some(s3_endpoint), Some(bucket), Some(dir)) => {
            Some(Engines { admin_url, s3_endpoint, bucket, dir: PathBuf::from(dir) })
        }
        _ => {
            assert!(
                std::env::var("CI").as_deref() != Ok("true"),
                "CI=true but PostgreSQL/S3 are not running: start them with \
                 `scripts/engines.sh start DIR` and source DIR/env"
            );
            eprintln!("distributed tests skipped: run `scripts/engines.sh start DIR; . DIR/env`");
            None
        }
    }
}

/// One deployment: a fresh database and bucket prefix, and the nodes started on it.
pub struct Cluster {
    pub eng: Engines,
    pub db_url: String,
    pub prefix: String,
    pub tmp: tempfile::TempDir,
    pub nodes: Vec<Node>,
}

/// One `serve` process.
pub struct Node {
    pub child: Child,
    pub base: String,
    pub worker_id: String,
}

impl Drop for Cluster {
    fn drop(&mut self) {
        for n in &mut self.nodes {
            let _ = n.child.kill();
            let _ = n.child.wait();
        }
    }
}

/// Sends `sig` (`KILL`, `STOP`, `CONT`, `TERM`) to `pid`.
pub fn signal(pid: u32, sig: &str) {
    let ok = Command::new("kill").args([&format!("-{sig}"), &pid.to_string()]).status().unwrap();
    assert!(ok.success(), "kill -{sig} {pid} failed");
}

impl Cluster {
    pub async fn new(name: &str) -> Option<Cluster> {
        let eng = engines()?;
        let tag = format!("{name}_{}", std::process::id());
        let admin = sqlx::PgPool::connect(&eng.admin_url).await.unwrap();
        sqlx::query(&format!("DROP DATABASE IF EXISTS {tag}")).execute(&admin).await.unwrap();
        sqlx::query(&format!("CREATE DATABASE {tag}")).execute(&admin).await.unwrap();
        admin.close().await;
        let db_url = match eng.admin_url.rsplit_once('/') {
            Some((base, _)) => format!("{base}/{tag}"),
            None => unreachable!(),
        };
        Some(Cluster { eng, db_url, prefix: tag, tmp: tempfile::tempdir().unwrap(), nodes: vec![] })
    }

    /// Starts `serve --role role` with the shared stores; returns its index.
    pub fn start(&mut self, role: &str, worker_id: &str, extra: &[&str]) -> usize {
        let i = self.nodes.len();
        let dir = self.tmp.path().join(format!("node{i}"));
        std::fs::create_dir_all(&dir).unwrap();
        let addr_file = dir.join("addr");
        let log = std::fs::File::create(dir.join("log")).unwrap();
        let mut args: Vec<String> = [
            "serve",
            "--role",
            role,
            "--addr",
            "127.0.0.1:0",
            "--worker-id",
            worker_id,
            "--database-url",
            &self.db_url,
            "--s3-endpoint",
            &self.eng.s3_endpoint,
            "--s3-bucket",
            &self.eng.bucket,
            "--s3-prefix",
            &self.prefix,
            "--lease-secs",
            "2",
            "--heartbeat-ms",
            "200",
            "--bake-threads",
            "2",
        ]
        .iter()
        .map(|s| s.to_string())
        .collect();
        args.push("--addr-file".into());
        args.push(addr_file.display().to_string());
        args.push("--data-dir".into());
        args.push(dir.join("data").display().to_string());
        args.extend(extra.iter().map(|s| s.to_string()));
        let child = Command::new(BIN)
            .args(&args)
            .env("RUST_LOG", "info")
            .stdout(Stdio::null())
            .stderr(log)
            .spawn()
            .unwrap();
        let t = Instant::now();
        while !addr_file.exists() || std::fs::read_to_string(&addr_file).unwrap().is_empty() {
            assert!(
                t.elapsed() < Duration::from_secs(60),
                "node {i} did not start: {}",
                std::fs::read_to_string(dir.join("log")).unwrap_or_default()
            );
            std::thread::sleep(Duration::from_millis(50));
        }
        let addr = std::fs::read_to_string(&addr_file).unwrap();
        self.nodes.push(Node {
            child,
            base: format!("http://{}", addr.trim()),
            worker_id: worker_id.to_owned(),
        });
        i
    }

    pub fn base(&self, i: usize) -> &str {
        &self.nodes[i].base
    }

    pub fn pid(&self, i: usize) -> u32 {
        self.nodes[i].child.id()
    }

    pub fn log(&self, i: usize) -> String {
        std::fs::read_to_string(self.tmp.path().join(format!("node{i}/log"))).unwrap_or_default()
    }

    pub async fn db(&self) -> sqlx::PgPool {
        sqlx::PgPool::connect(&self.db_url).await.unwrap()
    }

    /// Every blob some record references (the `blob_refs` table).
    pub async fn referenced_blobs(&self) -> BTreeSet<String> {
        let db = self.db().await;
        sqlx::query_scalar::<_, String>("SELECT hash FROM blob_refs")
            .fetch_all(&db)
            .await
            .unwrap()
            .into_iter()
            .collect()
    }

    /// Every blob object under this cluster's prefix.
    pub async fn bucket_blobs(&self) -> BTreeSet<String> {
        use futures_util::StreamExt;
        use object_store::ObjectStore;
        let s3 = object_store::aws::AmazonS3Builder::new()
            .with_endpoint(&self.eng.s3_endpoint)
            .with_bucket_name(&self.eng.bucket)
            .with_region("us-east-1")
            .with_allow_http(true)
            .with_access_key_id(std::env::var("AWS_ACCESS_KEY_ID").unwrap())
            .with_secret_access_key(std::env::var("AWS_SECRET_ACCESS_KEY").unwrap())
            .build()
            .unwrap();
        let root = object_store::path::Path::from(format!("{}/blobs", self.prefix));
        let metas: Vec<_> = s3.list(Some(&root)).collect().await;
        metas.into_iter().map(|m| m.unwrap().location.filename().unwrap().to_owned()).collect()
    }
}

/// POSTs a PNG with `query`: (status, body).
pub async fn submit(c: &reqwest::Client, base: &str, png: &[u8], query: &str) -> (u16, Value) {
    let r = c
        .post(format!("{base}/v1/bakes?{query}"))
        .header("content-type", "image/png")
        .body(png.to_vec())
        .send()
        .await
        .unwrap();
    let s = r.status().as_u16();
    (s, r.json().await.unwrap())
}

/// GETs JSON: (status, body, or null).
pub async fn get_json(c: &reqwest::Client, url: &str) -> (u16, Value) {
    let r = c.get(url).send().await.unwrap();
    let s = r.status().as_u16();
    (s, r.json().await.unwrap_or(Value::Null))
}

impl Cluster {
    /// The bake resource `id` on node `i`.
    pub fn url_of(&self, i: usize, id: &str) -> String {
        format!("{}/v1/bakes/{id}", self.base(i))
    }
}
