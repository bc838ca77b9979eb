// Reference three.js materials for a crowdbake export (docs/export.md):
//   loadKtx2Texture(url, opts)   a KTX2 file of the export as a three.js data or compressed texture
//   createVatMaterial(opts)      plays the cloth cycle from vertex-animation textures, per instance
//   createImpostorMaterial(opts) the UV-mapped impostor (Dobbyn et al. 2006, section 5), per instance
// Both materials draw InstancedBufferGeometry with two per-instance attributes:
//   iPose vec4: feet position (metres) and heading (radians about +Y; +Z turns to (sin h, 0, cos h))
//   iIds  vec4: mesh: (frame, variation, outfit, -); impostor: (atlas layer, variation, outfit, tile)
// Shading follows crowdview: unlit diffuse times outfit colour by region, Lambert with ambient 0.35,
// no colour-space conversion (set renderer.outputColorSpace = LinearSRGBColorSpace to match it).
import * as THREE from 'three';
import { read } from 'ktx-parse';
import { ZSTDDecoder } from 'three/addons/libs/zstddec.module.js';

// Vulkan format numbers the export writes (crowdbake/export/ktx2.py).
const VK_R8G8B8A8_UNORM = 37;
const VK_R8G8B8A8_SRGB = 43;
const VK_R16G16B16A16_UNORM = 91;
const VK_R32_UINT = 98;
// BC1 (DXT1, no alpha) and BC2 (DXT3) blocks as the bundle stores them; sRGB and UNORM variants are
// uploaded alike (no colour-space conversion, as crowdview does).
const BLOCK_FORMATS = {
  131: THREE.RGB_S3TC_DXT1_Format, 132: THREE.RGB_S3TC_DXT1_Format,
  135: THREE.RGBA_S3TC_DXT3_Format, 136: THREE.RGBA_S3TC_DXT3_Format,
};
export const S3TC_EXTENSION = 'WEBGL_compressed_texture_s3tc';

export const AMBIENT = 0.35;  // runtime/src/config.h CV_AMBIENT
export const MAX_MATERIALS = 4;  // GLSL ES 3.00 indexes sampler arrays only with constants

// A KTX2 file -> DataTexture (layerCount 0) or DataArrayTexture. Integer data (the UV map's uv32 words,
// the 16-bit VATs) is uploaded as unsigned-integer textures and read with texelFetch: WebGL2 has no
// 16-bit normalised textures without an extension, and words must not be filtered. BC1/BC2 files become
// CompressedTexture / CompressedArrayTexture, their blocks uploaded as they are; that needs S3TC
// (opts.renderer, when given, is asked first, so a missing extension is a clear error, not a black crowd).
// opts.headers go with the request (an Authorization header for a private bundle).
const KTX2_SUPERCOMPRESSION_ZSTD = 2;  // the export's levels are zstd-supercompressed (crowdbake/export/ktx2.py)
// three.js's ZSTDDecoder (WebAssembly), started on first use: the promise of it, so that textures loading
// at once all wait for the one init() (a second load decoding before it finished would fail).
let zstdReady = null;

export async function loadKtx2Texture(url, { filter = THREE.NearestFilter, headers = {}, renderer = null } = {}) {
  const response = await fetch(url, { headers });
  if (!response.ok) throw new Error(`${url}: HTTP ${response.status}`);
  const container = read(new Uint8Array(await response.arrayBuffer()));
  if (![0, KTX2_SUPERCOMPRESSION_ZSTD].includes(container.supercompressionScheme) || container.levels.length !== 1) {
    throw new Error(`${url}: expected one level, without supercompression or with zstd`);
  }
  let level = container.levels[0].levelData;
  if (container.supercompressionScheme === KTX2_SUPERCOMPRESSION_ZSTD) {
    zstdReady ??= (async () => {
      const decoder = new ZSTDDecoder();
      await decoder.init();
      return decoder;
    })();
    level = (await zstdReady).decode(level, container.levels[0].uncompressedByteLength);
  }
  const { pixelWidth: width, pixelHeight: height } = container;
  const layers = Math.max(container.layerCount, 1);
  if (container.vkFormat in BLOCK_FORMATS) {
    if (renderer && !renderer.extensions.has(S3TC_EXTENSION)) {
      throw new Error(`${url}: BC${container.vkFormat < 135 ? 1 : 2} blocks need ${S3TC_EXTENSION}, which this browser lacks (export with --ktx2 rgba8)`);
    }
    const format = BLOCK_FORMATS[container.vkFormat];
    const mipmaps = [{ data: new Uint8Array(level.buffer, level.byteOffset, level.byteLength), width, height }];
    const texture = container.layerCount > 0
      ? new THREE.CompressedArrayTexture(mipmaps, width, height, layers, format, THREE.UnsignedByteType)
      : new THREE.CompressedTexture(mipmaps, width, height, format, THREE.UnsignedByteType);
    texture.magFilter = texture.minFilter = filter;
    texture.generateMipmaps = false;
    texture.wrapS = texture.wrapT = filter === THREE.NearestFilter ? THREE.ClampToEdgeWrapping : THREE.RepeatWrapping;
    texture.flipY = false;  // compressed uploads cannot flip; rows are top first, as glTF's v wants
    texture.needsUpdate = true;
    texture.userData.vkFormat = container.vkFormat;
    return texture;
  }
  let data, format, type, internalFormat = null;
  switch (container.vkFormat) {
    case VK_R8G8B8A8_UNORM:
    case VK_R8G8B8A8_SRGB:
      data = new Uint8Array(level.buffer, level.byteOffset, level.byteLength);
      format = THREE.RGBAFormat;
      type = THREE.UnsignedByteType;
      break;
    case VK_R16G16B16A16_UNORM:
      data = new Uint16Array(level.buffer, level.byteOffset, level.byteLength / 2);
      format = THREE.RGBAIntegerFormat;
      type = THREE.UnsignedShortType;
      internalFormat = 'RGBA16UI';
      filter = THREE.NearestFilter;
      break;
    case VK_R32_UINT:
      data = new Uint32Array(level.buffer, level.byteOffset, level.byteLength / 4);
      format = THREE.RedIntegerFormat;
      type = THREE.UnsignedIntType;
      internalFormat = 'R32UI';
      filter = THREE.NearestFilter;
      break;
    default:
      throw new Error(`${url}: vkFormat ${container.vkFormat} is not one crowdbake exports`);
  }
  const texture = container.layerCount > 0
    ? new THREE.DataArrayTexture(data, width, height, layers)
    : new THREE.DataTexture(data, width, height, format, type);
  texture.format = format;
  texture.type = type;
  texture.internalFormat = internalFormat;
  texture.magFilter = filter;
  texture.minFilter = filter;
  texture.generateMipmaps = false;
  texture.wrapS = texture.wrapT = filter === THREE.NearestFilter ? THREE.ClampToEdgeWrapping : THREE.RepeatWrapping;
  texture.flipY = false;  // rows are stored top first and glTF's v grows downwards: no flip
  texture.unpackAlignment = 1;
  texture.needsUpdate = true;
  texture.userData.vkFormat = container.vkFormat;
  return texture;
}

const SHADING = /* glsl */ `
uniform highp sampler2D uOutfits;
uniform vec3 uLightDir;
const float AMBIENT = ${AMBIENT.toFixed(3)};
vec3 shade(vec3 albedo, float alpha, float outfit, vec3 normal) {
  int region = int(alpha * 255.0 / 17.0 + 0.5);  // SPEC.md: alpha = 17 * region code
  if (region != 0) albedo *= texelFetch(uOutfits, ivec2(region, int(outfit)), 0).rgb;
  return albedo * (AMBIENT + (1.0 - AMBIENT) * max(dot(normal, uLightDir), 0.0));
}
mat3 headingMatrix(float h) {
  float c = cos(h), s = sin(h);
  return mat3(c, 0.0, -s, 0.0, 1.0, 0.0, s, 0.0, c);
}
`;

const VAT_VERTEX = /* glsl */ `
precision highp float;
precision highp int;
precision highp usampler2D;
uniform mat4 projectionMatrix;
uniform mat4 viewMatrix;
uniform highp usampler2D uVat;     // vat.texture (RGBA16UI): frames, or a skin's rest pose, joints and weights
uniform highp usampler2D uJoints;  // vat.joints (RGBA16UI): a skin's joint matrices per pose frame
uniform vec3 uBoundsMin;
uniform vec3 uBoundsMax;
uniform int uRowsPerFrame;
uniform bool uSkinned;             // vat.kind == "skin"
uniform int uJointRowsPerFrame;
uniform vec4 uJointMin;
uniform vec4 uJointMax;
uniform int uFirstFrame;  // the clip played: its pose frames (export.json animations[].vat)
uniform int uFrameCount;
in vec2 uv;
in vec2 vatUv;  // glTF TEXCOORD_1: the vertex's VAT texel in block 0
in vec4 iPose;
in vec4 iIds;
out vec2 vUv;
out vec3 vNormal;
flat out vec2 vVariationOutfit;
mat3 headingMatrix(float h) {
  float c = cos(h), s = sin(h);
  return mat3(c, 0.0, -s, 0.0, 1.0, 0.0, s, 0.0, c);
}
vec4 vat(usampler2D map, ivec2 texel) { return vec4(texelFetch(map, texel, 0)) / 65535.0; }
// The octahedral normal word of a texel's alpha (shaders/vat.glsl cb_vat_octahedral).
vec3 octahedral(uint word) {
  vec2 e = vec2(float(word & 255u), float(word >> 8u)) * (2.0 / 255.0) - 1.0;
  vec3 n = vec3(e, 1.0 - abs(e.x) - abs(e.y));
  if (n.z < 0.0) n.xy = (1.0 - abs(e.yx)) * vec2(e.x >= 0.0 ? 1.0 : -1.0, e.y >= 0.0 ? 1.0 : -1.0);
  return normalize(n);
}
vec4 jointRow(int frame, int joint, int row) {
  int width = textureSize(uJoints, 0).x;
  int i = 3 * joint + row;
  return uJointMin + vat(uJoints, ivec2(i % width, frame * uJointRowsPerFrame + i / width)) * (uJointMax - uJointMin);
}
// Linear blend skinning at one pose frame, as crowdview skins (runtime/src/shaders/mesh.vert.glsl).
void skin(vec4 rest, vec3 restNormal, uvec4 joints, vec4 weights, int frame, out vec3 position, out vec3 normal) {
  position = vec3(0.0);
  normal = vec3(0.0);
  for (int k = 0; k < 4; ++k) {
    int j = int(joints[k]);
    vec4 r0 = jointRow(frame, j, 0), r1 = jointRow(frame, j, 1), r2 = jointRow(frame, j, 2);
    position += weights[k] * vec3(dot(r0, rest), dot(r1, rest), dot(r2, rest));
    normal += weights[k] * vec3(dot(r0.xyz, restNormal), dot(r1.xyz, restNormal), dot(r2.xyz, restNormal));
  }
  normal = normalize(normal);
}
void main() {
  ivec2 texel = ivec2(vatUv * vec2(textureSize(uVat, 0)));
  float frame = mod(iIds.x, float(uFrameCount));
  int f0 = int(floor(frame));
  int f1 = (f0 + 1) % uFrameCount;
  float t = frame - float(f0);
  vec3 extent = uBoundsMax - uBoundsMin;
  vec3 position, normal;
  if (uSkinned) {
    uvec4 rest = texelFetch(uVat, texel, 0);
    uvec4 joints = texelFetch(uVat, texel + ivec2(0, uRowsPerFrame), 0);
    vec4 weights = vat(uVat, texel + ivec2(0, 2 * uRowsPerFrame));
    vec4 restPosition = vec4(uBoundsMin + vec3(rest.rgb) / 65535.0 * extent, 1.0);
    vec3 restNormal = octahedral(rest.a), p0, n0, p1, n1;
    skin(restPosition, restNormal, joints, weights, uFirstFrame + f0, p0, n0);
    skin(restPosition, restNormal, joints, weights, uFirstFrame + f1, p1, n1);
    position = mix(p0, p1, t);
    normal = normalize(mix(n0, n1, t));
  } else {
    uvec4 a = texelFetch(uVat, texel + ivec2(0, (uFirstFrame + f0) * uRowsPerFrame), 0);
    uvec4 b = texelFetch(uVat, texel + ivec2(0, (uFirstFrame + f1) * uRowsPerFrame), 0);
    position = uBoundsMin + mix(vec3(a.rgb), vec3(b.rgb), t) / 65535.0 * extent;
    normal = normalize(mix(octahedral(a.a), octahedral(b.a), t));
  }
  mat3 heading = headingMatrix(iPose.w);
  gl_Position = projectionMatrix * viewMatrix * vec4(heading * position + iPose.xyz, 1.0);
  vUv = uv;
  vNormal = heading * normal;
  vVariationOutfit = iIds.yz;
}
`;

const VAT_FRAGMENT = /* glsl */ `
precision highp float;
precision highp int;
precision highp sampler2DArray;
uniform sampler2DArray uDiffuse;
uniform int uVariations;
${SHADING}
in vec2 vUv;
in vec3 vNormal;
flat in vec2 vVariationOutfit;
out vec4 fragColor;
void main() {
  float layer = mod(vVariationOutfit.x, float(uVariations));
  vec3 albedo = texture(uDiffuse, vec3(vUv, layer)).rgb;
  // Region codes are read unfiltered: blending two codes names a third, unrelated region.
  ivec2 size = textureSize(uDiffuse, 0).xy;
  ivec2 texel = clamp(ivec2(fract(vUv) * vec2(size)), ivec2(0), size - 1);
  float alpha = texelFetch(uDiffuse, ivec3(texel, int(layer)), 0).a;
  vec3 normal = normalize(gl_FrontFacing ? vNormal : -vNormal);  // garments show their inside
  fragColor = vec4(shade(albedo, alpha, vVariationOutfit.y, normal), 1.0);
}
`;

// vat: one part's export.json `vat` block; textures: {vat, joints (a skin's), diffuse, outfits} (loadKtx2Texture);
// clip: the looping clip to play, {first_frame, frames} (animations[].vat), every frame when not given.
export function createVatMaterial({ vat, textures, variations, lightDir, doubleSided, clip }) {
  const skinned = vat.kind === 'skin';
  if (skinned && !textures.joints) throw new Error('a skinned part needs its joint matrices (vat.joints)');
  return new THREE.RawShaderMaterial({
    glslVersion: THREE.GLSL3,
    vertexShader: VAT_VERTEX,
    fragmentShader: VAT_FRAGMENT,
    side: doubleSided ? THREE.DoubleSide : THREE.FrontSide,
    uniforms: {
      uVat: { value: textures.vat },
      uJoints: { value: skinned ? textures.joints : textures.vat },  // a frames part never reads it
      uBoundsMin: { value: new THREE.Vector3(...vat.bounds_min) },
      uBoundsMax: { value: new THREE.Vector3(...vat.bounds_max) },
      uRowsPerFrame: { value: vat.rows_per_frame },
      uSkinned: { value: skinned },
      uJointRowsPerFrame: { value: skinned ? vat.joints.rows_per_frame : 1 },
      uJointMin: { value: new THREE.Vector4(...(skinned ? vat.joints.min : [0, 0, 0, 0])) },
      uJointMax: { value: new THREE.Vector4(...(skinned ? vat.joints.max : [1, 1, 1, 1])) },
      uFirstFrame: { value: clip ? clip.first_frame : 0 },
      uFrameCount: { value: clip ? clip.frames : vat.frame_count },
      uDiffuse: { value: textures.diffuse },
      uVariations: { value: variations },
      uOutfits: { value: textures.outfits },
      uLightDir: { value: lightDir.clone().normalize() },
    },
  });
}

const IMPOSTOR_VERTEX = /* glsl */ `
precision highp float;
precision highp int;
uniform mat4 projectionMatrix;
uniform mat4 viewMatrix;
uniform vec3 cameraPosition;
uniform vec3 uCenter;   // bounds centre in the character's frame
uniform float uRadius;
uniform int uAzimuthCount;
uniform ivec4 uCrop;    // export.json impostor.crop: the stored part of every tile
in vec3 position;       // quad corner, x and y in {-1, 1}
in vec4 iPose;
in vec4 iIds;
out vec2 vTileUv;
flat out ivec3 vTile;
flat out float vHeading;
flat out vec2 vVariationOutfit;
mat3 headingMatrix(float h) {
  float c = cos(h), s = sin(h);
  return mat3(c, 0.0, -s, 0.0, 1.0, 0.0, s, 0.0, c);
}
void main() {
  // A camera-facing quad of 2 * radius metres around the bounds centre, framed like the bake's
  // orthographic views (SPEC.md "Impostor maps"): right = up x to_camera, +Y up.
  mat3 heading = headingMatrix(iPose.w);
  vec3 center = iPose.xyz + heading * uCenter;
  vec3 toCamera = normalize(cameraPosition - center);
  vec3 side = cross(vec3(0.0, 1.0, 0.0), toCamera);
  vec3 right = length(side) > 1e-4 ? normalize(side) : heading * vec3(1.0, 0.0, 0.0);
  vec3 up = cross(toCamera, right);
  gl_Position = projectionMatrix * viewMatrix * vec4(center + (position.x * right + position.y * up) * uRadius, 1.0);
  vTileUv = vec2(0.5 + 0.5 * position.x, 0.5 - 0.5 * position.y);
  int tile = int(iIds.w + 0.5);
  // Where tile texel (0, 0) would lie: the cell's origin less the crop's corner.
  vTile = ivec3((tile % uAzimuthCount) * uCrop.z - uCrop.x, (tile / uAzimuthCount) * uCrop.w - uCrop.y, int(iIds.x + 0.5));
  vHeading = iPose.w;
  vVariationOutfit = iIds.yz;
}
`;

const IMPOSTOR_FRAGMENT = /* glsl */ `
precision highp float;
precision highp int;
precision highp usampler2DArray;
precision highp sampler2DArray;
uniform usampler2DArray uUvMap;     // uv32 words (R32UI)
uniform sampler2DArray uNormalMap;
uniform sampler2DArray uDiffuse0, uDiffuse1, uDiffuse2, uDiffuse3;
uniform int uVariations[${MAX_MATERIALS}];
uniform int uMaterialCount;
uniform int uTileSize;
uniform ivec4 uCrop;
${SHADING}
in vec2 vTileUv;
flat in ivec3 vTile;
flat in float vHeading;
flat in vec2 vVariationOutfit;
out vec4 fragColor;
#define SAMPLE_MATERIAL(m, sampler)                                                   \\
  if (uMaterialCount > m && material == m) {                                          \\
    float layer = mod(vVariationOutfit.x, float(uVariations[m]));                     \\
    albedo = textureLod(sampler, vec3(uv, layer), 0.0).rgb;                           \\
    ivec2 size = textureSize(sampler, 0).xy;                                          \\
    ivec2 t = clamp(ivec2(uv * vec2(size)), ivec2(0), size - 1);                      \\
    alpha = texelFetch(sampler, ivec3(t, int(layer)), 0).a;                           \\
  }
void main() {
  ivec2 inTile = clamp(ivec2(vTileUv * float(uTileSize)), ivec2(0), ivec2(uTileSize - 1));
  if (any(lessThan(inTile, uCrop.xy)) || any(greaterThanEqual(inTile, uCrop.xy + uCrop.zw))) discard;  // outside the crop
  ivec2 texel = vTile.xy + inTile;
  uint word = texelFetch(uUvMap, ivec3(texel, vTile.z), 0).r;
  if ((word >> 31u) == 0u) discard;  // coverage: outside the character
  vec2 uv = vec2(float(word & 0x3FFFu), float((word >> 14u) & 0x3FFFu)) / 16383.0;
  int material = int((word >> 28u) & 7u);
  vec3 albedo = vec3(1.0, 0.0, 1.0);  // magenta: a material this page cannot address
  float alpha = 0.0;
  SAMPLE_MATERIAL(0, uDiffuse0)
  SAMPLE_MATERIAL(1, uDiffuse1)
  SAMPLE_MATERIAL(2, uDiffuse2)
  SAMPLE_MATERIAL(3, uDiffuse3)
  vec3 modelNormal = texelFetch(uNormalMap, ivec3(texel, vTile.z), 0).rgb * 2.0 - 1.0;
  vec3 normal = normalize(headingMatrix(vHeading) * modelNormal);
  fragColor = vec4(shade(albedo, alpha, vVariationOutfit.y, normal), 1.0);
}
`;

// export.json impostor.crop as GLSL ivec4 components (the whole tile where an export has none).
function impostorCrop(impostor) {
  const crop = impostor.crop ?? { x: 0, y: 0, width: impostor.tile_size, height: impostor.tile_size };
  return [crop.x, crop.y, crop.width, crop.height];
}

// impostor: export.json `impostor`; textures: {uv, normal, outfits, diffuse: [per material]}.
export function createImpostorMaterial({ impostor, textures, variations, lightDir }) {
  if (textures.uv.userData.vkFormat !== VK_R32_UINT) throw new Error('this material reads uv32 UV maps (R32_UINT)');
  if (textures.diffuse.length > MAX_MATERIALS) throw new Error(`at most ${MAX_MATERIALS} materials`);
  const diffuse = [0, 1, 2, 3].map((m) => textures.diffuse[Math.min(m, textures.diffuse.length - 1)]);
  return new THREE.RawShaderMaterial({
    glslVersion: THREE.GLSL3,
    vertexShader: IMPOSTOR_VERTEX,
    fragmentShader: IMPOSTOR_FRAGMENT,
    uniforms: {
      uCenter: { value: new THREE.Vector3(...impostor.bounds.center) },
      uRadius: { value: impostor.bounds.radius },
      uTileSize: { value: impostor.tile_size },
      uCrop: { value: impostorCrop(impostor) },
      uAzimuthCount: { value: impostor.azimuths_deg.length },
      uUvMap: { value: textures.uv },
      uNormalMap: { value: textures.normal },
      uDiffuse0: { value: diffuse[0] },
      uDiffuse1: { value: diffuse[1] },
      uDiffuse2: { value: diffuse[2] },
      uDiffuse3: { value: diffuse[3] },
      uVariations: { value: [0, 1, 2, 3].map((m) => variations[Math.min(m, variations.length - 1)]) },
      uMaterialCount: { value: textures.diffuse.length },
      uOutfits: { value: textures.outfits },
      uLightDir: { value: lightDir.clone().normalize() },
    },
  });
}
