"""The pass-2 edge metric (crowdbake.bake.edge_metric) and the pictures it compares (crowdbake.render)."""
from __future__ import annotations

import numpy as np
import pytest

from crowdbake.bake import edge_metric as em


def vertical_line(x: int, size: int = 64) -> np.ndarray:
    edges = np.zeros((size, size), dtype=bool)
    edges[8:56, x] = True
    return edges


class TestChamfer:
    def test_identical_edges_are_zero_apart(self):
        edges = vertical_line(20)
        assert em.chamfer_distance(edges, edges) == 0.0

    @pytest.mark.parametrize("shift", [1, 3, 7])
    def test_a_shifted_line_is_its_shift_away(self, shift):
        # Every pixel of each line is exactly `shift` from the other line (same rows): the mean is the shift.
        assert em.chamfer_distance(vertical_line(20), vertical_line(20 + shift), truncation_px=10) == pytest.approx(shift)

    def test_distances_are_truncated(self):
        assert em.chamfer_distance(vertical_line(10), vertical_line(40), truncation_px=5) == pytest.approx(5.0)

    def test_symmetric_and_both_directions_count(self):
        # A has one line, B has that line plus a far one: A -> B is 0, B -> A is half the truncation.
        a = vertical_line(10)
        b = a | vertical_line(50)
        assert em.directed_chamfer(a, em.distance_to_edges(b), 8.0) == 0.0
        assert em.directed_chamfer(b, em.distance_to_edges(a), 8.0) == pytest.approx(4.0)
        assert em.chamfer_distance(a, b, 8.0) == pytest.approx(2.0)
        assert em.chamfer_distance(b, a, 8.0) == em.chamfer_distance(a, b, 8.0)

    def test_empty_images(self):
        empty = np.zeros((32, 32), dtype=bool)
        assert em.chamfer_distance(empty, empty) == 0.0
        # Edges against nothing: all out of place, half the symmetric sum.
        assert em.chamfer_distance(vertical_line(10, 32), empty, truncation_px=6) == pytest.approx(3.0)

    def test_distance_transform_is_euclidean(self):
        edges = np.zeros((21, 21), dtype=bool)
        edges[10, 10] = True
        distance = em.distance_to_edges(edges)
        assert distance[10, 13] == pytest.approx(3.0, abs=1e-3)
        assert distance[13, 14] == pytest.approx(5.0, abs=1e-3)  # a 3-4-5 triangle

    def test_bad_input_is_refused(self):
        with pytest.raises(ValueError, match="one shape"):
            em.chamfer_distance(np.zeros((4, 4), bool), np.zeros((4, 5), bool))
        with pytest.raises(ValueError, match="truncation_px"):
            em.chamfer_distance(np.zeros((4, 4), bool), np.zeros((4, 4), bool), truncation_px=0)
        with pytest.raises(ValueError, match="uint8"):
            em.edge_image(np.zeros((8, 8), np.float32))


def disc_image(center_x: int, radius: int = 20, size: int = 96) -> np.ndarray:
    y, x = np.mgrid[:size, :size]
    return np.where((x - center_x) ** 2 + (y - size // 2) ** 2 <= radius**2, 200, 0).astype(np.uint8)


class TestCompareViews:
    def test_canny_finds_the_outline_of_a_disc(self):
        edges = em.edge_image(disc_image(48))
        ys, xs = np.nonzero(edges)
        radius = np.hypot(xs - 48, ys - 48)
        assert len(xs) > 100 and np.all(np.abs(radius - 20) < 2.5)

    def test_summed_over_views_and_growing_with_the_change(self):
        start = np.stack([disc_image(48), disc_image(40)])
        same = em.compare_views(start, start)
        assert same.total == 0.0 and same.per_view.shape == (2,)
        near = em.compare_views(start, np.stack([disc_image(49), disc_image(40)]))
        far = em.compare_views(start, np.stack([disc_image(52), disc_image(44)]))
        assert near.per_view[1] == 0.0 and near.per_view[0] > 0
        assert far.total == pytest.approx(far.per_view.sum())
        assert far.total > near.total
        assert far.edges_start.shape == (2, 96, 96) and far.edges_start.dtype == bool

    def test_colour_images_are_accepted(self):
        grey = disc_image(48)
        colour = np.repeat(grey[..., None], 3, axis=2)
        np.testing.assert_array_equal(em.edge_image(colour), em.edge_image(grey))

    def test_view_counts_must_match(self):
        with pytest.raises(ValueError, match="same non-zero number of views"):
            em.compare_views([disc_image(48)], [disc_image(48), disc_image(48)])


class TestOffscreenHelpers:
    def test_look_at_is_a_rotation_looking_down_minus_z(self):
        from crowdbake.render.offscreen import look_at

        pose = look_at([3.0, 2.0, 5.0], [0.0, 1.0, 0.0])
        rotation = pose[:3, :3]
        np.testing.assert_allclose(rotation.T @ rotation, np.eye(3), atol=1e-12)
        assert np.linalg.det(rotation) == pytest.approx(1.0)
        forward = -rotation[:, 2]
        expected = np.array([-3.0, -1.0, -5.0]) / np.linalg.norm([3.0, 1.0, 5.0])
        np.testing.assert_allclose(forward, expected, atol=1e-12)
        assert rotation[1, 1] > 0  # the image's up is the world's up
        # Straight down still gives a proper rotation.
        down = look_at([0.0, 5.0, 0.0], [0.0, 0.0, 0.0])
        assert np.linalg.det(down[:3, :3]) == pytest.approx(1.0)

    def test_view_pose_azimuth_convention(self):
        from crowdbake.render.offscreen import CAMERA_DISTANCE_RADII, view_pose

        front = view_pose([0, 1, 0], 0.5, azimuth_deg=0, elevation_deg=0)
        np.testing.assert_allclose(front[:3, 3], [0, 1, 0.5 * CAMERA_DISTANCE_RADII], atol=1e-12)
        side = view_pose([0, 1, 0], 0.5, azimuth_deg=90, elevation_deg=0)
        np.testing.assert_allclose(side[:3, 3], [0.5 * CAMERA_DISTANCE_RADII, 1, 0], atol=1e-12)
        above = view_pose([0, 0, 0], 1.0, azimuth_deg=0, elevation_deg=30)
        assert above[1, 3] == pytest.approx(CAMERA_DISTANCE_RADII * 0.5)


def cone_skirt(rings: int = 10, segments: int = 48, folds: int = 0, fold_depth: float = 0.0):
    t = np.linspace(0.0, 1.0, rings)[:, None]
    angle = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)[None, :]
    radius = 0.15 + 0.15 * t + fold_depth * t * np.sin(folds * angle)
    points = np.stack([radius * np.sin(angle), np.broadcast_to(1.0 - 0.6 * t, radius.shape), radius * np.cos(angle)], -1)
    i, j = np.meshgrid(np.arange(rings - 1), np.arange(segments), indexing="ij")
    a, b = i * segments + j, i * segments + (j + 1) % segments
    c, d = a + segments, b + segments
    faces = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)])
    return points.reshape(-1, 3), faces


class TestClothViews:
    def test_pictures_are_deterministic_and_folds_move_edges(self):
        from crowdbake.render.cloth_views import ClothViewRenderer

        smooth, faces = cone_skirt()
        folded, _ = cone_skirt(folds=9, fold_depth=0.03)
        body = np.array([[0, 1.2, 0], [0.1, 0.2, 0], [-0.1, 0.2, 0], [0, 0.2, 0.1]], dtype=np.float32)
        body_faces = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 1]])
        renderer = ClothViewRenderer(faces, body_faces, views=3, size=96)
        images = renderer(np.stack([smooth, smooth, folded]), np.stack([body, body, body]))
        assert images.shape == (3, 3, 96, 96) and images.dtype == np.uint8
        # Something was drawn, on a black background, inside the frame.
        assert images[0].max() > 100 and images[0][:, 0, 0].max() == 0
        np.testing.assert_array_equal(images[0], images[1])
        assert em.compare_views(images[0], images[1]).total == 0.0
        assert em.compare_views(images[0], images[2]).total > 1.0

    def test_body_without_faces_is_refused(self):
        from crowdbake.render.cloth_views import ClothViewRenderer

        _, faces = cone_skirt()
        renderer = ClothViewRenderer(faces, None, views=1, size=32)
        with pytest.raises(ValueError, match="no body_faces"):
            renderer(np.zeros((1, 480, 3)), np.zeros((1, 4, 3)))
