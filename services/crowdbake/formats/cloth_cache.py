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
from pathlib import Path, PurePosixPath

import numpy as np

from crowdbake.formats.cloth_frames import ClothCache, mesh_from_polygons  # noqa: F401 (imported from here too)
from crowdbake.formats.obj import ObjMesh, read_obj

CACHE_FORMATS = {".pc2": "pc2", ".mdd": "mdd", ".abc": "alembic", ".zip": "obj-sequence"}
# Frames of an OBJ sequence read here at most (the upload path has its own zip-bomb guards in
# crowdbake.validation; this reader is for files already on disk).
MAX_SEQUENCE_FRAMES = 100_000


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
