"""crowdview's impostor shader drawn in the bake's context (crowdbake.render.runtime_shader), the pictures
fidelity.json's `runtime` section scores, against the numpy copy of that shader
(crowdbake.reference.runtime_picture) on a small bake's own bundle, under OSMesa."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from crowdbake.bake import fidelity, map_codecs
from crowdbake.bake import view_blend
from crowdbake.reference import impostor_blend
from crowdbake.reference.runtime_picture import AtlasTiles, numpy_picture
from crowdbake.formats.binary import TextureArray
from crowdbake.formats.bundle import verify_bundle
from crowdbake.render import runtime_shader
from crowdbake.render.runtime_shader import RuntimePicture, samples_needed, shader_source

pytest.importorskip("pyrender")
from crowdbake.render import offscreen  # noqa: E402
from crowdbake.render.impostor import BakeRenderer  # noqa: E402
from crowdbake.stages.impostors import load_poses  # noqa: E402
from crowdbake.stages.runtime_fidelity import halfway_frame, picture_at, runtime_atlas, runtime_textures  # noqa: E402

@pytest.fixture(scope="module")
def bundle(small_bake):
    """(poses, the bundle's maps as TextureArrays, the poses stage's textures) of the session's small bake."""
    folder, work = small_bake
    baked = verify_bundle(folder)
    maps = {kind: baked.textures[path] for kind, path in baked.manifest["impostor"]["maps"].items()}
    return load_poses(work), maps, runtime_textures(work)


def pictures_of(poses) -> list[RuntimePicture]:
    """Cameras at baked views and frames, halfway between azimuths, between rings and between frames."""
    layout = poses.atlas_layout()
    layer = list(poses.frame_indices).index(poses.fidelity_frame)
    baked = view_blend.FrameWeights((layer, layer), 0.0)
    _, between = halfway_frame(poses)
    cameras = [(a, e, baked) for a in layout.azimuths_deg for e in layout.elevations_deg]
    cameras += [(22.5, 0.0, baked), (157.5, 30.0, baked), (225.0, 15.0, baked), (292.5, 15.0, between), (0.0, 30.0, between)]
    return [picture_at(layout, a, e, frames) for a, e, frames in cameras]


def draw(atlas, pictures):
    with BakeRenderer(atlas.tile_size) as renderer, offscreen.timed_renders() as gl:
        drawn = renderer.runtime_impostors(atlas, pictures)
    assert gl.renders == 1 and gl.seconds > 0, "the pictures are one render"
    return drawn


def test_the_shader_is_crowdviews_files_pasted_as_its_loader_does(tmp_path):
    source = shader_source("impostor_uv.frag.glsl", {"CV_WARP": 1, "CV_VIEW_SAMPLES": 4}, {"CV_AMBIENT": "0.3"})
    lines = source.splitlines()
    assert lines[0] == "#version 330 core" and lines[1:3] == ["#define CV_WARP 1", "#define CV_VIEW_SAMPLES 4"]
    assert not [line for line in lines if line.lstrip().startswith("#include")], "every include is pasted in"
    for included in ("impostor_warp.glsl", "impostor_uv_map.glsl"):
        assert (runtime_shader.SHADER_DIR / included).read_text().strip() in source
    assert "#define CV_AMBIENT 0.3" in lines and "#define CV_AMBIENT 0.35" not in source
    (tmp_path / "a.glsl").write_text('#version 330 core\n  #include "b.h"\nvoid main() {}\n')
    (tmp_path / "b.h").write_text("#define CV_OTHER 1\n")
    assert shader_source("a.glsl", {}, {}, tmp_path) == "#version 330 core\n#define CV_OTHER 1\n\nvoid main() {}\n"
    with pytest.raises(RuntimeError, match="no #define CV_AMBIENT"):
        shader_source("a.glsl", {}, {"CV_AMBIENT": "0.3"}, tmp_path)


def test_each_picture_gets_the_smallest_program_that_draws_it_whole():
    def picture(weights, frame_weight):
        return RuntimePicture(0.0, 0.0, (0, 1, 2, 3), weights, (0, 1), frame_weight)

    assert samples_needed(picture((1.0, 0.0, 0.0, 0.0), 0.0)) == (1, 1)
    assert samples_needed(picture((0.5, 0.5, 0.0, 0.0), 0.0)) == (4, 1)
    assert samples_needed(picture((1.0, 0.0, 0.0, 0.0), 0.25)) == (1, 2)
    assert samples_needed(picture((0.0, 1.0, 0.0, 0.0), 0.0)) == (4, 1), "only the first tile's weight alone allows one sample"


def compare_with_numpy(layout, atlas, pictures, drawn) -> tuple[float, float, float]:
    """(worst share of pixels whose coverage differs, worst SSIM, mean absolute difference over both
    coverages) of the shader's pictures against numpy's."""
    layout_tiles = AtlasTiles(layout, atlas.uv_map, atlas.normal_map, atlas.surface_map, atlas.radius)
    chains = [impostor_blend.mip_chain(texture) for texture in atlas.diffuse]
    worst_coverage, worst_ssim, differences = 0.0, 1.0, []
    for picture, image in zip(pictures, drawn):
        reference = numpy_picture(atlas, layout_tiles, picture, chains)
        covered, expected = image.max(axis=-1) > 0, reference.max(axis=-1) > 0
        worst_coverage = max(worst_coverage, float((covered != expected).mean()))
        worst_ssim = min(worst_ssim, fidelity.compare(reference, image.astype(np.float64))["ssim"])
        differences.append(np.abs(image - reference)[covered & expected].mean())
    return worst_coverage, worst_ssim, float(np.mean(differences))


@pytest.mark.parametrize("uv_format", ["uvblock", "uv32"])
@pytest.mark.parametrize("reprojected", [True, False], ids=["warp", "plain"])
def test_the_shaders_pictures_are_the_numpy_copys(bundle, uv_format, reprojected):
    poses, maps, textures = bundle
    uv_map = maps["uv"]
    assert uv_map.pixel_format == "uvblock" and maps["normal"].pixel_format == "bc5" and "surface" in maps
    if uv_format == "uv32":
        uv_map = TextureArray(uv_map.width, uv_map.height, "uv32", tuple(
            map_codecs.uvblock_to_uv32(layer, uv_map.width, uv_map.height).astype("<u4").tobytes() for layer in uv_map.layers))
    atlas = runtime_atlas(poses, poses.atlas_layout(), uv_map, maps["normal"], maps["surface"] if reprojected else None, textures)
    pictures = pictures_of(poses)
    drawn = draw(atlas, pictures)
    assert drawn.shape == (len(pictures), 64, 64, 3) and drawn.dtype == np.float32
    assert all((image.max(axis=-1) > 0).mean() > 0.05 for image in drawn), "every picture shows the character"
    coverage, ssim, difference = compare_with_numpy(poses.atlas_layout(), atlas, pictures, drawn)
    print(f"\n{uv_format}, reprojected {reprojected}: coverage differs in at most {coverage:.4f}, SSIM >= {ssim:.4f}, "
          f"mean difference {difference:.4f}")
    # Unreprojected, the two differ only by the sampler's 8-bit filter weights on llvmpipe (numpy's are
    # float64). Reprojected, a fixed-point iteration reads the surface map five times with those weights
    # and rounds to a texel: 45° from a baked view some texels land on a neighbour (at the sample's 32
    # azimuths of 128², the bake's own pictures agree to SSIM >= 0.995; docs/bake.md).
    assert coverage < 0.005
    assert (ssim > 0.97 and difference < 0.005) if reprojected else (ssim > 0.999 and difference < 0.002)


def test_the_smaller_programs_draw_the_default_programs_pictures(bundle, monkeypatch):
    """A sample of weight 0 adds nothing: the pictures of the programs samples_needed picks are those of
    crowdview's default program (four views, two frames), bit for bit."""
    poses, maps, textures = bundle
    atlas = runtime_atlas(poses, poses.atlas_layout(), maps["uv"], maps["normal"], maps["surface"], textures)
    pictures = pictures_of(poses)
    assert {samples_needed(picture) for picture in pictures} >= {(1, 1), (4, 1), (4, 2)}
    chosen = draw(atlas, pictures)
    monkeypatch.setattr(runtime_shader, "samples_needed", lambda picture: (4, 2))
    assert np.array_equal(draw(atlas, pictures), chosen)


def test_outfits_and_materials_without_regions_as_crowdview(bundle):
    """Region codes pick the outfit row's colour; a bc1 material (no regions) is drawn untinted."""
    poses, maps, textures = bundle
    atlas = runtime_atlas(poses, poses.atlas_layout(), maps["uv"], maps["normal"], maps["surface"], textures)
    pictures = pictures_of(poses)[:2]
    red = np.zeros((16, 4), dtype=np.uint8)
    red[:, 0] = red[:, 3] = 255
    tinted = draw(replace(atlas, outfit_row=red), pictures)
    plain = draw(replace(atlas, outfit_row=red, has_regions=[False] * len(atlas.diffuse)), pictures)
    covered = tinted.max(axis=-1) > 0
    assert np.array_equal(covered, plain.max(axis=-1) > 0)
    assert (tinted[covered][:, 1:] < 1e-6).mean() > 0.2, "tinted regions keep only red"
    assert (plain[covered][:, 1:] > 0.02).mean() > 0.5, "untinted, the texture's own colours show"
