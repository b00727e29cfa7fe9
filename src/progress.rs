//! Progress reporting and cooperative cancellation shared by a bake and whoever watches it.
//!
//! Kernels run on rayon threads and must not know about HTTP or terminals, so they only bump an
//! atomic counter between bands of rows and poll an atomic flag. The service reads the counter for
//! `progress` and SSE; the CLI drives a progress bar from it; `DELETE` sets the flag.
//!
//! It also carries where the bake may put scratch files (`sweep`'s spilled far field): the
//! runner that starts a bake knows that place (the service's data directory), the kernel that
//! needs it does not, and the handle is the one thing that travels from one to the other.

use std::sync::atomic::{AtomicBool, AtomicU64, AtomicU8, Ordering};
use std::sync::Arc;

/// The stage a bake is in, reported beside the fraction.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Stage {
    Queued,
    Decode,
    Bake,
    Fourier,
    Encode,
    Store,
    Done,
}

impl Stage {
    const ALL: [Stage; 7] = [
        Stage::Queued,
        Stage::Decode,
        Stage::Bake,
        Stage::Fourier,
        Stage::Encode,
        Stage::Store,
        Stage::Done,
    ];
}

/// Shared, lock-free progress of one bake. Cheap to clone (an `Arc`).
#[derive(Debug, Clone, Default)]
pub struct Progress {
    inner: Arc<Inner>,
}

#[derive(Debug, Default)]
struct Inner {
    done: AtomicU64,
    total: AtomicU64,
    stage: AtomicU8,
    cancel: AtomicBool,
    /// Where scratch files go; `None`: the system's temporary directory.
    scratch: Option<std::path::PathBuf>,
}

impl Progress {
    pub fn new() -> Self {
        Self::default()
    }

    /// A handle whose bake puts its scratch files in `dir` (`None`: the system's temporary
    /// directory, `TMPDIR`).
    pub fn with_scratch_dir(dir: Option<std::path::PathBuf>) -> Self {
        Progress { inner: Arc::new(Inner { scratch: dir, ..Inner::default() }) }
    }

    /// The directory this bake's scratch files go to.
    pub fn scratch_dir(&self) -> std::path::PathBuf {
        self.inner.scratch.clone().unwrap_or_else(std::env::temp_dir)
    }

    /// Enters `stage` with `total` units of work to do.
    pub fn start(&self, stage: Stage, total: u64) {
        self.inner.total.store(total.max(1), Ordering::Relaxed);
        self.inner.done.store(0, Ordering::Relaxed);
        self.inner.stage.store(stage as u8, Ordering::Relaxed);
    }

    /// Marks `n` more units of the current stage done.
    pub fn advance(&self, n: u64) {
        self.inner.done.fetch_add(n, Ordering::Relaxed);
    }

    /// The current stage.
    pub fn stage(&self) -> Stage {
        Stage::ALL[(self.inner.stage.load(Ordering::Relaxed) as usize).min(Stage::ALL.len() - 1)]
    }

    /// Fraction of the current stage done, in [0, 1].
    pub fn fraction(&self) -> f64 {
        let total = self.inner.total.load(Ordering::Relaxed).max(1);
        let done = self.inner.done.load(Ordering::Relaxed).min(total);
        done as f64 / total as f64
    }

    /// (done, total) units of the current stage.
    pub fn counts(&self) -> (u64, u64) {
        (self.inner.done.load(Ordering::Relaxed), self.inner.total.load(Ordering::Relaxed))
    }

    /// Asks the bake to stop at its next check.
    pub fn cancel(&self) {
        self.inner.cancel.store(true, Ordering::Relaxed);
    }

    /// Whether cancellation was asked for.
    pub fn is_canceled(&self) -> bool {
        self.inner.cancel.load(Ordering::Relaxed)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fraction_tracks_advance_and_clamps() {
        let p = Progress::new();
        p.start(Stage::Bake, 4);
        assert_eq!(p.fraction(), 0.0);
        p.advance(1);
        assert_eq!(p.fraction(), 0.25);
        p.advance(10);
        assert_eq!(p.fraction(), 1.0);
        assert_eq!(p.stage(), Stage::Bake);
        assert!(!p.is_canceled());
        p.clone().cancel();
        assert!(p.is_canceled());
    }

    #[test]
    fn scratch_dir_is_the_one_given_and_travels_with_clones() {
        assert_eq!(Progress::new().scratch_dir(), std::env::temp_dir());
        let p = Progress::with_scratch_dir(Some("/srv/hb/tmp".into()));
        assert_eq!(p.clone().scratch_dir(), std::path::PathBuf::from("/srv/hb/tmp"));
    }
}
