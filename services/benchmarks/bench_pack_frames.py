"""The pack stage's per-frame encoding, alone: every baked frame's stage_pack_frame, and its heaviest
array functions on the fidelity frame's atlases.

    PYTHONPATH=services python services/benchmarks/bench_pack_frames.py --work WORK [--repeat 5]
        [--out out/bench/pack_frames.json]

WORK: the work folder of a finished bake (`crowdbake bake ... --work WORK`). It is copied to a temporary
folder without pack/frames, and each baked frame is packed there one after another in this process
(wall and CPU seconds each; the frames' files are compared with WORK's, which the same code writes
byte for byte). Then, on the fidelity frame's atlases as the pack wrote them (its 16-bit UV atlas, its
uvblock layer, its detail atlas and that layer decoded), the best of --repeat runs of:

- map_codecs.uv_map_to_uvblock (the 16-bit UV atlas to its uvblock layer),
- map_codecs.uvblock_to_uv32 (the uvblock layer to uv32 words, for the export and the scores),
- compression.compression_error over the covered texels and over every texel.

The functions are the ones every version of the bake has, so the same command against an older checkout
(PYTHONPATH pointing at its services/) measures the code before a change.
"""
from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np


def best_of(repeat: int, call) -> float:
    """The shortest wall seconds of `repeat` calls (after one untimed call)."""
    call()
    times = []
    for _ in range(repeat):
        started = time.perf_counter()
        call()
        times.append(time.perf_counter() - started)
    return min(times)


def pack_every_frame(work: Path) -> tuple[list[dict], bool]:
    """Each frame packed afresh in a copy of `work`: [{frame, wall_s, cpu_s}], and whether every frame's
    file equals the one in `work`."""
    from crowdbake.stages.impostors import load_plan
    from crowdbake.stages.pack import frame_path, stage_pack_frame

    frames = list(load_plan(work).frame_indices)
    with tempfile.TemporaryDirectory(prefix="crowdbake-pack-") as scratch:
        copy = Path(scratch) / "work"
        shutil.copytree(work, copy, ignore=shutil.ignore_patterns("frames"))
        rows, same = [], True
        for frame in frames:
            wall, cpu = time.perf_counter(), time.process_time()
            stage_pack_frame(copy, frame)
            rows.append({"frame": frame, "wall_s": time.perf_counter() - wall, "cpu_s": time.process_time() - cpu})
            original = frame_path(work, frame)
            same &= original.is_file() and original.read_bytes() == frame_path(copy, frame).read_bytes()
    return rows, same


def atlas_functions(work: Path, repeat: int) -> dict[str, float]:
    """Best-of-`repeat` seconds of the array functions on the fidelity frame's atlases."""
    from crowdbake.bake import compression, map_codecs
    from crowdbake.stages.impostors import load_plan
    from crowdbake.stages.pack import frame_path

    with np.load(frame_path(work, load_plan(work).fidelity_frame)) as data:
        uv16, uvblock = data["fidelity_uv16"], data["layer_uv"].tobytes()
        detail, detail_layer = data["fidelity_detail"], data["layer_detail"].tobytes()
    height, width = uv16.shape[:2]
    covered = uv16[..., 3] >= 32768
    detail_format = "bc2" if len(detail_layer) == height * width else "bc1"
    decoded = compression.decode(detail_layer, detail_format, width, height)
    return {
        "atlas": f"{width}x{height}, {covered.mean():.3f} covered",
        "uv_map_to_uvblock_s": best_of(repeat, lambda: map_codecs.uv_map_to_uvblock(uv16)),
        "uvblock_to_uv32_s": best_of(repeat, lambda: map_codecs.uvblock_to_uv32(uvblock, width, height)),
        "compression_error_covered_s": best_of(repeat, lambda: compression.compression_error(detail, decoded, covered)),
        "compression_error_all_s": best_of(repeat, lambda: compression.compression_error(detail, decoded)),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--work", type=Path, required=True, help="the work folder of a finished bake")
    parser.add_argument("--repeat", type=int, default=5, help="timed runs of each array function (best kept; default 5)")
    parser.add_argument("--out", type=Path, default=Path("out/bench/pack_frames.json"), help="JSON report")
    args = parser.parse_args()
    if not (args.work / "pack" / "frames").is_dir():
        parser.error(f"{args.work} holds no packed frames (pack/frames): bake with --work first")
    frames, same = pack_every_frame(args.work)
    functions = atlas_functions(args.work, args.repeat)
    for row in frames:
        print(f"frame {row['frame']:4d}: {row['wall_s']:.3f} s wall, {row['cpu_s']:.3f} s CPU")
    print(f"all {len(frames)} frames: {sum(r['wall_s'] for r in frames):.2f} s wall, {sum(r['cpu_s'] for r in frames):.2f} s CPU; "
          f"files {'identical to' if same else 'DIFFERENT from'} the work folder's")
    print(f"fidelity frame's atlas ({functions['atlas']}), best of {args.repeat}:")
    for name, seconds in functions.items():
        if name.endswith("_s"):
            print(f"  {name[:-2]:28s} {seconds * 1000:8.1f} ms")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"work": str(args.work), "frames": frames, "frames_identical": same, "functions": functions}, indent=2) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
