// horizon.hlsl: decode horizon-bake's maps in HLSL (Shader Model 5: Direct3D 11/12, Unity,
// Unreal). Shipped by horizon-bake (`horizon-bake shaders -o DIR`, GET /v1/shaders/horizon.hlsl).
//
// Use: #include "horizon.hlsl"; see horizon_example.hlsl, the Unity Custom Function wrapper
// horizon_unity.hlsl and the Unreal Custom-expression snippet horizon_unreal_custom.hlsl.
// The same functions, names and constants exist in horizon.glsl, horizon.wgsl and
// horizon.gdshaderinc. Every value here is linear: sample the maps without sRGB.
//
// Tangent space: x = +u (image right), y per the bake's `y_axis` (Direct3D and Unreal are Y-:
// bake with y_axis=down; Unity is Y+: y_axis=up), z out of the surface; `light` is the unit
// direction to the light in that space.

#ifndef HORIZON_HLSL_INCLUDED
#define HORIZON_HLSL_INCLUDED

static const float HORIZON_DEFAULT_HARDNESS = 8.0;
static const float HORIZON_QUARTER_PI = 0.78539816;
static const float HORIZON_TWO_OVER_PI = 0.63661977;

// The signed channel factors from a texel of the UNORM cube map (`cube_N.png`): f = t*2 - 1.
// A SNORM cube map (`cubemap.ktx2`, `cubemap.dds`) samples to f directly: do not call this
// (the BC7 cube, `texture_precision=bc7`, is UNORM: call it).
float4 horizon_cube_factors(float4 texel)
{
    return texel * 2.0 - 1.0;
}

// The same factors computed from the light instead of looked up in the cube map (SPEC 3.3):
// 1 - t on the channel at or below the light's azimuth, t on the next one, a layer-1 channel's
// factor negated in its slot. Straight up takes azimuth 0.
float4 horizon_factors_analytic(float3 light)
{
    float phi = (length(light.xy) > 0.0 ? atan2(light.y, light.x) : 0.0);
    float pos = phi / HORIZON_QUARTER_PI;
    if (pos < 0.0) {
        pos += 8.0;
    }
    // Distance in channels from the light to channels 0..3 (around the circle, 0..4); channel
    // c + 4 is 4 minus it away. The operand of fmod is positive, so fmod is GLSL's mod here.
    float4 d = abs(fmod(pos.xxxx - float4(0.0, 1.0, 2.0, 3.0) + 4.0, 8.0) - 4.0);
    return max(1.0 - d, 0.0) - max(d - 3.0, 0.0);
}

// encoding=sqrt stores sqrt(s): the horizon value is v*v. encoding=linear needs nothing.
float4 horizon_decode_sqrt(float4 v)
{
    return v * v;
}

// Lengyel eq. 5.3: the horizon value s at the light's azimuth from the factors f and the two
// RGBA layers (layer 0 = channels 0..3, layer 1 = channels 4..7).
float horizon_s(float4 f, float4 h0, float4 h1)
{
    float4 p = max(f, 0.0) * h0 + max(-f, 0.0) * h1;
    return ((p.x + p.y) + p.z) + p.w;
}

// texture_precision=bc5: four RG layers holding channels (0,1), (2,3), (4,5), (6,7) (SPEC 8).
float horizon_s_bc5(float4 f, float2 l0, float2 l1, float2 l2, float2 l3)
{
    float4 pos = max(f, 0.0);
    float4 neg = max(-f, 0.0);
    return dot(l0, pos.xy) + dot(l1, pos.zw) + dot(l2, neg.xy) + dot(l3, neg.zw);
}

// The illumination factor F = clamp(k*(L_z - s) + 1, 0, 1); 0 at or below the tangent plane.
float horizon_illumination(float lz, float s, float hardness)
{
    if (lz <= 0.0) {
        return 0.0;
    }
    return clamp(hardness * (lz - s) + 1.0, 0.0, 1.0);
}

// F from the cube-map factors and the two layers (8-bit or 16-bit UNORM, encoding=linear).
float horizon_illumination_layers(float3 light, float4 f, float4 h0, float4 h1, float hardness)
{
    return horizon_illumination(light.z, horizon_s(f, h0, h1), hardness);
}

// The light's azimuth direction (x, y) = (cos phi, sin phi); (1, 0) straight up.
float2 horizon_light_dir(float3 light)
{
    float r = length(light.xy);
    return (r > 0.0 ? light.xy / r : float2(1.0, 0.0));
}

// SPEC 3.4: band coefficients from a texel of fourier_0 (or fourier_2). fourier_range=standard:
// v = t*4 - 2, C = v*|v|; expanded: v = t*2 - 1, C = v*|v|*2/pi.
float4 horizon_fourier_bands(float4 t, bool expanded)
{
    float4 v = (expanded ? t * 2.0 - 1.0 : t * 4.0 - 2.0);
    return v * abs(v) * (expanded ? HORIZON_TWO_OVER_PI : 1.0);
}

// SPEC 3.4: the constant term from fourier_1. standard: c = t*2 - 1, C_0 = c*|c|; expanded: t*t.
float horizon_fourier_const(float t, bool expanded)
{
    float c = (expanded ? t : t * 2.0 - 1.0);
    return c * abs(c);
}

// SPEC 3.4: s(phi) from the Fourier textures at the light's azimuth direction `dir`
// (horizon_light_dir). `terms` is the bake's fourier_terms (3, 5, 7 or 9); `t_high` is the
// fourier_2 texel (any value when terms < 7).
float horizon_fourier(float4 t_bands, float t_const, float4 t_high, float2 dir, int terms, bool expanded)
{
    float x = dir.x;
    float y = dir.y;
    float4 lq = horizon_fourier_bands(t_bands, expanded);
    float s = horizon_fourier_const(t_const, expanded) + lq.x * x + lq.y * y;
    if (terms >= 5) {
        s += lq.z * 2.0 * x * y + lq.w * (y * y - x * x);
    }
    if (terms >= 7)
    {
        float4 hq = horizon_fourier_bands(t_high, expanded);
        float c2 = x * x - y * y;
        s += hq.x * x * (x * x - 3.0 * y * y) + hq.y * y * (3.0 * x * x - y * y);
        if (terms >= 9) {
            s += hq.z * 4.0 * x * y * c2 + hq.w * (c2 * c2 - 4.0 * x * x * y * y);
        }
    }
    return s;
}

#endif // HORIZON_HLSL_INCLUDED
