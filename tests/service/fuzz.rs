//! Property tests as a fuzzer: arbitrary and mutated bytes into every decoder (PNG, TIFF, EXR;
//! headers and bodies) and arbitrary strings into every parameter parser. Whatever the input:
//! no panic, and every failure is a typed error that the service answers with a 4xx.

use horizon_bake::encode::exr::ExrPrecision;
use horizon_bake::encode::png::{encode16, encode8, PngColor};
use horizon_bake::encode::{Formats, TexturePrecision};
use horizon_bake::error::Error;
use horizon_bake::heightmap::{check_submission, decode, probe, Limits};
use horizon_bake::params::{json_object_pairs, BakeParams, Channel, PARAM_NAMES};
use horizon_bake::preview::{PreviewParams, PREVIEW_PARAM_NAMES};
use horizon_bake::service::problem::Problem;
use proptest::prelude::*;
use std::io::Cursor;

/// Small limits: a mutated header may claim anything, and the limits must catch it before a
/// decoder allocates.
const LIMITS: Limits =
    Limits { max_dim: 512, max_texels: 64 * 1024, max_bytes: 1 << 20, max_decode_bytes: u64::MAX };

/// A decoder failure must be the input's fault (4xx), never ours.
fn client_fault(e: &Error) -> Result<(), TestCaseError> {
    let status = Problem::from(clone_kind(e)).status;
    prop_assert!((400..500).contains(&status), "{e:?} would be answered {status}");
    Ok(())
}

/// `Problem::from` takes the error by value; rebuild one of the same kind.
fn clone_kind(e: &Error) -> Error {
    match e {
        Error::Decode(m) => Error::Decode(m.clone()),
        Error::Unsupported(m) => Error::Unsupported(m.clone()),
        Error::InvalidInput(m) => Error::InvalidInput(m.clone()),
        Error::Param { field, message } => Error::param(field.clone(), message.clone()),
        Error::Limits(l) => Error::Limits(l.clone()),
        Error::Canceled => Error::Canceled,
        Error::Io(io) => Error::Io(std::io::Error::new(io.kind(), io.to_string())),
        Error::Internal(m) => Error::Internal(m.clone()),
        Error::Unavailable(m) => Error::Unavailable(m.clone()),
        Error::StorageFull { store, cause } => Error::StorageFull { store, cause: cause.clone() },
        Error::MemoryBusy { needed, in_use, budget } => {
            Error::MemoryBusy { needed: *needed, in_use: *in_use, budget: *budget }
        }
    }
}

fn all_decoders(bytes: &[u8]) -> Result<(), TestCaseError> {
    for r in [probe(bytes, &LIMITS).map(|_| ())] {
        if let Err(e) = r {
            client_fault(&e)?;
        }
    }
    for channel in [Channel::Luma, Channel::A] {
        if let Err(e) = decode(bytes, channel, &LIMITS) {
            client_fault(&e)?;
        }
        if let Err(e) = check_submission(bytes, channel, &LIMITS) {
            client_fault(&e)?;
        }
    }
    Ok(())
}

fn tiff_gray16(w: u32, h: u32) -> Vec<u8> {
    let data: Vec<u16> = (0..w * h).map(|k| (k * 977 % 65536) as u16).collect();
    let mut out = Cursor::new(Vec::new());
    tiff::encoder::TiffEncoder::new(&mut out)
        .unwrap()
        .write_image::<tiff::encoder::colortype::Gray16>(w, h, &data)
        .unwrap();
    out.into_inner()
}

fn tiff_f32(w: u32, h: u32) -> Vec<u8> {
    let data: Vec<f32> = (0..w * h).map(|k| k as f32 * 0.25 - 3.0).collect();
    let mut out = Cursor::new(Vec::new());
    tiff::encoder::TiffEncoder::new(&mut out)
        .unwrap()
        .write_image::<tiff::encoder::colortype::Gray32Float>(w, h, &data)
        .unwrap();
    out.into_inner()
}

fn exr_y(w: usize, h: usize, half: bool) -> Vec<u8> {
    use exr::prelude::*;
    let values: Vec<f32> = (0..w * h).map(|k| k as f32 * 0.5).collect();
    let samples = if half {
        FlatSamples::F16(values.iter().map(|&v| f16::from_f32(v)).collect())
    } else {
        FlatSamples::F32(values)
    };
    let list: SmallVec<[AnyChannel<FlatSamples>; 4]> =
        std::iter::once(AnyChannel::new("Y", samples)).collect();
    let layer = Layer::new(
        (w, h),
        LayerAttributes::named("h"),
        Encoding::FAST_LOSSLESS,
        AnyChannels::sort(list),
    );
    let mut out = Cursor::new(Vec::new());
    Image::from_layer(layer).write().to_buffered(&mut out).unwrap();
    out.into_inner()
}

/// Valid inputs of every format and layout to mutate.
fn seeds() -> Vec<Vec<u8>> {
    let g8: Vec<u8> = (0..12 * 9).map(|k| (k * 37 % 256) as u8).collect();
    let rgba16: Vec<u16> = (0..7 * 5 * 4).map(|k| (k * 4099 % 65536) as u16).collect();
    vec![
        encode8(12, 9, PngColor::Gray, &g8).unwrap(),
        encode16(7, 5, PngColor::Rgba, &rgba16).unwrap(),
        tiff_gray16(6, 5),
        tiff_f32(5, 4),
        exr_y(6, 4, false),
        exr_y(3, 5, true),
    ]
}

/// One mutation of a valid file: overwrite, insert, delete or truncate, near the header
/// (`at` small) or anywhere.
#[derive(Debug, Clone)]
enum Mutation {
    Set(usize, u8),
    Insert(usize, Vec<u8>),
    Remove(usize, usize),
    Truncate(usize),
}

fn mutation() -> impl Strategy<Value = Mutation> {
    let at = prop_oneof![0usize..64, 0usize..4096];
    prop_oneof![
        (at.clone(), any::<u8>()).prop_map(|(a, b)| Mutation::Set(a, b)),
        (at.clone(), proptest::collection::vec(any::<u8>(), 1..16))
            .prop_map(|(a, v)| Mutation::Insert(a, v)),
        (at.clone(), 1usize..32).prop_map(|(a, n)| Mutation::Remove(a, n)),
        at.prop_map(Mutation::Truncate),
    ]
}

fn apply(mut bytes: Vec<u8>, ms: &[Mutation]) -> Vec<u8> {
    for m in ms {
        let len = bytes.len().max(1);
        match m {
            Mutation::Set(a, b) => {
                if !bytes.is_empty() {
                    bytes[a % len] = *b;
                }
            }
            Mutation::Insert(a, v) => {
                let at = a % (bytes.len() + 1);
                bytes.splice(at..at, v.iter().copied());
            }
            Mutation::Remove(a, n) => {
                let at = a % len;
                let end = (at + n).min(bytes.len());
                if at < end {
                    bytes.drain(at..end);
                }
            }
            Mutation::Truncate(a) => bytes.truncate(a % len),
        }
    }
    bytes
}

fn any_text() -> impl Strategy<Value = String> {
    prop_oneof![
        any::<String>(),
        "[-+0-9.eEaA-Za-z_,;= ]{0,24}",
        Just("NaN".to_owned()),
        Just("inf".to_owned()),
        Just("1e400".to_owned()),
        Just("-0".to_owned()),
        Just("4294967296".to_owned()),
    ]
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 2000, .. ProptestConfig::default() })]

    #[test]
    fn arbitrary_bytes_never_panic_a_decoder(
        magic in prop_oneof![
            Just(b"\x89PNG\r\n\x1a\n".to_vec()),
            Just(b"II*\0".to_vec()),
            Just(b"MM\0*".to_vec()),
            Just(vec![0x76, 0x2f, 0x31, 0x01]),
            Just(Vec::new()),
        ],
        rest in proptest::collection::vec(any::<u8>(), 0..600),
    ) {
        let mut bytes = magic;
        bytes.extend_from_slice(&rest);
        all_decoders(&bytes)?;
    }

    #[test]
    fn mutated_inputs_never_panic_a_decoder(
        seed in 0usize..6,
        ms in proptest::collection::vec(mutation(), 1..5),
    ) {
        let bytes = apply(seeds()[seed].clone(), &ms);
        all_decoders(&bytes)?;
    }

    #[test]
    fn every_bake_parameter_parser_names_its_key(key in 0usize..PARAM_NAMES.len(), v in any_text()) {
        let key = PARAM_NAMES[key];
        let mut p = BakeParams::default();
        if let Err(e) = p.set(key, &v) {
            match e {
                Error::Param { field, .. } => prop_assert_eq!(field, key),
                other => prop_assert!(false, "{key}={v:?}: {other:?}"),
            }
        }
    }

    #[test]
    fn every_preview_parameter_parser_names_its_key(
        key in 0usize..PREVIEW_PARAM_NAMES.len(), v in any_text(),
    ) {
        let key = PREVIEW_PARAM_NAMES[key];
        let mut p = PreviewParams::default();
        if let Err(e) = p.set(key, &v) {
            match e {
                Error::Param { field, .. } => prop_assert_eq!(field, key),
                other => prop_assert!(false, "{key}={v:?}: {other:?}"),
            }
        }
    }

    #[test]
    fn other_parsers_and_unknown_keys_are_param_errors(k in any_text(), v in any_text()) {
        for r in [
            Formats::parse(&v, TexturePrecision::Unorm8).map(|_| ()),
            TexturePrecision::parse(&v).map(|_| ()),
            ExrPrecision::parse("exr_precision", &v).map(|_| ()),
            BakeParams::from_pairs([(k.as_str(), v.as_str()), (k.as_str(), v.as_str())]).map(|_| ()),
            PreviewParams::default().set(&k, &v),
        ] {
            if let Err(e) = r {
                prop_assert!(matches!(e, Error::Param { .. }), "{k:?}={v:?}: {e:?}");
            }
        }
    }

    #[test]
    fn params_json_never_panics(text in prop_oneof![
        any::<String>(),
        "\\{(\"[a-z_]{1,12}\": ?(-?[0-9]{1,4}|\"[a-z0-9,]{0,8}\"|null|true|\\[\\]), ?){0,4}\\}",
    ]) {
        match json_object_pairs(text.as_bytes()) {
            Ok(pairs) => {
                let mut seen = std::collections::HashSet::new();
                for (k, _) in &pairs {
                    prop_assert!(seen.insert(k.clone()), "duplicate {k} accepted");
                }
            }
            Err(e) => prop_assert!(matches!(e, Error::Param { .. }), "{e:?}"),
        }
    }
}
