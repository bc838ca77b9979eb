// crowdbake export: the code of an Unreal material function's Custom node (docs/export.md "Unreal") that
// plays a vertex-animation texture (VAT). Paste the lines below the marker into the Custom node's Code.
// Custom node: Output Type CMOT Float 3 (the World Position Offset); Inputs: VatUV (TexCoord[1]), Frame,
// PositionMap, NormalMap (Texture Objects), BoundsMin, BoundsMax, RowsPerFrame, FrameCount, LocalPosition
// (Local Position, in the VAT's units: the importer's centimetres divided by 100); Additional Output
// Normal (CMOT Float 3). Values from export.json (lods[].parts[].vat). Unreal is Z-up and centimetres:
// glTF's (x, y, z) metres are (x, -z, y) * 100 there, as the importer turns the mesh.
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
Normal = float3(n.x, -n.z, n.y);
return float3(p.x, -p.z, p.y) * 100.0 - LocalPosition;
