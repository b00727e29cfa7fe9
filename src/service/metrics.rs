//! Prometheus metrics, written by hand in the text exposition format (a handful of counters,
//! gauges and one histogram do not need a metrics framework).
//!
//! - `horizon_http_requests_total{route,method,status}`: every answered request, by the matched
//!   route template (never the raw path, so ids do not explode the label set).
//! - `horizon_bakes{status}`: bakes currently stored, by status (read from the store).
//! - `horizon_bakes_finished_total{status}`, `horizon_bakes_submitted_total`,
//!   `horizon_bakes_deduplicated_total`.
//! - `horizon_queue_depth`, `horizon_bakes_running`.
//! - `horizon_bake_duration_seconds` (histogram, from a worker taking a bake to its outcome).
//! - `horizon_texels_baked_total`.
//! - `horizon_results_encoded_total`: result files encoded on their first request (png16, EXR,
//!   KTX2, DDS are not encoded with the bake; see `pipeline::job`).
//! - `horizon_renders_total{kind}`: previews (`preview`) and cube-map files (`cube`) computed,
//!   so an operator (and a test) can see that a revalidation answered 304 computed nothing.

use crate::jobs::record::Status;
use std::collections::BTreeMap;
use std::fmt::Write;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Mutex;

/// Upper bounds of the bake-duration histogram, in seconds.
pub const DURATION_BUCKETS: [f64; 12] =
    [0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0, 120.0, 300.0];

/// All counters of one server.
#[derive(Debug, Default)]
pub struct Metrics {
    http: Mutex<BTreeMap<(String, String, u16), u64>>,
    finished: [AtomicU64; 5],
    submitted: AtomicU64,
    deduplicated: AtomicU64,
    buckets: [AtomicU64; DURATION_BUCKETS.len()],
    duration_count: AtomicU64,
    duration_sum_us: AtomicU64,
    texels: AtomicU64,
    encoded: AtomicU64,
    renders: [AtomicU64; 2],
    /// Tiles this node ran, by how they ended ([`TILE_LABELS`]).
    tiles: [AtomicU64; 5],
}

/// How a tile this node ran ended (`horizon_tiles_total{status=…}`): `lost` is a tile whose
/// outcome was refused because another worker took it over (its lease ran out).
pub const TILE_LABELS: [&str; 5] = ["succeeded", "failed", "canceled", "released", "lost"];

/// What a render counted by [`Metrics::rendered`] produced.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Render {
    /// A shading preview of a bake.
    Preview,
    /// A cube-map face or texture.
    Cube,
}

impl Render {
    const ALL: [Render; 2] = [Render::Preview, Render::Cube];

    fn label(self) -> &'static str {
        match self {
            Render::Preview => "preview",
            Render::Cube => "cube",
        }
    }
}

fn status_index(s: Status) -> usize {
    Status::ALL.iter().position(|x| *x == s).unwrap_or(0)
}

impl Metrics {
    /// Counts one answered request.
    pub fn http(&self, route: &str, method: &str, status: u16) {
        let mut g = self.http.lock().unwrap_or_else(|e| e.into_inner());
        *g.entry((route.to_owned(), method.to_owned(), status)).or_insert(0) += 1;
    }

    /// Counts an accepted submission (or a deduplicated one).
    pub fn submitted(&self, deduplicated: bool) {
        if deduplicated {
            self.deduplicated.fetch_add(1, Ordering::Relaxed);
        } else {
            self.submitted.fetch_add(1, Ordering::Relaxed);
        }
    }

    /// Counts a bake reaching `status`, with its duration and texel count.
    pub fn finished(&self, status: Status, seconds: f64, texels: u64) {
        self.finished[status_index(status)].fetch_add(1, Ordering::Relaxed);
        if status == Status::Succeeded {
            self.texels.fetch_add(texels, Ordering::Relaxed);
        }
        for (b, le) in self.buckets.iter().zip(DURATION_BUCKETS) {
            if seconds <= le {
                b.fetch_add(1, Ordering::Relaxed);
            }
        }
        self.duration_count.fetch_add(1, Ordering::Relaxed);
        self.duration_sum_us.fetch_add((seconds * 1e6) as u64, Ordering::Relaxed);
    }

    /// Counts a tile this node ran, by how it ended (one of [`TILE_LABELS`]).
    pub fn tile(&self, label: &str) {
        if let Some(i) = TILE_LABELS.iter().position(|l| *l == label) {
            self.tiles[i].fetch_add(1, Ordering::Relaxed);
        }
    }

    /// Counts a result encoded on its first request.
    pub fn encoded_on_request(&self) {
        self.encoded.fetch_add(1, Ordering::Relaxed);
    }

    /// Counts a preview or cube-map file computed (not answered 304).
    pub fn rendered(&self, kind: Render) {
        self.renders[kind as usize].fetch_add(1, Ordering::Relaxed);
    }

    /// Mean bake duration so far, in seconds (for `Retry-After`), if any bake finished.
    pub fn mean_duration(&self) -> Option<f64> {
        let n = self.duration_count.load(Ordering::Relaxed);
        (n > 0).then(|| self.duration_sum_us.load(Ordering::Relaxed) as f64 / 1e6 / n as f64)
    }

    /// The exposition text. `stored` = bakes in the store by status.
    pub fn render(&self, stored: &[(Status, u64)], queue_depth: usize, running: usize) -> String {
        let mut s = String::new();
        let _ = writeln!(s, "# HELP horizon_http_requests_total HTTP requests answered.");
        let _ = writeln!(s, "# TYPE horizon_http_requests_total counter");
        for ((route, method, status), n) in
            self.http.lock().unwrap_or_else(|e| e.into_inner()).iter()
        {
            let _ = writeln!(
                s,
                "horizon_http_requests_total{{route=\"{route}\",method=\"{method}\",status=\"{status}\"}} {n}"
            );
        }
        let _ = writeln!(s, "# HELP horizon_bakes Bakes in the store, by status.");
        let _ = writeln!(s, "# TYPE horizon_bakes gauge");
        for (st, n) in stored {
            let _ = writeln!(s, "horizon_bakes{{status=\"{}\"}} {n}", st.as_str());
        }
        let _ =
            writeln!(s, "# HELP horizon_bakes_finished_total Bakes that reached a final state.");
        let _ = writeln!(s, "# TYPE horizon_bakes_finished_total counter");
        for st in [Status::Succeeded, Status::Failed, Status::Canceled] {
            let n = self.finished[status_index(st)].load(Ordering::Relaxed);
            let _ = writeln!(s, "horizon_bakes_finished_total{{status=\"{}\"}} {n}", st.as_str());
        }
        let _ =
            writeln!(s, "# HELP horizon_bakes_submitted_total Submissions that created a bake.");
        let _ = writeln!(s, "# TYPE horizon_bakes_submitted_total counter");
        let _ =
            writeln!(s, "horizon_bakes_submitted_total {}", self.submitted.load(Ordering::Relaxed));
        let _ = writeln!(
            s,
            "# HELP horizon_bakes_deduplicated_total Submissions answered with an existing bake."
        );
        let _ = writeln!(s, "# TYPE horizon_bakes_deduplicated_total counter");
        let _ = writeln!(
            s,
            "horizon_bakes_deduplicated_total {}",
            self.deduplicated.load(Ordering::Relaxed)
        );
        let _ = writeln!(s, "# HELP horizon_queue_depth Bakes waiting for a worker.");
        let _ = writeln!(s, "# TYPE horizon_queue_depth gauge");
        let _ = writeln!(s, "horizon_queue_depth {queue_depth}");
        let _ = writeln!(s, "# HELP horizon_bakes_running Bakes on the bake pool now.");
        let _ = writeln!(s, "# TYPE horizon_bakes_running gauge");
        let _ = writeln!(s, "horizon_bakes_running {running}");
        let _ = writeln!(
            s,
            "# HELP horizon_bake_duration_seconds Time from a worker taking a bake to its outcome."
        );
        let _ = writeln!(s, "# TYPE horizon_bake_duration_seconds histogram");
        for (b, le) in self.buckets.iter().zip(DURATION_BUCKETS) {
            let _ = writeln!(
                s,
                "horizon_bake_duration_seconds_bucket{{le=\"{le}\"}} {}",
                b.load(Ordering::Relaxed)
            );
        }
        let count = self.duration_count.load(Ordering::Relaxed);
        let _ = writeln!(s, "horizon_bake_duration_seconds_bucket{{le=\"+Inf\"}} {count}");
        let _ = writeln!(
            s,
            "horizon_bake_duration_seconds_sum {}",
            self.duration_sum_us.load(Ordering::Relaxed) as f64 / 1e6
        );
        let _ = writeln!(s, "horizon_bake_duration_seconds_count {count}");
        let _ = writeln!(s, "# HELP horizon_texels_baked_total Texels of succeeded bakes.");
        let _ = writeln!(s, "# TYPE horizon_texels_baked_total counter");
        let _ = writeln!(s, "horizon_texels_baked_total {}", self.texels.load(Ordering::Relaxed));
        let _ = writeln!(
            s,
            "# HELP horizon_results_encoded_total Result files encoded on their first request."
        );
        let _ = writeln!(s, "# TYPE horizon_results_encoded_total counter");
        let _ =
            writeln!(s, "horizon_results_encoded_total {}", self.encoded.load(Ordering::Relaxed));
        let _ = writeln!(
            s,
            "# HELP horizon_renders_total Previews and cube-map files computed (a 304 computes none)."
        );
        let _ = writeln!(s, "# TYPE horizon_renders_total counter");
        for kind in Render::ALL {
            let n = self.renders[kind as usize].load(Ordering::Relaxed);
            let _ = writeln!(s, "horizon_renders_total{{kind=\"{}\"}} {n}", kind.label());
        }
        let _ = writeln!(
            s,
            "# HELP horizon_tiles_total Tiles of tiled bakes this node ran, by how they ended."
        );
        let _ = writeln!(s, "# TYPE horizon_tiles_total counter");
        for (label, n) in TILE_LABELS.iter().zip(&self.tiles) {
            let _ = writeln!(
                s,
                "horizon_tiles_total{{status=\"{label}\"}} {}",
                n.load(Ordering::Relaxed)
            );
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn histogram_is_cumulative_and_counters_add_up() {
        let m = Metrics::default();
        m.finished(Status::Succeeded, 0.3, 100);
        m.finished(Status::Failed, 7.0, 100);
        m.http("/v1/bakes", "POST", 202);
        m.http("/v1/bakes", "POST", 202);
        let text = m.render(&[(Status::Queued, 3)], 2, 1);
        assert!(text.contains("horizon_bake_duration_seconds_bucket{le=\"0.25\"} 0\n"));
        assert!(text.contains("horizon_bake_duration_seconds_bucket{le=\"0.5\"} 1\n"));
        assert!(text.contains("horizon_bake_duration_seconds_bucket{le=\"10\"} 2\n"));
        assert!(text.contains("horizon_bake_duration_seconds_count 2\n"));
        assert!(text.contains("horizon_texels_baked_total 100\n"));
        assert!(text.contains(
            "horizon_http_requests_total{route=\"/v1/bakes\",method=\"POST\",status=\"202\"} 2\n"
        ));
        assert!(text.contains("horizon_bakes{status=\"queued\"} 3\n"));
        assert!(text.contains("horizon_queue_depth 2\n"));
        assert_eq!(m.mean_duration(), Some(3.65));
    }
}
