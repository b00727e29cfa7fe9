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
#[inline]
pub fn quantize8(v: f32) -> u8 {
    ((v as f64) * 255.0 + 0.5).floor().clamp(0.0, 255.0) as u8
}

/// 16-bit UNORM of a value in [0, 1]: floor(v·65535 + 0.5).
#[inline]
pub fn quantize16(v: f32) -> u16 {
    ((v as f64) * 65535.0 + 0.5).floor().clamp(0.0, 65535.0) as u16
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
