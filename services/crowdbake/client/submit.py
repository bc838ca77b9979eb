"""`crowdbake submit` (and `crowdbake-submit`, the same command from the client alone): upload a
character and its cloth to a crowdbake server, bake, follow, download.

Made for CI pipelines: a distinct exit code per kind of outcome (Exit in crowdbake.client.http),
`--json` for one JSON object on stdout at exit, progress on stderr (a bar on a terminal, a plain line
per change otherwise), retries across server restarts, and every check that can be made before
uploading made before uploading.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Sequence

from crowdbake.client.http import ClientError, Exit, Server, check_service_root, problem_line
from crowdbake.client.preflight import check_glb_magic, check_name_and_version
from crowdbake.client.progress import FINAL_STATES, Reporter
from crowdbake.errors import InputError
from crowdbake.ingest.input_modes import BakeInputSet, InputConflict, InputMode, command_line_inputs
from crowdbake.params import add_cli_options, option_for, params_from_args

DESCRIPTION = """\
Uploads CHAR.glb, the cloth (a .pc2 or .mdd cache with --cloth-mesh, or an Alembic .abc or a .zip of
OBJ frames alone; without --cloth the body alone is baked, its animation's own loop), the textures
(--textures DIR: diffuse_*.png or diffuse_*.jpg, and outfits.png) and a chosen cycle (--cycle cycle.json
from `crowdbake cycle`, with looped.pc2 when it lies beside it) or a clip timeline (--timeline
timeline.json: a cache of several clips) or one cache per clip (--clip-cloth NAME=CACHE[,MESH], repeated), starts a bake of NAME/VERSION and prints its id.
With --wait, follows it until it ends; with --download DIR, also fetches the published bundle to
DIR/NAME/VERSION and checks every file's size and sha256 (and, with the full crowdbake package,
the bundle's formats).

With --export-out DIR, also fetches the engine export (glTF, KTX2, VATs: docs/export.md) into
DIR/NAME/VERSION.

Before uploading anything, the server checks the key, its scopes, NAME, VERSION and the bake
parameters (a bake request naming no real assets, which starts nothing), and that NAME/VERSION is not
already published from other inputs (bundles never change; from the files' sha256, nothing uploaded).

The key comes from --key or CROWDBAKE_API_KEY (better in CI: it stays out of the process list)."""

EPILOG = """\
exit codes:
  0  done: the bake succeeded (and, with --download, the bundle downloaded and verified)
  1  the bake failed or was cancelled, or the downloaded bundle did not verify
  2  usage: options, missing files, flag combinations, a --server URL where no crowdbake service answers
  3  the input is rejected: name, version, parameters, files (by the server, or by the same check made here first)
  4  authentication or permission: no key, unknown key, missing scope
  5  server unreachable or failing, after retrying for --retry-for seconds
  6  timed out: the bake did not end within --timeout (it goes on on the server)
"""

# An asset id that never exists: the preflight bake request names it so that the server validates
# everything else and then refuses the request for want of assets, creating nothing.
PREFLIGHT_ASSET = "preflight-no-such-asset"
ASSET_FIELDS = ("character", "cloth", "cycle", "timeline")
# The cloth forms POST /v1/assets/cloth takes (crowdbake.api.routes.assets): cache suffix -> whether it
# needs its OBJ rest mesh beside it, and the multipart field the file goes in.
CLOTH_FORMS = {".pc2": (True, "cache"), ".mdd": (True, "cache"), ".abc": (False, "cache"), ".zip": (False, "sequence")}
# Texture names the bake request takes (crowdbake.api.schemas.TEXTURE_NAME_PATTERN): the outfit map is
# a PNG only, since its 16 exact colours a row would not survive JPEG.
DIFFUSE_SUFFIXES = (".png", ".jpg", ".jpeg")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("character", metavar="CHAR.glb", help="the skinned, animated character (.glb or .gltf)")
    parser.add_argument("--server", required=True, metavar="URL", help="the crowdbake server, e.g. http://127.0.0.1:8000")
    parser.add_argument("--key", metavar="KEY", default=os.environ.get("CROWDBAKE_API_KEY"), help="API key (default CROWDBAKE_API_KEY)")
    parser.add_argument("--cloth", metavar="CLOTH.pc2",
                        help="the cloth cache: .pc2 or .mdd with --cloth-mesh, or an Alembic .abc or a .zip of OBJ frames alone "
                             "(none: the body alone, its animation's own loop sampled at --fps, default 30)")
    parser.add_argument("--cloth-mesh", metavar="CLOTH.obj", help="the cloth's rest mesh (OBJ, in the cache's point order); only with a .pc2 or .mdd cache")
    parser.add_argument("--textures", metavar="DIR", help="folder with diffuse_*.png (or diffuse_*.jpg: no colour-region codes) and outfits.png")
    parser.add_argument("--cycle", metavar="cycle.json", help="bake this cycle (from `crowdbake cycle`; looped.pc2 beside it goes too) instead of searching")
    parser.add_argument("--timeline", metavar="timeline.json", help="the cloth plays several clips (docs/inputs.md, clip timeline): a loop per clip and the transitions between them")
    parser.add_argument("--clip-cloth", metavar="NAME=CACHE[,MESH]", action="append", default=[],
                        help="one cloth cache per clip, repeated (docs/inputs.md, one cache per clip): a separate simulation of the "
                             "animation NAME each, MESH defaulting to --cloth-mesh; a loop per clip, no transitions; instead of --cloth")
    parser.add_argument("--name", required=True, help="bundle name ([a-z0-9._-], checked by the server before uploading)")
    parser.add_argument("--version", required=True, dest="bundle_version", metavar="VERSION", help="bundle version; a published version never changes")
    parser.add_argument("--wait", action="store_true", help="follow the bake until it ends")
    parser.add_argument("--download", metavar="DIR", help="download and verify the bundle into DIR/NAME/VERSION (implies --wait)")
    parser.add_argument("--export-out", metavar="DIR", help="fetch the engine export (docs/export.md) into DIR/NAME/VERSION (implies --wait)")
    parser.add_argument("--no-publish", action="store_true", help="do not publish the bundle when the bake succeeds (publish later from the page or the API)")
    parser.add_argument("--public", action="store_true", help="make the bundle readable without a key")
    parser.add_argument("--created", metavar="TIME", help="manifest time, RFC 3339 UTC, as `crowdbake bake --created` (default: the server's)")
    parser.add_argument("--json", action="store_true", help="print one JSON object on stdout at exit (exit_code, state, bake_id, bundle, problem)")
    # The one parameter table (crowdbake.params, standard library only, so the client stays light): the same
    # names, bounds and choices as `crowdbake bake` and the REST model; omitted options keep server defaults.
    add_cli_options(parser.add_argument_group("bake parameters (server defaults when omitted)"), server_defaults=True)
    parser.add_argument("--poll", type=float, default=1.0, metavar="S", help="seconds between status checks (default 1)")
    parser.add_argument("--timeout", type=float, default=3600.0, metavar="S", help="give up waiting for the bake after S seconds: exit 6 (default 3600)")
    parser.add_argument("--retry-for", type=float, default=120.0, metavar="S",
                        help="keep retrying an unreachable or restarting server for S seconds before exit 5 (default 120)")


def build_parser(prog: str = "crowdbake-submit", argv: Sequence[str] | None = None) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=prog, description=DESCRIPTION, epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_arguments(parser)
    report_usage_errors_as_json(parser, argv)
    return parser


def report_usage_errors_as_json(parser: argparse.ArgumentParser, argv: Sequence[str] | None = None) -> None:
    """Make `parser` print the JSON result too when --json is among the arguments and they do not parse."""
    original = parser.error

    def error(message: str):
        arguments = sys.argv[1:] if argv is None else argv
        if "--json" in arguments:
            print(json.dumps(Outcome(exit_code=int(Exit.USAGE), problem=local_problem(message)).as_dict()), flush=True)
        original(message)  # prints the usage and exits 2

    parser.error = error


# ------------------------------------------------------------------------------------------ result


@dataclass
class Outcome:
    """What the command prints with --json: one object, whatever happened."""

    exit_code: int = int(Exit.DONE)
    state: str | None = None          # the bake's state when the command ended (None: no bake started)
    bake_id: str | None = None
    name: str | None = None
    version: str | None = None
    progress: float | None = None
    bundle: str | None = None         # the downloaded bundle's folder
    verified: str | None = None       # what was checked of it
    problem: dict[str, Any] | None = None  # RFC 9457 fields: the server's problem, or one made here
    retries: int = 0                  # requests repeated because the server was unreachable or restarting

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def local_problem(message: str, title: str = "Usage error") -> dict[str, Any]:
    return {"type": "about:blank", "title": title, "status": None, "detail": message}


# ------------------------------------------------------------------------------ local checks (exit 2)


@dataclass
class Inputs:
    character: Path
    cloth_files: dict[str, Path]   # multipart field -> file: cache + mesh, cache alone (.abc), sequence (.zip), or none (body only)
    cloth_data: dict[str, str]
    textures: dict[str, Path]      # texture name -> file
    params: dict[str, Any]
    cycle_files: dict[str, Path]   # multipart field -> file: cycle (and looped), or none
    timeline: Path | None = None   # a clip timeline (POST /v1/assets/timelines), or none
    clip_cloth: list[tuple[str, dict[str, Path]]] = field(default_factory=list)  # (clip, its cloth_form) per --clip-cloth

    def forms(self) -> BakeInputSet[dict[str, Path]]:
        """Each input's upload (multipart field -> file), by role."""
        return BakeInputSet(character={"file": self.character}, cloth=self.cloth_files or None, cycle=self.cycle_files or None,
                            timeline={"timeline": self.timeline} if self.timeline is not None else None,
                            textures={name: {"file": path} for name, path in self.textures.items()}, clip_cloth=self.clip_cloth)


def usage(message: str) -> ClientError:
    return ClientError(message, Exit.USAGE, local_problem(message))


def bake_params(args: argparse.Namespace) -> dict[str, Any]:
    """The bake parameters given on the command line, in the API's names (crowdbake.params)."""
    try:
        return params_from_args(args, given_only=True)
    except InputError as error:
        raise usage(f"{option_for(error.field)}: {error.message.split(': ', 1)[-1]}") from None


def texture_files(folder: str | None) -> dict[str, Path]:
    """Texture name -> file: diffuse_*.png / .jpg / .jpeg and outfits.png of `folder` (none without one)."""
    if not folder:
        return {}
    root = Path(folder)
    if not root.is_dir():
        raise usage(f"--textures {folder}: not a folder")
    for name in ("outfits.jpg", "outfits.jpeg"):
        if (root / name).is_file():
            raise usage(f"--textures {folder}: {name}: the outfit map must be a PNG (16 exact colours a row; JPEG blurs them)")
    files = {path.name: path for path in sorted(root.iterdir())
             if path.is_file() and ((path.name.startswith("diffuse_") and path.suffix in DIFFUSE_SUFFIXES) or path.name == "outfits.png")}
    if not any(name.startswith("diffuse_") for name in files):
        raise usage(f"--textures {folder}: no diffuse_*.png or diffuse_*.jpg in the folder")
    return files


def cloth_form(cloth: Path, mesh: Path | None) -> dict[str, Path]:
    """Multipart field -> file for POST /v1/assets/cloth, from the cache's suffix (CLOTH_FORMS)."""
    form = CLOTH_FORMS.get(cloth.suffix.lower())
    if form is None:
        raise usage(f"--cloth {cloth}: a cloth cache is .pc2 or .mdd (with --cloth-mesh), or .abc or .zip (alone)")
    needs_mesh, field = form
    if needs_mesh and mesh is None:
        raise usage(f"--cloth {cloth} needs --cloth-mesh CLOTH.obj (its rest mesh, in the cache's point order)")
    if not needs_mesh and mesh is not None:
        carries = "an Alembic .abc carries its own mesh" if field == "cache" else "a .zip of OBJ frames carries its own mesh"
        raise usage(f"--cloth-mesh goes with a .pc2 or .mdd cache; {carries}: drop --cloth-mesh")
    return {field: cloth, **({"mesh": mesh} if needs_mesh else {})}


def cycle_files(path: str | None) -> dict[str, Path]:
    """cycle.json and, as `crowdbake bake --cycle` takes it, the looped.pc2 beside it."""
    if not path:
        return {}
    document = Path(path)
    if not document.is_file():
        raise usage(f"--cycle {path}: no such file")
    looped = document.with_name("looped.pc2")
    return {"cycle": document, **({"looped": looped} if looped.is_file() else {})}


def check_locally(args: argparse.Namespace) -> Inputs:
    """Everything about the command line that needs no server: files, flag combinations, numbers."""
    for option, value in (("--download", args.download), ("--export-out", args.export_out)):
        if value and args.no_publish:
            raise usage(f"{option} needs a published bundle; drop --no-publish (or publish later and download then)")
    if args.export_out and args.export is False:
        raise usage("--export-out needs an engine export; drop --no-export")
    for option in ("poll", "timeout", "retry_for"):
        if getattr(args, option) <= 0:
            raise usage(f"--{option.replace('_', '-')} must be positive, got {getattr(args, option)}")
    params = bake_params(args)
    try:
        mode = command_line_inputs(args).mode(params.get("cycle_frames"))
    except InputConflict as conflict:
        raise usage(conflict.command_line()) from None
    character = Path(args.character)
    clip_cloth = clip_cloth_forms(args) if mode is InputMode.CLIP_CLOTH else []
    if args.cloth_mesh and mode is InputMode.BODY_ONLY:
        raise usage("--cloth-mesh goes with --cloth (a .pc2 or .mdd cache); without --cloth the body alone is baked")
    cloth = cloth_form(Path(args.cloth), Path(args.cloth_mesh) if args.cloth_mesh else None) if args.cloth else {}
    for path in (character, *cloth.values()):
        if not path.is_file():
            raise usage(f"{path}: no such file")
    for option, value in (("--download", args.download), ("--export-out", args.export_out)):
        if value and Path(value).exists() and not Path(value).is_dir():
            raise usage(f"{option} {value}: not a folder")
    not_glb = check_glb_magic(character)
    if not_glb:  # the input itself is wrong, as the server would say: exit 3, told before uploading
        raise ClientError(not_glb, Exit.REJECTED, local_problem(not_glb, "Rejected input"))
    cloth_data = {"cycle_frames": str(args.cycle_frames)} if args.cycle_frames and cloth else {}
    timeline = Path(args.timeline) if args.timeline else None
    if timeline is not None and not timeline.is_file():
        raise usage(f"--timeline {timeline}: no such file")
    return Inputs(character, cloth, cloth_data, texture_files(args.textures), params, cycle_files(args.cycle), timeline, clip_cloth)


def clip_cloth_forms(args: argparse.Namespace) -> list[tuple[str, dict[str, Path]]]:
    """(clip, multipart field -> file) per --clip-cloth NAME=CACHE[,MESH] (crowdbake.ingest.clip_caches)."""
    from crowdbake.ingest.clip_caches import parse_clip_cloth

    try:
        entries = parse_clip_cloth(args.clip_cloth, Path(args.cloth_mesh) if args.cloth_mesh else None)
    except InputError as error:
        raise usage(f"--clip-cloth: {error.message}") from None
    forms = []
    for entry in entries:
        try:
            form = cloth_form(entry.cache, entry.mesh)
        except ClientError as error:
            raise usage(f"--clip-cloth {entry.clip}: {error}") from None
        for path in form.values():
            if not path.is_file():
                raise usage(f"--clip-cloth {entry.clip}: {path}: no such file")
        forms.append((entry.clip, form))
    return forms


# --------------------------------------------------------------------------------- the server's part


def bake_body(args: argparse.Namespace, inputs: Inputs, assets: BakeInputSet[str]) -> dict[str, Any]:
    """The POST /v1/bakes body of `assets` (the asset id of each of inputs.forms())."""
    return {"name": args.name, "version": args.bundle_version, **assets.request_fields(),
            "params": inputs.params, "publish": not args.no_publish, "public": args.public,
            **({"created": args.created} if args.created else {})}


def is_missing_asset(error: dict[str, Any]) -> bool:
    field = str(error.get("field", ""))
    return (field in ASSET_FIELDS or field.startswith("textures.") or (field.startswith("clip_cloth.") and field.endswith(".cloth"))) and str(error.get("message", "")).startswith("no ")


def preflight(server: Server, args: argparse.Namespace, inputs: Inputs) -> None:
    """Ask the server to check the key, its scopes, the name, version and parameters, before uploading.

    The request names assets that do not exist, so the server (POST /v1/bakes) validates everything
    else first and then refuses it for want of the assets, starting nothing. Any other refusal is the
    one the real request would get after the uploads."""
    body = bake_body(args, inputs, inputs.forms().map(lambda role, form: PREFLIGHT_ASSET))
    response = server.request("POST", "/v1/bakes", "checking the bake request", json=body, accept=frozenset({422}))
    if response.status_code == 422:
        problem = response.json()
        if problem.get("errors") and all(is_missing_asset(error) for error in problem["errors"]):
            return
        raise ClientError(f"the server refuses this bake: {problem_line(problem)}", Exit.REJECTED, problem)
    raise ClientError(f"checking the bake request: the server accepted a bake of assets that do not exist (HTTP {response.status_code})",
                      Exit.UNREACHABLE, {"title": "Unexpected answer", "status": response.status_code, "detail": response.text[:200]})


def local_inputs(inputs: Inputs) -> dict[str, list[Path]]:
    """Input role (as the bake record names it) -> its local files, for the published-version check."""
    return {role: list(form.values()) for role, form in inputs.forms().roles().items()}


def upload(server: Server, endpoint: str, files: dict[str, Path], what: str, say, data: dict[str, str] | None = None) -> dict[str, Any]:
    # Files are reopened for every attempt: a retry after a restart sends them again from the start.
    response = server.request("POST", endpoint, f"uploading {what}", data=data or {},
                              files=lambda: {field: (path.name, open(path, "rb")) for field, path in files.items()})
    asset = response.json()
    say(f"{what}: {asset['id']} ({'stored' if response.status_code == 201 else 'already stored'}, sha256 {asset['digest'][:12]})")
    return asset


def follow(server: Server, bake_id: str, poll: float, timeout: float, reporter: Reporter, outcome: Outcome) -> dict[str, Any]:
    """Poll the bake until it ends; a server that goes away meanwhile is waited for (Server's retries)."""
    deadline = time.monotonic() + timeout
    try:
        while True:
            bake = server.request("GET", f"/v1/bakes/{bake_id}", f"following bake {bake_id}").json()
            progress = reporter.show(bake)
            outcome.state, outcome.progress = bake["state"], round(progress.overall, 4)
            if bake["state"] in FINAL_STATES:
                return bake
            if time.monotonic() > deadline:
                message = f"bake {bake_id} still {bake['state']} after {timeout:g} s (it goes on on the server)"
                raise ClientError(message, Exit.TIMED_OUT, local_problem(message, "Timed out"))
            time.sleep(min(poll, max(deadline - time.monotonic(), 0.0) + 0.01))
    finally:
        reporter.close()


def bake_problem(bake: dict[str, Any]) -> dict[str, Any]:
    error = bake.get("error") or {}
    if bake["state"] == "cancelled":
        return {"type": "about:blank", "title": "Bake cancelled", "status": None, "detail": f"bake {bake['id']} was cancelled"}
    return {"type": error.get("type", "about:blank"), "title": error.get("title", "Bake failed"), "status": None,
            "detail": error.get("detail", ""), "stage": error.get("stage"), "field": error.get("field")}


def bake_error_line(bake: dict[str, Any]) -> str:
    error = bake.get("error") or {}
    if bake["state"] == "cancelled":
        return f"bake {bake['id']} was cancelled"
    field = f" [{error['field']}]" if error.get("field") else ""
    return f"bake {bake['id']} failed in {error.get('stage', '?')}: {error.get('title', 'error')}: {error.get('detail', '')}{field}"


def submit(args: argparse.Namespace, outcome: Outcome, say, out) -> None:
    """The whole command; raises ClientError for every outcome but success."""
    import httpx

    from crowdbake.client.download import download_bundle, download_export

    outcome.name, outcome.version = args.name, args.bundle_version
    inputs = check_locally(args)
    if not args.key:
        raise ClientError("no API key: pass --key or set CROWDBAKE_API_KEY", Exit.AUTH, local_problem("no API key", "Missing API key"))
    headers = {"Authorization": f"Bearer {args.key}"}
    with httpx.Client(base_url=args.server.rstrip("/"), headers=headers, timeout=httpx.Timeout(60.0, read=600.0)) as client:
        server = Server(client, retry_for=args.retry_for, say=say)
        try:
            check_service_root(server)
            preflight(server, args, inputs)
            check_name_and_version(server, args.name, args.bundle_version, local_inputs(inputs), inputs.params, args.created, not args.no_publish)
            character = upload(server, "/v1/assets/characters", {"file": inputs.character}, f"character {inputs.character.name}", say)
            cloth = None
            if inputs.cloth_files:
                cloth_name = next(iter(inputs.cloth_files.values())).name
                cloth = upload(server, "/v1/assets/cloth", inputs.cloth_files, f"cloth {cloth_name}", say, inputs.cloth_data)["id"]
            textures = {name: upload(server, "/v1/assets/textures", {"file": path}, f"texture {name}", say)["id"] for name, path in inputs.textures.items()}
            cycle = upload(server, "/v1/assets/cycles", inputs.cycle_files, f"cycle {inputs.cycle_files['cycle'].name}", say)["id"] if inputs.cycle_files else None
            timeline = (upload(server, "/v1/assets/timelines", {"timeline": inputs.timeline}, f"timeline {inputs.timeline.name}", say)["id"]
                        if inputs.timeline is not None else None)
            clip_cloth = [(clip, upload(server, "/v1/assets/cloth", files, f"cloth of {clip}", say)["id"]) for clip, files in inputs.clip_cloth]
            assets = BakeInputSet(character=character["id"], cloth=cloth, cycle=cycle, timeline=timeline, textures=textures, clip_cloth=clip_cloth)
            body = bake_body(args, inputs, assets)
            response = server.request("POST", "/v1/bakes", "starting the bake", json=body)
            bake = response.json()
            outcome.bake_id, outcome.state, outcome.progress = bake["id"], bake["state"], bake["progress"]
            reused = " (same inputs as an earlier bake: reusing it)" if response.status_code == 200 else ""
            say(f"bake {bake['id']} {bake['state']}{reused}")
            out(bake["id"])
            if not (args.wait or args.download or args.export_out):
                return
            bake = follow(server, bake["id"], args.poll, args.timeout, Reporter(bake["id"], stream=sys.stderr), outcome)
            if bake["state"] != "succeeded":
                raise ClientError(bake_error_line(bake), Exit.BAKE_FAILED, bake_problem(bake))
            seconds = ", ".join(f"{stage['stage']} {stage['seconds']:.1f} s" for stage in bake["stages"] if stage.get("seconds") is not None)
            say(f"bake {bake['id']} succeeded ({seconds})")
            if args.download:
                folder, verified = download_bundle(server, args.name, args.bundle_version, Path(args.download))
                outcome.bundle, outcome.verified = str(folder), verified
                say(f"bundle verified ({verified}): {folder}")
                out(str(folder))
            if args.export_out:
                folder = download_export(server, args.name, args.bundle_version, Path(args.export_out))
                say(f"engine export: {folder}")
                out(str(folder))
        finally:
            outcome.retries = server.retries


def run(args: argparse.Namespace) -> int:
    """Run the command; prints the JSON result with --json; returns the exit code (never raises ClientError)."""
    outcome = Outcome()

    def say(line: str) -> None:
        print(line, file=sys.stderr, flush=True)

    def out(line: str) -> None:
        if not args.json:
            print(line, flush=True)

    try:
        submit(args, outcome, say, out)
    except ClientError as error:
        print(f"crowdbake submit: error: {error}", file=sys.stderr, flush=True)
        outcome.exit_code = int(error.exit_code)
        outcome.problem = error.problem or local_problem(str(error), "Error")
    except KeyboardInterrupt:
        print("crowdbake submit: interrupted", file=sys.stderr, flush=True)
        outcome.exit_code = 130
        outcome.problem = local_problem("interrupted", "Interrupted")
    if args.json:
        print(json.dumps(outcome.as_dict()), flush=True)
    return outcome.exit_code


def main(argv: list[str] | None = None) -> int:
    """`crowdbake-submit`: the submit command of the client distribution."""
    parser = build_parser(argv=argv)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
