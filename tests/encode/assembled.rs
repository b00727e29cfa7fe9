//! Streamed assembly of a tiled bake's results (`encode::assemble`, issue 23): layers cut into
//! tile result blobs in a real file blob store, read back band by band through ranged reads,
//! must give files byte-identical to the untiled writers' (PNG 8/16, KTX2 and DDS level 0 at
//! every uncompressed precision and both layouts, GeoTIFF), and the streamed GeoTIFF must read
//! back in GDAL (rasterio) with the same values.

use crate::support;
use crate::support::Rng;
use horizon_bake::encode::assemble::{self, tag, Plane, Section, TilePiece, TileRows};
use horizon_bake::encode::png::{self, PngColor};
use horizon_bake::encode::texture::{DdsHeader, TextureLayout, TexturePrecision};
use horizon_bake::encode::{self, geotiff, Formats};
use horizon_bake::jobs::blob::{self as blobs, BlobStore, FsBlobStore};
use horizon_bake::layers::HorizonLayers;
use std::sync::Arc;

/// Irregular tile interiors covering a `w × h` map.
fn pieces(w: usize, h: usize) -> Vec<(usize, usize, usize, usize)> {
    let xs = [0, 256, 300, w];
    let ys = [0, 100, 611, h];
    let mut out = Vec::new();
    for j in 0..3 {
        for i in 0..3 {
            out.push((xs[i], ys[j], xs[i + 1] - xs[i], ys[j + 1] - ys[j]));
        }
    }
    out
}

fn crop<T: Copy>(
    plane: &[T],
    w: usize,
    ch: usize,
    (x0, y0, pw, ph): (usize, usize, usize, usize),
) -> Vec<T> {
    let mut out = Vec::with_capacity(pw * ph * ch);
    for y in y0..y0 + ph {
        out.extend_from_slice(&plane[(y * w + x0) * ch..(y * w + x0 + pw) * ch]);
    }
    out
}

struct Fixture {
    _dir: tempfile::TempDir,
    store: Arc<dyn BlobStore>,
    pieces: Vec<TilePiece>,
    w: usize,
    h: usize,
    layers: HorizonLayers,
    bands: Vec<Vec<f32>>,
}

fn fixture() -> Fixture {
    let (w, h) = (701usize, 1100usize);
    let mut rng = Rng(42);
    let mut l8 = || (0..w * h * 4).map(|_| (rng.next_u64() % 256) as u8).collect::<Vec<u8>>();
    let u8s = [l8(), l8()];
    let mut rng = Rng(43);
    let mut l16 = || (0..w * h * 4).map(|_| (rng.next_u64() >> 40) as u16).collect::<Vec<u16>>();
    let u16s = [l16(), l16()];
    let mut rng = Rng(44);
    let mut lf = || (0..w * h * 4).map(|_| rng.f32()).collect::<Vec<f32>>();
    let f32s = [lf(), lf()];
    let mut rng = Rng(45);
    let bands: Vec<Vec<f32>> = (0..3)
        .map(|b| {
            (0..w * h)
                .map(|k| if (k + b) % 91 == 0 { f32::NAN } else { rng.f32() * 90.0 })
                .collect()
        })
        .collect();
    let dir = tempfile::tempdir().unwrap();
    let store: Arc<dyn BlobStore> = Arc::new(FsBlobStore::open(dir.path()).unwrap());
    let mut out = Vec::new();
    for p in pieces(w, h) {
        let (a8, b8) = (crop(&u8s[0], w, 4, p), crop(&u8s[1], w, 4, p));
        let (a16, b16) = (crop(&u16s[0], w, 4, p), crop(&u16s[1], w, 4, p));
        let (af, bf) = (crop(&f32s[0], w, 4, p), crop(&f32s[1], w, 4, p));
        let bs: Vec<Vec<f32>> = bands.iter().map(|b| crop(b, w, 1, p)).collect();
        let sections = [
            Section {
                tag: tag::HORIZON_U8,
                channels: 4,
                planes: vec![Plane::U8(&a8), Plane::U8(&b8)],
            },
            Section {
                tag: tag::HORIZON_U16,
                channels: 4,
                planes: vec![Plane::U16(&a16), Plane::U16(&b16)],
            },
            Section {
                tag: tag::HORIZON_F32,
                channels: 4,
                planes: vec![Plane::F32(&af), Plane::F32(&bf)],
            },
            Section {
                tag: tag::ANGLES,
                channels: 1,
                planes: bs.iter().map(|b| Plane::F32(b)).collect(),
            },
        ];
        let wr = store.writer().unwrap();
        let wr = assemble::write_tile_result(wr, p.2 as u32, p.3 as u32, &sections).unwrap();
        let hash = wr.commit(&|_| Ok(())).unwrap();
        out.push(TilePiece {
            x0: p.0 as u32,
            y0: p.1 as u32,
            width: p.2 as u32,
            height: p.3 as u32,
            hash,
        });
    }
    let layers =
        HorizonLayers { width: w, height: h, u8: Some(u8s), u16: Some(u16s), f32: Some(f32s) };
    Fixture { _dir: dir, store, pieces: out, w, h, layers, bands }
}

impl Fixture {
    fn rows(&self) -> TileRows {
        let store = self.store.clone();
        let read: assemble::ReadRange = std::sync::Arc::new(move |hash, start, len| {
            blobs::read_range(&*store, hash, start, len)
        });
        TileRows::new(read, self.pieces.clone(), self.w, self.h).unwrap()
    }
}

fn file<'a>(files: &'a [encode::OutFile], name: &str) -> &'a [u8] {
    &files.iter().find(|f| f.name == name).unwrap_or_else(|| panic!("{name} missing")).bytes
}

#[test]
fn png_layers_are_byte_identical() {
    let f = fixture();
    let (w, h) = (f.w, f.h);
    let mut rows = f.rows();
    let l8 = f.layers.u8.as_ref().unwrap();
    let l16 = f.layers.u16.as_ref().unwrap();
    for layer in 0..2 {
        let mut src = |p: usize, y: usize, out: &mut [u8]| rows.read(tag::HORIZON_U8, p, y, out);
        let got = assemble::write_png(Vec::new(), w, h, PngColor::Rgba, layer, &mut src).unwrap();
        let want = png::encode8(w, h, PngColor::Rgba, &l8[layer]).unwrap();
        assert!(got == want, "png8 layer {layer}: {} vs {} bytes", got.len(), want.len());
        let mut src = |p: usize, y: usize, out: &mut [u16]| rows.read(tag::HORIZON_U16, p, y, out);
        let got = assemble::write_png(Vec::new(), w, h, PngColor::Rgba, layer, &mut src).unwrap();
        let want = png::encode16(w, h, PngColor::Rgba, &l16[layer]).unwrap();
        assert!(got == want, "png16 layer {layer}");
        // And an outside decoder reads the samples back.
        let img = image::load_from_memory(&got).unwrap().into_rgba16();
        assert_eq!(img.as_raw(), &l16[layer]);
    }
    // More rows than band_rows gives: the PNG was written in several bands.
    assert!(assemble::band_rows(w * 4) < h);
}

#[test]
fn textures_are_byte_identical() {
    let f = fixture();
    let (w, h) = (f.w, f.h);
    let mut rows = f.rows();
    for (precision, t) in [
        (TexturePrecision::Unorm8, tag::HORIZON_U8),
        (TexturePrecision::Unorm16, tag::HORIZON_U16),
        (TexturePrecision::Float32, tag::HORIZON_F32),
    ] {
        for layout in [TextureLayout::Array, TextureLayout::Separate] {
            for header in [DdsHeader::Dx10, DdsHeader::Legacy] {
                let mut formats = Formats::parse("ktx2,dds", precision).unwrap();
                formats.texture.layout = layout;
                formats.texture.dds_header = header;
                if header == DdsHeader::Legacy && layout == TextureLayout::Array {
                    continue; // a legacy header holds no array (refused by both)
                }
                assemble::check_tiled_texture(&formats.texture).unwrap();
                let files = encode::horizon_files(&f.layers, &formats).unwrap();
                let sets: Vec<(&[usize], String, String)> = match layout {
                    TextureLayout::Array => {
                        vec![(&[0, 1], "horizon.ktx2".into(), "horizon.dds".into())]
                    }
                    TextureLayout::Separate => (0..2)
                        .map(|i| {
                            let planes: &[usize] = if i == 0 { &[0] } else { &[1] };
                            (planes, format!("horizon_{i}.ktx2"), format!("horizon_{i}.dds"))
                        })
                        .collect(),
                };
                // The one-call writer of every texture file gives the same files.
                let mut got: Vec<(&'static str, Vec<u8>)> = Vec::new();
                assemble::write_textures(
                    &mut rows,
                    w,
                    h,
                    &formats,
                    &mut |_| Ok(Vec::new()),
                    &mut |name, bytes| {
                        got.push((name, bytes));
                        Ok(())
                    },
                )
                .unwrap();
                let want: Vec<&str> = files
                    .iter()
                    .map(|f| f.name)
                    .filter(|n| n.ends_with(".ktx2") || n.ends_with(".dds"))
                    .collect();
                assert_eq!(got.iter().map(|g| g.0).collect::<Vec<_>>(), want);
                for (name, bytes) in &got {
                    assert!(bytes.as_slice() == file(&files, name), "write_textures {name}");
                }
                for (planes, ktx, dds) in sets {
                    let separate = (layout == TextureLayout::Separate).then_some(planes[0]);
                    let meta = formats.conventions.ktx2_json(&formats.texture, separate);
                    let (k, d) = match precision {
                        TexturePrecision::Unorm8 => {
                            let mut s = |p: usize, y: usize, o: &mut [u8]| rows.read(t, p, y, o);
                            (
                                assemble::write_ktx2(Vec::new(), w, h, planes, &meta, &mut s)
                                    .unwrap(),
                                assemble::write_dds(Vec::new(), w, h, planes, header, &mut s)
                                    .unwrap(),
                            )
                        }
                        TexturePrecision::Unorm16 => {
                            let mut s = |p: usize, y: usize, o: &mut [u16]| rows.read(t, p, y, o);
                            (
                                assemble::write_ktx2(Vec::new(), w, h, planes, &meta, &mut s)
                                    .unwrap(),
                                assemble::write_dds(Vec::new(), w, h, planes, header, &mut s)
                                    .unwrap(),
                            )
                        }
                        _ => {
                            let mut s = |p: usize, y: usize, o: &mut [f32]| rows.read(t, p, y, o);
                            (
                                assemble::write_ktx2(Vec::new(), w, h, planes, &meta, &mut s)
                                    .unwrap(),
                                assemble::write_dds(Vec::new(), w, h, planes, header, &mut s)
                                    .unwrap(),
                            )
                        }
                    };
                    assert!(k == file(&files, &ktx), "{ktx} {precision:?}");
                    assert!(d == file(&files, &dds), "{dds} {precision:?} {header:?}");
                }
            }
        }
    }
    // What a tiled bake cannot stream is refused naming the option.
    for (key, value) in
        [("mips", "full"), ("texture_precision", "bc7"), ("supercompression", "zstd")]
    {
        let opts =
            horizon_bake::encode::texture::TextureOptions::from_pairs([(key, value)]).unwrap();
        match assemble::check_tiled_texture(&opts) {
            Err(horizon_bake::Error::Param { field, .. }) => assert_eq!(field, key),
            other => panic!("{key}={value}: {other:?}"),
        }
    }
}

#[test]
fn geotiff_is_byte_identical_and_gdal_reads_it() {
    let f = fixture();
    let (w, h) = (f.w, f.h);
    let mut rows = f.rows();
    let names: Vec<String> = (0..3).map(|b| format!("azimuth {}", b * 120)).collect();
    let mut src = |b: usize, y: usize, out: &mut [f32]| rows.read(tag::ANGLES, b, y, out);
    let got =
        assemble::write_geotiff(Vec::new(), w, h, &names, None, f32::NAN, None, &mut src).unwrap();
    let bands: Vec<geotiff::Band<'_>> = f
        .bands
        .iter()
        .zip(&names)
        .map(|(p, d)| geotiff::Band { plane: p, description: d.clone() })
        .collect();
    let want = geotiff::encode(w, h, &bands, None, f32::NAN).unwrap();
    assert!(got == want, "{} vs {} bytes", got.len(), want.len());

    if !support::has_rasterio() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let tif = dir.path().join("angles.tif");
    std::fs::write(&tif, &got).unwrap();
    let raw = dir.path().join("bands.f32");
    let bytes: Vec<u8> = f.bands.iter().flatten().flat_map(|v| v.to_le_bytes()).collect();
    std::fs::write(&raw, bytes).unwrap();
    let script = format!(
        "import rasterio, numpy as np\n\
         with rasterio.open({tif:?}) as d:\n\
         \x20   a = d.read()\n\
         \x20   assert d.count == 3 and d.width == {w} and d.height == {h}, (d.count, d.width, d.height)\n\
         \x20   assert d.block_shapes[0] == (512, 512), d.block_shapes\n\
         \x20   assert d.descriptions == ('azimuth 0', 'azimuth 120', 'azimuth 240'), d.descriptions\n\
         \x20   assert np.isnan(d.nodata)\n\
         b = np.fromfile({raw:?}, dtype='<f4').reshape(3, {h}, {w})\n\
         assert np.array_equal(a, b, equal_nan=True)\n\
         print('ok', a.shape)\n"
    );
    let out = std::process::Command::new("python3").args(["-c", &script]).output().unwrap();
    eprintln!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "rasterio could not read the streamed GeoTIFF");
}
