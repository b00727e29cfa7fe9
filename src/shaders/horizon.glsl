// horizon.glsl: decode horizon-bake's maps in GLSL ES 3.00 (WebGL2) and GLSL 4.50.
// Shipped by horizon-bake (`horizon-bake shaders -o DIR`, GET /v1/shaders/horizon.glsl).
//
// GLSL has no #include: put this text after your `#version` and `precision` lines (GLSL ES
// fragment shaders need `precision highp float;` before it), or use GL_GOOGLE_include_directive
// with glslang/shaderc. The same functions, names and constants exist in horizon.hlsl,
// horizon.wgsl and horizon.gdshaderinc. Every value here is linear: sample the maps without sRGB.
//
// Tangent space: x = +u (image right), y per the bake's `y_axis`, z out of the surface; `light`
// is the unit direction to the light in that space.
//
// BEGIN horizon decode (this part is identical in horizon.gdshaderinc)

const float HORIZON_DEFAULT_HARDNESS = 8.0;
const float HORIZON_QUARTER_PI = 0.78539816;
const float HORIZON_TWO_OVER_PI = 0.63661977;

// The signed channel factors from a texel of the UNORM cube map (`cube_N.png`): f = t*2 - 1.
// A SNORM cube map (`cubemap.ktx2`, `cubemap.dds`) samples to f directly: do not call this
// (the BC7 cube, `texture_precision=bc7`, is UNORM: call it).
vec4 horizon_cube_factors(vec4 texel) {
    return texel * 2.0 - 1.0;
}

// The same factors computed from the light instead of looked up in the cube map (SPEC 3.3):
// 1 - t on the channel at or below the light's azimuth, t on the next one, a layer-1 channel's
// factor negated in its slot. Straight up takes azimuth 0.
vec4 horizon_factors_analytic(vec3 light) {
    float phi = (length(light.xy) > 0.0 ? atan(light.y, light.x) : 0.0);
    float pos = phi / HORIZON_QUARTER_PI;
    if (pos < 0.0) {
        pos += 8.0;
    }
    // Distance in channels from the light to channels 0..3 (around the circle, 0..4); channel
    // c + 4 is 4 minus it away.
    vec4 d = abs(mod(vec4(pos) - vec4(0.0, 1.0, 2.0, 3.0) + 4.0, 8.0) - 4.0);
    return max(vec4(1.0) - d, vec4(0.0)) - max(d - vec4(3.0), vec4(0.0));
}

// encoding=sqrt stores sqrt(s): the horizon value is v*v. encoding=linear needs nothing.
vec4 horizon_decode_sqrt(vec4 v) {
    return v * v;
}

// Lengyel eq. 5.3: the horizon value s at the light's azimuth from the factors f and the two
// RGBA layers (layer 0 = channels 0..3, layer 1 = channels 4..7).
float horizon_s(vec4 f, vec4 h0, vec4 h1) {
    vec4 p = max(f, vec4(0.0)) * h0 + max(-f, vec4(0.0)) * h1;
    return ((p.x + p.y) + p.z) + p.w;
}

// texture_precision=bc5: four RG layers holding channels (0,1), (2,3), (4,5), (6,7) (SPEC 8).
float horizon_s_bc5(vec4 f, vec2 l0, vec2 l1, vec2 l2, vec2 l3) {
    vec4 pos = max(f, vec4(0.0));
    vec4 neg = max(-f, vec4(0.0));
    return dot(l0, pos.xy) + dot(l1, pos.zw) + dot(l2, neg.xy) + dot(l3, neg.zw);
}

// The illumination factor F = clamp(k*(L_z - s) + 1, 0, 1); 0 at or below the tangent plane.
float horizon_illumination(float lz, float s, float hardness) {
    if (lz <= 0.0) {
        return 0.0;
    }
    return clamp(hardness * (lz - s) + 1.0, 0.0, 1.0);
}

// F from the cube-map factors and the two layers (8-bit or 16-bit UNORM, encoding=linear).
float horizon_illumination_layers(vec3 light, vec4 f, vec4 h0, vec4 h1, float hardness) {
    return horizon_illumination(light.z, horizon_s(f, h0, h1), hardness);
}

// The light's azimuth direction (x, y) = (cos phi, sin phi); (1, 0) straight up.
vec2 horizon_light_dir(vec3 light) {
    float r = length(light.xy);
    return (r > 0.0 ? light.xy / r : vec2(1.0, 0.0));
}

// SPEC 3.4: band coefficients from a texel of fourier_0 (or fourier_2). fourier_range=standard:
// v = t*4 - 2, C = v*|v|; expanded: v = t*2 - 1, C = v*|v|*2/pi.
vec4 horizon_fourier_bands(vec4 t, bool expanded) {
    vec4 v = (expanded ? t * 2.0 - 1.0 : t * 4.0 - 2.0);
    return v * abs(v) * (expanded ? HORIZON_TWO_OVER_PI : 1.0);
}

// SPEC 3.4: the constant term from fourier_1. standard: c = t*2 - 1, C_0 = c*|c|; expanded: t*t.
float horizon_fourier_const(float t, bool expanded) {
    float c = (expanded ? t : t * 2.0 - 1.0);
    return c * abs(c);
}

// SPEC 3.4: s(phi) from the Fourier textures at the light's azimuth direction `dir`
// (horizon_light_dir). `terms` is the bake's fourier_terms (3, 5, 7 or 9); `t_high` is the
// fourier_2 texel (any value when terms < 7).
float horizon_fourier(vec4 t_bands, float t_const, vec4 t_high, vec2 dir, int terms, bool expanded) {
    float x = dir.x;
    float y = dir.y;
    vec4 lq = horizon_fourier_bands(t_bands, expanded);
    float s = horizon_fourier_const(t_const, expanded) + lq.x * x + lq.y * y;
    if (terms >= 5) {
        s += lq.z * 2.0 * x * y + lq.w * (y * y - x * x);
    }
    if (terms >= 7) {
        vec4 hq = horizon_fourier_bands(t_high, expanded);
        float c2 = x * x - y * y;
        s += hq.x * x * (x * x - 3.0 * y * y) + hq.y * y * (3.0 * x * x - y * y);
        if (terms >= 9) {
            s += hq.z * 4.0 * x * y * c2 + hq.w * (c2 * c2 - 4.0 * x * x * y * y);
        }
    }
    return s;
}
