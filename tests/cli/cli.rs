//! The real `horizon-bake` binary: golden inputs baked through `bake` match the golden layers,
//! `bake.json` reports what was done, `cubemap` writes the golden faces, and every bad flag or
//! input exits non-zero with one line on stderr that names the problem, leaving the output
//! directory as it was. Output is piped here, so there must be no progress bar either.

use crate::support::{self, bin, terrain_png16};
use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn run(args: &[&str]) -> Output {
    bin().args(args).output().expect("the binary runs")
}

fn cases() -> Value {
    serde_json::from_slice(&std::fs::read(support::golden_dir().join("cases.json")).unwrap())
        .unwrap()
}

fn case(name: &str) -> Value {
    cases()["horizon_cases"].as_array().unwrap().iter().find(|c| c["name"] == name).unwrap().clone()
}

/// The golden case's parameters as `--kebab-case` flags (the same keys tests/kernels/golden.rs sets).
fn flags_of(case: &Value) -> Vec<String> {
    let mut out = Vec::new();
    for key in ["height_scale", "radius", "edge", "y_axis", "channel", "method", "bins"] {
        let v = &case[key];
        out.push(format!("--{}", key.replace('_', "-")));
        out.push(v.as_str().map(str::to_owned).unwrap_or_else(|| v.to_string()));
    }
    out
}

fn rgba8(path: &Path) -> Vec<u8> {
    image::open(path).unwrap_or_else(|e| panic!("{}: {e}", path.display())).to_rgba8().into_raw()
}

fn assert_close_u8(name: &str, got: &[u8], want: &[u8], tol: &Value) {
    assert_eq!(got.len(), want.len(), "{name}: size");
    let lsb = tol["png_lsb"].as_i64().unwrap() as i32;
    let frac = tol["png_lsb_fraction"].as_f64().unwrap();
    let mut off = 0usize;
    for (k, (&g, &w)) in got.iter().zip(want).enumerate() {
        let d = (g as i32 - w as i32).abs();
        assert!(d <= lsb, "{name}: byte {k} is {g}, expected {w}");
        off += (d > 0) as usize;
    }
    assert!(off as f64 <= frac * got.len() as f64, "{name}: {off} bytes off by one");
}

fn read_exr(path: &Path) -> Vec<f32> {
    use exr::prelude::*;
    let img = read()
        .no_deep_data()
        .largest_resolution_level()
        .rgba_channels(
            |res, _| (res.width(), vec![0f32; res.width() * res.height() * 4]),
            |(w, buf): &mut (usize, Vec<f32>),
             p: Vec2<usize>,
             (r, g, b, a): (f32, f32, f32, f32)| {
                let k = (p.y() * *w + p.x()) * 4;
                buf[k..k + 4].copy_from_slice(&[r, g, b, a]);
            },
        )
        .first_valid_layer()
        .all_attributes()
        .from_file(path)
        .unwrap();
    img.layer_data.channel_data.pixels.1
}

fn listing(dir: &Path) -> Vec<(String, Vec<u8>)> {
    let mut v: Vec<(String, Vec<u8>)> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| {
            let e = e.unwrap();
            (
                e.file_name().to_string_lossy().into_owned(),
                std::fs::read(e.path()).unwrap_or_default(),
            )
        })
        .collect();
    v.sort();
    v
}

#[test]
fn bake_golden_case_writes_every_format_and_bake_json() {
    let all = cases();
    let tol = &all["tolerance"];
    let gold = support::golden_dir();
    let tmp = tempfile::tempdir().unwrap();
    for name in ["ridge_r8_wrap_ydown", "rgb_g_r6_wrap"] {
        let c = case(name);
        let out = tmp.path().join(name).join("nested");
        let input = gold.join("inputs").join(c["input"].as_str().unwrap());
        let mut args: Vec<String> = vec![
            "bake".into(),
            input.display().to_string(),
            "-o".into(),
            out.display().to_string(),
        ];
        args.extend(flags_of(&c));
        args.extend(["--format".into(), "png8,exr,ktx2,dds".into()]);
        let o = bin().args(&args).output().unwrap();
        assert!(o.status.success(), "{name}: {}", String::from_utf8_lossy(&o.stderr));
        assert!(o.stdout.is_empty() && o.stderr.is_empty(), "{name}: output when piped: {o:?}");

        let names: Vec<String> = listing(&out).into_iter().map(|(n, _)| n).collect();
        assert_eq!(
            names,
            [
                "bake.json",
                "horizon.dds",
                "horizon.ktx2",
                "horizon_0.exr",
                "horizon_0.png",
                "horizon_1.exr",
                "horizon_1.png"
            ],
            "{name}"
        );
        let want_f32 = support::read_f32(&gold.join(c["expected_f32"].as_str().unwrap()));
        let f32_abs = tol["f32_abs"].as_f64().unwrap() as f32;
        for (l, file) in c["expected_layers"].as_array().unwrap().iter().enumerate() {
            let got = rgba8(&out.join(format!("horizon_{l}.png")));
            let want = rgba8(&gold.join(file.as_str().unwrap()));
            assert_close_u8(&format!("{name} layer {l}"), &got, &want, tol);
            // The EXR layer holds channels 4l..4l+3 of the golden f32 values.
            let exr = read_exr(&out.join(format!("horizon_{l}.exr")));
            for (t, px) in exr.chunks_exact(4).enumerate() {
                for c4 in 0..4 {
                    let want = want_f32[t * 8 + l * 4 + c4];
                    assert!(
                        (px[c4] - want).abs() <= f32_abs,
                        "{name} exr {l} texel {t}: {} vs {want}",
                        px[c4]
                    );
                }
            }
            // The KTX2 array's layer l holds the same bytes as the PNG.
            let ktx = std::fs::read(out.join("horizon.ktx2")).unwrap();
            let r = ktx2::Reader::new(&ktx[..]).unwrap();
            assert_eq!(r.header().layer_count, 2);
            let data = r.levels().next().unwrap().data;
            let n = got.len();
            assert_eq!(&data[l * n..(l + 1) * n], &got[..], "{name} ktx2 layer {l}");
        }

        let report: Value =
            serde_json::from_slice(&std::fs::read(out.join("bake.json")).unwrap()).unwrap();
        let p = &report["params"];
        assert_eq!(p["height_scale"].as_f64(), c["height_scale"].as_f64(), "{name}");
        assert_eq!(p["radius"], c["radius"]);
        assert_eq!(p["resolved_radius"]["texels"], c["radius"]);
        assert_eq!(p["edge"], c["edge"]);
        assert_eq!(p["y_axis"], c["y_axis"]);
        assert_eq!(p["channel"], c["channel"]);
        assert_eq!(p["bins"], 32);
        assert_eq!(p["encoding"], "linear");
        let i = &report["input"];
        assert_eq!(i["width"], c["width"]);
        assert_eq!(i["height"], c["height"]);
        assert_eq!(i["format"], "png");
        let bytes = std::fs::read(&input).unwrap();
        assert_eq!(i["content_hash"].as_str().unwrap(), blake3::hash(&bytes).to_hex().as_str());
        let t = &report["timings_ms"];
        let (d, b, e, total) = (
            t["decode"].as_f64().unwrap(),
            t["bake"].as_f64().unwrap(),
            t["encode"].as_f64().unwrap(),
            t["total"].as_f64().unwrap(),
        );
        assert!(d >= 0.0 && b > 0.0 && e >= 0.0, "{t}");
        assert!(total >= d + b + e - 0.01, "total {total} < sum of stages: {t}");
        assert_eq!(report["output"]["formats"]["texture_precision"], "unorm8");
    }
}

#[test]
fn png16_and_radius_auto_are_reported() {
    let gold = support::golden_dir();
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("o");
    let input = gold.join("inputs/bump64.png");
    let o = run(&[
        "bake",
        input.to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
        "--radius",
        "auto",
        "--min-elevation-deg",
        "30",
        "--format",
        "png16",
        "--encoding",
        "sqrt",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let img = image::open(out.join("horizon_0.png")).unwrap();
    assert_eq!(img.color(), image::ColorType::Rgba16);
    let report: Value =
        serde_json::from_slice(&std::fs::read(out.join("bake.json")).unwrap()).unwrap();
    assert_eq!(report["params"]["radius"], "auto");
    assert_eq!(report["params"]["encoding"], "sqrt");
    let texels = report["params"]["resolved_radius"]["texels"].as_u64().unwrap();
    assert!((1..=64).contains(&texels), "{report}");
    assert!(report["params"]["resolved_radius"]["reason"].as_str().unwrap().starts_with("auto"));
}

/// Runs a failing command against a DIR that already holds a file, and checks: exit code, one
/// line on stderr containing `needle`, DIR unchanged, no temporary directory left beside it.
fn assert_fails_cleanly(args: &[&str], dir: &Path, needle: &str, code: i32) {
    let before = listing(dir);
    let parent_before = listing(dir.parent().unwrap()).len();
    let o = run(args);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(code), "{args:?}: {stderr}");
    assert_eq!(stderr.lines().count(), 1, "{args:?}: not one line: {stderr:?}");
    assert!(stderr.contains(needle), "{args:?}: {stderr:?} does not name `{needle}`");
    assert!(o.stdout.is_empty(), "{args:?}: stdout {:?}", String::from_utf8_lossy(&o.stdout));
    assert_eq!(listing(dir), before, "{args:?}: DIR changed");
    assert_eq!(
        listing(dir.parent().unwrap()).len(),
        parent_before,
        "{args:?}: left files beside DIR"
    );
}

#[test]
fn bad_flags_and_inputs_fail_with_one_line_and_leave_dir_alone() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("out");
    std::fs::create_dir(&dir).unwrap();
    std::fs::write(dir.join("horizon_0.png"), b"previous result").unwrap();
    std::fs::write(dir.join("keep.txt"), b"unrelated").unwrap();
    let good = support::golden_dir().join("inputs/bump64.png");
    let good = good.to_str().unwrap();
    let d = dir.to_str().unwrap();

    let jpeg = tmp.path().join("photo.png");
    std::fs::write(&jpeg, [0xFF, 0xD8, 0xFF, 0xE0, 0, 0x10, b'J', b'F', b'I', b'F', 0, 1]).unwrap();
    let truncated = tmp.path().join("half.png");
    let full = std::fs::read(good).unwrap();
    std::fs::write(&truncated, &full[..full.len() / 2]).unwrap();
    let empty = tmp.path().join("empty.png");
    std::fs::write(&empty, b"").unwrap();
    let missing = tmp.path().join("missing.png");

    let cases: Vec<(Vec<&str>, &str)> = vec![
        (vec!["bake", good, "-o", d, "--bogus", "1"], "--bogus"),
        (vec!["bake", good, "-o", d, "--height-scale", "-1"], "height_scale"),
        (vec!["bake", good, "-o", d, "--bins", "24"], "bins"),
        (vec!["bake", good, "-o", d, "--radius", "0"], "radius"),
        (vec!["bake", good, "-o", d, "--edge", "clamp"], "edge"),
        (vec!["bake", good, "-o", d, "--format", "png8,jpeg"], "format"),
        (vec!["bake", good, "-o", d, "--format", "png8,png16"], "format"),
        (vec!["bake", good, "-o", d, "--texture-precision", "unorm4"], "texture_precision"),
        (vec!["bake", good, "-o", d, "--outputs", "horizon,normals"], "outputs"),
        (vec!["bake", good, "-o", d, "--fourier-terms", "4"], "fourier_terms"),
        (vec!["bake", good, "-o", d, "--max-dim", "32"], "64×64"),
        (vec!["bake", jpeg.to_str().unwrap(), "-o", d], "JPG"),
        (vec!["bake", truncated.to_str().unwrap(), "-o", d], "truncated"),
        (vec!["bake", empty.to_str().unwrap(), "-o", d], "empty"),
        (vec!["bake", missing.to_str().unwrap(), "-o", d], "missing.png"),
        (vec!["bake", good], "--out"),
        (vec!["cubemap", "-o", d, "--size", "0"], "size"),
        (vec!["cubemap", "-o", d, "--size", "100000"], "size"),
        (vec!["cubemap", "-o", d, "--format", "png16"], "format"),
    ];
    for (args, needle) in &cases {
        assert_fails_cleanly(args, &dir, needle, 2);
    }
    // A file where DIR should be.
    let file_dir = tmp.path().join("afile");
    std::fs::write(&file_dir, b"x").unwrap();
    let o = run(&["bake", good, "-o", file_dir.to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(2));
    assert_eq!(String::from_utf8_lossy(&o.stderr).lines().count(), 1);
    assert_eq!(std::fs::read(&file_dir).unwrap(), b"x");
}

#[test]
fn a_successful_bake_replaces_only_its_own_files() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("out");
    std::fs::create_dir(&dir).unwrap();
    std::fs::write(dir.join("horizon_0.png"), b"previous result").unwrap();
    std::fs::write(dir.join("keep.txt"), b"unrelated").unwrap();
    let good = support::golden_dir().join("inputs/bump64.png");
    let o = run(&["bake", good.to_str().unwrap(), "-o", dir.to_str().unwrap(), "--radius", "4"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let names: Vec<String> = listing(&dir).into_iter().map(|(n, _)| n).collect();
    assert_eq!(names, ["bake.json", "horizon_0.png", "horizon_1.png", "keep.txt"]);
    assert_eq!(std::fs::read(dir.join("keep.txt")).unwrap(), b"unrelated");
    assert_eq!(image::open(dir.join("horizon_0.png")).unwrap().width(), 64);
    // Nothing left beside DIR.
    let beside: Vec<String> = listing(tmp.path()).into_iter().map(|(n, _)| n).collect();
    assert_eq!(beside, ["out"]);
}

#[test]
fn cubemap_writes_golden_faces_ktx2_and_dds() {
    let all = cases();
    let tol = &all["tolerance"];
    let gold = support::golden_dir();
    let cube = &all["cube_cases"][0];
    let size = cube["size"].as_u64().unwrap();
    let tmp = tempfile::tempdir().unwrap();
    let out: PathBuf = tmp.path().join("cube");
    let size_s = size.to_string();
    let o = run(&[
        "cubemap",
        "-o",
        out.to_str().unwrap(),
        "--size",
        &size_s,
        "--format",
        "png8,ktx2,dds",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(o.stdout.is_empty() && o.stderr.is_empty());
    for (face, file) in cube["expected_faces"].as_array().unwrap().iter().enumerate() {
        let got = rgba8(&out.join(format!("cube_{face}.png")));
        let want = rgba8(&gold.join(file.as_str().unwrap()));
        assert_close_u8(&format!("face {face}"), &got, &want, tol);
    }
    let want = support::read_f32(&gold.join(cube["expected_f32"].as_str().unwrap()));
    let ktx = std::fs::read(out.join("cubemap.ktx2")).unwrap();
    let r = ktx2::Reader::new(&ktx[..]).unwrap();
    assert_eq!((r.header().face_count, r.header().format), (6, Some(ktx2::Format::R8G8B8A8_SNORM)));
    let data = r.levels().next().unwrap().data;
    for (k, (&b, &f)) in data.iter().zip(&want).enumerate() {
        assert!((b as i8 as f32 / 127.0 - f).abs() <= 0.5 / 127.0 + f32::EPSILON, "ktx2 value {k}");
    }
    let dds = ddsfile::Dds::read(&std::fs::read(out.join("cubemap.dds")).unwrap()[..]).unwrap();
    assert_eq!(dds.get_num_array_layers(), 6);
    assert_eq!(&dds.data[..], data);
    // Default: PNG faces only, 16 texels.
    let out2 = tmp.path().join("default");
    assert!(run(&["cubemap", "-o", out2.to_str().unwrap()]).status.success());
    let names: Vec<String> = listing(&out2).into_iter().map(|(n, _)| n).collect();
    assert_eq!(
        names,
        ["cube_0.png", "cube_1.png", "cube_2.png", "cube_3.png", "cube_4.png", "cube_5.png"]
    );
    assert_eq!(image::open(out2.join("cube_0.png")).unwrap().width(), 16);
}

#[test]
fn fourier_outputs_are_written_alone_or_beside_the_layers() {
    use horizon_bake::{bake, heightmap, params::BakeParams, progress::Progress};
    let tmp = tempfile::tempdir().unwrap();
    let good = support::golden_dir().join("inputs/bump64.png");
    let only = tmp.path().join("only");
    let o = run(&[
        "bake",
        good.to_str().unwrap(),
        "-o",
        only.to_str().unwrap(),
        "--radius",
        "6",
        "--outputs",
        "fourier",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let names: Vec<String> = listing(&only).into_iter().map(|(n, _)| n).collect();
    // Asking only for Fourier encodes no horizon layers.
    assert_eq!(names, ["bake.json", "fourier_0.png", "fourier_1.png"]);
    let report: Value =
        serde_json::from_slice(&std::fs::read(only.join("bake.json")).unwrap()).unwrap();
    assert_eq!(report["params"]["resolved_radius"]["texels"], 6);

    // The files hold exactly what the library's Fourier bake produces.
    let params = BakeParams::from_pairs([("radius", "6"), ("outputs", "fourier")]).unwrap();
    let bytes = std::fs::read(&good).unwrap();
    let (map, _) = heightmap::decode(&bytes, params.channel, &Default::default()).unwrap();
    let (layers, _) = bake::bake_fourier(&map, &params, &Progress::new()).unwrap();
    let f0 = image::open(only.join("fourier_0.png")).unwrap();
    assert_eq!(f0.color(), image::ColorType::Rgba8);
    assert_eq!(f0.to_rgba8().into_raw(), layers.bands);
    let f1 = image::open(only.join("fourier_1.png")).unwrap();
    assert_eq!(f1.color(), image::ColorType::L8);
    assert_eq!(f1.to_luma8().into_raw(), layers.constant);

    let both = tmp.path().join("both");
    let o = run(&[
        "bake",
        good.to_str().unwrap(),
        "-o",
        both.to_str().unwrap(),
        "--radius",
        "6",
        "--outputs",
        "horizon,fourier",
        "--fourier-terms",
        "9",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let names: Vec<String> = listing(&both).into_iter().map(|(n, _)| n).collect();
    assert_eq!(
        names,
        [
            "bake.json",
            "fourier_0.png",
            "fourier_1.png",
            "fourier_2.png",
            "horizon_0.png",
            "horizon_1.png"
        ]
    );
}

/// `--outputs fourier --format ktx2` would write no KTX2 while bake.json claimed one: refused
/// with exit 2, naming `format`, and nothing written.
#[test]
fn fourier_only_with_a_horizon_format_is_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("out");
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(dir.join("keep.txt"), b"x").unwrap();
    let good = support::golden_dir().join("inputs/bump64.png");
    for format in ["ktx2", "dds", "exr", "png16", "png8,exr"] {
        let args = [
            "bake",
            good.to_str().unwrap(),
            "-o",
            dir.to_str().unwrap(),
            "--outputs",
            "fourier",
            "--format",
            format,
        ];
        assert_fails_cleanly(&args, &dir, "format", 2);
    }
}

/// `preview` honours the umask like `bake` does (0644 under umask 022, not a temp file's 0600),
/// exits 2 for a missing output directory and writes the PNG to stdout for `-o -`.
#[cfg(unix)]
#[test]
fn preview_output_mode_missing_dir_and_stdout() {
    use std::os::unix::fs::PermissionsExt;
    let tmp = tempfile::tempdir().unwrap();
    let good = support::golden_dir().join("inputs/bump64.png");
    let good = good.to_str().unwrap();
    let out = tmp.path().join("p.png");
    // A shell sets the umask so the test does not depend on the one it was started with.
    let o = Command::new("sh")
        .arg("-c")
        .arg(format!(
            "umask 022 && exec \"$0\" preview {good} -o {} --radius 4",
            out.to_str().unwrap()
        ))
        .arg(env!("CARGO_BIN_EXE_horizon-bake"))
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let mode = std::fs::metadata(&out).unwrap().permissions().mode() & 0o777;
    assert_eq!(mode, 0o644, "preview file mode {mode:o}");
    let bake_dir = tmp.path().join("b");
    let o = Command::new("sh")
        .arg("-c")
        .arg(format!(
            "umask 022 && exec \"$0\" bake {good} -o {} --radius 4",
            bake_dir.to_str().unwrap()
        ))
        .arg(env!("CARGO_BIN_EXE_horizon-bake"))
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let bake_mode =
        std::fs::metadata(bake_dir.join("horizon_0.png")).unwrap().permissions().mode() & 0o777;
    assert_eq!(bake_mode, mode, "bake and preview files differ in mode");

    let missing = tmp.path().join("missing/p.png");
    let o = run(&["preview", good, "-o", missing.to_str().unwrap(), "--radius", "4"]);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{stderr}");
    assert_eq!(stderr.lines().count(), 1, "{stderr}");
    assert!(stderr.contains("missing"), "{stderr}");

    let o = run(&["preview", good, "-o", "-", "--radius", "4"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_eq!(o.stdout, std::fs::read(&out).unwrap(), "`-o -` is not the same PNG");
    assert!(!std::path::Path::new("-").exists(), "`-o -` wrote a file named -");
}

/// `--reduce point` means nothing to Lengyel's splat (the service's 422 is in the service binary's
/// `submissions`): the CLI refuses it with exit code 2 and one line naming `reduce`. From
/// tests/edges.rs (issue 25).
#[test]
fn cli_refuses_point_reduction_with_lengyel() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("h.png");
    std::fs::write(&input, terrain_png16(16, 16, 3)).unwrap();
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_horizon-bake"))
        .args(["bake", input.to_str().unwrap(), "-o"])
        .arg(dir.path().join("out"))
        .args(["--reduce", "point"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("reduce") && err.trim().lines().count() == 1, "{err}");
    assert!(!dir.path().join("out").exists());
}

/// The cube map's flags are what it takes: `cubemap --help` offers no `--texture-layout`
/// (`bake --help` does), and `--mip-filter rebake`, which bakes horizon levels again from the
/// heights, is refused for the cube map instead of silently being `box`.
#[test]
fn cubemap_offers_and_takes_only_its_own_texture_options() {
    let help = |cmd: &str| String::from_utf8(run(&[cmd, "--help"]).stdout).unwrap();
    assert!(!help("cubemap").contains("--texture-layout"), "{}", help("cubemap"));
    assert!(help("cubemap").contains("--mip-filter"));
    assert!(help("bake").contains("--texture-layout"));
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("cube");
    std::fs::create_dir(&dir).unwrap();
    let d = dir.to_str().unwrap();
    let args = ["cubemap", "-o", d, "--format", "ktx2", "--mips", "full", "--mip-filter", "rebake"];
    assert_fails_cleanly(&args, &dir, "mip_filter", 2);
    let box_filter = ["cubemap", "-o", d, "--format", "ktx2", "--mips", "full", "--mip-filter"];
    let o = run(&[&box_filter[..], &["max"]].concat());
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
}

/// `--supercompression zstd` with both containers compresses the KTX2 (supercompressionScheme
/// 2) and leaves the DDS as DDS is (it has no supercompression), as over HTTP; with `dds` alone
/// it is refused naming the option.
#[test]
fn zstd_with_both_containers_applies_to_the_ktx2_only() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("out");
    let input = support::golden_dir().join("inputs/bump64.png");
    let (i, o) = (input.to_str().unwrap(), out.to_str().unwrap());
    let both = ["bake", i, "-o", o, "--format", "ktx2,dds", "--supercompression", "zstd"];
    let r = run(&both);
    assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
    let ktx2 = std::fs::read(out.join("horizon.ktx2")).unwrap();
    assert_eq!(u32::from_le_bytes(ktx2[44..48].try_into().unwrap()), 2, "KTX2 not zstd");
    let dds = std::fs::read(out.join("horizon.dds")).unwrap();
    assert_eq!(&dds[..4], b"DDS ");
    // Uncompressed R8G8B8A8 layers: 64² texels × 4 bytes × 2 layers after the DX10 header.
    assert_eq!(dds.len(), 4 + 124 + 20 + 64 * 64 * 4 * 2);
    let dir = tmp.path().join("dds");
    std::fs::create_dir(&dir).unwrap();
    let d = dir.to_str().unwrap();
    let alone = ["bake", i, "-o", d, "--format", "dds", "--supercompression", "zstd"];
    assert_fails_cleanly(&alone, &dir, "supercompression", 2);
}

/// The flags' help says what the parser takes and the reference documents every flag (issue 44
/// item 8: `--outputs` omitted angles and svf, `--earth-curvature` named only exact and march,
/// `--method` called lengyel the default for a DEM too, `profile --bins` said "multiple of 16").
#[test]
fn every_flag_s_help_agrees_with_the_parser_and_the_reference() {
    let help = |cmd: &str| {
        let out = run(&[cmd, "--help"]);
        assert!(out.status.success());
        String::from_utf8(out.stdout).unwrap()
    };
    // The help text of one flag: from its line to the next flag's.
    fn of<'a>(help: &'a str, flag: &str) -> &'a str {
        let at = help
            .find(&format!("\n      --{flag} "))
            .or_else(|| help.find(&format!(", --{flag} ")))
            .unwrap_or_else(|| panic!("--{flag} missing"));
        let rest = &help[at + 1..];
        let rest = &rest[rest.find('\n').unwrap_or(0)..];
        let end = rest.find("\n      --").or_else(|| rest.find("\n  -")).unwrap_or(rest.len());
        &rest[..end]
    }
    let bake = help("bake");
    let words = |flag: &str, want: &[&str]| {
        let text = of(&bake, flag);
        for w in want {
            assert!(text.contains(w), "--{flag}'s help lacks `{w}`: {text}");
        }
    };
    words("method", &["lengyel", "exact", "march", "sweep", "DEM"]);
    words("outputs", &["horizon", "fourier", "angles", "svf"]);
    words("earth-curvature", &["exact", "march", "sweep"]);
    words("radius", &["unlimited", "auto", "16", "DEM"]);
    words("bins", &["16", "256", "720"]);
    // Every value the parser names in its refusals is in the help of its flag.
    for (flag, key) in [("method", "method"), ("outputs", "outputs"), ("edge", "edge")] {
        let out = run(&["bake", "x.png", "-o", "o", &format!("--{flag}"), "bogus"]);
        let err = String::from_utf8_lossy(&out.stderr).to_string();
        assert_eq!(out.status.code(), Some(2), "{err}");
        assert!(err.contains(key), "{err}");
    }
    let shadow = help("shadow");
    assert!(of(&shadow, "method").contains("exact ray"), "{}", of(&shadow, "method"));
    assert!(of(&shadow, "radius").contains("unlimited` (default)"), "{}", of(&shadow, "radius"));
    let profile = help("profile");
    let bins = of(&profile, "bins");
    assert!(bins.contains("3600") && !bins.contains("multiple of 16"), "{bins}");
    // The reference's flag tables name every flag of bake, shadow and profile.
    let reference =
        std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/docs/reference.md")).unwrap();
    for text in [&bake, &shadow, &profile] {
        for line in text.lines().map(str::trim_start).filter(|l| l.starts_with("--")) {
            let flag = line.split([' ', ',']).next().unwrap();
            if flag == "--help" || flag == "--version" {
                continue;
            }
            assert!(reference.contains(&format!("`{flag}")), "docs/reference.md lacks `{flag}`");
        }
    }
}

/// `shadow` and `profile` always cast exact rays: another ray method asked is named as not
/// used on stderr, and the output is the exact one's, byte for byte (issue 41: a user asking
/// `--method sweep` was not told).
#[test]
fn shadow_and_profile_say_a_method_they_do_not_use() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("h.png");
    std::fs::write(&input, terrain_png16(40, 32, 9)).unwrap();
    let inp = input.to_str().unwrap();
    let shadow = |m: &str, name: &str| {
        let out = dir.path().join(name);
        let o = run(&[
            "shadow",
            inp,
            "-o",
            out.to_str().unwrap(),
            "--method",
            m,
            "--sun-azimuth",
            "30",
            "--sun-elevation",
            "8",
        ]);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        (String::from_utf8_lossy(&o.stderr).to_string(), std::fs::read(out).unwrap())
    };
    let (note, swept) = shadow("sweep", "s.tif");
    let (quiet, exact) = shadow("exact", "e.tif");
    assert!(note.contains("--method sweep is not used"), "{note}");
    assert!(!quiet.contains("not used"), "{quiet}");
    assert!(swept == exact, "the shadow is the exact ray's whatever --method says");
    let profile = |m: &str| {
        let o = run(&["profile", inp, "--at", "20,16", "--bins", "24", "--method", m]);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        (String::from_utf8_lossy(&o.stderr).to_string(), o.stdout)
    };
    let (note, marched) = profile("march");
    let (_, exact) = profile("exact");
    assert!(note.contains("--method march is not used"), "{note}");
    assert_eq!(marched, exact);
}

/// zstd with `dds` alone is refused naming `supercompression`; with `ktx2,dds` the KTX2 files
/// take it and the DDS files (which have none) are written as without it, and stderr says so
/// (issue 45: it exited 0 silently while the reference said exit 2).
#[test]
fn zstd_is_for_the_ktx2_files_and_says_so_beside_dds() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("h.png");
    std::fs::write(&input, terrain_png16(32, 32, 3)).unwrap();
    let inp = input.to_str().unwrap();
    let bake = |out: &str, format: &str, zstd: bool| {
        let out = dir.path().join(out);
        let mut args = vec!["bake", inp, "-o", out.to_str().unwrap(), "--format", format];
        if zstd {
            args.extend(["--supercompression", "zstd"]);
        }
        let o = run(&args);
        (o.status.code(), String::from_utf8_lossy(&o.stderr).to_string(), out)
    };
    let (code, err, _) = bake("a", "dds", true);
    assert_eq!(code, Some(2), "{err}");
    assert!(err.contains("supercompression"), "{err}");
    let (code, err, both) = bake("b", "ktx2,dds", true);
    assert_eq!(code, Some(0), "{err}");
    assert!(err.contains("applies to the KTX2 files; DDS has none"), "{err}");
    let (_, quiet, plain) = bake("c", "ktx2,dds", false);
    assert!(!quiet.contains("note"), "{quiet}");
    let file = |d: &PathBuf, n: &str| std::fs::read(d.join(n)).unwrap();
    assert_eq!(file(&both, "horizon.dds"), file(&plain, "horizon.dds"));
    // The KTX2 is supercompressed: supercompressionScheme (offset 44) is 2, zstd.
    assert_eq!(file(&both, "horizon.ktx2")[44..48], 2u32.to_le_bytes());
    assert_eq!(file(&plain, "horizon.ktx2")[44..48], 0u32.to_le_bytes());
}
