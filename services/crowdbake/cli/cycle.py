"""`crowdbake cycle`: find the best loop in a long cloth simulation and close it (paper section 3)."""
from __future__ import annotations

import argparse
import sys
import tempfile
from contextlib import ExitStack
from pathlib import Path

from crowdbake.cli.common import CommandError, progress
from crowdbake.params import CYCLE_SHARED, add_cli_options

DESCRIPTION = """\
Search a long cloth cache for its best cycle of the walk's length: pass 1 compares every frame with the frame
one cycle later over all cloth vertices (position and velocity, in a window of frames); pass 2 renders the
best candidates at their first and last frame from several views and compares their Canny edge images.
The winner's seam is closed (none, the paper's linear blend, or a Hermite correction of position and
velocity), with penetration into the body measured before and after.

The cloth cache is a PC2 or MDD with its OBJ rest mesh (--mesh), or an Alembic .abc or a .zip of OBJ frames
alone. Its first frame must sit on the body: a Z-up or centimetre cache is refused, naming --up or --units,
and converted when they are given. The cache's frame rate is --fps, else its own (MDD, Alembic), else
24 / (the PC2 sample interval). Without --timeline the cloth must move one way all along the cache: one
whose cloth changes speed from one cycle to the next, as across several clips, is refused, naming the
frames, until its --timeline is given; with --character the garment must also follow the character over
the cache, as `crowdbake bake` checks (--no-fit skips that check).

Writes OUT/cycle.json, OUT/looped.pc2 (exactly one loop) and OUT/report.html with its plots (with
--timeline, a section per clip's loop and per transition)."""


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "cycle",
        help="find and close the best cloth cycle (pass 1 vertex metric, pass 2 edge metric)",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("cloth", metavar="CLOTH", nargs="?",
                        help="the cloth cache, many walk cycles long: .pc2 or .mdd (with --mesh), .abc, or a .zip of OBJ frames")
    parser.add_argument("--mesh", metavar="CLOTH.obj", help="the garment's rest mesh (OBJ, cache point order); .pc2 and .mdd need it")
    parser.add_argument("--clip-cloth", metavar="NAME=CACHE[,MESH]", action="append", default=[],
                        help="instead of CLOTH: one cache per clip of --character, each a simulation of its own (repeat per "
                             "clip; MESH defaults to --mesh): a loop per clip, as `crowdbake bake --clip-cloth`")
    body = parser.add_mutually_exclusive_group(required=True)
    body.add_argument("--character", metavar="CHAR.glb", help="the skinned character whose animation drove the cloth")
    body.add_argument("--body", metavar="BODY.pc2", help="the body as a cache over the same frames (needs --body-mesh)")
    parser.add_argument("--body-mesh", metavar="BODY.obj", help="the body cache's mesh (OBJ)")
    # Shared with `crowdbake bake` (one default and bound: crowdbake.params.PARAMS).
    add_cli_options(parser, CYCLE_SHARED, flags=CYCLE_SHARED)
    parser.add_argument("--blend-frames", type=int, metavar="B", help="frames of the linear blend (default a quarter cycle)")
    parser.add_argument("--push-out", choices=["none", "new", "all"], default="new",
                        help="push cloth out of the body: vertices closing pushed in (new, default), all, or none")
    parser.add_argument("--threshold", type=float, help="keep pass-1 candidates under this vertex distance (cache units)")
    parser.add_argument("--settle-frames", type=int, help="ignore start frames before this (default one cycle)")
    parser.add_argument("--window", type=int, default=5, metavar="K", help="pass-1 window in frames, odd (default 5)")
    parser.add_argument("--velocity-weight", type=float, default=1.0, metavar="LAMBDA", help="pass-1 velocity weight in frames (default 1)")
    parser.add_argument("--max-cycles", type=int, default=1, metavar="N", help="also try loops of 2..N walk cycles (default 1)")
    parser.add_argument("--image-size", type=int, default=256, metavar="PX", help="pass-2 picture size (default 256)")
    parser.add_argument("--truncation", type=float, default=10.0, metavar="PX", help="edge distance cap in pixels (default 10)")
    parser.add_argument("--timeline", metavar="timeline.json",
                        help="the cache plays several clips (docs/inputs.md, clip timeline): a loop per clip and a transition per change of clip")
    parser.add_argument("--no-edge-pass", action="store_true", help="skip pass 2 (no rendering); the best pass-1 candidate wins")
    parser.add_argument("--out", required=True, metavar="DIR", help="output folder")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from crowdbake.bake.cycle import CycleParams
    from crowdbake.errors import InputError
    from crowdbake.stages.cycle_job import run_cycle_job

    if args.body is not None and args.body_mesh is None:
        raise CommandError("--body needs --body-mesh")
    if args.body_mesh is not None and args.body is None:
        raise CommandError("--body-mesh needs --body")
    if args.clip_cloth:
        for given, option in ((args.cloth, "CLOTH"), (args.timeline, "--timeline"), (args.body, "--body"), (args.cycle_frames, "--cycle-frames")):
            if given is not None:
                raise CommandError(f"--clip-cloth gives every clip its own cache and its period from --character's animation: leave out {option}")
    elif args.cloth is None:
        raise CommandError("give the cloth cache CLOTH, or --clip-cloth NAME=CACHE[,MESH] for each clip")
    try:
        params = CycleParams(
            settle_frames=args.settle_frames,
            window=args.window,
            velocity_weight=args.velocity_weight,
            max_candidates=args.candidates,
            threshold=args.threshold,
            max_cycle_count=args.max_cycles,
            views=args.cycle_views,
            image_size=args.image_size,
            truncation_px=args.truncation,
            close=args.close,
            blend_frames=args.blend_frames,
            push_out=args.push_out,
        )
        params.validate()
    except ValueError as error:
        raise CommandError(str(error)) from None

    stages = ["load", "pass 1", "pass 2", "closing", "report"]
    if args.no_edge_pass:
        stages.remove("pass 2")
    # Several clips search pass 1, pass 2 and closing once per clip (per stretch of it): their count is the
    # timeline's, read by the job, so the bar counts the finished steps without a total.
    several = args.timeline is not None or bool(args.clip_cloth)
    with ExitStack() as stack, progress(None if several else len(stages), "cycle") as bar:
        def on_progress(stage: str, done: int, total: int) -> None:
            bar.set_description(f"cycle: {stage}")
            if done == total:
                bar.update(1)

        try:
            cloth, mesh, timeline = _cloth_inputs(args, stack)
            result = run_cycle_job(
                cloth, mesh, args.out,
                character=args.character, body_pc2=args.body, body_obj=args.body_mesh,
                cycle_frames=args.cycle_frames, fps=args.fps, params=params,
                up=args.up, units=args.units, animation=args.animation,
                progress=on_progress, edge_pass=not args.no_edge_pass, timeline=timeline,
                check_fit=args.fit and args.character is not None and timeline is None,
                accept_out_of_bounds=args.accept_out_of_bounds,
            )
        except InputError as error:
            raise CommandError(f"--clip-cloth: {error.message}" if error.field == "clip_cloth" else error.message) from None
        except (ValueError, OSError) as error:
            # One line: the readers and the search name the file and the problem.
            raise CommandError(str(error).splitlines()[0] if str(error) else type(error).__name__) from None
    seam = result.closing.seam_after
    print(
        f"cycle [{result.start_frame}, {result.end_frame}) of {result.cycle_frames} frames, closed with {result.closing.method}: "
        f"position jump {seam.position_jump_ratio:.3f}, velocity jump {seam.velocity_jump_ratio:.3f}, "
        f"penetrating vertex-frames {int(result.closing.penetrating_before.sum())} -> {int(result.closing.penetrating_after.sum())}; "
        f"wrote {args.out}/cycle.json",
        file=sys.stdout,
    )
    return 0


def _cloth_inputs(args: argparse.Namespace, stack: ExitStack) -> tuple[str, str | None, str | None]:
    """(cloth, mesh, timeline) to search: as given, or the --clip-cloth caches joined end to end with a
    timeline whose later segments are new simulations (crowdbake.ingest.clip_caches), in a temporary folder."""
    if not args.clip_cloth:
        return args.cloth, args.mesh, args.timeline
    from crowdbake.ingest.clip_caches import parse_clip_cloth, write_joined_inputs

    entries = parse_clip_cloth(args.clip_cloth, Path(args.mesh) if args.mesh else None)
    folder = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="crowdbake-clips-")))
    cloth, mesh, timeline = write_joined_inputs(entries, Path(args.character), args.fps, folder)
    return str(cloth), str(mesh), str(timeline)
