"""One impostor budget for a character of several clips, split among its clips and transitions by measuring.

A bundle of several clips stores, per baked pose frame, one cell of the crop per view in every map, so
its impostor bytes are (baked frames) x (bytes a frame). Which range gets how many frames is the split.
A fixed rule (frames by how far the vertices move, a budget per clip) served some characters and missed
others: the running cape of robot_clips needs every pose frame baked, its idle almost none, and how far
vertices move does not say how a blend of two pictures looks. So the split is measured: for each range
and each count on a ladder of frame counts, the impostor drawn between two of that count's baked frames
by crowdview's own shader is compared with the mesh there (crowdbake.stages.impostor_probe), giving a
score per (range, count). Then `allocate`:

1. each range takes the fewest frames of its ladder that score within `tolerance` of its best;
2. where those are over the budget, the highest score that every range reaches within it decides (no
   clip or transition is left far behind the others: a crowd shows them all), and the frames left over go
   to the range gaining most score a frame, up to its count of step 1;
3. where even every range's floor is over the budget, the floors are kept and `fits` is False.

Scores are made non-decreasing in the frame count first (`envelope`).

Pure functions; no I/O.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from crowdbake.bake import pose_ranges
from crowdbake.formats.ranges import Clip, Ranges, Transition

# Frame counts a range is probed at (its own length and the frames asked cap them): about 1.5x apart,
# so the probes cost a few times one range's frames, not all of them.
LADDER = (2, 3, 4, 5, 6, 8, 10, 12, 15, 18, 21, 24, 32, 48, 64)
# A range keeps the fewest frames scoring within this much SSIM of its best count.
TOLERANCE = 0.01


def range_name(ranges: Ranges, item: Clip | Transition) -> str:
    """A clip's name, or a transition's "From -> To" (as texture_memory.json and fidelity.json name it)."""
    if isinstance(item, Clip):
        return item.name
    return f"{ranges.clips[item.from_clip].name} -> {ranges.clips[item.to_clip].name}"


def ladder(item: Clip | Transition, most: int, switches: tuple[int, ...] = ()) -> list[int]:
    """The frame counts a range is probed at, ascending: LADDER's counts below min(most, its frames), and
    that cap itself. A clip never bakes fewer frames than its switch frames (each is kept), a transition
    never fewer than its two ends; a range of one frame bakes one."""
    top = max(1, min(int(most), item.frames))
    floor = min(top, max(2, len(set(switches))) if isinstance(item, Clip) else 2)
    counts = sorted({n for n in LADDER if floor <= n < top} | {top, floor})
    return counts


def ladders(ranges: Ranges, most: int) -> list[list[int]]:
    """ladder of every range (ranges.all() order: the clips first, each with its switch frames)."""
    switches = pose_ranges.switch_frames(ranges)
    return [ladder(item, most, switches[i] if i < len(switches) else ()) for i, item in enumerate(ranges.all())]


def frames_at(ranges: Ranges, index: int, count: int) -> list[int]:
    """Pose frames range `index` (ranges.all() order) bakes at `count`: a clip's evenly spread with its
    switch frames (pose_ranges.clip_frames), a transition's ends and evenly spaced frames between."""
    item = ranges.all()[index]
    if isinstance(item, Clip):  # ranges.all() lists the clips first
        return pose_ranges.clip_frames(item, count, pose_ranges.switch_frames(ranges)[index])
    return pose_ranges.transition_frames(item, 1.0, max(2, count))


def probed_counts(counts: list[int]) -> list[int]:
    """The counts of a ladder a probe draws, ascending: every other one from the bottom, and the top. The
    scores change smoothly with the count, so the skipped ones are interpolated (`interpolated`) at half
    the probes' cost."""
    return sorted(set(counts[::2]) | {counts[-1]})


def interpolated(table: dict[int, float], counts: list[int]) -> dict[int, float]:
    """{count: score} of `table` (probed counts) with every count of `counts` that lies between two probed
    ones added, linearly interpolated between them; counts outside the probed span are left out."""
    probed = sorted(table)
    out = dict(table)
    for count in counts:
        if count in out:
            continue
        below = [n for n in probed if n < count]
        above = [n for n in probed if n > count]
        if below and above:
            low, high = below[-1], above[0]
            out[count] = table[low] + (table[high] - table[low]) * (count - low) / (high - low)
    return {n: out[n] for n in sorted(out)}


@dataclass(frozen=True)
class Gap:
    """Where a probe scores: the blend between baked frames `first` and `second` of a range at pose frame
    `between`, the second weighing `weight` (crowdview's frame blend there)."""

    first: int
    second: int
    between: int
    weight: float


def gaps_to_score(item: Clip | Transition, frames: list[int], most: int) -> list[Gap]:
    """At most `most` gaps between consecutive baked `frames` of a range (a clip's last wraps to its first),
    spread evenly along it, each scored halfway (rounded down) as fidelity.json's ranges are
    (pose_ranges.scored_frames). A range of one baked frame: halfway round a clip; a transition's only
    frame, at itself."""
    pairs = list(zip(frames, frames[1:]))
    if isinstance(item, Clip):
        pairs.append((frames[-1], frames[0]))
    if not pairs:
        return [Gap(frames[0], frames[0], frames[0], 0.0)]
    chosen = [pairs[i] for i in np.unique(np.linspace(0, len(pairs), min(most, len(pairs)), endpoint=False).astype(int))]
    out = []
    for first, second in chosen:
        span = (second - first) % item.frames or item.frames if isinstance(item, Clip) else second - first
        step = span // 2
        between = item.first_frame + (first - item.first_frame + step) % item.frames
        out.append(Gap(first, second, between, step / span if span else 0.0))
    return out


@dataclass(frozen=True)
class Allocation:
    """allocate's answer: per range (ranges.all() order) its count, the frames it bakes and its score there
    (the envelope's), the bytes of them all, and whether they fit."""

    counts: list[int]
    frames: list[list[int]]
    bytes: int
    fits: bool
    scores: list[float]

    def frame_indices(self) -> list[int]:
        return sorted({f for frames in self.frames for f in frames})


def envelope(table: dict[int, float]) -> dict[int, float]:
    """{count: score} made non-decreasing in count (each count scores at least any smaller count): more
    baked frames never draw a worse impostor, and a probe that scored gaps of other lengths at a larger
    count (its gaps are spread, not the same) is noise, not evidence for fewer frames."""
    out, best = {}, float("-inf")
    for count in sorted(table):
        best = max(best, float(table[count]))
        out[count] = best
    return out


def allocate(ranges: Ranges, scores: list[dict[int, float]], bytes_per_frame: float, budget_bytes: float | None,
             tolerance: float = TOLERANCE) -> Allocation:
    """The frame count per range (module docstring). scores: per range (ranges.all() order) {count: mean
    SSIM between frames}, the counts its ladder probed; bytes_per_frame: one baked frame's maps (every view,
    every map); budget_bytes: None, no budget (step 1 alone)."""
    items = ranges.all()
    if len(scores) != len(items):
        raise ValueError(f"allocate: {len(scores)} score tables for {len(items)} ranges")
    if any(not table for table in scores):
        raise ValueError("allocate: a range has no probed count")
    tables = [envelope(table) for table in scores]
    sizes = [{n: len(frames_at(ranges, i, n)) for n in table} for i, table in enumerate(tables)]
    # Step 1: the fewest frames within tolerance of each range's best.
    enough = [min(n for n in table if table[n] >= max(table.values()) - tolerance) for table in tables]
    limit = None if budget_bytes is None else int(budget_bytes // bytes_per_frame)

    def cheapest(threshold: float) -> list[int]:
        return [min((n for n in table if table[n] >= min(threshold, table[top])), default=top)
                for table, top in zip(tables, enough)]

    def frames_of(counts: list[int]) -> int:
        return sum(size[n] for size, n in zip(sizes, counts))

    chosen = enough
    if limit is not None and frames_of(chosen) > limit:
        # Step 2: the highest score every range reaches within the budget, then the frames left over to
        # the range that gains most a frame.
        thresholds = sorted({s for table in tables for s in table.values()}, reverse=True)
        chosen = next((cheapest(t) for t in thresholds if frames_of(cheapest(t)) <= limit), [min(table) for table in tables])
        while True:
            upgrades = [((tables[i][n] - tables[i][chosen[i]]) / (sizes[i][n] - sizes[i][chosen[i]]), i, n)
                        for i in range(len(tables)) for n in tables[i]
                        if chosen[i] < n <= enough[i] and sizes[i][n] > sizes[i][chosen[i]]
                        and frames_of(chosen) - sizes[i][chosen[i]] + sizes[i][n] <= limit]
            if not upgrades:
                break
            _, i, n = max(upgrades)
            chosen = [n if k == i else c for k, c in enumerate(chosen)]
    frames = [frames_at(ranges, i, n) for i, n in enumerate(chosen)]
    total = int(round(len({f for fs in frames for f in fs}) * bytes_per_frame))
    return Allocation(list(chosen), frames, total, budget_bytes is None or total <= budget_bytes,
                      [table[n] for table, n in zip(tables, chosen)])


def allocation_document(ranges: Ranges, scores: list[dict[int, float]], allocation: Allocation, budget_mib: float | None,
                        bytes_per_frame: float, tolerance: float = TOLERANCE) -> dict:
    """texture_memory.json's account of the split: the budget, each range's probed scores and chosen
    count and score."""
    mib = 1024.0 * 1024.0
    items = ranges.all()
    return {
        "budget_mib": budget_mib,
        "mib": allocation.bytes / mib,
        "fits": allocation.fits,
        "frame_mib": bytes_per_frame / mib,
        "rule": (f"per range the fewest frames scoring within {tolerance:g} SSIM of its best probed count (crowdview's shader "
                 f"between two baked frames against the mesh, made non-decreasing in frames); over the budget, the highest "
                 f"score every range reaches within it, then the frames left to the range gaining most a frame"),
        "ranges": [{"name": range_name(ranges, item), "kind": "clip" if isinstance(item, Clip) else "transition",
                    "probed": {str(n): round(float(s), 4) for n, s in sorted(table.items())}, "frames": count,
                    "baked_frames": len(frames), "score": round(float(score), 4)}
                   for item, table, count, frames, score in zip(items, scores, allocation.counts, allocation.frames, allocation.scores)],
    }
