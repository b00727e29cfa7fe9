//! The channel-factor cube map (SPEC §2 "Cube map", §3.3).
//!
//! A shader samples this cube map with the tangent-space direction to the light and gets, in 4
//! slots, the weights that blend the two horizon channels bracketing the light's azimuth. Eight
//! channels fit in four slots because the two channels that share a slot (c and c+4) are never
//! both non-zero: a layer-1 channel's factor is stored negated, and the shader splits the sign
//! (s = max(f,0)·h0 + max(−f,0)·h1, Lengyel eq. 5.3).
//!
//! Faces are +X, −X, +Y, −Y, +Z, −Z, oriented by the OpenGL face-selection table; row 0 of a face
//! is t = −1 and texel centres sit at ((u + ½)·2/S − 1).

use std::f64::consts::PI;

/// The signed 4-slot factors for a light at azimuth `phi` (radians, from +x toward +y).
pub fn factors_for_azimuth(phi: f64) -> [f32; 4] {
    let pos = (phi / (PI / 4.0)).rem_euclid(8.0);
    let mut c = pos.floor() as usize;
    let mut t = pos - c as f64;
    if c >= 8 {
        // rem_euclid may round up to exactly 8.0 for tiny negative inputs.
        c = 0;
        t = 0.0;
    }
    let mut f = [0.0f32; 4];
    let mut put = |ch: usize, w: f64| {
        let sign = if ch >= 4 { -1.0 } else { 1.0 };
        f[ch % 4] += (sign * w) as f32;
    };
    put(c, 1.0 - t);
    put((c + 1) % 8, t);
    f
}

/// The signed factors for a tangent-space light direction (only its azimuth matters; straight
/// up, where the azimuth is undefined, takes azimuth 0 — any choice is shadow-free there since
/// the horizon is never above the zenith).
pub fn factors_for_direction(d: [f64; 3]) -> [f32; 4] {
    factors_for_azimuth(d[1].atan2(d[0]))
}

/// The unnormalised direction through texel (`u`, `v`) of `face` (0..6) of size `size`.
pub fn texel_direction(face: usize, u: usize, v: usize, size: usize) -> [f64; 3] {
    let sc = (2.0 * (u as f64 + 0.5)) / size as f64 - 1.0;
    let tc = (2.0 * (v as f64 + 0.5)) / size as f64 - 1.0;
    face_direction(face, sc, tc)
}

/// The unnormalised direction through face coordinates (`sc`, `tc`) ∈ [−1, 1]² of `face` (0..6);
/// coordinates past ±1 continue the face's plane (how seamless filtering finds a neighbour face).
pub fn face_direction(face: usize, sc: f64, tc: f64) -> [f64; 3] {
    // Inverse of the OpenGL table: (major axis, sc, tc) per face.
    match face {
        0 => [1.0, -tc, -sc],
        1 => [-1.0, -tc, sc],
        2 => [sc, 1.0, tc],
        3 => [sc, -1.0, -tc],
        4 => [sc, -tc, 1.0],
        _ => [-sc, -tc, -1.0],
    }
}

/// Which face and (s, t) ∈ [0,1]² a direction selects (the OpenGL table); used by the preview
/// renderer to sample the cube map as a GPU would.
pub fn select_face(d: [f64; 3]) -> (usize, f64, f64) {
    let [x, y, z] = d;
    let (ax, ay, az) = (x.abs(), y.abs(), z.abs());
    let (face, sc, tc, ma) = if ax >= ay && ax >= az {
        if x >= 0.0 {
            (0, -z, -y, ax)
        } else {
            (1, z, -y, ax)
        }
    } else if ay >= az {
        if y >= 0.0 {
            (2, x, z, ay)
        } else {
            (3, x, -z, ay)
        }
    } else if z >= 0.0 {
        (4, x, -y, az)
    } else {
        (5, -x, -y, az)
    };
    let ma = if ma > 0.0 { ma } else { 1.0 };
    (face, 0.5 * (sc / ma + 1.0), 0.5 * (tc / ma + 1.0))
}

/// The whole cube map: `6 · size · size · 4` signed factors, faces in order, row 0 = t = −1.
pub fn cube_factors(size: usize) -> Vec<f32> {
    let mut out = vec![0.0f32; 6 * size * size * 4];
    for (k, texel) in out.chunks_exact_mut(4).enumerate() {
        let face = k / (size * size);
        let rem = k % (size * size);
        let (v, u) = (rem / size, rem % size);
        texel.copy_from_slice(&factors_for_direction(texel_direction(face, u, v, size)));
    }
    out
}

/// Largest face size [`cube_factors_shared`] keeps (6·256²·4 f32 = 6 MiB); larger ones are
/// computed on every call rather than held for the life of the process.
pub const SHARED_MAX_SIZE: usize = 256;

/// [`cube_factors`] computed once per face size and shared: every face request, bake and
/// preview of one size reuses the same table (sizes up to [`SHARED_MAX_SIZE`]).
pub fn cube_factors_shared(size: usize) -> std::sync::Arc<[f32]> {
    use std::collections::HashMap;
    use std::sync::{Arc, Mutex, OnceLock};
    static CACHE: OnceLock<Mutex<HashMap<usize, Arc<[f32]>>>> = OnceLock::new();
    if size > SHARED_MAX_SIZE {
        return cube_factors(size).into();
    }
    let cache = CACHE.get_or_init(Default::default);
    if let Ok(map) = cache.lock() {
        if let Some(c) = map.get(&size) {
            return Arc::clone(c);
        }
    }
    // Computed outside the lock: a racing thread may compute the same table once more.
    let fresh: Arc<[f32]> = cube_factors(size).into();
    match cache.lock() {
        Ok(mut map) => Arc::clone(map.entry(size).or_insert(fresh)),
        Err(_) => fresh,
    }
}

/// UNORM 8-bit encoding of a signed factor: floor((f·0.5 + 0.5)·255 + 0.5).
#[inline]
pub fn unorm8(f: f32) -> u8 {
    (((f as f64) * 0.5 + 0.5) * 255.0 + 0.5).floor().clamp(0.0, 255.0) as u8
}

/// SNORM 8-bit encoding (0 exact): round(f·127), clamped to [−127, 127].
#[inline]
pub fn snorm8(f: f32) -> i8 {
    ((f as f64) * 127.0).round().clamp(-127.0, 127.0) as i8
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn factors_sum_to_one_in_magnitude() {
        for k in 0..720 {
            let phi = k as f64 * PI / 360.0 - PI;
            let f = factors_for_azimuth(phi);
            let sum: f32 = f.iter().map(|v| v.abs()).sum();
            assert!((sum - 1.0).abs() < 1e-6, "phi {phi}: {f:?}");
        }
    }

    #[test]
    fn channel_azimuths_select_one_channel() {
        for c in 0..8 {
            let f = factors_for_azimuth(c as f64 * PI / 4.0 + 1e-12);
            let expect = if c >= 4 { -1.0 } else { 1.0 };
            assert!((f[c % 4] - expect).abs() < 1e-6, "channel {c}: {f:?}");
        }
        // Halfway between channel 3 (layer 0, slot 3) and channel 4 (layer 1, slot 0).
        let f = factors_for_azimuth(3.5 * PI / 4.0);
        assert!((f[3] - 0.5).abs() < 1e-6 && (f[0] + 0.5).abs() < 1e-6, "{f:?}");
    }

    #[test]
    fn select_face_inverts_texel_direction() {
        let size = 8;
        for face in 0..6 {
            for v in 0..size {
                for u in 0..size {
                    let d = texel_direction(face, u, v, size);
                    let (f, s, t) = select_face(d);
                    assert_eq!(f, face);
                    assert!((s * size as f64 - (u as f64 + 0.5)).abs() < 1e-9);
                    assert!((t * size as f64 - (v as f64 + 0.5)).abs() < 1e-9);
                }
            }
        }
    }

    #[test]
    fn shared_cube_is_computed_once_per_size() {
        let a = cube_factors_shared(6);
        let b = cube_factors_shared(6);
        assert!(std::sync::Arc::ptr_eq(&a, &b), "the second call must reuse the first table");
        assert_eq!(&a[..], &cube_factors(6)[..]);
        assert!(!std::sync::Arc::ptr_eq(&a, &cube_factors_shared(7)));
    }

    #[test]
    fn unorm_and_snorm_encodings() {
        assert_eq!(unorm8(-1.0), 0);
        assert_eq!(unorm8(0.0), 128);
        assert_eq!(unorm8(1.0), 255);
        assert_eq!(snorm8(0.0), 0);
        assert_eq!(snorm8(-1.0), -127);
        assert_eq!(snorm8(0.5), 64);
    }
}
