"""The bake's copy of crowdview's impostor blending: which views and frames (crowdbake.bake.view_blend)
and the blended picture (crowdbake.reference.impostor_blend).

The weights are checked against runtime/tests/data/view_blend_vectors.json, which crowdview's
view_blend ctest reads too, so both sides follow one set of answers worked out from the README's rules.
The blended picture is checked on small tiles whose answer is known by construction.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from crowdbake.bake import view_blend
from crowdbake.reference import impostor_blend
from crowdbake.reference.impostor_blend import DecodedTile

VECTORS = Path(__file__).resolve().parents[2] / "runtime" / "tests" / "data" / "view_blend_vectors.json"


@pytest.fixture(scope="module")
def vectors() -> dict:
    return json.loads(VECTORS.read_text())


def test_view_weights_match_the_shared_vectors(vectors):
    tolerance = vectors["tolerance"]
    for case in vectors["views"]:
        azimuth, elevation = view_blend.view_angles_deg(np.array(case["to_camera"]), case["heading"])
        expected_azimuth, expected_elevation = case["angles_deg"]
        assert abs((azimuth - expected_azimuth + 180) % 360 - 180) < tolerance, case["why"]
        assert elevation == pytest.approx(expected_elevation, abs=tolerance), case["why"]
        weights = view_blend.blend_view_weights(azimuth, elevation, vectors["azimuths_deg"], vectors["elevations_deg"])
        assert sum(weights.weights) == pytest.approx(1.0)
        used = {(t, round(w, 6)) for t, w in zip(weights.tiles, weights.weights) if w > tolerance}
        expected = {(t, round(w, 6)) for t, w in zip(case["tiles"], case["weights"]) if w > tolerance}
        assert used == expected, case["why"]


def test_frame_weights_match_the_shared_vectors(vectors):
    for case in vectors["frames"]:
        got = view_blend.blend_frame_weights(case["frame"], case["frame_indices"], case["frame_count"])
        assert list(got.layers) == case["layers"], case["why"]
        assert got.weight == pytest.approx(case["weight"], abs=vectors["tolerance"]), case["why"]
    for case in vectors["cycle_frames"]:
        frame = view_blend.cycle_frame(case["seconds"], case["phase"], case["frames_per_second"], case["frame_count"])
        assert frame == case["frame"], case["why"]


def _tile(size: int, covered: np.ndarray, u: float, normal=(0.0, 0.0, 1.0)) -> DecodedTile:
    uv = np.zeros((size, size, 2))
    uv[..., 0], uv[..., 1] = u, 0.5
    return DecodedTile(uv, np.zeros((size, size), np.int64), covered, np.broadcast_to(np.array(normal, float), (size, size, 3)).copy())


def test_blend_averages_colours_and_fades_edges_where_the_samples_disagree():
    """Two reprojected samples of a two-colour texture: their colours mix by weight where both cover
    (opaque); where only the heavier one covers (coverage 0.75) its colour is drawn at edge_alpha(0.75);
    where only the lighter one covers (0.25) more faintly; where none covers, nothing."""
    size = 8
    texture = np.zeros((4, 4, 4), np.uint8)
    texture[:, :2, :3] = (200, 0, 0)  # u < 0.5 red
    texture[:, 2:, :3] = (0, 0, 200)  # u > 0.5 blue
    left = np.zeros((size, size), bool)
    left[:, :6] = True
    right = np.zeros((size, size), bool)
    right[:, 2:] = True
    samples = [(0.75, _tile(size, left, 0.125)), (0.25, _tile(size, right, 0.875))]
    light = np.array([0.0, 0.0, 1.0])  # along the normal: full diffuse, so colour = albedo
    outfit = np.zeros((16, 4), np.uint8)
    image = impostor_blend.blend_image(samples, [texture], outfit, light, tile_size=size)
    red, blue = 200 / 255.0, 200 / 255.0
    heavy, light_only = impostor_blend.edge_alpha(0.75), impostor_blend.edge_alpha(0.25)
    assert 0.5 < heavy < 1 and 0 < light_only < 0.5
    assert np.allclose(image[:, 3], [0.75 * red, 0, 0.25 * blue])  # both cover: 3:1 mix, opaque
    assert np.allclose(image[:, 0], [heavy * red, 0, 0])  # only the heavier sample
    assert np.allclose(image[:, 7], [0, 0, light_only * blue])  # only the lighter one
    none = [(1.0, _tile(size, np.zeros((size, size), bool), 0.125))]
    assert not impostor_blend.blend_image(none, [texture], outfit, light, tile_size=size).any()
    # Unmoved samples (no surface map): cut at one half, the heavier sample's edge opaque, the lighter's gone.
    cut = impostor_blend.blend_image(samples, [texture], outfit, light, tile_size=size, reprojected=False)
    assert np.allclose(cut[:, 0], [red, 0, 0]) and np.allclose(cut[:, 7], 0) and np.allclose(cut[:, 3], image[:, 3])


def test_a_reprojected_samples_colour_and_normal_blend_its_four_taps_colour_over_the_covered_ones():
    """impostor_uv.frag.glsl filtered_albedo and impostor_warp.glsl filtered_normal: the colour is the
    bilinear blend of the taps the character covers (an uncovered tap has no texture coordinate), the
    normal that of all four (the normal map is filled into the background)."""
    size = 4
    texture = np.zeros((4, 4, 4), np.uint8)
    texture[:, :2, :3] = (200, 0, 0)  # u < 0.5 red
    texture[:, 2:, :3] = (0, 0, 200)  # u > 0.5 blue
    everywhere, nowhere = np.ones((size, size), bool), np.zeros((size, size), bool)
    red, blue = _tile(size, everywhere, 0.125), _tile(size, everywhere, 0.875, normal=(1.0, 0.0, 0.0))
    weights = [np.full((size, size), w) for w in (0.5, 0.25, 0.25, 0.0)]
    taps = ((weights[0], red), (weights[1], blue), (weights[2], _tile(size, nowhere, 0.875)), (weights[3], red))
    sample = DecodedTile(red.uv, red.material, everywhere, red.normal, taps=taps)
    outfit = np.zeros((16, 4), np.uint8)
    colour, normal = impostor_blend.sample_albedo_and_normal(sample, [texture], [impostor_blend.mip_chain(texture)], outfit, size)
    # Colour over the covered taps: 0.5 red and 0.25 blue, renormalised to 2:1.
    np.testing.assert_allclose(colour[0, 0], [2 / 3 * 200 / 255, 0.0, 1 / 3 * 200 / 255], atol=1e-9)
    # Normal over all four: 0.75 of +Z (red and the uncovered tap) and 0.25 of +X.
    np.testing.assert_allclose(normal[0, 0], [0.25, 0.0, 0.75], atol=1e-12)
    # Without taps (plain blending, or a sample at its own view and frame): the texel's own.
    own_colour, own_normal = impostor_blend.sample_albedo_and_normal(red, [texture], [impostor_blend.mip_chain(texture)], outfit, size)
    np.testing.assert_allclose(own_colour[0, 0], [200 / 255, 0.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(own_normal[0, 0], [0.0, 0.0, 1.0])


def test_edge_alpha_is_configs_smoothstep():
    """Opaque where every sample covers, transparent at or under the threshold, one half at a tie, rising
    in between; the threshold is crowdview's config.h CV_EDGE_LOW, which its shaders read."""
    coverage = np.linspace(0.0, 1.0, 101)
    alpha = impostor_blend.edge_alpha(coverage)
    assert alpha[0] == 0 and alpha[-1] == 1 and abs(impostor_blend.edge_alpha(0.5) - 0.5) < 1e-12
    assert np.all(np.diff(alpha) >= 0) and np.all(alpha[coverage <= impostor_blend.EDGE_LOW] == 0)
    assert np.all(alpha[coverage >= 1 - impostor_blend.EDGE_LOW] == 1)
    assert np.array_equal(impostor_blend.edge_alpha(coverage, reprojected=False), (coverage > 0.5).astype(float))
    config = (VECTORS.parents[2] / "src" / "config.h").read_text()
    assert f"#define CV_EDGE_LOW {impostor_blend.EDGE_LOW}\n" in config


def test_trilinear_lookup_averages_at_coarse_levels():
    """At a level of detail of log2(size) the whole texture is one texel: its mean colour."""
    rng = np.random.default_rng(3)
    texture = rng.integers(0, 256, (8, 8, 4), dtype=np.uint8)
    chain = impostor_blend.mip_chain(texture)
    assert len(chain) == 4
    colour = impostor_blend.sample_trilinear(chain, np.array([[0.3, 0.7]]), np.array([3.0]))
    assert np.allclose(colour[0], texture[..., :3].reshape(-1, 3).mean(axis=0))
    exact = impostor_blend.sample_trilinear(chain, np.array([[2.5 / 8, 5.5 / 8]]), np.array([0.0]))
    assert np.allclose(exact[0], texture[5, 2, :3])


def test_samples_for_merges_repeated_pairs():
    view = view_blend.ViewWeights((3, 3, 3, 3), (1.0, 0.0, 0.0, 0.0))
    frames = view_blend.FrameWeights((0, 1), 0.25)
    assert sorted(impostor_blend.samples_for(view, frames)) == [(0.25, 3, 1), (0.75, 3, 0)]
