"""The garment-fit measure (crowdbake.bake.garment_fit) on good and bad character + garment pairs.

    PYTHONPATH=services python services/benchmarks/bench_garment_fit.py [SAMPLE_FOLDER ...]

Prints far_fraction (mean share of cloth points farther than FAR_FROM_BODY of the character's height
from its body) per pair: the thresholds in garment_fit.py were chosen from these figures.
"""
from __future__ import annotations

import sys
from pathlib import Path

from crowdbake.bake.garment_fit import FAR_FROM_BODY, MAX_FAR_FRACTION
from crowdbake.formats.gltf import load_character
from crowdbake.errors import InputError
from crowdbake.ingest.garment import check_garment_fit, read_cloth

ASSETS = Path(__file__).resolve().parents[3] / "shared" / "assets"
PAIRS = [("CesiumMan + long_skirt (good)", ASSETS / "CesiumMan.glb", ASSETS / "long_skirt" / "long_skirt", 0),
         ("RiggedFigure + long_skirt (bad)", ASSETS / "RiggedFigure.glb", ASSETS / "long_skirt" / "long_skirt", 0),
         ("robot + cape, Idle (good for its Idle part)", ASSETS / "robot_clips" / "robot.glb", ASSETS / "robot_clips" / "garment", "Idle")]


def main(samples: list[str]) -> None:
    pairs = PAIRS + [(f"sample {s} (good)", Path(s) / "character.glb", Path(s) / "cloth", 0) for s in samples]
    print(f"FAR_FROM_BODY {FAR_FROM_BODY}, MAX_FAR_FRACTION {MAX_FAR_FRACTION}")
    for label, character, cloth, animation in pairs:
        cache = read_cloth(cloth.with_suffix(".pc2"), cloth.with_suffix(".obj"))
        try:
            fit = check_garment_fit(load_character(character, animation=animation), cache, cache.fps or 24.0)
            print(f"{label}: far_fraction {fit.far_fraction:.3f}, worst frame {fit.worst_frame} {fit.worst_far_fraction:.3f}")
        except InputError as refused:
            print(f"{label}: refused: {refused.message}")


if __name__ == "__main__":
    main(sys.argv[1:])
