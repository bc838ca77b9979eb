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
    int CbVatRangeFirst;    // the animation played (export.json animations[].vat): first_frame
    int CbVatRangeFrames;   // frames
    int CbVatRangeLoop;     // loop: 1 wraps (a clip), 0 plays once (a transition)
    int CbVatRangeBefore;   // before_frame: a transition's key 0, the from clip's leave pose
    int CbVatRangeAfter;    // after_frame: the pose after the range's last frame
};

// The pose frame of key j (vat.glsl's cb_vat_key_frame).
int CbVatKeyFrame(int j) {
    if (CbVatRangeLoop != 0) return j < CbVatRangeFrames ? CbVatRangeFirst + j : CbVatRangeAfter;
    if (j <= 0) return CbVatRangeBefore;
    if (j > CbVatRangeFrames) return CbVatRangeAfter;
    return CbVatRangeFirst + j - 1;
}

// vatUV: the vertex's TEXCOORD_1; frame: seconds into the animation times fps, any real number (a clip
// wraps, a transition holds its ends; the nearest two keys blend).
void CbVatSample(float2 vatUV, float frame, out float3 position, out float3 normal) {
    uint width, height;
    CbVatPosition.GetDimensions(width, height);
    int2 texel = int2(vatUV * float2(width, height));
    float n = (float)CbVatRangeFrames;
    bool loop = CbVatRangeLoop != 0;
    float x = loop ? frame - n * floor(frame / n) : clamp(frame, 0.0, n + 1.0);
    int j0 = min((int)floor(x), loop ? CbVatRangeFrames - 1 : CbVatRangeFrames);
    float t = x - j0;
    int3 c0 = int3(texel + int2(0, CbVatKeyFrame(j0) * CbVatRowsPerFrame), 0);
    int3 c1 = int3(texel + int2(0, CbVatKeyFrame(j0 + 1) * CbVatRowsPerFrame), 0);
    float3 q = lerp(CbVatPosition.Load(c0).rgb, CbVatPosition.Load(c1).rgb, t);
    position = CbVatBoundsMin + q * (CbVatBoundsMax - CbVatBoundsMin);
    normal = normalize(lerp(CbVatNormal.Load(c0).rgb, CbVatNormal.Load(c1).rgb, t) * 2.0 - 1.0);
}
