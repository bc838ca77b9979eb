"""The position-based cloth simulator on small scenes whose right answer is known."""
from __future__ import annotations

import numpy as np
import pytest

from crowdbake.bake.mesh import unique_edges
from crowdbake.sample.cloth_sim import (
    ClothParams,
    bending_pairs,
    build_cloth_model,
    capsule_contacts,
    color_edges,
    edge_strain,
    inside_closed_parts,
    settling_curve,
    simulate,
    surface_distance,
    winding_numbers,
)
from crowdbake.sample.garments import grid_faces
from crowdbake.sample.humanoid import tube_mesh

FPS = 24.0
PARAMS = ClothParams(substeps=8, iterations=2, damping=1.0, bend_stiffness=0.5, friction=0.2)
# Extension (percent) an edge of a hanging sheet may keep: the tethers hold each straight column
# at its rest length, and Gauss-Seidel leaves a residual well under one substep of gravity.
HANGING_STRETCH_PERCENT = 1.0


def _sheet(rows: int = 12, columns: int = 12, spacing: float = 0.04):
    """A flat square sheet in the x-y plane, top row at y = 0, pinned along it."""
    r, c = np.meshgrid(np.arange(rows), np.arange(columns), indexing="ij")
    positions = np.stack([c.ravel() * spacing, -r.ravel() * spacing, np.zeros(rows * columns)], axis=1)
    faces = []
    for i in range(rows - 1):
        for j in range(columns - 1):
            a, b, d, e = i * columns + j, i * columns + j + 1, (i + 1) * columns + j, (i + 1) * columns + j + 1
            faces += [[a, d, b], [b, d, e]]
    return positions, np.array(faces), np.arange(columns)


def _static_tracks(pins: np.ndarray, capsules: np.ndarray, substeps: int):
    return np.repeat(pins[None], substeps, axis=0), np.repeat(capsules[None], substeps, axis=0)


def test_topology_helpers():
    faces = np.array([[0, 1, 2], [2, 1, 3]])
    np.testing.assert_array_equal(unique_edges(faces), [[0, 1], [0, 2], [1, 2], [1, 3], [2, 3]])
    np.testing.assert_array_equal(bending_pairs(faces), [[0, 3]])  # the two corners opposite edge 1-2
    grid, _ = grid_faces(6, 10)
    edges = unique_edges(grid)
    colours = color_edges(edges, 60)
    for colour in np.unique(colours):
        chosen = edges[colours == colour].ravel()
        assert len(chosen) == len(np.unique(chosen)), "two edges of one colour share a vertex"
    assert colours.max() + 1 <= 2 * 6 - 1  # greedy bound for a maximum degree of 6


def test_tethers_reach_the_nearest_pin():
    positions, faces, pinned = _sheet(4, 3)
    model = build_cloth_model(positions, faces, pinned)
    assert (model.tether_anchor[pinned] == -1).all()
    # Vertex in row 3, column 1 hangs from the pin straight above it, 3 edges away.
    vertex = 3 * 3 + 1
    assert model.tether_anchor[vertex] == 1
    assert model.tether_length[vertex] == pytest.approx(0.12)


def test_hanging_sheet_holds_its_length_and_its_pins():
    positions, faces, pinned = _sheet()
    model = build_cloth_model(positions, faces, pinned)
    pins, capsules = _static_tracks(positions[pinned], np.zeros((0, 2, 3)), PARAMS.substeps)
    points = simulate(model, PARAMS, positions, pins, capsules, np.zeros(0), 72, FPS)
    assert points.shape == (72, 144, 3) and points.dtype == np.float32
    np.testing.assert_allclose(points[:, pinned], np.broadcast_to(positions[pinned], (72, 12, 3)), atol=1e-6)
    strain = edge_strain(points[-24:], model.stretch, model.stretch_rest) * 100
    assert strain.max() < HANGING_STRETCH_PERCENT, strain.max()
    # It hangs: the sheet stays in its plane and the bottom row is still ~0.44 m below the pins.
    assert np.abs(points[-1, :, 2]).max() < 1e-3
    assert points[-1, -12:, 1].mean() == pytest.approx(-0.44, abs=0.02)
    assert np.abs(points[-1] - points[-2]).max() < 1e-3  # at rest


def test_cloth_drapes_over_a_capsule_without_passing_through():
    """A sheet falling onto a horizontal bar: no vertex ends inside the bar, and it drapes around it."""
    positions, faces, pinned = _sheet(14, 14, 0.03)
    flat = positions[:, [0, 2, 1]] * [1, 1, -1] + [-0.2, 0.3, -0.2]  # horizontal sheet at y = 0.3
    model = build_cloth_model(flat, faces, pinned[:1])  # one corner pinned so it cannot fly away
    bar = np.array([[[-0.5, 0.15, 0.0], [0.5, 0.15, 0.0]]])
    radius = np.array([0.05])
    pins, capsules = _static_tracks(flat[pinned[:1]], bar, PARAMS.substeps)
    points = simulate(model, PARAMS, flat, pins, capsules, radius, 48, FPS)
    depth = np.stack([capsule_contacts(p.astype(float), bar, radius)[0] for p in points])
    assert depth.max() < 0.002  # never more than 2 mm inside
    assert points[-1, :, 1].min() < 0.1  # the free side fell past the bar instead of sticking above it


def test_moving_capsule_pushes_cloth():
    """A capsule sweeping through a hanging sheet drags it along instead of passing through."""
    positions, faces, pinned = _sheet(10, 10, 0.04)
    model = build_cloth_model(positions, faces, pinned)
    substeps = PARAMS.substeps
    frames = 24
    steps = frames * substeps
    z = np.linspace(-0.3, 0.15, steps)  # the bar moves +z through the sheet's plane
    track = np.zeros((steps, 1, 2, 3))
    track[:, 0, 0] = np.stack([np.full(steps, -0.2), np.full(steps, -0.25), z], axis=1)
    track[:, 0, 1] = np.stack([np.full(steps, 0.6), np.full(steps, -0.25), z], axis=1)
    pins = np.repeat(positions[pinned][None], steps, axis=0)
    points = simulate(model, PARAMS, positions, pins, track, np.array([0.04]), frames, FPS)
    depth = np.stack([capsule_contacts(points[f].astype(float), track[f * substeps, 0][None], np.array([0.04]))[0] for f in range(frames)])
    assert depth.max() < 0.004
    assert points[-1, -10:, 2].mean() > 0.1  # the bottom row was carried forward


def test_simulation_is_deterministic_and_validates_inputs():
    positions, faces, pinned = _sheet(6, 6)
    model = build_cloth_model(positions, faces, pinned)
    pins, capsules = _static_tracks(positions[pinned], np.zeros((0, 2, 3)), PARAMS.substeps)
    first = simulate(model, PARAMS, positions, pins, capsules, np.zeros(0), 10, FPS)
    second = simulate(model, PARAMS, positions, pins, capsules, np.zeros(0), 10, FPS)
    assert first.tobytes() == second.tobytes()
    with pytest.raises(ValueError, match="pin_track"):
        simulate(model, PARAMS, positions, pins[:, :2], capsules, np.zeros(0), 10, FPS)
    with pytest.raises(ValueError, match="initial"):
        simulate(model, PARAMS, positions[:5], pins, capsules, np.zeros(0), 10, FPS)
    with pytest.raises(ValueError, match="pinned"):
        build_cloth_model(positions, faces, [])


def test_settling_curve_measures_distance_one_cycle_apart():
    cycle = 4
    periodic = np.tile(np.random.default_rng(0).normal(size=(cycle, 5, 3)), (3, 1, 1))
    np.testing.assert_allclose(settling_curve(periodic, cycle), [0.0, 0.0], atol=1e-12)
    drifting = periodic.copy()
    drifting[:, :, 0] += np.repeat([0.0, 1.0, 1.5], cycle)[:, None]  # moves 1, then 0.5 along x
    np.testing.assert_allclose(settling_curve(drifting, cycle), [1.0, 0.5])
    assert settling_curve(periodic[:cycle], cycle).size == 0


def test_winding_numbers_tell_inside_from_outside():
    tube = tube_mesh(np.array([[0, 0, 0], [0, 0.1, 0], [0, 0.9, 0], [0, 1, 0]]), np.array([[0, 0], [0.2, 0.2], [0.2, 0.2], [0, 0]]),
                     (0.0, 0.0, 1.0), rings=12, segments=24, uv_rect=(0, 0, 1, 1))
    points = np.array([[0, 0.5, 0], [0.15, 0.5, 0], [0.25, 0.5, 0], [0, 1.2, 0], [0, -0.1, 0]])
    winding = winding_numbers(points, tube.positions, tube.faces)
    np.testing.assert_allclose(winding, [1, 1, 0, 0, 0], atol=1e-9)
    inside = inside_closed_parts(points, tube.positions, tube.faces, [(0, len(tube.faces))])
    np.testing.assert_array_equal(inside, [True, True, False, False, False])


def test_surface_distance_to_a_tube():
    tube = tube_mesh(np.array([[0, 0, 0], [0, 0.1, 0], [0, 0.9, 0], [0, 1, 0]]), np.array([[0, 0], [0.2, 0.2], [0.2, 0.2], [0, 0]]),
                     (0.0, 0.0, 1.0), rings=12, segments=24, uv_rect=(0, 0, 1, 1))
    vertex = tube.positions[30]  # a ring vertex, on the surface
    points = np.array([vertex, vertex * [1.5, 1, 1.5], [0, 0.5, 0]])
    distance = surface_distance(points, tube.positions, tube.faces)
    assert distance[0] == pytest.approx(0.0, abs=1e-12)
    assert distance[1] == pytest.approx(0.5 * np.hypot(vertex[0], vertex[2]), abs=1e-3)  # straight out from the axis
    assert 0.19 < distance[2] <= 0.2  # the axis is a radius away, less the facets' sag


def test_tethers_allow_a_fraction_of_the_rest_detour():
    """A sheet bent at a right angle: the straight distance to its pin is shorter than along the cloth."""
    positions, faces, pinned = _sheet(4, 3)
    bent = positions.copy()
    below = bent[:, 1] < -0.05  # rows 2 and 3 fold out along +z from row 1
    bent[below, 2] = -0.04 - bent[below, 1]
    bent[below, 1] = -0.04
    vertex = 3 * 3 + 1
    straight = np.linalg.norm(bent[vertex] - bent[1])
    assert build_cloth_model(bent, faces, pinned).tether_length[vertex] == pytest.approx(0.12)
    assert build_cloth_model(bent, faces, pinned, tether_detour=0.0).tether_length[vertex] == pytest.approx(straight)
    assert build_cloth_model(bent, faces, pinned, tether_detour=0.5).tether_length[vertex] == pytest.approx((0.12 + straight) / 2)
