//! Files for recomputing the eval independently (`scripts/recompute_eval.py`).
//!
//! For each map, the default model's baked layers exactly as `horizon-bake bake` writes them
//! (`horizon_0.png`, `horizon_1.png`, 8-bit RGBA), the ground truth the eval compared them with
//! (`truth.f32`: little-endian f32, `H·W·192`, texel-major, bin n at azimuth n·2π/192), the
//! heights (`heights.f32`, texels) and `meta.json` with the numbers the eval reported. The
//! script decodes the PNGs with its own channel-factor code and must land on the same numbers.

use super::{corpus::Map, Metrics, DEFAULT_MODEL, ELEVATIONS_DEG, HORIZON_AZIMUTHS};
use super::{SHADOW_AZIMUTHS, TRUTH_BINS};
use crate::bake::HorizonLayers;
use crate::encode::png::{encode8, PngColor};
use crate::error::{Error, Result};
use crate::params::Edge;
use std::path::Path;

fn f32_bytes(v: &[f32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

/// Writes one map's files under `dir/<map name>/`.
///
/// # Errors
/// I/O errors; [`Error::Internal`] when the layers have no 8-bit precision.
pub fn write_map(
    dir: &Path,
    map: &Map,
    edge: Edge,
    truth: &[f32],
    layers: &HorizonLayers,
    metrics: &Metrics,
) -> Result<()> {
    let sub = dir.join(&map.name);
    std::fs::create_dir_all(&sub)?;
    let u8s = layers
        .u8
        .as_ref()
        .ok_or_else(|| Error::Internal("dump: the default model has no 8-bit layers".into()))?;
    for (k, layer) in u8s.iter().enumerate() {
        let png = encode8(layers.width, layers.height, PngColor::Rgba, layer)?;
        std::fs::write(sub.join(format!("horizon_{k}.png")), png)?;
    }
    std::fs::write(sub.join("truth.f32"), f32_bytes(truth))?;
    std::fs::write(sub.join("heights.f32"), f32_bytes(&map.heights))?;
    let meta = serde_json::json!({
        "map": map.name,
        "width": map.width,
        "height": map.height,
        "edge": edge,
        "model": DEFAULT_MODEL,
        "truth_bins": TRUTH_BINS,
        "elevations_deg": ELEVATIONS_DEG,
        "shadow_azimuths": SHADOW_AZIMUTHS,
        "horizon_azimuths": HORIZON_AZIMUTHS,
        "metrics": metrics,
    });
    let text = serde_json::to_vec_pretty(&meta)
        .map_err(|e| Error::Internal(format!("dump: meta.json: {e}")))?;
    std::fs::write(sub.join("meta.json"), text)?;
    Ok(())
}
