// crowdbake export: the UV-mapped impostor (Dobbyn et al. 2006, section 5) in an HLSL pixel shader.
// See impostor_uv.glsl for the idea; bind impostor/uv.ktx2 as DXGI_FORMAT_R32_UINT, the normal map
// as R8G8B8A8_UNORM, diffuse and outfits as R8G8B8A8_UNORM_SRGB (or _UNORM to shade in gamma space
// like crowdview).

Texture2DArray<uint> CbUvMap;
Texture2DArray<float4> CbNormalMap;
Texture2DArray<float4> CbDiffuse;
Texture2D<float4> CbOutfits;
SamplerState CbLinearSampler;

cbuffer CbImpostor {
    float3 CbLightDir;  // unit, towards the light, world space
    int CbTileSize;
    int4 CbCrop;  // export.json impostor.crop: x, y, width, height of the stored part of every tile
};

static const float CB_AMBIENT = 0.35;  // crowdview's ambient term (runtime/src/config.h)

// Returns false where the impostor does not cover the pixel (clip it). cellOrigin: the top-left texel
// of the view's cell, (a * crop.width, e * crop.height).
bool CbImpostorColour(float2 tileUV, int2 cellOrigin, int layer, float heading, int variation, int outfit, out float3 colour) {
    int2 t = clamp(int2(tileUV * CbTileSize), int2(0, 0), int2(CbTileSize - 1, CbTileSize - 1)) - CbCrop.xy;
    colour = float3(0, 0, 0);
    if (any(t < int2(0, 0)) || any(t >= CbCrop.zw)) return false;
    int2 texel = cellOrigin + t;
    // crowdview's uv32 decode, as impostor_uv.glsl (services/tests/test_export_shader_mirror.py checks both copies).
    uint word = CbUvMap.Load(int4(texel, layer, 0));
    if ((word >> 31) == 0) return false;
    float2 uv = float2(word & 0x3FFF, (word >> 14) & 0x3FFF) / 16383.0;
    float4 diffuse = CbDiffuse.SampleLevel(CbLinearSampler, float3(uv, variation), 0);
    int region = (int)(diffuse.a * 255.0 / 17.0 + 0.5);
    float3 albedo = diffuse.rgb;
    if (region != 0) albedo *= CbOutfits.Load(int3(region, outfit, 0)).rgb;
    float3 modelNormal = CbNormalMap.Load(int4(texel, layer, 0)).rgb * 2.0 - 1.0;
    float c = cos(heading), s = sin(heading);
    // Rotation about +Y by heading (column-major in GLSL; written out per row here).
    float3 normal = normalize(float3(c * modelNormal.x + s * modelNormal.z, modelNormal.y, -s * modelNormal.x + c * modelNormal.z));
    colour = albedo * (CB_AMBIENT + (1.0 - CB_AMBIENT) * max(dot(normal, CbLightDir), 0.0));
    return true;
}
