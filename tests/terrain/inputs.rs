//! Height-map input (SPEC §2): every supported layout decodes to known values, and every broken
//! or unsupported input gets its own clear error. Files are written in the test with the png,
//! tiff and exr crates (or by hand, for headers no encoder would write).

use horizon_bake::error::{Error, LimitError};
use horizon_bake::heightmap::{decode, probe, Limits};
use horizon_bake::params::{BakeParams, Channel};
use std::io::Cursor;

fn close(got: &[f32], want: &[f32], what: &str) {
    assert_eq!(got.len(), want.len(), "{what}: length");
    for (k, (g, w)) in got.iter().zip(want).enumerate() {
        assert!((g - w).abs() <= 1e-6, "{what}: value {k} is {g}, expected {w}");
    }
}

fn png(w: u32, h: u32, color: png::ColorType, depth: png::BitDepth, data: &[u8]) -> Vec<u8> {
    let mut out = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut out, w, h);
        enc.set_color(color);
        enc.set_depth(depth);
        let mut wr = enc.write_header().unwrap();
        wr.write_image_data(data).unwrap();
    }
    out
}

fn be16(v: &[u16]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_be_bytes()).collect()
}

fn luma(r: f32, g: f32, b: f32) -> f32 {
    (0.2126 * r as f64 + 0.7152 * g as f64 + 0.0722 * b as f64) as f32
}

#[test]
fn png_layouts_decode_to_normalised_heights() {
    use png::{BitDepth as D, ColorType as C};
    let lim = Limits::default();
    // 3×2 gray 8-bit.
    let g8 = [0u8, 51, 255, 102, 7, 200];
    let (m, info) = decode(&png(3, 2, C::Grayscale, D::Eight, &g8), Channel::Luma, &lim).unwrap();
    assert_eq!((m.width, m.height), (3, 2));
    close(&m.values, &g8.map(|v| v as f32 / 255.0), "gray8");
    assert_eq!(
        (info.format.as_str(), info.color.as_str(), info.bit_depth, info.float),
        ("png", "gray", 8, false)
    );
    assert_eq!(info.content_hash.len(), 64);

    // Gray 16-bit: v / 65535.
    let g16 = [0u16, 1, 65535, 32768, 1000, 40000];
    let (m, info) =
        decode(&png(2, 3, C::Grayscale, D::Sixteen, &be16(&g16)), Channel::Luma, &lim).unwrap();
    assert_eq!((m.width, m.height, info.bit_depth), (2, 3, 16));
    close(&m.values, &g16.map(|v| (v as f64 / 65535.0) as f32), "gray16");

    // Gray+alpha: the gray sample, whatever `channel` says.
    let ga8 = [10u8, 255, 20, 0, 30, 128];
    let (m, info) =
        decode(&png(3, 1, C::GrayscaleAlpha, D::Eight, &ga8), Channel::A, &lim).unwrap();
    close(&m.values, &[10.0 / 255.0, 20.0 / 255.0, 30.0 / 255.0], "gray_alpha8");
    assert_eq!(info.color, "gray_alpha");
    let ga16 = [1000u16, 0, 65535, 5];
    let (m, _) =
        decode(&png(2, 1, C::GrayscaleAlpha, D::Sixteen, &be16(&ga16)), Channel::Luma, &lim)
            .unwrap();
    close(&m.values, &[(1000.0 / 65535.0f64) as f32, 1.0], "gray_alpha16");

    // RGB 8-bit: each channel and luma on the stored values.
    let rgb = [255u8, 0, 0, 10, 20, 30];
    let bytes = png(2, 1, C::Rgb, D::Eight, &rgb);
    let n = |v: u8| v as f32 / 255.0;
    for (ch, want) in [
        (Channel::R, [1.0, n(10)]),
        (Channel::G, [0.0, n(20)]),
        (Channel::B, [0.0, n(30)]),
        (Channel::A, [1.0, 1.0]),
        (Channel::Luma, [luma(1.0, 0.0, 0.0), luma(n(10), n(20), n(30))]),
    ] {
        let (m, info) = decode(&bytes, ch, &lim).unwrap();
        close(&m.values, &want, &format!("rgb8 {ch:?}"));
        assert_eq!(info.color, "rgb");
    }
    // RGBA 16-bit, alpha channel and G.
    let rgba16 = [0u16, 65535, 0, 13107, 65535, 0, 0, 65535];
    let bytes = png(2, 1, C::Rgba, D::Sixteen, &be16(&rgba16));
    let (m, info) = decode(&bytes, Channel::A, &lim).unwrap();
    close(&m.values, &[0.2, 1.0], "rgba16 a");
    assert_eq!((info.color.as_str(), info.bit_depth), ("rgba", 16));
    let (m, _) = decode(&bytes, Channel::G, &lim).unwrap();
    close(&m.values, &[1.0, 0.0], "rgba16 g");
    // RGB 16 and RGBA 8.
    let (m, _) =
        decode(&png(1, 1, C::Rgb, D::Sixteen, &be16(&[0, 0, 65535])), Channel::B, &lim).unwrap();
    close(&m.values, &[1.0], "rgb16 b");
    let (m, _) = decode(&png(1, 1, C::Rgba, D::Eight, &[0, 0, 0, 51]), Channel::A, &lim).unwrap();
    close(&m.values, &[0.2], "rgba8 a");
}

/// Gray + alpha TIFF: the tiff crate has no encoder colour type for it, so declare one.
struct GrayA16;
impl tiff::encoder::colortype::ColorType for GrayA16 {
    type Inner = u16;
    const TIFF_VALUE: tiff::tags::PhotometricInterpretation =
        tiff::tags::PhotometricInterpretation::BlackIsZero;
    const BITS_PER_SAMPLE: &'static [u16] = &[16, 16];
    const SAMPLE_FORMAT: &'static [tiff::tags::SampleFormat] = &[tiff::tags::SampleFormat::Uint; 2];
    fn horizontal_predict(row: &[u16], result: &mut Vec<u16>) {
        result.extend_from_slice(row);
    }
}

fn tiff<C: tiff::encoder::colortype::ColorType>(w: u32, h: u32, data: &[C::Inner]) -> Vec<u8>
where
    [C::Inner]: tiff::encoder::TiffValue,
{
    let mut buf = Cursor::new(Vec::new());
    let mut enc = tiff::encoder::TiffEncoder::new(&mut buf).unwrap();
    enc.write_image::<C>(w, h, data).unwrap();
    buf.into_inner()
}

#[test]
fn tiff_layouts_decode_including_float() {
    use tiff::encoder::colortype as ct;
    let lim = Limits::default();
    let (m, info) = decode(&tiff::<ct::Gray8>(3, 1, &[0, 128, 255]), Channel::Luma, &lim).unwrap();
    close(&m.values, &[0.0, 128.0 / 255.0, 1.0], "tiff gray8");
    assert_eq!((info.format.as_str(), info.color.as_str(), info.bit_depth), ("tiff", "gray", 8));

    let (m, info) =
        decode(&tiff::<ct::Gray16>(1, 3, &[0, 65535, 300]), Channel::Luma, &lim).unwrap();
    assert_eq!((m.width, m.height, info.bit_depth), (1, 3, 16));
    close(&m.values, &[0.0, 1.0, (300.0 / 65535.0f64) as f32], "tiff gray16");

    let (m, info) =
        decode(&tiff::<GrayA16>(2, 1, &[6553, 0, 65535, 65535]), Channel::A, &lim).unwrap();
    close(&m.values, &[(6553.0 / 65535.0f64) as f32, 1.0], "tiff gray+alpha16");
    assert_eq!(info.color, "gray_alpha");

    let (m, info) = decode(&tiff::<ct::RGB8>(1, 1, &[0, 51, 255]), Channel::Luma, &lim).unwrap();
    close(&m.values, &[luma(0.0, 0.2, 1.0)], "tiff rgb8 luma");
    assert_eq!(info.color, "rgb");
    let (m, _) = decode(&tiff::<ct::RGBA16>(1, 1, &[1, 2, 3, 65535]), Channel::A, &lim).unwrap();
    close(&m.values, &[1.0], "tiff rgba16 a");
    let (m, _) = decode(&tiff::<ct::RGBA8>(1, 1, &[1, 2, 51, 9]), Channel::B, &lim).unwrap();
    close(&m.values, &[0.2], "tiff rgba8 b");

    // 32-bit float gray, what terrain tools export: used as is, negative and > 1 included.
    let f = [-3.5f32, 0.0, 1.25, 1000.0, 1e-7, 0.5];
    let (m, info) = decode(&tiff::<ct::Gray32Float>(3, 2, &f), Channel::Luma, &lim).unwrap();
    assert_eq!(m.values, f, "float gray is bit-exact");
    assert_eq!((info.color.as_str(), info.bit_depth, info.float), ("gray", 32, true));

    let rgbf = [0.1f32, 2.0, -1.0, 4.0, 5.0, 6.0];
    let (m, _) = decode(&tiff::<ct::RGB32Float>(2, 1, &rgbf), Channel::G, &lim).unwrap();
    assert_eq!(m.values, [2.0, 5.0]);
    let (m, info) =
        decode(&tiff::<ct::RGBA32Float>(1, 1, &[1.0, 2.0, 3.0, 7.5]), Channel::A, &lim).unwrap();
    assert_eq!(m.values, [7.5]);
    assert_eq!((info.color.as_str(), info.float), ("rgba", true));
}

fn exr_bytes(w: usize, h: usize, channels: Vec<(&str, exr::prelude::FlatSamples)>) -> Vec<u8> {
    use exr::prelude::*;
    let list: SmallVec<[AnyChannel<FlatSamples>; 4]> =
        channels.into_iter().map(|(n, s)| AnyChannel::new(n, s)).collect();
    let layer = Layer::new(
        (w, h),
        LayerAttributes::named("height"),
        Encoding::FAST_LOSSLESS,
        AnyChannels::sort(list),
    );
    let mut out = Cursor::new(Vec::new());
    Image::from_layer(layer).write().to_buffered(&mut out).unwrap();
    out.into_inner()
}

#[test]
fn exr_gray_half_and_rgba_decode() {
    use exr::prelude::{f16, FlatSamples};
    let lim = Limits::default();
    let y = vec![0.0f32, -2.0, 3.25, 100.0, 0.125, 7.0];
    let (m, info) =
        decode(&exr_bytes(3, 2, vec![("Y", FlatSamples::F32(y.clone()))]), Channel::Luma, &lim)
            .unwrap();
    assert_eq!((m.width, m.height), (3, 2));
    assert_eq!(m.values, y);
    assert_eq!((info.format.as_str(), info.color.as_str(), info.float), ("exr", "gray", true));

    // A single channel with any name, stored as half.
    let half: Vec<f16> = [0.5f32, 1.5, -0.25].iter().map(|&v| f16::from_f32(v)).collect();
    let (m, _) =
        decode(&exr_bytes(1, 3, vec![("height", FlatSamples::F16(half))]), Channel::Luma, &lim)
            .unwrap();
    assert_eq!(m.values, [0.5, 1.5, -0.25]);

    let bytes = exr_bytes(
        2,
        1,
        vec![
            ("R", FlatSamples::F32(vec![1.0, 2.0])),
            ("G", FlatSamples::F32(vec![3.0, 4.0])),
            ("B", FlatSamples::F32(vec![5.0, 6.0])),
            ("A", FlatSamples::F32(vec![0.25, 0.75])),
        ],
    );
    let (m, info) = decode(&bytes, Channel::G, &lim).unwrap();
    assert_eq!(m.values, [3.0, 4.0]);
    assert_eq!(info.color, "rgba");
    let (m, _) = decode(&bytes, Channel::A, &lim).unwrap();
    assert_eq!(m.values, [0.25, 0.75]);
    let (m, _) = decode(&bytes, Channel::Luma, &lim).unwrap();
    close(&m.values, &[luma(1.0, 3.0, 5.0), luma(2.0, 4.0, 6.0)], "exr luma");

    // Two unnamed channels: which one is the height is ambiguous.
    let bytes = exr_bytes(
        1,
        1,
        vec![("U", FlatSamples::F32(vec![1.0])), ("V", FlatSamples::F32(vec![2.0]))],
    );
    match decode(&bytes, Channel::Luma, &lim) {
        Err(Error::Unsupported(m)) => assert!(m.contains("U, V"), "{m}"),
        other => panic!("{other:?}"),
    }
    // Infinity in an EXR is rejected with its position.
    let bytes = exr_bytes(2, 2, vec![("Y", FlatSamples::F32(vec![0.0, 0.0, 0.0, f32::INFINITY]))]);
    match decode(&bytes, Channel::Luma, &lim) {
        Err(Error::InvalidInput(m)) => {
            assert!(m.contains("column 1, row 1") && m.contains("inf"), "{m}")
        }
        other => panic!("{other:?}"),
    }
}

/// CRC-32 (ISO-HDLC) as PNG chunks need it.
fn crc32(bytes: &[u8]) -> u32 {
    let mut c = 0xFFFF_FFFFu32;
    for &b in bytes {
        c ^= b as u32;
        for _ in 0..8 {
            c = if c & 1 != 0 { 0xEDB8_8320 ^ (c >> 1) } else { c >> 1 };
        }
    }
    !c
}

/// A PNG signature + IHDR (+ IEND) with valid CRCs, no pixel data: what an attacker sends.
fn png_header(w: u32, h: u32) -> Vec<u8> {
    let mut out = b"\x89PNG\r\n\x1a\n".to_vec();
    let mut chunk = |kind: &[u8], data: &[u8]| {
        out.extend((data.len() as u32).to_be_bytes());
        let mut body = kind.to_vec();
        body.extend_from_slice(data);
        out.extend(&body);
        out.extend(crc32(&body).to_be_bytes());
    };
    let mut ihdr = Vec::new();
    ihdr.extend(w.to_be_bytes());
    ihdr.extend(h.to_be_bytes());
    ihdr.extend([8, 0, 0, 0, 0]); // 8-bit gray, deflate, adaptive filter, no interlace
    chunk(b"IHDR", &ihdr);
    chunk(b"IEND", &[]);
    out
}

#[test]
fn crc_matches_the_png_crate() {
    // A real encoder's IHDR CRC equals ours, so the hand-built headers are valid PNG headers.
    let real = png(5, 7, png::ColorType::Grayscale, png::BitDepth::Eight, &[0; 35]);
    assert_eq!(&real[..33], &png_header(5, 7)[..33]);
}

/// Every unsupported or broken input gets its own error, and the messages differ.
#[test]
fn broken_inputs_each_get_a_clear_error() {
    let lim = Limits::default();
    let mut messages = Vec::new();

    // Truncated PNG: a real 32×32 image cut in the middle of its pixel data.
    let data: Vec<u8> = (0..32 * 32).map(|k| (k * 37 % 251) as u8).collect();
    let full = png(32, 32, png::ColorType::Grayscale, png::BitDepth::Eight, &data);
    let e = decode(&full[..full.len() / 2], Channel::Luma, &lim).unwrap_err();
    assert!(matches!(e, Error::Decode(_)), "{e:?}");
    assert!(e.to_string().contains("truncated") || e.to_string().contains("EOF"), "{e}");
    messages.push(e.to_string());

    // A JPEG.
    let jpeg =
        [0xFF, 0xD8, 0xFF, 0xE0, 0x00, 0x10, b'J', b'F', b'I', b'F', 0, 1, 1, 0, 0, 1, 0, 1, 0, 0];
    let e = decode(&jpeg, Channel::Luma, &lim).unwrap_err();
    assert!(
        matches!(&e, Error::Unsupported(m) if m.contains("JPG") || m.contains("JPEG")),
        "{e:?}"
    );
    messages.push(e.to_string());

    // Not an image at all.
    let e = decode(b"hello, world\n", Channel::Luma, &lim).unwrap_err();
    assert!(matches!(&e, Error::Unsupported(m) if m.contains("signature")), "{e:?}");
    messages.push(e.to_string());

    // Empty.
    let e = decode(&[], Channel::Luma, &lim).unwrap_err();
    assert!(matches!(&e, Error::Unsupported(m) if m.contains("empty")), "{e:?}");
    messages.push(e.to_string());

    // 0×0 header.
    let e = decode(&png_header(0, 0), Channel::Luma, &lim).unwrap_err();
    assert!(matches!(&e, Error::InvalidInput(m) if m.contains("0×0")), "{e:?}");
    messages.push(e.to_string());

    // 100000×100000 header: rejected from the header, before any allocation, in milliseconds.
    let huge = png_header(100_000, 100_000);
    let t = std::time::Instant::now();
    let e = decode(&huge, Channel::Luma, &lim).unwrap_err();
    let probe_err = probe(&huge, &lim).unwrap_err();
    let elapsed = t.elapsed();
    assert!(elapsed.as_millis() < 50, "took {elapsed:?}: the header check must come first");
    match &e {
        Error::Limits(LimitError::Dimensions { width: 100_000, height: 100_000, max_dim }) => {
            assert_eq!(*max_dim, lim.max_dim)
        }
        other => panic!("{other:?}"),
    }
    assert_eq!(e.to_string(), probe_err.to_string());
    assert!(e.to_string().contains("100000×100000"), "{e}");
    messages.push(e.to_string());

    // Within each side's limit but over the texel budget.
    let small =
        Limits { max_dim: 1000, max_texels: 10_000, max_bytes: 1 << 20, ..Limits::default() };
    let e = decode(&png_header(200, 100), Channel::Luma, &small).unwrap_err();
    assert!(matches!(e, Error::Limits(LimitError::Texels { texels: 20_000, .. })), "{e:?}");
    messages.push(e.to_string());
    let e = decode(&full, Channel::Luma, &Limits { max_bytes: 100, ..small }).unwrap_err();
    assert!(matches!(e, Error::Limits(LimitError::Bytes { max_bytes: 100, .. })), "{e:?}");
    messages.push(e.to_string());

    // NaN in a float TIFF, named by position.
    let mut f = vec![0.5f32; 4 * 3];
    f[4 + 2] = f32::NAN; // column 2, row 1
    let e = decode(&tiff::<tiff::encoder::colortype::Gray32Float>(4, 3, &f), Channel::Luma, &lim)
        .unwrap_err();
    assert!(
        matches!(&e, Error::InvalidInput(m) if m.contains("column 2, row 1") && m.contains("NaN")),
        "{e:?}"
    );
    messages.push(e.to_string());

    // Truncated TIFF.
    let t = tiff::<tiff::encoder::colortype::Gray16>(16, 16, &[7u16; 256]);
    let e = decode(&t[..40], Channel::Luma, &lim).unwrap_err();
    assert!(matches!(e, Error::Decode(_)), "{e:?}");
    messages.push(e.to_string());

    // Parameters: each names its field.
    for (k, v) in [("height_scale", "-2"), ("bins", "40"), ("radius", "0")] {
        let e = BakeParams::from_pairs([(k, v)]).unwrap_err();
        match &e {
            Error::Param { field, .. } => assert_eq!(field, k),
            other => panic!("{other:?}"),
        }
        assert!(e.to_string().contains(k), "{e}");
        messages.push(e.to_string());
    }

    for (i, a) in messages.iter().enumerate() {
        assert!(!a.contains('\n'), "one line: {a}");
        for b in &messages[i + 1..] {
            assert_ne!(a, b, "two failures share one message");
        }
    }
}

/// A hand-built little-endian TIFF header (one IFD, one strip) declaring `w × h` 8-bit gray, with
/// no pixel data behind it.
fn tiff_header(w: u32, h: u32) -> Vec<u8> {
    let entries: [(u16, u16, u32); 8] = [
        (256, 4, w),       // ImageWidth, LONG
        (257, 4, h),       // ImageLength
        (258, 3, 8),       // BitsPerSample, SHORT
        (259, 3, 1),       // Compression: none
        (262, 3, 1),       // PhotometricInterpretation: BlackIsZero
        (273, 4, 1 << 20), // StripOffsets: past the end of the file
        (277, 3, 1),       // SamplesPerPixel
        (279, 4, 16),      // StripByteCounts
    ];
    let mut out = b"II*\0".to_vec();
    out.extend(8u32.to_le_bytes());
    out.extend((entries.len() as u16).to_le_bytes());
    for (tag, ty, value) in entries {
        out.extend(tag.to_le_bytes());
        out.extend(ty.to_le_bytes());
        out.extend(1u32.to_le_bytes());
        if ty == 3 {
            out.extend((value as u16).to_le_bytes());
            out.extend([0, 0]);
        } else {
            out.extend(value.to_le_bytes());
        }
    }
    out.extend(0u32.to_le_bytes());
    out
}

#[test]
fn huge_tiff_header_is_rejected_before_decoding() {
    let lim = Limits::default();
    let t = std::time::Instant::now();
    let e = decode(&tiff_header(100_000, 100_000), Channel::Luma, &lim).unwrap_err();
    assert!(t.elapsed().as_millis() < 50, "took {:?}", t.elapsed());
    assert!(
        matches!(e, Error::Limits(LimitError::Dimensions { width: 100_000, height: 100_000, .. })),
        "{e:?}"
    );
    // The same header at a small size gets as far as the missing pixel data: truncated.
    let e = decode(&tiff_header(4, 4), Channel::Luma, &lim).unwrap_err();
    assert!(matches!(e, Error::Decode(_)), "{e:?}");
}

#[test]
fn huge_exr_header_is_rejected_before_decoding() {
    use exr::prelude::FlatSamples;
    let mut bytes = exr_bytes(2, 2, vec![("Y", FlatSamples::F32(vec![0.0; 4]))]);
    // Patch the data window (box2i: xMin, yMin, xMax, yMax) to 100000 × 100000.
    let key = b"dataWindow\0box2i\0";
    let at = bytes.windows(key.len()).position(|w| w == key).unwrap() + key.len() + 4;
    bytes[at + 8..at + 12].copy_from_slice(&99_999i32.to_le_bytes());
    bytes[at + 12..at + 16].copy_from_slice(&99_999i32.to_le_bytes());
    let t = std::time::Instant::now();
    let e = decode(&bytes, Channel::Luma, &Limits::default()).unwrap_err();
    assert!(t.elapsed().as_millis() < 50, "took {:?}", t.elapsed());
    assert!(
        matches!(e, Error::Limits(LimitError::Dimensions { width: 100_000, height: 100_000, .. })),
        "{e:?}"
    );
}

#[test]
fn inverted_exr_data_window_is_refused_at_the_header_check() {
    // xMax < xMin (or yMax < yMin) describes no image at all: the header check (which the
    // service runs before it answers 202) must refuse it, as a decoding error (415), rather than
    // let a bake fail later or size a buffer from a wrapped-around width.
    use exr::prelude::FlatSamples;
    let key = b"dataWindow\0box2i\0";
    for (field, value) in [(8usize, -5i32), (12, -3), (8, i32::MIN)] {
        let mut bytes = exr_bytes(4, 4, vec![("Y", FlatSamples::F32(vec![0.5; 16]))]);
        let at = bytes.windows(key.len()).position(|w| w == key).unwrap() + key.len() + 4;
        bytes[at + field..at + field + 4].copy_from_slice(&value.to_le_bytes());
        let e = probe(&bytes, &Limits::default()).unwrap_err();
        assert!(matches!(e, Error::Decode(_)), "field {field} = {value}: {e:?}");
        assert!(e.to_string().contains("data window"), "{e}");
        let d = decode(&bytes, Channel::Luma, &Limits::default()).unwrap_err();
        assert_eq!(d.to_string(), e.to_string());
    }
}

/// A half-float EXR reports the bit depth it stores (16), a float one 32; out-of-range float
/// heights are the input's fault (an `InvalidInput` naming the range, not `height_scale`).
#[test]
fn exr_half_bit_depth_and_out_of_range_floats() {
    use exr::prelude::{f16, FlatSamples};
    let lim = Limits::default();
    let half = exr_bytes(2, 2, vec![("Y", FlatSamples::F16(vec![f16::from_f32(0.5); 4]))]);
    let (_, info) = decode(&half, Channel::Luma, &lim).unwrap();
    assert_eq!((info.bit_depth, info.float), (16, true));
    let float = exr_bytes(2, 2, vec![("Y", FlatSamples::F32(vec![0.5; 4]))]);
    assert_eq!(decode(&float, Channel::Luma, &lim).unwrap().1.bit_depth, 32);
    let huge = exr_bytes(2, 2, vec![("Y", FlatSamples::F32(vec![0.5, 3.0e38, 0.5, 0.5]))]);
    match decode(&huge, Channel::Luma, &lim) {
        Err(Error::InvalidInput(m)) => {
            assert!(m.contains("out of range") && !m.contains("height_scale"), "{m}")
        }
        other => panic!("expected InvalidInput, got {other:?}"),
    }
}
