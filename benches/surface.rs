//! What the surface maps (SPEC §3.8: `normal`, `ao`, `bent_normal`) cost beside the horizon
//! layers they come from: prints a Markdown table, per method, of the bake through
//! `pipeline::produce` (decode excluded; the PNGs encoded, kept in memory) with
//! `--outputs horizon` and with `horizon,normal,ao,bent_normal`, best of 3 each, the ratio of
//! the two measured in the same run, and Mtexel/s of each.
//!
//! ```sh
//! cargo test --bench surface            # 2048², the optimised test profile
//! cargo test --bench surface -- 1024    # another size
//! ```
//!
//! The map: periodic fBm value noise (`common::fbm`), 64 texels of relief, `edge=wrap`, png8
//! layers (the streamed path: the surface maps come from the layers' own kernel pass).

mod common;

use horizon_bake::encode::{Formats, OutFile};
use horizon_bake::heightmap::HeightMap;
use horizon_bake::params::BakeParams;
use horizon_bake::pipeline::{self, Sink};
use horizon_bake::progress::Progress;
use std::time::Instant;

/// Keeps every file's bytes in memory, as the CLI's staging directory keeps them on disk.
struct Keep(Vec<(&'static str, usize)>);

impl Sink for Keep {
    type Writer = Vec<u8>;
    fn writer(&mut self, _name: &'static str) -> horizon_bake::Result<Vec<u8>> {
        Ok(Vec::new())
    }
    fn finish(&mut self, files: [(&'static str, Vec<u8>); 2]) -> horizon_bake::Result<()> {
        self.0.extend(files.iter().map(|(n, b)| (*n, b.len())));
        Ok(())
    }
    fn put(&mut self, file: OutFile) -> horizon_bake::Result<()> {
        self.0.push((file.name, file.bytes.len()));
        Ok(())
    }
    fn finish_one(&mut self, name: &'static str, file: Vec<u8>) -> horizon_bake::Result<()> {
        self.0.push((name, file.len()));
        Ok(())
    }
}

/// Best of 3 wall seconds of one bake, and the files it kept.
fn bake(map: &HeightMap, pairs: &[(&str, &str)]) -> (f64, Vec<(&'static str, usize)>) {
    let params = BakeParams::from_pairs(pairs.iter().copied()).expect("params");
    let mut best = f64::MAX;
    let mut kept = Vec::new();
    for _ in 0..3 {
        let mut sink = Keep(Vec::new());
        let t = Instant::now();
        pipeline::produce(map.clone(), &params, &Formats::default(), &Progress::new(), &mut sink)
            .expect("bake");
        best = best.min(t.elapsed().as_secs_f64());
        kept = sink.0;
    }
    (best, kept)
}

fn main() {
    let n: usize = std::env::args().skip(1).find_map(|a| a.parse().ok()).unwrap_or(2048);
    let map = HeightMap::from_values(n, n, common::fbm(n)).expect("map");
    let texels = (n * n) as f64;
    println!(
        "fBm {n}², height_scale 64, edge=wrap, png8, {} threads; best of 3 each.\n",
        rayon::current_num_threads()
    );
    println!("| method | horizon s | + normal, ao, bent_normal s | ratio | Mtexel/s horizon | Mtexel/s all |");
    println!("|---|---:|---:|---:|---:|---:|");
    for (name, method) in [
        ("lengyel R 16", &[("method", "lengyel"), ("radius", "16")][..]),
        ("exact R 16, 32 bins", &[("method", "exact"), ("radius", "16")][..]),
        ("march R 64, 32 bins", &[("method", "march"), ("radius", "64")][..]),
        ("sweep unlimited, 32 bins", &[("method", "sweep"), ("radius", "unlimited")][..]),
    ] {
        let mut pairs = vec![("height_scale", "64"), ("outputs", "horizon")];
        pairs.extend_from_slice(method);
        let (alone, files) = bake(&map, &pairs);
        assert_eq!(files.len(), 2, "{name}: {files:?}");
        pairs[1] = ("outputs", "horizon,normal,ao,bent_normal");
        let (all, files) = bake(&map, &pairs);
        assert_eq!(files.len(), 5, "{name}: {files:?}");
        println!(
            "| {name} | {alone:.3} | {all:.3} | {:.2} | {:.2} | {:.2} |",
            all / alone,
            texels / alone / 1e6,
            texels / all / 1e6
        );
    }
}
