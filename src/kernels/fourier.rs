//! Radial Fourier encoding of the horizon function (SPEC §3.4).
//!
//! The technique is the one in "Self-shadowing textures using radial horizon maps"
//! (codedeposit.blogspot.com, 2010): the horizon function s(φ) of a texel (sin of the horizon
//! elevation at azimuth φ) is a periodic waveform, so a few Fourier bands describe it; the shader
//! evaluates them at the light's azimuth with polynomials in (x, y) instead of trigonometry.
//!
//! With (x, y) = (cos φ, sin φ), the basis b_0..b_8 ([`basis`]) is 1, x, y, 2xy, y² − x²,
//! x³ − 3xy², 3x²y − y³, 4xy(x² − y²), (x² − y²)² − 4x²y² (the bands up to 4φ), and
//! `fourier_terms` = 3, 5, 7, 9 keeps k < terms. The coefficients are the projections over the
//! bake's `bins` samples, premultiplied by 2 for k ≥ 1 ([`Projector`]): for 16 bins or more
//! that is the least-squares fit, and the decoder is simply s(φ) = Σ_k C_k b_k(φ)
//! ([`evaluate_xy`]).
//!
//! They are stored in 8-bit UNORM so that the write-up's shader decodes them unchanged (SPEC
//! §3.4): a sign-preserving square root ([`compand`]) around ½, t = ½ + ¼·v with
//! `fourier_range=standard` (the default), which uses only about 0.2 of the byte range on each
//! side since |C_k| ≤ [`COEFF_BOUND`] = 2/π; `expanded` divides by that bound first and stores
//! t = ½ + ½·v, for a shader changed in two lines.
//!
//! Layout ([`FourierLayers`]):
//! - `fourier_0`: RGBA8 = C_1, C_2, C_3, C_4 (with 3 terms, B and A hold the encoded zero, 128);
//! - `fourier_1`: one channel = √C_0 (stored as ½ + ½·√C_0 with `standard`);
//! - `fourier_2` (7 and 9 terms only): RGBA8 = C_5, C_6, C_7, C_8 (B, A = 128 with 7 terms).
//!
//! So a 5-term bake is exactly what SPEC §3.4 names, and higher orders only add a layer.
//! docs/fourier.md has the full account: the exact formulas, the shader's decode, the ranges.

use crate::params::FourierRange;
use std::f64::consts::PI;

/// The largest magnitude of a premultiplied non-constant coefficient of s ∈ [0, 1]: 2/π.
pub const COEFF_BOUND: f64 = 2.0 / PI;

/// Most terms supported.
pub const MAX_TERMS: usize = 9;

/// The 9 basis functions at (x, y) = (cos φ, sin φ), in the order of the module doc's list.
#[inline]
pub fn basis(x: f64, y: f64) -> [f64; MAX_TERMS] {
    let (x2, y2) = (x * x, y * y);
    let xy = x * y;
    let c2 = x2 - y2;
    [
        1.0,
        x,
        y,
        2.0 * xy,
        y2 - x2,
        x * (x2 - 3.0 * y2),
        y * (3.0 * x2 - y2),
        4.0 * xy * c2,
        c2 * c2 - 4.0 * x2 * y2,
    ]
}

/// Projects per-bin horizon samples onto the first `terms` basis functions.
///
/// Built once per bake (the basis table is `bins × terms`), then applied to every texel.
#[derive(Debug, Clone)]
pub struct Projector {
    terms: usize,
    bins: usize,
    /// `weights[n * terms + k]` = b_k(φ_n) / B, times 2 for k ≥ 1.
    weights: Vec<f64>,
}

impl Projector {
    /// A projector for `bins` samples (φ_n = n·2π/bins) and `terms` ∈ {3, 5, 7, 9}.
    pub fn new(bins: usize, terms: usize) -> Self {
        let terms = terms.clamp(1, MAX_TERMS);
        let bins = bins.max(1);
        let mut weights = vec![0.0; bins * terms];
        for n in 0..bins {
            let phi = n as f64 * 2.0 * PI / bins as f64;
            let b = basis(phi.cos(), phi.sin());
            for k in 0..terms {
                let two = if k == 0 { 1.0 } else { 2.0 };
                weights[n * terms + k] = two * b[k] / bins as f64;
            }
        }
        Projector { terms, bins, weights }
    }

    /// Number of terms.
    pub fn terms(&self) -> usize {
        self.terms
    }

    /// The premultiplied coefficients C_0 .. C_{terms−1} of `s` (`bins` samples); the rest of
    /// `out` is zeroed.
    #[inline]
    pub fn project(&self, s: &[f32], out: &mut [f64; MAX_TERMS]) {
        *out = [0.0; MAX_TERMS];
        for (n, &v) in s.iter().enumerate().take(self.bins) {
            let w = &self.weights[n * self.terms..(n + 1) * self.terms];
            for (o, &wk) in out.iter_mut().zip(w) {
                *o += v as f64 * wk;
            }
        }
    }
}

/// s(φ) from premultiplied coefficients (the first `terms` of them).
#[inline]
pub fn evaluate(coeffs: &[f64; MAX_TERMS], terms: usize, phi: f64) -> f64 {
    evaluate_xy(coeffs, terms, phi.cos(), phi.sin())
}

/// s at the azimuth whose (cos, sin) is (x, y) — what a shader does with the light's
/// normalised tangent-plane direction, no trigonometry.
#[inline]
pub fn evaluate_xy(coeffs: &[f64; MAX_TERMS], terms: usize, x: f64, y: f64) -> f64 {
    let b = basis(x, y);
    coeffs.iter().zip(&b).take(terms.min(MAX_TERMS)).map(|(c, b)| c * b).sum()
}

/// The scale a stored non-constant coefficient is divided by before companding.
#[inline]
pub fn range_scale(range: FourierRange) -> f64 {
    match range {
        FourierRange::Standard => 1.0,
        FourierRange::Expanded => COEFF_BOUND,
    }
}

/// How far the companded value v = sign(c)·√|c / range_scale| reaches from the UNORM midpoint:
/// the write-up's shader decodes `t·4 − 2`, so the standard range stores v·¼ + ½; `expanded`
/// (a shader changed to `t·2 − 1`) stores v·½ + ½.
#[inline]
fn half_span(range: FourierRange) -> f64 {
    match range {
        FourierRange::Standard => 0.25,
        FourierRange::Expanded => 0.5,
    }
}

/// Sign-preserving square root.
#[inline]
pub fn compand(c: f64) -> f64 {
    c.signum() * c.abs().sqrt()
}

/// The byte storing a non-constant premultiplied coefficient.
#[inline]
pub fn encode_coeff(c: f64, range: FourierRange) -> u8 {
    let v = compand(c / range_scale(range)).clamp(-1.0, 1.0);
    crate::layers::quantize8((v * half_span(range) + 0.5) as f32)
}

/// The byte storing the constant term C_0 ∈ [0, 1]: the write-up's shader decodes it as
/// c = t·2 − 1, c·|c| (`standard`, t = ½ + ½√C_0); `expanded` stores t = √C_0, decoded t².
#[inline]
pub fn encode_constant(c0: f64, range: FourierRange) -> u8 {
    let r = c0.clamp(0.0, 1.0).sqrt();
    let t = match range {
        FourierRange::Standard => 0.5 + 0.5 * r,
        FourierRange::Expanded => r,
    };
    crate::layers::quantize8(t as f32)
}

/// A non-constant coefficient from its filtered UNORM value `t` ∈ [0, 1].
#[inline]
pub fn decode_coeff(t: f64, range: FourierRange) -> f64 {
    let v = (t - 0.5) / half_span(range);
    v * v.abs() * range_scale(range)
}

/// The constant term from its filtered UNORM value `t`.
#[inline]
pub fn decode_constant(t: f64, range: FourierRange) -> f64 {
    match range {
        FourierRange::Standard => {
            let c = t * 2.0 - 1.0;
            c * c.abs()
        }
        FourierRange::Expanded => t * t,
    }
}

/// Which stored layer and channel hold coefficient k (k ≥ 1): (layer index in
/// `fourier_0`/`fourier_2` order: 0 or 2, channel 0..3). The constant lives in layer 1.
#[inline]
pub fn slot_of(k: usize) -> (usize, usize) {
    if k <= 4 {
        (0, k - 1)
    } else {
        (2, k - 5)
    }
}

/// Encodes one texel's coefficients into its layer bytes: `bands` (4 bytes of `fourier_0`),
/// `constant` (1 byte of `fourier_1`) and, for 7/9 terms, `high` (4 bytes of `fourier_2`).
/// Slots past `terms` hold the encoded zero.
#[inline]
pub fn encode_texel(
    coeffs: &[f64; MAX_TERMS],
    terms: usize,
    range: FourierRange,
    bands: &mut [u8],
    constant: &mut u8,
    high: Option<&mut [u8]>,
) {
    *constant = encode_constant(coeffs[0], range);
    let zero = encode_coeff(0.0, range);
    for (i, b) in bands.iter_mut().enumerate().take(4) {
        let k = i + 1;
        *b = if k < terms { encode_coeff(coeffs[k], range) } else { zero };
    }
    if let Some(h) = high {
        for (i, b) in h.iter_mut().enumerate().take(4) {
            let k = i + 5;
            *b = if k < terms { encode_coeff(coeffs[k], range) } else { zero };
        }
    }
}

/// Decodes coefficients from filtered layer values (each in [0, 1]): `bands` = fourier_0 RGBA,
/// `constant` = fourier_1, `high` = fourier_2 RGBA (ignored below 7 terms).
#[inline]
pub fn decode_texel(
    bands: [f64; 4],
    constant: f64,
    high: [f64; 4],
    terms: usize,
    range: FourierRange,
) -> [f64; MAX_TERMS] {
    let mut c = [0.0; MAX_TERMS];
    c[0] = decode_constant(constant, range);
    for k in 1..terms.min(MAX_TERMS) {
        let t = if k <= 4 { bands[k - 1] } else { high[k - 5] };
        c[k] = decode_coeff(t, range);
    }
    c
}

/// The encoded Fourier layers of a bake (see the module doc for the layout).
#[derive(Debug, Clone, PartialEq)]
pub struct FourierLayers {
    pub width: usize,
    pub height: usize,
    /// 3, 5, 7 or 9.
    pub terms: usize,
    pub range: FourierRange,
    /// `fourier_0`: RGBA8, `height · width · 4`, C_1..C_4 companded.
    pub bands: Vec<u8>,
    /// `fourier_1`: one channel, `height · width`, √C_0.
    pub constant: Vec<u8>,
    /// `fourier_2` (7 and 9 terms): RGBA8, C_5..C_8 companded.
    pub high: Option<Vec<u8>>,
}

impl FourierLayers {
    /// Number of stored layers: 2, or 3 with 7 and 9 terms.
    pub fn layer_count(&self) -> usize {
        if self.high.is_some() {
            3
        } else {
            2
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn basis_matches_trigonometry() {
        for i in 0..97 {
            let phi = i as f64 * 0.137 - 3.0;
            let b = basis(phi.cos(), phi.sin());
            let want = [
                1.0,
                phi.cos(),
                phi.sin(),
                (2.0 * phi).sin(),
                -(2.0 * phi).cos(),
                (3.0 * phi).cos(),
                (3.0 * phi).sin(),
                (4.0 * phi).sin(),
                (4.0 * phi).cos(),
            ];
            for k in 0..9 {
                assert!((b[k] - want[k]).abs() < 1e-12, "k {k} phi {phi}");
            }
        }
    }

    #[test]
    fn projection_recovers_each_basis_function() {
        for terms in [3usize, 5, 7, 9] {
            let p = Projector::new(32, terms);
            for k in 0..terms {
                let s: Vec<f32> = (0..32)
                    .map(|n| {
                        let phi = n as f64 * 2.0 * PI / 32.0;
                        (0.25 * basis(phi.cos(), phi.sin())[k]) as f32
                    })
                    .collect();
                let mut c = [0.0; MAX_TERMS];
                p.project(&s, &mut c);
                for (j, &cj) in c.iter().enumerate() {
                    let want = if j == k { 0.25 } else { 0.0 };
                    assert!((cj - want).abs() < 1e-6, "terms {terms} k {k} j {j}: {cj}");
                }
            }
        }
    }

    #[test]
    fn literal_bytes() {
        // Zero encodes to 128 (0.5·255 + 0.5 = 128) and 128 decodes to (4·128/255 − 2)².
        assert_eq!(encode_coeff(0.0, FourierRange::Standard), 128);
        let z = decode_coeff(128.0 / 255.0, FourierRange::Standard);
        assert!((z - (2.0 / 255.0f64).powi(2)).abs() < 1e-15);
        // C = 0.25 → √ = 0.5 → (0.5·0.25 + 0.5)·255 + 0.5 = 159.875 → 159.
        assert_eq!(encode_coeff(0.25, FourierRange::Standard), 159);
        assert_eq!(encode_coeff(-0.25, FourierRange::Standard), 96);
        // Expanded: the bound itself maps to 255.
        assert_eq!(encode_coeff(COEFF_BOUND, FourierRange::Expanded), 255);
        // C_0 = 0.25 → √ = 0.5 → standard 0.75·255 + 0.5 → 191; expanded 0.5·255 + 0.5 → 128.
        assert_eq!(encode_constant(0.25, FourierRange::Standard), 191);
        assert_eq!(encode_constant(0.25, FourierRange::Expanded), 128);
        assert!((decode_constant(191.0 / 255.0, FourierRange::Standard) - 0.2475).abs() < 1e-3);
        assert!((decode_constant(128.0 / 255.0, FourierRange::Expanded) - 0.2519).abs() < 1e-3);
    }
}
