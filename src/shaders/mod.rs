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
//! layout and every binding model. They are hand-written per language, because the syntaxes
//! differ in more than type names, and held equal by the tests below, not generated:
//! `horizon.glsl` is valid GLSL ES 3.00 and GLSL 4.50 alike, `horizon.gdshaderinc` is its
//! decode byte for byte after its own header, and `horizon.hlsl` and `horizon.wgsl` are its
//! decode statement for statement once both texts are brought to one normal form.
//! tests/encode/shaders.rs compiles every file but Godot's with real compilers (Godot's has
//! none here). The numbers are proven in GLSL by the browser test, and through these equalities for
//! the other languages; `horizon_factors_analytic` by a port checked against the cube map's
//! definition below. docs/reference.md (§16, "How the includes are kept equal") has each rule.

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

    /// Lines of code: comments and preprocessor lines dropped.
    fn code_lines(src: &str) -> Vec<&str> {
        src.lines()
            .map(|l| l.split("//").next().unwrap_or(""))
            .filter(|l| !l.trim_start().starts_with('#'))
            .collect()
    }

    /// `fn name(a,b,…)` from a parameter list, each parameter named by `name_of`.
    fn signature(name: &str, params: &str, name_of: impl Fn(&str) -> String) -> String {
        let names: Vec<String> =
            params.split(',').map(str::trim).filter(|p| !p.is_empty()).map(name_of).collect();
        format!("fn {name}({})", names.join(","))
    }

    /// GLSL in a form WGSL can be brought to: untyped signatures, constants and locals (`let`),
    /// no whitespace, and WGSL's `%` spelling of the one `mod`.
    fn glsl_normal(src: &str) -> String {
        let mut out = String::new();
        for line in code_lines(src) {
            let trimmed = line.trim_start();
            let indented = trimmed.len() != line.len();
            let open = line.find('(');
            if !indented && line.starts_with("const ") {
                // const TYPE NAME = v;
                let (lhs, rhs) = line.split_once('=').unwrap();
                let name = lhs.split_whitespace().last().unwrap();
                out += &format!("const {name} ={rhs}");
            } else if let (false, Some(open), Some(close)) = (indented, open, line.rfind(')')) {
                if trimmed.is_empty() {
                    continue;
                }
                let name = line[..open].split_whitespace().last().unwrap();
                out += &signature(name, &line[open + 1..close], |p| {
                    p.split_whitespace().last().unwrap().to_owned()
                });
                out += &line[close + 1..];
            } else if let Some(rest) = ["float ", "vec2 ", "vec3 ", "vec4 ", "int ", "bool "]
                .iter()
                .find_map(|t| trimmed.strip_prefix(t).filter(|r| r.contains(" = ")))
            {
                out += &format!("let {rest}");
            } else {
                out += line;
            }
        }
        let mut s: String = out.chars().filter(|c| !c.is_whitespace()).collect();
        s = s.replace(
            "mod(vec4(pos)-vec4(0.0,1.0,2.0,3.0)+4.0,8.0)",
            "(vec4(pos)-vec4(0.0,1.0,2.0,3.0)+4.0)%vec4(8.0)",
        );
        s
    }

    /// `select(a, b, c)` → `(c?b:a)`, innermost last, in whitespace-free text.
    fn unselect(mut s: String) -> String {
        while let Some(i) = s.find("select(") {
            let start = i + "select(".len();
            let (mut depth, mut end) = (1, start);
            let mut commas = Vec::new();
            for (k, ch) in s[start..].char_indices() {
                match ch {
                    '(' => depth += 1,
                    ')' => depth -= 1,
                    ',' if depth == 1 => commas.push(start + k),
                    _ => {}
                }
                if depth == 0 {
                    end = start + k;
                    break;
                }
            }
            assert_eq!(commas.len(), 2, "select with {} arguments", commas.len() + 1);
            let a = &s[start..commas[0]];
            let b = &s[commas[0] + 1..commas[1]];
            let c = &s[commas[1] + 1..end];
            s = format!("{}({c}?{b}:{a}){}", &s[..i], &s[end + 1..]);
        }
        s
    }

    /// WGSL brought to the form of [`glsl_normal`]: untyped signatures and constants, `var` as
    /// `let`, GLSL's type and `atan` names, `select` as a ternary, no whitespace.
    fn wgsl_normal(src: &str) -> String {
        let mut out = String::new();
        for line in code_lines(src) {
            if let Some(rest) = line.strip_prefix("fn ") {
                let open = rest.find('(').unwrap();
                let close = rest.rfind(')').unwrap();
                out += &signature(&rest[..open], &rest[open + 1..close], |p| {
                    p.split(':').next().unwrap().trim().to_owned()
                });
                out += &rest[rest.find('{').unwrap()..];
            } else if let Some(rest) = line.strip_prefix("const ") {
                // const NAME: T = v;
                let (lhs, rhs) = rest.split_once('=').unwrap();
                out += &format!("const {} ={rhs}", lhs.split(':').next().unwrap().trim());
            } else if let Some(rest) = line.trim_start().strip_prefix("var ") {
                out += &format!("let {rest}");
            } else {
                out += line;
            }
        }
        let mut s: String = out.chars().filter(|c| !c.is_whitespace()).collect();
        for (from, to) in [
            ("vec4<f32>", "vec4"),
            ("vec3<f32>", "vec3"),
            ("vec2<f32>", "vec2"),
            ("atan2(", "atan("),
        ] {
            s = s.replace(from, to);
        }
        unselect(s)
    }

    #[test]
    fn wgsl_is_the_glsl_decode_statement_for_statement() {
        let (glsl, wgsl) = (glsl_normal(GLSL), wgsl_normal(WGSL));
        if glsl != wgsl {
            let at = glsl.chars().zip(wgsl.chars()).take_while(|(a, b)| a == b).count();
            panic!(
                "horizon.wgsl departs from horizon.glsl at: glsl `{}` vs wgsl `{}`",
                glsl.chars().skip(at).take(60).collect::<String>(),
                wgsl.chars().skip(at).take(60).collect::<String>()
            );
        }
        // The normal form still says something: the decode's statements are in it.
        assert!(
            glsl.contains("fnhorizon_s(f,h0,h1){letp=max(f,vec4(0.0))*h0+max(-f,vec4(0.0))*h1;")
        );
        assert!(glsl.contains("letv=(expanded?t*2.0-1.0:t*4.0-2.0);"), "{glsl}");
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
