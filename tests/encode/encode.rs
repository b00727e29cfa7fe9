//! The texture writers, proven by independent readers: every KTX2 file is parsed by the `ktx2`
//! crate (header, DFD compared with the one that crate generates for the format, every texel of
//! every layer/face), every DDS file by `ddsfile`'s reader, EXR by the `exr` crate, PNG by
//! `image`. Sample values are chosen so that a swapped layer, face, channel or byte order shows.

use crate::support::Rng;
use horizon_bake::bake::{self, HorizonLayers, Precisions};
use horizon_bake::encode::{self, dds, ktx2 as kw, Formats, Shape, Texels, TexturePrecision};
use horizon_bake::heightmap::HeightMap;
use horizon_bake::kernels::cubemap;
use horizon_bake::params::BakeParams;
use horizon_bake::progress::Progress;
use ktx2::{dfd, Format, Reader};

/// Distinct samples: value k of image `img` (as f64 in [0, 1]).
fn sample(img: usize, k: usize, n: usize) -> f64 {
    ((img * n + k) as f64 * 0.618_033_988_75).fract()
}

fn u8_images(w: usize, h: usize, count: usize) -> Vec<Vec<u8>> {
    let n = w * h * 4;
    (0..count).map(|i| (0..n).map(|k| (sample(i, k, n) * 255.0) as u8).collect()).collect()
}
fn u16_images(w: usize, h: usize, count: usize) -> Vec<Vec<u16>> {
    let n = w * h * 4;
    (0..count).map(|i| (0..n).map(|k| (sample(i, k, n) * 65535.0) as u16).collect()).collect()
}
fn f32_images(w: usize, h: usize, count: usize) -> Vec<Vec<f32>> {
    let n = w * h * 4;
    (0..count).map(|i| (0..n).map(|k| sample(i, k, n) as f32 - 0.25).collect()).collect()
}
fn i8_images(w: usize, h: usize, count: usize) -> Vec<Vec<i8>> {
    let n = w * h * 4;
    (0..count).map(|i| (0..n).map(|k| (sample(i, k, n) * 254.0 - 127.0) as i8).collect()).collect()
}

fn le_bytes(t: &Texels<'_>) -> Vec<u8> {
    let mut v = Vec::new();
    t.extend_le(&mut v);
    v
}

/// Reads `bytes` with the `ktx2` crate and checks the header, the DFD and every texel.
fn check_ktx2(bytes: &[u8], w: usize, h: usize, shape: Shape, images: &[Texels<'_>], fmt: Format) {
    let r = Reader::new(bytes).expect("ktx2 crate parses our file");
    let hd = r.header();
    assert_eq!(hd.format, Some(fmt));
    assert_eq!((hd.pixel_width, hd.pixel_height, hd.pixel_depth), (w as u32, h as u32, 0));
    match shape {
        Shape::Array(n) => assert_eq!((hd.layer_count, hd.face_count), (n, 1)),
        Shape::Cube => assert_eq!((hd.layer_count, hd.face_count), (0, 6)),
    }
    assert_eq!(hd.level_count, 1);
    assert!(hd.supercompression_scheme.is_none());
    let (want_dfd, type_size) = dfd::Basic::from_format(fmt).unwrap();
    assert_eq!(hd.type_size, type_size);
    assert_eq!(r.basic_dfd(), Some(&want_dfd), "DFD differs from the ktx2 crate's for {fmt:?}");
    let levels: Vec<_> = r.levels().collect();
    assert_eq!(levels.len(), 1);
    let data = levels[0].data;
    assert_eq!(levels[0].uncompressed_byte_length as usize, data.len());
    // Level data offset must be aligned to the texel size (KTX2 §3.9 "lcm(texel size, 4)").
    let offset = data.as_ptr() as usize - bytes.as_ptr() as usize;
    assert_eq!(offset % (4 * type_size as usize).max(4), 0);
    let per = data.len() / images.len();
    assert_eq!(per * images.len(), data.len());
    for (i, img) in images.iter().enumerate() {
        assert_eq!(&data[i * per..(i + 1) * per], &le_bytes(img)[..], "image {i} of {fmt:?}");
    }
}

#[test]
fn ktx2_array_textures_read_back_texel_for_texel() {
    for (w, h) in [(1, 1), (1, 5), (7, 1), (13, 9)] {
        let a8 = u8_images(w, h, 2);
        let t8 = [Texels::Unorm8(&a8[0]), Texels::Unorm8(&a8[1])];
        let a16 = u16_images(w, h, 2);
        let t16 = [Texels::Unorm16(&a16[0]), Texels::Unorm16(&a16[1])];
        let a32 = f32_images(w, h, 2);
        let t32 = [Texels::Float32(&a32[0]), Texels::Float32(&a32[1])];
        for (imgs, fmt) in [
            (&t8, Format::R8G8B8A8_UNORM),
            (&t16, Format::R16G16B16A16_UNORM),
            (&t32, Format::R32G32B32A32_SFLOAT),
        ] {
            let bytes = kw::encode(w, h, Shape::Array(2), imgs).unwrap();
            check_ktx2(&bytes, w, h, Shape::Array(2), imgs, fmt);
        }
        // Explicit values, not only bytes round-tripping: texel (x, y) of layer 1, channel B.
        let bytes = kw::encode(w, h, Shape::Array(2), &t16).unwrap();
        let r = Reader::new(&bytes[..]).unwrap();
        let data = r.levels().next().unwrap().data;
        let (x, y) = (w - 1, h - 1);
        let k = (w * h * 4) + (y * w + x) * 4 + 2;
        assert_eq!(u16::from_le_bytes([data[2 * k], data[2 * k + 1]]), a16[1][(y * w + x) * 4 + 2]);
    }
}

#[test]
fn ktx2_cube_map_is_snorm_with_six_faces_in_order() {
    for size in [1usize, 3, 16] {
        let factors = cubemap::cube_factors(size);
        let snorm: Vec<i8> = factors.iter().map(|&f| cubemap::snorm8(f)).collect();
        let faces: Vec<Texels<'_>> =
            snorm.chunks_exact(size * size * 4).map(Texels::Snorm8).collect();
        let bytes = kw::encode(size, size, Shape::Cube, &faces).unwrap();
        check_ktx2(&bytes, size, size, Shape::Cube, &faces, Format::R8G8B8A8_SNORM);
        // Decode as a GPU would (v/127) and compare with the factors: zero is exact.
        let r = Reader::new(&bytes[..]).unwrap();
        let data = r.levels().next().unwrap().data;
        for (k, (&b, &f)) in data.iter().zip(&factors).enumerate() {
            let v = b as i8 as f32 / 127.0;
            assert!((v - f).abs() <= 0.5 / 127.0 + 1e-6, "texel value {k}: {v} vs {f}");
            if f == 0.0 {
                assert_eq!(b, 0, "texel value {k}: zero must be exact");
            }
        }
    }
    let other = i8_images(2, 2, 6);
    let faces: Vec<Texels<'_>> = other.iter().map(|f| Texels::Snorm8(f)).collect();
    let bytes = kw::encode(2, 2, Shape::Cube, &faces).unwrap();
    check_ktx2(&bytes, 2, 2, Shape::Cube, &faces, Format::R8G8B8A8_SNORM);
}

#[test]
fn dds_array_and_cube_read_back() {
    use ddsfile::{Dds, DxgiFormat, MiscFlag};
    let (w, h) = (5, 3);
    let a16 = u16_images(w, h, 2);
    let t16 = [Texels::Unorm16(&a16[0]), Texels::Unorm16(&a16[1])];
    let a32 = f32_images(w, h, 2);
    let t32 = [Texels::Float32(&a32[0]), Texels::Float32(&a32[1])];
    let a8 = u8_images(w, h, 2);
    let t8 = [Texels::Unorm8(&a8[0]), Texels::Unorm8(&a8[1])];
    for (imgs, fmt) in [
        (&t8, DxgiFormat::R8G8B8A8_UNorm),
        (&t16, DxgiFormat::R16G16B16A16_UNorm),
        (&t32, DxgiFormat::R32G32B32A32_Float),
    ] {
        let bytes = dds::encode(w, h, Shape::Array(2), imgs).unwrap();
        let d = Dds::read(&bytes[..]).unwrap();
        assert_eq!(d.get_dxgi_format(), Some(fmt));
        assert_eq!((d.get_width(), d.get_height()), (w as u32, h as u32));
        assert_eq!(d.get_num_array_layers(), 2);
        assert_eq!(d.get_num_mipmap_levels(), 1);
        assert!(!d.header10.as_ref().unwrap().misc_flag.contains(MiscFlag::TEXTURECUBE));
        for (l, img) in imgs.iter().enumerate() {
            assert_eq!(d.get_data(l as u32).unwrap(), &le_bytes(img)[..], "{fmt:?} layer {l}");
        }
    }
    let size = 4;
    let snorm: Vec<i8> = cubemap::cube_factors(size).iter().map(|&f| cubemap::snorm8(f)).collect();
    let faces: Vec<Texels<'_>> = snorm.chunks_exact(size * size * 4).map(Texels::Snorm8).collect();
    let bytes = dds::encode(size, size, Shape::Cube, &faces).unwrap();
    let d = Dds::read(&bytes[..]).unwrap();
    assert_eq!(d.get_dxgi_format(), Some(DxgiFormat::R8G8B8A8_SNorm));
    let h10 = d.header10.as_ref().unwrap();
    assert!(h10.misc_flag.contains(MiscFlag::TEXTURECUBE));
    assert_eq!(h10.array_size, 1);
    assert!(d.header.caps2.contains(ddsfile::Caps2::CUBEMAP));
    assert_eq!(d.get_num_array_layers(), 6);
    for (f, img) in faces.iter().enumerate() {
        assert_eq!(d.get_data(f as u32).unwrap(), &le_bytes(img)[..], "face {f}");
    }
}

#[test]
fn mismatched_images_are_errors_not_panics() {
    let a = vec![0u8; 2 * 2 * 4];
    let b = vec![0u16; 2 * 2 * 4];
    let short = vec![0u8; 3];
    for enc in [kw::encode, dds::encode] {
        assert!(enc(2, 2, Shape::Array(2), &[Texels::Unorm8(&a)]).is_err());
        assert!(enc(2, 2, Shape::Array(2), &[Texels::Unorm8(&a), Texels::Unorm16(&b)]).is_err());
        assert!(enc(2, 2, Shape::Array(2), &[Texels::Unorm8(&a), Texels::Unorm8(&short)]).is_err());
        assert!(enc(0, 2, Shape::Array(1), &[Texels::Unorm8(&[])]).is_err());
    }
}

fn read_exr_rgba(bytes: &[u8]) -> (usize, usize, Vec<f32>) {
    use exr::prelude::*;
    let img = read()
        .no_deep_data()
        .largest_resolution_level()
        .rgba_channels(
            |res, _| (res.width(), vec![0f32; res.width() * res.height() * 4]),
            |(w, buf): &mut (usize, Vec<f32>),
             p: Vec2<usize>,
             (r, g, b, a): (f32, f32, f32, f32)| {
                let k = (p.y() * *w + p.x()) * 4;
                buf[k..k + 4].copy_from_slice(&[r, g, b, a]);
            },
        )
        .first_valid_layer()
        .all_attributes()
        .from_buffered(std::io::Cursor::new(bytes))
        .unwrap();
    let size = img.layer_data.size;
    (size.width(), size.height(), img.layer_data.channel_data.pixels.1)
}

/// A real bake through `horizon_files`: every file it writes decodes to the baked layers.
#[test]
fn horizon_files_hold_the_baked_layers() {
    let mut rng = Rng(7);
    let (w, h) = (11, 6);
    let values: Vec<f32> = (0..w * h).map(|_| rng.f32()).collect();
    let map = HeightMap::from_values(w, h, values).unwrap();
    let params = BakeParams::from_pairs([("radius", "4"), ("height_scale", "6")]).unwrap();
    let (layers, _) = bake::bake_horizon(&map, &params, Precisions::ALL, &Progress::new()).unwrap();
    let l8 = layers.u8.as_ref().unwrap();
    let l16 = layers.u16.as_ref().unwrap();
    let l32 = layers.f32.as_ref().unwrap();
    assert!(l32[0].iter().any(|&v| v > 0.05), "the test map must have some horizon");

    let files = |list: &str, p: TexturePrecision| {
        let f = Formats::parse(list, p).unwrap();
        encode::horizon_files(&layers, &f).unwrap()
    };
    let get = |fs: &[encode::OutFile], name: &str| -> Vec<u8> {
        fs.iter().find(|f| f.name == name).unwrap_or_else(|| panic!("{name} missing")).bytes.clone()
    };

    let fs = files("png8,exr,ktx2,dds", TexturePrecision::Unorm8);
    let names: Vec<&str> = fs.iter().map(|f| f.name).collect();
    assert_eq!(
        names,
        [
            "horizon_0.png",
            "horizon_1.png",
            "horizon_0.exr",
            "horizon_1.exr",
            "horizon.ktx2",
            "horizon.dds"
        ]
    );
    for l in 0..2 {
        let png = image::load_from_memory(&get(&fs, &format!("horizon_{l}.png"))).unwrap();
        assert_eq!(png.color(), image::ColorType::Rgba8);
        assert_eq!(png.to_rgba8().as_raw(), &l8[l]);
        let (ew, eh, px) = read_exr_rgba(&get(&fs, &format!("horizon_{l}.exr")));
        assert_eq!((ew, eh), (w, h));
        assert_eq!(px, l32[l], "exr layer {l} must be bit-exact");
    }
    let t8 = [Texels::Unorm8(&l8[0]), Texels::Unorm8(&l8[1])];
    check_ktx2(&get(&fs, "horizon.ktx2"), w, h, Shape::Array(2), &t8, Format::R8G8B8A8_UNORM);
    let d = ddsfile::Dds::read(&get(&fs, "horizon.dds")[..]).unwrap();
    assert_eq!(d.get_data(1).unwrap(), &l8[1][..]);

    let fs = files("png16,ktx2", TexturePrecision::Unorm16);
    for (l, layer) in l16.iter().enumerate() {
        let png = image::load_from_memory(&get(&fs, &format!("horizon_{l}.png"))).unwrap();
        assert_eq!(png.color(), image::ColorType::Rgba16);
        assert_eq!(png.to_rgba16().as_raw(), layer);
    }
    let t16 = [Texels::Unorm16(&l16[0]), Texels::Unorm16(&l16[1])];
    check_ktx2(&get(&fs, "horizon.ktx2"), w, h, Shape::Array(2), &t16, Format::R16G16B16A16_UNORM);

    let fs = files("ktx2", TexturePrecision::Float32);
    let t32 = [Texels::Float32(&l32[0]), Texels::Float32(&l32[1])];
    check_ktx2(&get(&fs, "horizon.ktx2"), w, h, Shape::Array(2), &t32, Format::R32G32B32A32_SFLOAT);

    // Each precision agrees with the f32 values as SPEC §2 quantises them.
    for l in 0..2 {
        for k in 0..l32[l].len() {
            assert_eq!(l8[l][k], encode::quantize8(l32[l][k]));
            assert_eq!(l16[l][k], encode::quantize16(l32[l][k]));
        }
    }
}

#[test]
fn sqrt_encoding_stores_the_root() {
    let mut rng = Rng(11);
    let (w, h) = (9, 7);
    let values: Vec<f32> = (0..w * h).map(|_| rng.f32()).collect();
    let map = HeightMap::from_values(w, h, values).unwrap();
    let lin = BakeParams::from_pairs([("radius", "3")]).unwrap();
    let sq = BakeParams::from_pairs([("radius", "3"), ("encoding", "sqrt")]).unwrap();
    let p = Precisions { u8: true, u16: false, f32: true };
    let (a, _) = bake::bake_horizon(&map, &lin, p, &Progress::new()).unwrap();
    let (b, _) = bake::bake_horizon(&map, &sq, p, &Progress::new()).unwrap();
    let (a, b): (&HorizonLayers, &HorizonLayers) = (&a, &b);
    let mut nonzero = 0;
    for l in 0..2 {
        for (k, (&s, &r)) in
            a.f32.as_ref().unwrap()[l].iter().zip(&b.f32.as_ref().unwrap()[l]).enumerate()
        {
            assert!((r - s.sqrt()).abs() < 1e-6, "layer {l} value {k}: {r} vs sqrt({s})");
            assert_eq!(b.u8.as_ref().unwrap()[l][k], encode::quantize8(s.sqrt()));
            nonzero += (s > 0.01) as usize;
        }
    }
    assert!(nonzero > 0);
}

/// Little-endian u32 at byte `o`.
fn u32_at(b: &[u8], o: usize) -> u32 {
    u32::from_le_bytes(b[o..o + 4].try_into().unwrap())
}

/// SPEC §8: a DX10 DDS sets only DDPF_FOURCC (0x4) in its pixel format, FourCC `DX10`, zero
/// bit count and masks (a reader that sees DDPF_RGB reads the zero masks instead of the DXGI
/// format: Pillow decoded 1.9% of a layer right), mip count and array size filled.
#[test]
fn dds_pixel_format_is_fourcc_only_next_to_dx10() {
    let (w, h) = (6, 5);
    let a8 = u8_images(w, h, 2);
    let t8 = [Texels::Unorm8(&a8[0]), Texels::Unorm8(&a8[1])];
    let size = 4;
    let snorm: Vec<i8> = cubemap::cube_factors(size).iter().map(|&f| cubemap::snorm8(f)).collect();
    let faces: Vec<Texels<'_>> = snorm.chunks_exact(size * size * 4).map(Texels::Snorm8).collect();
    for (bytes, array_size, what) in [
        (dds::encode(w, h, Shape::Array(2), &t8).unwrap(), 2, "horizon array"),
        (dds::encode(size, size, Shape::Cube, &faces).unwrap(), 1, "cube map"),
    ] {
        assert_eq!(&bytes[..4], b"DDS ", "{what}");
        assert_eq!(u32_at(&bytes, 4), 124, "{what}: header size");
        assert_eq!(u32_at(&bytes, 76), 32, "{what}: pixel format size");
        assert_eq!(u32_at(&bytes, 80), 0x4, "{what}: pixel format flags must be DDPF_FOURCC alone");
        assert_eq!(&bytes[84..88], b"DX10", "{what}");
        assert!(bytes[88..108].iter().all(|&b| b == 0), "{what}: bit count and masks must be 0");
        let flags = u32_at(&bytes, 8);
        assert_eq!(flags & 0x1007, 0x1007, "{what}: CAPS | HEIGHT | WIDTH | PIXELFORMAT");
        assert_ne!(flags & 0x20000, 0, "{what}: DDSD_MIPMAPCOUNT");
        assert_eq!(u32_at(&bytes, 28), 1, "{what}: mip count");
        assert_eq!(u32_at(&bytes, 140), array_size, "{what}: DX10 array size");
        assert_eq!(u32_at(&bytes, 132), 3, "{what}: resource dimension TEXTURE2D");
    }
}
