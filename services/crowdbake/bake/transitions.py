"""Transitions between clip loops, taken from the simulation that played the clips one after another.

When the simulation changed from clip A to clip B (segments k and k + 1 of the timeline), the cloth's
frames from a point of A's segment to a point of B's segment are a move between the two that the solver
made. Playback goes loop A -> the transition -> loop B:

- it leaves loop A at a cache frame `a` of A's pure frames whose clip frame is the clip frame of a loop
  frame `i` (so the body's pose matches), and arrives in loop B at a cache frame `b` of B's pure frames
  whose clip frame is that of loop B's frame `j`;
- each join is judged like pass 1 of the cycle search (crowdbake.bake.cycle_search): a binomially weighted
  position + velocity distance over all vertices between the loop played on and the simulation, over
  the join's crossfade window; candidates are the local minima, tried nearest the change of clip first;
- each join is closed the way a loop's seam is (crowdbake.bake.loop_closing, "crossfade"): over the h
  frames either side of it the played cloth fades from the loop into the simulation (or back) with the
  quintic weight, then edge lengths are restored. So the transition's frames are
      blend(loop A[i - h_A .. i + h_A), x[a - h_A .. a + h_A)) + x[a + h_A .. b - h_B) + blend(x[b - h_B .. b + h_B), loop B[j - h_B .. j + h_B)),
  b - a + h_A + h_B frames, played after loop A's frame i - h_A - 1 and followed by loop B's frame j + h_B;
- each join is measured with the loop's quality figures (crowdbake.bake.loop_quality.LoopQuality:
  stretch, deviation in join jumps, acceleration at the join) against the same QUALITY_BOUNDS. The
  first candidate (nearest the change first, for the shortest transition) whose join keeps the bounds is
  taken, trying wider crossfades and more candidates where none does at the loop's own width, else the
  first;
- candidates whose switch falls at a slow phase of the loop come first (switch_is_slow): at a switch a
  character steps from the loop to the transition (or back) as the loop itself steps at that phase, and
  a robot's walk steps up to twice its median round the loop, so a switch at a fast phase reads as a pop
  (crowdview's switch figure, runtime/README.md "Clips and switches").

Pure numpy; no I/O. Penetration into the body is not measured here (no push-out on transitions).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from crowdbake.bake.clips import ClipLoop
from crowdbake.bake.timeline import Timeline
from crowdbake.bake.cycle_search import DEFAULT_MAX_CANDIDATES, DEFAULT_VELOCITY_WEIGHT, binomial_weights, pick_candidates
from crowdbake.bake.loop_closing import crossfade_blend, crossfade_weights, default_crossfade_frames
from crowdbake.bake.cycle import CROSSFADE_WIDTH_FACTORS, MORE_CANDIDATES_FACTOR
from crowdbake.bake.loop_quality import MIN_REFERENCE_STRAIN, QUALITY_BOUNDS, LoopQuality, _ratio, _rms, mean_edge_strain
from crowdbake.bake.mesh import edge_lengths, unique_edges


def join_errors(
    loop: np.ndarray,
    loop_phase: int,
    period: int,
    cloth: np.ndarray,
    frames: np.ndarray,
    clip_frame: np.ndarray,
    half_width: int,
    velocity_weight: float = DEFAULT_VELOCITY_WEIGHT,
) -> tuple[np.ndarray, np.ndarray]:
    """For each cache frame a in `frames`, the loop frame of the same clip phase and the join distance.

    loop: (L, V, 3) a closed loop, L a multiple of `period`; loop frame k shows clip frame
    (loop_phase + k) mod period. cloth: (F, V, 3); frames: (N,) cache frames, each with h + 1 frames
    either side in the cache; clip_frame: (F,) int, the clip frame at each cache frame; half_width: h.
    D(a)^2 = sum_t w_t [P(t) + lambda^2 V(t)], t = -h .. h, w binomial (2h + 1 points), with
    P(t) = mean_v |loop(i + t) - x(a + t)|^2 and V(t) the same for central-difference velocities, the
    loop indexed cyclically: an RMS length in cache units, as pass 1's.
    Returns (loop_frames (N,) int64, distances (N,) float64); with several loop frames of one phase
    (L = n periods) the nearer is kept.
    """
    loop = np.asarray(loop, dtype=np.float64)
    frames = np.asarray(frames, dtype=np.int64)
    length = loop.shape[0]
    if length % period:
        raise ValueError(f"join_errors: a loop of {length} frames is no whole number of {period}-frame periods")
    if len(frames) and (frames.min() - half_width - 1 < 0 or frames.max() + half_width + 1 >= len(cloth)):
        raise ValueError(f"join_errors: frames {frames.min()}..{frames.max()} with {half_width + 1} either side leave the cache")
    offsets = np.arange(-half_width - 1, half_width + 2)  # one more each side for the velocities
    weights = binomial_weights(2 * half_width + 1)
    loop_frames = np.zeros(len(frames), dtype=np.int64)
    distances = np.full(len(frames), np.inf)
    for row, a in enumerate(frames):
        simulated = np.asarray(cloth[a + offsets], dtype=np.float64)
        for i in range((int(clip_frame[a]) - loop_phase) % period, length, period):
            error = loop[(i + offsets) % length] - simulated  # (2h + 3, V, 3)
            position = np.mean(np.sum(np.square(error[1:-1]), axis=-1), axis=-1)
            velocity = np.mean(np.sum(np.square(0.5 * (error[2:] - error[:-2])), axis=-1), axis=-1)
            distance = float(np.sqrt(max(np.dot(weights, position + velocity_weight**2 * velocity), 0.0)))
            if distance < distances[row]:
                loop_frames[row], distances[row] = i, distance
    return loop_frames, distances


def _accelerations(played: np.ndarray) -> np.ndarray:
    """(n,) RMS second difference of (n, V, 3) frames; the end frames (no neighbour) are NaN."""
    out = np.full(played.shape[0], np.nan)
    out[1:-1] = _rms(played[2:] - 2.0 * played[1:-1] + played[:-2])
    return out


def join_quality(
    played: np.ndarray,
    centre: int,
    half_width: int,
    leaving: np.ndarray,
    arriving: np.ndarray,
    edges: np.ndarray | None,
    rest_lengths: np.ndarray | None,
    period: int,
) -> LoopQuality:
    """The loop-quality figures (crowdbake.bake.loop_quality.LoopQuality) of one join of a transition.

    played: (n, V, 3) what playback shows: loop, transition, loop; centre: index of the join's t = 0 in
    `played` (the blend covers centre - h .. centre + h - 1, h = half_width); leaving, arriving: (2h + 2,
    V, 3) the two trajectories the join fades between, unblended, over t = -h - 1 .. h (what would play
    without the blend is `leaving` for t < 0 and `arriving` for t >= 0). The figures, as for a loop's seam:
    stretch_ratio: mean edge strain over one `period` of playback centred on the join (the loop's
    length, as a loop's stretch covers its whole period) over that of the same frames unblended (at
    least MIN_REFERENCE_STRAIN); deviation_ratio: the largest RMS distance blended - unblended over the join's
    raw jump |leaving(0) - arriving(0)|; seam_acceleration_ratio: the played acceleration at t = -1 and
    0 over the larger of the played sequence's median acceleration and the simulator's own there (the
    leaving trajectory's at t = -1, the arriving one's at t = 0); max_acceleration_ratio: the largest
    played acceleration over the blend window over that median.
    """
    played = np.asarray(played, dtype=np.float64)
    h = int(half_width)
    if leaving.shape != arriving.shape or leaving.shape[0] != 2 * h + 2:
        raise ValueError(f"join_quality: leaving {leaving.shape} and arriving {arriving.shape} must both be ({2 * h + 2}, V, 3)")
    if centre - h < 1 or centre + h + 1 > len(played):
        raise ValueError(f"join_quality: a {h}-frame join at {centre} needs a frame either side in the {len(played)} played frames")
    zero = h + 1  # row of t = 0 in leaving / arriving
    unblended = np.concatenate([leaving[1:zero], arriving[zero:-1]])  # t = -h .. h - 1
    blended = played[centre - h : centre + h]
    acceleration = _accelerations(played)
    median = float(np.nanmedian(acceleration))
    jump = float(_rms(leaving[zero] - arriving[zero]))
    simulated = max(float(_rms(leaving[zero] - 2.0 * leaving[zero - 1] + leaving[zero - 2])),
                    float(_rms(arriving[zero + 1] - 2.0 * arriving[zero] + arriving[zero - 1])))
    seam = float(max(acceleration[centre - 1], acceleration[centre]))
    stretch = None
    if edges is not None and rest_lengths is not None and len(edges):
        # Over one period of playback centred on the join, as a loop's stretch is over its period with
        # the seam's blend inside: the unblended side is the same frames with the blend undone.
        first = max(centre - max(period // 2, h), 0)
        last = min(first + max(period, 2 * h), len(played))
        shown = played[first:last]
        undone = shown.copy()
        undone[centre - h - first : centre + h - first] = unblended
        stretch = _ratio(mean_edge_strain(shown, edges, rest_lengths), max(mean_edge_strain(undone, edges, rest_lengths), MIN_REFERENCE_STRAIN))
    ratios = {
        "stretch_ratio": stretch,
        "deviation_ratio": _ratio(float(_rms(blended - unblended).max()), jump),
        "seam_acceleration_ratio": _ratio(seam, max(median, simulated)),
    }
    exceeded = tuple(name for name, bound in QUALITY_BOUNDS.items() if ratios[name] is not None and not ratios[name] <= bound)
    return LoopQuality(
        stretch_ratio=stretch,
        deviation_ratio=ratios["deviation_ratio"],
        seam_acceleration_ratio=ratios["seam_acceleration_ratio"],
        max_acceleration_ratio=_ratio(float(np.nanmax(acceleration[centre - h : centre + h])), median),
        seam_jump=jump,
        seam_acceleration=seam,
        median_acceleration=median,
        simulated_seam_acceleration=simulated,
        exceeded=exceeded,
    )


@dataclass(frozen=True)
class Join:
    """One end of a transition: cache frame `cache_frame` (a or b) meets loop frame `loop_frame` (i or j)
    of the same clip phase; distance: join_errors' D (cache units); half_width: h of its crossfade;
    quality: its figures (join_quality); candidates: (cache frame, loop frame, distance) of every
    candidate the search weighed, best first; switch_step_ratio: what body and cloth move at the switch
    against the reference step (switch_step_ratio below; at most SLOW_SWITCH_RATIO is a slow phase)."""

    cache_frame: int
    loop_frame: int
    distance: float
    half_width: int
    quality: LoopQuality
    candidates: tuple[tuple[int, int, float], ...]
    switch_step_ratio: float = 0.0


@dataclass
class Transition:
    """The move from loop A to loop B the simulation made at one change of clip.

    from_clip/to_clip, from_segment/to_segment: the timeline's segments of the change.
    leave_loop_frame: loop A's frame the transition replaces first (playback: loop A up to the frame
    before it, then the transition); arrive_loop_frame: loop B's frame played right after it.
    frames: (n, V, 3) float32, n = b - a + h_A + h_B; source_frames: the cache frames it spans, [a - h_A, b + h_B).
    leave, arrive: the two joins.
    """

    from_clip: str
    to_clip: str
    from_segment: int
    to_segment: int
    leave_loop_frame: int
    arrive_loop_frame: int
    frames: np.ndarray
    source_frames: tuple[int, int]
    leave: Join
    arrive: Join

    @property
    def within_bounds(self) -> bool:
        return self.leave.quality.within_bounds and self.arrive.quality.within_bounds


def transition_frames(loop_a: np.ndarray, i: int, a: int, loop_b: np.ndarray, j: int, b: int, cloth: np.ndarray,
                      h_a: int, h_b: int, edges: np.ndarray | None) -> np.ndarray:
    """The transition's (b - a + h_a + h_b, V, 3) float64 frames (see the module docstring).

    loop_a: (La, V, 3), left at loop frame i ~ cache frame a; loop_b: (Lb, V, 3), reached at loop frame
    j ~ cache frame b > a; cloth: (F, V, 3); h_a, h_b: the joins' crossfade half-widths; edges: (E, 2) or None."""
    if not a + h_a <= b - h_b:
        raise ValueError(f"transition_frames: the joins at {a} (h {h_a}) and {b} (h {h_b}) overlap")
    offsets, weight = crossfade_weights(h_a)
    leave = crossfade_blend(np.asarray(loop_a[(i + offsets) % len(loop_a)], np.float64),
                            np.asarray(cloth[a + offsets], np.float64), weight, edges)
    offsets, weight = crossfade_weights(h_b)
    arrive = crossfade_blend(np.asarray(cloth[b + offsets], np.float64),
                             np.asarray(loop_b[(j + offsets) % len(loop_b)], np.float64), weight, edges)
    return np.concatenate([leave, np.asarray(cloth[a + h_a : b - h_b], np.float64), arrive])


def _played(loop_a, leave_frame, frames, loop_b, arrive_frame) -> np.ndarray:
    """One period of loop A up to the transition, the transition, one period of loop B after it."""
    la, lb = len(loop_a), len(loop_b)
    return np.concatenate([np.asarray(loop_a[np.arange(leave_frame - la, leave_frame) % la], np.float64), frames,
                           np.asarray(loop_b[np.arange(arrive_frame, arrive_frame + lb) % lb], np.float64)])


# Join candidates are looked for first within this many of the clip's periods of the change of clip.
NEAR_CHANGE_PERIODS = 2

# A switch is at a slow phase when the loop's step there is at most this times the reference step (the
# larger of the two loops' median steps, as crowdview's switch figure). The figure's target is 1.5 on
# screen, where a step read up to 1.33 times its 3D share against the median (the view hides depth
# motion; the clips sample's Running), against a reference up to 22 % lower for impostors (blending sparse
# baked frames moves along chords; robot_clips' Running): 0.8 x 1.33 / 0.78 = 1.36 keeps the target, and
# a walk or run still has about a third of its phases this slow.
SLOW_SWITCH_RATIO = 0.8


def loop_steps(cloth_loop: np.ndarray, body_loop: np.ndarray | None = None) -> np.ndarray:
    """(L,) float64: per loop frame k, the RMS over every vertex (cloth and body together) of the step from
    loop frame k to k + 1 (the last to the first), metres: what the character moves on screen in a frame.

    cloth_loop: (L, V, 3); body_loop: (L, Vb, 3) the body posed at each loop frame, or None (cloth alone)."""
    parts = [np.asarray(cloth_loop, dtype=np.float64)]
    if body_loop is not None:
        parts.append(np.asarray(body_loop, dtype=np.float64))
        if parts[1].shape[0] != parts[0].shape[0]:
            raise ValueError(f"loop_steps: a {parts[0].shape[0]}-frame cloth loop with a {parts[1].shape[0]}-frame body")
    frames = np.concatenate(parts, axis=1)
    return _rms(np.roll(frames, -1, axis=0) - frames)


def reference_step(steps_a: np.ndarray, steps_b: np.ndarray) -> float:
    """The larger of two loops' median steps (loop_steps), steps that move nothing left out; 0 when both are still.
    A switch out of a nearly still idle is held to the motion it leads into, as crowdview's switch figure holds it."""
    medians = [float(np.median(s[s > 0])) for s in (np.asarray(steps_a), np.asarray(steps_b)) if np.any(np.asarray(s) > 0)]
    return max(medians, default=0.0)


def switch_is_slow(steps: np.ndarray, switch_steps: np.ndarray, reference: float, ratio: float = SLOW_SWITCH_RATIO) -> np.ndarray:
    """(N,) bool: whether each switch, at loop step switch_steps (N,) int (index into steps, taken modulo
    its length), moves at most `ratio` times `reference` (metres; reference_step). All True when reference
    is 0 (still loops: no switch can pop)."""
    steps = np.asarray(steps, dtype=np.float64)
    index = np.asarray(switch_steps, dtype=np.int64) % len(steps)
    if reference <= 0:
        return np.ones(len(index), dtype=bool)
    return steps[index] <= ratio * reference


def switch_step_ratio(steps: np.ndarray, switch_step: int, reference: float) -> float:
    """The loop's step at `switch_step` (index into steps (L,), metres, taken modulo L) over `reference`
    (metres; reference_step); 0 when reference is 0 (still loops: no switch can pop)."""
    return 0.0 if reference <= 0 else float(np.asarray(steps, np.float64)[int(switch_step) % len(steps)] / reference)


def body_loop(body: np.ndarray, loop: ClipLoop) -> np.ndarray:
    """(L, Vb, 3): the body at each of a loop's L frames, from `body` (F, Vb, 3), posed per cache frame:
    loop frame k shows clip frame (clip_phase + k) mod period, which cache frame start_frame + (k mod period) shows."""
    return np.asarray(body[loop.start_frame + np.arange(len(loop.looped)) % loop.period])


def _candidates(loop: ClipLoop, cloth, timeline: Timeline, segment: int, h: int, max_candidates: int, velocity_weight: float,
                latest_first: bool, slow_at=None):
    """(cache frames, loop frames, distances) of a join's candidates in a segment's pure frames, in the order
    they are tried: first the best local minima within NEAR_CHANGE_PERIODS periods of the change of clip,
    nearest it first (the latest where the transition leaves the segment, latest_first; the earliest where
    it arrives), then the segment's best elsewhere, best first. The first within the bounds makes the
    shortest transition: a crowd character asked to walk should not idle on for several Idle periods.
    slow_at: None, or a function of the (N,) loop frames of the segment's frames giving (N,) bool, whether
    a switch through that join is at a slow phase (switch_is_slow). Then the candidates whose switch is
    slow, with those of the same search over the slow frames alone, come first, nearest the change
    first; then the fast candidates in the order above."""
    seg = timeline.segments[segment]
    frames = np.arange(seg.pure_first_frame + h + 1, seg.pure_last_frame - h)
    if len(frames) == 0:
        raise ValueError(f"segment {segment} ({seg.clip}, pure frames {seg.pure_first_frame}..{seg.pure_last_frame}) "
                         f"is too short for a {h}-frame join either side")
    loop_frames, distances = join_errors(loop.looped, loop.clip_phase, loop.period, cloth, frames, timeline.clip_frame, h, velocity_weight)
    spacing = (loop.period + 1) // 2
    reach = NEAR_CHANGE_PERIODS * loop.period
    near = np.flatnonzero(frames >= frames[-1] - reach if latest_first else frames <= frames[0] + reach)

    def ordered(curve: np.ndarray) -> np.ndarray:
        """Indices of the candidates on `curve` (inf: not a candidate): near the change, nearest first, then
        the best elsewhere."""
        picked_near = near[np.asarray(pick_candidates(frames[near], curve[near], spacing, max_candidates), dtype=np.int64)]
        picked_near = picked_near[np.argsort(-frames[picked_near] if latest_first else frames[picked_near], kind="stable")]
        # The segment's best elsewhere, best first, where none near the change keeps the bounds.
        picked_all = np.asarray(pick_candidates(frames, curve, spacing, max_candidates), dtype=np.int64)
        return np.concatenate([picked_near, picked_all[~np.isin(picked_all, picked_near)]])

    picked = ordered(distances)
    if slow_at is not None:
        slow = np.asarray(slow_at(loop_frames), dtype=bool)
        # With the minima over the slow frames alone (a valley whose bottom is at a fast phase offers its
        # best slow frame), every slow candidate nearest the change first: the shortest slow transition.
        extra = ordered(np.where(slow, distances, np.inf))
        first = np.union1d(picked[slow[picked]], extra)
        first = first[np.argsort(-frames[first] if latest_first else frames[first], kind="stable")]
        picked = np.concatenate([first, picked[~slow[picked]]])
    return frames[picked], loop_frames[picked], distances[picked]


def find_transition(
    cloth: np.ndarray,
    cloth_faces: np.ndarray | None,
    timeline: Timeline,
    from_segment: int,
    loop_a: ClipLoop,
    loop_b: ClipLoop,
    max_candidates: int = DEFAULT_MAX_CANDIDATES,
    velocity_weight: float = DEFAULT_VELOCITY_WEIGHT,
    rest_positions: np.ndarray | None = None,
    body: np.ndarray | None = None,
    slow_switch_ratio: float | None = SLOW_SWITCH_RATIO,
) -> Transition:
    """The transition from loop_a (the clip of segment from_segment) to loop_b (that of the next segment).

    cloth: (F, V, 3) the whole cache; cloth_faces: (T, 3) for edge restoration and the stretch ratio (None
    skips both); rest_positions: (V, 3), default the cache's first frame; body: (F, Vb, 3) the body posed
    at each cache frame (crowdbake.stages.cycle_inputs.pose_clips_body), or None: the switch phases are
    then judged by the cloth alone; slow_switch_ratio: switch_is_slow's ratio (None: no phase is preferred).
    Each join takes the first of its candidates (switches at a slow phase first, nearest the change of clip
    first, see _candidates) that keeps QUALITY_BOUNDS, crossfaded over the loop's own half-width
    (loop_closing.default_crossfade_frames), then wider, then among more candidates (_join_options); where
    none keeps them, the first (its quality.exceeded says which bounds it breaks).
    """
    to_segment = from_segment + 1
    edges = None if cloth_faces is None else unique_edges(cloth_faces)
    rest_lengths = None if edges is None else edge_lengths(np.asarray(cloth[0] if rest_positions is None else rest_positions, np.float64), edges)
    la, lb = len(loop_a.looped), len(loop_b.looped)
    steps_a = loop_steps(loop_a.looped, None if body is None else body_loop(body, loop_a))
    steps_b = loop_steps(loop_b.looped, None if body is None else body_loop(body, loop_b))
    reference = reference_step(steps_a, steps_b)
    slow = slow_switch_ratio is not None

    # Leaving, loop frame i - h_a - 1 (the manifest's leave_frame) steps to the transition's first frame,
    # about loop frame i - h_a; arriving, its last frame, about loop frame j + h_b - 1, steps to j + h_b.
    def leaving(count: int, h: int):
        return _candidates(loop_a, cloth, timeline, from_segment, h, count, velocity_weight, latest_first=True,
                           slow_at=(lambda i: switch_is_slow(steps_a, i - h - 1, reference, slow_switch_ratio)) if slow else None)

    def arriving(count: int, h: int):
        return _candidates(loop_b, cloth, timeline, to_segment, h, count, velocity_weight, latest_first=False,
                           slow_at=(lambda j: switch_is_slow(steps_b, j + h - 1, reference, slow_switch_ratio)) if slow else None)

    def build(leave: _JoinChoice, arrive: _JoinChoice):
        (h_a, a, i), (h_b, b, j) = leave.join(), arrive.join()
        frames = transition_frames(loop_a.looped, i, a, loop_b.looped, j, b, cloth, h_a, h_b, edges)
        leave_frame, arrive_frame = (i - h_a) % la, (j + h_b) % lb
        played = _played(loop_a.looped, leave_frame, frames, loop_b.looped, arrive_frame)
        span = np.arange(-h_a - 1, h_a + 1)
        quality_leave = join_quality(played, la + h_a, h_a, np.asarray(loop_a.looped[(i + span) % la], np.float64),
                                     np.asarray(cloth[a + span], np.float64), edges, rest_lengths, la)
        span = np.arange(-h_b - 1, h_b + 1)
        quality_arrive = join_quality(played, la + len(frames) - h_b, h_b, np.asarray(cloth[b + span], np.float64),
                                      np.asarray(loop_b.looped[(j + span) % lb], np.float64), edges, rest_lengths, lb)
        return frames, leave_frame, arrive_frame, quality_leave, quality_arrive

    options_a = _join_options(leaving, la, timeline.segments[from_segment], max_candidates)
    options_b = _join_options(arriving, lb, timeline.segments[to_segment], max_candidates)
    # Each join's figures depend on the other only through the played median: choose them one after the
    # other, the leaving join against the first arriving candidate.
    first_b = _JoinChoice(*next(_join_options(arriving, lb, timeline.segments[to_segment], max_candidates)), 0)
    leave = _first_keeping_bounds(options_a, lambda choice: build(choice, first_b)[3])
    arrive = _first_keeping_bounds(options_b, lambda choice: build(leave, choice)[4])
    frames, leave_frame, arrive_frame, quality_leave, quality_arrive = build(leave, arrive)
    (h_a, a, i), (h_b, b, j) = leave.join(), arrive.join()
    return Transition(
        from_clip=loop_a.clip, to_clip=loop_b.clip, from_segment=from_segment, to_segment=to_segment,
        leave_loop_frame=int(leave_frame), arrive_loop_frame=int(arrive_frame), frames=frames.astype(np.float32),
        source_frames=(a - h_a, b + h_b),
        leave=Join(a, i, leave.distance(), h_a, quality_leave, leave.listed(), switch_step_ratio(steps_a, i - h_a - 1, reference)),
        arrive=Join(b, j, arrive.distance(), h_b, quality_arrive, arrive.listed(), switch_step_ratio(steps_b, j + h_b - 1, reference)),
    )


@dataclass(frozen=True)
class _JoinChoice:
    """Candidate `index` of the candidates (cache frames, loop frames, distances; _candidates) found for a
    join crossfaded over `half_width` frames either side."""

    half_width: int
    found: tuple[np.ndarray, np.ndarray, np.ndarray]
    index: int

    def join(self) -> tuple[int, int, int]:
        """(h, cache frame, loop frame)."""
        return self.half_width, int(self.found[0][self.index]), int(self.found[1][self.index])

    def distance(self) -> float:
        return float(self.found[2][self.index])

    def listed(self) -> tuple[tuple[int, int, float], ...]:
        """Every candidate weighed at this width: (cache frame, loop frame, distance), in the order tried."""
        return tuple((int(f), int(k), float(d)) for f, k, d in zip(*self.found))


def _join_widths(loop_frames: int, segment) -> list[int]:
    """A join's crossfade half-widths in the order tried: the loop's own (loop_closing.default_crossfade_frames),
    then CROSSFADE_WIDTH_FACTORS times it, each at most half the loop and leaving a candidate frame in the
    segment's pure frames (the loop's own is kept even then: _candidates says why it does not fit)."""
    default = default_crossfade_frames(loop_frames)
    widths = [default]
    for factor in CROSSFADE_WIDTH_FACTORS[1:]:
        width = min(int(round(default * factor)), loop_frames // 2)
        if width not in widths and segment.pure_last_frame - segment.pure_first_frame > 2 * width + 1:
            widths.append(width)
    return widths


def _join_options(candidates_at, loop_frames: int, segment, max_candidates: int):
    """(half-width, candidates) in the order a join tries them: the loop's own crossfade, then wider ones
    (_join_widths), then MORE_CANDIDATES_FACTOR times as many candidates at each width, as a loop's seam
    tries them (crowdbake.bake.cycle). candidates_at(count, h) -> _candidates' (frames, loop frames, distances)."""
    for count in (max_candidates, MORE_CANDIDATES_FACTOR * max_candidates):
        for width in _join_widths(loop_frames, segment):
            yield width, candidates_at(count, width)


def _first_keeping_bounds(options, judge) -> _JoinChoice:
    """The first candidate of `options` (_join_options) whose join `judge` (a _JoinChoice -> LoopQuality)
    finds within QUALITY_BOUNDS, else the very first; each (width, cache frame) is judged once."""
    first = None
    judged = set()
    for width, found in options:
        for index in range(len(found[0])):
            choice = _JoinChoice(width, found, index)
            key = choice.join()[:2]
            if key in judged:
                continue
            judged.add(key)
            first = first or choice
            if judge(choice).within_bounds:
                return choice
    return first


def find_transitions(cloth: np.ndarray, cloth_faces: np.ndarray | None, timeline: Timeline, loops: list[ClipLoop],
                     max_candidates: int = DEFAULT_MAX_CANDIDATES, velocity_weight: float = DEFAULT_VELOCITY_WEIGHT,
                     rest_positions: np.ndarray | None = None, body: np.ndarray | None = None,
                     slow_switch_ratio: float | None = SLOW_SWITCH_RATIO) -> list[Transition]:
    """find_transition for every change of clip in the timeline (timeline.changes()), in playing order."""
    by_clip = {loop.clip: loop for loop in loops}
    return [
        find_transition(cloth, cloth_faces, timeline, k, by_clip[timeline.segments[k].clip], by_clip[timeline.segments[k + 1].clip],
                        max_candidates, velocity_weight, rest_positions, body, slow_switch_ratio)
        for k, _ in timeline.changes()
    ]


def join_jump_ratios(played: np.ndarray, at: int, reference: np.ndarray) -> tuple[float, float]:
    """A join's seam figures as a loop's (crowdbake.bake.loop_quality.SeamFigures): how far playback at
    frame `at` is from what the loop on the other side of the join shows there, in position and in
    velocity, over the median RMS frame-to-frame step of `played`.

    played: (n, V, 3) what playback shows (loop, transition, loop); at: 1 <= at < n - 1, the first frame
    that differs from the loop (leaving: the transition's first frame; arriving: its last);
    reference: (3, V, 3) that loop at at - 1, at, at + 1.
    """
    played = np.asarray(played, dtype=np.float64)
    reference = np.asarray(reference, dtype=np.float64)
    if not 1 <= at < len(played) - 1 or reference.shape != (3, *played.shape[1:]):
        raise ValueError(f"join_jump_ratios: frame {at} of {len(played)} played, reference {reference.shape}")
    median_step = float(np.median(_rms(np.diff(played, axis=0))))
    position = float(_rms(played[at] - reference[1]))
    velocity = float(_rms(0.5 * (played[at + 1] - played[at - 1]) - 0.5 * (reference[2] - reference[0])))
    return _ratio(position, median_step), _ratio(velocity, median_step)


def transition_jump_ratios(transition: Transition, loop_a: np.ndarray, loop_b: np.ndarray) -> tuple[float, float]:
    """(position, velocity) jump ratios of a transition, each the worse of its two joins (join_jump_ratios):
    leaving, its first frame against loop A going on; arriving, its last frame against loop B's frame before
    arrive_loop_frame. loop_a, loop_b: (L, V, 3) the loops it joins."""
    la, lb = len(loop_a), len(loop_b)
    played = _played(loop_a, transition.leave_loop_frame, np.asarray(transition.frames, np.float64), loop_b, transition.arrive_loop_frame)
    leave = join_jump_ratios(played, la, np.asarray(loop_a[(transition.leave_loop_frame + np.arange(-1, 2)) % la]))
    arrive = join_jump_ratios(played, la + len(transition.frames) - 1, np.asarray(loop_b[(transition.arrive_loop_frame + np.arange(-2, 1)) % lb]))
    return max(leave[0], arrive[0]), max(leave[1], arrive[1])
