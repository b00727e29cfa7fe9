// horizon_unity.hlsl: Unity Shader Graph Custom Function wrappers over horizon.hlsl.
// Put horizon.hlsl and this file in your Assets; in a Custom Function node choose Type = File,
// Source = this file, and Name = HorizonIllumination, HorizonFactors or HorizonFourier (Unity
// appends _float or _half from the graph's precision). Sample the horizon textures with
// Sample Texture 2D nodes (Type Default, sRGB off in the importer, Wrap Repeat for edge=wrap)
// and pass the light in tangent space (Unity is Y+: bake with y_axis=up).
#ifndef HORIZON_UNITY_INCLUDED
#define HORIZON_UNITY_INCLUDED

#include "horizon.hlsl"

// Factors: the signed channel factors, from HorizonFactors or from sampling the SNORM cube map
// (cubemap.dds) with LightTS. Illumination: F in [0, 1]; multiply the light's diffuse and
// specular terms by it.
void HorizonIllumination_float(float3 LightTS, float4 Factors, float4 Layer0, float4 Layer1,
                               float Hardness, out float Illumination)
{
    Illumination = horizon_illumination_layers(LightTS, Factors, Layer0, Layer1, Hardness);
}

void HorizonIllumination_half(half3 LightTS, half4 Factors, half4 Layer0, half4 Layer1,
                              half Hardness, out half Illumination)
{
    Illumination = (half)horizon_illumination_layers((float3)LightTS, (float4)Factors,
                                                     (float4)Layer0, (float4)Layer1,
                                                     (float)Hardness);
}

// The channel factors computed from the light: no cube map texture needed.
void HorizonFactors_float(float3 LightTS, out float4 Factors)
{
    Factors = horizon_factors_analytic(LightTS);
}

void HorizonFactors_half(half3 LightTS, out half4 Factors)
{
    Factors = (half4)horizon_factors_analytic((float3)LightTS);
}

// outputs=fourier: F from fourier_0 (Bands), fourier_1 (Const, its red channel) and fourier_2
// (High, any value for fourier_terms 3 or 5); Terms = the bake's fourier_terms; Expanded = 1 for
// fourier_range=expanded.
void HorizonFourier_float(float3 LightTS, float4 Bands, float Const, float4 High, float Terms,
                          float Expanded, float Hardness, out float Illumination)
{
    float s = horizon_fourier(Bands, Const, High, horizon_light_dir(LightTS), (int)Terms,
                              Expanded > 0.5);
    Illumination = horizon_illumination(LightTS.z, s, Hardness);
}

void HorizonFourier_half(half3 LightTS, half4 Bands, half Const, half4 High, half Terms,
                         half Expanded, half Hardness, out half Illumination)
{
    float s = horizon_fourier((float4)Bands, (float)Const, (float4)High,
                              horizon_light_dir((float3)LightTS), (int)Terms, Expanded > 0.5);
    Illumination = (half)horizon_illumination((float)LightTS.z, s, (float)Hardness);
}

#endif // HORIZON_UNITY_INCLUDED
