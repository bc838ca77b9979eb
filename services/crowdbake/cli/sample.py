"""`crowdbake sample OUT_DIR`: generate the procedural clothed walking character.

Writes character.glb, cloth.pc2 + cloth.obj, textures/diffuse_00..07.png, textures/outfits.png,
settling.json and sample.json (see crowdbake.sample.generate). Deterministic for a seed. With --clips,
the garment is simulated once through Idle / Walking / Running and timeline.json is written too.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

from crowdbake.cli.common import CommandError, progress
from crowdbake.sample.clips import DEFAULT_BLEND_FRAMES, DEFAULT_SEQUENCE, clip_periods, parse_sequence, sequence_layout
from crowdbake.sample.garments import GARMENT_NAMES
from crowdbake.sample.generate import DEFAULT_CYCLES, DEFAULT_TEXTURE_SIZE, SETTLED_RMS, generate_sample
from crowdbake.sample.humanoid import BUILD_NAMES
from crowdbake.sample.walk import DEFAULT_CYCLE_FRAMES, MAX_CYCLE_FRAMES, MIN_CYCLE_FRAMES


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "sample",
        help="generate the procedural sample: a skinned walking humanoid and its simulated skirt",
        description=(
            "Generate a clothed walking character entirely by code, in the formats users bring: "
            "a skinned, animated glTF (.glb), the garment's point cache (PC2) with its rest mesh (OBJ), "
            "8 diffuse texture variations and an outfit colour map. The garment is simulated for N walk "
            "cycles from rest; settling.json records how close each cycle comes to the one before."
        ),
    )
    parser.add_argument("out_dir", metavar="OUT_DIR", type=Path, help="folder to write into (created if missing)")
    parser.add_argument("--garment", choices=GARMENT_NAMES, default="loose", help="which skirt to simulate (default: loose)")
    parser.add_argument(
        "--build", choices=BUILD_NAMES, default="standard",
        help="the body's proportions: standard, heavy (shorter, wider shoulders and hips, more girth) or slim (default: standard)",
    )
    parser.add_argument("--cycles", type=int, help=f"walk cycles to simulate (default: {DEFAULT_CYCLES})")
    parser.add_argument("--seed", type=int, default=0, help="seed for textures, outfits and the cloth's starting jitter (default: 0)")
    parser.add_argument(
        "--cycle-frames",
        type=int,
        default=DEFAULT_CYCLE_FRAMES,
        help=f"frames per walk cycle at 24 fps, {MIN_CYCLE_FRAMES}..{MAX_CYCLE_FRAMES} (default: {DEFAULT_CYCLE_FRAMES})",
    )
    parser.add_argument(
        "--texture-size", type=int, default=DEFAULT_TEXTURE_SIZE, help=f"texture width and height in texels, a power of two (default: {DEFAULT_TEXTURE_SIZE})"
    )
    default_sequence = ",".join(f"{clip}:{repeats}" for clip, repeats in DEFAULT_SEQUENCE)
    parser.add_argument(
        "--clips",
        nargs="?",
        const=default_sequence,
        metavar="SEQUENCE",
        help="simulate the garment once through several clips instead of --cycles walk cycles: CLIP:REPEATS,... of "
        f"Idle, Walking, Running (bare --clips: {default_sequence}); writes the animations Idle, Walking and "
        "Running into character.glb and timeline.json for `crowdbake bake --timeline`",
    )
    parser.add_argument(
        "--blend-frames", type=int,
        help=f"with --clips: frames over which the body blends from one clip into the next (default: {DEFAULT_BLEND_FRAMES})",
    )
    parser.add_argument("--cloth-rows", type=int, help="rings of the garment's mesh (default: the garment's own; fewer is faster)")
    parser.add_argument("--cloth-columns", type=int, help="vertices a ring of the garment's mesh (default: the garment's own, 72)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if args.clips is not None and args.cycles is not None:
        raise CommandError("--cycles counts walk cycles; with --clips the sequence says how often each clip plays (CLIP:REPEATS)")
    if args.clips is None and args.blend_frames is not None:
        raise CommandError("--blend-frames blends one clip into the next: it needs --clips")
    args.cycles = DEFAULT_CYCLES if args.cycles is None else args.cycles
    args.blend_frames = DEFAULT_BLEND_FRAMES if args.blend_frames is None else args.blend_frames
    if args.cycles < 1:
        raise CommandError(f"--cycles must be at least 1, got {args.cycles}")
    if not MIN_CYCLE_FRAMES <= args.cycle_frames <= MAX_CYCLE_FRAMES:
        raise CommandError(f"--cycle-frames must lie in {MIN_CYCLE_FRAMES}..{MAX_CYCLE_FRAMES}, got {args.cycle_frames}")
    size = args.texture_size
    if size < 64 or size & (size - 1):
        raise CommandError(f"--texture-size must be a power of two of at least 64, got {size}")
    if args.out_dir.exists() and not args.out_dir.is_dir():
        raise CommandError(f"{args.out_dir} exists and is not a folder")
    if not 0 <= args.seed < 2**63:
        raise CommandError(f"--seed must be a non-negative integer below 2^63, got {args.seed}")

    if args.cloth_rows is not None and not 3 <= args.cloth_rows <= 200:
        raise CommandError(f"--cloth-rows must lie in 3..200, got {args.cloth_rows}")
    if args.cloth_columns is not None and not 8 <= args.cloth_columns <= 400:
        raise CommandError(f"--cloth-columns must lie in 8..400, got {args.cloth_columns}")
    sequence = None
    frames = args.cycles * args.cycle_frames
    if args.clips is not None:
        try:
            sequence = parse_sequence(args.clips)
            frames = sequence_layout(sequence, clip_periods(args.cycle_frames), args.blend_frames)[1]
        except ValueError as error:
            raise CommandError(f"--clips {args.clips}: {error}") from None
    started = time.perf_counter()
    try:
        with progress(frames, f"simulating {args.garment} skirt") as bar:
            result = generate_sample(
                args.out_dir,
                garment=args.garment,
                cycles=args.cycles,
                seed=args.seed,
                cycle_frames=args.cycle_frames,
                texture_size=size,
                on_frame=lambda frame: bar.update(1),
                clips=sequence,
                blend_frames=args.blend_frames,
                cloth_rows=args.cloth_rows,
                cloth_columns=args.cloth_columns,
                build=args.build,
            )
    except OSError as error:
        raise CommandError(f"cannot write the sample into {args.out_dir}: {error}") from None
    elapsed = time.perf_counter() - started

    played = f"{args.cycles} cycles of {args.cycle_frames} frames" if sequence is None else f"clips {args.clips}, {frames} frames"
    body = "" if args.build == "standard" else f"{args.build} build, "
    print(f"wrote the sample ({body}{args.garment} skirt, {played}, seed {args.seed}) to {args.out_dir} in {elapsed:.1f} s:")
    for name, path in result.files.items():
        print(f"  {name:<12} {path}")
    if sequence is not None:
        return _print_quality(result.quality)
    settling = ", ".join(f"{value * 1000:.1f}" for value in result.settling)
    print(f"settling (RMS mm between frames one cycle apart, cycles 1..{args.cycles - 1}): {settling or 'n/a (one cycle)'}")
    if result.settled_cycle is None:
        print(f"no cycle came within {SETTLED_RMS * 1000:.0f} mm RMS of the one before it in {args.cycles} cycles")
    else:
        print(f"first cycle within {SETTLED_RMS * 1000:.0f} mm RMS of the one before it: cycle {result.settled_cycle}")
    return _print_quality(result.quality)


def _print_quality(quality: dict) -> int:
    print(f"cloth vertices more than {quality['capsule_penetration_tolerance_m'] * 1000:.0f} mm inside the collision capsules: "
          f"max {quality['penetrating_vertices_max']} of {quality['vertex_count']} per frame; inside the body mesh on frames "
          f"{quality['inside_body_mesh_frames']}: {quality['inside_body_mesh_vertices']}")
    print(f"edge extension after the first cycle: p99 {quality['edge_stretch_percent_p99']:.1f} %, max {quality['edge_stretch_percent_max']:.1f} %")
    return 0
