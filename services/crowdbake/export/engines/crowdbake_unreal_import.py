"""crowdbake export -> Unreal Engine 5 assets that play the cloth from vertex-animation textures (VATs).

Export with --vat-png. Once per project, make the material PARENT_MATERIAL: a material function's Custom
node with the code of shaders/unreal_vat_custom_node.hlsl, its inputs fed by parameters named as the
*_PARAMETER constants below, Frame = Time * FramesPerSecond. Then run this file in the editor (Tools >
Execute Python Script, or `py crowdbake_unreal_import.py [EXPORT_DIR] [ANIMATION]` in the Output Log's
Python console). It imports every LOD's .glb and the VAT PNGs under /Game/Crowdbake/<name>/<version>/,
gives the PNGs the settings below, and makes one material instance per part with every parameter set
from export.json. Assign each instance to its part's mesh; the .glb's own materials show its looks.

EXPORT_DIR defaults to the folder above this file's, where the export puts it.
"""
from __future__ import annotations

import json
import os
import sys

import unreal

PARENT_MATERIAL = "/Game/Crowdbake/M_CrowdbakeVat"
DESTINATION_ROOT = "/Game/Crowdbake"

VAT_MAP_PARAMETER = "VatMap"
JOINT_MAP_PARAMETER = "JointMap"
BOUNDS_MIN_PARAMETER = "BoundsMin"
BOUNDS_MAX_PARAMETER = "BoundsMax"
ROWS_PER_FRAME_PARAMETER = "RowsPerFrame"
SKINNED_PARAMETER = "Skinned"  # 1 for a skinned body (vat.kind "skin"), whose joint matrices the Joint* parameters describe
JOINT_ROWS_PER_FRAME_PARAMETER = "JointRowsPerFrame"
JOINT_MIN_PARAMETER = "JointMin"
JOINT_MAX_PARAMETER = "JointMax"
FRAMES_PER_SECOND_PARAMETER = "FramesPerSecond"
RANGE_PARAMETER = "Range"  # first_frame, frames, loop, before_frame: the Custom node's Range input
RANGE_AFTER_PARAMETER = "RangeAfter"
NODE_TRANSLATION_PARAMETER = "NodeTranslation"
NODE_SCALE_PARAMETER = "NodeScale"

# The compression of the 16-bit VATs. None of Unreal's TextureCompressionSettings (the Python API's
# list, UE 5.0 to 5.7) keeps 16-bit unsigned RGBA: TC_HDR stores RGBA16F ("HDR" is RGBA16F in Unreal's
# ETextureImportFloatingPointFormat), whose 11-bit significand rounds q / 65535 to steps of 1/2048 between
# 0.5 and 1 (0.9 mm on a 1.8 m character); TC_VectorDisplacementmap stores 8 bits a channel; TC_Grayscale,
# TC_Displacementmap and TC_HalfFloat keep one channel. TC_HDR_F32 (UE 5.1 on) stores 32-bit floats, whose
# 24-bit significand holds every q / 65535 exactly: the one setting that keeps the PNG's precision, at
# 16 bytes a texel. The octahedral normal words and joint indices need every bit too.
VAT_COMPRESSION = "TC_HDR_F32"


def read_sidecar(export_dir: str) -> dict:
    path = os.path.join(export_dir, "export.json")
    with open(path, encoding="utf-8") as handle:
        sidecar = json.load(handle)
    if sidecar.get("format") != "crowdbake-export":
        raise ValueError(f"{path} is not a crowdbake export.json")
    return sidecar


def pick_animation(animations: list[dict], name: str | None) -> dict:
    """The animations[] entry named `name`, or the first (a clip) when None."""
    for animation in animations:
        if name is None or animation["name"] == name:
            return animation
    raise ValueError(f"export.json has no animation named {name!r}")


def compression(name: str):
    setting = getattr(unreal.TextureCompressionSettings, name, None)
    if setting is None:  # TC_HDR_F32 came with UE 5.1; an older TC_HDR would round the positions
        raise RuntimeError(f"this Unreal has no TextureCompressionSettings.{name}: crowdbake's VATs need UE 5.1 or later")
    return setting


def import_files(files: list[str], destination: str) -> list[list[str]]:
    """Import each file into the `destination` folder: per file, the paths of the assets made."""
    tasks = []
    for filename in files:
        task = unreal.AssetImportTask()
        task.set_editor_property("filename", filename)
        task.set_editor_property("destination_path", destination)
        task.set_editor_property("automated", True)
        task.set_editor_property("replace_existing", True)
        task.set_editor_property("save", True)
        tasks.append(task)
    unreal.AssetToolsHelpers.get_asset_tools().import_asset_tasks(tasks)
    imported = [list(task.get_editor_property("imported_object_paths")) for task in tasks]
    for filename, paths in zip(files, imported):
        if not paths:
            raise RuntimeError(f"Unreal imported nothing from {filename}")
    return imported


def configure_vat(texture, compression_name: str) -> None:
    """A VAT as data: its own bits (compression_name), linear, point sampled, no mips, always resident
    (the shader reads single texels, which streaming would replace by a smaller mip)."""
    texture.set_editor_property("compression_settings", compression(compression_name))
    texture.set_editor_property("srgb", False)
    texture.set_editor_property("filter", unreal.TextureFilter.TF_NEAREST)
    texture.set_editor_property("mip_gen_settings", unreal.TextureMipGenSettings.TMGS_NO_MIPMAPS)
    texture.set_editor_property("never_stream", True)
    unreal.EditorAssetLibrary.save_loaded_asset(texture)


def import_vats(export_dir: str, vat: dict, destination: str, done: dict[str, object]) -> dict[str, object]:
    """The textures of a part's `vat` block by material parameter (its VAT; a skin's joint matrices too),
    imported and configured; `done` (PNG path -> texture) keeps those imported already, as LODs share files."""
    files = {VAT_MAP_PARAMETER: vat["texture"]} | ({JOINT_MAP_PARAMETER: vat["joints"]} if vat["kind"] == "skin" else {})
    if any("png" not in file for file in files.values()):
        raise ValueError("the export has no VAT PNGs (Unreal does not import KTX2): export it with --vat-png")
    new = sorted({file["png"] for file in files.values()} - set(done))
    for png, (path, *_) in zip(new, import_files([os.path.join(export_dir, png) for png in new], destination) if new else []):
        done[png] = unreal.load_asset(path)
        configure_vat(done[png], VAT_COMPRESSION)
    return {parameter: done[file["png"]] for parameter, file in files.items()}


def vector(values: list[float], w: float = 0.0):
    return unreal.LinearColor(float(values[0]), float(values[1]), float(values[2]), w)


def material_parameters(part: dict, played: dict) -> tuple[dict[str, float], dict[str, object]]:
    """(scalar parameters, vector parameters) of a part's material: its VAT layout (lods[].parts[].vat),
    its quantized mesh's node (lods[].parts[].node) and the range of pose frames played (animations[].vat).
    Values stay in glTF's axes and metres: the Custom node turns its result into Unreal's."""
    vat, node = part["vat"], part["node"]
    scalars = {
        ROWS_PER_FRAME_PARAMETER: float(vat["rows_per_frame"]),
        SKINNED_PARAMETER: 1.0 if vat["kind"] == "skin" else 0.0,
        FRAMES_PER_SECOND_PARAMETER: float(vat["frames_per_second"]),
        RANGE_AFTER_PARAMETER: float(played["after_frame"]),
        NODE_SCALE_PARAMETER: float(node["scale"]),
    }
    vectors = {
        BOUNDS_MIN_PARAMETER: vector(vat["bounds_min"]),
        BOUNDS_MAX_PARAMETER: vector(vat["bounds_max"]),
        RANGE_PARAMETER: unreal.LinearColor(float(played["first_frame"]), float(played["frames"]), float(played["loop"]), float(played["before_frame"])),
        NODE_TRANSLATION_PARAMETER: vector(node["translation"]),
    }
    if vat["kind"] == "skin":
        joints = vat["joints"]
        scalars[JOINT_ROWS_PER_FRAME_PARAMETER] = float(joints["rows_per_frame"])
        vectors[JOINT_MIN_PARAMETER] = unreal.LinearColor(*(float(v) for v in joints["min"]))
        vectors[JOINT_MAX_PARAMETER] = unreal.LinearColor(*(float(v) for v in joints["max"]))
    return scalars, vectors


def make_material_instance(name: str, destination: str, parent, part: dict, played: dict, textures: dict[str, object]):
    path = f"{destination}/{name}"
    if unreal.EditorAssetLibrary.does_asset_exist(path):  # a second run updates the instance in place
        instance = unreal.load_asset(path)
    else:
        asset_tools = unreal.AssetToolsHelpers.get_asset_tools()
        instance = asset_tools.create_asset(name, destination, unreal.MaterialInstanceConstant, unreal.MaterialInstanceConstantFactoryNew())
    library = unreal.MaterialEditingLibrary
    library.set_material_instance_parent(instance, parent)
    scalars, vectors = material_parameters(part, played)
    for parameter, value in scalars.items():
        library.set_material_instance_scalar_parameter_value(instance, parameter, value)
    for parameter, value in vectors.items():
        library.set_material_instance_vector_parameter_value(instance, parameter, value)
    for parameter, texture in textures.items():
        library.set_material_instance_texture_parameter_value(instance, parameter, texture)
    unreal.EditorAssetLibrary.save_loaded_asset(instance)
    return instance


def main(export_dir: str, animation_name: str | None = None) -> None:
    sidecar = read_sidecar(export_dir)
    played = pick_animation(sidecar["animations"], animation_name)["vat"]
    parent = unreal.load_asset(PARENT_MATERIAL)
    if parent is None:
        raise RuntimeError(f"no material at {PARENT_MATERIAL}: make it first (this file's docstring)")
    bundle = sidecar["bundle"]
    destination = f"{DESTINATION_ROOT}/{bundle['name']}/{bundle['version']}".replace(".", "_")
    vats: dict[str, object] = {}
    for lod in sidecar["lods"]:
        import_files([os.path.join(export_dir, lod["glb"])], f"{destination}/lod{lod['lod']}")
        for part in lod["parts"]:
            if "node" not in part:  # exported with --cloth-bones: a skinned mesh that plays its own bones
                continue
            name = f"{part['part']}_lod{lod['lod']}"
            textures = import_vats(export_dir, part["vat"], f"{destination}/vat", vats)
            make_material_instance(f"MI_{name}", f"{destination}/materials", parent, part, played, textures)
            unreal.log(f"crowdbake: MI_{name} plays {part['part']} (LOD {lod['lod']})")


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
         sys.argv[2] if len(sys.argv) > 2 else None)
