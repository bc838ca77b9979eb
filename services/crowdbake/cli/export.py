"""`crowdbake export BUNDLE_DIR --out DIR`: a bundle as glTF 2.0 + KTX2 + vertex-animation textures.

See docs/export.md for the files and how engines and three.js use them.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from crowdbake.cli.common import CommandError
from crowdbake.formats.errors import FormatError

# Dem Bones holds a (frames x vertices x bones) problem and iterates over it: these bounds keep one garment's
# fit to minutes and a few GB. auto tops out at 128 (cloth_bones.AUTO_BONE_COUNTS), which already fits a
# long skirt's loop to about a centimetre; more bones or iterations than this buy nothing measurable.
MAX_CLOTH_BONES = 256
MAX_CLOTH_BONE_ITERATIONS = 100


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "export",
        help="export a bundle for engines and the web: glTF 2.0 (.glb), KTX2 textures, vertex-animation textures, shaders",
        description=(
            "Verify a bundle and write engine-ready files: one glTF 2.0 binary per LOD (body and garments with "
            "their UVs and materials, the cloth cycle as morph targets and an animation, and as vertex-animation "
            "textures named in the mesh extras), the impostor atlases and diffuse variations as KTX2, a JSON "
            "sidecar (export.json) with the view layout, frames, switch distance and region codes, and reference "
            "GLSL/HLSL shaders. OUT must be new or empty."
        ),
    )
    parser.add_argument("bundle_dir", metavar="BUNDLE_DIR", type=Path, help="a bundle folder (manifest.json and its files)")
    parser.add_argument("--out", required=True, type=Path, metavar="DIR", help="folder to write (new or empty)")
    parser.add_argument(
        "--ktx2", choices=("bc", "rgba8"), default="bc",
        help="bc (default): colour and normal maps keep the bundle's BC1/BC2 blocks, copied as they are; "
        "rgba8: decoded to RGBA8 texels, for targets without BC (S3TC) support",
    )
    parser.add_argument(
        "--vat-png", action="store_true",
        help="also write each vertex-animation texture as a PNG (16-bit positions, 8-bit normals) beside its KTX2, "
        "for engines that import PNG but not KTX2 (Unity, Unreal)",
    )
    parser.add_argument(
        "--cloth-bones", metavar="N|auto",
        help="play each garment as a skinned mesh of N extra bones (linear blend skinning fitted to the loop by Dem Bones) "
        f"instead of morph targets; N at most {MAX_CLOTH_BONES}; auto: the fewest of 4, 8, ... 128 bones within "
        "--cloth-bones-budget",
    )
    parser.add_argument("--cloth-bones-budget", type=float, default=5.0, metavar="MM",
                        help="RMS error in millimetres that --cloth-bones auto aims for (default 5)")
    parser.add_argument("--cloth-bones-iterations", type=int, default=30, metavar="K", help=f"Dem Bones iterations (default 30, at most {MAX_CLOTH_BONE_ITERATIONS})")
    parser.add_argument("--surface-map", action="store_true",
                        help="also write the impostor surface map (per texel depth and motion, for reprojecting between views "
                        "and frames as crowdview's warp blend does; the shipped shaders do not read it)")
    parser.add_argument("--json", action="store_true", help="print the written files and sizes as JSON")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from crowdbake.export.writer import export_bundle

    if not args.bundle_dir.is_dir():
        raise CommandError(f"{args.bundle_dir} is not a folder")
    cloth_bones = None
    if args.cloth_bones is not None:
        from crowdbake.export.writer import ClothBonesRequest

        count = None if args.cloth_bones == "auto" else (int(args.cloth_bones) if args.cloth_bones.isdigit() else 0)
        if count == 0 or (count is not None and count > MAX_CLOTH_BONES):
            raise CommandError(f"--cloth-bones: expected a bone count from 1 to {MAX_CLOTH_BONES} or auto, got {args.cloth_bones!r}")
        if not 0 < args.cloth_bones_budget < float("inf") or not 1 <= args.cloth_bones_iterations <= MAX_CLOTH_BONE_ITERATIONS:
            raise CommandError(f"--cloth-bones-budget must be positive millimetres and --cloth-bones-iterations from 1 "
                               f"to {MAX_CLOTH_BONE_ITERATIONS}")
        try:
            import py_dem_bones  # noqa: F401
        except ImportError:
            raise CommandError("--cloth-bones needs py-dem-bones (pip install py-dem-bones; services/requirements.txt pins it)") from None
        cloth_bones = ClothBonesRequest(count, args.cloth_bones_budget, args.cloth_bones_iterations, report=print_bones_line)
    try:
        summary = export_bundle(args.bundle_dir, args.out, args.ktx2, vat_png=args.vat_png, cloth_bones=cloth_bones,
                                surface_map=args.surface_map)
    except FormatError as error:
        raise CommandError(f"the bundle does not verify: {error}") from None
    except FileExistsError as error:
        raise CommandError(str(error)) from None
    except MemoryError:
        raise CommandError("the export ran out of memory; with --cloth-bones, try fewer bones or iterations", exit_code=1) from None
    if args.json:
        print(json.dumps({"out": str(summary.out_dir), "files": summary.files}, indent=2))
    else:
        for path, size in summary.files.items():
            print(f"file     {path}: {size:,} bytes")
        print(f"exported {len(summary.files)} files to {summary.out_dir}")
    return 0


def print_bones_line(line: str) -> None:
    """A garment's bone count and error, as the fit ends: a garment's fit can take minutes."""
    print(f"crowdbake export: {line}", file=sys.stderr, flush=True)
