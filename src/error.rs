//! The library's one error type.
//!
//! Every fallible function in the crate returns [`Error`]. Its variants say whose fault a failure
//! is (the input's, a parameter's, a limit's, the machine's), because that is what decides the
//! HTTP status and the CLI's message: the service maps each variant to a problem+json answer with
//! a stable `code` (see `service::problem`), the CLI prints the `Display` text on one line.

use std::fmt;

/// Result alias used throughout the library.
pub type Result<T, E = Error> = std::result::Result<T, E>;

/// What went wrong, and whose fault it is.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The bytes are an image format we read, but they are broken (truncated, corrupt).
    #[error("cannot decode the height map: {0}")]
    Decode(String),
    /// Not an image, or an image format / pixel layout we do not read (e.g. JPEG).
    #[error("unsupported input: {0}")]
    Unsupported(String),
    /// The image decodes but its content is unusable (NaN heights, 0×0, ...).
    #[error("invalid height map: {0}")]
    InvalidInput(String),
    /// A parameter is out of range or malformed; `field` names it as the API spells it.
    #[error("invalid parameter `{field}`: {message}")]
    Param { field: String, message: String },
    /// The input exceeds a configured limit (dimensions, pixels, bytes).
    #[error("limit exceeded: {0}")]
    Limits(LimitError),
    /// The bake was canceled by its owner.
    #[error("canceled")]
    Canceled,
    /// File-system or other I/O failure on our side (an I/O error that carries an object
    /// storage failure becomes [`Error::Unavailable`]: see the `From<std::io::Error>` impl).
    #[error("I/O error: {0}")]
    Io(std::io::Error),
    /// A bug or an unexpected internal failure (a caught panic, an encoder that refused).
    #[error("internal error: {0}")]
    Internal(String),
    /// A backing service (the database, object storage) cannot be reached right now; the
    /// request may succeed later. Never the input's fault.
    #[error("temporarily unavailable: {0}")]
    Unavailable(String),
    /// A store has no space left (ENOSPC or a quota: `ErrorKind::StorageFull`); `store` names
    /// which, `cause` is the underlying error (logged, not shown to a client). Writes succeed
    /// again once space is freed.
    #[error("{store} is full: {cause}")]
    StorageFull { store: &'static str, cause: String },
    /// A decode could not reserve its estimated peak memory from the process-wide decode budget
    /// within its wait: other decodes hold it. Retrying shortly succeeds once they finish.
    #[error(
        "the server's decode memory is busy: this input needs about {} MiB to decode, and \
         {} MiB of the {} MiB decode budget (--decode-memory-bytes) are held by other decodes; \
         retry shortly",
        mib(*needed), mib(*in_use), mib(*budget)
    )]
    MemoryBusy { needed: u64, in_use: u64, budget: u64 },
}

/// `bytes` in MiB with one decimal, for messages.
pub fn mib(bytes: u64) -> String {
    format!("{:.1}", bytes as f64 / (1024.0 * 1024.0))
}

/// Which limit an input broke, with the numbers, so the message can say by how much.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum LimitError {
    /// Width or height over the configured maximum.
    Dimensions { width: u64, height: u64, max_dim: u32 },
    /// Width × height over the configured maximum texel count.
    Texels { texels: u64, max_texels: u64 },
    /// Encoded input larger than allowed.
    Bytes { bytes: u64, max_bytes: u64 },
    /// The memory a decode would hold at its peak (estimated from the header) over the
    /// per-request decode budget.
    DecodeBytes { estimate: u64, max_decode_bytes: u64 },
}

impl fmt::Display for LimitError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            LimitError::Dimensions { width, height, max_dim } => {
                write!(f, "image is {width}×{height}, each side must be at most {max_dim} texels")
            }
            LimitError::Texels { texels, max_texels } => {
                write!(f, "image has {texels} texels, at most {max_texels} are allowed")
            }
            LimitError::Bytes { bytes, max_bytes } => {
                write!(f, "input is {bytes} bytes, at most {max_bytes} are allowed")
            }
            LimitError::DecodeBytes { estimate, max_decode_bytes } => write!(
                f,
                "decoding this image would hold about {} MiB, over the decode budget of {} MiB \
                 per request (--max-decode-bytes)",
                mib(*estimate),
                mib(*max_decode_bytes)
            ),
        }
    }
}

impl Error {
    /// A parameter error naming `field`.
    pub fn param(field: impl Into<String>, message: impl Into<String>) -> Self {
        Error::Param { field: field.into(), message: message.into() }
    }

    /// Process exit code for the CLI: 2 for the caller's mistakes (input, parameters, limits),
    /// 130 for a cancel, 1 for our own failures.
    pub fn exit_code(&self) -> u8 {
        match self {
            Error::Decode(_)
            | Error::Unsupported(_)
            | Error::InvalidInput(_)
            | Error::Param { .. }
            | Error::Limits(_) => 2,
            Error::Canceled => 130,
            Error::Io(_)
            | Error::Internal(_)
            | Error::Unavailable(_)
            | Error::StorageFull { .. }
            | Error::MemoryBusy { .. } => 1,
        }
    }

    /// A stable, machine-readable code for this error (used as problem+json `code`).
    pub fn code(&self) -> &'static str {
        match self {
            Error::Decode(_) => "decode_failed",
            Error::Unsupported(_) => "unsupported_media_type",
            Error::InvalidInput(_) => "invalid_input",
            Error::Param { .. } => "invalid_parameter",
            Error::Limits(LimitError::Bytes { .. }) => "payload_too_large",
            Error::Limits(_) => "dimensions_too_large",
            Error::Canceled => "canceled",
            Error::Io(_) => "io_error",
            Error::Internal(_) => "internal",
            Error::Unavailable(_) => "store_unavailable",
            Error::StorageFull { .. } => "insufficient_storage",
            Error::MemoryBusy { .. } => "decode_memory_busy",
        }
    }
}

impl From<std::io::Error> for Error {
    /// The S3 store's streamed readers and writers speak `std::io` (a bake writes its layers
    /// through them, the split its tile windows), so an object-storage failure in the middle of
    /// a stream arrives as an I/O error. It is the store being away (a 5xx after the client's
    /// retries, a full volume, a dropped connection), never the bake's fault: it becomes
    /// [`Error::Unavailable`], so the job goes back to the queue (a bounded number of times)
    /// instead of failing as an internal error, as a failed whole-blob put already did.
    fn from(e: std::io::Error) -> Self {
        if let Some(s) = e.get_ref().and_then(|i| i.downcast_ref::<object_store::Error>()) {
            return Error::Unavailable(format!("object storage: {s}"));
        }
        if is_storage_full(&e) {
            return Error::StorageFull { store: "the data directory", cause: e.to_string() };
        }
        Error::Io(e)
    }
}

/// Whether `e` is a full disk or an exhausted quota (ENOSPC, EDQUOT).
pub fn is_storage_full(e: &std::io::Error) -> bool {
    const ENOSPC: i32 = 28;
    const EDQUOT: i32 = 122;
    e.kind() == std::io::ErrorKind::StorageFull
        || e.kind() == std::io::ErrorKind::QuotaExceeded
        || matches!(e.raw_os_error(), Some(ENOSPC | EDQUOT))
}

#[cfg(test)]
mod io_tests {
    use super::Error;

    /// Found by the tiles bench: weed ran out of volumes mid-upload, the S3 writer's part PUT
    /// failed with a 500, and the bake failed as `io_error` ("an internal error occurred")
    /// instead of going back to the queue like a failed whole-blob put.
    #[test]
    fn an_object_storage_failure_inside_a_stream_is_unavailable_not_io() {
        let store = object_store::Error::Generic {
            store: "S3",
            source: "Server returned non-2xx status code: 500 Internal Server Error".into(),
        };
        let e: Error = std::io::Error::other(store).into();
        assert!(matches!(&e, Error::Unavailable(m) if m.contains("500")), "{e:?}");
        assert_eq!(e.code(), "store_unavailable");
        // Plain I/O stays I/O.
        let e: Error = std::io::Error::new(std::io::ErrorKind::PermissionDenied, "no").into();
        assert!(matches!(e, Error::Io(_)), "{e:?}");
    }
}
