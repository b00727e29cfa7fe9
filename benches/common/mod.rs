//! Maps and clocks shared by the benches (each bench is its own crate and includes this file).
#![allow(dead_code)]

pub fn splitmix(state: &mut u64) -> u64 {
    *state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
    let mut z = *state;
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Periodic fBm value noise, 7 octaves, normalised to [0, 1].
pub fn fbm(n: usize) -> Vec<f32> {
    let mut out = vec![0f32; n * n];
    let mut seed = 1234u64;
    let mut amp = 1.0f32;
    let mut cells = 4usize;
    while cells <= n && cells <= 256 {
        let lattice: Vec<f32> = (0..cells * cells)
            .map(|_| (splitmix(&mut seed) >> 40) as f32 / (1u64 << 24) as f32)
            .collect();
        let step = n as f32 / cells as f32;
        for y in 0..n {
            let fy = y as f32 / step;
            let (y0, ty) = (fy.floor() as usize % cells, fy.fract());
            let y1 = (y0 + 1) % cells;
            let ty = ty * ty * (3.0 - 2.0 * ty);
            for x in 0..n {
                let fx = x as f32 / step;
                let (x0, tx) = (fx.floor() as usize % cells, fx.fract());
                let x1 = (x0 + 1) % cells;
                let tx = tx * tx * (3.0 - 2.0 * tx);
                let a = lattice[y0 * cells + x0] * (1.0 - tx) + lattice[y0 * cells + x1] * tx;
                let b = lattice[y1 * cells + x0] * (1.0 - tx) + lattice[y1 * cells + x1] * tx;
                out[y * n + x] += amp * (a * (1.0 - ty) + b * ty);
            }
        }
        amp *= 0.5;
        cells *= 2;
    }
    let (lo, hi) = out.iter().fold((f32::MAX, f32::MIN), |(l, h), &v| (l.min(v), h.max(v)));
    out.iter().map(|v| (v - lo) / (hi - lo)).collect()
}

pub fn white(n: usize) -> Vec<f32> {
    let mut seed = 99u64;
    (0..n * n).map(|_| (splitmix(&mut seed) >> 40) as f32 / (1u64 << 24) as f32).collect()
}

/// CPU seconds used by this process so far (all threads), from /proc/self/stat: on a shared
/// machine wall time alone overstates the cost.
pub fn cpu_secs() -> f64 {
    let stat = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    let after = stat.rsplit(')').next().unwrap_or("");
    let f: Vec<&str> = after.split_whitespace().collect();
    let tick = |i: usize| f.get(i).and_then(|v| v.parse::<f64>().ok()).unwrap_or(0.0);
    // Fields 14 and 15 (utime, stime) are the 12th and 13th after the command name.
    (tick(11) + tick(12)) / 100.0
}

/// A 16-bit PNG of smooth waves plus 5% noise (N×N), the service benches' input; `seed` varies
/// the noise (0: the maps earlier runs measured).
pub fn terrain_png16(n: usize, seed: u64) -> Vec<u8> {
    use std::f64::consts::TAU;
    let mut data = Vec::with_capacity(n * n);
    let mut state = 0x1234_5678_9abc_def0u64 ^ seed.wrapping_mul(0x9e37_79b9_7f4a_7c15);
    for y in 0..n {
        for x in 0..n {
            state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            let (u, v) = (x as f64 / n as f64, y as f64 / n as f64);
            let s =
                (u * TAU * 3.0).sin() * (v * TAU * 2.0).cos() + 0.5 * ((u + v) * TAU * 5.0).sin();
            let noise = ((state >> 40) as f64 / (1u64 << 24) as f64 - 0.5) * 0.1;
            data.push((((s / 1.5 + 1.0) * 0.45 + noise).clamp(0.0, 1.0) * 65535.0) as u16);
        }
    }
    horizon_bake::encode::png::encode16(n, n, horizon_bake::encode::png::PngColor::Gray, &data)
        .expect("encode input")
}

/// A `horizon-bake serve` child process, killed when dropped.
pub struct ServerChild(pub std::process::Child);

impl Drop for ServerChild {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Starts the real binary as a server on 127.0.0.1:0 with its data in `dir` and `args` added;
/// returns it and its base URL once it has written its address.
pub fn start_server(dir: &std::path::Path, args: &[&str]) -> (ServerChild, String) {
    use std::time::{Duration, Instant};
    std::fs::create_dir_all(dir).expect("server dir");
    let addr_file = dir.join("addr");
    let child = std::process::Command::new(env!("CARGO_BIN_EXE_horizon-bake"))
        .arg("serve")
        .args(["--addr", "127.0.0.1:0", "--max-body-bytes", "1073741824", "--data-dir"])
        .arg(dir.join("data"))
        .arg("--addr-file")
        .arg(&addr_file)
        .args(args)
        .env_remove("HORIZON_API_KEY")
        .env("RUST_LOG", "warn")
        .stdout(std::process::Stdio::null())
        .spawn()
        .expect("server");
    let child = ServerChild(child);
    let t = Instant::now();
    loop {
        // Non-empty: the file may be seen between its creation and its write.
        if let Ok(a) = std::fs::read_to_string(&addr_file) {
            if !a.is_empty() {
                return (child, format!("http://{a}"));
            }
        }
        assert!(t.elapsed() < Duration::from_secs(60), "server did not start");
        std::thread::sleep(Duration::from_millis(20));
    }
}
