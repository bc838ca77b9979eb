// crowdbake export: play a vertex-animation texture (VAT) in an HLSL vertex shader (SM 4.0+).
// Values come from export.json (lods[].parts[].vat) or the glTF mesh's extras.crowdbake.vat.
// Bind every VAT as DXGI_FORMAT_R16G16B16A16_UNORM (the KTX2s' vkFormat): Load returns 0..1.
// vat.kind "frames": CbVatTexture holds per pose frame each vertex's position (rgb) and octahedral normal (a).
// vat.kind "skin": CbVatTexture holds per vertex its rest position and normal, four joints and four weights,
// CbVatJoints per pose frame each joint's 3 x 4 matrix (vat.glsl says more).

Texture2D<float4> CbVatTexture;  // vat.texture
Texture2D<float4> CbVatJoints;   // vat.joints (a skin's)

cbuffer CbVat {
    float3 CbVatBoundsMin;          // vat.bounds_min
    int CbVatRowsPerFrame;          // vat.rows_per_frame
    float3 CbVatBoundsMax;          // vat.bounds_max
    int CbVatSkinned;               // 1 where vat.kind is "skin"
    float4 CbVatJointMin;           // vat.joints.min
    float4 CbVatJointMax;           // vat.joints.max
    int CbVatJointRowsPerFrame;     // vat.joints.rows_per_frame
    int CbVatRangeFirst;            // the animation played (export.json animations[].vat): first_frame
    int CbVatRangeFrames;           // frames
    int CbVatRangeLoop;             // loop: 1 wraps (a clip), 0 plays once (a transition)
    int CbVatRangeBefore;           // before_frame: a transition's key 0, the from clip's leave pose
    int CbVatRangeAfter;            // after_frame: the pose after the range's last frame
};

// The pose frame of key j (vat.glsl's cb_vat_key_frame).
int CbVatKeyFrame(int j) {
    if (CbVatRangeLoop != 0) return j < CbVatRangeFrames ? CbVatRangeFirst + j : CbVatRangeAfter;
    if (j <= 0) return CbVatRangeBefore;
    if (j > CbVatRangeFrames) return CbVatRangeAfter;
    return CbVatRangeFirst + j - 1;
}

// A normal's octahedral word (vat.glsl's cb_vat_octahedral).
float3 CbVatOctahedral(float a) {
    float word = floor(a * 65535.0 + 0.5);
    float2 e = float2(fmod(word, 256.0), floor(word / 256.0)) * (2.0 / 255.0) - 1.0;
    float3 n = float3(e, 1.0 - abs(e.x) - abs(e.y));
    if (n.z < 0.0) n.xy = (1.0 - abs(e.yx)) * float2(e.x >= 0.0 ? 1.0 : -1.0, e.y >= 0.0 ? 1.0 : -1.0);
    return normalize(n);
}

// Row `row` of joint `joint`'s matrix at pose frame `frame` (vat.glsl's cb_vat_joint_row).
float4 CbVatJointRow(int frame, int joint, int row) {
    uint width, height;
    CbVatJoints.GetDimensions(width, height);
    int i = 3 * joint + row;
    float4 q = CbVatJoints.Load(int3(i % (int)width, frame * CbVatJointRowsPerFrame + i / (int)width, 0));
    return CbVatJointMin + q * (CbVatJointMax - CbVatJointMin);
}

// Linear blend skinning at one pose frame (vat.glsl's cb_vat_skin), the normal normalised.
void CbVatSkin(float4 rest, float3 restNormal, int4 joints, float4 weights, int frame, out float3 position, out float3 normal) {
    position = 0;
    normal = 0;
    for (int k = 0; k < 4; ++k) {
        float4 r0 = CbVatJointRow(frame, joints[k], 0), r1 = CbVatJointRow(frame, joints[k], 1), r2 = CbVatJointRow(frame, joints[k], 2);
        position += weights[k] * float3(dot(r0, rest), dot(r1, rest), dot(r2, rest));
        normal += weights[k] * float3(dot(r0.xyz, restNormal), dot(r1.xyz, restNormal), dot(r2.xyz, restNormal));
    }
    normal = normalize(normal);
}

// vatUV: the vertex's TEXCOORD_1; frame: seconds into the animation times fps, any real number (a clip
// wraps, a transition holds its ends; the nearest two keys blend).
void CbVatSample(float2 vatUV, float frame, out float3 position, out float3 normal) {
    uint width, height;
    CbVatTexture.GetDimensions(width, height);
    int2 texel = int2(vatUV * float2(width, height));
    float n = (float)CbVatRangeFrames;
    bool loop = CbVatRangeLoop != 0;
    float x = loop ? frame - n * floor(frame / n) : clamp(frame, 0.0, n + 1.0);
    int j0 = min((int)floor(x), loop ? CbVatRangeFrames - 1 : CbVatRangeFrames);
    float t = x - j0;
    int f0 = CbVatKeyFrame(j0), f1 = CbVatKeyFrame(j0 + 1);
    float3 extent = CbVatBoundsMax - CbVatBoundsMin;
    if (CbVatSkinned != 0) {
        float4 rest = CbVatTexture.Load(int3(texel, 0));
        int4 joints = int4(CbVatTexture.Load(int3(texel + int2(0, CbVatRowsPerFrame), 0)) * 65535.0 + 0.5);
        float4 weights = CbVatTexture.Load(int3(texel + int2(0, 2 * CbVatRowsPerFrame), 0));
        float4 restPosition = float4(CbVatBoundsMin + rest.rgb * extent, 1.0);
        float3 restNormal = CbVatOctahedral(rest.a), p0, n0, p1, n1;
        CbVatSkin(restPosition, restNormal, joints, weights, f0, p0, n0);
        CbVatSkin(restPosition, restNormal, joints, weights, f1, p1, n1);
        position = lerp(p0, p1, t);
        normal = normalize(lerp(n0, n1, t));
    } else {
        float4 a = CbVatTexture.Load(int3(texel + int2(0, f0 * CbVatRowsPerFrame), 0));
        float4 b = CbVatTexture.Load(int3(texel + int2(0, f1 * CbVatRowsPerFrame), 0));
        position = CbVatBoundsMin + lerp(a.rgb, b.rgb, t) * extent;
        normal = normalize(lerp(CbVatOctahedral(a.a), CbVatOctahedral(b.a), t));
    }
}
