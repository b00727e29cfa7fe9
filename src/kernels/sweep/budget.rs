//! Memory budgets of the far-field table: when it stays in memory, when it goes to a
//! [`FarSpill`] store, and the largest bake [`check_memory`] accepts.

use super::*;

/// Most bytes the far-field table may take in memory (4·bins bytes per texel: a 2048² map at
/// 32 bins); a bigger one waits in a [`FarSpill`] store instead, so that the process stays
/// within about 1.5 GB for the largest map the service takes (8192² at any bins).
pub const MAX_TABLE_BYTES: u64 = 512 << 20;

/// Most bytes the planes being swept may take when the table is spilled (up to 3 planes of
/// W·H f32 per azimuth in flight: the plane, the missing weights and the transposed sums), so
/// fewer azimuths run at once on a big map: one at 8192², two (on two threads) at 4096².
pub(super) const SPILL_SWEEP_BYTES: usize = 768 << 20;

/// Most bytes the second azimuth of a pair may add to the sweeps' scratch over all threads
/// (its sums and missing weights, 2 planes of W·H f32 per thread): 2048² pairs on 2 threads
/// with 64 MiB, 4096² with 256 MiB; bigger maps sweep each azimuth alone, as before.
pub(super) const PAIR_SCRATCH_BYTES: usize = 256 << 20;

/// Most bytes a spilled table may take on disk: 32 GiB, an 8192² map at 128 bins.
pub const MAX_SPILL_BYTES: u64 = 32 << 30;

/// The bytes of the far-field table of a `width` × `height` map at `bins` azimuths.
pub fn table_bytes(width: u32, height: u32, bins: u32) -> u64 {
    u64::from(width) * u64::from(height) * u64::from(bins.max(1)) * 4
}

/// Whether a bake of this size should give the kernel a [`FarSpill`] store (its table would
/// pass [`MAX_TABLE_BYTES`]).
pub fn spills(width: u32, height: u32, bins: u32) -> bool {
    table_bytes(width, height, bins) > MAX_TABLE_BYTES
}

/// Keeps the first failure of the spill store and says there is one.
pub(super) fn record(
    failure: &Mutex<Option<(std::io::ErrorKind, String)>>,
    failed: &AtomicBool,
    e: std::io::Error,
) {
    if let Ok(mut f) = failure.lock() {
        f.get_or_insert_with(|| (e.kind(), e.to_string()));
    }
    failed.store(true, Ordering::Relaxed);
}

/// A spill failure as the bake's error: a full disk is a condition to retry later (`Unavailable`,
/// so a queued bake goes back to the queue a bounded number of times), anything else an I/O error.
pub(super) fn spill_error(e: std::io::Error) -> crate::error::Error {
    if e.kind() == std::io::ErrorKind::StorageFull {
        crate::error::Error::Unavailable(format!(
            "method=sweep could not write its far field to disk (no space left): {e}"
        ))
    } else {
        crate::error::Error::Io(std::io::Error::new(
            e.kind(),
            format!("method=sweep's far field on disk: {e}"),
        ))
    }
}

/// Refuses a `width` × `height` map at `bins` azimuths whose far-field table would exceed
/// [`MAX_SPILL_BYTES`] even on disk, before anything is decoded or queued.
///
/// # Errors
/// [`Error::Param`] naming `method`, with the size and what to use instead.
pub fn check_memory(width: u32, height: u32, bins: u32) -> crate::error::Result<()> {
    let bytes = table_bytes(width, height, bins.max(8));
    if bytes > MAX_SPILL_BYTES {
        return Err(crate::error::Error::param(
            "method",
            format!(
                "method=sweep keeps its far field for the whole map (in memory up to {} MiB, \
                 beyond that in a temporary file), width × height × bins × 4 bytes = {} MiB for \
                 this {width}×{height} map at {} bins, over the {} MiB it may use; use fewer \
                 bins, or method=march with a finite radius or max_distance, or method=exact",
                MAX_TABLE_BYTES >> 20,
                bytes >> 20,
                bins.max(8),
                MAX_SPILL_BYTES >> 20
            ),
        ));
    }
    Ok(())
}
