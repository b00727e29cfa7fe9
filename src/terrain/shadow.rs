//! Sun shadows (SPEC §3.7 `shadow`): a texel is lit when the sun stands above its horizon at the
//! sun's own azimuth (one ray per texel at exactly that azimuth, never interpolated between
//! bins). A sun at or below 0° shadows everything.
//!
//! With `method=lengyel`, which has no ray, lit means L_z > s of §3.3 decoded from the baked
//! layers ([`lit_from_layers`]): the channel factors of the sun's tangent-space direction (what
//! the cube map holds for it, [`crate::kernels::cubemap::factors_for_direction`]) blend the two
//! stored channels that bracket its azimuth, s = max(f,0)·h0 + max(−f,0)·h1 (Lengyel eq. 5.3,
//! [`crate::kernels::shade::horizon_s`], as the preview's horizon shading and a shader decode
//! it), from the 8-bit layers the bake stores (`encoding=sqrt`: s = v²).

use crate::kernels::{cubemap, shade};
use crate::params::Encoding;

/// Value of a lit texel in `shadow.tif`.
pub const LIT: u8 = 1;
/// Value of a shadowed texel.
pub const SHADOW: u8 = 0;
/// Value of a hole (the GDAL_NODATA of `shadow.tif`).
pub const NODATA: u8 = 255;

/// Whether the sun at `elevation_deg` clears a horizon of sin α = `horizon_sin`.
#[inline]
pub fn lit(horizon_sin: f64, elevation_deg: f64) -> bool {
    elevation_deg > 0.0 && elevation_deg.to_radians().sin() > horizon_sin
}

/// The tangent-space direction L = (cos e cos φ, cos e sin φ, sin e) of a sun at tangent-space
/// azimuth `phi` (radians, SPEC §2's φ) and elevation `elevation_deg`.
pub fn sun_direction(phi: f64, elevation_deg: f64) -> [f64; 3] {
    let e = elevation_deg.to_radians();
    [e.cos() * phi.cos(), e.cos() * phi.sin(), e.sin()]
}

/// The shadow of every texel for the sun at `elevation_deg` and tangent-space azimuth `phi`
/// from the two 8-bit RGBA horizon layers (`layers[k]` = layer k, 4 samples per texel), into
/// `out` ([`LIT`] or [`SHADOW`]; texels already [`NODATA`] stay so).
pub fn lit_from_layers(
    layers: [&[u8]; 2],
    encoding: Encoding,
    phi: f64,
    elevation_deg: f64,
    out: &mut [u8],
) {
    let l = sun_direction(phi, elevation_deg);
    let f = cubemap::factors_for_direction(l);
    let decode = |v: u8| {
        let t = v as f32 / 255.0;
        if encoding == Encoding::Sqrt {
            t * t
        } else {
            t
        }
    };
    let texels = layers[0].chunks_exact(4).zip(layers[1].chunks_exact(4));
    for (o, (a, b)) in out.iter_mut().zip(texels) {
        if *o == NODATA {
            continue;
        }
        let (h0, h1) =
            (std::array::from_fn(|i| decode(a[i])), std::array::from_fn(|i| decode(b[i])));
        let s = shade::horizon_s(f, h0, h1) as f64;
        *o = if elevation_deg > 0.0 && l[2] > s { LIT } else { SHADOW };
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sun_against_horizon() {
        assert!(lit(0.0, 0.1));
        assert!(!lit(0.0, 0.0));
        assert!(!lit(0.0, -5.0));
        assert!(!lit(0.5, 30.0));
        assert!(lit(0.5, 30.1));
    }
}
