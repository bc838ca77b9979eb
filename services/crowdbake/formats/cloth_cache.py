"""Every cloth cache crowdbake accepts, read into one typed object.

    read_cloth_cache(cache, mesh=None, ...) -> ClothCache

| input                          | cache            | mesh (rest, faces, UVs) | fps                          |
|--------------------------------|------------------|-------------------------|------------------------------|
| PC2 point cache                | `.pc2`           | `.obj` (required)       | None: PC2 stores the spacing of samples in frames (`frame_step`), not a rate |
| OBJ sequence                   | `.zip` of `.obj` | the first frame         | None                         |
| MDD point cache (LightWave, Blender, Houdini) | `.mdd` | `.obj` (required) | from the frame times in the file |
| Alembic (`crowdbake[alembic]`) | `.abc`           | from the `.abc`          | from the archive's time sampling |

Frames are in point order: point k is OBJ position k (for an OBJ rest mesh) or Alembic point k;
`ClothCache.mesh.source_index` maps split (UV seam) vertices back to points, as crowdbake.formats.obj
documents. Units are the file's; crowdbake.bake.placement checks them (and the up axis) against the
character and converts when told.
"""
from __future__ import annotations

import os
import re
import threading
import zipfile
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

import numpy as np

from crowdbake.formats.obj import ObjMesh, read_obj

CACHE_FORMATS = {".pc2": "pc2", ".mdd": "mdd", ".abc": "alembic", ".zip": "obj-sequence"}
# Frames of an OBJ sequence read here at most (the upload path has its own zip-bomb guards in
# crowdbake.validation; this reader is for files already on disk).
MAX_SEQUENCE_FRAMES = 100_000


@dataclass(frozen=True)
class ClothCache:
    """A garment's simulation, whatever file it came from.

    mesh: the rest mesh (positions (V, 3) float32, faces (T, 3) uint32, uvs (V, 2) float32 in glTF's
    convention (v down) or None, source_index (V,) int64, position_count P); frames: (F, P, 3) float32,
    point order, the file's units (metres once placement has converted it); fps: frames per second
    when the file says, else None; frame_step: frames between samples (PC2's sampleRate, else 1);
    source: "pc2" | "mdd" | "alembic" | "obj-sequence".
    """

    mesh: ObjMesh
    frames: np.ndarray
    fps: float | None
    frame_step: float
    source: str

    @property
    def rest_vertices(self) -> np.ndarray:
        """(V, 3) float32 rest positions (UV seams split)."""
        return self.mesh.positions

    @property
    def faces(self) -> np.ndarray:
        return self.mesh.faces

    @property
    def uvs(self) -> np.ndarray | None:
        return self.mesh.uvs

    @property
    def frame_count(self) -> int:
        return int(self.frames.shape[0])

    @property
    def point_count(self) -> int:
        return int(self.frames.shape[1])

    def vertex_frames(self) -> np.ndarray:
        """(F, V, 3) frames per mesh vertex (seam copies included)."""
        return self.frames[:, self.mesh.source_index]

    def fps_or(self, default_base_fps: float) -> float:
        """The cache's frame rate: its own when known, else default_base_fps / frame_step."""
        return float(self.fps) if self.fps is not None else default_base_fps / self.frame_step

    def with_frames(self, frames: np.ndarray, rest_positions: np.ndarray | None = None) -> "ClothCache":
        """The same cache with converted frames (F, P, 3) and optionally converted rest positions (V, 3)."""
        mesh = self.mesh
        if rest_positions is not None:
            mesh = ObjMesh(np.asarray(rest_positions, np.float32), mesh.faces, mesh.uvs, mesh.source_index, mesh.position_count)
        return ClothCache(mesh, np.asarray(frames, np.float32), self.fps, self.frame_step, self.source)


def mesh_from_polygons(points: np.ndarray, polygon_sizes: np.ndarray, corner_points: np.ndarray, corner_uvs: np.ndarray | None) -> ObjMesh:
    """A rest mesh from polygons, laid out as crowdbake.formats.obj.read_obj lays out an OBJ.

    points (P, 3); polygon_sizes (N,) int >= 3; corner_points (sum of sizes,) int into points;
    corner_uvs (sum of sizes, 2) float with v up (OBJ's and Blender's convention) or None.
    Polygons are fan-triangulated. Where a point has several UVs (a seam) it is split: the first P
    vertices are the points with the UV of their first use, copies follow; source_index maps back.
    """
    points = np.asarray(points, np.float32)
    sizes = np.asarray(polygon_sizes, np.int64)
    corners = np.asarray(corner_points, np.int64)
    if (sizes < 3).any() or sizes.sum() != len(corners):
        raise ValueError("polygons need 3 or more corners, and the corner count must match their sizes")
    if corners.size and (corners.min() < 0 or corners.max() >= len(points)):
        raise ValueError(f"a polygon corner names point {corners.max()}, there are {len(points)}")
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    # Fan triangles (start, start+k, start+k+1) for k = 1 .. size-2 of every polygon, as corner indices.
    polygon_of_triangle = np.repeat(np.arange(len(sizes)), sizes - 2)
    k = np.arange(len(polygon_of_triangle)) - np.repeat(np.cumsum(sizes - 2) - (sizes - 2), sizes - 2) + 1
    first = starts[polygon_of_triangle]
    triangle_corners = np.stack([first, first + k, first + k + 1], axis=1)
    if corner_uvs is None:
        faces = corners[triangle_corners]
        return ObjMesh(points.copy(), faces.astype(np.uint32), None, np.arange(len(points), dtype=np.int64), len(points))
    uvs = np.asarray(corner_uvs, np.float64).copy()
    uvs[:, 1] = 1.0 - uvs[:, 1]  # to glTF's convention, as read_obj does
    # One vertex per distinct (point, uv); the first use of each point keeps the point's own index.
    keys = np.round(uvs * 2**20).astype(np.int64)  # UVs equal to 1e-6 are one UV
    corner_vertex = np.empty(len(corners), np.int64)
    vertex_uv = np.zeros((len(points), 2), np.float64)
    first_uv_set = np.zeros(len(points), bool)
    extra_sources: list[int] = []
    extra_uvs: list[np.ndarray] = []
    seen: dict[tuple[int, int, int], int] = {}
    for corner in range(len(corners)):  # file order: the first use wins, as in read_obj
        point = corners[corner]
        key = (int(point), int(keys[corner, 0]), int(keys[corner, 1]))
        vertex = seen.get(key)
        if vertex is None:
            if not first_uv_set[point]:
                vertex = int(point)
                first_uv_set[point] = True
                vertex_uv[point] = uvs[corner]
            else:
                vertex = len(points) + len(extra_sources)
                extra_sources.append(int(point))
                extra_uvs.append(uvs[corner])
            seen[key] = vertex
        corner_vertex[corner] = vertex
    source_index = np.concatenate([np.arange(len(points)), np.asarray(extra_sources, np.int64)])
    positions = points[source_index]
    all_uvs = np.concatenate([vertex_uv, np.asarray(extra_uvs).reshape(-1, 2)]).astype(np.float32)
    faces = corner_vertex[triangle_corners].astype(np.uint32)
    return ObjMesh(positions, faces, all_uvs, source_index, len(points))


def _natural_key(name: str) -> list:
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", name)]


def read_obj_sequence(path: str | os.PathLike) -> ClothCache:
    """A zip of OBJ frames (one topology, natural name order) -> ClothCache with the first frame as the
    rest mesh. For files on disk; uploads go through crowdbake.validation's guarded converter."""
    import tempfile

    path = Path(path)
    try:
        archive = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError) as error:
        raise ValueError(f"{path}: not a readable zip: {error}") from None
    with archive, tempfile.TemporaryDirectory(prefix="obj-sequence-") as scratch:
        names = sorted((info.filename for info in archive.infolist() if info.filename.lower().endswith(".obj")
                        and not info.filename.startswith("__MACOSX/") and not PurePosixPath(info.filename).name.startswith("._")),
                       key=_natural_key)
        if not names:
            raise ValueError(f"{path}: the zip holds no .obj frame")
        if len(names) > MAX_SEQUENCE_FRAMES:
            raise ValueError(f"{path}: {len(names)} frames, at most {MAX_SEQUENCE_FRAMES}")
        rest: ObjMesh | None = None
        frames = []
        for index, name in enumerate(names):
            frame_path = Path(scratch) / f"frame{index}.obj"
            frame_path.write_bytes(archive.read(name))
            mesh = read_obj(frame_path)
            if rest is None:
                rest = mesh
            elif mesh.position_count != rest.position_count or not np.array_equal(mesh.source_index[mesh.faces], rest.source_index[rest.faces]):
                raise ValueError(f"{path}: {name} changes the topology of the first frame")
            frames.append(mesh.positions[: mesh.position_count])
            frame_path.unlink()
    return ClothCache(rest, np.stack(frames).astype(np.float32), None, 1.0, "obj-sequence")


def read_cloth_cache(cache: str | os.PathLike, mesh: str | os.PathLike | None = None, alembic_object: str | None = None,
                     cancel: threading.Event | None = None) -> ClothCache:
    """Read any supported cloth cache (by extension, see the module table) into a ClothCache.

    PC2 and MDD need `mesh` (their OBJ rest mesh, one position per cache point); an Alembic file carries
    its own mesh (`alembic_object` names the garment when the file holds several meshes); an OBJ
    sequence's first frame is its rest mesh. Raises ValueError naming the file for anything wrong,
    including an Alembic file when the `crowdbake[alembic]` extra is not installed.
    `cancel` (another thread sets it) ends an Alembic read's Blender child: alembic.ReadCancelled.
    """
    cache = Path(cache)
    kind = CACHE_FORMATS.get(cache.suffix.lower())
    if kind is None:
        raise ValueError(f"{cache}: unknown cloth cache type {cache.suffix!r}; use one of {', '.join(sorted(CACHE_FORMATS))}")
    if kind == "alembic":
        from crowdbake.formats.alembic import read_alembic

        return read_alembic(cache, alembic_object, cancel)
    if kind == "obj-sequence":
        return read_obj_sequence(cache)
    if mesh is None:
        raise ValueError(f"{cache}: a .{kind} cache needs its rest mesh (.obj)")
    rest = read_obj(mesh)
    if kind == "pc2":
        from crowdbake.formats.pc2 import read_pc2

        point_cache = read_pc2(cache)
        frames, fps, step = point_cache.points, None, point_cache.sample_rate
    else:
        from crowdbake.formats.mdd import read_mdd

        mdd = read_mdd(cache)
        frames, fps, step = mdd.points, mdd.fps, 1.0
    if frames.shape[1] != rest.position_count:
        raise ValueError(f"{cache}: {frames.shape[1]} points per frame, but {Path(mesh).name} has {rest.position_count} positions")
    return ClothCache(rest, frames, fps, step, kind)


def write_pc2_obj(cache: ClothCache, pc2_path: str | os.PathLike, obj_path: str | os.PathLike) -> None:
    """Store any ClothCache as the PC2 + OBJ pair the bake reads (rest mesh = cache.mesh, UVs kept).

    The OBJ is written with one `v` per point and `vt` per split vertex, so read_obj gives back the same
    vertices. The frame rate is not stored (PC2 has no field for it): keep `cache.fps` beside it."""
    from crowdbake.formats.obj import write_obj
    from crowdbake.formats.pc2 import write_pc2

    mesh = cache.mesh
    point_faces = mesh.source_index[mesh.faces.astype(np.int64)]
    rest_points = np.zeros((mesh.position_count, 3), np.float32)
    rest_points[mesh.source_index] = mesh.positions
    if mesh.uvs is None:
        write_obj(obj_path, rest_points, point_faces)
    else:
        write_obj(obj_path, rest_points, point_faces, uvs=mesh.uvs, uv_faces=mesh.faces.astype(np.int64))
    write_pc2(pc2_path, cache.frames, start_frame=0.0, sample_rate=cache.frame_step)
