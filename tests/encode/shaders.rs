//! The shader includes (issue 21, SPEC §8) through real compilers and the real binary:
//! - `horizon-bake shaders -o DIR` writes exactly the shipped files, all or nothing;
//! - glslangValidator (Debian `glslang-tools`) compiles, from that directory, the GLSL ES 3.00
//!   example (with horizon.glsl spliced in, as a WebGL application does), the GLSL 4.50 example
//!   (its `#include` resolved by glslang), the web viewer's fragment shader composed as
//!   viewer.js composes it, the HLSL example and the Unity and Unreal wrappers; a broken include
//!   is refused (the check can fail);
//! - naga validates horizon.wgsl with its example and finds every decode function in it;
//! - `GET /v1/shaders` lists the files and `GET /v1/shaders/{file}` serves each with a strong
//!   ETag (304 on revalidation), 404 problem+json for any other name, no API key needed.
//!
//! Godot's shading language has no offline compiler here: its files are held to the GLSL text
//! by the unit tests in src/shaders/mod.rs. Under `CI=true` a missing glslangValidator fails
//! these tests instead of skipping them.

use crate::support::{bin, idle_state};
use axum::body::Body;
use axum::http::{Request, StatusCode};
use horizon_bake::service;
use horizon_bake::shaders::{self, FILES, FUNCTIONS};
use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::Command;
use tower::ServiceExt;

/// `horizon-bake shaders -o DIR` into a fresh directory.
fn written() -> (tempfile::TempDir, PathBuf) {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("shaders");
    let out = bin().args(["shaders", "-o"]).arg(&dir).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert!(out.stderr.is_empty(), "{}", String::from_utf8_lossy(&out.stderr));
    (tmp, dir)
}

/// glslangValidator, or None (skip) when it is missing outside CI.
fn glslang() -> Option<&'static str> {
    let found = Command::new("glslangValidator").arg("--version").output().is_ok();
    if found {
        return Some("glslangValidator");
    }
    if std::env::var("CI").is_ok_and(|v| v == "true") {
        panic!(
            "glslangValidator is missing (apt-get install glslang-tools); CI must run this test"
        );
    }
    eprintln!("skipped: glslangValidator not found (apt-get install glslang-tools)");
    None
}

/// Runs glslangValidator with `args` on `file`; Ok or the compiler's output. With `-V` the
/// SPIR-V goes to a scratch file beside `file`.
fn compile(exe: &str, args: &[&str], file: &Path) -> Result<(), String> {
    let spv = file.with_extension("spv");
    let mut cmd = Command::new(exe);
    cmd.args(args);
    if args.contains(&"-V") {
        cmd.arg("-o").arg(&spv);
    }
    let out = cmd.arg(file).output().unwrap();
    let _ = std::fs::remove_file(&spv);
    if out.status.success() {
        Ok(())
    } else {
        Err(format!(
            "{}: {}{}",
            file.display(),
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        ))
    }
}

/// GLSL ES 3.00 (WebGL2): checked against the ES profile its `#version` names.
const ES_ARGS: &[&str] = &[];
/// GLSL 4.50 to Vulkan SPIR-V: glslang resolves `#include` only when it generates code.
const GL450_ARGS: &[&str] = &["-V"];
/// HLSL as a pixel shader with entry point `main`.
const HLSL_ARGS: &[&str] = &["-D", "-V", "-e", "main", "-S", "frag"];

fn text(dir: &Path, name: &str) -> String {
    std::fs::read_to_string(dir.join(name)).unwrap()
}

/// The GLSL ES example with `#include "horizon.glsl"` replaced by `include`, as a WebGL
/// application builds the source string.
fn es300_source(dir: &Path, include: &str) -> String {
    let example = text(dir, "horizon_es300_example.frag");
    let line = "#include \"horizon.glsl\"";
    assert_eq!(example.matches(line).count(), 1);
    example.replace(line, include)
}

/// The web viewer's fragment shader, composed as viewer.js does: its header, the include, its
/// body (the `${…}` numbers of the template literal put in as JavaScript would).
fn viewer_source(include: &str) -> String {
    let js = horizon_bake::service::ui::ASSETS
        .iter()
        .find(|(n, _, _)| *n == "viewer.js")
        .map(|(_, _, text)| *text)
        .unwrap();
    let literal = |name: &str| {
        let start = js.find(&format!("const {name} = `")).unwrap() + name.len() + 10;
        let len = js[start..].find("`;").unwrap();
        js[start..start + len].to_owned()
    };
    let constant = |name: &str| -> f64 {
        let start = js.find(&format!("export const {name} = ")).unwrap() + name.len() + 16;
        js[start..].split(';').next().unwrap().trim().parse().unwrap()
    };
    assert!(js.contains("${FRAGMENT_HEAD}\\n${include}\\n${FRAGMENT_BODY}"));
    let mut body = literal("FRAGMENT_BODY");
    for name in ["SPECULAR", "ALBEDO", "AMBIENT", "ENV_REFLECTION"] {
        body = body.replace(&format!("${{{name}.toFixed(6)}}"), &format!("{:.6}", constant(name)));
    }
    body = body.replace("${SHININESS}", "24");
    assert!(!body.contains("${"), "a template substitution this test does not know");
    format!("{}\n{include}\n{body}", literal("FRAGMENT_HEAD"))
}

#[test]
fn cli_writes_every_shader_file_all_or_nothing() {
    let (tmp, dir) = written();
    let mut names: Vec<String> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .collect();
    names.sort();
    let mut want: Vec<String> = FILES.iter().map(|f| f.name.to_owned()).collect();
    want.sort();
    assert_eq!(names, want);
    for f in FILES {
        assert_eq!(text(&dir, f.name), f.text, "{}", f.name);
    }
    // DIR is a file: exit 2, one line naming the problem, the file untouched.
    let file = tmp.path().join("a-file");
    std::fs::write(&file, b"keep").unwrap();
    let out = bin().args(["shaders", "-o"]).arg(&file).output().unwrap();
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(err.trim_end().lines().count(), 1, "{err}");
    assert!(err.contains("out"), "{err}");
    assert_eq!(std::fs::read(&file).unwrap(), b"keep");
    // No -o: a usage error, exit 2.
    let out = bin().arg("shaders").output().unwrap();
    assert_eq!(out.status.code(), Some(2));
}

#[test]
fn glsl_compiles_with_glslang() {
    let Some(exe) = glslang() else { return };
    let (_tmp, dir) = written();
    // GLSL 4.50: the example as written, its #include resolved by glslang from DIR.
    compile(exe, GL450_ARGS, &dir.join("horizon_450_example.frag")).unwrap();
    // GLSL ES 3.00: horizon.glsl spliced in.
    let es = dir.join("es300_spliced.frag");
    std::fs::write(&es, es300_source(&dir, &text(&dir, "horizon.glsl"))).unwrap();
    compile(exe, ES_ARGS, &es).unwrap();
    // The web viewer's own shader.
    let viewer = dir.join("viewer.frag");
    std::fs::write(&viewer, viewer_source(shaders::GLSL)).unwrap();
    compile(exe, ES_ARGS, &viewer).unwrap();
}

#[test]
fn glslang_refuses_a_broken_include() {
    // The check above can fail: an include missing one function does not compile.
    let Some(exe) = glslang() else { return };
    let (_tmp, dir) = written();
    let broken = shaders::GLSL.replace("float horizon_s(vec4 f,", "float horizon_s_gone(vec4 f,");
    let es = dir.join("broken.frag");
    std::fs::write(&es, es300_source(&dir, &broken)).unwrap();
    let err = compile(exe, ES_ARGS, &es).unwrap_err();
    assert!(err.contains("horizon_s"), "{err}");
}

#[test]
fn hlsl_compiles_with_glslang() {
    let Some(exe) = glslang() else { return };
    let (_tmp, dir) = written();
    compile(exe, HLSL_ARGS, &dir.join("horizon_example.hlsl")).unwrap();
    // The Unity wrappers, every function called from a pixel shader (both precisions).
    let unity = dir.join("unity_harness.hlsl");
    std::fs::write(
        &unity,
        r#"#include "horizon_unity.hlsl"
float4 main(float4 p : SV_Position) : SV_Target
{
    float3 l = normalize(float3(0.6, -0.2, 0.5));
    float4 f;
    HorizonFactors_float(l, f);
    half4 fh;
    HorizonFactors_half((half3)l, fh);
    float a;
    HorizonIllumination_float(l, f, p * 0.001, p * 0.002, 8.0, a);
    half b;
    HorizonIllumination_half((half3)l, fh, (half4)(p * 0.001), (half4)(p * 0.002), 8.0, b);
    float c;
    HorizonFourier_float(l, p * 0.001, 0.6, p * 0.003, 9.0, 1.0, 8.0, c);
    half d;
    HorizonFourier_half((half3)l, (half4)(p * 0.001), 0.6, (half4)(p * 0.003), 5.0, 0.0, 8.0, d);
    return float4(a, b, c, d);
}
"#,
    )
    .unwrap();
    compile(exe, HLSL_ARGS, &unity).unwrap();
    // The Unreal Custom expression: its code is the body of a function of the node's inputs,
    // with horizon.hlsl included (Unreal would include it as horizon.ush).
    let unreal = dir.join("unreal_harness.hlsl");
    std::fs::write(
        &unreal,
        format!(
            "#include \"horizon.hlsl\"\n\
             float custom_expression(float3 LightTS, float4 Layer0, float4 Layer1, float Hardness)\n\
             {{\n{}\n}}\n\
             float4 main(float4 p : SV_Position) : SV_Target\n\
             {{\n    return custom_expression(normalize(float3(0.3, 0.4, 0.5)), p * 0.001, p * 0.002, 8.0).xxxx;\n}}\n",
            text(&dir, "horizon_unreal_custom.hlsl")
        ),
    )
    .unwrap();
    compile(exe, HLSL_ARGS, &unreal).unwrap();
}

/// Parses and validates a WGSL module with naga; the module or naga's report.
fn naga_module(src: &str) -> Result<naga::Module, String> {
    let module = naga::front::wgsl::parse_str(src).map_err(|e| e.emit_to_string(src))?;
    naga::valid::Validator::new(
        naga::valid::ValidationFlags::all(),
        naga::valid::Capabilities::empty(),
    )
    .validate(&module)
    .map_err(|e| format!("{e:?}"))?;
    Ok(module)
}

#[test]
fn wgsl_validates_with_naga() {
    let (_tmp, dir) = written();
    let include = text(&dir, "horizon.wgsl");
    let module = naga_module(&include).unwrap();
    let mut names: Vec<&str> =
        module.functions.iter().filter_map(|(_, f)| f.name.as_deref()).collect();
    names.sort_unstable();
    let mut want: Vec<&str> = FUNCTIONS.iter().map(|(n, _)| *n).collect();
    want.sort_unstable();
    assert_eq!(names, want);
    for (_, f) in module.functions.iter() {
        let name = f.name.as_deref().unwrap();
        let arity = FUNCTIONS.iter().find(|(n, _)| *n == name).unwrap().1;
        assert_eq!(f.arguments.len(), arity, "{name}");
    }
    // The example: the include's text followed by the example's, as its comment says.
    let example = format!("{include}\n{}", text(&dir, "horizon_example.wgsl"));
    let module = naga_module(&example).unwrap();
    assert_eq!(module.entry_points.len(), 1);
    assert_eq!(module.entry_points[0].stage, naga::ShaderStage::Fragment);
    // And the example alone does not validate: it calls the include.
    assert!(naga_module(&text(&dir, "horizon_example.wgsl")).is_err());
}

async fn get(
    app: &axum::Router,
    uri: &str,
    etag: Option<&str>,
) -> (StatusCode, axum::http::HeaderMap, Vec<u8>) {
    let mut req = Request::get(uri);
    if let Some(e) = etag {
        req = req.header("if-none-match", e);
    }
    let res = app.clone().oneshot(req.body(Body::empty()).unwrap()).await.unwrap();
    let (parts, body) = res.into_parts();
    let bytes = axum::body::to_bytes(body, usize::MAX).await.unwrap();
    (parts.status, parts.headers, bytes.to_vec())
}

#[tokio::test]
async fn service_lists_and_serves_the_shaders_without_a_key() {
    // With an API key set: shader files are open, like /openapi.yaml.
    let (st, _dir) = idle_state(|c| c.api_key = Some("k".into()));
    let app = service::app(st);
    let (s, h, body) = get(&app, "/v1/shaders", None).await;
    assert_eq!(s, 200);
    assert!(h["content-type"].to_str().unwrap().starts_with("application/json"));
    let list: Value = serde_json::from_slice(&body).unwrap();
    let files = list["files"].as_array().unwrap();
    assert_eq!(files.len(), FILES.len());
    for (entry, f) in files.iter().zip(FILES) {
        assert_eq!(entry["name"], f.name);
        assert_eq!(entry["bytes"], f.text.len());
        let href = entry["href"].as_str().unwrap();
        assert_eq!(href, format!("/v1/shaders/{}", f.name));
        let (s, h, body) = get(&app, href, None).await;
        assert_eq!(s, 200, "{href}");
        assert!(h["content-type"].to_str().unwrap().starts_with("text/plain"));
        assert_eq!(body, f.text.as_bytes(), "{href}");
        let etag = h["etag"].to_str().unwrap().to_owned();
        assert_eq!(entry["etag"], etag);
        assert!(etag.starts_with('"') && !etag.starts_with("W/"), "strong: {etag}");
        assert_eq!(h["cache-control"], "no-cache");
        let (s, h2, body) = get(&app, href, Some(&etag)).await;
        assert_eq!(s, 304);
        assert!(body.is_empty());
        assert_eq!(h2["etag"], h["etag"]);
    }
    // Distinct files, distinct tags.
    let mut tags: Vec<&str> = files.iter().map(|e| e["etag"].as_str().unwrap()).collect();
    tags.sort_unstable();
    tags.dedup();
    assert_eq!(tags.len(), FILES.len());
    for bad in ["/v1/shaders/horizon.glsl.bak", "/v1/shaders/..%2FCargo.toml", "/v1/shaders/x"] {
        let (s, h, body) = get(&app, bad, None).await;
        assert_eq!(s, 404, "{bad}");
        assert_eq!(h["content-type"], "application/problem+json");
        let p: Value = serde_json::from_slice(&body).unwrap();
        assert_eq!(p["code"], "shader_not_found", "{bad}");
        assert!(p["detail"].as_str().unwrap().contains("horizon.glsl"));
    }
}
