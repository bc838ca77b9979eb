"""A small cloth cache simulated across several clips, with its timeline: known answers by construction.

A cone skirt whose hem swings with the playing clip: "Walk" (12 frames a period) and "Run" (8 frames,
a larger swing), played Walk -> Run -> Walk with 4-frame linear blends. Each change of clip starts a
flutter that dies away over a few periods (as real cloth settles into a new clip), so the cleanest
loops lie late in each segment. Frames are a function of the clip frame alone once settled.
"""
from __future__ import annotations

import numpy as np

RINGS, SEGMENTS = 5, 20
PERIODS = {"Walk": 12, "Run": 8}
FPS = 24.0
BLEND = 4
# (clip, first_frame, last_frame): each strip fades in over the BLEND frames before its pure frames.
STRIPS = (("Walk", 0, 63), ("Run", 60, 127), ("Walk", 124, 171))
TOTAL = 172


def grid_faces(rings: int = RINGS, segments: int = SEGMENTS) -> np.ndarray:
    i, j = np.meshgrid(np.arange(rings - 1), np.arange(segments), indexing="ij")
    a, b = i * segments + j, i * segments + (j + 1) % segments
    c, d = a + segments, b + segments
    return np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)])


def _pose(clip: str, clip_frame: float, flutter: float, t: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """(V, 3) the skirt at a clip frame, plus `flutter` (0..1) of a non-periodic ripple."""
    swing = (0.25 if clip == "Walk" else 0.5) * np.sin(2 * np.pi * clip_frame / PERIODS[clip])
    ripple = flutter * 0.03 * t * np.sin(5 * angle + 1.7 * clip_frame)
    radius = 0.2 + 0.15 * t + ripple
    turned = angle + swing * t
    return np.stack([radius * np.sin(turned), 1.0 - 0.6 * t, radius * np.cos(turned)], -1).reshape(-1, 3)


def timeline_document(with_rows: bool = False) -> dict:
    """The timeline.json of the cache (segments; per-frame rows when asked)."""
    segments = []
    for k, (clip, first, last) in enumerate(STRIPS):
        pure_first = first if k == 0 else first + BLEND
        pure_last = last if k == len(STRIPS) - 1 else STRIPS[k + 1][1]
        segments.append({"clip": clip, "first_frame": first, "last_frame": last, "pure_first_frame": pure_first,
                         "pure_last_frame": pure_last, "clip_frames": PERIODS[clip]})
    document = {"fps": FPS, "total_frames": TOTAL, "blend_frames": BLEND, "segments": segments}
    if with_rows:
        rows = []
        for f in range(TOTAL):
            k = max(i for i, (_, first, _) in enumerate(STRIPS) if first <= f)
            clip, first, _ = STRIPS[k]
            row = {"frame": f, "clip": clip, "segment": k, "clip_frame": (f - first) % PERIODS[clip], "weight": 1.0}
            if k and f < first + BLEND:  # fading in: the row also names the clip fading out (robot_clips' form)
                old_clip, old_first, _ = STRIPS[k - 1]
                row.update(weight=(f - first) / BLEND, blend_from=old_clip, blend_from_frame=(f - old_first) % PERIODS[old_clip])
            rows.append(row)
        document["frames"] = rows
    return document


def multi_clip_cache() -> tuple[np.ndarray, np.ndarray]:
    """((TOTAL, V, 3) float32 cloth, (T, 3) faces): the skirt over the timeline's frames."""
    t = np.linspace(0, 1, RINGS)[:, None] * np.ones((1, SEGMENTS))
    angle = np.linspace(0, 2 * np.pi, SEGMENTS, endpoint=False)[None, :] * np.ones((RINGS, 1))
    frames = []
    for f in range(TOTAL):
        playing = [(k, clip, first) for k, (clip, first, last) in enumerate(STRIPS) if first <= f <= last]
        k, clip, first = playing[-1]
        flutter = np.exp(-(f - first) / 10.0)
        pose = _pose(clip, f - first, flutter, t, angle)
        if len(playing) == 2:  # a blend: the newer strip's weight rises 0 .. 1 over BLEND frames
            weight = (f - first) / BLEND
            _, old_clip, old_first = playing[0]
            pose = weight * pose + (1 - weight) * _pose(old_clip, f - old_first, np.exp(-(f - old_first) / 10.0), t, angle)
        frames.append(pose)
    return np.asarray(frames, dtype=np.float32), grid_faces()
