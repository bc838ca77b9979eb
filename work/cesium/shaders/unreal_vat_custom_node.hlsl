// crowdbake export: the code of an Unreal material function's Custom node (docs/export.md "Unreal") that
// plays a vertex-animation texture (VAT). Paste the lines below the marker into the Custom node's Code.
// Custom node: Output Type CMOT Float 3; Inputs: VatUV (TexCoord[1]), Frame (seconds into the animation * fps),
// PositionMap, NormalMap (Texture Objects), BoundsMin, BoundsMax, RowsPerFrame, Range (float4: first_frame,
// frames, loop, before_frame), RangeAfter (after_frame), NodeTranslation, NodeScale, LocalPosition (the Local
// Position node); Additional Output Normal (CMOT Float 3, local). Values from export.json: lods[].parts[].vat
// and .node, and animations[].vat (the clip or transition played: a clip wraps, a transition holds its
// ends; a Custom node has no functions, so the key lookup is written out twice). It returns the offset in the mesh's local space: pass it through a Transform
// Vector node (Local to World) into World Position Offset. Unreal is Z-up, left-handed, centimetres: the glTF
// importer turns glTF's (x, y, z) into (x, z, y) * 100, and so does this.
// ---- Custom node code ----
uint width, height;
PositionMap.GetDimensions(width, height);
int2 texel = int2(VatUV * float2(width, height));
int4 r = int4(Range);
int after = (int)RangeAfter;
float n = Range.y;
bool loop = r.z != 0;
float x = loop ? Frame - n * floor(Frame / n) : clamp(Frame, 0.0, n + 1.0);
int j0 = min((int)floor(x), loop ? r.y - 1 : r.y);
int j1 = j0 + 1;
float t = x - j0;
// Pose frames of keys j0 and j1: a transition's key 0 is before_frame, key frames + 1 after_frame.
int f0 = loop ? (j0 < r.y ? r.x + j0 : after) : (j0 <= 0 ? r.w : (j0 > r.y ? after : r.x + j0 - 1));
int f1 = loop ? (j1 < r.y ? r.x + j1 : after) : (j1 <= 0 ? r.w : (j1 > r.y ? after : r.x + j1 - 1));
int3 c0 = int3(texel + int2(0, f0 * (int)RowsPerFrame), 0);
int3 c1 = int3(texel + int2(0, f1 * (int)RowsPerFrame), 0);
float3 p = BoundsMin + lerp(PositionMap.Load(c0).rgb, PositionMap.Load(c1).rgb, t) * (BoundsMax - BoundsMin);
float3 m = normalize(lerp(NormalMap.Load(c0).rgb, NormalMap.Load(c1).rgb, t) * 2.0 - 1.0);
float3 local = (p - NodeTranslation) / NodeScale;  // the quantized mesh's own units (its node's transform undone)
Normal = float3(m.x, m.z, m.y);
return float3(local.x, local.z, local.y) * 100.0 - LocalPosition;
