//! An upload's body, read under the service's bounds.
//!
//! Two ways a client can hold server resources without sending anything must both end:
//! - a pause: every piece of the body must arrive within `body_timeout` of the previous one (an
//!   idle timeout, not a total one, so a large upload on a slow link still gets through), else
//!   the stream fails with [`BodyTimedOut`] and the handler answers 408, freeing its upload slot;
//! - a drip: over every [`RATE_WINDOW`] the body must bring at least `min_rate` bytes per second
//!   (`--min-upload-rate`), else [`BodyTooSlow`] and a 408: a byte every few seconds never
//!   trips the idle timeout, and a few such connections would hold every upload slot;
//! - a body over `max_body_bytes`: the stream fails with [`BodyTooLarge`], but only after reading
//!   and discarding the rest of the body (at most [`DRAIN_BOUND`] more bytes, each piece within
//!   the idle timeout). Answering while the client is still sending makes the connection close
//!   under it, and most clients then report a reset instead of the 413.
//!
//! (Unfinished request headers are hyper's to time out: see [`crate::service::serve`].)
//!
//! A large upload is never held in memory (SPEC §7.1): [`Spool`] keeps the first
//! [`STREAM_UPLOAD_ABOVE`] bytes of a body in memory (the small-input path, unchanged), and past
//! that streams the body into a blob writer of the store (a temporary file renamed to its hash,
//! or an S3 multipart upload), which hashes it as it goes. The server's memory then grows by a
//! few chunks in flight, not by the input.

use axum::body::{Body, Bytes};
use futures_util::StreamExt;
use std::time::Duration;

/// Bytes past the limit that are read and thrown away before a 413 is answered; beyond it the
/// connection is closed with the answer (a client sending gigabytes does not get them all read).
pub const DRAIN_BOUND: u64 = 64 * 1024 * 1024;

/// The body paused longer than the idle timeout.
#[derive(Debug, thiserror::Error)]
#[error("the request body stalled: no data for {0:?}")]
pub struct BodyTimedOut(pub Duration);

/// The window over which an upload's rate is held against `--min-upload-rate`.
pub const RATE_WINDOW: Duration = Duration::from_secs(10);

/// The body arrived slower than the minimum rate over a [`RATE_WINDOW`].
#[derive(Debug, thiserror::Error)]
#[error("the request body arrived slower than {0} bytes per second")]
pub struct BodyTooSlow(pub u64);

/// The body is larger than the limit.
#[derive(Debug, thiserror::Error)]
#[error("the request body is larger than {0} bytes")]
pub struct BodyTooLarge(pub u64);

/// What went wrong reading a body, found anywhere in an error's source chain.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BodyFault {
    TimedOut,
    TooSlow,
    TooLarge,
    Other,
}

/// Classifies an error from reading a [`guarded`] body (directly, or through multipart parsing,
/// which wraps it).
pub fn fault(e: &(dyn std::error::Error + 'static)) -> BodyFault {
    let mut cur: Option<&(dyn std::error::Error + 'static)> = Some(e);
    while let Some(c) = cur {
        if c.is::<BodyTimedOut>() {
            return BodyFault::TimedOut;
        }
        if c.is::<BodyTooSlow>() {
            return BodyFault::TooSlow;
        }
        if c.is::<BodyTooLarge>() || c.is::<http_body_util::LengthLimitError>() {
            return BodyFault::TooLarge;
        }
        cur = c.source();
    }
    BodyFault::Other
}

/// Reads and discards what is left of `s`, up to `bound` bytes, each piece within `idle`.
async fn drain<S>(s: &mut S, idle: Duration, bound: u64)
where
    S: futures_util::Stream<Item = Result<Bytes, axum::Error>> + Unpin,
{
    let mut discarded = 0u64;
    while discarded <= bound {
        match tokio::time::timeout(idle, s.next()).await {
            Ok(Some(Ok(chunk))) => discarded += chunk.len() as u64,
            _ => return,
        }
    }
}

/// A guarded body yields (is Pending once) after each this many bytes.
pub const PACE: u64 = 1 << 20;

/// How a body is bounded: at most `limit` bytes, no pause longer than `idle`, and at least
/// `min_rate` bytes per second over each [`RATE_WINDOW`] (0: no minimum).
#[derive(Debug, Clone, Copy)]
pub struct Bounds {
    pub limit: u64,
    pub idle: Duration,
    pub min_rate: u64,
}

/// Where a guarded body stands: its stream, the bytes so far, and the current rate window's
/// start and bytes.
struct Guard<S> {
    s: S,
    seen: u64,
    window_start: tokio::time::Instant,
    window_seen: u64,
}

/// `body` with the idle timeout, the minimum rate and the size limit applied (see the module
/// documentation), pausing once per [`PACE`] bytes so the multipart parser, which reads until
/// its source is Pending, never gathers a large part in memory.
pub fn guarded(body: Body, b: Bounds) -> Body {
    let Bounds { limit, idle, min_rate } = b;
    let start = Some(Guard {
        s: body.into_data_stream(),
        seen: 0u64,
        window_start: tokio::time::Instant::now(),
        window_seen: 0,
    });
    let stream = futures_util::stream::unfold(start, move |state| async move {
        let mut g = state?;
        let last = tokio::time::Instant::now();
        let item: Result<Bytes, axum::BoxError> = loop {
            // Wake at the idle deadline, or at the rate window's end to judge it.
            let window_end = g.window_start + RATE_WINDOW;
            let idle_end = last + idle;
            let wake = if min_rate > 0 { idle_end.min(window_end) } else { idle_end };
            match tokio::time::timeout_at(wake, g.s.next()).await {
                Err(_) if tokio::time::Instant::now() >= idle_end => {
                    break Err(BodyTimedOut(idle).into());
                }
                Err(_) => {
                    if let Some(e) = rate_check(&mut g, min_rate) {
                        break Err(e.into());
                    }
                }
                Ok(None) => return None,
                Ok(Some(Err(e))) => break Err(e.into()),
                Ok(Some(Ok(chunk))) => {
                    let n = chunk.len() as u64;
                    g.seen += n;
                    g.window_seen += n;
                    if g.seen > limit {
                        drain(&mut g.s, idle, DRAIN_BOUND).await;
                        break Err(BodyTooLarge(limit).into());
                    }
                    if let Some(e) = rate_check(&mut g, min_rate) {
                        break Err(e.into());
                    }
                    if g.seen / PACE != (g.seen - n) / PACE {
                        // Pending once per PACE bytes: a reader that polls until Pending (the
                        // multipart parser does) buffers at most this much of a fast body.
                        tokio::task::yield_now().await;
                    }
                    return Some((Ok(chunk), Some(g)));
                }
            }
        };
        // After an error the stream ends.
        Some((item, None))
    });
    Body::from_stream(stream)
}

/// At the end of a rate window: the body's fault when the window brought fewer than `min_rate`
/// bytes per second, else a new window.
fn rate_check<S>(g: &mut Guard<S>, min_rate: u64) -> Option<BodyTooSlow> {
    let now = tokio::time::Instant::now();
    let elapsed = now.duration_since(g.window_start);
    if min_rate == 0 || elapsed < RATE_WINDOW {
        return None;
    }
    if (g.window_seen as f64) < min_rate as f64 * elapsed.as_secs_f64() {
        return Some(BodyTooSlow(min_rate));
    }
    g.window_start = now;
    g.window_seen = 0;
    None
}

/// Reads all of `body` into one buffer sized from `expected` (the announced Content-Length,
/// capped by the caller at the body limit) so a large upload is neither regrown nor copied
/// again after it is read.
///
/// # Errors
/// The body's own errors (from [`guarded`]: [`BodyTimedOut`], [`BodyTooLarge`]).
pub async fn read_all(body: Body, expected: usize) -> Result<Vec<u8>, axum::Error> {
    let mut out = Vec::new();
    // A client may announce more than it sends: reserving is only a hint, and a refusal of the
    // allocator is not an error (the buffer then grows as usual).
    let _ = out.try_reserve_exact(expected);
    let mut s = body.into_data_stream();
    while let Some(chunk) = s.next().await {
        out.extend_from_slice(&chunk?);
    }
    Ok(out)
}

/// Uploads larger than this are streamed to the blob store instead of read into memory.
pub const STREAM_UPLOAD_ABOVE: usize = 64 << 20;

/// An upload's body once read: in memory, or already stored as a blob.
#[derive(Debug)]
pub enum Upload {
    Memory(Vec<u8>),
    /// Stored (and pinned for the submission) under `hash`, `len` bytes.
    Stored {
        hash: String,
        len: u64,
    },
}

enum Piece {
    Data(Bytes),
    /// The body ended: commit the blob.
    Done,
}

/// Where a spilled upload is written: a blob writer committed once the body ends.
pub trait SpoolWriter: std::io::Write + Send {
    /// Publishes the bytes written; returns their hash.
    ///
    /// # Errors
    /// The store's failure.
    fn commit(self: Box<Self>) -> crate::Result<String>;
}

impl SpoolWriter for crate::jobs::PinnedWriter {
    fn commit(self: Box<Self>) -> crate::Result<String> {
        crate::jobs::PinnedWriter::commit(*self)
    }
}

/// Opens the blob writer a spilled upload streams into (called once, on a blocking thread).
pub type OpenWriter = Box<dyn FnOnce() -> crate::Result<Box<dyn SpoolWriter>> + Send>;

/// A body read piece by piece: in memory up to a threshold, then streamed to a blob writer
/// on a blocking thread (at most [`SPOOL_DEPTH`] pieces in flight). Dropped before
/// [`Spool::finish`], the writer discards what it wrote.
pub struct Spool {
    buf: Vec<u8>,
    above: usize,
    open: Option<OpenWriter>,
    tx: Option<tokio::sync::mpsc::Sender<Piece>>,
    task: Option<tokio::task::JoinHandle<crate::Result<(String, u64)>>>,
}

/// Pieces of a spilled upload queued for the blob writer.
pub const SPOOL_DEPTH: usize = 8;

impl Spool {
    /// A spool that keeps up to `above` bytes in memory (reserving `expected`, the announced
    /// length, when it fits), then streams into the writer `open` gives.
    ///
    /// A body announced larger than `above` goes to the writer from its first byte.
    pub fn new(expected: usize, above: usize, open: OpenWriter) -> Self {
        let mut buf = Vec::new();
        let above = if expected > above { 0 } else { above };
        // A hint only: a refusal of the allocator is not an error.
        let _ = buf.try_reserve_exact(expected.min(above));
        Spool { buf, above, open: Some(open), tx: None, task: None }
    }

    async fn send(&mut self, piece: Piece) -> crate::Result<()> {
        let Some(tx) = &self.tx else { return Ok(()) };
        if tx.send(piece).await.is_err() {
            // The writer stopped: its error says why.
            return Err(self.join().await.err().unwrap_or_else(|| {
                crate::Error::Internal("the upload's blob writer stopped".into())
            }));
        }
        Ok(())
    }

    async fn join(&mut self) -> crate::Result<(String, u64)> {
        match self.task.take() {
            Some(t) => {
                t.await.map_err(|e| crate::Error::Internal(format!("upload writer: {e}")))?
            }
            None => Err(crate::Error::Internal("the upload's blob writer is gone".into())),
        }
    }

    /// Adds a piece of the body.
    ///
    /// # Errors
    /// The blob store's failure, once the body spilled to it.
    pub async fn push(&mut self, chunk: Bytes) -> crate::Result<()> {
        if self.tx.is_none() {
            if self.buf.len() + chunk.len() <= self.above {
                self.buf.extend_from_slice(&chunk);
                return Ok(());
            }
            let open = self.open.take().ok_or_else(|| {
                crate::Error::Internal("the upload's blob writer was opened twice".into())
            })?;
            let (tx, mut rx) = tokio::sync::mpsc::channel::<Piece>(SPOOL_DEPTH);
            self.task = Some(tokio::task::spawn_blocking(move || {
                use std::io::Write;
                let mut w = open()?;
                let mut len = 0u64;
                while let Some(p) = rx.blocking_recv() {
                    match p {
                        Piece::Data(b) => {
                            w.write_all(&b)?;
                            len += b.len() as u64;
                        }
                        Piece::Done => return Ok((w.commit()?, len)),
                    }
                }
                // The body failed or the request was dropped: the writer discards its bytes.
                Err(crate::Error::Canceled)
            }));
            self.tx = Some(tx);
            let head = Bytes::from(std::mem::take(&mut self.buf));
            self.send(Piece::Data(head)).await?;
        }
        self.send(Piece::Data(chunk)).await
    }

    /// The whole body: in memory, or the stored blob.
    ///
    /// # Errors
    /// The blob store's failure.
    pub async fn finish(mut self) -> crate::Result<Upload> {
        if self.tx.is_none() {
            return Ok(Upload::Memory(std::mem::take(&mut self.buf)));
        }
        self.send(Piece::Done).await?;
        self.tx = None;
        let (hash, len) = self.join().await?;
        Ok(Upload::Stored { hash, len })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn over_the_limit_is_too_large_after_the_whole_body_is_read() {
        let read = std::sync::Arc::new(std::sync::atomic::AtomicUsize::new(0));
        let counter = read.clone();
        let chunks = futures_util::stream::iter((0..10).map(move |_| {
            counter.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
            Ok::<_, std::io::Error>(Bytes::from(vec![0u8; 100]))
        }));
        let body = guarded(
            Body::from_stream(chunks),
            Bounds { limit: 250, idle: Duration::from_secs(5), min_rate: 0 },
        );
        let err = axum::body::to_bytes(body, usize::MAX).await.unwrap_err();
        assert_eq!(fault(&err), BodyFault::TooLarge);
        assert_eq!(read.load(std::sync::atomic::Ordering::SeqCst), 10, "the rest was not drained");
        let ok = guarded(
            Body::from(vec![1u8; 250]),
            Bounds { limit: 250, idle: Duration::from_secs(5), min_rate: 0 },
        );
        assert_eq!(axum::body::to_bytes(ok, usize::MAX).await.unwrap().len(), 250);
    }

    /// A file-store writer with nothing to pin.
    struct Plain(Box<dyn crate::jobs::blob::BlobWriter>);
    impl std::io::Write for Plain {
        fn write(&mut self, b: &[u8]) -> std::io::Result<usize> {
            self.0.write(b)
        }
        fn flush(&mut self) -> std::io::Result<()> {
            self.0.flush()
        }
    }
    impl SpoolWriter for Plain {
        fn commit(self: Box<Self>) -> crate::Result<String> {
            self.0.commit(&|_| Ok(()))
        }
    }

    fn opener(store: &std::sync::Arc<crate::jobs::blob::FsBlobStore>) -> OpenWriter {
        use crate::jobs::blob::BlobStore;
        let s = store.clone();
        Box::new(move || Ok(Box::new(Plain(s.writer()?)) as Box<dyn SpoolWriter>))
    }

    #[tokio::test]
    async fn a_large_body_spills_to_the_store_a_small_one_stays_in_memory() {
        use crate::jobs::blob::{BlobStore, FsBlobStore};
        let dir = tempfile::tempdir().unwrap();
        let store = std::sync::Arc::new(FsBlobStore::open(dir.path()).unwrap());
        let pieces: Vec<Vec<u8>> = (0..40u8).map(|k| vec![k; 1000 + k as usize]).collect();
        let all: Vec<u8> = pieces.concat();
        let mut spool = Spool::new(all.len(), 5000, opener(&store));
        for p in &pieces {
            spool.push(Bytes::from(p.clone())).await.unwrap();
        }
        match spool.finish().await.unwrap() {
            Upload::Stored { hash, len } => {
                assert_eq!(len, all.len() as u64);
                assert_eq!(hash, blake3::hash(&all).to_hex().to_string());
                assert_eq!(store.get(&hash).unwrap().unwrap(), all);
            }
            other => panic!("{other:?}"),
        }
        let mut small = Spool::new(0, 5000, opener(&store));
        small.push(Bytes::from(vec![7u8; 4999])).await.unwrap();
        assert!(matches!(small.finish().await.unwrap(), Upload::Memory(v) if v.len() == 4999));
        // A body that fails half-way leaves no blob behind.
        let before = store.list().unwrap().len();
        let mut broken = Spool::new(0, 100, opener(&store));
        broken.push(Bytes::from(vec![1u8; 5000])).await.unwrap();
        drop(broken);
        tokio::time::sleep(Duration::from_millis(200)).await;
        assert_eq!(store.list().unwrap().len(), before);
    }

    #[tokio::test]
    async fn a_stalled_body_times_out() {
        let chunks = futures_util::stream::iter([Ok::<_, std::io::Error>(Bytes::from("ab"))])
            .chain(futures_util::stream::pending());
        let body = guarded(
            Body::from_stream(chunks),
            Bounds { limit: 1000, idle: Duration::from_millis(50), min_rate: 0 },
        );
        let err = axum::body::to_bytes(body, usize::MAX).await.unwrap_err();
        assert_eq!(fault(&err), BodyFault::TimedOut);
    }

    /// A drip (a byte a second: never a pause the idle timeout sees) is cut at the end of the
    /// first rate window when the minimum is 100 bytes/s, and read whole without a minimum; a
    /// body at a steady 2 KiB/s passes a minimum of 1 KiB/s over several windows.
    #[tokio::test(start_paused = true)]
    async fn a_drip_is_cut_at_the_minimum_rate() {
        let drip = |n: usize, every: Duration, size: usize| {
            futures_util::stream::iter(0..n).then(move |_| async move {
                tokio::time::sleep(every).await;
                Ok::<_, std::io::Error>(Bytes::from(vec![7u8; size]))
            })
        };
        let bounds = |min_rate| Bounds { limit: 1 << 20, idle: Duration::from_secs(5), min_rate };
        let t = tokio::time::Instant::now();
        let body = guarded(Body::from_stream(drip(60, Duration::from_secs(1), 1)), bounds(100));
        let err = axum::body::to_bytes(body, usize::MAX).await.unwrap_err();
        assert_eq!(fault(&err), BodyFault::TooSlow);
        let cut = t.elapsed();
        assert!(cut >= RATE_WINDOW && cut < RATE_WINDOW + Duration::from_secs(2), "{cut:?}");
        let body = guarded(Body::from_stream(drip(60, Duration::from_secs(1), 1)), bounds(0));
        assert_eq!(axum::body::to_bytes(body, usize::MAX).await.unwrap().len(), 60);
        let steady = drip(40, Duration::from_millis(500), 1024);
        let body = guarded(Body::from_stream(steady), bounds(1024));
        assert_eq!(axum::body::to_bytes(body, usize::MAX).await.unwrap().len(), 40 * 1024);
    }
}
