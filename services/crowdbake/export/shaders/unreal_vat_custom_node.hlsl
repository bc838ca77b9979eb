// crowdbake export: the code of an Unreal material function's Custom node (docs/export.md "Unreal") that
// plays a vertex-animation texture (VAT). Paste the lines below the marker into the Custom node's Code.
// Custom node: Output Type CMOT Float 3; Inputs: VatUV (TexCoord[1]), Frame (seconds into the animation * fps),
// VatMap, JointMap (Texture Objects), BoundsMin, BoundsMax, RowsPerFrame, Skinned (1 for a skin), JointRowsPerFrame,
// JointMin, JointMax, Range (float4: first_frame, frames, loop, before_frame), RangeAfter (after_frame),
// NodeTranslation, NodeScale, LocalPosition (the Local Position node); Additional Output Normal (CMOT Float 3,
// local). Values from export.json: lods[].parts[].vat (vat.joints for the Joint* inputs of a skin) and .node,
// and animations[].vat (the clip or transition played: a clip wraps, a transition holds its ends). A Custom
// node has no functions, so the key lookup and the two frames' decode (shaders/vat.glsl's, with its
// octahedral normal and skinning) are written out in a loop. It returns the offset in the mesh's local space:
// pass it through a Transform Vector node (Local to World) into World Position Offset. Unreal is Z-up,
// left-handed, centimetres: the glTF importer turns glTF's (x, y, z) into (x, z, y) * 100, and so does this.
// ---- Custom node code ----
uint width, height, jointWidth, jointHeight;
VatMap.GetDimensions(width, height);
JointMap.GetDimensions(jointWidth, jointHeight);
int2 texel = int2(VatUV * float2(width, height));
int4 r = int4(Range);
int after = (int)RangeAfter;
int rows = (int)RowsPerFrame;
float n = Range.y;
bool loop = r.z != 0;
float x = loop ? Frame - n * floor(Frame / n) : clamp(Frame, 0.0, n + 1.0);
int j0 = min((int)floor(x), loop ? r.y - 1 : r.y);
float t = x - j0;
float3 extent = BoundsMax - BoundsMin;
float4 rest = VatMap.Load(int3(texel, 0));
int4 joints = int4(VatMap.Load(int3(texel + int2(0, rows), 0)) * 65535.0 + 0.5);
float4 weights = VatMap.Load(int3(texel + int2(0, 2 * rows), 0));
float3 p[2], m[2];
for (int s = 0; s < 2; ++s) {
    // Pose frame of key j0 + s: a transition's key 0 is before_frame, key frames + 1 after_frame.
    int j = j0 + s;
    int f = loop ? (j < r.y ? r.x + j : after) : (j <= 0 ? r.w : (j > r.y ? after : r.x + j - 1));
    float4 a = Skinned > 0.5 ? rest : VatMap.Load(int3(texel + int2(0, f * rows), 0));
    float word = floor(a.a * 65535.0 + 0.5);  // the octahedral normal: u = word % 256, v = word / 256
    float2 e = float2(fmod(word, 256.0), floor(word / 256.0)) * (2.0 / 255.0) - 1.0;
    float3 o = float3(e, 1.0 - abs(e.x) - abs(e.y));
    if (o.z < 0.0) o.xy = (1.0 - abs(e.yx)) * float2(e.x >= 0.0 ? 1.0 : -1.0, e.y >= 0.0 ? 1.0 : -1.0);
    p[s] = BoundsMin + a.rgb * extent;
    m[s] = normalize(o);
    if (Skinned > 0.5) {  // the rest vertex skinned by its four joints at frame f
        float4 restPosition = float4(p[s], 1.0);
        float3 restNormal = m[s];
        p[s] = 0;
        m[s] = 0;
        for (int k = 0; k < 4; ++k) {
            float4 row[3];
            for (int q = 0; q < 3; ++q) {
                int i = 3 * joints[k] + q;
                row[q] = JointMin + JointMap.Load(int3(i % (int)jointWidth, f * (int)JointRowsPerFrame + i / (int)jointWidth, 0)) * (JointMax - JointMin);
            }
            p[s] += weights[k] * float3(dot(row[0], restPosition), dot(row[1], restPosition), dot(row[2], restPosition));
            m[s] += weights[k] * float3(dot(row[0].xyz, restNormal), dot(row[1].xyz, restNormal), dot(row[2].xyz, restNormal));
        }
        m[s] = normalize(m[s]);
    }
}
float3 position = lerp(p[0], p[1], t);
float3 normal = normalize(lerp(m[0], m[1], t));
float3 local = (position - NodeTranslation) / NodeScale;  // the quantized mesh's own units (its node's transform undone)
Normal = float3(normal.x, normal.z, normal.y);
return float3(local.x, local.z, local.y) * 100.0 - LocalPosition;
