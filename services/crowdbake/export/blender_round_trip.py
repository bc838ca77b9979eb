"""An export's .glb as Blender sees it: imported with Blender's own glTF importer, its cloth loop played.

    python -m crowdbake.export.blender_round_trip GLB OUT.npz

Run in a child process (Blender's `bpy` module, the `crowdbake[alembic]` extra, is large and keeps
global state). Writes OUT.npz:

- `mesh_<name>`: (F, V, 3) float32 world positions of each mesh at each frame of the active action (a v1 export: `cycle`),
  in glTF's axes (+Y up; Blender's importer turns glTF (x, y, z) into (x, -z, y) and back is applied
  here), evaluated by Blender at the time the animation keys frame k (shape keys driven by its action);
- `action_<k>_mesh_<name>`: (K, V, 3) the same at every key of action k (`info["actions"]`, one per glTF
  animation: a clip or a transition), that action assigned to every animated data-block;
- `info`: JSON with the scene's frame rate, the actions, each action's key frames (`action_keys`), the
  material names, the KHR_materials_variants variant names and per mesh the variants its materials are
  mapped for.

crowdbake.export.writer's tests compare these with the bundle's pose caches.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np


def _key_frames(mesh) -> dict[int, float]:
    """Blender frame at which shape key frame_k peaks, for every frame_k key (the one-hot keys of `cycle`)."""
    action = mesh.shape_keys.animation_data.action
    curves = {c.data_path: c for c in _fcurves(action)}
    peaks = {}
    for block in mesh.shape_keys.key_blocks[1:]:
        curve = curves.get(f'key_blocks["{block.name}"].value')
        if block.name.startswith("frame_") and curve is not None:
            peaks[int(block.name[len("frame_"):])] = max(curve.keyframe_points, key=lambda p: p.co[1]).co[0]
    return peaks


def _fcurves(action):
    """Every F-curve of an action (Blender 5 keeps them in layers, strips and channel bags)."""
    if hasattr(action, "fcurves") and len(action.fcurves):
        return list(action.fcurves)
    curves = []
    for layer in action.layers:
        for strip in layer.strips:
            for bag in strip.channelbags:
                curves.extend(bag.fcurves)
    return curves


def _play(bpy, scene, ob, frames: list[float]) -> np.ndarray:
    """(len(frames), V, 3) float32 world positions of mesh object `ob` at each (fractional) scene frame,
    in glTF's axes."""
    positions = []
    for frame in frames:
        scene.frame_set(int(np.floor(frame)), subframe=float(frame - np.floor(frame)))
        evaluated = ob.evaluated_get(bpy.context.evaluated_depsgraph_get())
        data = evaluated.to_mesh()
        local = np.array([v.co[:] for v in data.vertices], dtype=np.float64)
        world = local @ np.array(ob.matrix_world)[:3, :3].T + np.array(ob.matrix_world)[:3, 3]
        evaluated.to_mesh_clear()
        positions.append(np.stack([world[:, 0], world[:, 2], -world[:, 1]], axis=1))
    return np.asarray(positions, dtype=np.float32)


def main(glb: Path, out: Path) -> None:
    from crowdbake.export.bpy_import import import_bpy

    bpy = import_bpy()

    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.import_scene.gltf(filepath=str(glb))
    scene = bpy.context.scene
    meshes = [ob for ob in bpy.data.objects if ob.type == "MESH"]
    if not meshes:
        raise SystemExit(f"{glb}: Blender imported no mesh")
    # Each frame_k key peaks at frame k; an export whose base is frame 0 (no frame_0 key) shows frame 0 one
    # frame step before frame_1 peaks, every weight 0.
    keyed = next((ob.data for ob in meshes if ob.data.shape_keys and ob.data.shape_keys.animation_data), None)
    peaks = _key_frames(keyed) if keyed is not None else {}
    if peaks and 0 not in peaks and 1 in peaks and 2 in peaks:
        peaks[0] = peaks[1] - (peaks[2] - peaks[1])
    frames = [peaks[k] for k in sorted(peaks)] or [float(scene.frame_start)]
    arrays = {f"mesh_{ob.name}": _play(bpy, scene, ob, frames) for ob in meshes}
    # Every action in turn on every animated data-block (shape keys, armatures): the importer makes one
    # action per glTF animation, its slots named for the data-blocks, so assigning it finds their slots.
    animated = [d for ob in bpy.data.objects for d in (ob, ob.data.shape_keys if ob.type == "MESH" else None)
                if d is not None and d.animation_data is not None]
    actions = list(bpy.data.actions)
    action_keys = {}
    for k, action in enumerate(actions):
        for data in animated:
            data.animation_data.action = action
        keys = sorted({point.co[0] for curve in _fcurves(action) for point in curve.keyframe_points})
        action_keys[action.name] = keys
        for ob in meshes:
            arrays[f"action_{k}_mesh_{ob.name}"] = _play(bpy, scene, ob, keys)
    info = {
        "fps": scene.render.fps / scene.render.fps_base,
        "frames": frames,
        "actions": [action.name for action in actions],
        "action_keys": action_keys,
        "materials": sorted(m.name for m in bpy.data.materials),
        "variants": [v.name for v in getattr(scene, "gltf2_KHR_materials_variants_variants", [])],
        "mesh_variants": {
            ob.name: sorted({variant.variant.variant_idx for mapping in ob.data.gltf2_variant_mesh_data for variant in mapping.variants})
            for ob in meshes if hasattr(ob.data, "gltf2_variant_mesh_data")
        },
    }
    np.savez(out, info=np.array(json.dumps(info)), **arrays)


if __name__ == "__main__":
    if len(sys.argv) != 3:
        raise SystemExit("usage: python -m crowdbake.export.blender_round_trip GLB OUT.npz")
    main(Path(sys.argv[1]), Path(sys.argv[2]))
