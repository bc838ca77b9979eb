"""The engines' import scripts (services/crowdbake/export/engines, copied into every export's engines/) read
what the export writes and set up everything export.json lists for a part's VAT material.

No engine runs here, so each script is checked as far as its language's tools go on this machine:

* all three: every shader input export.json carries (a part's `vat` and `node` blocks, an animation's
  `vat` range) is read by each script, so a new one cannot be forgotten (keys that are not shader inputs
  are listed below with the reason);
* Godot: the GDScript parses and lints with gdtoolkit, and sets every uniform of crowdbake_vat.gdshader;
* Unity: the C# compiles with Mono's mcs against stubs of the UnityEngine / UnityEditor members it uses
  (tests/engine_stubs/UnityStubs.cs), and sets a property for every input of the Custom Function;
* Unreal: the Python runs against a fake `unreal` module that records every call: the glb and the VAT PNGs
  are imported (a file LODs share once), every 16-bit VAT gets TC_HDR_F32, and each material instance gets
  every parameter with export.json's value.
"""
from __future__ import annotations

import importlib.util
import json
import re
import shutil
import subprocess
import sys
import types
from pathlib import Path

import pytest

from crowdbake.export.writer import export_bundle

EXPORT_SHADERS = Path(__file__).resolve().parents[1] / "crowdbake" / "export" / "shaders"
UNITY_STUBS = Path(__file__).resolve().parent / "engine_stubs" / "UnityStubs.cs"
GODOT = "engines/crowdbake_godot_import.gd"
UNITY = "engines/CrowdbakeUnityImport.cs"
UNREAL = "engines/crowdbake_unreal_import.py"

# Keys of a part's `vat` and `node` blocks that no shader takes, with the reason; every other key is a
# shader input each script must read.
NOT_SHADER_INPUTS = {
    "encoding": "words for a reader",
    "texel_of_vertex": "words for a reader",
    "meaning": "words for a reader",
    "max_position_error_m": "an accuracy figure",
    "width": "the texture's own size, which the shaders read from it",
    "height": "the texture's own size, which the shaders read from it",
    "frame_count": "the texture's rows over rows_per_frame; animations[].vat says which frames play",
    "vertex_count": "the mesh's",
    "texcoord": "always 1: each shader reads its engine's second UV set",
    "texels_of_lod": "which LOD's files these are: the files and layout the block names are the ones read",
    "joint_count": "the joint texture's own rows, which the shaders index by the joints the skin texture names",
    "texel_of_row": "words for a reader",
}
# How each script reads a key of export.json: GDScript and Python index a parsed dictionary, the C# reads
# the field of the class JsonUtility fills.
KEY_READ = {GODOT: r'\["{key}"\]', UNITY: r"\.{key}\b", UNREAL: r'\["{key}"\]'}


@pytest.fixture(scope="module")
def vat_png_export(small_bake, tmp_path_factory) -> Path:
    """The small sample's export with the VAT PNGs Unity and Unreal import (--vat-png)."""
    bundle, _ = small_bake
    out = tmp_path_factory.mktemp("engine_import") / "sample"
    export_bundle(bundle, out, vat_png=True)
    return out


@pytest.fixture(scope="module")
def sidecar(vat_png_export) -> dict:
    return json.loads((vat_png_export / "export.json").read_text())


def shader_input_keys(sidecar: dict) -> set[str]:
    """The keys of export.json a VAT material is set from, over every part (a skin's `joints` block too) and
    animation."""
    keys = set()
    for lod in sidecar["lods"]:
        for part in lod["parts"]:
            keys |= set(part["vat"]) | set(part.get("node", {})) | (set(part["vat"]["joints"]) - {"ktx2", "png"} if "joints" in part["vat"] else set())
    for animation in sidecar["animations"]:
        keys |= set(animation["vat"])
    return keys - set(NOT_SHADER_INPUTS)


def test_the_export_ships_every_engine_script(sidecar, vat_png_export):
    assert sorted(sidecar["engines"]) == sorted([GODOT, UNITY, UNREAL])
    for path in sidecar["engines"]:
        assert (vat_png_export / path).read_bytes() == (Path(__file__).resolve().parents[1] / "crowdbake" / "export" / path).read_bytes()


@pytest.mark.parametrize("script", [GODOT, UNITY, UNREAL])
def test_each_script_reads_every_shader_input_of_export_json(sidecar, vat_png_export, script):
    keys = shader_input_keys(sidecar)
    # The sample's export has the inputs the shaders take today; a new key shows up here and must be read.
    assert {"kind", "texture", "joints", "bounds_min", "bounds_max", "rows_per_frame", "min", "max", "frames_per_second", "translation", "scale",
            "first_frame", "frames", "loop", "before_frame", "after_frame"} <= keys
    source = (vat_png_export / script).read_text()
    unread = sorted(key for key in keys if not re.search(KEY_READ[script].format(key=key), source))
    assert not unread, f"{script} does not read {unread} from export.json"


def test_the_key_check_can_fail(sidecar, vat_png_export):
    """A script that forgets a key is caught: the Godot script without its bounds_max line."""
    source = "\n".join(line for line in (vat_png_export / GODOT).read_text().splitlines() if '["bounds_max"]' not in line)
    assert not re.search(KEY_READ[GODOT].format(key="bounds_max"), source)


# ----------------------------------------------------------------------------- Godot


def test_godot_script_parses_and_lints(vat_png_export):
    """gdtoolkit's parser takes Godot 4 GDScript; its linter checks names and style (our lines run to 150)."""
    parser = pytest.importorskip("gdtoolkit.parser").parser
    linter = pytest.importorskip("gdtoolkit.linter")
    source = (vat_png_export / GODOT).read_text()
    parser.parse(source)
    problems = linter.lint_code(source, {**linter.DEFAULT_CONFIG, "max-line-length": 150})
    assert not problems, [f"{p.line}: {p.description}" for p in problems]
    from lark.exceptions import UnexpectedInput  # gdtoolkit's parser is lark's

    with pytest.raises(UnexpectedInput):
        parser.parse(source.replace("func vector3(values: Array) -> Vector3:", "func vector3(values: Array) -> Vector3"))


def test_godot_script_sets_every_uniform_of_the_shader(vat_png_export):
    shader = (vat_png_export / "shaders" / "crowdbake_vat.gdshader").read_text()
    uniforms = set(re.findall(r"^uniform \w+ (\w+)", shader, re.M))
    script = (vat_png_export / GODOT).read_text()
    set_by_script = set(re.findall(r'set_shader_parameter\("(\w+)"', script))
    # phase offsets one instance's clock: game code sets it per character (-TIME starts a transition now).
    assert set_by_script == uniforms - {"phase"}


# ----------------------------------------------------------------------------- Unity


def compile_unity(tmp_path: Path, script: Path) -> subprocess.CompletedProcess:
    mcs = shutil.which("mcs")
    if mcs is None:
        pytest.skip("Mono's C# compiler is not installed (apt-get install mono-mcs; scripts/setup.sh does)")
    return subprocess.run([mcs, "-define:UNITY_EDITOR", "-target:library", "-warnaserror", f"-out:{tmp_path / 'unity.dll'}", str(UNITY_STUBS),
                           str(script)], capture_output=True, text=True, timeout=120)


def test_unity_script_compiles_against_unity_stubs(tmp_path, vat_png_export):
    result = compile_unity(tmp_path, vat_png_export / UNITY)
    assert result.returncode == 0, result.stdout + result.stderr
    broken = tmp_path / "Broken.cs"  # the check can fail: a call the stubs (and Unity) do not have
    broken.write_text((vat_png_export / UNITY).read_text().replace("material.SetFloat(NodeScale,", "material.SetScalar(NodeScale,"))
    assert compile_unity(tmp_path, broken).returncode != 0


def test_unity_script_sets_every_custom_function_input(vat_png_export):
    hlsl = (EXPORT_SHADERS / "unity_vat_custom_function.hlsl").read_text()
    signature = re.search(r"void CrowdbakeVat_float\(([^)]*)\)", hlsl).group(1)
    inputs = set(re.findall(r"(?<!out )(?:float\d?|UnityTexture2D) (\w+)", signature))
    script = (vat_png_export / UNITY).read_text()
    properties = dict(re.findall(r'(\w+) = "_(\w+)"', script))
    # VatUV is the mesh's UV1; Frame is Time * FramesPerSecond in the graph; BaseMap feeds the fragment stage.
    assert set(properties.values()) == inputs - {"VatUV", "Frame"} | {"FramesPerSecond", "BaseMap"}
    for constant in properties:
        assert re.search(rf"material\.Set\w+\({constant},", script), constant


# ----------------------------------------------------------------------------- Unreal


class FakeAsset:
    def __init__(self, path: str):
        self.path = path
        self.properties: dict[str, object] = {}
        self.parent = None
        self.parameters: dict[str, object] = {}
        self.saved = 0

    def set_editor_property(self, name: str, value) -> None:
        self.properties[name] = value

    def get_editor_property(self, name: str):
        return self.properties[name]


def fake_unreal(has_hdr_f32: bool = True) -> types.ModuleType:
    """A stand-in for Unreal's `unreal` module: the calls the script makes, recorded. Imported assets are
    named by file (a folder's `x.png` becomes `<folder>/x`); enum values are their names."""
    unreal = types.ModuleType("unreal")
    assets: dict[str, FakeAsset] = {}
    unreal.assets, unreal.imported, unreal.logged = assets, [], []

    def asset(path: str) -> FakeAsset:
        return assets.setdefault(path, FakeAsset(path))

    class AssetImportTask(FakeAsset):
        def __init__(self):
            super().__init__("")

    class AssetTools:
        @staticmethod
        def import_asset_tasks(tasks):
            for task in tasks:
                name = Path(task.properties["filename"]).stem.replace(".", "_")  # Unreal's object names have no dots
                path = f"{task.properties['destination_path']}/{name}"
                asset(path)
                task.properties["imported_object_paths"] = [path]
                unreal.imported.append(dict(task.properties))

        @staticmethod
        def create_asset(name, package_path, asset_class, factory):
            assert asset_class is unreal.MaterialInstanceConstant and isinstance(factory, unreal.MaterialInstanceConstantFactoryNew)
            path = f"{package_path}/{name}"
            assert path not in assets, f"{path} exists: Unreal asks before replacing it"
            return asset(path)

    class MaterialEditingLibrary:
        @staticmethod
        def set_material_instance_parent(instance, parent):
            instance.parent = parent

        @staticmethod
        def set_material_instance_scalar_parameter_value(instance, name, value):
            assert isinstance(value, float)
            instance.parameters[name] = value

        @staticmethod
        def set_material_instance_vector_parameter_value(instance, name, value):
            assert isinstance(value, unreal.LinearColor)
            instance.parameters[name] = value

        @staticmethod
        def set_material_instance_texture_parameter_value(instance, name, value):
            assert isinstance(value, FakeAsset)
            instance.parameters[name] = value

    class EditorAssetLibrary:
        @staticmethod
        def save_loaded_asset(saved):
            saved.saved += 1

        @staticmethod
        def does_asset_exist(path):
            return path in assets

    class LinearColor(tuple):
        def __new__(cls, r, g, b, a):
            return super().__new__(cls, (r, g, b, a))

    compression = ["TC_DEFAULT", "TC_HDR", "TC_HALF_FLOAT", "TC_GRAYSCALE", "TC_VECTOR_DISPLACEMENTMAP"] + (["TC_HDR_F32"] if has_hdr_f32 else [])
    unreal.TextureCompressionSettings = types.SimpleNamespace(**{name: name for name in compression})
    unreal.TextureFilter = types.SimpleNamespace(TF_NEAREST="TF_NEAREST", TF_DEFAULT="TF_DEFAULT")
    unreal.TextureMipGenSettings = types.SimpleNamespace(TMGS_NO_MIPMAPS="TMGS_NO_MIPMAPS")
    unreal.AssetImportTask = AssetImportTask
    unreal.AssetToolsHelpers = types.SimpleNamespace(get_asset_tools=AssetTools)
    unreal.MaterialEditingLibrary = MaterialEditingLibrary
    unreal.EditorAssetLibrary = EditorAssetLibrary
    unreal.MaterialInstanceConstant = type("MaterialInstanceConstant", (), {})
    unreal.MaterialInstanceConstantFactoryNew = type("MaterialInstanceConstantFactoryNew", (), {})
    unreal.LinearColor = LinearColor
    unreal.load_asset = lambda path: asset(path)
    unreal.log = unreal.logged.append
    return unreal


def run_unreal_script(export_dir: Path, unreal: types.ModuleType, monkeypatch) -> None:
    """Run the export's copy of the Unreal script on `export_dir` with `unreal` as its `unreal` module."""
    monkeypatch.setitem(sys.modules, "unreal", unreal)
    spec = importlib.util.spec_from_file_location("crowdbake_unreal_import", export_dir / UNREAL)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    module.main(str(export_dir))


def test_unreal_script_compiles(vat_png_export):
    import py_compile

    py_compile.compile(str(vat_png_export / UNREAL), doraise=True, cfile=str(vat_png_export.parent / "unreal.pyc"))


def test_unreal_script_imports_16_bit_positions_at_full_precision(vat_png_export, sidecar, monkeypatch):
    unreal = fake_unreal()
    run_unreal_script(vat_png_export, unreal, monkeypatch)
    imported = {Path(task["filename"]).relative_to(vat_png_export).as_posix(): task for task in unreal.imported}
    parts = [(lod, part) for lod in sidecar["lods"] for part in lod["parts"]]
    vats = {part["vat"][k]["png"] for _, part in parts for k in ("texture", "joints") if k in part["vat"]}
    assert any("joints" in part["vat"] for _, part in parts)  # a skinned body's joint matrices, and vertex frames
    assert {lod["glb"] for lod in sidecar["lods"]} | vats == set(imported)
    assert len(unreal.imported) == len(imported), "a file LODs share is imported once"
    assert all(task["automated"] and task["replace_existing"] for task in unreal.imported)
    for png in vats:
        texture = unreal.assets[imported[png]["imported_object_paths"][0]]
        assert texture.properties == {"compression_settings": "TC_HDR_F32", "srgb": False, "filter": "TF_NEAREST",
                                      "mip_gen_settings": "TMGS_NO_MIPMAPS", "never_stream": True}, (png, texture.properties)
        assert texture.saved


def test_unreal_material_instances_carry_every_value_of_export_json(vat_png_export, sidecar, monkeypatch):
    unreal = fake_unreal()
    run_unreal_script(vat_png_export, unreal, monkeypatch)
    played = sidecar["animations"][0]["vat"]
    instances = {path.rsplit("/", 1)[1]: a for path, a in unreal.assets.items() if "/materials/MI_" in path}
    parts = [(lod["lod"], part) for lod in sidecar["lods"] for part in lod["parts"]]
    assert set(instances) == {f"MI_{part['part']}_lod{lod}" for lod, part in parts}
    hlsl = (EXPORT_SHADERS / "unreal_vat_custom_node.hlsl").read_text()
    listed = re.search(r"Inputs: (.*?); Additional Output", hlsl, re.S).group(1).replace("\n// ", " ")
    node_inputs = {name.strip() for name in re.sub(r"\s*\([^)]*\)", "", listed).split(",")}
    for lod, part in parts:
        instance = instances[f"MI_{part['part']}_lod{lod}"]
        vat, node = part["vat"], part["node"]
        assert instance.parent is unreal.assets["/Game/Crowdbake/M_CrowdbakeVat"] and instance.saved
        # VatUV is the mesh's TexCoord[1], Frame is Time * FramesPerSecond, LocalPosition the Local Position node;
        # vertex frames need no joint matrices.
        skinned = vat["kind"] == "skin"
        joint_inputs = {"JointMap", "JointRowsPerFrame", "JointMin", "JointMax"}
        assert set(instance.parameters) == node_inputs - {"VatUV", "Frame", "LocalPosition"} - (set() if skinned else joint_inputs) | {"FramesPerSecond"}
        values = instance.parameters
        assert values["Skinned"] == (1.0 if skinned else 0.0)
        if skinned:
            joints = vat["joints"]
            assert values["JointRowsPerFrame"] == joints["rows_per_frame"]
            assert values["JointMin"] == pytest.approx(joints["min"]) and values["JointMax"] == pytest.approx(joints["max"])
            assert values["JointMap"].path.endswith(Path(joints["png"]).stem.replace(".", "_"))
        assert values["BoundsMin"][:3] == pytest.approx(vat["bounds_min"]) and values["BoundsMax"][:3] == pytest.approx(vat["bounds_max"])
        assert values["RowsPerFrame"] == vat["rows_per_frame"] and values["FramesPerSecond"] == vat["frames_per_second"]
        assert values["NodeTranslation"][:3] == pytest.approx(node["translation"]) and values["NodeScale"] == pytest.approx(node["scale"])
        assert values["Range"] == (played["first_frame"], played["frames"], played["loop"], played["before_frame"])
        assert values["RangeAfter"] == played["after_frame"]
        assert values["VatMap"].path.endswith(Path(vat["texture"]["png"]).stem.replace(".", "_"))
        assert values["VatMap"].properties["compression_settings"] == "TC_HDR_F32"


def test_a_second_unreal_run_updates_the_same_assets(vat_png_export, monkeypatch):
    unreal = fake_unreal()
    run_unreal_script(vat_png_export, unreal, monkeypatch)
    first = dict(unreal.assets)
    run_unreal_script(vat_png_export, unreal, monkeypatch)
    assert unreal.assets == first
    assert all(asset.saved == 2 for path, asset in first.items() if "/materials/MI_" in path)


def test_unreal_script_refuses_an_unreal_without_32_bit_float_textures(vat_png_export, monkeypatch):
    """UE 5.0 has no TC_HDR_F32; falling back to TC_HDR would round the positions to float16, so the
    script stops naming the setting instead."""
    with pytest.raises(RuntimeError, match="TC_HDR_F32"):
        run_unreal_script(vat_png_export, fake_unreal(has_hdr_f32=False), monkeypatch)


def test_unreal_script_needs_the_vat_pngs(small_bake, tmp_path, monkeypatch):
    out = tmp_path / "no_png"
    export_bundle(small_bake[0], out)
    with pytest.raises(ValueError, match="--vat-png"):
        run_unreal_script(out, fake_unreal(), monkeypatch)
