"""A cloth cache in memory: frames of point positions with the mesh they move (ClothCache), and the
mesh of a polygon list with per-corner UVs split at UV seams (mesh_from_polygons), which the readers of
crowdbake.formats.cloth_cache and crowdbake.formats.alembic build.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from crowdbake.formats.obj import ObjMesh


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
