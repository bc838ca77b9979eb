"""crowdview's impostor shader drawn in the bake's GL context: the pictures fidelity.json's `runtime`
section scores against the mesh (crowdbake.stages.runtime_fidelity).

The shader is crowdview's own files (runtime/src/shaders/impostor.vert.glsl, impostor_uv.frag.glsl and
what they include), pasted together as crowdview's loader does (runtime/src/renderer.cpp,
load_shader_source and compile_shader: each `#include "x"` line replaced by the file x beside it, one
level; the program's defines right after the #version line), blended over black as crowdview blends
impostors over its scene, in the blending of samples crowdview draws by default:
four views times two frames, reprojected by the surface map where the bundle has one (CV_WARP). So the
scores measure the runtime's code, not a copy of it. Two things differ from a crowd frame, both so that
the picture can be compared with the fidelity references (crowdbake.render.map_shader's REFERENCE pass):

- the light: the references' (crowdbake.bake.shading.camera_light, ambient shading.AMBIENT), config.h's
  CV_AMBIENT replaced in the pasted source;
- the camera: orthographic along the view, the tile's framing at one texel a pixel; the character at the
  origin with heading 0, variation 0 of every material, the outfit row given.

The maps go up as crowdview uploads them (renderer.cpp upload_texture_array): uvblock as its RG32UI
blocks, uv32 as R32UI words, rgba16 as RGBA16, BC blocks decoded to RGBA8 on the CPU (crowdview's path
where a driver lacks S3TC; crowdbake.bake.compression.decode); diffuse textures as the bundle's decoded
texels under glGenerateMipmap's chain, trilinear and REPEAT. The instance data crowdview's CPU computes
(view_blend.h: four tiles and their weights, two layers and the frame weight) are crowdbake.bake.view_blend's,
set as constant vertex attributes, one draw a picture into its own viewport of a float framebuffer that is
read back once.

crowdbake.reference.runtime_picture draws the same picture in float64 numpy: the reference this is
tested against (services/tests/test_runtime_shader.py).
"""
from __future__ import annotations

import ctypes
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from crowdbake.bake import compression, impostor_views, shading
from crowdbake.formats.binary import TextureArray
from crowdbake.render.map_shader import tiles_of

# crowdview's shader folder, in the repository's layout (the service image keeps it: deploy/Dockerfile).
SHADER_DIR = Path(__file__).resolve().parents[3] / "runtime" / "src" / "shaders"
# renderer.cpp and config.h: attribute locations, texture units and array limits the shader is built with.
ATTR_INSTANCE_POSE, ATTR_INSTANCE_IDS, ATTR_TILES, ATTR_VIEW_WEIGHTS, ATTR_LAYERS, ATTR_FRAME_WEIGHT = 1, 2, 3, 4, 5, 6
UNIT_OUTFITS, UNIT_NORMAL, UNIT_UV, UNIT_DIFFUSE0, UNIT_SURFACE = 1, 2, 3, 5, 9
MAX_MATERIALS, MAX_AZIMUTHS, MAX_ELEVATIONS = 4, 64, 9
# Widest framebuffer row of pictures, in pixels.
MAX_ROW_PIXELS = 4096


@dataclass(frozen=True)
class RuntimeAtlas:
    """What crowdview samples for one character's impostor, from the bundle's own bytes.

    tile_size, azimuths_deg, elevations_deg: the atlas layout; center (3,) and radius (metres): the
    impostor's bounds; uv_map, normal_map, surface_map (or None): the bundle's CBTX arrays (only the layers
    the pictures read need bytes); diffuse: per material, variation 0 as decoded, (h, w, 4) uint8;
    has_regions: per material, whether its alpha holds region codes (crowdview: not bc1); outfit_row:
    (16, 4) uint8, the outfit drawn; crop: (x, y, width, height) of every tile the maps store.
    """

    tile_size: int
    azimuths_deg: tuple[float, ...]
    elevations_deg: tuple[float, ...]
    center: np.ndarray
    radius: float
    uv_map: TextureArray
    normal_map: TextureArray
    surface_map: TextureArray | None
    diffuse: list[np.ndarray]
    has_regions: list[bool]
    outfit_row: np.ndarray
    crop: tuple[int, int, int, int] | None = None  # the stored part of every tile (crowdbake.bake.atlas); None: all of it
    warp: bool = True  # reproject with the surface map (crowdview's `warp`); False: its alpha only (`full`)


@dataclass(frozen=True)
class RuntimePicture:
    """One impostor as crowdview's CPU side hands it to the shader (view_blend.h): a camera at (azimuth,
    elevation) degrees, up to four atlas tiles and their weights, two atlas layers and the second's weight."""

    azimuth_deg: float
    elevation_deg: float
    tiles: tuple[int, ...]
    view_weights: tuple[float, ...]
    layers: tuple[int, int]
    frame_weight: float


def shader_source(file: str, defines: dict[str, int], replace: dict[str, str], directory: Path = SHADER_DIR) -> str:
    """The GLSL of `file` as crowdview compiles it (module docstring), with `defines` ("#define NAME value"
    lines after #version) and config.h's #define lines named in `replace` given other values (an error when
    one is not there: the bake must not silently score with the crowd's value)."""
    lines = []
    for line in (directory / file).read_text().splitlines():
        if line.lstrip().startswith('#include "'):
            included = line.lstrip()[len('#include "'):].split('"')[0]
            lines.append((directory / included).read_text())
        else:
            lines.append(line)
    source = "\n".join(lines) + "\n"
    for name, value in replace.items():
        source, count = re.subn(rf"^#define {name}\b.*$", f"#define {name} {value}", source, flags=re.M)
        if count == 0:
            raise RuntimeError(f"{directory / file}: no #define {name} to replace")
    end_of_version = source.index("\n") + 1
    return source[:end_of_version] + "".join(f"#define {name} {value}\n" for name, value in defines.items()) + source[end_of_version:]


def program_defines(atlas: RuntimeAtlas, view_samples: int = 4, frame_samples: int = 2) -> dict[str, int]:
    """The defines crowdview builds an impostor program with (renderer.cpp): the UV map's format, bc5
    normals in the tile's view, reprojection where there is a surface map (and atlas.warp), and the blend's samples: four
    views or one, two frames or one (its blend modes; four and two by default)."""
    return {"CV_UV_MAP_UV32": int(atlas.uv_map.pixel_format == "uv32"), "CV_UV_MAP_UVBLOCK": int(atlas.uv_map.pixel_format == "uvblock"),
            "CV_NORMAL_VIEW_XY": int(atlas.normal_map.pixel_format == "bc5"), "CV_VIEW_SAMPLES": view_samples,
            "CV_FRAME_SAMPLES": frame_samples, "CV_WARP": int(atlas.surface_map is not None and atlas.warp)}


def samples_needed(picture: RuntimePicture) -> tuple[int, int]:
    """(view samples, frame samples) of the smallest of crowdview's programs that draws `picture` as its
    default program (four views, two frames) does: a sample of weight 0 adds nothing to the blend, and a
    CPU rasteriser runs the shader's every sample whatever its weight. At a baked view the first tile
    holds the whole weight (blend_view_weights), at a baked frame the first layer."""
    views = 1 if all(weight == 0.0 for weight in picture.view_weights[1:]) else 4
    return views, 1 if picture.frame_weight == 0.0 else 2


def quad_view_projection(center: np.ndarray, radius: float, to_camera: np.ndarray) -> np.ndarray:
    """(4, 4) float32 orthographic view-projection (row-major) under which impostor.vert.glsl's quad round
    `center`, seen from `to_camera` (unit), fills the viewport exactly: the quad's own right and up (the
    vertex shader's, +X where the camera is straight above or below) are the clip axes."""
    side = np.cross([0.0, 1.0, 0.0], to_camera)
    right = side / np.linalg.norm(side) if np.linalg.norm(side) > 1e-4 else np.array([1.0, 0.0, 0.0])
    up = np.cross(to_camera, right)
    back = np.asarray(to_camera, dtype=np.float64)
    matrix = np.zeros((4, 4))
    for row, (axis, scale) in enumerate(((right, 1.0 / radius), (up, 1.0 / radius), (back, -0.5 / radius))):
        matrix[row, :3] = axis * scale
        matrix[row, 3] = -np.dot(axis, center) * scale
    matrix[3, 3] = 1.0
    return matrix.astype(np.float32)


def _layer_texels(array: TextureArray, layer: int) -> np.ndarray:
    """One layer of an impostor map as crowdview uploads it: uint32 words (uvblock blocks, uv32), uint16
    (rgba16) or uint8 RGBA (rgba8, and BC blocks decoded on the CPU)."""
    if array.pixel_format == "uvblock":
        return np.frombuffer(array.layers[layer], "<u4").reshape(array.height // 4, 3 * (array.width // 4), 2)
    if array.pixel_format in ("bc1", "bc2", "bc5"):
        return compression.decode(array.layers[layer], array.pixel_format, array.width, array.height)
    return array.texels(layer)


# (internal format, format, type) of each impostor map format's upload (renderer.cpp upload_texture_array).
_UPLOADS = {"uvblock": ("GL_RG32UI", "GL_RG_INTEGER", "GL_UNSIGNED_INT"), "uv32": ("GL_R32UI", "GL_RED_INTEGER", "GL_UNSIGNED_INT"),
            "rgba16": ("GL_RGBA16", "GL_RGBA", "GL_UNSIGNED_SHORT")}
_RGBA8 = ("GL_RGBA8", "GL_RGBA", "GL_UNSIGNED_BYTE")


def used_layers(pictures: list[RuntimePicture]) -> list[int]:
    """The atlas layers the pictures read, ascending: the only ones uploaded (in this order)."""
    return sorted({layer for picture in pictures for layer in picture.layers})


def map_texels(atlas: RuntimeAtlas, pictures: list[RuntimePicture]) -> list[tuple[int, np.ndarray, tuple[str, str, str], str]]:
    """(texture unit, (L, H, W[, C]) texels, upload formats, filtering) of each impostor map, the layers
    the pictures read only (used_layers): the CPU's part of the upload, BC blocks decoded here."""
    layers = used_layers(pictures)
    return [(unit, np.stack([_layer_texels(array, layer) for layer in layers]), _UPLOADS.get(array.pixel_format, _RGBA8), filtering)
            for unit, array, filtering in ((UNIT_UV, atlas.uv_map, "nearest"), (UNIT_NORMAL, atlas.normal_map, "nearest"),
                                           (UNIT_SURFACE, atlas.surface_map, "linear")) if array is not None]


class RuntimeImpostorShader:
    """crowdview's impostor programs in the current context (by their defines), and a framebuffer. Every
    method needs the owning context current (crowdbake.render.offscreen.Offscreen.current)."""

    def __init__(self):
        self._programs: dict[tuple, int] = {}
        self._vao = None
        self._framebuffer = self._target = None
        self._target_size = (0, 0)
        self._textures: list[int] = []

    def draw(self, atlas: RuntimeAtlas, pictures: list[RuntimePicture], maps: list) -> np.ndarray:
        """(N, S, S, 3) float32 pictures, 0..1, black where crowdview draws nothing; rows top first. maps:
        map_texels(atlas, pictures), decoded by the caller (outside its GL timing)."""
        from OpenGL import GL

        if len(atlas.azimuths_deg) > MAX_AZIMUTHS or len(atlas.elevations_deg) > MAX_ELEVATIONS:
            raise ValueError(f"crowdview's impostor shader holds at most {MAX_AZIMUTHS} azimuths and {MAX_ELEVATIONS} elevations")
        if not pictures:
            return np.zeros((0, atlas.tile_size, atlas.tile_size, 3), dtype=np.float32)
        size = atlas.tile_size
        compact = {layer: k for k, layer in enumerate(used_layers(pictures))}
        columns = max(1, min(len(pictures), MAX_ROW_PIXELS // size))
        rows = -(-len(pictures) // columns)
        self._ensure_framebuffer(columns * size, rows * size)
        self._upload(atlas, maps)

        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, self._framebuffer)
        GL.glDrawBuffers(1, [GL.GL_COLOR_ATTACHMENT0])
        GL.glViewport(0, 0, columns * size, rows * size)
        GL.glDisable(GL.GL_SCISSOR_TEST)
        GL.glColorMask(GL.GL_TRUE, GL.GL_TRUE, GL.GL_TRUE, GL.GL_TRUE)
        GL.glClearBufferfv(GL.GL_COLOR, 0, np.zeros(4, dtype=np.float32))
        GL.glDisable(GL.GL_DEPTH_TEST)
        GL.glDisable(GL.GL_CULL_FACE)
        # crowdview's impostor blending (renderer.cpp): soft silhouettes mix over the black clear.
        GL.glEnable(GL.GL_BLEND)
        GL.glBlendFuncSeparate(GL.GL_SRC_ALPHA, GL.GL_ONE_MINUS_SRC_ALPHA, GL.GL_ONE, GL.GL_ONE_MINUS_SRC_ALPHA)
        # The character stands at the origin with heading 0: its model frame is the world's.
        GL.glVertexAttrib4f(ATTR_INSTANCE_POSE, 0.0, 0.0, 0.0, 0.0)
        order = sorted(range(len(pictures)), key=lambda k: samples_needed(pictures[k]))
        program = None
        for k in order:
            picture = pictures[k]
            wanted = self._program(program_defines(atlas, *samples_needed(picture)))
            if wanted != program:
                program = wanted
                GL.glUseProgram(program)
                GL.glBindVertexArray(self._vao)
                self._set_atlas_uniforms(atlas, program)
                location = {name: GL.glGetUniformLocation(program, name) for name in ("u_view_projection", "u_camera_position", "u_light_dir")}
            view = impostor_views.ortho_view(atlas.center, atlas.radius, picture.azimuth_deg, picture.elevation_deg, size)
            tiles = list(picture.tiles) + [0] * (4 - len(picture.tiles))
            weights = list(picture.view_weights) + [0.0] * (4 - len(picture.view_weights))
            layers = [compact[layer] for layer in picture.layers]
            GL.glVertexAttribI4ui(ATTR_INSTANCE_IDS, layers[0], 0, 0, tiles[0])
            GL.glVertexAttribI4ui(ATTR_TILES, *tiles)
            GL.glVertexAttrib4f(ATTR_VIEW_WEIGHTS, *weights)
            GL.glVertexAttribI4ui(ATTR_LAYERS, layers[0], layers[1], 0, 0)
            GL.glVertexAttrib1f(ATTR_FRAME_WEIGHT, picture.frame_weight)
            GL.glUniformMatrix4fv(location["u_view_projection"], 1, GL.GL_TRUE, quad_view_projection(atlas.center, atlas.radius, view.back))
            GL.glUniform3f(location["u_camera_position"], *(atlas.center + view.back * 4.0 * atlas.radius).tolist())
            GL.glUniform3f(location["u_light_dir"], *shading.camera_light(view).tolist())
            column, row = k % columns, k // columns
            GL.glViewport(column * size, (rows - 1 - row) * size, size, size)  # GL's rows grow upwards
            GL.glDrawArrays(GL.GL_TRIANGLE_STRIP, 0, 4)
        GL.glReadBuffer(GL.GL_COLOR_ATTACHMENT0)
        image = np.empty((rows * size, columns * size, 3), dtype=np.float32)
        GL.glPixelStorei(GL.GL_PACK_ALIGNMENT, 4)
        GL.glReadPixels(0, 0, columns * size, rows * size, GL.GL_RGB, GL.GL_FLOAT, image.ctypes.data_as(ctypes.c_void_p))
        GL.glDisable(GL.GL_BLEND)
        GL.glBindVertexArray(0)
        GL.glUseProgram(0)
        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, 0)
        return np.clip(tiles_of(image[::-1], size, columns, len(pictures)), 0.0, 1.0)

    def _program(self, defines: dict[str, int]) -> int:
        """The program of `defines`, compiled once."""
        from OpenGL import GL
        from OpenGL.GL import shaders

        key = tuple(sorted(defines.items()))
        if key not in self._programs:
            replace = {"CV_AMBIENT": repr(float(shading.AMBIENT))}
            self._programs[key] = shaders.compileProgram(
                shaders.compileShader(shader_source("impostor.vert.glsl", defines, replace), GL.GL_VERTEX_SHADER),
                shaders.compileShader(shader_source("impostor_uv.frag.glsl", defines, replace), GL.GL_FRAGMENT_SHADER),
                validate=False,  # validation needs a bound VAO, which core profile contexts lack at this point
            )
        if self._vao is None:  # no attribute arrays: every draw reads the constant instance values set before it
            self._vao = GL.glGenVertexArrays(1)
        return self._programs[key]

    def _ensure_framebuffer(self, width: int, height: int) -> None:
        from OpenGL import GL

        if self._framebuffer is not None and width <= self._target_size[0] and height <= self._target_size[1]:
            return
        self._delete_framebuffer()
        width, height = max(width, self._target_size[0]), max(height, self._target_size[1])
        self._framebuffer = GL.glGenFramebuffers(1)
        self._target = int(GL.glGenTextures(1))
        GL.glBindTexture(GL.GL_TEXTURE_2D, self._target)
        GL.glTexImage2D(GL.GL_TEXTURE_2D, 0, GL.GL_RGBA32F, width, height, 0, GL.GL_RGBA, GL.GL_FLOAT, None)
        GL.glTexParameteri(GL.GL_TEXTURE_2D, GL.GL_TEXTURE_MIN_FILTER, GL.GL_NEAREST)
        GL.glTexParameteri(GL.GL_TEXTURE_2D, GL.GL_TEXTURE_MAG_FILTER, GL.GL_NEAREST)
        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, self._framebuffer)
        GL.glFramebufferTexture2D(GL.GL_FRAMEBUFFER, GL.GL_COLOR_ATTACHMENT0, GL.GL_TEXTURE_2D, self._target, 0)
        status = GL.glCheckFramebufferStatus(GL.GL_FRAMEBUFFER)
        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, 0)
        self._target_size = (width, height)
        if status != GL.GL_FRAMEBUFFER_COMPLETE:
            raise RuntimeError(f"the runtime shader's framebuffer ({width}x{height} RGBA32F) is incomplete: status 0x{int(status):x}")

    def _delete_framebuffer(self) -> None:
        from OpenGL import GL

        if self._framebuffer is not None:
            GL.glDeleteFramebuffers(1, [self._framebuffer])
            GL.glDeleteTextures(1, [self._target])
        self._framebuffer = self._target = None
        self._target_size = (0, 0)

    def _texture_array(self, unit: int, texels: np.ndarray, upload: tuple[str, str, str], filtering: str) -> None:
        """(L, H, W[, C]) texels as a GL_TEXTURE_2D_ARRAY on texture unit `unit`: filtering "nearest" (the
        impostor maps, base level), "linear" (the surface map) or "mipmaps" (diffuse: trilinear, REPEAT)."""
        from OpenGL import GL

        texture = int(GL.glGenTextures(1))
        self._textures.append(texture)
        GL.glActiveTexture(GL.GL_TEXTURE0 + unit)
        GL.glBindTexture(GL.GL_TEXTURE_2D_ARRAY, texture)
        GL.glPixelStorei(GL.GL_UNPACK_ALIGNMENT, 1)
        internal, pixel_format, pixel_type = (getattr(GL, name) for name in upload)
        texels = np.ascontiguousarray(texels)
        GL.glTexImage3D(GL.GL_TEXTURE_2D_ARRAY, 0, internal, texels.shape[2], texels.shape[1], texels.shape[0], 0, pixel_format, pixel_type, texels)
        GL.glPixelStorei(GL.GL_UNPACK_ALIGNMENT, 4)
        wrap = GL.GL_REPEAT if filtering == "mipmaps" else GL.GL_CLAMP_TO_EDGE
        GL.glTexParameteri(GL.GL_TEXTURE_2D_ARRAY, GL.GL_TEXTURE_WRAP_S, wrap)
        GL.glTexParameteri(GL.GL_TEXTURE_2D_ARRAY, GL.GL_TEXTURE_WRAP_T, wrap)
        if filtering == "mipmaps":
            GL.glTexParameteri(GL.GL_TEXTURE_2D_ARRAY, GL.GL_TEXTURE_MAX_LEVEL, 1000)
            GL.glGenerateMipmap(GL.GL_TEXTURE_2D_ARRAY)
            GL.glTexParameteri(GL.GL_TEXTURE_2D_ARRAY, GL.GL_TEXTURE_MIN_FILTER, GL.GL_LINEAR_MIPMAP_LINEAR)
            GL.glTexParameteri(GL.GL_TEXTURE_2D_ARRAY, GL.GL_TEXTURE_MAG_FILTER, GL.GL_LINEAR)
        else:
            GL.glTexParameteri(GL.GL_TEXTURE_2D_ARRAY, GL.GL_TEXTURE_MAX_LEVEL, 0)
            chosen = GL.GL_LINEAR if filtering == "linear" else GL.GL_NEAREST
            GL.glTexParameteri(GL.GL_TEXTURE_2D_ARRAY, GL.GL_TEXTURE_MIN_FILTER, chosen)
            GL.glTexParameteri(GL.GL_TEXTURE_2D_ARRAY, GL.GL_TEXTURE_MAG_FILTER, chosen)

    def _upload(self, atlas: RuntimeAtlas, maps: list) -> None:
        """The atlas's textures on crowdview's units (config.h): the maps' texels (map_texels), diffuse, outfits."""
        from OpenGL import GL

        self._delete_textures()
        for unit, texels, upload, filtering in maps:
            self._texture_array(unit, texels, upload, filtering)
        for material in range(MAX_MATERIALS):
            # A material the character lacks gets a 1x1 white array, as crowdview binds (never sampled).
            texture = atlas.diffuse[material] if material < len(atlas.diffuse) else np.full((1, 1, 4), 255, dtype=np.uint8)
            self._texture_array(UNIT_DIFFUSE0 + material, np.asarray(texture, dtype=np.uint8)[None], _RGBA8,
                                "mipmaps" if material < len(atlas.diffuse) else "nearest")
        outfits = int(GL.glGenTextures(1))
        self._textures.append(outfits)
        GL.glActiveTexture(GL.GL_TEXTURE0 + UNIT_OUTFITS)
        GL.glBindTexture(GL.GL_TEXTURE_2D, outfits)
        row = np.ascontiguousarray(np.asarray(atlas.outfit_row, dtype=np.uint8).reshape(1, -1, 4))
        GL.glTexImage2D(GL.GL_TEXTURE_2D, 0, GL.GL_RGBA8, row.shape[1], 1, 0, GL.GL_RGBA, GL.GL_UNSIGNED_BYTE, row)
        GL.glTexParameteri(GL.GL_TEXTURE_2D, GL.GL_TEXTURE_MIN_FILTER, GL.GL_NEAREST)
        GL.glTexParameteri(GL.GL_TEXTURE_2D, GL.GL_TEXTURE_MAG_FILTER, GL.GL_NEAREST)
        GL.glTexParameteri(GL.GL_TEXTURE_2D, GL.GL_TEXTURE_MAX_LEVEL, 0)
        GL.glActiveTexture(GL.GL_TEXTURE0)

    def _set_atlas_uniforms(self, atlas: RuntimeAtlas, program: int) -> None:
        from OpenGL import GL

        def at(name: str) -> int:
            return GL.glGetUniformLocation(program, name)

        for name, unit in (("u_outfits", UNIT_OUTFITS), ("u_normal_map", UNIT_NORMAL), ("u_uv_map", UNIT_UV), ("u_surface_map", UNIT_SURFACE)):
            GL.glUniform1i(at(name), unit)
        for material in range(MAX_MATERIALS):
            present = material < len(atlas.diffuse)
            GL.glUniform1i(at(f"u_diffuse[{material}]"), UNIT_DIFFUSE0 + material)
            GL.glUniform1i(at(f"u_variations[{material}]"), 1)
            GL.glUniform1i(at(f"u_has_regions[{material}]"), int(present and atlas.has_regions[material]))
        GL.glUniform1i(at("u_material_count"), len(atlas.diffuse))
        GL.glUniform1i(at("u_has_surface"), int(atlas.surface_map is not None))
        GL.glUniform1i(at("u_tile_size"), atlas.tile_size)
        GL.glUniform1i(at("u_azimuth_count"), len(atlas.azimuths_deg))
        GL.glUniform4i(at("u_crop"), *(atlas.crop or (0, 0, atlas.tile_size, atlas.tile_size)))
        GL.glUniform1f(at("u_radius"), float(atlas.radius))
        GL.glUniform3f(at("u_center"), *np.asarray(atlas.center, dtype=np.float64).tolist())
        GL.glUniform1fv(at("u_azimuths_deg"), len(atlas.azimuths_deg), np.asarray(atlas.azimuths_deg, dtype=np.float32))
        GL.glUniform1fv(at("u_elevations_deg"), len(atlas.elevations_deg), np.asarray(atlas.elevations_deg, dtype=np.float32))

    def _delete_textures(self) -> None:
        from OpenGL import GL

        if self._textures:
            GL.glDeleteTextures(len(self._textures), self._textures)
        self._textures = []

    def delete(self) -> None:
        """Free the GL objects (the context must be current)."""
        from OpenGL import GL

        self._delete_textures()
        self._delete_framebuffer()
        if self._vao is not None:
            GL.glDeleteVertexArrays(1, [self._vao])
        for program in self._programs.values():
            GL.glDeleteProgram(program)
        self.__init__()
