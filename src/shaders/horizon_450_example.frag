#version 450
// horizon_450_example.frag: the smallest GLSL 4.50 fragment shader that shades with
// horizon-bake's maps, read from the KTX2 files (`--format ktx2`: one 2-layer array, and the
// SNORM cube map of `horizon-bake cubemap --format ktx2`). glslang and shaderc resolve the
// #include below; for a driver's GLSL compiler, paste horizon.glsl in its place.
#extension GL_GOOGLE_include_directive : require

#include "horizon.glsl"

layout(binding = 0) uniform sampler2DArray u_horizon;  // horizon.ktx2: layers 0 and 1, UNORM
layout(binding = 1) uniform samplerCube u_cube;        // cubemap.ktx2: SNORM, samples to f
layout(std140, binding = 2) uniform HorizonLight {
    vec3 light;       // unit direction to the light, tangent space
    float hardness;   // HORIZON_DEFAULT_HARDNESS unless you want softer edges
} u;

layout(location = 0) in vec2 v_uv;
layout(location = 0) out vec4 o_color;

void main() {
    vec4 f = texture(u_cube, u.light);   // SNORM: already the signed factors
    vec4 h0 = texture(u_horizon, vec3(v_uv, 0.0));
    vec4 h1 = texture(u_horizon, vec3(v_uv, 1.0));
    float F = horizon_illumination_layers(u.light, f, h0, h1, u.hardness);
    o_color = vec4(vec3(F), 1.0);
}
