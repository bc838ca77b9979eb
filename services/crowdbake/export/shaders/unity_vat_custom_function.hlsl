// crowdbake export: a Shader Graph Custom Function (Unity URP/HDRP, docs/export.md "Unity") that plays a
// vertex-animation texture (VAT). Custom Function node: Type File, this file, Name CrowdbakeVat, precision
// Float. Inputs: VatUV (Vector 2, UV1 = glTF TEXCOORD_1), Frame (Float: seconds into the animation * fps),
// VatMap, JointMap (Texture 2D), BoundsMin, BoundsMax (Vector 3), RowsPerFrame (Float), Skinned (Float: 1 for
// a skin), JointRowsPerFrame (Float), JointMin, JointMax (Vector 4), Range (Vector 4: first_frame, frames, loop,
// before_frame), RangeAfter (Float: after_frame), NodeTranslation (Vector 3), NodeScale (Float). Outputs:
// Position, Normal (Vector 3, object space) into the Vertex stage's Position and Normal. Values from
// export.json: lods[].parts[].vat (vat.joints for the Joint* inputs of a skin), lods[].parts[].node (the
// quantized mesh's node transform) and animations[].vat (the clip or transition played: its range of pose
// frames). glTFast turns glTF's right-handed axes into Unity's left-handed ones by negating x; so does this.

// The pose frame of key j of the range (first, frames, loop, before) then after (vat.glsl's cb_vat_key_frame).
int CrowdbakeKeyFrame(int j, int4 range, int after) {
    if (range.z != 0) return j < range.y ? range.x + j : after;
    if (j <= 0) return range.w;
    if (j > range.y) return after;
    return range.x + j - 1;
}

// A normal's octahedral word (vat.glsl's cb_vat_octahedral).
float3 CrowdbakeOctahedral(float a) {
    float word = floor(a * 65535.0 + 0.5);
    float2 e = float2(fmod(word, 256.0), floor(word / 256.0)) * (2.0 / 255.0) - 1.0;
    float3 n = float3(e, 1.0 - abs(e.x) - abs(e.y));
    if (n.z < 0.0) n.xy = (1.0 - abs(e.yx)) * float2(e.x >= 0.0 ? 1.0 : -1.0, e.y >= 0.0 ? 1.0 : -1.0);
    return normalize(n);
}

// Linear blend skinning at one pose frame (vat.glsl's cb_vat_skin), the normal normalised.
void CrowdbakeSkin(Texture2D<float4> jointMap, int jointRows, float4 jointMin, float4 jointMax, float4 rest, float3 restNormal, int4 joints,
                   float4 weights, int frame, out float3 position, out float3 normal) {
    uint width, height;
    jointMap.GetDimensions(width, height);
    position = 0;
    normal = 0;
    for (int k = 0; k < 4; ++k) {
        float4 rows[3];
        for (int r = 0; r < 3; ++r) {
            int i = 3 * joints[k] + r;
            rows[r] = jointMin + jointMap.Load(int3(i % (int)width, frame * jointRows + i / (int)width, 0)) * (jointMax - jointMin);
        }
        position += weights[k] * float3(dot(rows[0], rest), dot(rows[1], rest), dot(rows[2], rest));
        normal += weights[k] * float3(dot(rows[0].xyz, restNormal), dot(rows[1].xyz, restNormal), dot(rows[2].xyz, restNormal));
    }
    normal = normalize(normal);
}

// The sampling itself, on plain HLSL textures (what the test compiles). A clip wraps, a transition holds its ends.
void CrowdbakeVatSample(float2 vatUV, float frame, Texture2D<float4> vatMap, Texture2D<float4> jointMap, float3 boundsMin, float3 boundsMax,
                        float rowsPerFrame, float skinned, float jointRowsPerFrame, float4 jointMin, float4 jointMax, float4 range,
                        float rangeAfter, out float3 position, out float3 normal) {
    uint width, height;
    vatMap.GetDimensions(width, height);
    int2 texel = int2(vatUV * float2(width, height));
    int4 r = int4(range);
    int rows = (int)rowsPerFrame;
    float n = range.y;
    bool loop = r.z != 0;
    float x = loop ? frame - n * floor(frame / n) : clamp(frame, 0.0, n + 1.0);
    int j0 = min((int)floor(x), loop ? r.y - 1 : r.y);
    float t = x - j0;
    int f0 = CrowdbakeKeyFrame(j0, r, (int)rangeAfter), f1 = CrowdbakeKeyFrame(j0 + 1, r, (int)rangeAfter);
    float3 extent = boundsMax - boundsMin;
    if (skinned > 0.5) {
        float4 rest = vatMap.Load(int3(texel, 0));
        int4 joints = int4(vatMap.Load(int3(texel + int2(0, rows), 0)) * 65535.0 + 0.5);
        float4 weights = vatMap.Load(int3(texel + int2(0, 2 * rows), 0));
        float4 restPosition = float4(boundsMin + rest.rgb * extent, 1.0);
        float3 restNormal = CrowdbakeOctahedral(rest.a), p0, n0, p1, n1;
        CrowdbakeSkin(jointMap, (int)jointRowsPerFrame, jointMin, jointMax, restPosition, restNormal, joints, weights, f0, p0, n0);
        CrowdbakeSkin(jointMap, (int)jointRowsPerFrame, jointMin, jointMax, restPosition, restNormal, joints, weights, f1, p1, n1);
        position = lerp(p0, p1, t);
        normal = normalize(lerp(n0, n1, t));
    } else {
        float4 a = vatMap.Load(int3(texel + int2(0, f0 * rows), 0));
        float4 b = vatMap.Load(int3(texel + int2(0, f1 * rows), 0));
        position = boundsMin + lerp(a.rgb, b.rgb, t) * extent;
        normal = normalize(lerp(CrowdbakeOctahedral(a.a), CrowdbakeOctahedral(b.a), t));
    }
}

// glTF metres round the character -> the imported mesh's object space in Unity's axes.
void CrowdbakeToObject(float3 position, float3 normal, float3 nodeTranslation, float nodeScale, out float3 objectPosition, out float3 objectNormal) {
    float3 local = (position - nodeTranslation) / nodeScale;
    objectPosition = float3(-local.x, local.y, local.z);
    objectNormal = float3(-normal.x, normal.y, normal.z);
}

#ifdef UNITY_COMMON_INCLUDED
// Shader Graph hands textures over as UnityTexture2D; the texture itself is .tex.
void CrowdbakeVat_float(float2 VatUV, float Frame, UnityTexture2D VatMap, UnityTexture2D JointMap, float3 BoundsMin, float3 BoundsMax,
                        float RowsPerFrame, float Skinned, float JointRowsPerFrame, float4 JointMin, float4 JointMax, float4 Range, float RangeAfter,
                        float3 NodeTranslation, float NodeScale, out float3 Position, out float3 Normal) {
    float3 position, normal;
    CrowdbakeVatSample(VatUV, Frame, VatMap.tex, JointMap.tex, BoundsMin, BoundsMax, RowsPerFrame, Skinned, JointRowsPerFrame, JointMin, JointMax,
                       Range, RangeAfter, position, normal);
    CrowdbakeToObject(position, normal, NodeTranslation, NodeScale, Position, Normal);
}
#endif
