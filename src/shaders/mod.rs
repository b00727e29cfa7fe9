//! The shader includes (SPEC §8): the decode of the baked maps written once per shading
//! language, shipped in the binary, written by `horizon-bake shaders -o DIR` and served at
//! `/v1/shaders/{file}`. The web page's WebGL2 viewer compiles [`GLSL`] itself, so the browser
//! test (tests/browser) proves that include pixel by pixel against the CPU preview.
//!
//! # What they decode
//! - the channel factors: from a UNORM cube-map texel (`f = t·2 − 1`), from a SNORM one as
//!   sampled, or computed from the light (`horizon_factors_analytic`, the cube map's definition
//!   in SPEC §3.3, for engines where a cube-map texture is a chore);
//! - s = Σ max(f,0)·h0 + max(−f,0)·h1 (Lengyel eq. 5.3), the `bc5` four-layer RG form (SPEC §8),
//!   `encoding=sqrt` (s = v²);
//! - F = clamp(k·(L_z − s) + 1, 0, 1), 0 for L_z ≤ 0 (SPEC §3.3);
//! - the Fourier form of SPEC §3.4 (3, 5, 7 or 9 terms, both `fourier_range`s).
//!
//! # One source
//! The functions take sampled values, not textures, so the same code serves every texture
//! layout (array or separate layers, KTX2, DDS or PNG) and every binding model (Unity's Custom
//! Function node and Unreal's Custom expression pass values). They are hand-written per
//! language, because the four syntaxes differ in more than type names (WGSL's `select`, `let`
//! and braces; HLSL's `fmod`, `atan2`), and held equal by the tests below, not generated:
//! - `horizon.glsl` is valid GLSL ES 3.00 *and* GLSL 4.50 (the common subset: no `#version`, no
//!   precision statements, explicit float literals), so both dialects share one file; each has
//!   its example (`horizon_es300_example.frag`, `horizon_450_example.frag`);
//! - `horizon.gdshaderinc` is byte-for-byte the GLSL decode after its own header (Godot's
//!   shading language accepts that subset), checked by a test;
//! - `horizon.hlsl` is the GLSL decode statement for statement: with HLSL's spellings mapped
//!   back (`float4` → `vec4`, `atan2` → `atan`, `fmod` → `mod` on a positive operand, a scalar
//!   for a splatted vector) and comments and whitespace removed, the two texts are equal;
//! - `horizon.wgsl` declares the same functions with the same parameter counts (read by naga in
//!   tests/shaders.rs) and the same constants with the same values; its bodies follow the GLSL
//!   ones line by line in WGSL's syntax (`select`, `let`, braces), which no test compares;
//! - tests/shaders.rs compiles every file with real compilers (glslangValidator for GLSL and
//!   HLSL, naga for WGSL). Godot's language has no offline compiler here, so the Godot files are
//!   held to the GLSL text instead.
//!
//! The numbers are proven in GLSL: the viewer renders through [`GLSL`] and the browser test
//! compares it with the CPU preview (src/kernels/shade.rs), which also proves Godot's copy and,
//! through the statement-for-statement test, HLSL's. `horizon_factors_analytic`, which the
//! viewer does not use, is checked by a port of its expressions against the cube map's
//! definition (`cubemap::factors_for_azimuth`) below.

use crate::encode::OutFile;

/// What a shader file is for.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Kind {
    /// The decode functions, to include in your own shader.
    Include,
    /// A minimal fragment shader that calls an include.
    Example,
    /// Glue for one engine's node editor (Unity Custom Function, Unreal Custom expression).
    Wrapper,
}

/// One shipped shader file.
#[derive(Debug, Clone, Copy, serde::Serialize)]
pub struct ShaderFile {
    /// File name, as written by `horizon-bake shaders` and served at `/v1/shaders/{name}`.
    pub name: &'static str,
    /// Shading language: `glsl`, `hlsl`, `wgsl` or `godot`.
    pub language: &'static str,
    pub kind: Kind,
    /// Who uses it, in a few words.
    pub description: &'static str,
    /// The file's text.
    #[serde(skip)]
    pub text: &'static str,
}

/// The GLSL include (GLSL ES 3.00 and GLSL 4.50), which the web viewer compiles.
pub const GLSL: &str = include_str!("horizon.glsl");
/// The HLSL (SM 5) include.
pub const HLSL: &str = include_str!("horizon.hlsl");
/// The WGSL include.
pub const WGSL: &str = include_str!("horizon.wgsl");
/// The Godot 4 shader include.
pub const GODOT: &str = include_str!("horizon.gdshaderinc");

/// Every shipped file, includes first.
pub const FILES: &[ShaderFile] = &[
    ShaderFile {
        name: "horizon.glsl",
        language: "glsl",
        kind: Kind::Include,
        description: "GLSL ES 3.00 (WebGL2) and GLSL 4.50 include: OpenGL, Vulkan, custom engines",
        text: GLSL,
    },
    ShaderFile {
        name: "horizon.hlsl",
        language: "hlsl",
        kind: Kind::Include,
        description: "HLSL Shader Model 5 include: Direct3D 11/12, Unity, Unreal",
        text: HLSL,
    },
    ShaderFile {
        name: "horizon.wgsl",
        language: "wgsl",
        kind: Kind::Include,
        description: "WGSL include: WebGPU, wgpu",
        text: WGSL,
    },
    ShaderFile {
        name: "horizon.gdshaderinc",
        language: "godot",
        kind: Kind::Include,
        description: "Godot 4 shader include",
        text: GODOT,
    },
    ShaderFile {
        name: "horizon_es300_example.frag",
        language: "glsl",
        kind: Kind::Example,
        description: "GLSL ES 3.00 (WebGL2) fragment shader: PNG layers, UNORM cube faces",
        text: include_str!("horizon_es300_example.frag"),
    },
    ShaderFile {
        name: "horizon_450_example.frag",
        language: "glsl",
        kind: Kind::Example,
        description: "GLSL 4.50 fragment shader: KTX2 array layers, SNORM cube map",
        text: include_str!("horizon_450_example.frag"),
    },
    ShaderFile {
        name: "horizon_example.hlsl",
        language: "hlsl",
        kind: Kind::Example,
        description: "HLSL SM 5 pixel shader: DDS array layers, SNORM cube map",
        text: include_str!("horizon_example.hlsl"),
    },
    ShaderFile {
        name: "horizon_unity.hlsl",
        language: "hlsl",
        kind: Kind::Wrapper,
        description: "Unity Shader Graph Custom Function node (File mode) over horizon.hlsl",
        text: include_str!("horizon_unity.hlsl"),
    },
    ShaderFile {
        name: "horizon_unreal_custom.hlsl",
        language: "hlsl",
        kind: Kind::Wrapper,
        description: "Unreal material Custom expression code over horizon.hlsl (as horizon.ush)",
        text: include_str!("horizon_unreal_custom.hlsl"),
    },
    ShaderFile {
        name: "horizon_example.wgsl",
        language: "wgsl",
        kind: Kind::Example,
        description: "WGSL fragment shader (append to horizon.wgsl): KTX2 layers, SNORM cube map",
        text: include_str!("horizon_example.wgsl"),
    },
    ShaderFile {
        name: "horizon_example.gdshader",
        language: "godot",
        kind: Kind::Example,
        description: "Godot 4 spatial shader: PNG layers, factors computed from the light",
        text: include_str!("horizon_example.gdshader"),
    },
];

/// The shipped file called `name`.
pub fn find(name: &str) -> Option<&'static ShaderFile> {
    FILES.iter().find(|f| f.name == name)
}

/// Every file, as `horizon-bake shaders` writes them.
pub fn out_files() -> Vec<OutFile> {
    FILES.iter().map(|f| OutFile { name: f.name, bytes: f.text.as_bytes().to_vec() }).collect()
}

/// The decode functions every include declares, with their parameter counts.
pub const FUNCTIONS: &[(&str, usize)] = &[
    ("horizon_cube_factors", 1),
    ("horizon_factors_analytic", 1),
    ("horizon_decode_sqrt", 1),
    ("horizon_s", 3),
    ("horizon_s_bc5", 5),
    ("horizon_illumination", 3),
    ("horizon_illumination_layers", 5),
    ("horizon_light_dir", 1),
    ("horizon_fourier_bands", 2),
    ("horizon_fourier_const", 2),
    ("horizon_fourier", 6),
];

/// The constants every include declares, with their values.
pub const CONSTANTS: &[(&str, f64)] = &[
    ("HORIZON_DEFAULT_HARDNESS", crate::kernels::shade::DEFAULT_HARDNESS),
    ("HORIZON_QUARTER_PI", std::f64::consts::FRAC_PI_4),
    ("HORIZON_TWO_OVER_PI", std::f64::consts::FRAC_2_PI),
];

#[cfg(test)]
mod tests {
    use super::*;

    /// `(name, parameter count)` of every top-level function defined in `src` (a function is a
    /// line that starts at column 0, is not a comment and has `name(` before `)`; GLSL, HLSL and
    /// Godot write `type name(...)`, WGSL `fn name(...) -> type`).
    fn functions(src: &str) -> Vec<(String, usize)> {
        let mut out = Vec::new();
        for line in src.lines() {
            let first = line.chars().next().unwrap_or(' ');
            if !(first.is_ascii_alphabetic())
                || line.starts_with("const")
                || line.starts_with("static")
            {
                continue;
            }
            let Some(open) = line.find('(') else { continue };
            let Some(close) = line.rfind(')') else { continue };
            let Some(name) = line[..open].split_whitespace().last() else { continue };
            if !name.starts_with("horizon_") {
                continue;
            }
            let args = line[open + 1..close].trim();
            let n = if args.is_empty() { 0 } else { args.split(',').count() };
            out.push((name.to_owned(), n));
        }
        out
    }

    /// `(name, value)` of every `HORIZON_*` constant defined in `src`.
    fn constants(src: &str) -> Vec<(String, f64)> {
        let mut out = Vec::new();
        for line in src.lines() {
            let line = line.trim();
            if !(line.starts_with("const") || line.starts_with("static const")) {
                continue;
            }
            let Some(eq) = line.find('=') else { continue };
            let name = line[..eq]
                .split(|c: char| c.is_whitespace() || c == ':')
                .find(|w| w.starts_with("HORIZON_"))
                .unwrap_or_else(|| panic!("constant without a HORIZON_ name: {line}"));
            let value: f64 = line[eq + 1..].trim().trim_end_matches(';').parse().unwrap();
            out.push((name.to_owned(), value));
        }
        out
    }

    fn by_name(src: &'static str) -> &'static str {
        FILES.iter().find(|f| f.text == src).unwrap().name
    }

    #[test]
    fn every_include_declares_the_same_functions_and_constants() {
        let want_fns: Vec<(String, usize)> =
            FUNCTIONS.iter().map(|(n, k)| (n.to_string(), *k)).collect();
        for src in [GLSL, HLSL, WGSL, GODOT] {
            assert_eq!(functions(src), want_fns, "{}", by_name(src));
            let got = constants(src);
            assert_eq!(got.len(), CONSTANTS.len(), "{}: {got:?}", by_name(src));
            for ((name, value), (want_name, want)) in got.iter().zip(CONSTANTS) {
                assert_eq!(name, want_name, "{}", by_name(src));
                // Written with 8 significant digits: f32 holds no more.
                assert!(
                    ((value - want) / want).abs() < 1e-7,
                    "{}: {name} = {value}, expected {want}",
                    by_name(src)
                );
            }
        }
    }

    #[test]
    fn godot_include_is_the_glsl_decode_verbatim() {
        let marker = "// BEGIN horizon decode";
        let body = |src: &str| src[src.find(marker).expect("marker")..].to_owned();
        assert_eq!(body(GODOT), body(GLSL));
        // And nothing after the GLSL header that a Godot shader cannot hold.
        for word in ["#version", "precision ", "#extension", "uniform "] {
            assert!(!body(GLSL).contains(word), "{word}");
        }
    }

    /// The code of `src` with comments, preprocessor lines and all whitespace removed.
    fn code(src: &str) -> String {
        src.lines()
            .map(|l| l.split("//").next().unwrap_or(""))
            .filter(|l| !l.trim_start().starts_with('#'))
            .flat_map(|l| l.chars())
            .filter(|c| !c.is_whitespace())
            .collect()
    }

    #[test]
    fn hlsl_is_the_glsl_decode_statement_for_statement() {
        // Spelling only: HLSL's type names, atan2/fmod (fmod is GLSL's mod on the positive
        // operand it gets), `static const`, a scalar swizzle for a vector constructor, and a
        // scalar where GLSL writes a splatted vector (HLSL promotes it).
        let mut hlsl = HLSL.to_owned();
        for (from, to) in [
            ("float4", "vec4"),
            ("float3", "vec3"),
            ("float2", "vec2"),
            ("atan2(", "atan("),
            ("fmod(", "mod("),
            ("static const", "const"),
            ("pos.xxxx", "vec4(pos)"),
        ] {
            hlsl = hlsl.replace(from, to);
        }
        let splats = |mut s: String| {
            for v in ["0.0", "1.0", "3.0"] {
                s = s.replace(&format!("vec4({v})"), v);
            }
            s
        };
        let (glsl, hlsl) = (splats(code(GLSL)), splats(code(&hlsl)));
        if glsl != hlsl {
            let at = glsl.chars().zip(hlsl.chars()).take_while(|(a, b)| a == b).count();
            panic!(
                "horizon.hlsl departs from horizon.glsl at: glsl `{}` vs hlsl `{}`",
                glsl.chars().skip(at).take(60).collect::<String>(),
                hlsl.chars().skip(at).take(60).collect::<String>()
            );
        }
    }

    #[test]
    fn every_example_calls_its_include() {
        for f in FILES.iter().filter(|f| f.kind != Kind::Include) {
            let include =
                FILES.iter().find(|i| i.kind == Kind::Include && i.language == f.language).unwrap();
            let calls = FUNCTIONS.iter().filter(|(n, _)| f.text.contains(&format!("{n}("))).count();
            assert!(calls >= 1, "{} calls no decode function", f.name);
            if f.language != "wgsl" {
                // WGSL has no #include (its example is appended to the include instead), and
                // Unreal's Custom node names its include in the node's settings.
                let wanted = if f.name.contains("unreal") { "horizon.ush" } else { include.name };
                assert!(f.text.contains(wanted), "{} does not name {wanted}", f.name);
            }
        }
    }

    #[test]
    fn names_are_unique_and_found() {
        let mut names: Vec<&str> = FILES.iter().map(|f| f.name).collect();
        names.sort_unstable();
        names.dedup();
        assert_eq!(names.len(), FILES.len());
        for f in FILES {
            assert_eq!(find(f.name).unwrap().text, f.text);
            assert!(!f.text.is_empty());
        }
        assert!(find("../Cargo.toml").is_none());
        assert_eq!(out_files().len(), FILES.len());
    }

    /// A port of `horizon_factors_analytic` (the same expressions, in f32 as a GPU computes
    /// them) agrees with the cube map's own definition, `cubemap::factors_for_azimuth`.
    #[test]
    fn analytic_factors_match_the_cube_map_definition() {
        use crate::kernels::cubemap::factors_for_direction;
        let glsl_mod = |x: f32, y: f32| x - y * (x / y).floor();
        for k in 0..=1440 {
            let phi = (k as f64 / 1440.0) * 4.0 * std::f64::consts::PI - 2.0 * std::f64::consts::PI;
            let l = [0.7 * phi.cos(), 0.7 * phi.sin(), 0.714_142_8];
            let (x, y) = (l[0] as f32, l[1] as f32);
            let phi32 = if x.hypot(y) > 0.0 { y.atan2(x) } else { 0.0 };
            // HORIZON_QUARTER_PI = 0.78539816 rounds to this f32.
            let mut pos = phi32 / std::f32::consts::FRAC_PI_4;
            if pos < 0.0 {
                pos += 8.0;
            }
            let mut got = [0.0f32; 4];
            for (c, g) in got.iter_mut().enumerate() {
                let d = (glsl_mod(pos - c as f32 + 4.0, 8.0) - 4.0).abs();
                *g = (1.0 - d).max(0.0) - (d - 3.0).max(0.0);
            }
            let want = factors_for_direction(l);
            for c in 0..4 {
                assert!((got[c] - want[c]).abs() < 2e-5, "phi {phi}: {got:?} vs {want:?}");
            }
        }
        // Straight up: azimuth 0, all of channel 0, as the cube map's +Z face centre.
        assert_eq!(factors_for_direction([0.0, 0.0, 1.0]), [1.0, 0.0, 0.0, 0.0]);
    }
}
