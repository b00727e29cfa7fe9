//! Output encoders: PNG 8/16-bit, OpenEXR f32, KTX2 and DDS array textures and cube maps.
//!
//! Encoders take finished, quantised buffers and return bytes; they never compute. Quantisation
//! lives here too ([`quantize8`], [`quantize16`]) so every producer rounds the same way
//! (SPEC §2: floor(v·255 + 0.5), floor(v·65535 + 0.5)).

pub mod png;

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
