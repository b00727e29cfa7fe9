//! An upload's body, read under the service's bounds.
//!
//! Two ways a client can hold server resources without sending anything must both end:
//! - a pause: every piece of the body must arrive within `body_timeout` of the previous one (an
//!   idle timeout, not a total one, so a large upload on a slow link still gets through), else
//!   the stream fails with [`BodyTimedOut`] and the handler answers 408, freeing its upload slot;
//! - a body over `max_body_bytes`: the stream fails with [`BodyTooLarge`], but only after reading
//!   and discarding the rest of the body (at most [`DRAIN_BOUND`] more bytes, each piece within
//!   the idle timeout). Answering while the client is still sending makes the connection close
//!   under it, and most clients then report a reset instead of the 413.
//!
//! (Unfinished request headers are hyper's to time out: see [`crate::service::serve`].)

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

/// The body is larger than the limit.
#[derive(Debug, thiserror::Error)]
#[error("the request body is larger than {0} bytes")]
pub struct BodyTooLarge(pub u64);

/// What went wrong reading a body, found anywhere in an error's source chain.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BodyFault {
    TimedOut,
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

/// `body` with the idle timeout and the size limit applied (see the module documentation).
pub fn guarded(body: Body, limit: u64, idle: Duration) -> Body {
    let start = Some((body.into_data_stream(), 0u64));
    let stream = futures_util::stream::unfold(start, move |state| async move {
        let (mut s, seen) = state?;
        let item: Result<Bytes, axum::BoxError> = match tokio::time::timeout(idle, s.next()).await {
            Err(_) => Err(BodyTimedOut(idle).into()),
            Ok(None) => return None,
            Ok(Some(Err(e))) => Err(e.into()),
            Ok(Some(Ok(chunk))) => {
                let seen = seen + chunk.len() as u64;
                if seen > limit {
                    drain(&mut s, idle, DRAIN_BOUND).await;
                    Err(BodyTooLarge(limit).into())
                } else {
                    return Some((Ok(chunk), Some((s, seen))));
                }
            }
        };
        // After an error the stream ends.
        Some((item, None))
    });
    Body::from_stream(stream)
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
        let body = guarded(Body::from_stream(chunks), 250, Duration::from_secs(5));
        let err = axum::body::to_bytes(body, usize::MAX).await.unwrap_err();
        assert_eq!(fault(&err), BodyFault::TooLarge);
        assert_eq!(read.load(std::sync::atomic::Ordering::SeqCst), 10, "the rest was not drained");
        let ok = guarded(Body::from(vec![1u8; 250]), 250, Duration::from_secs(5));
        assert_eq!(axum::body::to_bytes(ok, usize::MAX).await.unwrap().len(), 250);
    }

    #[tokio::test]
    async fn a_stalled_body_times_out() {
        let chunks = futures_util::stream::iter([Ok::<_, std::io::Error>(Bytes::from("ab"))])
            .chain(futures_util::stream::pending());
        let body = guarded(Body::from_stream(chunks), 1000, Duration::from_millis(50));
        let err = axum::body::to_bytes(body, usize::MAX).await.unwrap_err();
        assert_eq!(fault(&err), BodyFault::TimedOut);
    }
}
