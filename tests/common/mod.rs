//! Helpers shared by the integration tests.
#![allow(dead_code)]

use horizon_bake::kernels::{Grid, HorizonRows};
use horizon_bake::params::Edge;
use std::path::PathBuf;

/// The golden files, kept in the repository (tests/golden: a copy of the shared acceptance set), so
/// a lone clone passes its tests; `HORIZON_GOLDEN_DIR` points at another copy instead.
pub fn golden_dir() -> PathBuf {
    if let Ok(d) = std::env::var("HORIZON_GOLDEN_DIR") {
        return PathBuf::from(d);
    }
    let d = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/golden");
    assert!(
        d.join("cases.json").exists(),
        "golden files not found at {} (set HORIZON_GOLDEN_DIR)",
        d.display()
    );
    d
}

/// Whether python3 with rasterio and numpy (GDAL, for reading our GeoTIFFs back) is here; when
/// it is not, says so (the caller skips its read-back), except under `CI=true`, where that is
/// a failure.
pub fn has_rasterio() -> bool {
    let ci = std::env::var("CI").is_ok_and(|v| v == "true");
    let has = std::process::Command::new("python3")
        .args(["-c", "import rasterio, numpy"])
        .status()
        .is_ok_and(|s| s.success());
    if !has {
        assert!(!ci, "CI=true: python3 with rasterio and numpy is required (pip install rasterio)");
        eprintln!("skipped the GDAL read-back: python3 with rasterio is missing");
    }
    has
}

/// Little-endian f32 file.
pub fn read_f32(path: &std::path::Path) -> Vec<f32> {
    let b = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    b.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect()
}

/// A tiny deterministic RNG (SplitMix64) so property tests need no extra crates to reproduce.
pub struct Rng(pub u64);
impl Rng {
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    pub fn f32(&mut self) -> f32 {
        (self.next_u64() >> 40) as f32 / (1u64 << 24) as f32
    }
    pub fn range(&mut self, lo: usize, hi: usize) -> usize {
        lo + (self.next_u64() % (hi - lo + 1) as u64) as usize
    }
}

/// The bilinear surface at image point (X, Y): wrapped, or on [0, W−1]×[0, H−1] for edge=none.
pub fn surface(g: &Grid<'_>, x: f64, y: f64) -> f64 {
    let (w, h) = (g.width as i64, g.height as i64);
    let cell = |p: f64, n: i64| -> (i64, f64) {
        let mut c = p.floor() as i64;
        if g.edge == Edge::None {
            c = c.clamp(0, (n - 2).max(0));
        }
        (c, p - c as f64)
    };
    let (cx, fx) = cell(x, w);
    let (cy, fy) = cell(y, h);
    let at = |c: i64, r: i64| -> f64 {
        let (c, r) = match g.edge {
            Edge::Wrap => (c.rem_euclid(w), r.rem_euclid(h)),
            Edge::None => (c.clamp(0, w - 1), r.clamp(0, h - 1)),
        };
        g.heights[(r * w + c) as usize] as f64
    };
    let top = at(cx, cy) * (1.0 - fx) + at(cx + 1, cy) * fx;
    let bot = at(cx, cy + 1) * (1.0 - fx) + at(cx + 1, cy + 1) * fx;
    top * (1.0 - fy) + bot * fy
}

/// Three smooth waves of whole periods over the map (so `edge=wrap` has no seam): frequencies
/// 0..=`max_freq` per axis, amplitudes up to `amp` texels, random phases.
pub fn waves(rng: &mut Rng, w: usize, h: usize, max_freq: usize, amp: f32) -> Vec<f32> {
    let mut v = vec![0.0f32; w * h];
    for _ in 0..3 {
        let (fx, fy) = (rng.range(0, max_freq) as f32, rng.range(0, max_freq) as f32);
        let (a, p) = (amp * rng.f32(), std::f32::consts::TAU * rng.f32());
        for r in 0..h {
            for c in 0..w {
                let t = std::f32::consts::TAU
                    * (fx * c as f32 / w as f32 + fy * r as f32 / h as f32)
                    + p;
                v[r * w + c] += a * t.sin();
            }
        }
    }
    v
}

/// Per-bin sin α of every texel of `k` (`bins_out`), computed in bands of `band` rows so band
/// seams are exercised.
pub fn per_bin(k: &dyn HorizonRows, band: usize) -> Vec<f32> {
    let (w, h, nb) = (k.width(), k.height(), k.bins());
    let mut out = vec![0.0f32; w * h * nb];
    let mut ch = vec![0.0f32; w * band * 8];
    for y0 in (0..h).step_by(band) {
        let rows = band.min(h - y0);
        k.rows(y0, &mut ch[..rows * w * 8], Some(&mut out[y0 * w * nb..(y0 + rows) * w * nb]));
    }
    out
}

/// Mean and 99th percentile of `d`.
pub fn mean_p99(mut d: Vec<f64>) -> (f64, f64) {
    let mean = d.iter().sum::<f64>() / d.len() as f64;
    d.sort_by(f64::total_cmp);
    (mean, d[((d.len() as f64 * 0.99) as usize).min(d.len() - 1)])
}
