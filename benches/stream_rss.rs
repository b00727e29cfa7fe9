//! Peak resident memory (VmHWM) of the streamed pieces of issue 23 on a large map: the streamed
//! decode of a SIZE² 16-bit PNG into tile blobs (tile 2048, halo 17, edge=wrap), the streamed
//! assembly of a SIZE² RGBA8 PNG layer and a float32 GeoTIFF band, and an upload of 512 MiB
//! spooled to the file blob store. Not a timed benchmark: it prints the peak of each phase
//! (the peak is reset between phases through /proc/self/clear_refs).
//!
//! `cargo bench --bench stream_rss -- [SIZE]` (default 16384; Linux only). Each phase runs in a
//! process of its own (this binary with `--phase NAME`), so one phase's freed memory, which the
//! allocator keeps, is not counted in the next one's peak.

use horizon_bake::encode::assemble;
use horizon_bake::encode::png::{PngColor, PngRowWriter};
use horizon_bake::heightmap::stream::{self, Window};
use horizon_bake::heightmap::Limits;
use horizon_bake::params::{Channel, NoData};
use std::io::Write;
use std::time::Instant;

#[path = "common/proc_status.rs"]
mod proc_status;
use proc_status::status;

/// Peak and current resident memory, MiB.
fn mem() -> (f64, f64) {
    (status("VmHWM:") as f64 / 1024.0, status("VmRSS:") as f64 / 1024.0)
}

fn reset_peak() {
    let _ = std::fs::write("/proc/self/clear_refs", "5");
}

fn report(phase: &str, t: Instant, extra: &str) {
    let (hwm, rss) = mem();
    println!(
        "{phase:<34} {:>8.1} s   peak {hwm:>8.1} MiB   now {rss:>8.1} MiB   {extra}",
        t.elapsed().as_secs_f64()
    );
}

fn height(x: usize, y: usize) -> u16 {
    let v = (x as f32 * 0.0031).sin() * (y as f32 * 0.0047).cos() * 20000.0
        + ((x * 31 + y * 17) % 97) as f32 * 40.0;
    (v + 32768.0).clamp(0.0, 65535.0) as u16
}

const PHASES: [&str; 4] = ["decode", "png", "geotiff", "upload"];

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let size: usize = args
        .iter()
        .skip(1)
        .find(|a| a.parse::<usize>().is_ok())
        .and_then(|a| a.parse().ok())
        .unwrap_or(16384);
    let phase = args.iter().position(|a| a == "--phase").and_then(|i| args.get(i + 1));
    let Some(phase) = phase else {
        println!(
            "map {size}² ({} Mtexel), tile 2048 + halo 17, edge=wrap",
            size * size / 1_000_000
        );
        let me = std::env::current_exe().unwrap();
        for p in PHASES {
            let st = std::process::Command::new(&me)
                .args([&size.to_string(), "--phase", p])
                .status()
                .unwrap();
            assert!(st.success(), "phase {p} failed");
        }
        return;
    };
    run(size, phase);
}

fn run(size: usize, phase: &str) {
    let dir = tempfile::tempdir().unwrap();
    if phase == "decode" {
        decode(size, &dir);
    }
    if phase == "png" {
        png_layer(size, &dir);
    }
    if phase == "geotiff" {
        geotiff_band(size, &dir);
    }
    if phase == "upload" {
        upload(&dir);
    }
}

fn decode(size: usize, dir: &tempfile::TempDir) {
    // The input, written row by row.
    let t = Instant::now();
    let path = dir.path().join("in.png");
    {
        let f = std::io::BufWriter::new(std::fs::File::create(&path).unwrap());
        let mut w = PngRowWriter::<_, u16>::new(f, size, size, PngColor::Gray).unwrap();
        let mut row = vec![0u16; size];
        for y in 0..size {
            for (x, v) in row.iter_mut().enumerate() {
                *v = height(x, y);
            }
            w.write_rows(&row).unwrap();
        }
        w.finish().unwrap().flush().unwrap();
    }
    let bytes = std::fs::metadata(&path).unwrap().len();
    report("write the input PNG", t, &format!("{:.1} MiB", bytes as f64 / (1 << 20) as f64));

    // Streamed decode into tile blobs.
    reset_peak();
    let t = Instant::now();
    let (tile, halo) = (2048usize, 17i64);
    let mut windows = Vec::new();
    for ty in (0..size).step_by(tile) {
        for tx in (0..size).step_by(tile) {
            let (tw, th) = (tile.min(size - tx), tile.min(size - ty));
            windows.push(Window {
                x0: tx as i64 - halo,
                y0: ty as i64 - halo,
                width: (tw as i64 + 2 * halo) as u32,
                height: (th as i64 + 2 * halo) as u32,
            });
        }
    }
    let limits = Limits {
        max_dim: 65536,
        max_texels: 65536 * 65536,
        max_bytes: u64::MAX,
        max_decode_bytes: u64::MAX,
    };
    let mut blobs = 0usize;
    let mut blob_bytes = 0u64;
    let mut hasher = blake3::Hasher::new();
    let stats = stream::decode_tiles(
        std::fs::File::open(&path).unwrap(),
        "bench",
        Channel::Luma,
        NoData::Auto,
        &limits,
        &windows,
        &mut |_, blob| {
            blobs += 1;
            blob_bytes += blob.len() as u64;
            hasher.update(&blob[..64.min(blob.len())]);
            Ok(())
        },
    )
    .unwrap();
    report(
        "streamed decode into tile blobs",
        t,
        &format!(
            "{blobs} blobs, {:.0} MiB, range {:.4}..{:.4}",
            blob_bytes as f64 / (1 << 20) as f64,
            stats.min,
            stats.max
        ),
    );
}

fn png_layer(size: usize, dir: &tempfile::TempDir) {
    // Streamed assembly of one RGBA8 PNG layer (a synthetic row source).
    let t = Instant::now();
    let out = std::io::BufWriter::new(std::fs::File::create(dir.path().join("h0.png")).unwrap());
    let mut src = |_: usize, y0: usize, out: &mut [u8]| {
        for (k, v) in out.iter_mut().enumerate() {
            let (x, y) = ((k / 4) % size, y0 + k / (4 * size));
            *v = (height(x, y) >> 8) as u8 ^ (k % 4) as u8;
        }
        Ok(())
    };
    assemble::write_png::<u8, _>(out, size, size, PngColor::Rgba, 0, &mut src)
        .unwrap()
        .flush()
        .unwrap();
    report("streamed PNG layer (RGBA8)", t, "");
}

fn geotiff_band(size: usize, dir: &tempfile::TempDir) {
    // Streamed GeoTIFF band.
    let t = Instant::now();
    let out = std::io::BufWriter::new(std::fs::File::create(dir.path().join("a.tif")).unwrap());
    let mut src = |_: usize, y0: usize, out: &mut [f32]| {
        for (k, v) in out.iter_mut().enumerate() {
            *v = height(k % size, y0 + k / size) as f32 * 0.01;
        }
        Ok(())
    };
    let names = ["svf".to_string()];
    assemble::write_geotiff(out, size, size, &names, None, f32::NAN, Some(dir.path()), &mut src)
        .unwrap()
        .flush()
        .unwrap();
    report("streamed GeoTIFF band (f32)", t, "");
}

fn upload(dir: &tempfile::TempDir) {
    // An upload of 512 MiB spooled to the file blob store, 64 KiB pieces.
    let t = Instant::now();
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build();
    let rt = rt.unwrap();
    let store = std::sync::Arc::new(
        horizon_bake::jobs::blob::FsBlobStore::open(&dir.path().join("blobs")).unwrap(),
    );
    let total: usize = 512 << 20;
    let stored = rt.block_on(async {
        use horizon_bake::jobs::blob::BlobStore;
        use horizon_bake::service::upload::{Spool, SpoolWriter};
        struct Plain(Box<dyn horizon_bake::jobs::blob::BlobWriter>);
        impl Write for Plain {
            fn write(&mut self, b: &[u8]) -> std::io::Result<usize> {
                self.0.write(b)
            }
            fn flush(&mut self) -> std::io::Result<()> {
                self.0.flush()
            }
        }
        impl SpoolWriter for Plain {
            fn commit(self: Box<Self>) -> horizon_bake::Result<String> {
                self.0.commit(&|_| Ok(()))
            }
        }
        let s = store.clone();
        let mut spool = Spool::new(
            total,
            horizon_bake::service::upload::STREAM_UPLOAD_ABOVE,
            Box::new(move || Ok(Box::new(Plain(s.writer()?)) as Box<dyn SpoolWriter>)),
        );
        let piece = vec![0x5au8; 64 << 10];
        for _ in 0..total / piece.len() {
            spool.push(bytes::Bytes::copy_from_slice(&piece)).await.unwrap();
        }
        spool.finish().await.unwrap()
    });
    report("upload of 512 MiB, spooled", t, &format!("{stored:?}"));
}
