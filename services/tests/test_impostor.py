"""The test oracles of the impostor maps: pyrender's visibility buffer (crowdbake.reference.triangle_ids),
the exact coverage resolved from it (crowdbake.reference.coverage) and the exact per-texel maps
computed from that (crowdbake.reference.impostor_maps); and the cameras they share with the bake."""
from __future__ import annotations

import numpy as np
import pytest

from crowdbake.bake import impostor_views
from crowdbake.reference import coverage as exact
from crowdbake.reference import impostor_maps as maps
from crowdbake.bake import map_codecs, short_rows
from crowdbake.formats.texel_codecs import region_alpha

pyrender = pytest.importorskip("pyrender")
from crowdbake.render import offscreen  # noqa: E402
from crowdbake.reference import triangle_ids  # noqa: E402
from crowdbake.reference.triangle_ids import TriangleIdRenderer  # noqa: E402
from shapes import uv_sphere  # noqa: E402

# Detail map against pyrender's own textured rendering of the same mesh (GL's bilinear filter and
# rasterisation against ours): measured 0.99; below 0.95 something is flipped or misaligned.
PYRENDER_DETAIL_SSIM = 0.95
# 16-bit UV: one step is 1/65535; rounding costs at most half of it (plus float noise).
UV_STEP = 1.0 / 65535.0
UV32_STEP = 1.0 / 16383.0  # uv32 stores 14 bits a coordinate


def sphere_texture(size: int = 64) -> np.ndarray:
    """(size, size, 4) uint8: smooth colours, periodic in u so the seam is invisible; regions in alpha."""
    v, u = (np.mgrid[0:size, 0:size] + 0.5) / size
    texture = np.zeros((size, size, 4), dtype=np.uint8)
    texture[..., 0] = np.rint(128 + 100 * np.sin(2 * np.pi * u))
    texture[..., 1] = np.rint(128 + 100 * np.cos(np.pi * v))
    texture[..., 2] = np.rint(128 + 80 * np.cos(2 * np.pi * u))
    texture[..., 3] = region_alpha((np.floor(u * 4).astype(int) + 4 * (v > 0.5)) % 16)
    return texture


def render_maps(positions, normals, uvs, faces, texture, azimuth, elevation, size=64, center=(0.0, 0.0, 0.0), radius=1.0):
    view = impostor_views.ortho_view(center, radius, azimuth, elevation, size)
    with TriangleIdRenderer(size) as renderer:
        renderer.set_mesh(positions, faces)
        coverage = renderer.coverage(view, positions, faces)
    return view, maps.view_maps(view, coverage, positions, normals, uvs, faces, np.zeros(len(faces), int), [texture])


def test_camera_is_the_spec_camera_and_matches_offscreen():
    for azimuth, elevation in ((0, 0), (90, 0), (200, 35), (30, -60), (0, 90)):
        view = impostor_views.ortho_view((0.1, 0.9, -0.2), 0.8, azimuth, elevation, 32)
        np.testing.assert_allclose(triangle_ids.camera_pose(view), offscreen.view_pose((0.1, 0.9, -0.2), 0.8, azimuth, elevation), atol=1e-12)
    front = impostor_views.ortho_view((0, 0, 0), 1.0, 0.0, 0.0, 64)
    # From the front (+Z) the character's left (+X) is on the image's right, its head (+Y) at the top.
    xy, depth = impostor_views.project(front, np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 0]]))
    np.testing.assert_allclose(xy, [[64, 32], [32, 0], [32, 32]])
    assert depth[2] == pytest.approx(impostor_views.CAMERA_DISTANCE_RADII)
    side = impostor_views.ortho_view((0, 0, 0), 1.0, 90.0, 0.0, 64)
    np.testing.assert_allclose(side.back, [1, 0, 0], atol=1e-12)  # azimuth 90: the camera on +X


def test_one_offscreen_compiles_each_shader_program_once():
    """Many renders through one Offscreen (new meshes and scenes each time, as the cycle search and the
    impostor tasks draw) compile each shader program once: pyrender's own cache, keyed by a context handle
    that PyOpenGL's OSMesa binding makes anew on every call, compiled them on every render."""
    positions, normals, _, faces = uv_sphere(8, 12)
    material = offscreen.lit_material((0.8, 0.6, 0.4))
    with offscreen.Offscreen(32, 32) as shared:
        images = []
        for k in range(6):
            scene = pyrender.Scene(bg_color=[0.0, 0.0, 0.0, 1.0], ambient_light=[0.3] * 3)
            scene.add(offscreen.triangle_mesh(positions * (1.0 + 0.1 * k), faces, normals, material))
            pose = offscreen.view_pose((0.0, 0.0, 0.0), 2.0, 30.0 * k, 10.0)
            scene.add(offscreen.orthographic_camera(2.0), pose=pose)
            scene.add(pyrender.DirectionalLight(color=np.ones(3), intensity=3.0), pose=pose)
            images.append(shared.render(scene)[0])
        programs = shared._renderer._renderer._program_cache  # pyrender's, as Offscreen installed it
        assert len(programs._program_cache) == len(programs._by_source) == 1
    assert all(image.max() > 0 for image in images)


def test_triangle_ids_round_trip():
    colours = triangle_ids.triangle_id_colours(70_000)
    image = colours.reshape(1, -1, 3)
    np.testing.assert_array_equal(triangle_ids.decode_triangle_ids(image)[0], np.arange(70_000))
    assert triangle_ids.decode_triangle_ids(np.zeros((1, 1, 3), np.uint8))[0, 0] == -1


def test_uv_map_decodes_to_the_texel_on_a_facing_quad():
    """A quad facing the camera with UVs linear in position: every covered texel's decoded UV is the exact
    UV at its centre to within one 16-bit step, coverage is exactly the texels whose centres it holds, and
    depth comes back as the orthographic eye distance."""
    positions = np.array([[-0.5, -0.5, 0.0], [0.5, -0.5, 0.0], [0.5, 0.5, 0.0], [-0.5, 0.5, 0.0]])
    # glTF: v grows downwards. A quarter-texel offset (of a 1024² texture) keeps the texel centres of the
    # image off the texture's texel boundaries, so "the same texel" is well defined.
    offset = 0.25 / 1024
    uvs = np.array([[0.0, 1.0], [1.0, 1.0], [1.0, 0.0], [0.0, 0.0]]) * (1 - 2 * offset) + offset
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    normals = np.tile([0.0, 0.0, 1.0], (4, 1))
    texture = sphere_texture(1024)
    view = impostor_views.ortho_view((0, 0, 0), 1.0, 0.0, 0.0, 64)
    with TriangleIdRenderer(64) as renderer:
        renderer.set_mesh(positions, faces)
        image = renderer.render(view)
        coverage = exact.resolve_coverage(view, image.ids, positions, faces, image.depth)
    result = maps.view_maps(view, coverage, positions, normals, uvs, faces, np.zeros(2, int), [texture])
    uv, material, covered = map_codecs.decode_uv_map(result.uv)
    expected = np.zeros((64, 64), bool)
    expected[16:48, 16:48] = True  # the quad spans [-0.5, 0.5] of [-1, 1]: texels 16..47
    np.testing.assert_array_equal(covered, expected)
    assert coverage.repaired == 0
    centres = (np.arange(64) + 0.5) / 64.0 * 2.0 - 1.0  # texel centre positions in metres
    exact_u = np.broadcast_to((centres[None, :] + 0.5) * (1 - 2 * offset) + offset, (64, 64))
    exact_v = np.broadcast_to((0.5 - (-centres[:, None])) * (1 - 2 * offset) + offset, (64, 64))
    assert np.abs(uv[..., 0] - exact_u)[expected].max() <= UV_STEP
    assert np.abs(uv[..., 1] - exact_v)[expected].max() <= UV_STEP
    # To the texel of a 1024² texture: the stored coordinates address the same texel as the exact ones.
    np.testing.assert_array_equal(np.floor(uv[expected] * 1024), np.floor(np.stack([exact_u, exact_v], -1)[expected] * 1024))
    assert (material == 0).all() and (result.uv[~expected] == 0).all()
    np.testing.assert_allclose(image.depth[expected], impostor_views.CAMERA_DISTANCE_RADII, atol=1e-4)
    assert (image.depth[~expected] == 0).all()
    np.testing.assert_array_equal(result.normal[expected][:, :3], np.tile([128, 128, 255], (expected.sum(), 1)))
    # Packed as uv32 (what a default bundle stores): the same coverage and material, and coordinates
    # within half a 14-bit step of the exact ones, 1/32 texel of a 1024² texture.
    words = map_codecs.uv_map_to_uv32(result.uv)
    assert words.shape == (64, 64) and words.dtype == np.uint32 and (words[~expected] == 0).all()
    uv32, material32, covered32 = map_codecs.decode_uv_map(words)
    np.testing.assert_array_equal(covered32, expected)
    assert (material32 == 0).all()
    assert np.abs(uv32[..., 0] - exact_u)[expected].max() <= UV32_STEP / 2 + UV_STEP
    assert np.abs(uv32[..., 1] - exact_v)[expected].max() <= UV32_STEP / 2 + UV_STEP


def test_detail_map_matches_pyrenders_textured_render():
    from skimage.metrics import structural_similarity

    positions, normals, uvs, faces = uv_sphere()
    texture = sphere_texture()
    view, result = render_maps(positions, normals, uvs, faces, texture, 30.0, 20.0, size=96)
    material = pyrender.MetallicRoughnessMaterial(
        baseColorFactor=[1.0, 1.0, 1.0, 1.0], baseColorTexture=pyrender.Texture(source=texture[..., :3].copy(), source_channels="RGB"), doubleSided=True
    )
    # pyrender flips a texture on upload (it expects trimesh's OBJ-style v-up coordinates): give it 1 - v.
    obj_uvs = np.stack([uvs[:, 0], 1.0 - uvs[:, 1]], axis=-1).astype(np.float32)
    primitive = pyrender.Primitive(
        positions=positions.astype(np.float32), texcoord_0=obj_uvs, indices=faces.astype(np.uint32), material=material, mode=4
    )
    scene = pyrender.Scene(bg_color=[0.0, 0.0, 0.0, 0.0], ambient_light=[0.0, 0.0, 0.0])
    scene.add(pyrender.Mesh([primitive]))
    near, far = triangle_ids.clip_range(view)
    scene.add(pyrender.OrthographicCamera(xmag=1.0, ymag=1.0, znear=near, zfar=far), pose=triangle_ids.camera_pose(view))
    renderer = pyrender.OffscreenRenderer(96, 96)
    try:
        colour, _ = renderer.render(scene, flags=pyrender.RenderFlags.FLAT)
    finally:
        renderer.delete()
    covered = result.coverage.mask
    drawn = colour.max(axis=-1) > 0
    assert (covered != drawn).sum() <= 0.01 * covered.sum(), "both rasterise the same silhouette"
    ours = np.where(covered[..., None], result.detail[..., :3], 0)
    score = structural_similarity(ours, colour, channel_axis=2, data_range=255)
    assert score >= PYRENDER_DETAIL_SSIM


def test_silhouette_texels_carry_their_own_triangles_coordinates():
    """The paper's filtering artefact (section 5): a silhouette texel blended with the background gets a
    texture coordinate from nowhere. Here every covered texel's UV lies inside its triangle's UV range,
    the background is all zero, and the region codes in the detail map are whole codes."""
    positions, normals, uvs, faces = uv_sphere()
    view, result = render_maps(positions, normals, uvs, faces, sphere_texture(), 75.0, 10.0)
    uv, _, covered = map_codecs.decode_uv_map(result.uv)
    triangles = result.coverage.triangle[covered]
    corner_uvs = uvs[faces[triangles]]
    low, high = corner_uvs.min(axis=1) - UV_STEP, corner_uvs.max(axis=1) + UV_STEP
    assert ((uv[covered] >= low) & (uv[covered] <= high)).all()
    assert (result.uv[~covered] == 0).all() and (result.detail[~covered][:, 3] == 0).all()
    assert (result.detail[covered][:, 3] % 17 == 0).all()
    edge = covered & ~np.pad(covered, 1)[2:, 1:-1] | covered & ~np.pad(covered, 1)[:-2, 1:-1]
    assert edge.sum() > 20  # the test did look at silhouette texels


def test_multisample_blends_on_the_silhouette_are_repaired():
    """Under EGL pyrender resolves a 4x multisampled buffer, which can average two ids into a third.
    Corrupting the silhouette's ids that way must leave the same coverage after the repair."""
    positions, normals, uvs, faces = uv_sphere()
    view = impostor_views.ortho_view((0, 0, 0), 1.0, 10.0, 5.0, 64)
    with TriangleIdRenderer(64) as renderer:
        renderer.set_mesh(positions, faces)
        image = renderer.render(view)
    clean = exact.resolve_coverage(view, image.ids, positions, faces, image.depth)
    inside = image.ids >= 0
    border = inside & ~(np.roll(inside, 1, 0) & np.roll(inside, -1, 0) & np.roll(inside, 1, 1) & np.roll(inside, -1, 1))
    blended = image.ids.copy()
    blended[border] = (image.ids[border] + 1) // 2 + 7  # an averaged colour decodes to an unrelated id
    repaired = exact.resolve_coverage(view, blended, positions, faces, image.depth)
    assert repaired.repaired >= border.sum() * 0.9
    np.testing.assert_array_equal(repaired.mask, clean.mask)
    # Where a centre sits on an edge either triangle is right; the surface point must be the same.
    texel_metres = 2.0 * view.radius / view.size
    moved = np.linalg.norm(exact.interpolate(positions, faces, repaired) - exact.interpolate(positions, faces, clean), axis=-1)
    assert moved.max() <= 0.1 * texel_metres


def test_inside_of_an_open_shape_is_lit_from_the_camera_side():
    positions, normals, uvs, faces = uv_sphere()
    open_top = faces[positions[faces].mean(axis=1)[:, 1] < 0.3]  # cut the cap off: the inside shows from above
    view, result = render_maps(positions, normals, uvs, open_top, sphere_texture(), 0.0, 70.0)
    decoded = map_codecs.decode_normal_map(result.normal)[result.coverage.mask]
    inside = (result.coverage.triangle[result.coverage.mask] >= 0)
    assert inside.all()
    # Normals point towards the camera side even where the camera sees the back of a triangle.
    assert (decoded @ view.back > -0.05).all()


def test_texture_sampling_conventions():
    texture = np.zeros((2, 2, 4), dtype=np.uint8)
    texture[0, 0] = (255, 0, 0, 17)
    texture[0, 1] = (0, 255, 0, 34)
    texture[1, 0] = (0, 0, 255, 51)
    texture[1, 1] = (255, 255, 255, 68)
    # glTF (0, 0) is the top-left texel's corner; texel centres sit at (0.25, 0.25) etc. for 2x2.
    samples = impostor_views.sample_texture(texture, np.array([[0.25, 0.25], [0.75, 0.25], [0.25, 0.75], [0.5, 0.5], [1.25, 0.25]]))
    np.testing.assert_allclose(samples[0], [255, 0, 0, 17])
    np.testing.assert_allclose(samples[1], [0, 255, 0, 34])
    np.testing.assert_allclose(samples[2], [0, 0, 255, 51])
    np.testing.assert_allclose(samples[3, :3], [127.5, 127.5, 127.5])  # bilinear RGB
    assert samples[3, 3] in (17, 34, 51, 68)  # nearest alpha: a region code, never a blend
    np.testing.assert_allclose(samples[4], samples[0])  # REPEAT
    np.testing.assert_allclose(exact.wrap_uv(np.array([1.0, -0.25, 1.5])), [1.0, 0.75, 0.5])


def test_all_views_at_once_equal_view_by_view():
    """resolve_coverage_views / view_maps_views run one numpy pass over the texels of every view; each
    view's maps must be exactly what the one-view functions give, whatever the other views hold: views
    of different azimuths and elevations, one of them with corrupted (repaired) ids, one empty."""
    positions, normals, uvs, faces = uv_sphere()
    material = np.zeros(len(faces), int)
    views = [impostor_views.ortho_view((0, 0, 0), 1.0, azimuth, elevation, 32) for azimuth, elevation in ((0, 0), (70, 20), (200, -40))]
    with TriangleIdRenderer(32) as renderer, offscreen.timed_renders() as gl:
        renderer.set_mesh(positions, faces)
        images = [renderer.render(view) for view in views]
    assert gl.renders == len(views) and gl.seconds > 0, "every render goes through the timing hook"
    ids = np.stack([image.ids for image in images])
    depth = np.stack([image.depth for image in images])
    ids[1][ids[1] >= 0] += 5  # wrong ids in view 1: every covered texel there needs repairing
    ids[2] = -1  # nothing drawn in view 2
    depth[2] = 0.0
    together = exact.resolve_coverage_views(views, ids, positions, faces, depth)
    assert together[1].repaired > 0 and not together[2].mask.any()
    together_maps = maps.view_maps_views(views, together, positions, normals, uvs, faces, material, [sphere_texture()])
    for k, view in enumerate(views):
        alone = exact.resolve_coverage(view, ids[k], positions, faces, depth[k])
        np.testing.assert_array_equal(together[k].triangle, alone.triangle)
        np.testing.assert_array_equal(together[k].barycentric, alone.barycentric)
        assert together[k].repaired == alone.repaired
        alone_maps = maps.view_maps(view, alone, positions, normals, uvs, faces, material, [sphere_texture()])
        for kind in ("normal", "uv", "detail"):
            np.testing.assert_array_equal(getattr(together_maps[k], kind), getattr(alone_maps, kind))


def test_row_reductions_are_bitwise_numpys():
    """The maps' column arithmetic must give numpy's own row sums, norms and minima to the bit (the bake's
    bytes depend on it), for rows of 2 and 3 values of very different magnitudes."""
    rng = np.random.default_rng(7)
    for width in (2, 3):
        values = rng.standard_normal((5000, width)) * 10.0 ** rng.uniform(-6, 6, (5000, width))
        assert np.array_equal(short_rows.row_sum(values), values.sum(axis=1))
        assert np.array_equal(short_rows.row_norm(values), np.linalg.norm(values, axis=1))
        assert np.array_equal(short_rows.row_min(values), values.min(axis=1))
    u, v = rng.standard_normal((2, 5000, 3))
    assert np.array_equal(impostor_views.face_normals(np.concatenate([np.zeros((5000, 3)), u, v]), np.arange(15000).reshape(3, 5000).T), np.cross(u, v))
