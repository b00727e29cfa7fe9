//! Issue 41 item 2: peak resident memory (VmHWM) and speed of `sweep`'s terrain products at
//! `unlimited`, `edge=none`, by the way their horizons come: the planes (`angles` and a plain
//! SVF: azimuth by azimuth, no far-field table) against the table (a `tilted` SVF, which reads
//! the bands: the table in memory up to 512 MiB, beyond that in a temporary file). Not a timed
//! benchmark in the usual sense: each case runs in a process of its own (this binary with
//! `--case N`), so one case's freed memory, which the allocator keeps, is not counted in the
//! next one's peak; the times of one run are comparable with each other only.
//!
//! `cargo bench --bench sweep_rss -- [SIZE]` (default 2048: the map is SIZE², and the cases run
//! 32 and 360 bins on it; Linux only).

use horizon_bake::bake;
use horizon_bake::heightmap::HeightMap;
use horizon_bake::params::BakeParams;
use horizon_bake::progress::Progress;
use std::time::Instant;

#[path = "common/proc_status.rs"]
mod proc_status;
use proc_status::status;

/// (svf model, bins): `radiative` comes from the planes, `tilted` from the table.
const CASES: [(&str, u32); 4] =
    [("radiative", 32), ("tilted", 32), ("radiative", 360), ("tilted", 360)];

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let size: usize = args
        .iter()
        .skip(1)
        .find(|a| a.parse::<usize>().is_ok())
        .and_then(|a| a.parse().ok())
        .unwrap_or(2048);
    let case = args.iter().position(|a| a == "--case").and_then(|i| args.get(i + 1));
    let Some(case) = case else {
        println!("map {size}², sweep, radius=unlimited, edge=none, outputs=svf (Linux VmHWM)");
        println!(
            "{:<34} {:>9} {:>10} {:>11} {:>12}",
            "case", "wall s", "Mtexel/s", "peak MiB", "table MiB"
        );
        let me = std::env::current_exe().unwrap();
        for i in 0..CASES.len() {
            let st = std::process::Command::new(&me)
                .args([&size.to_string(), "--case", &i.to_string()])
                .status()
                .unwrap();
            assert!(st.success(), "case {i} failed");
        }
        return;
    };
    let (model, bins) = CASES[case.parse::<usize>().unwrap()];
    // An fBm-like terrain of a few octaves, heights in texels.
    let values: Vec<f32> = (0..size * size)
        .map(|k| {
            let (x, y) = ((k % size) as f32, (k / size) as f32);
            let mut v = 0.0;
            let mut f = 0.002;
            let mut a = 120.0;
            for _ in 0..6 {
                v += a * (x * f + 0.3 * (y * f * 1.7).sin()).sin() * (y * f * 1.3 + 0.7).cos();
                f *= 2.1;
                a *= 0.45;
            }
            v
        })
        .collect();
    let map = HeightMap::from_values(size, size, values).unwrap();
    let bins_s = bins.to_string();
    let pairs = [
        ("method", "sweep"),
        ("radius", "unlimited"),
        ("edge", "none"),
        ("height_scale", "1"),
        ("outputs", "svf"),
        ("svf_model", model),
        ("bins", bins_s.as_str()),
    ];
    let p = BakeParams::from_pairs(pairs).unwrap();
    let how = if bake::needs_table(&p) { "table" } else { "planes" };
    let table = horizon_bake::kernels::sweep::table_bytes(size as u32, size as u32, bins);
    let spilled = horizon_bake::kernels::sweep::spills(size as u32, size as u32, bins);
    let _ = std::fs::write("/proc/self/clear_refs", "5");
    let t = Instant::now();
    let (products, _) = bake::bake_terrain(&map, &p, &Progress::new()).unwrap();
    let secs = t.elapsed().as_secs_f64();
    let svf = products.svf.unwrap();
    let mean = svf.iter().map(|&v| f64::from(v)).sum::<f64>() / svf.len() as f64;
    let label = format!("{model} svf, {bins} bins ({how})");
    let table_note = match (how, spilled) {
        ("planes", _) => "none".to_string(),
        (_, true) => format!("{} on disk", table >> 20),
        _ => format!("{}", table >> 20),
    };
    println!(
        "{label:<34} {secs:>9.2} {:>10.3} {:>11.1} {table_note:>12}   mean svf {mean:.4}",
        (size * size) as f64 / secs / 1e6,
        status("VmHWM:") as f64 / 1024.0,
    );
}
