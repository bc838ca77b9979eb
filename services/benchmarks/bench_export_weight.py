"""What each file and each part of an export costs: bytes unpacked and inside the published export.zip.

Exports each bundle the way publishing does (crowdbake.storage.exports.build_export: export/, export.zip,
index.json) and prints, then writes as JSON, per file its bytes and its compressed bytes in the zip,
largest first; the same summed per part of the export (each LOD's .glb, each mesh part's VATs, each
impostor map, the looks, the diffuse textures, the rest); and inside each .glb, per mesh part and for the
animations, the bytes of its buffer views and what they deflate to alone (zlib at the zip's level), an
estimate of its share of the .glb's zipped bytes.

    PYTHONPATH=services python services/benchmarks/bench_export_weight.py [LABEL=]BUNDLE ... [--out weight.json]

BUNDLE: a bundle folder, e.g. the demo's (`scripts/demo.sh`): sample=out/demo/bundles/sample-walker/1.0.0
(the procedural sample, default bake) and robot=out/demo/bundles/robot/1.0.0 (the shared robot with its
cape through Idle, Walking and Running).
"""
from __future__ import annotations

import argparse
import json
import re
import struct
import tempfile
import time
import zipfile
import zlib
from collections import defaultdict
from pathlib import Path

from crowdbake.storage.exports import FILES_FOLDER, ZIP_NAME, build_export, zip_level


def part_of(path: str) -> str:
    """The part of the export a file belongs to: `glb lod<k>`, `vat <part>` (all LODs and textures of a mesh
    part), `impostor <map>`, `looks`, `textures`, or `other` (export.json, shaders, engine scripts)."""
    if match := re.fullmatch(r"character_lod(\d+)\.glb", path):
        return f"glb lod{match.group(1)}"
    if match := re.fullmatch(r"vat/(.+?)(?:_lod\d+)?\.\w+\.(?:ktx2|png)", path):
        return f"vat {match.group(1)}"
    if match := re.fullmatch(r"impostor/(\w+)\.ktx2", path):
        return f"impostor {match.group(1)}"
    folder = path.split("/", 1)[0]
    return folder if folder in ("looks", "textures") else "other"


def glb_parts(data: bytes, level: int = zip_level(".glb")) -> dict[str, dict[str, int]]:
    """{owner: {"bytes", "deflated"}} of a .glb's buffer views: each mesh's (by name: its attributes, indices and
    morph targets), `animations`, `skins`, `images` and `json`; deflated: the owner's views deflated alone."""
    json_length = struct.unpack_from("<I", data, 12)[0]
    gltf = json.loads(data[20:20 + json_length])
    binary = 20 + json_length + 8
    owner_of: dict[int, str] = {}

    def own(accessor: int | None, owner: str) -> None:
        if accessor is not None and gltf["accessors"][accessor].get("bufferView") is not None:
            owner_of.setdefault(gltf["accessors"][accessor]["bufferView"], owner)

    for mesh in gltf.get("meshes", []):
        for primitive in mesh["primitives"]:
            for accessor in list(primitive["attributes"].values()) + [primitive.get("indices")]:
                own(accessor, mesh["name"])
            for target in primitive.get("targets", []):
                for accessor in target.values():
                    own(accessor, mesh["name"])
    for animation in gltf.get("animations", []):
        for sampler in animation["samplers"]:
            own(sampler["input"], "animations")
            own(sampler["output"], "animations")
    for skin in gltf.get("skins", []):
        own(skin.get("inverseBindMatrices"), "skins")
    for image in gltf.get("images", []):
        if "bufferView" in image:
            owner_of.setdefault(image["bufferView"], "images")
    chunks: dict[str, list[bytes]] = defaultdict(list)
    for index, view in enumerate(gltf.get("bufferViews", [])):
        start = binary + view.get("byteOffset", 0)
        chunks[owner_of.get(index, "other")].append(data[start:start + view["byteLength"]])
    chunks["json"].append(data[20:20 + json_length])
    out = {}
    for owner, pieces in chunks.items():
        joined = b"".join(pieces)
        out[owner] = {"bytes": len(joined), "deflated": len(zlib.compress(joined, level))}
    return dict(sorted(out.items(), key=lambda item: -item[1]["deflated"]))


def export_weight(bundle: Path) -> dict:
    """{"files": [{path, part, bytes, zipped}], "parts": [{part, bytes, zipped}], "glb": {file: glb_parts},
    "total_bytes", "zip_bytes", "seconds"} of the bundle's export."""
    with tempfile.TemporaryDirectory() as tmp:
        staging = Path(tmp)
        start = time.perf_counter()
        build_export(bundle, staging)
        seconds = time.perf_counter() - start
        with zipfile.ZipFile(staging / ZIP_NAME) as archive:
            zipped = {info.filename.split("/", 1)[1]: info.compress_size for info in archive.infolist()}
        files = [{"path": path, "part": part_of(path), "bytes": (staging / FILES_FOLDER / path).stat().st_size, "zipped": zipped[path]}
                 for path in zipped]
        files.sort(key=lambda row: -row["zipped"])
        parts: dict[str, dict[str, int]] = defaultdict(lambda: {"bytes": 0, "zipped": 0})
        for row in files:
            parts[row["part"]]["bytes"] += row["bytes"]
            parts[row["part"]]["zipped"] += row["zipped"]
        glb = {row["path"]: glb_parts((staging / FILES_FOLDER / row["path"]).read_bytes()) for row in files if row["path"].endswith(".glb")}
        return {"bundle": str(bundle), "files": files,
                "parts": [{"part": name, **sizes} for name, sizes in sorted(parts.items(), key=lambda item: -item[1]["zipped"])],
                "glb": glb, "total_bytes": sum(r["bytes"] for r in files), "zip_bytes": (staging / ZIP_NAME).stat().st_size,
                "seconds": round(seconds, 2)}


def print_weight(label: str, result: dict) -> None:
    print(f"== {label}: {result['bundle']}")
    print(f"{'file':48s} {'bytes':>12s} {'in zip':>12s}")
    for row in result["files"]:
        print(f"{row['path']:48s} {row['bytes']:12,d} {row['zipped']:12,d}")
    print(f"{'part':48s} {'bytes':>12s} {'in zip':>12s}")
    for row in result["parts"]:
        print(f"{row['part']:48s} {row['bytes']:12,d} {row['zipped']:12,d}")
    for path, owners in result["glb"].items():
        print(f"{path + ' by owner':48s} {'bytes':>12s} {'deflated':>12s}")
        for owner, sizes in owners.items():
            print(f"  {owner:46s} {sizes['bytes']:12,d} {sizes['deflated']:12,d}")
    print(f"{'total':48s} {result['total_bytes']:12,d} {result['zip_bytes']:12,d}  (export.zip; {result['seconds']} s)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("bundles", nargs="+", help="[LABEL=]BUNDLE folder")
    parser.add_argument("--out", type=Path, default=Path("out/bench/export_weight.json"))
    args = parser.parse_args()
    results = {}
    for spec in args.bundles:
        label, _, folder = spec.rpartition("=")
        label = label or Path(folder).parent.name
        results[label] = export_weight(Path(folder))
        print_weight(label, results[label])
    print(f"{'zip bytes':24s}" + "".join(f" {label:>14s}" for label in results))
    print(f"{'':24s}" + "".join(f" {result['zip_bytes']:14,d}" for result in results.values()))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=2) + "\n")


if __name__ == "__main__":
    main()
