// crowdbake export: the code of an Unreal material function's Custom node (docs/export.md "Unreal") that
// plays a vertex-animation texture (VAT). Paste the lines below the marker into the Custom node's Code.
// Custom node: Output Type CMOT Float 3; Inputs: VatUV (TexCoord[1]), Frame, PositionMap, NormalMap (Texture
// Objects), BoundsMin, BoundsMax, RowsPerFrame, FrameCount, NodeTranslation, NodeScale, LocalPosition (the
// Local Position node); Additional Output Normal (CMOT Float 3, local). Values from export.json:
// lods[].parts[].vat and .node. It returns the offset in the mesh's local space: pass it through a Transform
// Vector node (Local to World) into World Position Offset. Unreal is Z-up, left-handed, centimetres: the glTF
// importer turns glTF's (x, y, z) into (x, z, y) * 100, and so does this.
// ---- Custom node code ----
uint width, height;
PositionMap.GetDimensions(width, height);
int2 texel = int2(VatUV * float2(width, height));
float wrapped = Frame - FrameCount * floor(Frame / FrameCount);
int f0 = (int)floor(wrapped);
int f1 = (f0 + 1) % (int)FrameCount;
float t = wrapped - f0;
int3 c0 = int3(texel + int2(0, f0 * (int)RowsPerFrame), 0);
int3 c1 = int3(texel + int2(0, f1 * (int)RowsPerFrame), 0);
float3 p = BoundsMin + lerp(PositionMap.Load(c0).rgb, PositionMap.Load(c1).rgb, t) * (BoundsMax - BoundsMin);
float3 n = normalize(lerp(NormalMap.Load(c0).rgb, NormalMap.Load(c1).rgb, t) * 2.0 - 1.0);
float3 local = (p - NodeTranslation) / NodeScale;  // the quantized mesh's own units (its node's transform undone)
Normal = float3(n.x, n.z, n.y);
return float3(local.x, local.z, local.y) * 100.0 - LocalPosition;
