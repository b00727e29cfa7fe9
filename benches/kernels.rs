//! Kernel benchmarks: prints a Markdown table (method, size, radius, bins, threads, ms,
//! Mtexel/s, ratio to the oracle measured in the same run).
//!
//! ```sh
//! cargo bench --bench kernels --no-run        # build once (release profile)
//! target/release/deps/kernels-<hash> [--quick] # or: cargo bench --bench kernels -- --quick
//! ```
//!
//! The plain oracle is far too slow for a 2048² map (minutes), so it is timed on a crop at the
//! same radius and bins and its time scaled by texel count to the full size; the table says so.
//! Fast rows run through the band driver with a sink that only reads the result, so they time
//! the kernel, not output buffers. The last row bakes 8192² through `bake::bake_horizon` with
//! 16-bit precision and encodes both layers with `encode::png::encode16`, in a child process so
//! its peak resident memory (VmHWM) is its own. `--quick` (or `HORIZON_BENCH_QUICK=1`) shrinks
//! everything for a smoke run.

use horizon_bake::bake::{self, Precisions};
use horizon_bake::encode::png::{encode16, PngColor};
use horizon_bake::heightmap::HeightMap;
use horizon_bake::kernels::lengyel::LengyelNaive;
use horizon_bake::kernels::lengyel_fast::{Isa, LengyelFast};
use horizon_bake::kernels::{band_rows, run_bands, Grid, HorizonRows};
use horizon_bake::params::{BakeParams, Edge, YAxis};
use horizon_bake::progress::Progress;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Instant;

/// A deterministic rolling terrain with fine noise, in texel units (a few texels of relief).
fn terrain(w: usize, h: usize) -> Vec<f32> {
    let mut state = 0x9E37_79B9_7F4A_7C15u64;
    (0..w * h)
        .map(|k| {
            let (x, y) = ((k % w) as f32, (k / w) as f32);
            state = state.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1);
            let noise = (state >> 40) as f32 / (1u64 << 24) as f32;
            let smooth = (x * 0.031).sin() * (y * 0.023).cos() + 0.5 * (x * 0.11 + y * 0.07).sin();
            4.0 * smooth + 0.8 * noise
        })
        .collect()
}

/// CPU seconds (user + system, all threads) this process has used, from /proc/self/stat; 0
/// off Linux. The machine is shared, so wall time alone can hide how fast the kernel is.
fn cpu_seconds() -> f64 {
    let Ok(s) = std::fs::read_to_string("/proc/self/stat") else {
        return 0.0;
    };
    // Fields after the parenthesised command name; utime and stime are fields 14 and 15.
    let rest = s.rsplit_once(')').map(|(_, r)| r).unwrap_or("");
    let f: Vec<&str> = rest.split_whitespace().collect();
    let ticks: f64 =
        f.get(11..13).map_or(0.0, |v| v.iter().filter_map(|x| x.parse::<f64>().ok()).sum());
    ticks / 100.0 // USER_HZ is 100 on Linux
}

/// (wall seconds, CPU seconds) to run `kernel` over its whole grid (best wall of `reps`).
fn time_kernel<K: HorizonRows + ?Sized>(kernel: &K, reps: usize) -> (f64, f64) {
    let mut best = (f64::INFINITY, 0.0);
    for _ in 0..reps {
        let sink_sum = AtomicU64::new(0);
        let cpu0 = cpu_seconds();
        let t = Instant::now();
        let band = band_rows(kernel.width(), kernel.height());
        run_bands(kernel, band, false, &Progress::new(), |_, b| {
            // Read one value per band so the work cannot be optimised away.
            let v = b.channels.first().copied().unwrap_or(0.0);
            sink_sum.fetch_add(v.to_bits() as u64, Ordering::Relaxed);
        })
        .expect("not canceled");
        let wall = t.elapsed().as_secs_f64();
        if wall < best.0 {
            best = (wall, cpu_seconds() - cpu0);
        }
        std::hint::black_box(sink_sum.load(Ordering::Relaxed));
    }
    best
}

struct Row {
    method: String,
    size: String,
    radius: u32,
    bins: u32,
    threads: usize,
    ms: f64,
    cpu_ms: f64,
    texels: f64,
    ratio: String,
}

fn print_table(rows: &[Row]) {
    println!(
        "| method | size | radius | bins | threads | ms | Mtexel/s | ratio to oracle \
         | CPU ms | Mtexel per CPU-s |"
    );
    println!("| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |");
    for r in rows {
        println!(
            "| {} | {} | {} | {} | {} | {:.1} | {:.2} | {} | {:.0} | {:.2} |",
            r.method,
            r.size,
            r.radius,
            r.bins,
            r.threads,
            r.ms,
            r.texels / r.ms / 1e3,
            r.ratio,
            r.cpu_ms,
            r.texels / r.cpu_ms / 1e3
        );
    }
    println!(
        "\nratio = fast Mtexel/s ÷ oracle Mtexel/s at the same radius and bins, both measured \
         in this run; CPU ms counts every thread, so on a busy machine Mtexel per CPU-s × \
         threads estimates the uncontended all-core rate."
    );
}

/// Reads a `VmHWM`-style line of /proc/self/status in MiB (None off Linux).
fn proc_status_mib(key: &str) -> Option<f64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = s.lines().find(|l| l.starts_with(key))?;
    let kb: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb / 1024.0)
}

/// The memory bake, run in a child process: prints one line
/// `MEM <bake ms> <total ms> <peak MiB after the bake> <peak MiB after encoding> <png bytes>`.
fn memory_child(n: usize) {
    let map = HeightMap::from_values(n, n, terrain(n, n)).expect("valid map");
    let params = BakeParams::default();
    let t = Instant::now();
    let (layers, _) = bake::bake_horizon(
        &map,
        &params,
        Precisions { u8: false, u16: true, f32: false },
        &Progress::new(),
    )
    .expect("bake");
    let bake_ms = t.elapsed().as_secs_f64() * 1e3;
    let hwm_bake = proc_status_mib("VmHWM:").unwrap_or(f64::NAN);
    drop(map);
    let mut png_bytes = 0;
    if let Some(l16) = layers.u16.as_ref() {
        for layer in l16 {
            png_bytes += encode16(n, n, PngColor::Rgba, layer).expect("png16").len();
        }
    }
    let total_ms = t.elapsed().as_secs_f64() * 1e3;
    let hwm = proc_status_mib("VmHWM:").unwrap_or(f64::NAN);
    println!("MEM {bake_ms:.1} {total_ms:.1} {hwm_bake:.1} {hwm:.1} {png_bytes}");
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    if let Some(k) = args.iter().position(|a| a == "--memory-child") {
        let n = args.get(k + 1).and_then(|s| s.parse().ok()).unwrap_or(8192);
        memory_child(n);
        return;
    }
    if let Some(k) = args.iter().position(|a| a == "--profile") {
        // A loop of the default fast configuration only, for `perf record`.
        let reps = args.get(k + 1).and_then(|s| s.parse().ok()).unwrap_or(10);
        let hs = terrain(2048, 2048);
        let grid = Grid::new(2048, 2048, &hs, Edge::Wrap, YAxis::Up);
        let (secs, cpu) = time_kernel(&LengyelFast::new(grid, 16, 32), reps);
        println!("best {:.1} ms, {:.0} CPU ms", secs * 1e3, cpu * 1e3);
        return;
    }
    let quick = args.iter().any(|a| a == "--quick")
        || std::env::var("HORIZON_BENCH_QUICK").is_ok_and(|v| v != "0");
    let threads = rayon::current_num_threads();
    let n = if quick { 512 } else { 2048 };
    let hs = terrain(n, n);
    let grid = Grid::new(n, n, &hs, Edge::Wrap, YAxis::Up);
    println!(
        "horizon-bake kernel bench: {} threads, CPU variant {:?}{}\n",
        threads,
        Isa::detect(),
        if quick { " (quick)" } else { "" }
    );

    let configs: [(u32, u32); 4] = [(16, 32), (32, 32), (64, 32), (16, 64)];
    let mut rows = Vec::new();
    // Oracle per (radius, bins): crop size chosen so each run takes a fraction of a second.
    let mut oracle_rate = Vec::new();
    for &(r, b) in &configs {
        let crop = (if quick { 8192 } else { 65536 }) / (r as usize / 16).pow(2);
        let cw = crop.min(n).min(128);
        let ch = (crop / cw).clamp(1, n);
        let crop_hs: Vec<f32> = (0..ch).flat_map(|y| hs[y * n..y * n + cw].to_vec()).collect();
        let cg = Grid::new(cw, ch, &crop_hs, Edge::Wrap, YAxis::Up);
        let (secs, cpu) = time_kernel(&LengyelNaive::new(cg, r, b), 1);
        let rate = (cw * ch) as f64 / secs;
        let scale = (n * n) as f64 / (cw * ch) as f64;
        oracle_rate.push(rate);
        let full = (n * n) as f64;
        rows.push(Row {
            method: format!("oracle (timed on {cw}×{ch} crop, scaled)"),
            size: format!("{n}²"),
            radius: r,
            bins: b,
            threads,
            ms: full / rate * 1e3,
            cpu_ms: cpu * scale * 1e3,
            texels: full,
            ratio: "1.0×".into(),
        });
    }
    let reps = if quick { 1 } else { 3 };
    for (k, &(r, b)) in configs.iter().enumerate() {
        let isas: &[Isa] =
            if k == 0 { &[Isa::Avx512, Isa::Avx2, Isa::Baseline] } else { &[Isa::detect()] };
        for &isa in isas {
            if !isa.supported() {
                continue; // this CPU lacks the variant
            }
            let kernel = LengyelFast::with_isa(grid, r, b, isa);
            let (secs, cpu) = time_kernel(&kernel, reps);
            let full = (n * n) as f64;
            rows.push(Row {
                method: format!("lengyel fast ({:?})", kernel.isa()),
                size: format!("{n}²"),
                radius: r,
                bins: b,
                threads,
                ms: secs * 1e3,
                cpu_ms: cpu * 1e3,
                texels: full,
                ratio: format!("{:.0}×", full / secs / oracle_rate[k]),
            });
        }
    }
    print_table(&rows);

    // Peak memory of a full bake + PNG16 encode, in a fresh process.
    let mem_n = if quick { 2048 } else { 8192 };
    println!();
    match std::env::current_exe().and_then(|exe| {
        std::process::Command::new(exe).args(["--memory-child", &mem_n.to_string()]).output()
    }) {
        Ok(out) => {
            let text = String::from_utf8_lossy(&out.stdout);
            let line = text.lines().find(|l| l.starts_with("MEM ")).unwrap_or("");
            let f: Vec<&str> = line.split_whitespace().collect();
            if f.len() == 6 {
                let bake_ms: f64 = f[1].parse().unwrap_or(f64::NAN);
                let png_mib = f[5].parse::<f64>().unwrap_or(0.0) / 1048576.0;
                println!(
                    "| what | size | threads | bake ms \
                     | bake + PNG ms | Mtexel/s (bake) | peak RSS after bake MiB \
                     | peak RSS after PNG MiB | PNG MiB |"
                );
                println!("| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |");
                println!(
                    "| bake_horizon (defaults, u16) + encode16 ×2 | {mem_n}² | {threads} | {bake_ms:.0} | {} | {:.2} \
                     | {} | {} | {png_mib:.1} |",
                    f[2],
                    (mem_n * mem_n) as f64 / bake_ms / 1e3,
                    f[3],
                    f[4],
                );
                let mib = |bytes: usize| bytes as f64 / 1048576.0;
                let texels = mem_n * mem_n;
                println!(
                    "\nwhere it goes: input heights {:.0} MiB + scaled copy {:.0} MiB + two u16 \
                     layers {:.0} MiB during the bake; encode16 adds a big-endian copy of a layer \
                     ({:.0} MiB) and the PNGs themselves.",
                    mib(texels * 4),
                    mib(texels * 4),
                    mib(texels * 8 * 2),
                    mib(texels * 4 * 2)
                );
            } else {
                println!(
                    "memory bench failed: {}\n{}",
                    out.status,
                    String::from_utf8_lossy(&out.stderr)
                );
            }
        }
        Err(e) => println!("memory bench could not start: {e}"),
    }
}
