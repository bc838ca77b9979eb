"""Export size with BC1/BC2 blocks kept (`--ktx2 bc`, the default) against decoded RGBA8 (`--ktx2 rgba8`).

Bakes the procedural sample with the docs' small parameters (docs/export.md), exports it both ways and
prints the bytes of the whole export and of its colour/normal KTX2 files (diffuse, outfits, impostor
maps; the VATs are 16-bit and the same in both modes).

    PYTHONPATH=services PYOPENGL_PLATFORM=osmesa python services/benchmarks/bench_export_sizes.py
"""
from __future__ import annotations

import contextlib
import io
import json
import tempfile
from pathlib import Path

from crowdbake.cli import main as cli


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp, contextlib.redirect_stdout(io.StringIO()):  # only the JSON below
        work = Path(tmp)
        assert cli(["sample", str(work / "sample"), "--cycles", "3", "--cycle-frames", "24", "--texture-size", "64"]) == 0
        sample = work / "sample"
        assert cli(["bake", str(sample / "character.glb"), "--cloth", str(sample / "cloth.pc2"), "--cloth-mesh", str(sample / "cloth.obj"),
                    "--textures", str(sample / "textures"), "--name", "sample", "--version", "1.0", "--out", str(work / "bundles"),
                    "--frames", "2", "--azimuths", "4", "--elevations", "0,30", "--tile", "32", "--lod-triangles", "1200", "--no-export"]) == 0
        result = {}
        for mode in ("bc", "rgba8"):
            out = work / mode
            assert cli(["export", str(work / "bundles" / "sample" / "1.0"), "--out", str(out), "--ktx2", mode]) == 0
            files = {p.relative_to(out).as_posix(): p.stat().st_size for p in out.rglob("*") if p.is_file()}
            textures = {k: v for k, v in files.items() if k.endswith(".ktx2") and not k.startswith("vat/")}
            result[mode] = {"export_bytes": sum(files.values()), "texture_ktx2_bytes": sum(textures.values()), "texture_ktx2": textures}
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
