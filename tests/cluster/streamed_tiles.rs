//! The streamed decode of issue 23 (`heightmap::stream`) against the whole decode: every tile
//! blob, filled with the pass's stats, must equal bit for bit the same window cut from
//! `heightmap::decode_with` (values, holes, nodata), for PNG 8/16 (grey, RGB with a channel
//! pick, RGBA luma), TIFF strips and tiles (int16 with nodata, f32, f32 NaN nodata), odd sizes,
//! wrap and clipped halos; and a refusal must be the whole decode's.

use crate::support::Rng;
use horizon_bake::heightmap::stream::{self, MapStats, TileHeights, Window};
use horizon_bake::heightmap::{self, HeightMap, Limits};
use horizon_bake::params::{Channel, NoData};
use std::io::Cursor;

/// The windows of a tile plan: tiles of `t` plus a halo `halo`, wrapped or clipped.
fn plan(w: usize, h: usize, t: usize, halo: usize, wrap: bool) -> Vec<Window> {
    let mut out = Vec::new();
    for ty in (0..h).step_by(t) {
        for tx in (0..w).step_by(t) {
            let (tw, th) = (t.min(w - tx), t.min(h - ty));
            let (mut x0, mut y0) = (tx as i64 - halo as i64, ty as i64 - halo as i64);
            let (mut x1, mut y1) = ((tx + tw + halo) as i64, (ty + th + halo) as i64);
            if !wrap {
                x0 = x0.max(0);
                y0 = y0.max(0);
                x1 = x1.min(w as i64);
                y1 = y1.min(h as i64);
            }
            out.push(Window { x0, y0, width: (x1 - x0) as u32, height: (y1 - y0) as u32 });
        }
    }
    out
}

/// `win` cut from the whole map (modulo its size).
fn crop(map: &HeightMap, win: &Window) -> (Vec<f32>, Option<Vec<bool>>) {
    let (w, h) = (map.width as i64, map.height as i64);
    let mut v = Vec::new();
    let mut holes = Vec::new();
    for j in 0..win.height as i64 {
        for i in 0..win.width as i64 {
            let k = ((win.y0 + j).rem_euclid(h) * w + (win.x0 + i).rem_euclid(w)) as usize;
            v.push(map.values[k]);
            if let Some(m) = &map.terrain.holes {
                holes.push(m[k]);
            }
        }
    }
    (v, map.terrain.holes.as_ref().map(|_| holes))
}

fn same_nodata(a: Option<f64>, b: Option<f64>) -> bool {
    a.map(f64::to_bits) == b.map(f64::to_bits)
}

/// Decodes `bytes` both ways over the plans (wrap and clipped) and compares.
fn check(bytes: &[u8], channel: Channel, nodata: NoData, t: usize, halo: usize) -> MapStats {
    let limits = Limits::default();
    let (whole, info) = heightmap::decode_with(bytes, channel, nodata, &limits).unwrap();
    let mut last = None;
    for wrap in [true, false] {
        let windows = plan(whole.width, whole.height, t, halo, wrap);
        let mut got: Vec<Option<Vec<u8>>> = vec![None; windows.len()];
        let stats = stream::decode_tiles(
            Cursor::new(bytes),
            &info.content_hash,
            channel,
            nodata,
            &limits,
            &windows,
            &mut |i, blob| {
                assert!(got[i].is_none(), "window {i} emitted twice");
                got[i] = Some(blob);
                Ok(())
            },
        )
        .unwrap();
        assert_eq!(stats.info, info);
        assert_eq!(stats.georef, whole.terrain.georef);
        assert!(same_nodata(stats.nodata, whole.terrain.nodata));
        let holes = whole.terrain.holes.as_ref().map_or(0, |m| m.iter().filter(|&&b| b).count());
        assert_eq!(stats.holes, holes as u64);
        let lo = whole.values.iter().copied().fold(f32::INFINITY, f32::min);
        let hi = whole.values.iter().copied().fold(f32::NEG_INFINITY, f32::max);
        assert_eq!((stats.min.to_bits(), stats.max.to_bits()), (lo.to_bits(), hi.to_bits()));
        let round = MapStats::from_json(&stats.to_json()).unwrap();
        assert_eq!(round.info, stats.info);
        assert!(same_nodata(round.nodata, stats.nodata));
        assert_eq!((round.min, round.max, round.fill), (stats.min, stats.max, stats.fill));
        for (i, win) in windows.iter().enumerate() {
            let blob = got[i].take().unwrap_or_else(|| panic!("window {i} ({win:?}) missing"));
            let tile = TileHeights::decode(&blob).unwrap();
            assert_eq!(tile.window, *win);
            let map = tile.into_map(&stats);
            let (want, want_holes) = crop(&whole, win);
            assert_eq!((map.width, map.height), (win.width as usize, win.height as usize));
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&map.values), bits(&want), "window {i} {win:?} wrap {wrap}");
            assert_eq!(map.terrain.holes, want_holes, "holes of window {i}");
            assert!(same_nodata(map.terrain.nodata, whole.terrain.nodata));
        }
        last = Some(stats);
    }
    last.unwrap()
}

/// Bytes per value of each blob of a one-pass cut into windows of `t` + `halo` (wrapped).
fn bytes_per_value(bytes: &[u8], t: usize, halo: usize) -> Vec<usize> {
    let limits = Limits::default();
    let (whole, info) =
        heightmap::decode_with(bytes, Channel::Luma, NoData::None, &limits).unwrap();
    let windows = plan(whole.width, whole.height, t, halo, true);
    let mut out = vec![0; windows.len()];
    stream::decode_tiles(
        Cursor::new(bytes),
        &info.content_hash,
        Channel::Luma,
        NoData::None,
        &limits,
        &windows,
        &mut |i, blob| {
            let n = windows[i].width as usize * windows[i].height as usize;
            out[i] = (blob.len() - stream::TILE_HEADER) / n;
            Ok(())
        },
    )
    .unwrap();
    out
}

fn png_bytes(img: image::DynamicImage) -> Vec<u8> {
    let mut out = Cursor::new(Vec::new());
    img.write_to(&mut out, image::ImageFormat::Png).unwrap();
    out.into_inner()
}

#[test]
fn png_8_and_16_bit_grey_odd_sizes() {
    let mut rng = Rng(7);
    let (w, h) = (37u32, 23u32);
    let g8 = image::GrayImage::from_fn(w, h, |_, _| image::Luma([(rng.next_u64() % 256) as u8]));
    check(&png_bytes(g8.into()), Channel::Luma, NoData::Auto, 8, 3);
    let g16 = image::ImageBuffer::<image::Luma<u16>, _>::from_fn(w, h, |_, _| {
        image::Luma([(rng.next_u64() % 65536) as u16])
    });
    let bytes = png_bytes(g16.into());
    check(&bytes, Channel::Luma, NoData::Auto, 8, 3);
    // Tiles larger than the map, halos larger than a tile, a one-tile plan.
    check(&bytes, Channel::Luma, NoData::Auto, 64, 5);
    check(&bytes, Channel::Luma, NoData::Auto, 5, 9);
    // 16-bit samples cross the blob store in 2 bytes each (the same values, as checked above).
    assert!(bytes_per_value(&bytes, 8, 3).iter().all(|&b| b == 2));
    // 16-bit with a nodata value as stored (a hole wherever the sample is 0..=4095 → 0 here).
    let holed = image::ImageBuffer::<image::Luma<u16>, _>::from_fn(w, h, |x, y| {
        image::Luma([if (x * 7 + y * 3) % 11 == 0 { 1000 } else { (x * 1700 + y * 90) as u16 }])
    });
    let s = check(&png_bytes(holed.into()), Channel::Luma, NoData::Value(1000.0), 8, 2);
    assert!(s.holes > 0 && s.fill.is_some());
}

#[test]
fn png_colour_channel_picks() {
    let mut rng = Rng(11);
    let (w, h) = (29u32, 31u32);
    let rgb = image::RgbImage::from_fn(w, h, |_, _| {
        let v = rng.next_u64();
        image::Rgb([v as u8, (v >> 8) as u8, (v >> 16) as u8])
    });
    let bytes = png_bytes(rgb.into());
    for c in [Channel::R, Channel::G, Channel::B, Channel::Luma] {
        check(&bytes, c, NoData::Auto, 7, 2);
    }
    let rgba16 = image::ImageBuffer::<image::Rgba<u16>, _>::from_fn(w, h, |_, _| {
        let v = rng.next_u64();
        image::Rgba([v as u16, (v >> 16) as u16, (v >> 32) as u16, (v >> 48) as u16])
    });
    let bytes = png_bytes(rgba16.into());
    for c in [Channel::A, Channel::Luma] {
        check(&bytes, c, NoData::Auto, 10, 4);
    }
}

fn tiff_i16_strips(w: u32, h: u32, data: &[i16]) -> Vec<u8> {
    let mut out = Cursor::new(Vec::new());
    let mut enc = tiff::encoder::TiffEncoder::new(&mut out).unwrap();
    let mut img = enc.new_image::<tiff::encoder::colortype::GrayI16>(w, h).unwrap();
    img.rows_per_strip(5).unwrap();
    img.write_data(data).unwrap();
    out.into_inner()
}

#[test]
fn tiff_int16_strips_with_nodata() {
    let (w, h) = (41u32, 27u32);
    let data: Vec<i16> = (0..w * h)
        .map(|k| if k % 13 == 4 { -32768 } else { (k as i32 * 37 % 3000 - 1200) as i16 })
        .collect();
    let bytes = tiff_i16_strips(w, h, &data);
    let s = check(&bytes, Channel::Luma, NoData::Value(-32768.0), 8, 3);
    assert!(s.holes > 0);
    assert!(bytes_per_value(&bytes, 8, 3).iter().all(|&b| b == 2), "signed DEM: 2 bytes");
    check(&bytes, Channel::Luma, NoData::None, 6, 2);
}

/// A tiled float TIFF (512² tiles, DEFLATE + predictor 3), written by our GeoTIFF writer with
/// a GDAL_NODATA tag the decode picks up by default.
fn tiff_f32_tiled(w: usize, h: usize, values: &[f32], nodata: f32) -> Vec<u8> {
    let band = horizon_bake::encode::geotiff::Band { plane: values, description: "h".into() };
    horizon_bake::encode::geotiff::encode(w, h, &[band], None, nodata).unwrap()
}

#[test]
fn tiff_f32_tiles_strips_and_nan_nodata() {
    let mut rng = Rng(3);
    // Wider than one 512 tile, odd, with NaN holes declared by the file's GDAL_NODATA.
    let (w, h) = (517usize, 19usize);
    let values: Vec<f32> =
        (0..w * h).map(|k| if k % 97 == 5 { f32::NAN } else { rng.f32() * 300.0 - 50.0 }).collect();
    let bytes = tiff_f32_tiled(w, h, &values, f32::NAN);
    let s = check(&bytes, Channel::Luma, NoData::Auto, 128, 17);
    assert!(s.holes > 0);
    // The same values in strips, with `nodata=nan` asked explicitly.
    let mut out = Cursor::new(Vec::new());
    let mut enc = tiff::encoder::TiffEncoder::new(&mut out).unwrap();
    let mut img =
        enc.new_image::<tiff::encoder::colortype::Gray32Float>(w as u32, h as u32).unwrap();
    img.rows_per_strip(4).unwrap();
    img.write_data(&values).unwrap();
    check(&out.into_inner(), Channel::Luma, NoData::Nan, 100, 6);
}

#[test]
fn refusals_are_the_whole_decodes() {
    let (w, h) = (20usize, 9usize);
    let limits = Limits::default();
    let mut values: Vec<f32> = (0..w * h).map(|k| k as f32).collect();
    values[3 * w + 7] = 1e30; // out of range, before…
    values[5 * w + 2] = f32::INFINITY; // …a non-finite texel, which the whole decode names
    let mut out = Cursor::new(Vec::new());
    tiff::encoder::TiffEncoder::new(&mut out)
        .unwrap()
        .write_image::<tiff::encoder::colortype::Gray32Float>(w as u32, h as u32, &values)
        .unwrap();
    let bytes = out.into_inner();
    for nodata in [NoData::Auto, NoData::Value(-1.0), NoData::Value(1.0)] {
        let whole = heightmap::decode_with(&bytes, Channel::Luma, nodata, &limits).unwrap_err();
        let streamed = stream::decode_tiles(
            Cursor::new(&bytes),
            "x",
            Channel::Luma,
            nodata,
            &limits,
            &plan(w, h, 8, 2, true),
            &mut |_, _| Ok(()),
        )
        .unwrap_err();
        assert_eq!(streamed.to_string(), whole.to_string(), "{nodata:?}");
    }
    // Every texel nodata.
    let bytes = tiff_i16_strips(4, 4, &[7; 16]);
    let whole = heightmap::decode_with(&bytes, Channel::Luma, NoData::Value(7.0), &limits);
    let streamed = stream::decode_tiles(
        Cursor::new(&bytes),
        "x",
        Channel::Luma,
        NoData::Value(7.0),
        &limits,
        &plan(4, 4, 2, 1, true),
        &mut |_, _| Ok(()),
    );
    assert_eq!(streamed.unwrap_err().to_string(), whole.unwrap_err().to_string());
    // The header probe needs no pixels, and refuses over the limits.
    let png = png_bytes(image::GrayImage::new(300, 200).into());
    assert_eq!(stream::probe_reader(Cursor::new(&png), &limits).unwrap(), ("png", 300, 200));
    let small = Limits { max_dim: 100, ..limits };
    assert!(stream::probe_reader(Cursor::new(&png), &small).is_err());
}

#[test]
fn decodes_through_ranged_reads_of_a_blob_store() {
    use horizon_bake::jobs::blob::{BlobSeekReader, BlobStore, FsBlobStore};
    let dir = tempfile::tempdir().unwrap();
    let store: std::sync::Arc<dyn BlobStore> =
        std::sync::Arc::new(FsBlobStore::open(dir.path()).unwrap());
    let (w, h) = (517usize, 40usize);
    let mut rng = Rng(9);
    let values: Vec<f32> = (0..w * h).map(|_| rng.f32() * 10.0).collect();
    let limits = Limits::default();
    for bytes in [
        tiff_f32_tiled(w, h, &values, -9999.0),
        tiff_i16_strips(41, 27, &(0..41 * 27).map(|k| k as i16).collect::<Vec<_>>()),
    ] {
        let hash = store.put(&bytes, &|_| Ok(())).unwrap();
        let (whole, _) =
            heightmap::decode_with(&bytes, Channel::Luma, NoData::Auto, &limits).unwrap();
        let windows = plan(whole.width, whole.height, 16, 4, true);
        let mut n = 0;
        let r = BlobSeekReader::open(store.clone(), &hash).unwrap().unwrap();
        assert_eq!(r.len(), bytes.len() as u64);
        let stats = stream::decode_tiles(
            r,
            &hash,
            Channel::Luma,
            NoData::Auto,
            &limits,
            &windows,
            &mut |i, blob| {
                let map = TileHeights::decode(&blob).unwrap();
                let (want, _) = crop(&whole, &windows[i]);
                assert_eq!(map.values, want);
                n += 1;
                Ok(())
            },
        )
        .unwrap();
        assert_eq!(n, windows.len());
        assert_eq!(stats.info.content_hash, hash);
        let r = BlobSeekReader::open(store.clone(), &hash).unwrap().unwrap();
        assert_eq!(stream::probe_reader(r, &limits).unwrap().1 as usize, whole.width);
    }
}

#[test]
fn what_cannot_stream_is_refused_from_the_header() {
    let limits = Limits::default();
    let png = png_bytes(image::GrayImage::new(30, 20).into());
    stream::check_streamable(Cursor::new(&png), Channel::Luma, &limits).unwrap();
    let tif = tiff_i16_strips(4, 4, &[1; 16]);
    stream::check_streamable(Cursor::new(&tif), Channel::Luma, &limits).unwrap();
    let mut exr = vec![0x76, 0x2f, 0x31, 0x01];
    exr.extend_from_slice(&[0; 60]);
    match stream::check_streamable(Cursor::new(&exr), Channel::Luma, &limits) {
        Err(horizon_bake::Error::Unsupported(m)) => assert!(m.contains("OpenEXR"), "{m}"),
        other => panic!("{other:?}"),
    }
}

#[test]
fn truncated_and_corrupt_inputs_are_errors_not_panics() {
    let limits = Limits::default();
    let mut rng = Rng(5);
    let g16 = image::ImageBuffer::<image::Luma<u16>, _>::from_fn(33, 21, |x, y| {
        image::Luma([(x * 1000 + y * 77) as u16])
    });
    let png = png_bytes(g16.into());
    let tif = tiff_i16_strips(41, 27, &(0..41 * 27).map(|k| k as i16).collect::<Vec<_>>());
    for bytes in [png, tif] {
        let windows = plan(16, 16, 8, 2, true);
        for cut in [8, 30, bytes.len() / 2, bytes.len() - 5] {
            let r = stream::decode_tiles(
                Cursor::new(&bytes[..cut]),
                "x",
                Channel::Luma,
                NoData::Auto,
                &limits,
                &windows,
                &mut |_, _| Ok(()),
            );
            assert!(r.is_err(), "cut at {cut} of {} decoded", bytes.len());
        }
        for _ in 0..40 {
            let mut b = bytes.clone();
            let k = 8 + (rng.next_u64() as usize) % (b.len() - 8);
            b[k] ^= 1 << (rng.next_u64() % 8);
            // Either result, never a panic (a whole-decode Ok must be a streamed Ok too).
            let whole = heightmap::decode_with(&b, Channel::Luma, NoData::Auto, &limits);
            let streamed = stream::decode_tiles(
                Cursor::new(&b),
                "x",
                Channel::Luma,
                NoData::Auto,
                &limits,
                &windows,
                &mut |_, _| Ok(()),
            );
            if let Ok((m, _)) = whole {
                let s = streamed.unwrap_or_else(|e| panic!("byte {k}: whole ok, streamed {e}"));
                let lo = m.values.iter().copied().fold(f32::INFINITY, f32::min);
                assert_eq!(s.min.to_bits(), lo.to_bits(), "byte {k}");
            }
        }
    }
}
