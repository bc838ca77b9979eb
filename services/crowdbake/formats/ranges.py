"""Clips and transitions of a bundle (shared_formats/SPEC.md, "Version 2: clips and transitions").

Every pose cache of a bundle holds `pose_frames` frames cut into *ranges*: looping clips first, then
the transitions between them. A v1 manifest reads as one clip named `cycle` and no transitions, so
everything downstream sees clips and transitions only. The checks here are the manifest's own
(`manifest_invalid`) and the impostor layers' (`invalid_data`); the schema has already run.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from crowdbake.formats.errors import FormatError

V1_CLIP_NAME = "cycle"
_CLIP_FIGURES = ("source_start_frame", "source_end_frame", "closing", "position_jump_ratio", "velocity_jump_ratio")


@dataclass(frozen=True)
class Clip:
    """A looping range: clip frame k (0 <= k < frames) is pose frame first_frame + k; frames-1 wraps to 0."""

    name: str
    first_frame: int
    frames: int
    source_start_frame: int
    source_end_frame: int
    closing: str
    position_jump_ratio: float
    velocity_jump_ratio: float

    def to_manifest(self) -> dict[str, Any]:
        return dict(self.__dict__)


@dataclass(frozen=True)
class Transition:
    """A range played once: after loop frame `leave_frame` of clip `from_clip`, frames 0..frames-1, then
    loop frame `arrive_frame` of clip `to_clip`."""

    from_clip: int
    to_clip: int
    leave_frame: int
    arrive_frame: int
    first_frame: int
    frames: int
    source_start_frame: int
    source_end_frame: int
    position_jump_ratio: float
    velocity_jump_ratio: float

    def to_manifest(self) -> dict[str, Any]:
        return dict(self.__dict__)


@dataclass(frozen=True)
class Ranges:
    """What every reader sees of a bundle's timing, whatever its format_version."""

    pose_frames: int
    clips: tuple[Clip, ...]
    transitions: tuple[Transition, ...]

    def all(self) -> list[Clip | Transition]:
        """Clips in order, then transitions in order: the order the ranges tile the pose frames."""
        return [*self.clips, *self.transitions]


def _invalid(message: str) -> FormatError:
    return FormatError("manifest_invalid", message, "manifest.json")


def read_ranges(manifest: dict[str, Any]) -> Ranges:
    """The clips and transitions of a schema-valid manifest of format_version 1 or 2.

    Raises FormatError('manifest_invalid', file 'manifest.json') when v2 ranges do not tile the pose
    frames, a clip name repeats, or a transition names a clip or loop frame that does not exist.
    """
    if manifest["format_version"] == 1:
        cycle = manifest["cycle"]
        clip = Clip(V1_CLIP_NAME, 0, cycle["frames"], **{key: cycle[key] for key in _CLIP_FIGURES})
        return Ranges(cycle["frames"], (clip,), ())
    clips = tuple(Clip(**{key: entry[key] for key in Clip.__dataclass_fields__}) for entry in manifest["clips"])
    transitions = tuple(Transition(**{key: entry[key] for key in Transition.__dataclass_fields__}) for entry in manifest["transitions"])
    ranges = Ranges(manifest["pose_frames"], clips, transitions)
    check_ranges(ranges)
    return ranges


def check_ranges(ranges: Ranges) -> None:
    """SPEC.md's rules on ranges: unique clip names, tiling, transition indices and loop frames."""
    names = [clip.name for clip in ranges.clips]
    for index, name in enumerate(names):
        if name in names[:index]:
            raise _invalid(f"clips/{index}/name: {name!r} is already the name of clip {names.index(name)}")
    expected_first = 0
    for where, item in _labelled(ranges):
        if item.first_frame != expected_first:
            raise _invalid(f"{where}/first_frame: {item.first_frame}, the ranges tile the pose frames so it must be {expected_first}")
        expected_first += item.frames
    if expected_first != ranges.pose_frames:
        raise _invalid(f"pose_frames: {ranges.pose_frames}, the clips and transitions end at pose frame {expected_first}")
    for index, transition in enumerate(ranges.transitions):
        where = f"transitions/{index}"
        for key in ("from_clip", "to_clip"):
            clip_index = getattr(transition, key)
            if clip_index >= len(ranges.clips):
                raise _invalid(f"{where}/{key}: {clip_index}, the bundle has {len(ranges.clips)} clips")
        if transition.from_clip == transition.to_clip:
            raise _invalid(f"{where}: from_clip and to_clip are both {transition.from_clip}; a transition joins two different clips")
        for key, clip_index in (("leave_frame", transition.from_clip), ("arrive_frame", transition.to_clip)):
            frame, clip = getattr(transition, key), ranges.clips[clip_index]
            if frame >= clip.frames:
                raise _invalid(f"{where}/{key}: {frame}, clip {clip.name!r} has {clip.frames} loop frames")


def _labelled(ranges: Ranges) -> list[tuple[str, Clip | Transition]]:
    return [(f"clips/{i}", c) for i, c in enumerate(ranges.clips)] + [(f"transitions/{i}", t) for i, t in enumerate(ranges.transitions)]


def check_impostor_frames(ranges: Ranges, frame_indices: list[int]) -> None:
    """SPEC.md: every clip holds >= 1 baked frame, every transition its own first and last frame.

    frame_indices: ascending pose frames below pose_frames (checked by the caller).
    Raises FormatError('invalid_data', file 'manifest.json').
    """
    baked = set(frame_indices)
    for where, item in _labelled(ranges):
        last = item.first_frame + item.frames - 1
        if isinstance(item, Clip):
            if not any(item.first_frame <= f <= last for f in baked):
                raise FormatError("invalid_data", f"impostor/frame_indices: no baked frame in {where} "
                                  f"(pose frames {item.first_frame}..{last})", "manifest.json")
        else:
            missing = [f for f in (item.first_frame, last) if f not in baked]
            if missing:
                raise FormatError("invalid_data", f"impostor/frame_indices: {where} (pose frames {item.first_frame}..{last}) "
                                  f"needs its first and last frame baked, {missing[0]} is not", "manifest.json")
