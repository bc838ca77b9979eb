"""A cloth cache as every entry point takes it: read from any supported file, its frame rate decided by
one rule, and placed on the character (up axis, units, overlap) before anything is baked.

`crowdbake cycle`, `crowdbake bake` (through the validate stage) and the REST bake request all go
through here, so a Z-up or centimetre cache is refused with the same words everywhere, naming the
parameter that fixes it (`up`, `units`), and converted the same way when that parameter is given.

    read_cloth(cache, mesh)               -> ClothCache            (InputError "cloth" / "cloth_mesh")
    body_at_rest(character)               -> (V, 3) Y-up metres    (the character at its animation's time 0;
                                                                    InputError "character" if not 0.3-10 m tall)
    place_cloth(cache, body, up, units)   -> ClothCache in Y-up metres, or InputError "up" / "units" / "cloth"
    check_garment_fit(character, cache, fps) -> GarmentFit, or InputError "cloth" when the garment does not
                                            follow this body over the cache (crowdbake.bake.garment_fit)
"""
from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from crowdbake.bake.garment_fit import FAR_FROM_BODY, MAX_FAR_FRACTION, GarmentFit, checked_frames, measure_garment_fit
from crowdbake.bake.placement import Placement, check_placement
from crowdbake.errors import InputError
from crowdbake.formats.cloth_cache import CACHE_FORMATS, ClothCache, read_cloth_cache

# Caches that carry their own rest mesh; the others need an OBJ beside them.
SELF_CONTAINED = {".abc", ".zip"}
CACHE_SUFFIXES = tuple(sorted(CACHE_FORMATS))


def needs_mesh(cache: str | os.PathLike) -> bool:
    """True for caches that need an OBJ rest mesh (PC2, MDD)."""
    return Path(cache).suffix.lower() not in SELF_CONTAINED


def read_cloth(cache: str | os.PathLike, mesh: str | os.PathLike | None = None, cache_field: str = "cloth",
               mesh_field: str = "cloth_mesh") -> ClothCache:
    """Read any cloth cache crowdbake takes (crowdbake.formats.cloth_cache) and check it can be baked.

    Raises InputError naming `cache_field` or `mesh_field`: an unknown type, a PC2/MDD without its
    mesh, a mesh given to a cache that carries its own, a parse error, no faces, non-finite points."""
    cache = Path(cache)
    if cache.suffix.lower() not in CACHE_FORMATS:
        raise InputError(f"{cache.name}: a cloth cache must be one of {', '.join(CACHE_SUFFIXES)}", cache_field)
    if needs_mesh(cache) and mesh is None:
        raise InputError(f"{cache.name}: a {cache.suffix.lower()} cache needs its rest mesh (.obj)", mesh_field)
    if not needs_mesh(cache) and mesh is not None:
        raise InputError(f"{cache.name} carries its own mesh: leave out the .obj", mesh_field)
    if mesh is not None and Path(mesh).suffix.lower() != ".obj":
        raise InputError(f"{Path(mesh).name}: the rest mesh must be an .obj", mesh_field)
    try:
        result = read_cloth_cache(cache, mesh)
    except (ValueError, OSError) as error:
        text = str(error).splitlines()[0] if str(error) else type(error).__name__
        # A message naming the mesh (its parse error, or a point count that does not match it) is the mesh's.
        field = mesh_field if mesh is not None and Path(mesh).name in text.replace(str(cache), "") else cache_field
        raise InputError(text, field) from None
    if len(result.faces) == 0:
        raise InputError(f"{cache.name}: the garment's mesh has no faces", mesh_field if mesh is not None else cache_field)
    if result.frame_count == 0:
        raise InputError(f"{cache.name}: the cache has no frames", cache_field)
    if not np.isfinite(result.frames).all():
        raise InputError(f"{cache.name}: the cache holds NaN or infinite positions", cache_field)
    return result


# Heights (metres, after every node transform) a character may have. A human's 0.5-3 m would refuse
# robots and creatures, so the range is wide: a 0.3 m toy robot to a 10 m mech. Outside it the file's
# scale is wrong: a Mixamo-style export whose root node scales it to 0.215 m, or centimetres read as metres.
CHARACTER_HEIGHT_RANGE_M = (0.3, 10.0)


def _root_node_scale(character) -> float:
    """The uniform scale the nodes above the skeleton's root joint apply (1 without joints)."""
    parents = np.asarray(getattr(character, "joint_parents", []))
    transforms = np.asarray(getattr(character, "joint_parent_transforms", []), np.float64)
    roots = np.flatnonzero(parents < 0)
    if roots.size == 0 or transforms.ndim != 3:
        return 1.0
    return float(abs(np.linalg.det(transforms[roots[0]][:3, :3])) ** (1.0 / 3.0))


def check_character_height(character, body: np.ndarray) -> None:
    """Refuse (InputError "character") a body (V, 3) Y-up metres outside CHARACTER_HEIGHT_RANGE_M, naming
    the scale its root node applies and what to change: no parameter scales the character."""
    height = float(np.ptp(body[:, 1])) if len(body) else 0.0
    low, high = CHARACTER_HEIGHT_RANGE_M
    if low <= height <= high:
        return
    scale = _root_node_scale(character)
    names = list(getattr(character, "joint_names", []))
    root = names[int(np.flatnonzero(np.asarray(character.joint_parents) < 0)[0])] if names else ""
    cause = (f"the node above its root joint {root!r} scales it by {scale:.3g}: set that node's scale in the file "
             f"(to about {scale * 1.75 / height:.3g} for a 1.75 m human)" if abs(scale - 1.0) > 1e-3 else
             "its mesh is in another unit than metres: scale it (or its root node) in the file")
    raise InputError(f"the character is {height:.3g} m tall after its node transforms, outside the {low:g}-{high:g} m crowdbake "
                     f"takes: {cause}; no parameter scales the character (`units` converts only the cloth cache)", "character")


def body_at_rest(character) -> np.ndarray:
    """The character posed at its animation's time 0, (V, 3) float32 Y-up metres: the body the cloth's
    first frame was simulated on. InputError "character" when its height is implausible (check_character_height),
    so a mis-scaled character is refused before its garment is blamed for not fitting it."""
    from crowdbake.bake.skinning import pose_character

    if getattr(character, "animation_duration", 0) and character.animation_duration > 0:
        body = pose_character(character, 1.0, 1)[0][0]
    else:  # the bind pose, with its morph targets at their default weights
        from crowdbake.bake.skinning import apply_morph_targets, morph_weights

        targets = getattr(character, "morph_targets", None) or []
        body = apply_morph_targets(character.positions, character.normals, targets, morph_weights(character, np.zeros(1))[0])[0]
    check_character_height(character, body)
    return body


def refusal_field(placement: Placement) -> str:
    """The parameter a refusal names: up when the axis is wrong, units when only the unit is, else cloth."""
    if placement.suggested_up is not None and placement.suggested_up != placement.up:
        return "up"
    if placement.suggested_units is not None and placement.suggested_units != placement.units:
        return "units"
    return "cloth"


def check_cloth_placement(cloth_first_frame: np.ndarray, body: np.ndarray, up: str | None, units: str | None) -> Placement:
    """check_placement, raising InputError(field up | units | cloth) with its one line when it refuses."""
    placement = check_placement(cloth_first_frame, body, up=up, units=units)
    if not placement.ok:
        raise InputError(placement.message, refusal_field(placement))
    return placement


def place_cloth(cache: ClothCache, body: np.ndarray, up: str | None = None, units: str | None = None) -> ClothCache:
    """The cache in Y-up metres after checking its first frame against `body` (Y-up metres).

    Raises InputError("up" | "units" | "cloth") when the garment does not sit on the character in the
    declared frame (None: detect; a cache that fits only another frame is refused, naming the flag)."""
    placement = check_cloth_placement(cache.frames[0], body, up, units)
    if (placement.up, placement.units) == ("y", "m"):
        return cache
    return cache.with_frames(placement.apply(cache.frames), placement.apply(cache.mesh.positions))


def check_garment_fit(character, cache: ClothCache, fps: float) -> GarmentFit:
    """Refuse (InputError "cloth") a garment, already placed in Y-up metres, that does not follow the
    character posed at each frame's time (animation time = frame / fps, looped over the animation):
    a garment simulated on another character. The message says how far off it is and how to bake anyway
    (`--no-fit`, params.fit = false)."""
    from crowdbake.bake.skinning import pose_at_times

    frames = checked_frames(cache.frame_count)
    duration = float(getattr(character, "animation_duration", 0) or 0)
    times = (frames / float(fps)) % duration if duration > 0 else np.zeros(len(frames))
    body, _ = pose_at_times(character, times)
    fit = measure_garment_fit(cache.frames[frames], body, character.faces, frames)
    if not fit.ok:
        raise InputError(
            f"the garment does not fit the character: over the cache {fit.far_fraction:.0%} of the cloth hangs more than "
            f"{FAR_FROM_BODY * fit.height:.2f} m ({FAR_FROM_BODY:.0%} of its {fit.height:.2f} m height) from its body "
            f"(frame {fit.worst_frame}: {fit.worst_far_fraction:.0%}), above the {MAX_FAR_FRACTION:.0%} a garment simulated on "
            f"this character and animation shows: {_misfit_remedies(character)}", "cloth")
    return fit


def _misfit_remedies(character) -> str:
    """What to do about a misfit. A character of several clips most often means a cache simulated across
    them with no timeline given, so the body was posed with one clip over all of it: the timeline first."""
    names = list(getattr(character, "animation_names", None) or [])
    anyway = "or pass --no-fit (params.fit = false) to bake it anyway"
    if len(names) > 1:
        return (f"if the cache was simulated across several of the character's {len(names)} animations "
                f"({', '.join(repr(name) for name in names[:6])}{', ...' if len(names) > 6 else ''}), give its timeline "
                "(--timeline, or the bake's timeline input); else name the animation it was simulated with, "
                f"simulate the garment on this character, {anyway}")
    return f"simulate the garment on this character (or pick the animation it was simulated with), {anyway}"


_FLAG = re.compile(r"--(up|units) (\w+)")


def rest_wording(message: str) -> str:
    """A placement message as a REST client reads it: `pass --up z` -> `set params.up to "z"`."""
    return _FLAG.sub(lambda m: f'params.{m.group(1)} = "{m.group(2)}"', message).replace(": pass params.", ": set params.")
