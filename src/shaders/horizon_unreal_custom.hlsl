// horizon_unreal_custom.hlsl: the Code of an Unreal Engine material Custom expression that
// returns the illumination factor F (Output Type: CMOT Float 1).
// Setup: copy horizon.hlsl as horizon.ush into a shader directory your project or plugin maps
// (a plugin's Shaders/ folder is /Plugin/<Name>/; a game module maps one with
// AddShaderSourceDirectoryMapping), and add that virtual path (e.g. /Plugin/Horizon/horizon.ush)
// to the Custom node's Include File Paths.
// Inputs (names as below): LightTS (float3, unit light direction in tangent space; Unreal is
// Y-: bake with y_axis=down), Layer0 and Layer1 (float4, the RGBA of horizon_0 and horizon_1
// from Texture Sample nodes, Sampler Type Linear Color, sRGB off, Wrap for edge=wrap), Hardness
// (float, 8 by default).
// Multiply the light's contribution (or the shadow term of a custom lighting model) by it.
// The channel factors are computed from the light, so no cube map texture is needed.
return horizon_illumination_layers(LightTS, horizon_factors_analytic(LightTS), Layer0, Layer1, Hardness);
