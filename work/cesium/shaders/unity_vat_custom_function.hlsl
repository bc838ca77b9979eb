// crowdbake export: a Shader Graph Custom Function (Unity URP/HDRP, docs/export.md "Unity") that plays a
// vertex-animation texture (VAT). Custom Function node: Type File, this file, Name CrowdbakeVat, precision
// Float. Inputs: VatUV (Vector 2, UV1 = glTF TEXCOORD_1), Frame (Float: seconds into the animation * fps),
// PositionMap, NormalMap (Texture 2D), BoundsMin, BoundsMax (Vector 3), RowsPerFrame (Float), Range (Vector 4:
// first_frame, frames, loop, before_frame), RangeAfter (Float: after_frame), NodeTranslation (Vector 3),
// NodeScale (Float). Outputs: Position, Normal (Vector 3, object space) into the Vertex stage's Position and
// Normal. Values from export.json: lods[].parts[].vat, lods[].parts[].node (the quantized mesh's node
// transform) and animations[].vat (the clip or transition played: its range of pose frames).
// glTFast turns glTF's right-handed axes into Unity's left-handed ones by negating x; so does this.

// The pose frame of key j of the range (first, frames, loop, before) then after (vat.glsl's cb_vat_key_frame).
int CrowdbakeKeyFrame(int j, int4 range, int after) {
    if (range.z != 0) return j < range.y ? range.x + j : after;
    if (j <= 0) return range.w;
    if (j > range.y) return after;
    return range.x + j - 1;
}

// The sampling itself, on plain HLSL textures (what the test compiles). A clip wraps, a transition holds its ends.
void CrowdbakeVatSample(float2 vatUV, float frame, Texture2D<float4> positionMap, Texture2D<float4> normalMap, float3 boundsMin,
                        float3 boundsMax, float rowsPerFrame, float4 range, float rangeAfter, out float3 position, out float3 normal) {
    uint width, height;
    positionMap.GetDimensions(width, height);
    int2 texel = int2(vatUV * float2(width, height));
    int4 r = int4(range);
    float n = range.y;
    bool loop = r.z != 0;
    float x = loop ? frame - n * floor(frame / n) : clamp(frame, 0.0, n + 1.0);
    int j0 = min((int)floor(x), loop ? r.y - 1 : r.y);
    float t = x - j0;
    int3 c0 = int3(texel + int2(0, CrowdbakeKeyFrame(j0, r, (int)rangeAfter) * (int)rowsPerFrame), 0);
    int3 c1 = int3(texel + int2(0, CrowdbakeKeyFrame(j0 + 1, r, (int)rangeAfter) * (int)rowsPerFrame), 0);
    position = boundsMin + lerp(positionMap.Load(c0).rgb, positionMap.Load(c1).rgb, t) * (boundsMax - boundsMin);
    normal = normalize(lerp(normalMap.Load(c0).rgb, normalMap.Load(c1).rgb, t) * 2.0 - 1.0);
}

// glTF metres round the character -> the imported mesh's object space in Unity's axes.
void CrowdbakeToObject(float3 position, float3 normal, float3 nodeTranslation, float nodeScale, out float3 objectPosition, out float3 objectNormal) {
    float3 local = (position - nodeTranslation) / nodeScale;
    objectPosition = float3(-local.x, local.y, local.z);
    objectNormal = float3(-normal.x, normal.y, normal.z);
}

#ifdef UNITY_COMMON_INCLUDED
// Shader Graph hands textures over as UnityTexture2D; the texture itself is .tex.
void CrowdbakeVat_float(float2 VatUV, float Frame, UnityTexture2D PositionMap, UnityTexture2D NormalMap, float3 BoundsMin, float3 BoundsMax,
                        float RowsPerFrame, float4 Range, float RangeAfter, float3 NodeTranslation, float NodeScale, out float3 Position,
                        out float3 Normal) {
    float3 position, normal;
    CrowdbakeVatSample(VatUV, Frame, PositionMap.tex, NormalMap.tex, BoundsMin, BoundsMax, RowsPerFrame, Range, RangeAfter, position, normal);
    CrowdbakeToObject(position, normal, NodeTranslation, NodeScale, Position, Normal);
}
#endif
