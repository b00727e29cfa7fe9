#version 300 es
// horizon_es300_example.frag: the smallest GLSL ES 3.00 (WebGL2) fragment shader that shades
// with horizon-bake's maps. GLSL has no #include: replace the #include line below with the text
// of horizon.glsl when you build the source string (horizon-bake's own web viewer does exactly
// that with GET /v1/shaders/horizon.glsl).
precision highp float;

#include "horizon.glsl"

uniform sampler2D u_horizon0;   // horizon_0.png: RGBA8, linear (no sRGB), REPEAT for edge=wrap
uniform sampler2D u_horizon1;   // horizon_1.png
uniform samplerCube u_cube;     // cube_0.png .. cube_5.png (UNORM): faces +X, -X, +Y, -Y, +Z, -Z
uniform vec3 u_light;           // unit direction to the light, tangent space
uniform float u_hardness;       // HORIZON_DEFAULT_HARDNESS unless you want softer edges

in vec2 v_uv;
out vec4 o_color;

void main() {
    vec4 f = horizon_cube_factors(texture(u_cube, u_light));
    float F = horizon_illumination(u_light.z,
        horizon_s(f, texture(u_horizon0, v_uv), texture(u_horizon1, v_uv)), u_hardness);
    o_color = vec4(vec3(F), 1.0);
}
