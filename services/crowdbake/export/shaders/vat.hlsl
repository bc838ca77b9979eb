// crowdbake export: play a vertex-animation texture (VAT) in an HLSL vertex shader (SM 4.0+).
// Values come from export.json (lods[].parts[].vat) or the glTF mesh's extras.crowdbake.vat.
// Bind the position VAT as DXGI_FORMAT_R16G16B16A16_UNORM and the normal VAT as DXGI_FORMAT_R8G8B8A8_UNORM
// (the KTX2s' vkFormats): Load returns 0..1.

Texture2D<float4> CbVatPosition;
Texture2D<float4> CbVatNormal;

cbuffer CbVat {
    float3 CbVatBoundsMin;  // vat.bounds_min
    int CbVatRowsPerFrame;  // vat.rows_per_frame
    float3 CbVatBoundsMax;  // vat.bounds_max
    int CbVatFrameCount;    // vat.frame_count
};

// vatUV: the vertex's TEXCOORD_1; frame: any real number (wraps; the nearest two frames blend).
void CbVatSample(float2 vatUV, float frame, out float3 position, out float3 normal) {
    uint width, height;
    CbVatPosition.GetDimensions(width, height);
    int2 texel = int2(vatUV * float2(width, height));
    float wrapped = frame - CbVatFrameCount * floor(frame / CbVatFrameCount);
    int f0 = (int)floor(wrapped);
    int f1 = (f0 + 1) % CbVatFrameCount;
    float t = wrapped - f0;
    int3 c0 = int3(texel + int2(0, f0 * CbVatRowsPerFrame), 0);
    int3 c1 = int3(texel + int2(0, f1 * CbVatRowsPerFrame), 0);
    float3 q = lerp(CbVatPosition.Load(c0).rgb, CbVatPosition.Load(c1).rgb, t);
    position = CbVatBoundsMin + q * (CbVatBoundsMax - CbVatBoundsMin);
    normal = normalize(lerp(CbVatNormal.Load(c0).rgb, CbVatNormal.Load(c1).rgb, t) * 2.0 - 1.0);
}
