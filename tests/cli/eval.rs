//! The eval (SPEC §4) and `radius=auto` (SPEC §3.6): metrics on inputs whose answer is known,
//! the quick eval end to end through the binary, and the promise `auto` makes.

use horizon_bake::bake;
use horizon_bake::eval::{self, corpus, Factors, TRUTH_BINS};
use horizon_bake::kernels::{self, Grid};
use horizon_bake::params::{BakeParams, Edge, Method, Radius, YAxis};
use horizon_bake::progress::Progress;

/// Truth where every azimuth of texel t has horizon `v[t]`, and channels that decode to `c[t]`.
fn flat_case(v: &[f64], c: &[f64]) -> (Vec<f64>, Vec<f32>) {
    let truth: Vec<f32> =
        v.iter().flat_map(|&x| std::iter::repeat_n(x as f32, TRUTH_BINS)).collect();
    let ch: Vec<f64> = c.iter().flat_map(|&x| std::iter::repeat_n(x, 8)).collect();
    (ch, truth)
}

#[test]
fn metrics_of_known_answers() {
    // Perfect channels: no error at all, with exact factors and with any cube map (the factors
    // of a UNORM8 cube sum to ~1, and 8 equal channels make their split irrelevant up to the
    // quantisation of 0 as 128/255·2 − 1 = 1/255 per slot).
    let v: Vec<f64> = (0..50).map(|k| (k as f64 / 49.0) * 0.9).collect();
    let (ch, truth) = flat_case(&v, &v.iter().map(|&x| x as f32 as f64).collect::<Vec<_>>());
    let m = eval::metrics(&ch, &truth, Factors::Exact);
    assert_eq!(m.shadow_error, 0.0);
    assert!(m.horizon_error_deg < 1e-4, "{}", m.horizon_error_deg);

    // Truth 0 everywhere, model s = sin 15° on half the texels: those are wrongly shadowed for
    // the 5° and 10° lights and nowhere else, so the error is ½ at two of six elevations, and
    // the horizon error is 15° on half the texels.
    let v = vec![0.0; 40];
    let c: Vec<f64> =
        (0..40).map(|k| if k % 2 == 0 { 15f64.to_radians().sin() } else { 0.0 }).collect();
    let (ch, truth) = flat_case(&v, &c);
    let m = eval::metrics(&ch, &truth, Factors::Exact);
    assert_eq!(m.shadow_by_elevation, [0.5, 0.5, 0.0, 0.0, 0.0, 0.0]);
    assert!((m.shadow_error - 1.0 / 6.0).abs() < 1e-12);
    assert!((m.horizon_error_deg - 7.5).abs() < 1e-9, "{}", m.horizon_error_deg);
}

#[test]
fn metrics_see_the_channel_interpolation() {
    // A single occluder direction: truth is sin 40° for azimuths within ±10° of 0° and 0
    // elsewhere. A model holding sin 40° in channel 0 only decodes (1 − t)·sin 40° between 0°
    // and 45° (and t·sin 40° between 315° and 360°): at 15° and 345° it decodes 0.43, wrongly
    // shadowing the 5°, 10° and 20° lights; at 30° and 330° it decodes 0.21, wrongly shadowing
    // the 5° and 10° lights. So 4, 4, 2, 0, 0, 0 of 24 azimuths.
    let n = 10;
    let s40 = 40f64.to_radians().sin();
    let mut truth = vec![0.0f32; n * TRUTH_BINS];
    for t in 0..n {
        for b in 0..TRUTH_BINS {
            let deg = b as f64 * 360.0 / TRUTH_BINS as f64;
            if !(10.0..=350.0).contains(&deg) {
                truth[t * TRUTH_BINS + b] = s40 as f32;
            }
        }
    }
    let mut ch = vec![0.0f64; n * 8];
    for t in 0..n {
        ch[t * 8] = s40;
    }
    let m = eval::metrics(&ch, &truth, Factors::Exact);
    let wrong_az = |el: f64| {
        let lz = el.to_radians().sin();
        (0..24)
            .filter(|&a| {
                let deg = a as f64 * 15.0;
                let t = ((deg % 45.0) / 45.0, (deg / 45.0).floor() as i32);
                let model = match t.1 {
                    0 => (1.0 - t.0) * s40,
                    7 => t.0 * s40,
                    _ => 0.0,
                };
                let truth = if !(10.0..=350.0).contains(&deg) { s40 } else { 0.0 };
                (lz > model) != (lz > truth)
            })
            .count() as f64
            / 24.0
    };
    for (e, el) in eval::ELEVATIONS_DEG.iter().enumerate() {
        assert!(
            (m.shadow_by_elevation[e] - wrong_az(*el)).abs() < 1e-12,
            "{el}°: {} vs {}",
            m.shadow_by_elevation[e],
            wrong_az(*el)
        );
    }
    let want = [4.0, 4.0, 2.0, 0.0, 0.0, 0.0].map(|k| k / 24.0);
    for (got, want) in m.shadow_by_elevation.iter().zip(want) {
        assert!((got - want).abs() < 1e-12, "{:?}", m.shadow_by_elevation);
    }
    assert!(m.horizon_error_deg > 1.0);
}

#[test]
fn quick_eval_ranks_models_sensibly() {
    let res = eval::run(&eval::Options { quick: true, size: 32, ..Default::default() }).unwrap();
    let specs = eval::models(true);
    assert_eq!(res.rows.len(), specs.len() * 2, "every model on both quick maps");
    for r in &res.rows {
        let m = &r.metrics;
        assert!(r.ms > 0.0 && r.mtexel_per_s.is_finite(), "{}: {} ms", r.model, r.ms);
        assert!((0.0..=1.0).contains(&m.shadow_error), "{}", r.model);
        assert!(m.horizon_error_deg.is_finite() && m.horizon_error_deg >= 0.0, "{}", r.model);
        let mean = m.shadow_by_elevation.iter().sum::<f64>() / 6.0;
        assert!((mean - m.shadow_error).abs() < 1e-12);
    }
    let get = |model: &str, map: &str| {
        res.rows.iter().find(|r| r.model == model && r.map == map).unwrap().metrics
    };
    // On the bump (peak 6.4 texels, radius 32/3) a radius of 4 misses most of the long, low
    // shadows that a radius of 16 catches.
    let r4 = get("lengyel R4 B32", "bump");
    let r16 = get("lengyel R16 B32", "bump");
    assert!(r4.shadow_by_elevation[0] > r16.shadow_by_elevation[0] + 0.02, "{r4:?} {r16:?}");
    // 16-bit storage of the same bake is never less accurate than 8-bit, on the horizon.
    for map in ["bump", "fractal"] {
        let u8 = get("lengyel R16 B32", map).horizon_error_deg;
        let u16 = get("lengyel R16 B32 u16", map).horizon_error_deg;
        assert!(u16 <= u8 + 1e-3, "{map}: u16 {u16} vs u8 {u8}");
    }
    // The sweep at unlimited radius is within its tolerance of exact at unlimited radius: the
    // same horizon error against the ground truth to a few hundredths of a degree.
    for map in ["bump", "fractal"] {
        let sweep = get("sweep Runlimited average", map).horizon_error_deg;
        let exact = get("exact Runlimited average", map).horizon_error_deg;
        assert!((sweep - exact).abs() <= 0.05, "{map}: sweep {sweep}° vs exact {exact}°");
    }
    // Auto resolved a finite radius from the height range (bump: 6.4 / tan 10° → 37 → capped
    // at 32), and reports it.
    let auto = res.rows.iter().find(|r| r.family == "auto" && r.map == "bump").unwrap();
    let dh = corpus::bump(32).heights.iter().copied().fold(0.0f32, f32::max) as f64;
    let want = ((dh / 10f64.to_radians().tan()).ceil() as u32).min(32);
    assert_eq!(auto.resolved_radius, want);
    assert_eq!(auto.min_elevation_deg, Some(10.0));
}

fn per_bin(p: &BakeParams, m: &corpus::Map) -> Vec<f32> {
    let r = bake::resolve_radius(p, m.width, m.height, &m.heights);
    let g = Grid::new(m.width, m.height, &m.heights, p.edge, YAxis::Up);
    let k = bake::make_kernel(p, g, r.texels, &Progress::new());
    let nb = k.bins();
    let mut out = vec![0.0f32; m.width * m.height * nb];
    let band = kernels::band_rows(m.width, m.height);
    let chunks: Vec<std::sync::Mutex<&mut [f32]>> =
        out.chunks_mut(band * m.width * nb).map(std::sync::Mutex::new).collect();
    kernels::run_bands(k.as_ref(), band, true, &Progress::new(), |b, band| {
        chunks[b].lock().unwrap().copy_from_slice(band.bins.unwrap());
    })
    .unwrap();
    drop(chunks);
    out
}

#[test]
fn auto_radius_loses_nothing_at_or_above_min_elevation() {
    // SPEC §3.6: an occluder further than Δh / tan θ is below θ. So wherever the unlimited
    // horizon is at or above θ it is the same with radius=auto, and wherever it is below θ the
    // auto one is too: the shadow test of any light at elevation ≥ θ agrees bin by bin.
    for map in [corpus::bump(40), corpus::fractal(40, 1), corpus::spikes(40, 2)] {
        for method in [Method::Lengyel, Method::Exact] {
            for theta in [20.0f64, 40.0] {
                let unl = BakeParams {
                    method,
                    radius: Radius::Unlimited,
                    edge: Edge::Wrap,
                    ..Default::default()
                };
                let auto =
                    BakeParams { radius: Radius::Auto, min_elevation_deg: theta, ..unl.clone() };
                let r = bake::resolve_radius(&auto, map.width, map.height, &map.heights);
                assert!(
                    r.texels < 40,
                    "{}: auto should cut the radius, got {}",
                    map.name,
                    r.texels
                );
                let a = per_bin(&auto, &map);
                let u = per_bin(&unl, &map);
                let st = theta.to_radians().sin() as f32;
                for (k, (x, y)) in a.iter().zip(&u).enumerate() {
                    if *y > st + 1e-5 {
                        assert!(
                            (x - y).abs() < 1e-5,
                            "{} {method:?} θ {theta}: bin {k}: {x} vs {y}",
                            map.name
                        );
                    } else {
                        assert!(
                            *x <= st + 1e-5,
                            "{} {method:?} θ {theta}: bin {k}: {x} > sin θ",
                            map.name
                        );
                    }
                }
            }
        }
    }
}

#[test]
fn resolve_radius_follows_spec_3_6() {
    let p =
        |t: f64| BakeParams { radius: Radius::Auto, min_elevation_deg: t, ..Default::default() };
    // Δh = 10 texels: R = ceil(10 / tan θ).
    let mut h = vec![0.0f32; 50 * 40];
    h[7] = 10.0;
    assert_eq!(bake::resolve_radius(&p(45.0), 50, 40, &h).texels, 10);
    assert_eq!(bake::resolve_radius(&p(30.0), 50, 40, &h).texels, 18); // 17.32 → 18
                                                                       // Capped at max(W, H).
    assert_eq!(bake::resolve_radius(&p(5.0), 50, 40, &h).texels, 50);
    assert_eq!(bake::resolve_radius(&p(1e-9), 50, 40, &h).texels, 50);
    // A flat map needs no search at all; the smallest radius a kernel accepts is 1.
    let flat = vec![3.0f32; 50 * 40];
    assert_eq!(bake::resolve_radius(&p(5.0), 50, 40, &flat).texels, 1);
    // The reason names the inputs.
    let r = bake::resolve_radius(&p(30.0), 50, 40, &h);
    assert!(r.reason.contains("auto") && r.reason.contains("30"), "{}", r.reason);
}

#[test]
fn cli_eval_writes_every_output_and_the_dump() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("docs");
    let dump = dir.path().join("dump");
    std::fs::create_dir_all(&out).unwrap();
    std::fs::write(out.join("accuracy.md"), "# Title\n\nProse kept.\n").unwrap();
    let st = std::process::Command::new(env!("CARGO_BIN_EXE_horizon-bake"))
        .args(["eval", "--quick", "--quiet", "--size", "24", "--repeat-budget-ms", "0"])
        .arg("--out")
        .arg(&out)
        .arg("--dump")
        .arg(&dump)
        .output()
        .unwrap();
    assert!(st.status.success(), "{}", String::from_utf8_lossy(&st.stderr));
    let md = std::fs::read_to_string(out.join("accuracy.md")).unwrap();
    assert!(md.starts_with("# Title\n\nProse kept.\n"));
    assert!(md.contains("| lengyel R16 B32 ") && md.contains(eval::report::END));
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("accuracy.json")).unwrap()).unwrap();
    let rows = json["rows"].as_array().unwrap();
    let csv = std::fs::read_to_string(out.join("accuracy.csv")).unwrap();
    assert_eq!(csv.lines().count(), rows.len() + 1);
    let png = image::open(out.join("accuracy.png")).unwrap();
    assert_eq!((png.width(), png.height()), (1200, 520));
    // The dump holds the default model's layers and the numbers the eval reported for them.
    for map in ["bump", "fractal"] {
        let meta: serde_json::Value =
            serde_json::from_slice(&std::fs::read(dump.join(map).join("meta.json")).unwrap())
                .unwrap();
        let row = rows.iter().find(|r| r["model"] == "lengyel R16 B32" && r["map"] == map).unwrap();
        assert_eq!(meta["metrics"]["shadow_error"], row["shadow_error"]);
        let truth = std::fs::metadata(dump.join(map).join("truth.f32")).unwrap().len();
        assert_eq!(truth, (24 * 24 * TRUTH_BINS * 4) as u64);
        let l0 = image::open(dump.join(map).join("horizon_0.png")).unwrap().to_rgba8();
        assert_eq!(l0.dimensions(), (24, 24));
    }
}

#[test]
fn outputs_fourier_alone_bakes_no_horizon_layers() {
    // `outputs=fourier` must not quantise or encode horizon layers: only the Fourier files and
    // bake.json are written, and bake.json lists exactly those.
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("in.png");
    let px: Vec<u8> = (0..16 * 12).map(|k| ((k * 37) % 251) as u8).collect();
    std::fs::write(
        &input,
        horizon_bake::encode::png::encode8(16, 12, horizon_bake::encode::png::PngColor::Gray, &px)
            .unwrap(),
    )
    .unwrap();
    // (`--format png16,exr` with `--outputs fourier` alone is refused: see tests/cli/cli.rs.)
    let run = |outputs: &str, format: &str, out: &std::path::Path| {
        let st = std::process::Command::new(env!("CARGO_BIN_EXE_horizon-bake"))
            .arg("bake")
            .arg(&input)
            .arg("-o")
            .arg(out)
            .args(["--outputs", outputs, "--format", format])
            .output()
            .unwrap();
        assert!(st.status.success(), "{}", String::from_utf8_lossy(&st.stderr));
        let mut names: Vec<String> = std::fs::read_dir(out)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        names.sort();
        names
    };
    let only = run("fourier", "png8", &dir.path().join("f"));
    assert_eq!(only, ["bake.json", "fourier_0.png", "fourier_1.png"]);
    let both = run("horizon,fourier", "png16,exr", &dir.path().join("hf"));
    assert!(both.iter().any(|n| n == "horizon_0.png") && both.iter().any(|n| n == "horizon_0.exr"));
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("f/bake.json")).unwrap()).unwrap();
    let listed = json.to_string();
    assert!(!listed.contains("horizon_0"), "bake.json lists horizon files: {listed}");
}

/// `eval` writes nothing unless `--out` names a directory (it used to replace ./docs), and `-q`
/// prints nothing at all.
#[test]
fn cli_eval_writes_only_when_told_and_quiet_is_silent() {
    let dir = tempfile::tempdir().unwrap();
    let quick = ["eval", "--quick", "--size", "16", "--repeat-budget-ms", "0"];
    let st = std::process::Command::new(env!("CARGO_BIN_EXE_horizon-bake"))
        .args(quick)
        .current_dir(dir.path())
        .output()
        .unwrap();
    assert!(st.status.success(), "{}", String::from_utf8_lossy(&st.stderr));
    assert!(String::from_utf8_lossy(&st.stdout).contains("| lengyel R16 B32 "));
    let left: Vec<_> = std::fs::read_dir(dir.path()).unwrap().collect();
    assert!(left.is_empty(), "eval without --out wrote {left:?}");
    let st = std::process::Command::new(env!("CARGO_BIN_EXE_horizon-bake"))
        .args(quick)
        .arg("-q")
        .arg("--out")
        .arg(dir.path().join("docs"))
        .output()
        .unwrap();
    assert!(st.status.success(), "{}", String::from_utf8_lossy(&st.stderr));
    assert!(st.stdout.is_empty(), "-q printed {}", String::from_utf8_lossy(&st.stdout));
    assert!(st.stderr.is_empty(), "-q printed {}", String::from_utf8_lossy(&st.stderr));
    assert!(dir.path().join("docs/accuracy.md").exists());
}
