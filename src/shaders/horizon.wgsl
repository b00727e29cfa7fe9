// horizon.wgsl: decode horizon-bake's maps in WGSL (WebGPU, wgpu).
// Shipped by horizon-bake (`horizon-bake shaders -o DIR`, GET /v1/shaders/horizon.wgsl).
//
// WGSL has no #include: concatenate this text with your shader module's source (module-scope
// declarations may come in any order); see horizon_example.wgsl. The same functions, names and
// constants exist in horizon.glsl, horizon.hlsl and horizon.gdshaderinc. Every value here is
// linear: use *Unorm (not *UnormSrgb) texture formats.
//
// Tangent space: x = +u (image right), y per the bake's `y_axis`, z out of the surface; `light`
// is the unit direction to the light in that space.

const HORIZON_DEFAULT_HARDNESS: f32 = 8.0;
const HORIZON_QUARTER_PI: f32 = 0.78539816;
const HORIZON_TWO_OVER_PI: f32 = 0.63661977;

// The signed channel factors from a texel of the UNORM cube map (`cube_N.png`): f = t*2 - 1.
// A SNORM cube map (`cubemap.ktx2`, `cubemap.dds`) samples to f directly: do not call this
// (the BC7 cube, `texture_precision=bc7`, is UNORM: call it).
fn horizon_cube_factors(texel: vec4<f32>) -> vec4<f32> {
    return texel * 2.0 - 1.0;
}

// The same factors computed from the light instead of looked up in the cube map (SPEC 3.3):
// 1 - t on the channel at or below the light's azimuth, t on the next one, a layer-1 channel's
// factor negated in its slot. Straight up takes azimuth 0.
fn horizon_factors_analytic(light: vec3<f32>) -> vec4<f32> {
    let phi = select(0.0, atan2(light.y, light.x), length(light.xy) > 0.0);
    var pos = phi / HORIZON_QUARTER_PI;
    if (pos < 0.0) {
        pos += 8.0;
    }
    // Distance in channels from the light to channels 0..3 (around the circle, 0..4); channel
    // c + 4 is 4 minus it away. The operand of % is positive, so % is GLSL's mod here.
    let d = abs((vec4<f32>(pos) - vec4<f32>(0.0, 1.0, 2.0, 3.0) + 4.0) % vec4<f32>(8.0) - 4.0);
    return max(vec4<f32>(1.0) - d, vec4<f32>(0.0)) - max(d - vec4<f32>(3.0), vec4<f32>(0.0));
}

// encoding=sqrt stores sqrt(s): the horizon value is v*v. encoding=linear needs nothing.
fn horizon_decode_sqrt(v: vec4<f32>) -> vec4<f32> {
    return v * v;
}

// Lengyel eq. 5.3: the horizon value s at the light's azimuth from the factors f and the two
// RGBA layers (layer 0 = channels 0..3, layer 1 = channels 4..7).
fn horizon_s(f: vec4<f32>, h0: vec4<f32>, h1: vec4<f32>) -> f32 {
    let p = max(f, vec4<f32>(0.0)) * h0 + max(-f, vec4<f32>(0.0)) * h1;
    return ((p.x + p.y) + p.z) + p.w;
}

// texture_precision=bc5: four RG layers holding channels (0,1), (2,3), (4,5), (6,7) (SPEC 8).
fn horizon_s_bc5(f: vec4<f32>, l0: vec2<f32>, l1: vec2<f32>, l2: vec2<f32>, l3: vec2<f32>) -> f32 {
    let pos = max(f, vec4<f32>(0.0));
    let neg = max(-f, vec4<f32>(0.0));
    return dot(l0, pos.xy) + dot(l1, pos.zw) + dot(l2, neg.xy) + dot(l3, neg.zw);
}

// The illumination factor F = clamp(k*(L_z - s) + 1, 0, 1); 0 at or below the tangent plane.
fn horizon_illumination(lz: f32, s: f32, hardness: f32) -> f32 {
    if (lz <= 0.0) {
        return 0.0;
    }
    return clamp(hardness * (lz - s) + 1.0, 0.0, 1.0);
}

// F from the cube-map factors and the two layers (8-bit or 16-bit UNORM, encoding=linear).
fn horizon_illumination_layers(light: vec3<f32>, f: vec4<f32>, h0: vec4<f32>, h1: vec4<f32>, hardness: f32) -> f32 {
    return horizon_illumination(light.z, horizon_s(f, h0, h1), hardness);
}

// The light's azimuth direction (x, y) = (cos phi, sin phi); (1, 0) straight up.
fn horizon_light_dir(light: vec3<f32>) -> vec2<f32> {
    let r = length(light.xy);
    return select(vec2<f32>(1.0, 0.0), light.xy / r, r > 0.0);
}

// SPEC 3.4: band coefficients from a texel of fourier_0 (or fourier_2). fourier_range=standard:
// v = t*4 - 2, C = v*|v|; expanded: v = t*2 - 1, C = v*|v|*2/pi.
fn horizon_fourier_bands(t: vec4<f32>, expanded: bool) -> vec4<f32> {
    let v = select(t * 4.0 - 2.0, t * 2.0 - 1.0, expanded);
    return v * abs(v) * select(1.0, HORIZON_TWO_OVER_PI, expanded);
}

// SPEC 3.4: the constant term from fourier_1. standard: c = t*2 - 1, C_0 = c*|c|; expanded: t*t.
fn horizon_fourier_const(t: f32, expanded: bool) -> f32 {
    let c = select(t * 2.0 - 1.0, t, expanded);
    return c * abs(c);
}

// SPEC 3.4: s(phi) from the Fourier textures at the light's azimuth direction `dir`
// (horizon_light_dir). `terms` is the bake's fourier_terms (3, 5, 7 or 9); `t_high` is the
// fourier_2 texel (any value when terms < 7).
fn horizon_fourier(t_bands: vec4<f32>, t_const: f32, t_high: vec4<f32>, dir: vec2<f32>, terms: i32, expanded: bool) -> f32 {
    let x = dir.x;
    let y = dir.y;
    let lq = horizon_fourier_bands(t_bands, expanded);
    var s = horizon_fourier_const(t_const, expanded) + lq.x * x + lq.y * y;
    if (terms >= 5) {
        s += lq.z * 2.0 * x * y + lq.w * (y * y - x * x);
    }
    if (terms >= 7) {
        let hq = horizon_fourier_bands(t_high, expanded);
        let c2 = x * x - y * y;
        s += hq.x * x * (x * x - 3.0 * y * y) + hq.y * y * (3.0 * x * x - y * y);
        if (terms >= 9) {
            s += hq.z * 4.0 * x * y * c2 + hq.w * (c2 * c2 - 4.0 * x * x * y * y);
        }
    }
    return s;
}
