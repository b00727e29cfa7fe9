// horizon_example.hlsl: the smallest HLSL (SM 5) pixel shader that shades with horizon-bake's
// maps, read from the DDS files (`--format dds`: one 2-layer array, and the SNORM cube map of
// `horizon-bake cubemap --format dds`). Entry point `main`.
#include "horizon.hlsl"

Texture2DArray<float4> HorizonLayers : register(t0);  // horizon.dds: layers 0 and 1, UNORM
TextureCube<float4> HorizonCube : register(t1);       // cubemap.dds: SNORM, samples to f
SamplerState LinearRepeat : register(s0);             // Clamp instead for edge=none
SamplerState LinearClamp : register(s1);

cbuffer HorizonLight : register(b0)
{
    float3 LightTS;    // unit direction to the light, tangent space
    float Hardness;    // HORIZON_DEFAULT_HARDNESS unless you want softer edges
};

struct PixelIn
{
    float4 position : SV_Position;
    float2 uv : TEXCOORD0;
};

float4 main(PixelIn i) : SV_Target
{
    float4 f = HorizonCube.Sample(LinearClamp, LightTS);  // SNORM: already the signed factors
    float4 h0 = HorizonLayers.Sample(LinearRepeat, float3(i.uv, 0.0));
    float4 h1 = HorizonLayers.Sample(LinearRepeat, float3(i.uv, 1.0));
    float F = horizon_illumination_layers(LightTS, f, h0, h1, Hardness);
    return float4(F, F, F, 1.0);
}
