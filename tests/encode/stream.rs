//! The streaming bake (`bake::stream_horizon` into `PngRowWriter`s, what the CLI uses for
//! PNG-only outputs) against the whole-layer path (`bake_horizon` + `encode::png`): the decoded
//! samples must be identical, bands must arrive in row order, and a cancel must stop the stream
//! and leave the output directory untouched.

use crate::support::Rng;
use horizon_bake::bake::{self, LayerRows, Precisions, Sample};
use horizon_bake::cli::bake::Staging;
use horizon_bake::encode::png::{encode16, encode8, PngColor, PngRowWriter, PngSample};
use horizon_bake::encode::Formats;
use horizon_bake::heightmap::HeightMap;
use horizon_bake::params::BakeParams;
use horizon_bake::progress::{Progress, Stage};
use horizon_bake::Error;
use std::process::Command;

fn random_map(rng: &mut Rng, w: usize, h: usize) -> HeightMap {
    HeightMap::from_values(w, h, (0..w * h).map(|_| rng.f32()).collect()).unwrap()
}

/// What [`stream`] saw: the two PNGs, (y0, rows) of each band handed on, final progress counts.
type Streamed = ([Vec<u8>; 2], Vec<(usize, usize)>, (u64, u64));

/// Streams `map` into two in-memory PNGs.
fn stream<T: Sample + PngSample>(map: &HeightMap, params: &BakeParams) -> Streamed {
    let (w, h) = (map.width, map.height);
    let progress = Progress::new();
    let mut writers = [
        PngRowWriter::<Vec<u8>, T>::new(Vec::new(), w, h, PngColor::Rgba).unwrap(),
        PngRowWriter::<Vec<u8>, T>::new(Vec::new(), w, h, PngColor::Rgba).unwrap(),
    ];
    let mut bands = Vec::new();
    bake::stream_horizon(map.clone(), params, &progress, |rows: LayerRows<'_, T>| {
        assert_eq!(rows.layers[0].len(), rows.rows * w * 4);
        assert_eq!(rows.layers[1].len(), rows.rows * w * 4);
        bands.push((rows.y0, rows.rows));
        writers[0].write_rows(rows.layers[0])?;
        writers[1].write_rows(rows.layers[1])
    })
    .unwrap();
    let [a, b] = writers;
    ([a.finish().unwrap(), b.finish().unwrap()], bands, progress.counts())
}

fn decode8(png: &[u8]) -> Vec<u8> {
    image::load_from_memory(png).unwrap().to_rgba8().into_raw()
}

fn decode16(png: &[u8]) -> Vec<u16> {
    let img = image::load_from_memory(png).unwrap();
    assert!(matches!(img, image::DynamicImage::ImageRgba16(_)), "not a 16-bit RGBA PNG");
    img.to_rgba16().into_raw()
}

fn check_case(rng: &mut Rng, w: usize, h: usize, encoding: &str) {
    let map = random_map(rng, w, h);
    let radius = rng.range(1, 12).to_string();
    let params = BakeParams::from_pairs([
        ("radius", radius.as_str()),
        ("height_scale", "5"),
        ("encoding", encoding),
    ])
    .unwrap();
    let both = Precisions { u8: true, u16: true, f32: false };
    let (layers, _) = bake::bake_horizon(&map, &params, both, &Progress::new()).unwrap();
    let (l8, l16) = (layers.u8.as_ref().unwrap(), layers.u16.as_ref().unwrap());
    let what = format!("{w}×{h} radius {radius} {encoding}");

    let (png, bands, counts) = stream::<u8>(&map, &params);
    for k in 0..2 {
        let whole = decode8(&encode8(w, h, PngColor::Rgba, &l8[k]).unwrap());
        assert_eq!(whole, l8[k], "{what}: whole-layer png8 round trip");
        assert!(decode8(&png[k]) == whole, "{what}: streamed png8 layer {k} differs");
    }
    // Bands in row order, covering every row once; progress counted every row.
    let mut next = 0;
    for &(y0, rows) in &bands {
        assert_eq!(y0, next, "{what}: band order");
        assert!(rows > 0);
        next += rows;
    }
    assert_eq!(next, h, "{what}: rows streamed");
    assert_eq!(counts, (h as u64, h as u64), "{what}: progress");

    let (png, _, _) = stream::<u16>(&map, &params);
    for k in 0..2 {
        let whole = decode16(&encode16(w, h, PngColor::Rgba, &l16[k]).unwrap());
        assert_eq!(whole, l16[k], "{what}: whole-layer png16 round trip");
        assert!(decode16(&png[k]) == whole, "{what}: streamed png16 layer {k} differs");
    }
}

#[test]
fn streamed_pngs_decode_to_the_whole_layer_samples() {
    let mut rng = Rng(0x5EED);
    // 1×1, thin maps, odd sizes, and heights whose band count does not divide them (with 2
    // threads a band of 101 rows is 4 rows: 26 bands, the last one row).
    let sizes = [(1, 1), (1, 9), (11, 1), (7, 5), (45, 101), (300, 67), (129, 257)];
    for (k, &(w, h)) in sizes.iter().enumerate() {
        check_case(&mut rng, w, h, if k % 2 == 0 { "linear" } else { "sqrt" });
    }
}

#[test]
fn streamed_pngs_match_with_other_thread_counts() {
    // The window is 2 × threads bands: 1 and 3 threads give other windows and band sizes.
    for threads in [1, 3] {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
        let mut rng = Rng(threads as u64);
        pool.install(|| {
            check_case(&mut rng, 33, 71, "sqrt");
            check_case(&mut rng, 2, 130, "linear");
        });
    }
}

#[test]
fn streamed_bake_keeps_the_kernel_values() {
    // The f32 "precision" of the stream hands on the kernel's values, so the streamed rows
    // can be checked against the whole-layer f32 bake to the bit.
    let mut rng = Rng(41);
    let map = random_map(&mut rng, 23, 19);
    let params = BakeParams::from_pairs([("radius", "7"), ("method", "exact")]).unwrap();
    let (layers, r1) =
        bake::bake_horizon(&map, &params, Precisions::ALL, &Progress::new()).unwrap();
    let f = layers.f32.unwrap();
    let mut got = [Vec::new(), Vec::new()];
    let r2 = bake::stream_horizon(map, &params, &Progress::new(), |rows: LayerRows<'_, f32>| {
        got[0].extend_from_slice(rows.layers[0]);
        got[1].extend_from_slice(rows.layers[1]);
        Ok(())
    })
    .unwrap();
    assert_eq!(r1, r2);
    assert!(got[0] == f[0] && got[1] == f[1], "streamed f32 layers differ");
}

/// A parent directory with `out/` holding an old `horizon_0.png`.
fn out_dir_with_old_file() -> (tempfile::TempDir, std::path::PathBuf) {
    let parent = tempfile::tempdir().unwrap();
    let out = parent.path().join("out");
    std::fs::create_dir(&out).unwrap();
    std::fs::write(out.join("horizon_0.png"), b"old").unwrap();
    (parent, out)
}

/// DIR still holds only the old file, and no staging directory is left beside it.
fn assert_untouched(parent: &std::path::Path, out: &std::path::Path) {
    let names: Vec<String> = std::fs::read_dir(out)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    assert_eq!(names, ["horizon_0.png"]);
    assert_eq!(std::fs::read(out.join("horizon_0.png")).unwrap(), b"old");
    let left: Vec<_> = std::fs::read_dir(parent).unwrap().map(|e| e.unwrap().file_name()).collect();
    assert_eq!(left, ["out"], "staging directory left behind");
}

#[test]
fn cancel_mid_stream_stops_and_leaves_the_directory_alone() {
    let (parent, out) = out_dir_with_old_file();
    let mut rng = Rng(3);
    let (w, h) = (64, 200);
    let map = random_map(&mut rng, w, h);
    let params = BakeParams::from_pairs([("radius", "4")]).unwrap();
    let progress = Progress::new();
    let staging = Staging::new(&out).unwrap();
    let files =
        [staging.create("horizon_0.png").unwrap(), staging.create("horizon_1.png").unwrap()];
    let mut writers = [
        PngRowWriter::<_, u16>::new(files[0].try_clone().unwrap(), w, h, PngColor::Rgba).unwrap(),
        PngRowWriter::<_, u16>::new(files[1].try_clone().unwrap(), w, h, PngColor::Rgba).unwrap(),
    ];
    let mut calls = 0;
    let mut first_rows = 0;
    let res = bake::stream_horizon(map, &params, &progress, |rows: LayerRows<'_, u16>| {
        calls += 1;
        first_rows = rows.rows;
        writers[0].write_rows(rows.layers[0])?;
        writers[1].write_rows(rows.layers[1])?;
        progress.cancel();
        Ok(())
    });
    assert!(matches!(res, Err(Error::Canceled)), "got {:?}", res.map(|_| ()));
    assert_eq!(calls, 1, "a band was handed on after the cancel");
    assert!(first_rows > 0 && first_rows < h);
    // Progress counts the one band that was handed on, nothing after it.
    assert_eq!(progress.counts(), (first_rows as u64, h as u64));
    // The writers cannot finish a half-written image.
    let [a, _] = writers;
    assert!(matches!(a.finish(), Err(Error::Internal(_))));
    drop(files);
    drop(staging);
    assert_untouched(parent.path(), &out);
}

#[test]
fn canceled_png_streaming_leaves_the_directory_alone() {
    // The CLI's own streaming function, canceled from another thread once rows are flowing.
    let (parent, out) = out_dir_with_old_file();
    let mut rng = Rng(99);
    let map = random_map(&mut rng, 512, 1024);
    let params = BakeParams::from_pairs([("radius", "48")]).unwrap();
    let formats = Formats { png8: false, png16: true, ..Formats::default() };
    let progress = Progress::new();
    let watcher = progress.clone();
    let canceller = std::thread::spawn(move || loop {
        let (done, _) = watcher.counts();
        if watcher.stage() == Stage::Bake && done > 0 {
            watcher.cancel();
            return done;
        }
        std::thread::yield_now();
    });
    let mut staging = Staging::new(&out).unwrap();
    let res = horizon_bake::pipeline::produce(map, &params, &formats, &progress, &mut staging);
    assert!(canceller.join().unwrap() > 0);
    assert!(matches!(res, Err(Error::Canceled)), "got {:?}", res.map(|_| ()));
    let (done, total) = progress.counts();
    assert!(done < total / 2, "{done} of {total} rows done after cancel");
    drop(staging);
    assert_untouched(parent.path(), &out);
}

#[test]
fn cli_png16_stream_matches_the_library_bake() {
    let dir = tempfile::tempdir().unwrap();
    let mut rng = Rng(12);
    let (w, h) = (41, 77);
    let gray: Vec<u16> = (0..w * h).map(|_| (rng.next_u64() >> 48) as u16).collect();
    let input = dir.path().join("in.png");
    std::fs::write(&input, encode16(w, h, PngColor::Gray, &gray).unwrap()).unwrap();
    let out = dir.path().join("out");
    let st = Command::new(env!("CARGO_BIN_EXE_horizon-bake"))
        .args(["bake", input.to_str().unwrap(), "-o", out.to_str().unwrap()])
        .args(["--format", "png16", "--radius", "6"])
        .output()
        .unwrap();
    assert!(st.status.success(), "{}", String::from_utf8_lossy(&st.stderr));

    let values = gray.iter().map(|&v| (v as f64 / 65535.0) as f32).collect();
    let map = HeightMap::from_values(w, h, values).unwrap();
    let params = BakeParams::from_pairs([("radius", "6")]).unwrap();
    let p16 = Precisions { u8: false, u16: true, f32: false };
    let (layers, _) = bake::bake_horizon(&map, &params, p16, &Progress::new()).unwrap();
    let l16 = layers.u16.unwrap();
    for (k, want) in l16.iter().enumerate() {
        let got = decode16(&std::fs::read(out.join(format!("horizon_{k}.png"))).unwrap());
        assert!(got == *want, "CLI horizon_{k}.png differs from bake_horizon");
    }
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("bake.json")).unwrap()).unwrap();
    assert_eq!(report["output"]["files"], serde_json::json!(["horizon_0.png", "horizon_1.png"]));
    assert_eq!(report["output"]["width"], w);
    assert_eq!(report["output"]["height"], h);
}

/// A small streamed PNG is never larger than its raw samples (plus the chunk framing): on a
/// rough map the horizon layers are close to noise, where a streaming fast deflate used to
/// write 312 KB for 262 KB of samples at 256².
#[test]
fn small_streamed_pngs_are_not_larger_than_raw() {
    let mut rng = Rng(1414);
    for (n, scale) in [(256usize, "64"), (181, "200"), (64, "30")] {
        let map = random_map(&mut rng, n, n);
        let params = BakeParams::from_pairs([("height_scale", scale)]).unwrap();
        let (pngs, _, _) = stream::<u8>(&map, &params);
        let (pngs16, _, _) = stream::<u16>(&map, &params);
        for (png, raw) in
            pngs.iter().map(|p| (p, n * n * 4)).chain(pngs16.iter().map(|p| (p, n * n * 8)))
        {
            assert!(png.len() <= raw + 1024, "{n}²: {} bytes for {raw} raw", png.len());
        }
        // Still the same samples.
        assert_eq!(decode8(&pngs[0]).len(), n * n * 4);
    }
}
