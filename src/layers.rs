//! The horizon layers as a bake produces them and an encoder consumes them, and the quantisers
//! between the two (SPEC §2 rounding).
//!
//! A leaf module on purpose: the bake writes these types and the encoders read them, so they
//! live in neither, and neither imports the other for them (no bake ↔ encode cycle).

/// Which sample precisions of the horizon layers to produce.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Precisions {
    pub u8: bool,
    pub u16: bool,
    pub f32: bool,
}

impl Precisions {
    /// Only 8-bit layers (the default `png8` output).
    pub const U8: Precisions = Precisions { u8: true, u16: false, f32: false };
    /// Every precision.
    pub const ALL: Precisions = Precisions { u8: true, u16: true, f32: true };
}

/// The two RGBA horizon layers (layer 0 = channels 0..3, layer 1 = channels 4..7), each
/// `height · width · 4` samples row-major from the top row, in every precision asked for.
/// Values are s, or √s with `encoding=sqrt`.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct HorizonLayers {
    pub width: usize,
    pub height: usize,
    pub u8: Option<[Vec<u8>; 2]>,
    pub u16: Option<[Vec<u16>; 2]>,
    pub f32: Option<[Vec<f32>; 2]>,
}

/// 8-bit UNORM of a value in [0, 1]: floor(v·255 + 0.5).
///
/// Clamped first, then truncated by the cast: on [0, 255] truncation is the floor, so the
/// bytes are floor's, without the libm call `floor` is on the baseline x86-64 (no SSE4.1
/// `roundsd`): that call alone was 4 % of a 2048² `lengyel` bake's profile.
#[inline]
pub fn quantize8(v: f32) -> u8 {
    ((v as f64) * 255.0 + 0.5).clamp(0.0, 255.0) as u8
}

/// 16-bit UNORM of a value in [0, 1]: floor(v·65535 + 0.5) (truncated after the clamp, as
/// [`quantize8`]).
#[inline]
pub fn quantize16(v: f32) -> u16 {
    ((v as f64) * 65535.0 + 0.5).clamp(0.0, 65535.0) as u16
}

/// A sample type horizon layers are quantised to (SPEC §2 rounding): `u8`, `u16` or `f32`.
pub trait Sample: Copy + Default + Send + Sync + 'static {
    /// The sample of a value in [0, 1].
    fn quantize(v: f32) -> Self;
}

impl Sample for u8 {
    #[inline]
    fn quantize(v: f32) -> Self {
        quantize8(v)
    }
}

impl Sample for u16 {
    #[inline]
    fn quantize(v: f32) -> Self {
        quantize16(v)
    }
}

impl Sample for f32 {
    #[inline]
    fn quantize(v: f32) -> Self {
        v
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The cast after the clamp gives floor's bytes: at every rounding boundary (k − ½)/255
    /// and /65535 within a few ulp either side, on a sweep of f32 values through and beyond
    /// [0, 1], and for NaN and the infinities.
    #[test]
    fn quantizing_by_truncation_is_the_floor() {
        let floor8 = |v: f32| ((v as f64) * 255.0 + 0.5).floor().clamp(0.0, 255.0) as u8;
        let floor16 = |v: f32| ((v as f64) * 65535.0 + 0.5).floor().clamp(0.0, 65535.0) as u16;
        let near = |x: f64| {
            let c = x as f32;
            (-4i32..=4).map(move |d| f32::from_bits((c.to_bits() as i64 + d as i64).max(0) as u32))
        };
        let mut checked = 0usize;
        for k in 0..=256u32 {
            for v in near((k as f64 - 0.5) / 255.0) {
                assert_eq!(quantize8(v), floor8(v), "{v:e}");
                checked += 1;
            }
        }
        for k in 0..=65536u32 {
            for v in near((k as f64 - 0.5) / 65535.0) {
                assert_eq!(quantize16(v), floor16(v), "{v:e}");
                checked += 1;
            }
        }
        let (lo, hi) = ((-0.25f32).to_bits(), 1.25f32.to_bits());
        for bits in (0..=hi).step_by(997).chain((1u32 << 31..=lo).step_by(991)) {
            let v = f32::from_bits(bits);
            assert_eq!(quantize8(v), floor8(v), "{v:e}");
            assert_eq!(quantize16(v), floor16(v), "{v:e}");
            checked += 1;
        }
        for v in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY, 0.0, -0.0, 1.0] {
            assert_eq!(quantize8(v), floor8(v), "{v}");
            assert_eq!(quantize16(v), floor16(v), "{v}");
        }
        assert!(checked > 1_000_000, "{checked}");
        assert_eq!((quantize8(0.5), quantize8(1.0), quantize16(1.0)), (128, 255, 65535));
    }
}
