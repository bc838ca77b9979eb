"""Run by crowdbake.formats.alembic in a child process with Blender's `bpy` module; not imported by crowdbake.

    python bpy_alembic_dump.py CACHE.abc OUT_DIR FPS START_TIME SAMPLES [OBJECT_NAME]

Imports the Alembic file into an empty Blender scene, evaluates one mesh at the given sample times
(Blender frame = time * FPS, the scene set to that rate), and writes into OUT_DIR:

    meta.json      {"object", "objects", "points", "polygons", "corners", "has_uvs"}
    topology.bin   int32 polygon sizes (polygons), int32 corner vertex indices (corners),
                   float32 corner UVs (corners, 2) in Blender's convention (v up) if has_uvs
    frames.bin     per sample: float32 world matrix (4, 4) row-major, then float32 points (points, 3),
                   in Blender's Z-up world (the importer turns Alembic's Y-up into Z-up)

Only the standard library and bpy are used here (bpy's own numpy pin must not matter). A problem is
reported as one line on stderr starting with "crowdbake-alembic:" and exit status 2.
"""
import array
import json
import math
import os
import struct
import sys


def fail(message):
    sys.stderr.write(f"crowdbake-alembic: {message}\n")
    sys.exit(2)


def main(argv):
    if len(argv) not in (6, 7):
        fail("usage: bpy_alembic_dump.py CACHE.abc OUT_DIR FPS START_TIME SAMPLES [OBJECT_NAME]")
    path, out_dir, fps, start_time, samples = argv[1], argv[2], float(argv[3]), float(argv[4]), int(argv[5])
    wanted = argv[6] if len(argv) == 7 else None
    import bpy

    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    # Blender maps frame f to time f / (fps / fps_base); an integer fps with a base keeps 29.97 exact.
    scene.render.fps = max(1, round(fps))
    scene.render.fps_base = scene.render.fps / fps
    if "FINISHED" not in bpy.ops.wm.alembic_import(filepath=path, set_frame_range=False):
        fail("Blender could not import the file as Alembic")
    meshes = [obj for obj in scene.objects if obj.type == "MESH"]
    names = sorted(obj.name for obj in meshes)
    if not meshes:
        fail("the Alembic file holds no mesh")
    if wanted is not None:
        chosen = [obj for obj in meshes if obj.name == wanted]
        if not chosen:
            fail(f"no mesh named {wanted!r}; the file has {', '.join(names)}")
    elif len(meshes) > 1:
        fail(f"the Alembic file holds {len(meshes)} meshes ({', '.join(names)}); name the garment's")
    else:
        chosen = meshes
    obj = chosen[0]

    def evaluated_mesh():
        depsgraph = bpy.context.evaluated_depsgraph_get()
        return obj.evaluated_get(depsgraph).data, obj.evaluated_get(depsgraph).matrix_world

    first_frame = start_time * fps
    scene.frame_set(math.floor(first_frame), subframe=first_frame - math.floor(first_frame))
    mesh, _ = evaluated_mesh()
    points, polygons, corners = len(mesh.vertices), len(mesh.polygons), len(mesh.loops)
    # The caller's budget (crowdbake.formats.alembic.MAX_POINT_SAMPLES), checked before any frame is written.
    budget = int(os.environ.get("CROWDBAKE_ABC_MAX_POINT_SAMPLES", "0"))
    if budget and samples * points > budget:
        fail(f"{samples} samples of {points} points are {samples * points} point samples, more than the {budget} a cache may hold")
    sizes = array.array("i", [0]) * polygons
    mesh.polygons.foreach_get("loop_total", sizes)
    starts = array.array("i", [0]) * polygons
    mesh.polygons.foreach_get("loop_start", starts)
    running = 0
    for start, size in zip(starts, sizes):
        if start != running:
            fail("polygon corners are not stored in polygon order")
        running += size
    corner_vertices = array.array("i", [0]) * corners
    mesh.loops.foreach_get("vertex_index", corner_vertices)
    uv_layer = mesh.uv_layers.active
    with open(os.path.join(out_dir, "topology.bin"), "wb") as handle:
        sizes.tofile(handle)
        corner_vertices.tofile(handle)
        if uv_layer is not None:
            uvs = array.array("f", [0.0]) * (2 * corners)
            uv_layer.data.foreach_get("uv", uvs)
            uvs.tofile(handle)

    with open(os.path.join(out_dir, "frames.bin"), "wb") as handle:
        for sample in range(samples):
            frame = (start_time + sample / fps) * fps
            whole = math.floor(frame + 1e-6)
            scene.frame_set(whole, subframe=max(0.0, frame - whole))
            mesh, matrix = evaluated_mesh()
            if len(mesh.vertices) != points:
                fail(f"the mesh changes topology: {len(mesh.vertices)} points at sample {sample}, {points} at the first")
            handle.write(struct.pack("<16f", *[value for row in matrix for value in row]))
            coordinates = array.array("f", [0.0]) * (3 * points)
            mesh.vertices.foreach_get("co", coordinates)
            coordinates.tofile(handle)
    meta = {"object": obj.name, "objects": names, "points": points, "polygons": polygons, "corners": corners,
            "has_uvs": uv_layer is not None}
    with open(os.path.join(out_dir, "meta.json"), "w") as handle:
        json.dump(meta, handle)


if __name__ == "__main__":
    main(sys.argv)
