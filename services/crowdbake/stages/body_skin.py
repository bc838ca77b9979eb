"""The poses stage's skinned body (crowdbake.bake.body_skin): the joint matrices of every pose frame, built
the way crowdbake.stages.poses.high_parts builds the body's vertex frames, and the body's pose caches
written as CBSK where skinning reproduces those frames (SPEC.md "Skinned pose cache"), else as CBPC.
"""
from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path

import numpy as np

from crowdbake.bake import pose_ranges
from crowdbake.bake.body_skin import (
    SKIN_NORMAL_TOLERANCE_DEG, SKIN_POSITION_TOLERANCE_M, BodySkin, cycle_times, frames_disagreement, pose_body_cycle,
    without_root_offsets,
)
from crowdbake.bake.cycle import estimate_root_offsets
from crowdbake.bake.poses import FALLBACK_NORMAL, PartPoses
from crowdbake.bake.skinning import apply_morph_targets, joint_matrices, morph_weights
from crowdbake.formats.gltf import load_character
from crowdbake.formats.errors import FormatError
from crowdbake.formats.skinned_cache import MAX_JOINTS, decode_skinned_pose_cache, encode_skinned_pose_cache, skin_frames, weight_codes
from crowdbake.stages.records import CycleRecord, JobRecord

logger = logging.getLogger(__name__)


def why_not_skinned(job: JobRecord, character) -> str | None:
    """Why this job's body cannot be stored as skinning (None: it can)."""
    if not job.bake_params.skinning:
        return "the bake was asked for vertex frames (skinning false)"
    if not 1 <= character.joint_count <= MAX_JOINTS:
        return f"{character.joint_count} joints (a skinned pose cache holds 1 to {MAX_JOINTS})"
    return None


def _rows(character, times: np.ndarray) -> np.ndarray:
    """(F, J, 3, 4) float32 skinning matrices' top rows at `times` seconds."""
    return joint_matrices(character, times)[:, :, :3, :]


def _ranges_matrices(character_path: Path, timeline_path: Path, cycle: CycleRecord) -> tuple[np.ndarray, list[np.ndarray]]:
    """crowdbake.stages.poses.ranges_body for matrices: each clip's loop, then each transition with its
    blends; and each clip's morph target weights at its frames ((P, N) each)."""
    from crowdbake.ingest.timeline import read_timeline

    timeline = read_timeline(timeline_path)
    ranges = cycle.bundle_ranges()
    posed, morphs = {}, []
    for clip in timeline.clips():
        character, times = load_character(character_path, animation=clip), np.arange(timeline.period(clip)) / cycle.fps
        rows = _rows(character, times)
        posed[clip] = (rows, rows)
        morphs.append(morph_weights(character, times))
    pieces = [pose_ranges.clip_body(posed[clip.name], phase, clip.frames)[0] for clip, phase in zip(ranges.clips, cycle.ranges["clip_phases"])]
    pieces += [pose_ranges.body_at_cache_frames(posed, timeline, np.arange(t.source_start_frame, t.source_end_frame))[0] for t in ranges.transitions]
    return np.concatenate(pieces).astype(np.float32), morphs


def rest_mesh(character, morph_rows: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray] | None:
    """The bind-pose positions and normals (V, 3) that skin to the body's frames: the character's own, or
    with its morph targets applied when their weights hold still over every frame posed (a face's
    neutral shape, a garment-fit corrective); None when they move (joints cannot move those vertices)."""
    targets = getattr(character, "morph_targets", None) or []
    if not targets:
        return np.asarray(character.positions, np.float32), np.asarray(character.normals, np.float32)
    weights = np.concatenate([np.asarray(rows, np.float64).reshape(-1, len(targets)) for rows in morph_rows])
    if not (weights == weights[0]).all():
        return None
    return apply_morph_targets(character.positions, character.normals, targets, weights[0])


def body_skin(job: JobRecord, cycle: CycleRecord, inputs: Path, character) -> BodySkin | None:
    """The body of crowdbake.stages.poses.high_parts as skinning, or None (logged) when it cannot be."""
    reason = why_not_skinned(job, character)
    if reason is not None:
        logger.info("the body keeps vertex frames: %s", reason)
        return None
    names = job.inputs
    if cycle.ranges is not None:
        matrices, morphs = _ranges_matrices(inputs / names["character"], inputs / names["timeline"], cycle)
    else:
        start = cycle.start_frame if cycle.clip_phase is None else cycle.clip_phase
        times = cycle_times(float(character.animation_duration), cycle.fps, start, cycle.pose_frames)
        matrices, morphs = _rows(character, times), [morph_weights(character, times)]
        if cycle.root_motion_removed:
            everything, _ = pose_body_cycle(character, cycle.fps, 0, job.cache_frames)
            offsets = estimate_root_offsets(everything)[cycle.start_frame : cycle.start_frame + cycle.pose_frames]
            matrices = without_root_offsets(matrices, offsets)
    rest = rest_mesh(character, morphs)
    if rest is None:
        logger.info("the body keeps vertex frames: its morph targets' weights change over the animation")
        return None
    return BodySkin(rest[0], rest[1], np.asarray(character.joints, np.int64), np.asarray(character.weights, np.float32), matrices)


def skinned_body(job: JobRecord, cycle: CycleRecord, inputs: Path, character, body: PartPoses) -> PartPoses:
    """`body` (its vertex frames, high LOD) as skinning where that reproduces them within
    SKIN_POSITION_TOLERANCE_M and SKIN_NORMAL_TOLERANCE_DEG: its frames replaced by the skinned ones (so
    the impostors draw what the runtime draws, to the bit) and its `skin` set; else `body` (logged)."""
    skin = body_skin(job, cycle, inputs, character)
    if skin is None:
        return body
    if skin.matrices.shape[0] != body.frame_count or len(skin.rest_positions) != body.vertex_count:
        logger.warning("the body keeps vertex frames: %d skinned frames of %d vertices for %d of %d", skin.matrices.shape[0],
                       len(skin.rest_positions), body.frame_count, body.vertex_count)
        return body
    positions, normals = skin_frames(skin.rest_positions, skin.rest_normals, skin.joints, weight_codes(skin.weights), skin.matrices)
    no_normal = (body.normals == FALLBACK_NORMAL.astype(np.float32)).all(axis=-1)
    distance, angle = frames_disagreement(positions, normals, body.positions, body.normals, no_normal)
    if distance > SKIN_POSITION_TOLERANCE_M or angle > SKIN_NORMAL_TOLERANCE_DEG:
        logger.warning("the body keeps vertex frames: skinning differs from them by up to %.3f mm and %.2f degrees", distance * 1e3, angle)
        return body
    skinned = replace(body, positions=positions, normals=normals, skin=skin, simplify_pose=body.positions[0])
    refusal = reader_refusal(skinned, cycle.fps)
    if refusal is not None:
        logger.warning("the body keeps vertex frames: its skinning breaks a rule of the skinned pose cache: %s", refusal)
        return body
    logger.info("the body is stored as skinning: %d joints, within %.4f mm and %.3f degrees of its vertex frames", skin.matrices.shape[1],
                distance * 1e3, angle)
    return skinned


def reader_refusal(part: PartPoses, fps: float) -> str | None:
    """Why a reader would refuse `part`'s CBSK (every rule SPEC.md gives: a joint scaled to nothing to hide
    a prop makes a singular matrix), or None: the bake never publishes a bundle no reader opens."""
    try:
        decode_skinned_pose_cache(skinned_cache_bytes(part, fps), "body")
    except (FormatError, ValueError) as error:
        return str(error)
    return None


def skinned_cache_bytes(part: PartPoses, fps: float) -> bytes:
    """The CBSK of a part whose `skin` is set (skinned_body)."""
    skin = part.skin
    return encode_skinned_pose_cache(part.faces, part.uvs, skin.rest_positions, skin.rest_normals, skin.joints, skin.weights, skin.matrices, fps)
