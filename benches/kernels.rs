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
//! the kernel, not output buffers.
//!
//! The memory table bakes 8192² at defaults with 16-bit outputs three ways, each in its own
//! process so its peak resident memory is its own: the whole-layer baseline
//! (`bake::bake_horizon` + `encode::png::encode16` ×2 in memory), the streaming path
//! (`bake::stream_horizon` into two `PngRowWriter` files) and the real CLI
//! (`horizon-bake bake terrain.png --format png16`) on a ridged fractal terrain written as a
//! 16-bit PNG (peak sampled from /proc/PID/status while it runs). `--write-terrain PATH N` writes
//! that input alone. `--quick` (or `HORIZON_BENCH_QUICK=1`) shrinks everything for a smoke run.

use horizon_bake::bake::{self, LayerRows, Precisions};
use horizon_bake::encode::png::{encode16, PngColor, PngRowWriter};
use horizon_bake::heightmap::HeightMap;
use horizon_bake::kernels::isa::Isa;
use horizon_bake::kernels::lengyel::LengyelFast;
use horizon_bake::kernels::lengyel::LengyelNaive;
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

/// A ridged multifractal terrain (value noise, 8 octaves) as 16-bit samples spanning 0..65535:
/// sharp crests and smooth valleys, with detail at every scale, like an exported DEM. It does
/// not compress the way a smooth test pattern would.
fn ridged_terrain(n: usize) -> Vec<u16> {
    fn hash(x: i64, y: i64, o: u64) -> f32 {
        let mut z = (x as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
            ^ (y as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F)
            ^ o.wrapping_mul(0x1656_67B1_9E37_79F9);
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) >> 40) as f32 / (1u64 << 24) as f32
    }
    fn noise(x: f32, y: f32, o: u64) -> f32 {
        let (xi, yi) = (x.floor() as i64, y.floor() as i64);
        let (fx, fy) = (x - x.floor(), y - y.floor());
        let (sx, sy) = (fx * fx * (3.0 - 2.0 * fx), fy * fy * (3.0 - 2.0 * fy));
        let a = hash(xi, yi, o) + (hash(xi + 1, yi, o) - hash(xi, yi, o)) * sx;
        let b = hash(xi, yi + 1, o) + (hash(xi + 1, yi + 1, o) - hash(xi, yi + 1, o)) * sx;
        a + (b - a) * sy
    }
    let mut v: Vec<f32> = (0..n * n)
        .map(|k| {
            let (x, y) = ((k % n) as f32, (k / n) as f32);
            let (mut sum, mut amp, mut freq, mut weight) = (0.0f32, 0.5f32, 4.0 / n as f32, 1.0);
            for o in 0..8 {
                let r = 1.0 - (2.0 * noise(x * freq, y * freq, o) - 1.0).abs();
                let r = r * r * weight;
                weight = r.clamp(0.0, 1.0);
                sum += r * amp;
                amp *= 0.5;
                freq *= 2.0;
            }
            sum
        })
        .collect();
    let (lo, hi) = v.iter().fold((f32::MAX, f32::MIN), |(l, h), &x| (l.min(x), h.max(x)));
    let span = (hi - lo).max(1e-6);
    v.iter_mut().for_each(|x| *x = (*x - lo) / span);
    v.into_iter().map(|x| (x * 65535.0).round() as u16).collect()
}

/// Writes [`ridged_terrain`] as a 16-bit gray PNG.
fn write_terrain(path: &std::path::Path, n: usize) -> std::io::Result<()> {
    let png = encode16(n, n, PngColor::Gray, &ridged_terrain(n)).map_err(std::io::Error::other)?;
    std::fs::write(path, png)
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

/// The streaming memory bake, run in a child process: `stream_horizon` into two PNG files in a
/// temporary directory. Prints the same `MEM` line as [`memory_child`] (bake and encoding are
/// one pass here, so both peaks are the same reading).
fn memory_child_stream(n: usize) {
    let map = HeightMap::from_values(n, n, terrain(n, n)).expect("valid map");
    let dir = tempfile::tempdir().expect("temp dir");
    let t = Instant::now();
    let file =
        |k: usize| std::fs::File::create(dir.path().join(format!("h{k}.png"))).expect("file");
    let mut writers = [
        PngRowWriter::<_, u16>::new(file(0), n, n, PngColor::Rgba).expect("png"),
        PngRowWriter::<_, u16>::new(file(1), n, n, PngColor::Rgba).expect("png"),
    ];
    bake::stream_horizon(
        map,
        &BakeParams::default(),
        &Progress::new(),
        |rows: LayerRows<'_, u16>| {
            // As the CLI does: the two layers' deflate streams in parallel.
            let [w0, w1] = &mut writers;
            let (a, b) =
                rayon::join(|| w0.write_rows(rows.layers[0]), || w1.write_rows(rows.layers[1]));
            a.and(b)
        },
    )
    .expect("bake");
    let mut png_bytes = 0;
    for w in writers {
        let f = w.finish().expect("png finish");
        png_bytes += f.metadata().map(|m| m.len() as usize).unwrap_or(0);
    }
    let ms = t.elapsed().as_secs_f64() * 1e3;
    let hwm = proc_status_mib("VmHWM:").unwrap_or(f64::NAN);
    println!("MEM {ms:.1} {ms:.1} {hwm:.1} {hwm:.1} {png_bytes}");
}

/// Runs this bench binary with `args` and parses its `MEM` line.
fn run_child(args: &[&str]) -> Result<Vec<f64>, String> {
    let exe = std::env::current_exe().map_err(|e| e.to_string())?;
    let out = std::process::Command::new(exe).args(args).output().map_err(|e| e.to_string())?;
    let text = String::from_utf8_lossy(&out.stdout);
    let line = text.lines().find(|l| l.starts_with("MEM ")).unwrap_or("");
    let f: Vec<f64> = line.split_whitespace().skip(1).filter_map(|x| x.parse().ok()).collect();
    if f.len() == 5 {
        Ok(f)
    } else {
        Err(format!("{}: {}", out.status, String::from_utf8_lossy(&out.stderr)))
    }
}

/// Peak RSS in MiB of the real CLI baking `input` to png16, sampled from /proc/PID/status every
/// 5 ms while it runs (VmHWM only grows, so the last reading is the peak up to then), and the
/// wall time in ms.
fn cli_peak(
    input: &std::path::Path,
    out: &std::path::Path,
    extra: &[&str],
) -> Result<(f64, f64), String> {
    let t = Instant::now();
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_horizon-bake"))
        .arg("bake")
        .arg(input)
        .arg("-o")
        .arg(out)
        .args(["--format", "png16"])
        .args(extra)
        .stderr(std::process::Stdio::piped())
        .spawn()
        .map_err(|e| e.to_string())?;
    let status_path = format!("/proc/{}/status", child.id());
    let mut peak = 0.0f64;
    loop {
        if let Ok(s) = std::fs::read_to_string(&status_path) {
            if let Some(kb) = s
                .lines()
                .find(|l| l.starts_with("VmHWM:"))
                .and_then(|l| l.split_whitespace().nth(1))
                .and_then(|v| v.parse::<f64>().ok())
            {
                peak = peak.max(kb / 1024.0);
            }
        }
        match child.try_wait() {
            Ok(Some(st)) if st.success() => return Ok((peak, t.elapsed().as_secs_f64() * 1e3)),
            Ok(Some(st)) => return Err(format!("CLI failed: {st}")),
            Ok(None) => std::thread::sleep(std::time::Duration::from_millis(5)),
            Err(e) => return Err(e.to_string()),
        }
    }
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    if let Some(k) = args.iter().position(|a| a == "--memory-child") {
        let n = args.get(k + 1).and_then(|s| s.parse().ok()).unwrap_or(8192);
        memory_child(n);
        return;
    }
    if let Some(k) = args.iter().position(|a| a == "--memory-child-stream") {
        let n = args.get(k + 1).and_then(|s| s.parse().ok()).unwrap_or(8192);
        memory_child_stream(n);
        return;
    }
    if let Some(k) = args.iter().position(|a| a == "--write-terrain") {
        let path = args.get(k + 1).map(String::as_str).unwrap_or("terrain.png");
        let n = args.get(k + 2).and_then(|s| s.parse().ok()).unwrap_or(8192);
        write_terrain(std::path::Path::new(path), n).expect("write terrain");
        return;
    }
    if let Some(k) = args.iter().position(|a| a == "--profile") {
        // A loop of the default fast configuration only, for `perf record`:
        // `--profile [REPS] [avx512|avx2|baseline]` (the CPU's best variant by default).
        let reps = args.get(k + 1).and_then(|s| s.parse().ok()).unwrap_or(10);
        let isa = match args.get(k + 2).map(String::as_str) {
            Some("avx2") => Isa::Avx2,
            Some("baseline") => Isa::Baseline,
            _ => Isa::detect(),
        };
        let hs = terrain(2048, 2048);
        let grid = Grid::new(2048, 2048, &hs, Edge::Wrap, YAxis::Up);
        let kernel = LengyelFast::with_isa(grid, 16, 32, isa);
        let (secs, cpu) = time_kernel(&kernel, reps);
        println!("best {:.1} ms, {:.0} CPU ms ({:?})", secs * 1e3, cpu * 1e3, kernel.isa());
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

    // Peak memory of a full 16-bit bake + PNG encode, each way in a fresh process.
    let mem_n = if quick { 2048 } else { 8192 };
    let n_arg = mem_n.to_string();
    println!(
        "\n| what | size | threads | bake ms | bake + PNG ms | Mtexel/s (bake + PNG) \
         | peak RSS after bake MiB | peak RSS after PNG MiB | PNG MiB |"
    );
    println!("| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |");
    let texels = (mem_n * mem_n) as f64;
    let children = [
        ("baseline, whole layers: bake_horizon (u16) + encode16 ×2 in memory", "--memory-child"),
        ("streamed: stream_horizon (u16) → PngRowWriter ×2 → files", "--memory-child-stream"),
    ];
    for (what, flag) in children {
        match run_child(&[flag, &n_arg]) {
            Ok(f) => println!(
                "| {what} | {mem_n}² | {threads} | {:.0} | {:.0} | {:.2} | {:.0} | {:.0} | {:.1} |",
                f[0],
                f[1],
                texels / f[1] / 1e3,
                f[2],
                f[3],
                f[4] / 1048576.0
            ),
            Err(e) => println!("| {what} | {mem_n}² | {threads} | failed: {e} | | | | | |"),
        }
    }
    // The real CLI on a 16-bit PNG of ridged fractal terrain (defaults, --format png16).
    // And `method=sweep` at `unlimited`, whose far field (W·H·bins f32: 8 GiB at 8192²) goes
    // to a temporary file beyond 512 MiB: its memory must stay near the others'.
    let sweep = ["--method", "sweep", "--radius", "unlimited", "--edge", "none"];
    let cli_rows = [
        ("CLI: horizon-bake bake terrain.png --format png16 (decode + stream)", &[][..]),
        ("CLI: the same with --method sweep --radius unlimited --edge none", &sweep[..]),
    ];
    for (what, extra) in cli_rows {
        let cli_row = tempfile::tempdir().map_err(|e| e.to_string()).and_then(|dir| {
            let input = dir.path().join("terrain.png");
            write_terrain(&input, mem_n).map_err(|e| e.to_string())?;
            let (peak, ms) = cli_peak(&input, &dir.path().join("out"), extra)?;
            let png: u64 = ["horizon_0.png", "horizon_1.png"]
                .iter()
                .filter_map(|f| std::fs::metadata(dir.path().join("out").join(f)).ok())
                .map(|m| m.len())
                .sum();
            Ok((peak, ms, png))
        });
        match cli_row {
            Ok((peak, ms, png)) => println!(
                "| {what} | {mem_n}² | {threads} | | {ms:.0} | {:.2} | {peak:.0} | {peak:.0} | {:.1} |",
                texels / ms / 1e3,
                png as f64 / 1048576.0
            ),
            Err(e) => println!("| {what} | {mem_n}² | {threads} | failed: {e} | | | | | |"),
        }
    }
    let mib = |bytes: usize| bytes as f64 / 1048576.0;
    let t = mem_n * mem_n;
    println!(
        "\nbaseline: input heights {:.0} MiB + scaled copy {:.0} MiB + two u16 layers {:.0} MiB \
         during the bake; encode16 adds a big-endian copy of a layer ({:.0} MiB) and the PNGs \
         themselves. streamed: the heights scaled in place ({:.0} MiB) plus a few windows of \
         bands. The CLI row includes decoding the input (its bytes, the decoded 16-bit image and \
         the f32 heights are alive together for a moment); its time includes decoding and \
         writing bake.json.",
        mib(t * 4),
        mib(t * 4),
        mib(t * 8 * 2),
        mib(t * 4 * 2),
        mib(t * 4),
    );
}
