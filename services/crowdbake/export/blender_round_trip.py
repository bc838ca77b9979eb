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

With `--bundle DIR` (the bundle the export was made from), it then compares what Blender played with
the bundle's own pose caches: every animation (clip or transition) at its keys, every mesh of the GLB's
LOD (from the `export.json` beside the GLB, else LOD 0). It prints one line per animation with the
largest distance per mesh, then a verdict, and exits 1 when a distance passes the bound: `--tolerance-mm`
(default 1), plus a part's stated `max_mm` where the export approximates it with bones.
"""
from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np


def _key_frames(mesh) -> dict[int, float]:
    """Blender frame at which the action shows pose frame k, for every frame_k shape key. A key shows frame k
    with shape key frame_k and those of its path to the base at 1 (crowdbake.export.glb.QuantizedPart), so
    of the keys where frame_k is 1, the one with the fewest keys at 1 shows frame k itself (an older
    export's one-hot keys: the one where frame_k peaks)."""
    action = mesh.shape_keys.animation_data.action
    curves = {c.data_path: c for c in _fcurves(action)}
    full: dict[float, set[int]] = {}  # key time -> the frame_k keys at 1 there
    for block in mesh.shape_keys.key_blocks[1:]:
        curve = curves.get(f'key_blocks["{block.name}"].value')
        if block.name.startswith("frame_") and curve is not None:
            for point in curve.keyframe_points:
                if point.co[1] > 0.5:
                    full.setdefault(float(point.co[0]), set()).add(int(block.name[len("frame_"):]))
    peaks: dict[int, float] = {}
    for time, frames in sorted(full.items(), key=lambda item: (len(item[1]), item[0])):
        for frame in frames:
            peaks.setdefault(frame, time)
    return peaks


def _loop_keys(bpy) -> list[float]:
    """The first action's key frames less its last (a loop's last key is its first pose again): frame k of a
    one-clip export when no mesh has a frame_k shape key for every frame (bodies and garments all skinned)."""
    if not bpy.data.actions:
        return []
    keys = sorted({point.co[0] for curve in _fcurves(bpy.data.actions[0]) for point in curve.keyframe_points})
    return keys[:-1]


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
    # frame step before frame_1 peaks, every weight 0. A skinned body keys only its corrective frames, so
    # the mesh with the most frame_k keys says; with none keying every frame, the first action's keys do.
    keyed = max((ob.data for ob in meshes if ob.data.shape_keys and ob.data.shape_keys.animation_data),
                key=lambda mesh: len(mesh.shape_keys.key_blocks), default=None)
    peaks = _key_frames(keyed) if keyed is not None else {}
    if peaks and 0 not in peaks and 1 in peaks and 2 in peaks:
        peaks[0] = peaks[1] - (peaks[2] - peaks[1])
    loop = _loop_keys(bpy)
    frames = ([peaks[k] for k in sorted(peaks)] if len(peaks) >= len(loop) else loop) or [float(scene.frame_start)]
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


@dataclass(frozen=True)
class AnimationDistance:
    """The largest distance (mm) between what Blender played and the bundle, per mesh, in one animation."""

    animation: str
    max_mm: dict[str, float]


def played_against_bundle(seen: dict[str, np.ndarray], info: dict, meshes: list[tuple[str, np.ndarray]], plans: list) -> list[AnimationDistance]:
    """Compare Blender's playback with the bundle's frames.

    seen: main()'s arrays (`mesh_<part>` (F, V, 3), `action_<k>_mesh_<part>` (K, V, 3), metres); info: its
    JSON; meshes: (part, the bundle's (F, V, 3) positions) of the GLB's LOD; plans: the bundle's
    crowdbake.export.animations.AnimationPlan list. A one-clip export's shape keys peak at every frame, so
    its animation is compared frame by frame (`mesh_<part>`); otherwise each action at its keys. An
    animation Blender does not list, or a shape that disagrees, is an infinite distance: a failure."""
    actions = list(info.get("actions", []))
    distances = []
    for plan in plans:
        per_mesh = {}
        for part, positions in meshes:
            expected = positions[plan.keys]
            played = seen.get(f"action_{actions.index(plan.name)}_mesh_{part}") if plan.name in actions else None
            if (played is None or played.shape != expected.shape) and len(plans) == 1:
                played, expected = seen.get(f"mesh_{part}"), positions
            if played is None or played.shape != expected.shape:
                per_mesh[part] = float("inf")
            else:
                per_mesh[part] = float(np.linalg.norm(played.astype(np.float64) - expected, axis=-1).max() * 1000.0)
        distances.append(AnimationDistance(plan.name, per_mesh))
    return distances


def compare_with_bundle(glb: Path, out: Path, bundle_dir: Path, tolerance_mm: float) -> int:
    """Read main()'s OUT.npz and the bundle; print the comparison; 0 when every distance is within its
    bound, else 1."""
    from crowdbake.export.animations import animation_plans
    from crowdbake.formats.bundle import verify_bundle

    bundle = verify_bundle(bundle_dir)
    sidecar_path = glb.parent / "export.json"
    lod, bones_mm = 0, {}
    if sidecar_path.is_file():
        sidecar = json.loads(sidecar_path.read_text())
        entry = next((entry for entry in sidecar.get("lods", []) if entry.get("glb") == glb.name), None)
        if entry is not None:
            lod = int(entry["lod"])
            bones_mm = {part["part"]: float(part["bones"]["max_mm"]) for part in entry.get("parts", []) if "bones" in part}
    meshes = [(mesh["part"], bundle.pose_caches[mesh["file"]].positions) for mesh in bundle.manifest["meshes"] if mesh["lod"] == lod]
    with np.load(out) as archive:
        seen = {key: archive[key] for key in archive.files}
    info = json.loads(str(seen.pop("info")))
    failed = []
    for distance in played_against_bundle(seen, info, meshes, animation_plans(bundle.ranges)):
        parts = ", ".join(f"{part} {mm:.2f} mm" for part, mm in distance.max_mm.items())
        print(f"{distance.animation}: {parts}")
        failed += [f"{distance.animation} / {part}" for part, mm in distance.max_mm.items() if not mm <= tolerance_mm + bones_mm.get(part, 0.0)]
    bound = f"{tolerance_mm:g} mm" + (" (plus the stated bone error of " + ", ".join(bones_mm) + ")" if bones_mm else "")
    if failed:
        print(f"Blender's playback is farther than {bound} from the bundle in: {'; '.join(failed)}", file=sys.stderr)
        return 1
    print(f"Blender plays every animation of LOD {lod} within {bound} of the bundle {bundle_dir}")
    return 0


def parse_arguments(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m crowdbake.export.blender_round_trip",
                                     description="Play an export's .glb in Blender; with --bundle, compare it with the bundle.")
    parser.add_argument("glb", type=Path, help="a .glb of an export")
    parser.add_argument("out", type=Path, help="the .npz to write (vertices at each key of each animation)")
    parser.add_argument("--bundle", type=Path, help="the bundle the export was made from: compare with its pose caches")
    parser.add_argument("--tolerance-mm", type=float, default=1.0, help="largest distance allowed (default 1)")
    return parser.parse_args(argv)


if __name__ == "__main__":
    arguments = parse_arguments(sys.argv[1:])
    main(arguments.glb, arguments.out)
    if arguments.bundle is not None:
        raise SystemExit(compare_with_bundle(arguments.glb, arguments.out, arguments.bundle, arguments.tolerance_mm))
