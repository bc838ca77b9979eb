#!/usr/bin/env python3
"""How much of a bundle's impostor maps the character covers, and what tighter rectangles would hold it.

    PYTHONPATH=services python services/benchmarks/bench_impostor_occupancy.py LABEL=BUNDLE [LABEL=BUNDLE ...]
        [--out out/bench/impostor_occupancy.json]

Every stored cell of the atlas (one view of one baked frame) is today the bundle's one crop (SPEC.md
"Impostor maps"): the rectangle that holds the character in every view and frame. From the UV map's
coverage (rgba16, uv32 or uvblock), per bundle, each as a share of the stored texels:

- covered: the texels the character covers;
- cell_boxes: each cell's own bounding rectangle, on 4-texel blocks (what per-cell rectangles would store);
- cell_boxes_margin: the same, each grown by a block on every side (below);
- view_boxes: per view, the rectangle holding it in every baked frame (what per-view rectangles would store);
- view_boxes_margin: the same, each grown by a block on every side (the margin the crop keeps, so that a
  bilinear read at a cell's edge never reaches the next cell);
- union_box: the one rectangle holding every view and frame, as the crop is meant to (without its margin).

So cell_boxes and view_boxes are the memory a packed atlas would need for the same texels, before packing
waste and margins: the headroom for more frames or views within one budget. Prints a line per bundle and
writes JSON.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

BLOCK = 4  # block compression's 4 x 4 texels: a stored rectangle starts and ends on blocks


def block_box_area(mask: np.ndarray, margin: int = 0) -> int:
    """Texels of the smallest rectangle on BLOCK-texel boundaries holding every True of `mask` (H, W), grown
    by `margin` blocks on every side within the mask's bounds; 0 if none."""
    rows, columns = np.nonzero(mask)
    if rows.size == 0:
        return 0
    grow = margin * BLOCK
    top, left = max(0, rows.min() // BLOCK * BLOCK - grow), max(0, columns.min() // BLOCK * BLOCK - grow)
    bottom = min(mask.shape[0], -(-(rows.max() + 1) // BLOCK) * BLOCK + grow)
    right = min(mask.shape[1], -(-(columns.max() + 1) // BLOCK) * BLOCK + grow)
    return int((bottom - top) * (right - left))


def occupancy(coverage: np.ndarray) -> dict[str, float]:
    """coverage (F, V, H, W) bool: per baked frame and view, the cell's covered texels. Returns the shares
    of the F·V·H·W stored texels (module docstring): covered, cell_boxes, view_boxes, union_box, and
    cell_boxes_margin and view_boxes_margin: each cell's or view's rectangle grown by a block on every side
    within the cell, the margin of dilated background the crop keeps (bilinear reads at a cell's edge must
    not reach the next cell)."""
    frames, views, height, width = coverage.shape
    stored = float(frames * views * height * width)
    cells = sum(block_box_area(coverage[f, v]) for f in range(frames) for v in range(views))
    cells_margin = sum(block_box_area(coverage[f, v], 1) for f in range(frames) for v in range(views))
    per_view = sum(block_box_area(coverage[:, v].any(axis=0)) for v in range(views)) * frames
    per_view_margin = sum(block_box_area(coverage[:, v].any(axis=0), 1) for v in range(views)) * frames
    union = block_box_area(coverage.any(axis=(0, 1))) * frames * views
    return {"covered": float(coverage.sum() / stored), "cell_boxes": cells / stored, "cell_boxes_margin": cells_margin / stored,
            "view_boxes": per_view / stored,
            "view_boxes_margin": per_view_margin / stored, "union_box": union / stored}


def bundle_coverage(bundle: Path) -> tuple[np.ndarray, dict]:
    """(F, V, H, W) bool coverage of a bundle's impostor UV map, cells as crowdbake.bake.atlas lays them out
    (azimuths along x, rings along y), and the manifest's impostor entry."""
    from crowdbake.api.routes.web import decode_uv_layer
    from crowdbake.formats.binary import decode_texture_array

    impostor = json.loads((bundle / "manifest.json").read_text())["impostor"]
    maps = decode_texture_array((bundle / impostor["maps"]["uv"]).read_bytes(), f"{bundle} uv map")
    crop = impostor.get("crop") or {"width": impostor["tile_size"], "height": impostor["tile_size"]}
    width, height = int(crop["width"]), int(crop["height"])
    azimuths, rings = len(impostor["azimuths_deg"]), len(impostor["elevations_deg"])
    layers = []
    for layer in maps.layers:
        covered = decode_uv_layer(layer, maps.pixel_format, maps.width, maps.height)[..., 3] > 0
        cells = covered[:rings * height, :azimuths * width].reshape(rings, height, azimuths, width).transpose(0, 2, 1, 3)
        layers.append(cells.reshape(rings * azimuths, height, width))
    return np.stack(layers), impostor


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("bundles", nargs="+", metavar="LABEL=BUNDLE")
    parser.add_argument("--out", type=Path, default=Path("out/bench/impostor_occupancy.json"))
    args = parser.parse_args()
    results = {}
    for entry in args.bundles:
        label, _, path = entry.partition("=")
        if not path:
            print(f"bench_impostor_occupancy: {entry!r} is not LABEL=BUNDLE", file=sys.stderr)
            return 2
        coverage, impostor = bundle_coverage(Path(path))
        shares = occupancy(coverage)
        frames, views, height, width = coverage.shape
        results[label] = {"bundle": path, "frames": frames, "views": views, "cell": [width, height], "tile": impostor["tile_size"], **shares}
        print(f"{label}: {frames} frames x {views} views of {width}x{height} texels; covered {shares['covered']:.1%}, "
              f"per-cell rectangles {shares['cell_boxes']:.1%} ({shares['cell_boxes_margin']:.1%} with a block of margin), per-view rectangles {shares['view_boxes']:.1%} "
              f"({shares['view_boxes_margin']:.1%} with a block of margin), "
              f"one rectangle {shares['union_box']:.1%} of the stored texels")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=2) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
