"""`export_bundle`: a verified bundle folder -> engine-ready files (layout in docs/export.md).

    OUT/export.json                     the sidecar: every file below and how to read it
    OUT/character_lod<k>.glb            glTF 2.0 per LOD: parts, materials, an animation per clip and transition, VAT extras
    OUT/looks/<material>_look_<k>.<png|jpg>             the glTF variants' base colours, shared by the LODs
    OUT/vat/<part>_lod<k>.<frames|skin>.<ktx2|png>, vat/<part>.joints.<ktx2|png>   vertex-animation textures (16-bit)
    OUT/textures/<material>_diffuse.ktx2, outfits.ktx2   diffuse variations (array), outfit colours
    OUT/impostor/<normal|uv|detail|surface>.ktx2         impostor atlases, one layer per baked frame
    OUT/shaders/*.glsl, *.hlsl, *.gdshader               reference shaders for engines
    OUT/engines/*.gd, *.cs, *.py                         Godot, Unity and Unreal scripts that set an engine up from export.json

The heavy lifting is in pure modules (vat, glb, ktx2, textures); this one reads the bundle, calls them
and writes the files.
"""
from __future__ import annotations

import io
import json
import logging
import math
import shutil
import tempfile
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any, Callable

import cv2
import numpy as np
from PIL import Image

from crowdbake import __version__
from crowdbake.bake.atlas import AtlasLayout
from crowdbake.export import ktx2
from crowdbake.export.animations import AnimationPlan, animation_plans, sidecar_animations
from crowdbake.bake.shading import apply_outfit
from crowdbake.export.body_skin import GltfSkin, gltf_skin, morph_bytes, play, skin_bytes, why_not_a_skin
from crowdbake.export.cloth_bones import DEFAULT_ITERATIONS, ClothBones, choose_bone_count, decompose_cloth
from crowdbake.export.glb import GlbMaterial, GlbPart, GlbVariant, build_glb, node_transform
from crowdbake.export.textures import (KTX2_MODES, NOTHING_PREPARED, PreparedLayers, colour_ktx2, covered_texels, model_space_normal_ktx2, over_half_covered,
                                        region_codes_used, rgba8_layers, uv_map_layers)
from crowdbake.export import vat
from crowdbake.formats.bundle import Bundle, verify_bundle
from crowdbake.formats.skinned_cache import SkinnedPoseCache

logger = logging.getLogger(__name__)

EXPORT_FORMAT = "crowdbake-export"
# 5: one VAT file a part (positions with octahedral normals in A), skinned bodies as a skin texture and joint matrices,
# a coarser LOD reading a finer LOD's texels where its vertices are that LOD's;
# 4: one glTF animation per clip and per transition, listed in `animations`; 3: KTX2 levels zstd-supercompressed, 8-bit VAT normals, VAT PNGs only when asked, quantized glTF meshes,
# the looks in looks/; 2: colour and normal maps keep the bundle's BC1/BC2 blocks; 1 decoded them to RGBA8.
EXPORT_FORMAT_VERSION = 5
# crowdview's defaults (runtime/src/main.cpp, crowd.h LodRule), so the sidecar's switch distance is
# the one crowdview uses for a window of this height.
REFERENCE_VIEWPORT_HEIGHT_PX = 720
REFERENCE_FOV_Y_DEG = 45.0
LOW_MESH_FRACTION = 0.5
LOD_HYSTERESIS = 0.05
# glTF variants (KHR_materials_variants): at most this many looks, each a base-colour image per material,
# a PNG (lossless or 256 colours) or a JPEG (look_image; 0.05-0.15 MB for a 1024² look), in looks/ beside the .glb files.
MAX_VARIANTS = 16
LOOKS_FOLDER = "looks"
LOOK_JPEG_QUALITY = 90
LOOK_PNG_LEVEL = 6  # zlib's default: level 9 saves about 1 % on the sample's looks, for twice the time


@dataclass(frozen=True)
class ClothBonesRequest:
    """--cloth-bones: each garment as a skinned mesh of `count` bones, or (count None) of the fewest bones of
    cloth_bones.AUTO_BONE_COUNTS whose RMS error against the loop is within budget_mm."""

    count: int | None = None
    budget_mm: float = 5.0
    iterations: int = DEFAULT_ITERATIONS
    # One line per decomposition (a garment's chosen count and, in auto mode, each count tried): a garment
    # can take minutes, so the CLI prints them as they come. None: logged at INFO.
    report: Callable[[str], None] | None = None

    def decompose(self, positions: np.ndarray, triangles: np.ndarray, label: str) -> ClothBones:
        """The garment `label` (named in the report lines) decomposed as asked."""
        if self.count is not None:
            bones = decompose_cloth(positions, triangles, min(self.count, positions.shape[1]), self.iterations)
        else:
            def tried(candidate: ClothBones) -> None:
                self._say(f"{label}: tried {candidate.bone_count} bones, {candidate.rms_m * 1000:.2f} mm RMS "
                          f"(budget {self.budget_mm:g} mm)")

            bones = choose_bone_count(positions, triangles, self.budget_mm, iterations=self.iterations, on_try=tried)
            if bones.rms_m * 1000 > self.budget_mm:  # written all the same: the most bones tried, said in export.json
                logger.warning("--cloth-bones auto: %d bones leave %.1f mm RMS, over the %.1f mm budget", bones.bone_count, bones.rms_m * 1000, self.budget_mm)
        self._say(f"{label}: {bones.bone_count} bones, {bones.rms_m * 1000:.2f} mm RMS, {bones.max_m * 1000:.1f} mm max")
        return bones

    def _say(self, line: str) -> None:
        if self.report is not None:
            self.report(line)
        else:
            logger.info("%s", line)


def bones_entry(bones: ClothBones, request: ClothBonesRequest, vertex_count: int, key_count: int) -> dict[str, Any]:
    """export.json's `bones` block of a garment: the count, its error against the pose frames and its bytes in
    the .glb (JOINTS_0 and WEIGHTS_0, and per bone and key of every animation a rotation and a translation)."""
    skin_bytes = vertex_count * (8 + 16) + bones.bone_count * key_count * (8 + 12)  # snorm16 rotation, float translation
    return {"count": bones.bone_count, "asked": request.count if request.count is not None else "auto",
            **({"budget_mm": request.budget_mm} if request.count is None else {}), "iterations": bones.iterations,
            "rms_mm": round(bones.rms_m * 1000, 3), "max_mm": round(bones.max_m * 1000, 3), "bytes": skin_bytes}


def skin_entry(skin: GltfSkin, cache: SkinnedPoseCache, key_count: int) -> dict[str, Any]:
    """export.json's `skin` block of a body played as a glTF skin: its joints, the pose frames that carry a
    corrective target, its largest distance from the bundle's frames (metres -> mm) and its bytes in the .glb
    (body_skin.skin_bytes)."""
    played = play(skin, np.arange(cache.frame_count))
    max_mm = float(np.linalg.norm(played - cache.positions, axis=-1).max() * 1000)
    return {"joints": skin.joint_count, "animated_joints": int(skin.animated.size), "corrective_frames": skin.corrected.tolist(),
            "max_mm": round(max_mm, 4), "bytes": skin_bytes(skin, key_count),
            "meaning": "the rest mesh skinned by joint nodes keyed per animation (translation, rotation, scale); "
                       "a corrective frame (a blend of two poses) adds its morph target"}


def body_skin(cache: SkinnedPoseCache, key_count: int) -> tuple[GltfSkin | None, str | None]:
    """(the glTF skin of a skinned pose cache, None) or (None, why it keeps morph targets): a joint with no
    rotation to animate, or a skin no smaller than the morph targets (a small LOD of many joints and keys)."""
    refused = why_not_a_skin(cache)
    if refused is not None:
        return None, refused
    skin = gltf_skin(cache)
    size, morph = skin_bytes(skin, key_count), morph_bytes(cache.vertex_count, cache.frame_count)
    if size >= morph:
        return None, f"its skin would take {size} bytes, its morph targets {morph}"
    return skin, None


@dataclass(frozen=True)
class ExportSummary:
    out_dir: Path
    files: dict[str, int]  # relative path -> bytes
    sidecar: dict[str, Any]


def switch_distance(radius_m: float, tile_size: int, viewport_height_px: float, fov_y_deg: float) -> float:
    """Metres at which one impostor texel covers one pixel (crowdview's impostor_switch_distance):
    a tile spans 2·radius with tile_size texels; a pixel at depth d spans 2·d·tan(fov/2)/H."""
    return radius_m * viewport_height_px / (tile_size * math.tan(math.radians(fov_y_deg) / 2))


def png_rgba(image: np.ndarray) -> bytes:
    """(H, W, 4) uint16 or uint8 RGBA -> a 16- or 8-bit RGBA PNG's bytes (OpenCV writes both; it wants BGRA)."""
    ok, encoded = cv2.imencode(".png", cv2.cvtColor(image, cv2.COLOR_RGBA2BGRA))
    if not ok:
        raise RuntimeError(f"OpenCV could not encode a {image.dtype} PNG")
    return encoded.tobytes()


class _Out:
    """Writes files under the export folder and remembers their sizes; hands each to `on_write` (path, bytes)
    once written, when given."""

    def __init__(self, root: Path, on_write: Callable[[str, bytes], None] | None = None):
        self.root = root
        self.files: dict[str, int] = {}
        self.on_write = on_write
        self.written: list[tuple[str, bytes]] | None = None  # held for release() instead of handed on

    def write(self, path: str, data: bytes) -> str:
        target = self.root / path
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_bytes(data)
        self.files[path] = len(data)
        if self.written is not None:
            self.written.append((path, data))
        elif self.on_write is not None:
            self.on_write(path, data)
        return path

    def held(self) -> _Out:
        """An _Out into the same folder that keeps what it writes until release(): files written side by side
        reach on_write in the order of their release, so the zip is the same bytes every time."""
        out = _Out(self.root)
        out.written = []
        return out

    def release(self, held: _Out) -> None:
        for path, data in held.written or []:
            self.files[path] = len(data)
            if self.on_write is not None:
                self.on_write(path, data)


def _stem(name: str) -> str:
    return "".join(c if c.isalnum() or c in "._-" else "_" for c in name)


def _texture_entry(path: str, vk_format: int, layers: int, width: int, height: int, encoding: str) -> dict[str, Any]:
    return {"ktx2": path, "vk_format": ktx2.format_name(vk_format), "width": width, "height": height, "layers": layers, "encoding": encoding}


def _export_textures(bundle: Bundle, out: _Out, mode: str, prepared: PreparedLayers) -> tuple[list[dict], dict, list[np.ndarray]]:
    manifest = bundle.manifest
    materials, diffuse_arrays = [], []
    for material in manifest["materials"]:
        texture = bundle.textures[material["diffuse"]]
        layers = rgba8_layers(texture, prepared)  # for the glTF's PNG and the region codes
        diffuse_arrays.append(layers)
        vk_format, data = colour_ktx2(texture, True, mode)
        path = out.write(f"textures/{_stem(material['name'])}_diffuse.ktx2", data)
        entry = _texture_entry(path, vk_format, layers.shape[0], layers.shape[2], layers.shape[1], "rgb colour, alpha = 17 * region code")
        materials.append({"name": material["name"], "variations": material["variations"], "diffuse": entry})
    outfit_texture = bundle.textures[manifest["outfits"]["file"]]
    outfit_map = rgba8_layers(outfit_texture)
    vk_format, data = colour_ktx2(outfit_texture, True, mode, array=False)
    path = out.write("textures/outfits.ktx2", data)
    outfits = {
        **_texture_entry(path, vk_format, 0, 16, manifest["outfits"]["count"], "texel (x = region, y = outfit): rgb multiplies the diffuse colour"),
        "count": manifest["outfits"]["count"],
        "colours": outfit_map[0, :, :, :3].tolist(),
    }
    return materials, outfits, diffuse_arrays


def _export_impostor(bundle: Bundle, out: _Out, mode: str, prepared: PreparedLayers, surface_map: bool) -> dict[str, Any]:
    impostor = dict(bundle.manifest["impostor"])
    maps = {}
    kinds = [("normal", False, "model-space unit normal n as rgb = (n + 1) / 2")]
    if "detail" in impostor["maps"]:  # stored only when the bake was asked for it (--detail-map)
        kinds.append(("detail", True, "diffuse variation 0 unlit, alpha = 17 * region code"))
    # SPEC.md "Impostor maps": for reprojecting samples between views and frames, as crowdview's warp blend
    # does; no shipped shader or engine script does, so it is written only when asked (a fifth of a zip).
    if surface_map and "surface" in impostor["maps"]:
        kinds.append(("surface", False, "per texel, metres = (c / 255 * 2 - 1) * range: r = depth along the view's back axis "
                      "(range bounds.radius), g, b = velocity over one baked step along the view's right and up axes "
                      "(range bounds.radius / 2); dilated past the silhouette; a = the share of the texel the character covers "
                      "(an anti-aliased silhouette; 1 in bc1 bundles)"))
    uv_format, uv = uv_map_layers(bundle.textures[impostor["maps"]["uv"]], prepared)
    surface = bundle.textures.get(impostor["maps"].get("surface", ""))
    if surface is not None and surface.pixel_format in ("bc2", "rgba8"):  # its alpha: each texel's coverage
        uv = over_half_covered(uv, rgba8_layers(surface, prepared)[..., 3])
    for kind, colour, encoding in kinds:
        texture = bundle.textures[impostor["maps"][kind]]
        if texture.pixel_format == "bc5":  # two components in each tile's view: handed to engines in model space, where covered
            vk_format, data = model_space_normal_ktx2(texture, impostor, mode, prepared, covered_texels(uv))
            encoding += "; 0 where the UV map covers no texel (of the block, in BC1)"
        else:
            vk_format, data = colour_ktx2(texture, colour, mode)
        path = out.write(f"impostor/{kind}.ktx2", data)
        maps[kind] = _texture_entry(path, vk_format, len(texture.layers), texture.width, texture.height, encoding)
    vk_format = uv_format
    path = out.write("impostor/uv.ktx2", ktx2.encode_ktx2(vk_format, uv))
    encoding = (
        "uv32: u = (w & 0x3FFF) / 16383, v = ((w >> 14) & 0x3FFF) / 16383, material = (w >> 28) & 7, covered = w >> 31"
        if vk_format == ktx2.VK_FORMAT_R32_UINT
        else "rgba16: u = R, v = G, material = B * 65535, covered = A > 0.5"
    ) + "; covered: the character covers over half the texel"
    maps["uv"] = _texture_entry(path, vk_format, uv.shape[0], uv.shape[2], uv.shape[1], encoding)
    tile = impostor["tile_size"]
    layout = AtlasLayout.from_manifest(impostor)
    radius = impostor["bounds"]["radius"]
    return {
        "tile_size": tile,
        "azimuths_deg": impostor["azimuths_deg"],
        "elevations_deg": impostor["elevations_deg"],
        "crop": layout.crop_box_manifest(),
        "tile_of_view": "the view (a, e) is a tile_size² square framing bounds; the maps store of it only the crop: "
        "cell (a, e) covers texels [a*crop.width, (a+1)*crop.width) x [e*crop.height, (e+1)*crop.height) and holds "
        "tile texels [crop.x, crop.x+crop.width) x [crop.y, crop.y+crop.height); tile texels outside it are not covered; "
        "camera for azimuth t, elevation p sits in direction (sin t cos p, sin p, cos t cos p) from bounds.center",
        "frame_indices": impostor["frame_indices"],
        "layer_of_frame": "layer k shows pose frame frame_indices[k]; draw the nearest one in the animation's range "
        "(animations[].vat): round a clip, clamped in a transition (shared_formats/SPEC.md, Playback)",
        "bounds": impostor["bounds"],
        "quad_size_m": 2 * radius,
        "maps": maps,
        "switch_distance": {
            "formula": "radius_m * viewport_height_px / (tile_size * tan(fov_y / 2))",
            "viewport_height_px": REFERENCE_VIEWPORT_HEIGHT_PX,
            "fov_y_deg": REFERENCE_FOV_Y_DEG,
            "distance_m": switch_distance(radius, tile, REFERENCE_VIEWPORT_HEIGHT_PX, REFERENCE_FOV_Y_DEG),
            "low_mesh_fraction": LOW_MESH_FRACTION,
            "hysteresis": LOD_HYSTERESIS,
        },
    }


def look_variants(variation_counts: list[int], outfit_count: int) -> list[GlbVariant]:
    """The export's glTF variants: as many as the most varied material has variations (at most
    MAX_VARIANTS), variant k showing variation k (of each material, wrapping) in outfit k (wrapping)."""
    count = min(max(variation_counts), MAX_VARIANTS)
    return [GlbVariant(f"look_{k}", k, k % outfit_count) for k in range(count)]


def outfit_look(rgba: np.ndarray, outfit_row: np.ndarray) -> np.ndarray:
    """(H, W, 4) uint8 diffuse texels (alpha = 17 · region) with the outfit's colours multiplied in:
    (H, W, 3) uint8, what crowdview's shader draws unlit (crowdbake.bake.shading.apply_outfit)."""
    rgb = apply_outfit(rgba.reshape(-1, 4), outfit_row)
    return np.rint(rgb * 255.0).astype(np.uint8).reshape(rgba.shape[:2] + (3,))


def jpeg_rgb(rgb: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    # 4:4:4: outfit regions change colour at a texel; halved chroma would smear them.
    Image.fromarray(np.ascontiguousarray(rgb)).save(buffer, format="JPEG", quality=LOOK_JPEG_QUALITY, subsampling=0)
    return buffer.getvalue()


def look_image(rgb: np.ndarray) -> tuple[str, bytes]:
    """(media type, bytes) of a look (H, W, 3) uint8: the smallest of a lossless PNG, a 256-colour PNG and
    the JPEG at LOOK_JPEG_QUALITY whose error (RMS over every texel and channel, in 8-bit levels) is no
    larger than the JPEG's. Flat, painted colours (the sample's: a few hundred colours, most of them edge
    blends) take the palette at a third of the lossless bytes within a level or two; photographic textures
    take the JPEG."""
    jpeg = jpeg_rgb(rgb)
    budget = rms_levels(np.asarray(Image.open(io.BytesIO(jpeg)).convert("RGB")), rgb)
    candidates = [("image/png", png_bytes(Image.fromarray(np.ascontiguousarray(rgb)))), ("image/jpeg", jpeg)]
    # Maximum coverage, not median cut or octree: its palette keeps every texel within a few levels of its
    # colour (median cut leaves a stray edge texel tens of levels off; octree shifts whole flat regions).
    palette = Image.fromarray(np.ascontiguousarray(rgb)).quantize(256, method=Image.Quantize.MAXCOVERAGE, dither=Image.Dither.NONE)
    if rms_levels(np.asarray(palette.convert("RGB")), rgb) <= budget:
        candidates.append(("image/png", png_bytes(palette)))
    return min(candidates, key=lambda candidate: len(candidate[1]))


def png_bytes(image: Image.Image) -> bytes:
    buffer = io.BytesIO()
    image.save(buffer, format="PNG", compress_level=LOOK_PNG_LEVEL)
    return buffer.getvalue()


def rms_levels(seen: np.ndarray, want: np.ndarray) -> float:
    """Root mean square difference of two (H, W, 3) uint8 images, in 8-bit levels."""
    return float(np.sqrt(np.mean((seen.astype(np.float64) - want.astype(np.float64)) ** 2)))


_FRAMES_ENCODING = ("R16G16B16A16 unorm, a texel per vertex per pose frame: position = bounds_min + rgb * (bounds_max - bounds_min); "
                    "a = octahedral normal word w = a * 65535: e = (w % 256, w // 256) / 255 * 2 - 1, n = (e, 1 - |e.x| - |e.y|), "
                    "where n.z < 0 n.xy = (1 - |e.yx|) * sign(e), normalise")
_SKIN_ENCODING = ("R16G16B16A16 unorm, three texels per vertex: block 0 the rest position (rgb, as a frame's) and rest normal (a, octahedral), "
                  "block 1 four joints (q * 65535), block 2 four weights (q, summing to 1); joints: per pose frame and joint the three rows "
                  "of its 3 x 4 matrix, channel c = joints.min[c] + q * (joints.max[c] - joints.min[c]); position = sum_k w_k M_jk (rest, 1), "
                  "normal = normalize(sum_k w_k L_jk rest_normal), L the 3 x 3 block")


class _VatWriter:
    """Each part's VAT files, once: a coarser LOD whose vertices are the finer LOD's (vat.shared_vertices)
    reads that LOD's texels; a skinned body's joint matrices serve every LOD that weighs the same joints."""

    def __init__(self, out: _Out, fps: float, vat_png: bool):
        self.out, self.fps, self.vat_png = out, fps, vat_png
        # part -> (its finest LOD, that LOD's cache, vat block and textures: a VertexAnimation, or the skin and joint textures)
        self.finest: dict[str, tuple[int, Any, dict[str, Any], Any]] = {}
        self.joints: dict[str, tuple[np.ndarray, np.ndarray, vat.JointTexture, dict[str, Any]]] = {}  # part -> (matrices, used, texture, block)

    def _write(self, path: str, texels: np.ndarray) -> dict[str, str]:
        files = {"ktx2": self.out.write(f"{path}.ktx2", ktx2.encode_ktx2(ktx2.VK_FORMAT_R16G16B16A16_UNORM, texels[None], array=False))}
        if self.vat_png:  # the same texels for importers that take PNG but not KTX2 (Unity, Unreal)
            files["png"] = self.out.write(f"{path}.png", png_rgba(texels))
        return files

    def _layout(self, layout: vat.VatLayout, frame_count: int) -> dict[str, Any]:
        return {"width": layout.width, "height": layout.height, "rows_per_frame": layout.rows_per_frame, "frame_count": frame_count,
                "vertex_count": layout.vertex_count, "frames_per_second": self.fps, "texcoord": 1}

    def export(self, part: str, lod: int, cache) -> tuple[dict[str, Any], np.ndarray]:
        """(export.json's `vat` block, the mesh's TEXCOORD_1 (V, 2)) of one part at one LOD, writing its files."""
        skinned = isinstance(cache, SkinnedPoseCache)
        finer = self.finest.get(part)
        if finer is not None and finer[2]["kind"] == ("skin" if skinned else "frames"):
            shared = self._shared(part, lod, cache, finer)
            if shared is not None:
                return shared
        block, uvs, texture = self._skin(part, lod, cache) if skinned else self._frames(part, lod, cache)
        self.finest.setdefault(part, (lod, cache, block, texture))
        return block, uvs

    def _frames(self, part: str, lod: int, cache) -> tuple[dict[str, Any], np.ndarray, vat.VertexAnimation]:
        animation = vat.encode_vat(cache.positions, cache.normals)
        block = {"kind": "frames", "texture": self._write(f"vat/{_stem(part)}_lod{lod}.frames", animation.texels), "encoding": _FRAMES_ENCODING,
                 "bounds_min": animation.bounds_min.tolist(), "bounds_max": animation.bounds_max.tolist(),
                 "max_position_error_m": animation.max_position_error.tolist(), **self._layout(animation.layout, cache.frame_count),
                 "texel_of_vertex": "(i % width, frame * rows_per_frame + i // width) for pose frame `frame` (export.json animations[].vat: "
                                    "the frames of each clip and transition); TEXCOORD_1 is frame 0's texel centre"}
        return block, vat.vat_texcoords(animation.layout), animation

    def _skin(self, part: str, lod: int, cache: SkinnedPoseCache) -> tuple[dict[str, Any], np.ndarray, tuple[vat.SkinTexture, vat.JointTexture]]:
        skin = vat.encode_skin(cache.rest_positions, cache.rest_normals, cache.joints, cache.weight_codes)
        used = np.zeros(cache.joint_count, dtype=bool)
        used[np.unique(cache.joints[cache.weight_codes > 0])] = True
        known = self.joints.get(part)
        if known is not None and np.array_equal(known[0], cache.matrices) and not (used & ~known[1]).any():
            joints, joints_block = known[2], known[3]
        else:
            joints = vat.encode_joints(cache.matrices, used)
            name = f"vat/{_stem(part)}.joints" if known is None else f"vat/{_stem(part)}_lod{lod}.joints"
            joints_block = {**self._write(name, joints.texels), "joint_count": joints.joint_count, "width": joints.layout.width,
                            "height": joints.layout.height, "rows_per_frame": joints.layout.rows_per_frame,
                            "min": joints.minimum.tolist(), "max": joints.maximum.tolist(),
                            "texel_of_row": "row r of joint j at pose frame f: i = 3 * j + r, texel (i % width, f * rows_per_frame + i // width)"}
            self.joints.setdefault(part, (cache.matrices, used, joints, joints_block))
        played, _ = vat.play_skin(skin, joints)
        block = {"kind": "skin", "texture": self._write(f"vat/{_stem(part)}_lod{lod}.skin", skin.texels), "joints": joints_block,
                 "encoding": _SKIN_ENCODING, "bounds_min": skin.bounds_min.tolist(), "bounds_max": skin.bounds_max.tolist(),
                 "max_position_error_m": np.abs(played - cache.positions).max(axis=(0, 1)).tolist(),
                 **self._layout(skin.layout, cache.frame_count),
                 "texel_of_vertex": "(i % width, block * rows_per_frame + i // width), block 0 rest pose, 1 joints, 2 weights; "
                                    "TEXCOORD_1 is block 0's texel centre"}
        return block, vat.vat_texcoords(skin.layout), (skin, joints)

    def _shared(self, part: str, lod: int, cache, finer) -> tuple[dict[str, Any], np.ndarray] | None:
        """This LOD reading the finer LOD's texels, when its vertices are that LOD's; None when they are not."""
        finer_lod, finer_cache, finer_block, texture = finer
        if finer_block["kind"] == "skin":
            if not np.array_equal(finer_cache.matrices, cache.matrices):
                return None
            vertices = vat.shared_skin_vertices(finer_cache.rest_positions, finer_cache.rest_normals, finer_cache.joints, finer_cache.weight_codes,
                                                cache.rest_positions, cache.rest_normals, cache.joints, cache.weight_codes)
            if vertices is None:
                return None
            played = vat.play_skin(*texture)[0][:, vertices]
            layout = texture[0].layout
        else:
            vertices = vat.shared_vertices(finer_cache.positions, finer_cache.normals, cache.positions, cache.normals)
            if vertices is None:
                return None
            played = vat.decode_vat(texture)[0][:, vertices]
            layout = texture.layout
        block = {**finer_block, "texels_of_lod": finer_lod, "max_position_error_m": np.abs(played - cache.positions).max(axis=(0, 1)).tolist()}
        return block, vat.vat_texcoords(layout, vertices)


def _export_lods(bundle: Bundle, out: _Out, diffuse_arrays: list[np.ndarray], variants: list[GlbVariant], outfit_rows: np.ndarray,
                 vat_png: bool, cloth_bones: ClothBonesRequest | None, plans: list[AnimationPlan]) -> list[dict]:
    manifest = bundle.manifest
    fps = manifest["frames_per_second"]
    # The looks are files of their own, shared by every LOD's .glb (embedded, each LOD held its own copy).
    glb_materials = []
    for material, layers in zip(manifest["materials"], diffuse_arrays):
        looks = []
        for variant in variants:
            mime_type, data = look_image(outfit_look(layers[variant.variation % len(layers)], outfit_rows[variant.outfit]))
            suffix = {"image/png": "png", "image/jpeg": "jpg"}[mime_type]
            looks.append((mime_type, out.write(f"{LOOKS_FOLDER}/{_stem(material['name'])}_{variant.name}.{suffix}", data)))
        glb_materials.append(GlbMaterial(material["name"], looks))
    lods = []
    vats = _VatWriter(out, fps, vat_png)
    for lod in sorted({mesh["lod"] for mesh in manifest["meshes"]}):
        parts, part_entries = [], []
        for mesh in (m for m in manifest["meshes"] if m["lod"] == lod):
            cache = bundle.pose_caches[mesh["file"]]
            vat_block, vat_uvs = vats.export(mesh["part"], lod, cache)
            extras = {"part": mesh["part"], "kind": mesh["kind"], "lod": lod, "material": mesh["material"], "vat": vat_block}
            bones = (cloth_bones.decompose(cache.positions, cache.indices, f"{mesh['part']} lod {lod}")
                     if cloth_bones is not None and mesh["kind"] == "garment" else None)
            # A skinned pose cache stays a skin where it can (body_skin), else morph targets like the rest.
            skin, refused = body_skin(cache, sum(plan.key_count for plan in plans)) if isinstance(cache, SkinnedPoseCache) else (None, None)
            if refused is not None:
                logger.warning("%s lod %d keeps morph targets: %s", mesh["part"], lod, refused)
            parts.append(
                GlbPart(mesh["part"], mesh["kind"], mesh["material"], cache.positions, cache.normals, cache.uvs, vat_uvs, cache.indices, extras,
                        bones, skin)
            )
            entry = {k: extras[k] for k in ("part", "kind", "material")} | {"vertex_count": cache.vertex_count, "triangle_count": cache.triangle_count, "vat": vat_block}
            entry["playback"] = "skin" if skin is not None else "bones" if bones is not None else "morph"
            if refused is not None:
                entry["skin_refused"] = refused
            if skin is not None:
                entry["skin"] = skin_entry(skin, cache, sum(plan.key_count for plan in plans))
                # The engine setups draw every part with a `node` by its VATs (metres in the character's space),
                # as they did this body's morph targets; glTF places a skinned mesh by its joints alone.
                entry["node"] = {"translation": [0.0, 0.0, 0.0], "scale": 1.0,
                                 "meaning": "a skinned mesh: its joints place it, in metres; VAT positions need no transform"}
            elif bones is None:
                translation, scale = node_transform(cache.positions)
                entry["node"] = {"translation": translation.tolist(), "scale": scale,
                                 "meaning": "the part's glTF node: position in metres = translation + scale * mesh position"}
            else:
                entry["bones"] = bones_entry(bones, cloth_bones, cache.vertex_count, sum(plan.key_count for plan in plans))
            part_entries.append(entry)
        root_extras = {"crowdbake": {"export": "export.json", "lod": lod, "frames_per_second": fps, "frame_count": bundle.ranges.pose_frames}}
        path = out.write(f"character_lod{lod}.glb", build_glb(parts, glb_materials, variants, fps, root_extras, plans))
        lods.append({"lod": lod, "glb": path, "parts": part_entries})
    return lods


# Files shipped with the package and copied into every export, by folder: the reference shaders and the
# engines' import scripts, which read export.json beside them (docs/export.md "Importing into an engine").
SHIPPED_FILES = {"shaders": (".glsl", ".hlsl", ".gdshader"), "engines": (".gd", ".cs", ".py")}


def _copy_shipped(out: _Out, folder: str) -> list[str]:
    written = []
    for entry in sorted(resources.files("crowdbake.export").joinpath(folder).iterdir(), key=lambda e: e.name):
        if entry.name.endswith(SHIPPED_FILES[folder]):
            written.append(out.write(f"{folder}/{entry.name}", entry.read_bytes()))
    return written


def export_bundle(bundle_dir: Path, out_dir: Path, ktx2_mode: str = KTX2_MODES[0], prepared: PreparedLayers = NOTHING_PREPARED,
                  on_write: Callable[[str, bytes], None] | None = None, vat_png: bool = False,
                  cloth_bones: ClothBonesRequest | None = None, surface_map: bool = False) -> ExportSummary:
    """Verify the bundle at `bundle_dir` and write its export into `out_dir` (new or empty).

    ktx2_mode: "bc" keeps the bundle's BC1/BC2 blocks in the KTX2 files, "rgba8" decodes them.
    prepared: impostor layers the bake converted already (the same bytes either way).
    on_write: called with (path under out_dir, bytes) as each file is written, always in the same order.
    vat_png: also write each VAT as a PNG (16-bit positions, 8-bit normals) beside its KTX2.
    cloth_bones: play each garment by bones instead of morph targets (ClothBonesRequest; needs py-dem-bones).
    surface_map: also write the impostor surface map (depth and motion per texel, for reprojection).
    Raises FormatError for a bundle that does not verify, FileExistsError for a non-empty `out_dir`
    (also when another writer renamed its export into place first), ValueError for an unknown mode.
    """
    if ktx2_mode not in KTX2_MODES:
        raise ValueError(f"ktx2_mode must be one of {KTX2_MODES}, got {ktx2_mode!r}")
    bundle = verify_bundle(Path(bundle_dir))
    out_dir = Path(out_dir)
    if out_dir.exists() and (not out_dir.is_dir() or any(out_dir.iterdir())):
        raise FileExistsError(f"{out_dir} exists and is not an empty folder")
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    # A staging folder of its own beside the target, so concurrent exports never share one.
    staging = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", suffix=".partial", dir=out_dir.parent))
    try:
        out = _Out(staging, on_write)
        manifest = bundle.manifest
        materials, outfits, diffuse_arrays = _export_textures(bundle, out, ktx2_mode, prepared)
        outfit_rows = rgba8_layers(bundle.textures[manifest["outfits"]["file"]])[0]
        variants = look_variants([m["variations"] for m in manifest["materials"]], manifest["outfits"]["count"])
        plans = animation_plans(bundle.ranges)
        # The impostor's maps and the LODs share nothing and take about as long (the sample: 2.1 and 2.0 s):
        # the maps are made in a thread beside the LODs (zstd, zlib, OpenCV and Pillow let go of the
        # interpreter lock while they compress), their files handed on in the order they always were.
        impostor_out, lods_out = out.held(), out.held()
        with ThreadPoolExecutor(1, thread_name_prefix="export-impostor") as pool:
            impostor_made = pool.submit(_export_impostor, bundle, impostor_out, ktx2_mode, prepared, surface_map)
            lods = _export_lods(bundle, lods_out, diffuse_arrays, variants, outfit_rows, vat_png, cloth_bones, plans)
            impostor = impostor_made.result()
        out.release(impostor_out)
        out.release(lods_out)
        shaders = _copy_shipped(out, "shaders")
        engines = _copy_shipped(out, "engines")
        sidecar = {
            "format": EXPORT_FORMAT,
            "format_version": EXPORT_FORMAT_VERSION,
            "producer": f"crowdbake {__version__}",
            "ktx2": ktx2_mode,
            "bundle": {"name": manifest["name"], "version": manifest["version"]},
            "frames_per_second": manifest["frames_per_second"],
            "frame_count": bundle.ranges.pose_frames,
            "animations": sidecar_animations(plans, manifest["frames_per_second"]),
            "lods": lods,
            "materials": materials,
            "outfits": outfits,
            "variants": [{"name": v.name, "variation": v.variation, "outfit": v.outfit} for v in variants],
            "regions": {"count": manifest["outfits"]["regions"], "alpha_scale": 17, "decode": "r = round(alpha * 255 / 17); 0 keeps the texture colour",
                        "used": region_codes_used(diffuse_arrays)},
            "impostor": impostor,
            "shaders": shaders,
            "engines": engines,
            "space": "right-handed, +Y up, metres; the character stands at the origin facing +Z",
        }
        out.write("export.json", (json.dumps(sidecar, indent=2) + "\n").encode())
        if out_dir.exists():
            out_dir.rmdir()
        try:
            staging.rename(out_dir)
        except OSError as error:  # another export was renamed into place first
            raise FileExistsError(f"{out_dir} exists and is not an empty folder") from error
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    logger.info("exported %s/%s: %d files", manifest["name"], manifest["version"], len(out.files))
    return ExportSummary(out_dir, dict(sorted(out.files.items())), sidecar)
