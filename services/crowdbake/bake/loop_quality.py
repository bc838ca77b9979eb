"""How good a closed loop is: the seam's figures and the loop's distance from the simulation it came from.

Trajectories run over frames Fs-1 .. Fe+1 (l + 3 frames, as crowdbake.bake.loop_closing.close_loop returns
them); the looped cache is Fs .. Fe-1. Every figure is a ratio to what the cloth itself does (its median
frame-to-frame step, its own acceleration, its simulated edge strain), so caches in any unit compare
alike. Pure numpy; no I/O.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from crowdbake.bake.mesh import as_point_frames, edge_lengths

# Steps shorter than this (cache units) mean the cloth does not move: seam ratios are then undefined.
STILL_STEP = 1e-12
# The stretch ratio's denominator is at least this mean strain (0.1 %): a cloth solver never holds its
# edges tighter than that, and a rigid synthetic cache (strain 0) would make any change read as infinite.
MIN_REFERENCE_STRAIN = 1e-3
# The deviation ratio's denominator (the seam's jump) is at least this fraction of the cloth's median
# frame-to-frame step. A seam the simulation nearly closed itself (jump near 0) would make any crossfade,
# which blends two stretches of cloth that differ away from the seam, read as an unbounded deviation and
# reject the best seam there is; a closing that moves no frame farther than 1.5 of the cloth's own median
# step strays less than playing the simulation a frame or two off, which nobody sees.
MIN_JUMP_STEP_FRACTION = 1.0


def _rms(delta: np.ndarray) -> np.ndarray:
    """RMS length over vertices of (..., V, 3) offsets: (...,) float64."""
    return np.sqrt(np.mean(np.sum(np.square(delta), axis=-1), axis=-1))



@dataclass(frozen=True)
class SeamFigures:
    """How visible the seam is, relative to the cycle's own motion.

    position_jump_ratio: RMS over vertices of x(Fe) - x(Fs), over the median RMS frame-to-frame step of the
        cycle. 0 for a closed loop; about 1 means the seam jumps as far as a typical frame moves.
    velocity_jump_ratio: RMS of x'(Fe) - x'(Fs) (central differences, per frame), over the same median step:
        0 when the cloth leaves Fe as it left Fs, whatever its acceleration.
    max_step_ratio: the largest step of the looped playback (the wrap-around step from Fe-1 to Fs
        included) over the median step: catches a kink a closing may leave inside the cycle.
    median_step: the median RMS frame-to-frame step from Fs to Fe (cache units per frame).
    Ratios are inf when the cloth does not move at all and the seam does.
    """

    position_jump_ratio: float
    velocity_jump_ratio: float
    max_step_ratio: float
    median_step: float


def _ratio(value: float, scale: float) -> float:
    if scale > STILL_STEP:
        return float(value / scale)
    return 0.0 if value <= STILL_STEP else float("inf")


def seam_figures(trajectory: np.ndarray) -> SeamFigures:
    """Seam figures of a (l + 3, V, 3) trajectory over Fs-1 .. Fe+1 (see close_loop), l >= 2."""
    trajectory = as_point_frames(trajectory, "seam_figures")
    if trajectory.shape[0] < 5:
        raise ValueError(f"seam_figures: need at least 5 frames (Fs-1 .. Fe+1), got {trajectory.shape[0]}")
    start, end = 1, trajectory.shape[0] - 2
    steps = _rms(np.diff(trajectory[start : end + 1], axis=0))  # the l steps Fs -> Fe
    median_step = float(np.median(steps))
    position_jump = float(_rms(trajectory[end] - trajectory[start]))
    velocity_end = 0.5 * (trajectory[end + 1] - trajectory[end - 1])
    velocity_start = 0.5 * (trajectory[start + 1] - trajectory[start - 1])
    velocity_jump = float(_rms(velocity_end - velocity_start))
    wrap_step = float(_rms(trajectory[start] - trajectory[end - 1]))
    loop_steps = np.append(steps[:-1], wrap_step)
    return SeamFigures(
        position_jump_ratio=_ratio(position_jump, median_step),
        velocity_jump_ratio=_ratio(velocity_jump, median_step),
        max_step_ratio=_ratio(float(loop_steps.max()), median_step),
        median_step=median_step,
    )


# Bounds a closing must keep to on every loop, each a ratio to what the simulator itself did (see LoopQuality):
# 10 % more mean edge strain than the raw frames is below what shows as rubbery cloth; no frame further from
# its simulated self than 1.5 seam jumps (a closing must move frames, but by the order of the jump it hides,
# not more); and no acceleration at the seam above 1.5 times the larger of the loop's median and the
# simulator's own acceleration there, the size of kink the eye picks out in a looping walk.
QUALITY_BOUNDS = {"stretch_ratio": 1.10, "deviation_ratio": 1.5, "seam_acceleration_ratio": 1.5}


@dataclass(frozen=True)
class LoopQuality:
    """How far a closed loop strays from the simulation it came from; every ratio is 1 or less for a good closing.

    stretch_ratio: mean edge strain |L / L_rest - 1| over the loop's frames and edges, over that of the raw
        frames Fs .. Fe-1 (at least MIN_REFERENCE_STRAIN; L_rest: the rest lengths given, by default the
        cache's first frame). None without edges.
    deviation_ratio: the largest per-frame RMS distance between a looped frame and the simulator's same frame,
        over the raw seam jump RMS |x(Fe) - x(Fs)| (at least MIN_JUMP_STEP_FRACTION of the median frame step: one step).
    seam_acceleration_ratio: RMS acceleration (second difference) at the two frames either side of the
        loop's wrap, over the larger of the loop's median acceleration and the simulator's own acceleration
        at those frames (a seam cut where the legs kick the cloth hardest is not a kink).
    max_acceleration_ratio: the loop's largest per-frame RMS acceleration over its median (kinks anywhere).
    seam_jump, seam_acceleration, median_acceleration, simulated_seam_acceleration: the figures behind the
        ratios (cache units, per frame and per frame squared).
    exceeded: names of the ratios above QUALITY_BOUNDS.
    """

    stretch_ratio: float | None
    deviation_ratio: float
    seam_acceleration_ratio: float
    max_acceleration_ratio: float
    seam_jump: float
    seam_acceleration: float
    median_acceleration: float
    simulated_seam_acceleration: float
    exceeded: tuple[str, ...]

    @property
    def within_bounds(self) -> bool:
        return not self.exceeded

    # The seam acceleration against each of its two references; the bound judges the smaller ratio (the
    # larger reference): a seam where the simulator itself accelerates hard is not a kink the loop made.
    @property
    def seam_acceleration_vs_median(self) -> float:
        return _ratio(self.seam_acceleration, self.median_acceleration)

    @property
    def seam_acceleration_vs_simulation(self) -> float:
        return _ratio(self.seam_acceleration, self.simulated_seam_acceleration)

    @property
    def seam_acceleration_judged_against(self) -> str:
        """'simulation' or 'median': the reference seam_acceleration_ratio (the bounded one) divides by."""
        return "simulation" if self.simulated_seam_acceleration > self.median_acceleration else "median"

    def seam_acceleration_note(self) -> str:
        """One sentence for reports: both seam ratios, which one the bound judges, and why."""
        simulation, median = f"{self.seam_acceleration_vs_simulation:.3g}", f"{self.seam_acceleration_vs_median:.3g}"
        if self.seam_acceleration_judged_against == "simulation":
            return (f"Seam acceleration: {simulation}x the simulator's own at the seam, {median}x the loop's median; "
                    f"the bound ({QUALITY_BOUNDS['seam_acceleration_ratio']:g}) judges {simulation}, against the simulator, "
                    "because the cloth accelerates that hard there as simulated, so that much is not a kink of the loop.")
        return (f"Seam acceleration: {median}x the loop's median, {simulation}x the simulator's own at the seam; "
                f"the bound ({QUALITY_BOUNDS['seam_acceleration_ratio']:g}) judges {median}, against the median, "
                "because the simulator is calmer there than the loop's typical frame, so the median is the fair reference.")


def mean_edge_strain(points: np.ndarray, edges: np.ndarray, rest_lengths: np.ndarray) -> float:
    """Mean over frames and edges of |L / L_rest - 1|: (N, V, 3) points, (E, 2) edges, (E,) rest lengths."""
    rest_lengths = np.asarray(rest_lengths, dtype=np.float64)
    valid = rest_lengths > STILL_STEP  # a degenerate rest edge has no strain to speak of
    strain = edge_lengths(points, edges[valid]) / rest_lengths[valid] - 1.0
    return float(np.mean(np.abs(strain))) if strain.size else 0.0


def _cyclic_accelerations(loop: np.ndarray) -> np.ndarray:
    """RMS over vertices of x(i + 1) - 2 x(i) + x(i - 1) for a (l, V, 3) loop played cyclically: (l,)."""
    return _rms(np.roll(loop, -1, axis=0) - 2.0 * loop + np.roll(loop, 1, axis=0))


def loop_quality(
    raw_trajectory: np.ndarray,
    looped: np.ndarray,
    edges: np.ndarray | None = None,
    rest_lengths: np.ndarray | None = None,
) -> LoopQuality:
    """LoopQuality of `looped` (l, V, 3) against the simulator's frames.

    raw_trajectory: (l + 3, V, 3) close_loop(..., "none"): frames Fs-1 .. Fe+1 as simulated.
    edges: (E, 2) cloth edges and rest_lengths (E,) for the stretch ratio (both or neither).
    """
    raw_trajectory = as_point_frames(raw_trajectory, "loop_quality raw")
    looped = as_point_frames(looped, "loop_quality looped")
    length = looped.shape[0]
    if raw_trajectory.shape != (length + 3, *looped.shape[1:]):
        raise ValueError(f"loop_quality: raw trajectory {raw_trajectory.shape} does not frame a loop of {looped.shape}")
    raw_loop = raw_trajectory[1:-2]
    seam_jump = float(_rms(raw_trajectory[-2] - raw_trajectory[1]))
    deviation = float(_rms(looped - raw_loop).max())
    acceleration = _cyclic_accelerations(looped)
    median_acceleration = float(np.median(acceleration))
    seam_acceleration = float(max(acceleration[0], acceleration[-1]))
    # The simulator's accelerations at the same frames: at Fs (from Fs-1, Fs, Fs+1) and at Fe-1.
    simulated = _rms(raw_trajectory[2:] - 2.0 * raw_trajectory[1:-1] + raw_trajectory[:-2])  # frames Fs .. Fe
    simulated_seam = float(max(simulated[0], simulated[length - 1]))
    stretch = None
    if edges is not None and rest_lengths is not None and len(edges):
        raw_strain = mean_edge_strain(raw_loop, edges, rest_lengths)
        stretch = _ratio(mean_edge_strain(looped, edges, rest_lengths), max(raw_strain, MIN_REFERENCE_STRAIN))
    ratios = {
        "stretch_ratio": stretch,
        "deviation_ratio": _ratio(deviation, max(seam_jump, MIN_JUMP_STEP_FRACTION * float(np.median(_rms(np.diff(raw_loop, axis=0)))))),
        "seam_acceleration_ratio": _ratio(seam_acceleration, max(median_acceleration, simulated_seam)),
    }
    exceeded = tuple(name for name, bound in QUALITY_BOUNDS.items() if ratios[name] is not None and not ratios[name] <= bound)
    return LoopQuality(
        stretch_ratio=ratios["stretch_ratio"],
        deviation_ratio=ratios["deviation_ratio"],
        seam_acceleration_ratio=ratios["seam_acceleration_ratio"],
        max_acceleration_ratio=_ratio(float(acceleration.max()), median_acceleration),
        seam_jump=seam_jump,
        seam_acceleration=seam_acceleration,
        median_acceleration=median_acceleration,
        simulated_seam_acceleration=simulated_seam,
        exceeded=exceeded,
    )
