//! PNG encode throughput: prints a Markdown table (layer, writer, threads, wall and process CPU
//! ms, MB/s of samples, ratio to the single-stream writer measured in the same run, compressed
//! size against its, and whether the bytes are its bytes).
//!
//! ```sh
//! cargo test --bench png_encode            # the optimised test profile, as the tiles bench runs
//! cargo test --bench png_encode -- --quick # 1024² instead of 4096²
//! ```
//!
//! Three RGBA8 layers of N² (N = 4096, `--quick` 1024): a real horizon layer (layer 0 of the
//! tiles bench's input, `common::terrain_png16`, baked at R 16 into png8 samples), the same
//! bake of a smooth fBm terrain (`common::fbm`, 100 texels of relief, no fine noise), and white
//! noise (every piece stored). Writers: the single-stream one the crate used before
//! (`png::single_stream`, the baseline), the parallel [`PngRowWriter`] on rayon pools of 1 and 2
//! threads and on a plain thread (its scoped-thread path, as the tiled assembly's encoder
//! thread runs it), and with every piece primed with the 32 KiB before it (what the small-image
//! level does; what priming costs and buys at level 1). Each row is the best of 3 runs; rows are fed in bands of 64 rows as the streaming
//! bake does.

mod common;

use horizon_bake::encode::png::single_stream::SingleStreamWriter;
use horizon_bake::encode::png::{PngColor, PngRowWriter};
use std::time::Instant;

const BAND: usize = 64;

fn single(n: usize, d: &[u8]) -> Vec<u8> {
    let mut w = SingleStreamWriter::<_, u8>::new(Vec::new(), n, n, PngColor::Rgba).expect("png");
    for rows in d.chunks(BAND * n * 4) {
        w.write_rows(rows).expect("rows");
    }
    w.finish().expect("finish")
}

fn parallel(n: usize, d: &[u8], dictionary: bool) -> Vec<u8> {
    let mut w = PngRowWriter::<_, u8>::new(Vec::new(), n, n, PngColor::Rgba).expect("png");
    if dictionary {
        w = w.dictionary(true);
    }
    for rows in d.chunks(BAND * n * 4) {
        w.write_rows(rows).expect("rows");
    }
    w.finish().expect("finish")
}

fn pool(n: usize) -> rayon::ThreadPool {
    rayon::ThreadPoolBuilder::new().num_threads(n).build().expect("pool")
}

/// Best of 3: (wall ms, CPU ms of the whole process in that run, output).
fn time(f: &dyn Fn() -> Vec<u8>) -> (f64, f64, Vec<u8>) {
    let (mut best, mut cpu) = (f64::MAX, 0.0);
    let mut out = Vec::new();
    for _ in 0..3 {
        let (t, c) = (Instant::now(), common::cpu_secs());
        out = f();
        let ms = t.elapsed().as_secs_f64() * 1e3;
        if ms < best {
            (best, cpu) = (ms, (common::cpu_secs() - c) * 1e3);
        }
    }
    (best, cpu, out)
}

fn main() {
    let quick = std::env::args().any(|a| a == "--quick")
        || std::env::var("HORIZON_BENCH_QUICK").is_ok_and(|v| v == "1");
    let n = if quick { 1024 } else { 4096 };
    eprintln!("baking the {n}² horizon layer…");
    let input = common::terrain_png16(n, 0);
    let params = horizon_bake::params::BakeParams::from_pairs([("radius", "16")]).expect("params");
    let (map, _) = horizon_bake::heightmap::decode(&input, params.channel, &Default::default())
        .expect("decode");
    let (layers, _) = horizon_bake::bake::bake_horizon(
        &map,
        &params,
        horizon_bake::bake::Precisions { u8: true, u16: false, f32: false },
        &horizon_bake::progress::Progress::new(),
    )
    .expect("bake");
    let [horizon, _] = layers.u8.expect("u8 layers");
    // A smoother one: the same bake of `common::fbm` (no fine noise), 100 texels of relief.
    let fbm: Vec<f32> = common::fbm(n).into_iter().map(|v| v * 100.0).collect();
    let smooth_map = horizon_bake::heightmap::HeightMap::from_values(n, n, fbm).expect("map");
    let (layers, _) = horizon_bake::bake::bake_horizon(
        &smooth_map,
        &horizon_bake::params::BakeParams::from_pairs([("radius", "16"), ("height_scale", "1")])
            .expect("params"),
        horizon_bake::bake::Precisions { u8: true, u16: false, f32: false },
        &horizon_bake::progress::Progress::new(),
    )
    .expect("bake");
    let [smooth, _] = layers.u8.expect("u8 layers");
    let heights: Vec<u8> = map.values.iter().flat_map(|v| v.to_le_bytes()).collect();
    let mut s = 5u64;
    let noise: Vec<u8> = (0..n * n * 4).map(|_| (common::splitmix(&mut s) >> 56) as u8).collect();
    let (p1, p2) = (pool(1), pool(2));
    println!(
        "\nPNG encode, {n}² RGBA8 ({:.1} MB of samples), best of 3, machine load {}\n",
        (n * n * 4) as f64 / 1e6,
        load()
    );
    println!(
        "| layer | writer | threads | ms | CPU ms | MB/s | × single-stream | bytes | × its size | \
         its bytes |"
    );
    println!("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |");
    let mut decodes = Vec::new();
    for (name, d) in [
        ("horizon R16 png8", &horizon),
        ("horizon R16 png8, smooth fBm", &smooth),
        ("noise", &noise),
    ] {
        let mb = d.len() as f64 / 1e6;
        let (base_ms, base_cpu, base) = time(&|| single(n, d));
        let want = image::load_from_memory(&base).expect("decode").to_rgba8().into_raw();
        assert!(&want == d, "the single-stream writer decodes to the samples");
        let row = |writer: &str, threads: &str, (ms, cpu, out): &(f64, f64, Vec<u8>)| {
            println!(
                "| {name} | {writer} | {threads} | {ms:.0} | {cpu:.0} | {:.0} | {:.2} | {} | {:.4} | {} |",
                mb / (ms / 1e3),
                base_ms / ms,
                out.len(),
                out.len() as f64 / base.len() as f64,
                if *out == base { "yes" } else { "no" }
            );
        };
        row("single stream (before)", "1", &(base_ms, base_cpu, base.clone()));
        let one = time(&|| p1.install(|| parallel(n, d, false)));
        row("pieces (the writer)", "1 (pool)", &one);
        let two = time(&|| p2.install(|| parallel(n, d, false)));
        row("pieces (the writer)", "2 (pool)", &two);
        let plain = time(&|| {
            std::thread::scope(|sc| sc.spawn(|| parallel(n, d, false)).join().expect("thread"))
        });
        let threads = format!("{} (plain thread)", rayon::current_num_threads());
        row("pieces (the writer)", &threads, &plain);
        let primed1 = time(&|| p1.install(|| parallel(n, d, true)));
        row("pieces primed with the 32 KiB before", "1 (pool)", &primed1);
        let primed2 = time(&|| p2.install(|| parallel(n, d, true)));
        row("pieces primed with the 32 KiB before", "2 (pool)", &primed2);
        let (out1, out2, outp) = (&one.2, &two.2, &plain.2);
        assert!(out1 == out2 && out1 == outp, "{name}: the same bytes on any number of threads");
        assert!(primed1.2 == primed2.2, "{name}: primed, the same bytes on 1 and 2 threads");
        for png in [out1, &primed1.2] {
            let got = image::load_from_memory(png).expect("decode").to_rgba8().into_raw();
            assert!(&got == d, "{name}: decodes to the samples");
        }
        // What readers pay: the `image` crate's decode of each writer's file (best of 3).
        let decode = |png: &[u8]| {
            time(&|| image::load_from_memory(png).expect("decode").to_rgba8().into_raw()).0
        };
        decodes.push((name, decode(&base), decode(out1)));
    }
    println!();
    println!("| layer | decode ms, single stream | decode ms, pieces | × |");
    println!("| --- | --- | --- | --- |");
    for (name, a, b) in decodes {
        println!("| {name} | {a:.0} | {b:.0} | {:.2} |", a / b);
    }
    // Issue 23's other lever: would tile blobs cross the store smaller? A tile result holds
    // the raw samples of its layers (as `horizon` here), a tile window the input's f32 heights.
    println!("\nzstd level 1 of raw tile blob contents, {n}², one thread\n");
    println!("| blob content | MB | zstd MB | × size | compress MB/s | decompress MB/s |");
    println!("| --- | --- | --- | --- | --- | --- |");
    for (name, d) in [
        ("tile result: horizon R16 png8 samples", &horizon),
        ("tile window: f32 heights of the input", &heights),
        ("noise", &noise),
    ] {
        let t = Instant::now();
        let z = zstd::bulk::compress(d, 1).expect("zstd");
        let c = t.elapsed().as_secs_f64();
        let t = Instant::now();
        let back = zstd::bulk::decompress(&z, d.len()).expect("unzstd");
        let u = t.elapsed().as_secs_f64();
        assert!(&back == d);
        let mb = d.len() as f64 / 1e6;
        println!(
            "| {name} | {mb:.1} | {:.1} | {:.3} | {:.0} | {:.0} |",
            z.len() as f64 / 1e6,
            z.len() as f64 / d.len() as f64,
            mb / c,
            mb / u
        );
    }
}

fn load() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .map(|l| l.split_whitespace().take(3).collect::<Vec<_>>().join(" "))
        .unwrap_or_default()
}
