"""The impostor maps drawn by a shader (crowdbake.render.map_shader) against the exact float64 maps of
crowdbake.reference.impostor_maps, resolved from a triangle-id render (crowdbake.reference):
the same texels covered, the same values up to rounding, on a closed and an open shape with two
materials, under OSMesa."""
from __future__ import annotations

import numpy as np
import pytest

from crowdbake.bake import impostor_views, shading
from crowdbake.reference import impostor_maps as maps
from crowdbake.reference import mesh_reference
from crowdbake.bake import map_codecs, surface_maps
from crowdbake.stages.impostors import fill_background

pytest.importorskip("pyrender")
from crowdbake.render import offscreen  # noqa: E402
from crowdbake.render.impostor import BakeRenderer  # noqa: E402
from crowdbake.reference.triangle_ids import TriangleIdRenderer  # noqa: E402
from shapes import uv_sphere  # noqa: E402
from test_impostor import sphere_texture  # noqa: E402

SIZE = 48
ANGLES = ((0.0, 0.0), (70.0, 20.0), (200.0, -40.0), (330.0, 70.0))


def scene():
    """A UV sphere with its cap cut off (its inside shows from above), the lower half a second material
    with its own texture, and a next frame moved and scaled a little (the surface map's motion)."""
    positions, normals, uvs, faces = uv_sphere()
    faces = faces[positions[faces].mean(axis=1)[:, 1] < 0.6]
    material = (positions[faces].mean(axis=1)[:, 1] < 0.0).astype(np.int64)
    textures = [sphere_texture(64), np.ascontiguousarray(sphere_texture(32)[::-1, :, [2, 0, 1, 3]])]
    next_positions = positions * 1.02 + np.array([0.03, -0.02, 0.01])
    return positions, normals, uvs, faces, material, textures, next_positions


def exact_maps(views, positions, normals, uvs, faces, material, textures, next_positions):
    """The numpy maps of the views (and their coverage) from pyrender's triangle ids."""
    with TriangleIdRenderer(SIZE) as renderer:
        renderer.set_mesh(positions, faces)
        coverages = [renderer.coverage(view, positions, faces) for view in views]
    result = maps.view_maps_views(views, coverages, positions, normals, uvs, faces, material, textures)
    surfaces = np.stack([surface_maps.encode_surface(*maps.surface_fields(view, coverage, positions, next_positions, faces), 1.0)
                         for view, coverage in zip(views, coverages)])
    return result, coverages, surfaces


def test_shader_maps_are_the_exact_maps_up_to_rounding():
    positions, normals, uvs, faces, material, textures, next_positions = scene()
    views = [impostor_views.ortho_view((0.0, 0.0, 0.0), 1.0, azimuth, elevation, SIZE) for azimuth, elevation in ANGLES]
    with BakeRenderer(SIZE) as renderer, offscreen.timed_renders() as gl:
        drawn = renderer.shader_maps(views, positions, normals, uvs, next_positions, faces, material, textures)
    assert gl.renders == 1 and gl.seconds > 0, "the shader's pass counts as a render"
    exact, coverages, surfaces = exact_maps(views, positions, normals, uvs, faces, material, textures, next_positions)
    mask = np.stack([coverage.mask for coverage in coverages])
    # Both rasterise texel centres: the covered texels agree but for ties on an edge.
    assert (drawn.mask != mask).mean() < 1e-3
    assert drawn.mask.sum() > 0.1 * drawn.mask.size
    both = drawn.mask & mask
    fill_background(drawn.mask, [drawn.normal, drawn.detail], unflattened=[drawn.surface])
    drawn.surface[..., 3] = 255

    uv_exact = np.stack([m.uv for m in exact])

    def near(kind: str, got: np.ndarray, want: np.ndarray, tolerance: int, share: float) -> None:
        """At least `share` of the texels both cover within `tolerance` codes in every channel."""
        difference = np.abs(got.astype(np.int64) - want.astype(np.int64))[both]
        assert (difference <= tolerance).all(axis=-1).mean() >= share, f"{kind}: worst {difference.max(axis=0)}"

    near("normal", drawn.normal, np.stack([m.normal for m in exact]), 1, 0.995)
    near("uv", drawn.uv, uv_exact, 2, 0.995)
    near("detail", drawn.detail, np.stack([m.detail for m in exact]), 1, 0.99)
    near("surface", drawn.surface, surfaces, 1, 0.995)
    assert (drawn.uv[..., 2][both] == uv_exact[..., 2][both]).mean() > 0.995, "material index"
    assert set(np.unique(drawn.uv[..., 2][drawn.mask])) == {0, 1}
    # Alpha: 255 / 65535 inside, 0 outside; the background takes the silhouette's colours.
    np.testing.assert_array_equal(drawn.normal[..., 3], np.where(drawn.mask, 255, 0))
    np.testing.assert_array_equal(drawn.uv[..., 3], np.where(drawn.mask, 65535, 0))
    assert (drawn.detail[..., 3][~drawn.mask] == 0).all()
    # Normals face the camera side, also where the camera sees the inside of the open top.
    decoded = map_codecs.decode_normal_map(drawn.normal)
    for k, view in enumerate(views):
        assert (decoded[k][drawn.mask[k]] @ view.back > -0.05).all()


def test_views_of_other_sizes_and_many_rows_share_one_renderer():
    """A task of more views than fit one framebuffer row, then a smaller tile: the framebuffer grows and
    every view lands in its own tile: each view is its maps drawn alone, covering the same texels (the
    rasteriser works in fixed point, where a viewport's whole-texel offset is exact) with values within a
    code, the UV's 16 bits within 1/2048 (the interpolation's float32 arithmetic sees the offset: these
    views lie up to 7,000 texels from the framebuffer's origin)."""
    positions, normals, uvs, faces, material, textures, next_positions = scene()
    many = [impostor_views.ortho_view((0.0, 0.0, 0.0), 1.0, 360.0 * k / 9, 10.0, 1024) for k in range(9)]
    with BakeRenderer(16) as renderer:
        together = renderer.shader_maps(many, positions, normals, uvs, next_positions, faces, material, textures)
        alone = renderer.shader_maps(many[5:6], positions, normals, uvs, next_positions, faces, material, textures)
        small = renderer.shader_maps([impostor_views.ortho_view((0.0, 0.0, 0.0), 1.0, 40.0, 10.0, 16)], positions, normals, uvs,
                                     next_positions, faces, material, textures)
    np.testing.assert_array_equal(together.mask[5], alone.mask[0])
    for kind, tolerance in (("normal", 1), ("uv", 32), ("detail", 1), ("surface", 1)):
        difference = np.abs(getattr(together, kind)[5].astype(np.int64) - getattr(alone, kind)[0])
        assert difference.max() <= tolerance and (difference > 0).mean() < 1e-2, kind
    assert not np.array_equal(together.mask[0], together.mask[4])
    assert small.mask.shape == (1, 16, 16) and small.mask.any()


def test_a_view_that_misses_the_mesh_is_empty():
    positions, normals, uvs, faces, material, textures, next_positions = scene()
    away = impostor_views.ortho_view((5.0, 0.0, 0.0), 0.5, 0.0, 0.0, SIZE)
    with BakeRenderer(SIZE) as renderer:
        drawn = renderer.shader_maps([away], positions, normals, uvs, next_positions, faces, material, textures)
    assert not drawn.mask.any()
    for kind in ("normal", "uv", "detail", "surface"):
        assert not getattr(drawn, kind).any()


def test_shader_references_are_the_exact_mesh_references(monkeypatch):
    """The fidelity references (shaded per sample, outfit colours by region, box-filtered on the GPU)
    against crowdbake.reference.mesh_reference in float64 from exact coverage: the same picture to
    float32 rounding but for texels where the two disagree on an edge, and more views than one pass
    draws (MAX_PASS_TEXELS, lowered here to 8 views), so that the batches land in order."""
    from crowdbake.bake import fidelity
    from crowdbake.render import map_shader

    positions, normals, uvs, faces, material, textures, _ = scene()
    textures[1][..., 3] = np.where(np.arange(32)[:, None] < 16, 17 * 3, 0)  # region 3 on half the lower texture
    outfit = np.full((16, 4), 255, dtype=np.uint8)
    outfit[3] = (60, 200, 90, 255)
    supersample = 3
    angles = [(360.0 * k / 7, elevation) for k in range(7) for elevation in (-30.0, 0.0, 40.0)]
    views = [impostor_views.ortho_view((0.0, 0.0, 0.0), 1.0, azimuth, elevation, SIZE * supersample) for azimuth, elevation in angles]
    monkeypatch.setattr(map_shader, "MAX_PASS_TEXELS", 8 * (SIZE * supersample) ** 2)
    with BakeRenderer(SIZE) as renderer:
        drawn = renderer.shader_references(views, positions, normals, uvs, faces, material, textures, outfit, supersample)
    assert drawn.shape == (len(views), SIZE, SIZE, 3) and drawn.dtype == np.float32
    with TriangleIdRenderer(SIZE * supersample) as renderer:
        renderer.set_mesh(positions, faces)
        exact = np.stack([mesh_reference.mesh_reference(view, renderer.coverage(view, positions, faces), supersample, positions, normals, uvs,
                                                  faces, material, textures, outfit, shading.camera_light(view)) for view in views])
    difference = np.abs(drawn - exact)
    assert (difference <= 1e-4).mean() > 0.999, f"worst {difference.max()}"
    assert difference.mean() < 1e-5
    tinted = np.isclose(exact[..., 1], drawn[..., 1], atol=1e-4) & (exact[..., 1] > exact[..., 0] + 0.05)
    assert tinted.any(), "the outfit's green shows where region 3 is"
    for k in range(len(views)):
        assert fidelity.compare(exact[k], drawn[k])["ssim"] > 0.999


def test_footprints_are_the_mean_shading_normal_and_the_share_of_each_texels_samples():
    positions, normals, uvs, faces, material, textures, _ = scene()
    supersample = 3
    views = [impostor_views.ortho_view((0.0, 0.0, 0.0), 1.0, azimuth, elevation, SIZE * supersample) for azimuth, elevation in ANGLES]
    with BakeRenderer(SIZE) as renderer:
        drawn = renderer.shader_footprints(views, positions, normals, faces, material, len(textures), supersample)
    assert drawn.shape == (len(views), SIZE, SIZE, 4) and drawn.dtype == np.float32
    with TriangleIdRenderer(SIZE * supersample) as renderer:
        renderer.set_mesh(positions, faces)
        exact = np.stack([maps.footprints(view, renderer.coverage(view, positions, faces), supersample, normals, positions, faces)
                          for view in views])
    difference = np.abs(drawn - exact)
    assert (difference <= 1e-4).mean() > 0.999, f"worst {difference.max()}"
    partial = (exact[..., 3] > 0.0) & (exact[..., 3] < 1.0)
    assert partial.sum() > 50 and (exact[..., 3] == 1.0).sum() > 500

