//! The connection under hyper: a socket wrapper that turns hyper's own bare error answers into
//! problem+json, so a client parses one error format even for requests hyper refuses before any
//! of our code runs.
//!
//! hyper answers a request head it cannot parse by itself (`on_parse_error`): 414 for a request
//! target over its fixed 65,534-byte limit (not configurable), 431 for a head over `max_buf_size`,
//! 400 for a malformed one. Those answers never reach a middleware; they are written straight to
//! the socket as a head with `connection: close` and `content-length: 0` and no body. Our own
//! limits (`max_uri_bytes`, `max_header_bytes`) sit below hyper's, so normally we answer first;
//! this covers what is above them.
//!
//! Why at the byte level: hyper offers no hook for these answers. The match is narrow: a whole
//! response head of status 400, 414 or 431 with `content-length: 0`, which no handler of ours
//! produces (every error of ours has a problem+json body), written as the first bytes of a
//! response. Everything else passes through untouched.

use crate::service::problem::{Problem, PROBLEM_JSON};
use axum::http::StatusCode;
use std::io;
use std::pin::Pin;
use std::task::{Context, Poll};
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};

/// A socket whose bare hyper error answers are rewritten (see the module docs).
#[derive(Debug)]
pub struct ProblemIo<T> {
    inner: T,
    /// A rewritten answer being written: its bytes, how many are out, and the length of the
    /// head it replaces (what hyper is told was written once all of it is out).
    pending: Option<(Vec<u8>, usize, usize)>,
}

impl<T> ProblemIo<T> {
    /// Wraps `inner`.
    pub fn new(inner: T) -> Self {
        ProblemIo { inner, pending: None }
    }
}

/// The problem+json answer that replaces hyper's bare `head`, if `head` is one.
pub fn rewrite(head: &[u8]) -> Option<Vec<u8>> {
    let text = std::str::from_utf8(head).ok()?;
    let rest = text.strip_prefix("HTTP/1.1 ")?;
    if !text.ends_with("\r\n\r\n") || text.matches("\r\n\r\n").count() != 1 {
        return None;
    }
    let lower = text.to_ascii_lowercase();
    if !lower.contains("\r\ncontent-length: 0\r\n") {
        return None;
    }
    let (status, code, detail) = match rest.get(..4)? {
        "414 " => (
            StatusCode::URI_TOO_LONG,
            "uri_too_long",
            "the request target is longer than the 65,534 bytes the HTTP parser accepts",
        ),
        "431 " => (
            StatusCode::REQUEST_HEADER_FIELDS_TOO_LARGE,
            "headers_too_large",
            "the request head is larger than the HTTP parser's buffer",
        ),
        "400 " => (
            StatusCode::BAD_REQUEST,
            "malformed_request",
            "the request line or a header could not be parsed as HTTP/1.1",
        ),
        _ => return None,
    };
    let body = serde_json::to_vec(&Problem::new(status, code, detail)).ok()?;
    let mut out = format!(
        "HTTP/1.1 {} {}\r\ncontent-type: {PROBLEM_JSON}\r\nconnection: close\r\n\
         content-length: {}\r\n",
        status.as_u16(),
        status.canonical_reason().unwrap_or("Error"),
        body.len()
    );
    // Keep hyper's other headers (its `date`).
    for line in text.split("\r\n").skip(1) {
        let l = line.to_ascii_lowercase();
        if !line.is_empty() && !l.starts_with("content-length:") && !l.starts_with("connection:") {
            out.push_str(line);
            out.push_str("\r\n");
        }
    }
    out.push_str("\r\n");
    let mut out = out.into_bytes();
    out.extend_from_slice(&body);
    Some(out)
}

impl<T: AsyncWrite + Unpin> ProblemIo<T> {
    /// Writes the pending rewritten answer; Ready(n) with the replaced head's length when done.
    fn drive(&mut self, cx: &mut Context<'_>) -> Poll<io::Result<usize>> {
        while let Some((bytes, done, replaced)) = &mut self.pending {
            if *done == bytes.len() {
                let n = *replaced;
                self.pending = None;
                return Poll::Ready(Ok(n));
            }
            match Pin::new(&mut self.inner).poll_write(cx, &bytes[*done..]) {
                Poll::Ready(Ok(0)) => return Poll::Ready(Err(io::ErrorKind::WriteZero.into())),
                Poll::Ready(Ok(n)) => *done += n,
                Poll::Ready(Err(e)) => {
                    self.pending = None;
                    return Poll::Ready(Err(e));
                }
                Poll::Pending => return Poll::Pending,
            }
        }
        Poll::Ready(Ok(0))
    }

    /// Starts a rewrite if `buf` is a bare hyper error head.
    fn check(&mut self, buf: &[u8]) -> bool {
        if self.pending.is_none() && buf.starts_with(b"HTTP/1.1 4") {
            if let Some(out) = rewrite(buf) {
                self.pending = Some((out, 0, buf.len()));
                return true;
            }
        }
        self.pending.is_some()
    }
}

impl<T: AsyncRead + Unpin> AsyncRead for ProblemIo<T> {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        Pin::new(&mut self.inner).poll_read(cx, buf)
    }
}

impl<T: AsyncWrite + Unpin> AsyncWrite for ProblemIo<T> {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        if self.check(buf) {
            return self.drive(cx);
        }
        Pin::new(&mut self.inner).poll_write(cx, buf)
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        // hyper writes such a head alone, as the only non-empty slice.
        let mut nonempty = bufs.iter().filter(|b| !b.is_empty());
        if let (Some(first), None) = (nonempty.next(), nonempty.next()) {
            if self.check(first) {
                return self.drive(cx);
            }
        } else if self.pending.is_some() {
            return self.drive(cx);
        }
        Pin::new(&mut self.inner).poll_write_vectored(cx, bufs)
    }

    fn is_write_vectored(&self) -> bool {
        self.inner.is_write_vectored()
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.inner).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.inner).poll_shutdown(cx)
    }
}

#[cfg(test)]
mod tests {
    use super::rewrite;

    #[test]
    fn only_bare_parser_answers_are_rewritten() {
        let bare = b"HTTP/1.1 414 URI Too Long\r\nconnection: close\r\ncontent-length: 0\r\n\
                     date: Mon, 30 Nov 2026 05:55:21 GMT\r\n\r\n";
        let out = String::from_utf8(rewrite(bare).expect("rewritten")).unwrap();
        let (head, body) = out.split_once("\r\n\r\n").unwrap();
        assert!(head.starts_with("HTTP/1.1 414 URI Too Long\r\n"), "{head}");
        assert!(head.contains("content-type: application/problem+json"), "{head}");
        assert!(head.contains("date: Mon, 30 Nov 2026"), "{head}");
        assert!(head.contains(&format!("content-length: {}", body.len())), "{head}");
        let v: serde_json::Value = serde_json::from_str(body).unwrap();
        assert_eq!((v["status"].as_u64(), v["code"].as_str()), (Some(414), Some("uri_too_long")));
        // Not bare (a body follows), another status, a body in the same buffer, or not a head.
        for not in [
            &b"HTTP/1.1 414 URI Too Long\r\ncontent-length: 120\r\n\r\n"[..],
            b"HTTP/1.1 404 Not Found\r\ncontent-length: 0\r\n\r\n",
            b"HTTP/1.1 400 Bad Request\r\ncontent-length: 0\r\n\r\n\r\n\r\n",
            b"HTTP/1.1 431 Request Header Fields Too Large\r\ncontent-length: 0\r\n",
        ] {
            assert!(rewrite(not).is_none(), "{}", String::from_utf8_lossy(not));
        }
    }
}
