//! A field of this process's `/proc/self/status` (Linux), in its unit (kB for the `Vm*` lines):
//! the peak and current resident memory the memory benches and tests read. Shared by path
//! (`#[path]`) between bench binaries and a test, which are separate crates.

/// The number after `key` (e.g. `"VmHWM:"`), 0 where there is none.
pub fn status(key: &str) -> u64 {
    let s = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    s.lines()
        .find(|l| l.starts_with(key))
        .and_then(|l| l.split_whitespace().nth(1))
        .and_then(|v| v.parse().ok())
        .unwrap_or(0)
}
