// horizon_example.wgsl: the smallest WGSL fragment shader that shades with horizon-bake's maps,
// read from the KTX2 files (`--format ktx2`: one 2-layer array, and the SNORM cube map of
// `horizon-bake cubemap --format ktx2`). WGSL has no #include: the module is the text of
// horizon.wgsl followed by this file.

@group(0) @binding(0) var horizon_layers: texture_2d_array<f32>;  // horizon.ktx2, Rgba8Unorm
@group(0) @binding(1) var horizon_cube: texture_cube<f32>;        // cubemap.ktx2, Rgba8Snorm
@group(0) @binding(2) var linear_repeat: sampler;                 // ClampToEdge for edge=none
@group(0) @binding(3) var linear_clamp: sampler;

struct HorizonLight {
    light: vec3<f32>,   // unit direction to the light, tangent space
    hardness: f32,      // HORIZON_DEFAULT_HARDNESS unless you want softer edges
}
@group(0) @binding(4) var<uniform> u: HorizonLight;

@fragment
fn fs_main(@location(0) uv: vec2<f32>) -> @location(0) vec4<f32> {
    let f = textureSample(horizon_cube, linear_clamp, u.light);  // SNORM: already the factors
    let h0 = textureSample(horizon_layers, linear_repeat, uv, 0);
    let h1 = textureSample(horizon_layers, linear_repeat, uv, 1);
    let F = horizon_illumination_layers(u.light, f, h0, h1, u.hardness);
    return vec4<f32>(F, F, F, 1.0);
}
