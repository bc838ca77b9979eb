"""Seconds and decoded error of the block encoder on a bake's own textures, per quicktex level.

    PYTHONPATH=services python services/benchmarks/bench_compression.py --work WORK [--levels 5,8,12]
        [--out out/bench/compression.json]

WORK is a bake's work folder (`crowdbake bake ... --work WORK`): its diffuse layers (poses/textures.npz)
and its impostor tiles (impostor/parts/*.npz), assembled into one atlas per baked frame as the pack
stage does. Every layer is encoded as the bundle stores it (diffuse and detail maps BC2, normal maps BC1)
and decoded again; the error is the mean absolute 8-bit difference over the texels that matter (covered
ones for the impostor maps, all of them for the diffuse textures), the figure the bake reports.

Without --levels the encoder runs as the module configures it, so pointing PYTHONPATH at another
checkout measures that checkout's encoder on the same inputs (how docs/bake.md compares encoders).
"""
from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

from crowdbake.bake import compression
from crowdbake.bake.atlas import AtlasLayout, assemble


def load_layers(work: Path) -> dict[str, list[tuple[np.ndarray, np.ndarray | None]]]:
    """{"diffuse" | "normal" | "detail": [(rgba (H, W, 4) uint8, mask (H, W) bool or None)]} of a work folder."""
    summary = json.loads((work / "poses" / "poses.json").read_text())
    layout_doc = summary["layout"]
    layout = AtlasLayout(layout_doc["tile_size"], tuple(layout_doc["azimuths_deg"]), tuple(layout_doc["elevations_deg"]))
    layers: dict[str, list] = {"diffuse": [], "normal": [], "detail": []}
    with np.load(work / "poses" / "textures.npz") as textures:
        for name in sorted(n for n in textures.files if n.startswith("material_") and n.count("_") == 1):
            layers["diffuse"].extend((layer, None) for layer in textures[name])
    tiles: dict[int, dict[str, dict]] = {}
    for part in sorted((work / "impostor" / "parts").glob("*.npz")):
        frame = int(part.stem.split("-")[0][1:])
        with np.load(part) as data:
            for kind in ("normal", "uv", "detail"):
                tiles.setdefault(frame, {}).setdefault(kind, {}).update(
                    {(a, e): tile for (a, e), tile in zip(data["views"].tolist(), data[kind])}
                )
    for frame in sorted(tiles):
        covered = assemble(layout, tiles[frame]["uv"])[..., 3] > 0
        for kind in ("normal", "detail"):
            layers[kind].append((assemble(layout, tiles[frame][kind]), covered))
    return layers


def measure(layers: dict[str, list], repeat: int) -> dict[str, dict]:
    """Per kind: encoder seconds (best of `repeat`, summed over layers), texels, mean |error| and worst PSNR."""
    formats = {"diffuse": "bc2", "normal": "bc1", "detail": "bc2"}
    out = {}
    for kind, items in layers.items():
        if not items:
            continue
        seconds, errors, texels = 0.0, [], 0
        for rgba, mask in items:
            best = float("inf")
            for _ in range(repeat):
                started = time.process_time()
                data = compression.encode(rgba, formats[kind])
                best = min(best, time.process_time() - started)
            seconds += best
            texels += rgba.shape[0] * rgba.shape[1]
            height, width = rgba.shape[:2]
            errors.append(compression.compression_error(rgba, compression.decode(data, formats[kind], width, height), mask))
        out[kind] = {
            "format": formats[kind],
            "layers": len(items),
            "megatexels": texels / 1e6,
            "cpu_seconds": seconds,
            "megatexels_per_cpu_second": texels / 1e6 / seconds,
            "rgb_mean_abs": float(np.mean([e["rgb_mean_abs"] for e in errors])),
            "rgb_psnr_db_worst": min(e["rgb_psnr_db"] for e in errors),
            "rgb_max": max(e["rgb_max"] for e in errors),
        }
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--work", type=Path, required=True, help="a bake's work folder (crowdbake bake --work)")
    parser.add_argument("--levels", help="quicktex levels to compare, e.g. 5,8,12 (default: the module's own)")
    parser.add_argument("--repeat", type=int, default=1, help="encodes per layer; the fastest counts (default 1)")
    parser.add_argument("--out", type=Path, default=Path("out/bench/compression.json"))
    args = parser.parse_args()

    layers = load_layers(args.work)
    levels = [int(v) for v in args.levels.split(",")] if args.levels else [getattr(compression, "BC1_LEVEL", None)]
    report = {"module": compression.__file__, "cpus": os.cpu_count(), "results": []}
    for level in levels:
        if level is not None:
            compression.BC1_LEVEL = level
            compression._bc1_encoder.cache_clear()
        result = measure(layers, args.repeat)
        report["results"].append({"level": level, "kinds": result})
        for kind, figures in result.items():
            print(
                f"level {level}: {kind:8s} {figures['format']} {figures['megatexels']:6.1f} Mtexels "
                f"{figures['cpu_seconds']:6.2f} s CPU ({figures['megatexels_per_cpu_second']:5.1f} Mtexels/s) "
                f"mean |error| {figures['rgb_mean_abs']:.3f}, worst PSNR {figures['rgb_psnr_db_worst']:.2f} dB"
            )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
