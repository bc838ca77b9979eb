"""Anti-aliased impostor silhouettes: the share of each texel the character covers, stored in the surface
map's alpha (SPEC.md "Impostor maps"), and the texels it covers only in part given a surface to draw."""
from __future__ import annotations

import json

import numpy as np
from crowdbake.bake import atlas, compression, impostor_views
from crowdbake.formats.binary import decode_texture_array
from crowdbake.stages.impostors import MIN_COVERAGE, extend_to_partial_texels, footprint_normals


def test_partly_covered_texels_take_their_nearest_covered_texel_and_join_the_mask():
    mask = np.zeros((1, 8, 8), dtype=bool)
    mask[0, 2:6, 2:6] = True
    coverage = mask.astype(np.float64)
    coverage[0, 1, 3] = 0.5  # a sliver above the square
    coverage[0, 6, 6] = 0.5 * MIN_COVERAGE  # too little to store: stays outside
    values = np.zeros((1, 8, 8, 2), dtype=np.uint16)
    values[0, 2, 3] = (7, 9)  # the covered texel under the sliver
    before = values.copy()
    extended = extend_to_partial_texels(mask, coverage, [values])
    assert extended[0, 1, 3] and not extended[0, 6, 6]
    assert (extended & ~mask).sum() == 1
    assert tuple(values[0, 1, 3]) == (7, 9)
    unchanged = np.ones((1, 8, 8), dtype=bool)
    unchanged[0, 1, 3] = False
    assert np.array_equal(values[unchanged], before[unchanged])


def test_a_full_mask_or_no_partial_texel_changes_nothing():
    mask = np.ones((1, 4, 4), dtype=bool)
    values = np.arange(16, dtype=np.float64).reshape(1, 4, 4, 1)
    assert extend_to_partial_texels(mask, np.ones((1, 4, 4)), [values]) is mask
    assert np.array_equal(values.ravel(), np.arange(16))


def test_a_texel_across_a_crease_keeps_the_direction_of_its_samples_mean_normal():
    """A flat-shaded ridge whose edge runs through a texel: a third of its samples on a face tilted 45° left,
    two thirds on one tilted 45° right. The map shader's centre sample saw one face; the texel keeps the
    mean's direction, coded as the shader codes a normal. A texel outside the mask, and one whose samples'
    normals cancel, keep their codes."""
    left, right = np.array([-1.0, 0.0, 1.0]) / np.sqrt(2.0), np.array([1.0, 0.0, 1.0]) / np.sqrt(2.0)
    sums = np.zeros((1, 1, 3, 3))
    sums[0, 0, 0] = (3 * left + 6 * right) / 9.0
    sums[0, 0, 1] = right  # outside the mask
    sums[0, 0, 2] = (left + np.array([1.0, 0.0, -1.0]) / np.sqrt(2.0)) / 2.0  # cancels
    centre = np.floor((right + 1.0) * 127.5 + 0.5).astype(np.uint8)
    codes = np.broadcast_to(centre, (1, 1, 3, 3)).copy()
    mask = np.array([[[True, False, True]]])
    coded = footprint_normals(sums, codes, mask)
    mean = (left + 2.0 * right) / np.linalg.norm(left + 2.0 * right)
    np.testing.assert_array_equal(coded[0, 0, 0], np.floor((mean + 1.0) * 127.5 + 0.5))
    assert not np.array_equal(coded[0, 0, 0], centre)
    np.testing.assert_array_equal(coded[0, 0, 1], centre)
    np.testing.assert_array_equal(coded[0, 0, 2], centre)
    assert coded.dtype == np.uint8


def test_the_surface_maps_alpha_is_the_share_of_each_texel_the_mesh_covers(small_bake):
    """The bake's alpha against pyrender's triangle-id render of the same view at 3 x 3 samples a texel
    (an independent rasteriser): equal within BC2's 4-bit step on every texel, and the silhouette soft."""
    from crowdbake.reference.triangle_ids import TriangleIdRenderer
    from crowdbake.stages.impostors import FIDELITY_SUPERSAMPLE, load_plan, load_poses, load_scene

    bundle, work = small_bake
    manifest = json.loads((bundle / "manifest.json").read_text())
    impostor = manifest["impostor"]
    surface = decode_texture_array((bundle / impostor["maps"]["surface"]).read_bytes())
    assert surface.pixel_format == "bc2"
    plan, poses = load_plan(work), load_poses(work)
    layout = poses.atlas_layout()
    frame = poses.frame_indices[0]
    alpha_atlas = compression.decode(surface.layers[0], "bc2", surface.width, surface.height)[..., 3] / 255.0
    scene = load_scene(work, plan, frame, runtime_textures=False)
    tile = layout.tile_size
    size = tile * FIDELITY_SUPERSAMPLE
    a, e = 1, 1
    view = impostor_views.ortho_view(plan.center, plan.radius, layout.azimuths_deg[a], layout.elevations_deg[e], size)
    with TriangleIdRenderer(size) as renderer:
        renderer.set_mesh(scene.positions, scene.faces)
        ids = renderer.render(view).ids
    expected = (ids >= 0).reshape(tile, FIDELITY_SUPERSAMPLE, tile, FIDELITY_SUPERSAMPLE).mean(axis=(1, 3))
    stored = atlas.view_tile(layout, alpha_atlas[..., None], a, e)[..., 0]
    error = np.abs(stored - expected)
    # 4-bit alpha: within half a step (1/30) where the mesh's share is stored; a texel whose centre the
    # mesh misses may round its sliver away (MIN_COVERAGE).
    assert np.percentile(error, 99.5) <= 1.0 / 30.0 + 1e-6, error.max()
    soft = (stored > 0.0) & (stored < 1.0)
    assert soft.sum() > 0.5 * (expected > 0).sum() ** 0.5  # the silhouette's texels, not a hard edge
    assert stored.max() == 1.0 and stored.min() == 0.0


def test_the_footprint_pass_is_the_references_alpha_to_the_bit(small_bake):
    """The impostor tasks take each texel's share from a pass that draws the mesh's samples unshaded: the
    same samples as the shaded references (one vertex shader), so the same alpha, bit for bit, from every
    view of a ring and at a frame between baked ones. Its RGB sums unit normals over the covered samples."""
    from crowdbake.stages.impostors import load_plan, load_poses, load_scene, mesh_footprints, mesh_references

    _bundle, work = small_bake
    plan, poses = load_plan(work), load_poses(work)
    layout = poses.atlas_layout()
    angles = [(azimuth, elevation) for elevation in layout.elevations_deg for azimuth in layout.azimuths_deg]
    for frame in (poses.frame_indices[0], poses.frame_indices[-1]):
        scene = load_scene(work, plan, frame, runtime_textures=True)
        shaded = mesh_references(scene, plan, angles, with_coverage=True)
        footprints = mesh_footprints(scene, plan, angles)
        coverage = footprints[..., 3]
        assert footprints.shape == shaded.shape and footprints.dtype == np.float32
        assert np.array_equal(coverage, shaded[..., 3])
        assert 0.0 < coverage.mean() < 1.0 and ((coverage > 0.0) & (coverage < 1.0)).any()
        # The mean of unit normals over a share c of the samples is no longer than c, and about c where
        # the surface is smooth over the texel.
        length = np.linalg.norm(footprints[..., :3], axis=-1)
        assert (length <= coverage + 1e-5).all()
        full = coverage == 1.0
        assert np.median(length[full]) > 0.95
