"""`crowdbake bake`: a clothed character in, a verified crowd bundle out (paper sections 3 to 6)."""
from __future__ import annotations

import argparse
import json
import sys
from contextlib import ExitStack
from pathlib import Path

from crowdbake.cli.common import CommandError, StageLines, bars_enabled, progress
from crowdbake.ingest.input_modes import INPUT_OPTIONS, InputConflict, InputMode, command_line_inputs
from crowdbake.params import add_cli_options, option_for, params_from_args
from crowdbake.render.gl_device import describe as describe_gl

DESCRIPTION = """\
Bake a skinned character (glTF) and its simulated garment (a PC2 or MDD cache with its OBJ rest mesh, an
Alembic .abc, or a .zip of OBJ frames) into a bundle:
the cloth cycle (searched, or given with --cycle), poses of the body and the garment for every cycle frame
at two LODs (meshoptimizer), UV-mapped impostors (normal, UV and surface maps, detail maps with
--detail-map, for --frames frames x --azimuths x elevations views, as many as fit --impostor-budget,
cropped to the character, rendered with pyrender under OSMesa, or EGL with PYOPENGL_PLATFORM=egl on the
device EGL_DEVICE_ID names, else the first that is not Mesa's software one),
block compression, the impostor's fidelity against the mesh and the texture memory of figure 4.

Writes OUT/NAME/VERSION (shared_formats bundle v1), verifies it, and prints sizes, timings, fidelity and the
GL renderer that drew the impostors.
A published NAME/VERSION never changes: baking it again with other results is an error.
The garment must sit on the character at its first frame: a Z-up or centimetre cache is refused, naming
--up or --units, and converted when they are given."""


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "bake",
        help="bake a clothed character into a verified bundle (poses, LODs, UV-mapped impostors)",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("character", metavar="CHAR.glb", help="the skinned, animated character (glTF 2.0, .glb or .gltf)")
    parser.add_argument("--cloth", metavar="CLOTH", help="the garment's simulated cache, many walk cycles: .pc2 or .mdd (with --cloth-mesh), .abc, or a .zip of OBJ frames (none: the body alone, its animation's own loop sampled at --fps, default 30)")
    parser.add_argument("--cloth-mesh", metavar="CLOTH.obj", help="the garment's rest mesh (OBJ, cache point order); .pc2 and .mdd need it")
    parser.add_argument("--cycle", metavar="cycle.json", help="use this cycle (from `crowdbake cycle`) instead of searching")
    parser.add_argument("--timeline", metavar="timeline.json", help="the cloth cache plays several clips (docs/inputs.md, clip timeline): "
                        "a loop per clip and the transitions between them; the bundle (format 3) carries them all")
    parser.add_argument("--clip-cloth", metavar="NAME=CACHE[,MESH]", action="append", default=[],
                        help="one cloth cache per clip, repeated per clip (docs/inputs.md, one cache per clip): each a separate "
                        "simulation of the character's animation NAME from rest; MESH defaults to --cloth-mesh. A loop per clip, "
                        "no transitions (no simulation joined the clips); instead of --cloth and --timeline")
    parser.add_argument("--textures", metavar="DIR", help="diffuse_*.png or diffuse_*.jpg variations (region codes in alpha: PNG only) and outfits.png (default: the glTF texture)")
    parser.add_argument("--name", required=True, help="bundle name ([a-z0-9][a-z0-9._-]*)")
    parser.add_argument("--version", required=True, dest="bundle_version", metavar="VER", help="bundle version")
    parser.add_argument("--out", required=True, metavar="DIR", help="bundles folder: the bundle goes to DIR/NAME/VER")
    # Every parameter that shapes the bundle, from the one table (crowdbake.params.PARAMS).
    add_cli_options(parser)
    parser.add_argument("--created", metavar="TIME", help="manifest time, RFC 3339 UTC (default: SOURCE_DATE_EPOCH or the inputs' time)")
    parser.add_argument("--work", metavar="DIR", help="keep the work folder here (a rerun resumes finished stages)")
    parser.add_argument("--figure4", metavar="PLOT.png", help="also plot figure 4 (texture memory) here, with its JSON beside it")
    parser.add_argument("--json", action="store_true", help="print the summary as JSON instead of text")
    parser.set_defaults(func=run)


class _Bars:
    """One progress bar per stage: (stage, done, total) callbacks from the stages drive them."""

    def __init__(self, stack: ExitStack):
        self._stack = stack
        self._stage: str | None = None
        self._bar = None
        self._inner: ExitStack | None = None

    def __call__(self, stage: str, done: int, total: int) -> None:
        if stage != self._stage or self._bar is None or self._bar.total != total:
            self.close()
            self._inner = ExitStack()
            self._bar = self._inner.enter_context(progress(max(total, 1), stage))
            self._stage = stage
        self._bar.n = min(done, self._bar.total)
        self._bar.refresh()

    def close(self) -> None:
        if self._inner is not None:
            self._inner.close()
        self._inner = self._bar = None


def _mib(size: float) -> str:
    return f"{size / (1024 * 1024):.2f} MiB"


def format_summary(summary) -> str:
    """The text printed after a bake: sizes, timings, LODs, fidelity, compression, figure 4."""
    lines = [f"bundle {summary.name}/{summary.version} -> {summary.bundle} ({_mib(summary.total_bytes)}, verified)"]
    cycle = summary.cycle
    lines.append(
        f"cycle    frames [{cycle['start_frame']}, {cycle['end_frame']}) = {cycle['cycle_frames']} at {cycle['fps']:g} fps, "
        f"closing {cycle['closing']}, seam position/velocity jump {_ratio(cycle['position_jump_ratio'])} / {_ratio(cycle['velocity_jump_ratio'])}"
    )
    lines.append("timings  " + ", ".join(f"{stage} {seconds:.2f} s" for stage, seconds in summary.timings_s.items()))
    timings = summary.timings
    if timings:
        lines.append(
            f"time     {timings['total_s']:.2f} s wall, {timings['cpu_s']:.2f} s CPU, {timings['render_s']:.2f} s in OpenGL "
            f"({timings['renders']} renders), {timings['workers']} process{'es' if timings['workers'] > 1 else ''} for poses and impostors"
        )
    impostor = summary.impostor
    if impostor.get("views"):
        render = impostor["render_seconds"]
        lines.append(
            f"impostor {impostor['views']} views in {impostor['tasks']} tasks: render {render:.2f} s "
            f"({impostor['views'] / render if render > 0 else float('inf'):.0f} views/s), maps {impostor['maps_seconds']:.2f} s, "
            f"fidelity references {impostor['reference_seconds']:.2f} s"
        )
    for gl in summary.gl_renderers:
        lines.append(f"gl       {gl['impostor_tasks']} impostor tasks drawn on {describe_gl(gl)}")
    for mesh in summary.meshes:
        extra = ""
        if mesh["lod"] == 1:
            extra = f" (target {mesh['target_triangles']}, error {mesh['relative_error']:.4f} of extent{', border locked' if mesh['locked_border'] else ''})"
        lines.append(f"mesh     {mesh['part']} lod {mesh['lod']}: {mesh['vertex_count']} vertices, {mesh['triangle_count']} triangles{extra}")
    fidelity = summary.fidelity
    for key, label in (("impostor", "impostor vs mesh"), ("impostor_uncompressed_normals", "  (normals uncompressed)"), ("nearest_view", "between views")):
        if key in fidelity:
            f = fidelity[key]
            lines.append(
                f"fidelity {label}: SSIM mean {f['ssim_mean']:.3f} worst {f['ssim_worst']:.3f}, "
                f"PSNR mean {f['psnr_db_mean']:.1f} dB worst {f['psnr_db_worst']:.1f} dB over {f['views']} views"
            )
    for key, label in (("at_views", "at baked views"), ("between_views", "between views and frames")):
        if key in fidelity.get("runtime", {}):
            f = fidelity["runtime"][key]
            lines.append(f"runtime  blended impostor {label}: SSIM mean {f['ssim_mean']:.3f} worst {f['ssim_worst']:.3f} over {f['views']} views")
    for entry in fidelity.get("runtime", {}).get("ranges", []):  # several clips: each clip and transition
        at, between = entry["at_views"], entry["between_views"]
        lines.append(f"runtime  {entry['kind']} {entry['name']}: SSIM at baked views {at['ssim_mean']:.3f} (worst {at['ssim_worst']:.3f}), "
                     f"between views and frames {between['ssim_mean']:.3f} (worst {between['ssim_worst']:.3f})")
    precision = fidelity.get("uv_precision", {})
    if "rgba8" in precision:
        lines.append(
            f"uv map   max texel error at {precision['texture_size']}²: rgba16 {precision['rgba16']['max_texels']:.4f}, "
            f"uv32 {precision['uv32']['max_texels']:.4f}, "
            f"rgba8 {precision['rgba8']['max_texels']:.2f}, bc1 {precision['bc1']['max_texels']:.1f}"
        )
    for name, errors in summary.compression.items():
        lines.append(
            f"compress {name} ({errors['pixel_format']}): RGB mean |error| {errors['rgb_mean_abs']:.2f}, "
            f"worst PSNR {errors['rgb_psnr_db_worst']:.1f} dB, alpha max error {errors['alpha_max']:.0f}"
        )
    memory = summary.texture_memory
    if "impostor" in memory:
        held = memory["impostor"]
        crop = held["crop"]
        lines.append(
            f"memory   impostor maps {held['stored_mib']:.1f} MiB ("
            + ", ".join(f"{kind} {size / 1048576:.1f}" for kind, size in held["stored_bytes"].items())
            + f") for {held['frames']} frames x {held['views']} views of {crop['width']}x{crop['height']} texels"
            + (f" (the character's crop of {held['tile_size']}²)" if (crop["width"], crop["height"]) != (held["tile_size"],) * 2 else "")
        )
        for entry in held.get("ranges", []):  # several clips (format v2): each loop and transition
            lines.append(f"{entry['kind']:<8} {entry['name']}: pose frames {entry['pose_frames'][0]}-{entry['pose_frames'][1] - 1}, "
                         f"{len(entry['baked_frames'])} baked ({entry['stored_mib']:.2f} MiB)")
        budget = held.get("budget")
        allocation = (budget or {}).get("allocation")
        chosen_layout = (budget or {}).get("layout", {}).get("chosen")
        if chosen_layout is not None:  # tile, azimuths and frames by measuring
            budget_text = "no budget" if budget["budget_mib"] is None else f"the {budget['budget_mib']:g} MiB budget"
            lines.append(f"memory   {budget_text}, chosen by measuring: {chosen_layout['tile']}² tiles, {chosen_layout['azimuths']} azimuths"
                         + ("" if "ranges" in budget else f", {budget['chosen']['frames']} frames")
                         + f" (asked {budget['asked']['tile']}², {budget['asked']['azimuths']}, at most {budget['asked']['frames']}); predicted SSIM "
                         f"{chosen_layout['at_views']:.3f} at baked views, {chosen_layout['between_worst']:.3f} between views and frames"
                         + ("" if budget["fits"] else "; still over it at the floors"))
        if allocation is not None and "ranges" in budget:  # several clips under one budget
            lines.append(f"memory   the {allocation['budget_mib']:g} MiB archetype budget, split by measuring: "
                         + ", ".join(f"{r['name']} {r['baked_frames']} frames (SSIM {r['score']:.3f})" for r in allocation["ranges"])
                         + ("" if allocation["fits"] else "; still over it at the floors"))
        for clip, chosen in ({} if allocation is not None else (budget or {}).get("per_clip", {})).items():
            if chosen["chosen"] != chosen["asked"]:
                lines.append(f"memory   the {chosen['budget_mib']:g} MiB budget chose {chosen['chosen']['azimuths']} azimuths and "
                             f"{chosen['chosen']['frames']} frames for {clip} (asked {chosen['asked']['azimuths']} and {chosen['asked']['frames']})"
                             + ("" if chosen["fits"] else "; still over it at the floors"))
        if budget and "per_clip" not in budget and chosen_layout is None and budget["chosen"] != budget["asked"]:
            motion = budget.get("motion", {})
            lines.append(f"memory   the {budget['budget_mib']:g} MiB budget chose {budget['chosen']['azimuths']} azimuths and "
                         f"{budget['chosen']['frames']} frames (asked {budget['asked']['azimuths']} and {budget['asked']['frames']}"
                         + (f"; the motion needs {motion['frames']} frames" if motion.get("max_texels") is not None else "") + ")"
                         + ("" if budget["fits"] else "; still over it at the floors"))
    lines.append(
        f"figure 4 paper model: 1 variation {memory['paper_mib']['1']:.0f} MiB both; 8 variations detail-mapped "
        f"{memory['paper_mib']['detail_8']:.0f} MiB vs UV-mapped {memory['paper_mib']['uv_8']:.0f} MiB; "
        f"this bundle breaks even at {memory['bundle_break_even_variations']:.1f} variations"
        + (f" (UV-mapped is no larger from {memory['break_even_variations']})" if memory.get("break_even_variations") else "")
    )
    for path, size in sorted(summary.files.items()):
        lines.append(f"file     {path}: {size:,} bytes")
    return "\n".join(lines)


def _ratio(value) -> str:
    return "n/a" if value is None else f"{value:.3g}"


def write_figure4(report: dict, png_path: Path) -> None:
    """Plot figure 4 (texture memory against texture variations) from a texture_memory.json document."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(1, 2, figsize=(10, 4), constrained_layout=True)
    for axis, (key, title) in zip(axes, (("paper", "paper's assumptions (1024², 10 frames, DXT)"), ("bundle", "this bundle's bytes"))):
        series = report[key]
        axis.plot(series["variations"], series["detail_mapped_mib"], "o-", label="detail-mapped impostor")
        axis.plot(series["variations"], series["uv_mapped_mib"], "s-", label="UV-mapped impostor")
        axis.set_xlabel("texture variations")
        axis.set_ylabel("texture memory (MiB)")
        axis.set_title(title)
        axis.grid(True, alpha=0.3)
        axis.legend()
    figure.suptitle("Texture memory for one clothed character (Dobbyn et al. 2006, figure 4)")
    png_path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(png_path, dpi=120)
    plt.close(figure)


def run(args: argparse.Namespace) -> int:
    from crowdbake.errors import InputError
    from crowdbake.params import BakeParams

    try:
        params = BakeParams.from_dict(params_from_args(args))
    except InputError as error:
        raise CommandError(_option_message(error)) from None
    try:
        mode = command_line_inputs(args).mode(params.cycle_frames)
    except InputConflict as conflict:
        raise CommandError(conflict.command_line()) from None
    with ExitStack() as stack:
        try:
            cloth = _joined_clip_cloth(args, params, stack) if mode is InputMode.CLIP_CLOTH else _cloth_as_given(args)
        except InputError as error:
            raise CommandError(_option_message(error)) from None
        return _bake(args, params, cloth)


def _cloth_as_given(args: argparse.Namespace) -> tuple[Path | None, Path | None, Path | None]:
    """(cloth, cloth mesh, timeline) as the command line gave them."""
    return (Path(args.cloth) if args.cloth else None, Path(args.cloth_mesh) if args.cloth_mesh else None,
            Path(args.timeline) if args.timeline else None)


def _joined_clip_cloth(args: argparse.Namespace, params, stack: ExitStack) -> tuple[Path, Path, Path]:
    """(cloth, cloth mesh, timeline) of the --clip-cloth caches joined into one cache and its timeline
    (crowdbake.ingest.clip_caches), written under --work or a temporary folder."""
    import tempfile

    from crowdbake.ingest.clip_caches import parse_clip_cloth, write_joined_inputs

    entries = parse_clip_cloth(args.clip_cloth, Path(args.cloth_mesh) if args.cloth_mesh else None)
    folder = Path(args.work) / "clip_cloth" if args.work else Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="crowdbake-clips-")))
    return write_joined_inputs(entries, Path(args.character), params.fps, folder)


def _bake(args: argparse.Namespace, params, cloth: tuple[Path | None, Path | None, Path | None]) -> int:
    from crowdbake.formats.errors import FormatError
    from crowdbake.errors import InputError, VersionConflict
    from crowdbake.stages.runner import run_bake
    from crowdbake.stages.validate import BakeInputs

    inputs = BakeInputs(
        character=Path(args.character),
        cloth=cloth[0],
        cloth_mesh=cloth[1],
        textures=Path(args.textures) if args.textures else None,
        cycle=Path(args.cycle) if args.cycle else None,
        name=args.name,
        version=args.bundle_version,
        params=params,
        created=args.created,
        timeline=cloth[2],
    )
    with ExitStack() as stack:
        bars = _Bars(stack) if bars_enabled() else StageLines("bake")
        stack.callback(bars.close)
        try:
            summary = run_bake(inputs, Path(args.out), Path(args.work) if args.work else None, progress=bars)
        except InputError as error:
            raise CommandError(_option_message(error)) from None
        except VersionConflict as error:
            raise CommandError(str(error), exit_code=3) from None
        except FormatError as error:  # the packed bundle failed the publish stage's verification
            raise CommandError(f"the written bundle does not verify: {error}", exit_code=1) from None
    # The publish stage verified the packed bundle and compared the published copy with it byte for byte.

    if args.figure4:
        plot = Path(args.figure4)
        report = json.loads((summary.bundle / "texture_memory.json").read_text())
        write_figure4(report, plot)
        plot.with_suffix(".json").write_text(json.dumps(report, indent=2) + "\n")
    if args.json:
        json.dump(summary.to_dict(), sys.stdout, indent=2)
        sys.stdout.write("\n")
    else:
        print(format_summary(summary))
        if args.clip_cloth:
            print(f"clips    {len(args.clip_cloth)} loops from separate simulations, no transitions (no simulation joined the clips): "
                  "crowdview keeps each character in its first clip")
        if summary.texture_note:
            print(f"textures {summary.texture_note}")
        if summary.animation_choice:
            choice = summary.animation_choice
            print(f"animation {choice['name']!r} ({choice['frames']} frames) picked: {choice['reason']}")
        if args.figure4:
            print(f"figure 4 plot: {args.figure4}")
    return 0


# The inputs' options (crowdbake.ingest.input_modes) and the bundle's identity; the parameters' flags come from crowdbake.params.
_OPTIONS = {
    **INPUT_OPTIONS,
    "cloth_mesh": "--cloth-mesh",
    "name": "--name",
    "version": "--version",
    "created": "--created",
}


def _option_message(error) -> str:
    """An InputError as a one-liner naming the command-line option at fault."""
    option = option_for(error.field) or _OPTIONS.get(error.field or "", error.field)
    message = error.message
    if error.field and message.startswith(f"{error.field}: "):
        message = message[len(error.field) + 2 :]
    return f"{option}: {message}" if option else message
