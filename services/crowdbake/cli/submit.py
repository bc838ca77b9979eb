"""`crowdbake submit`: upload a character and its cloth to a crowdbake server, bake, follow, download.

Made for CI pipelines: progress goes to stderr (a bar on a terminal, plain lines otherwise), the bake id
and the downloaded bundle's folder go to stdout, and any failure is one line and a non-zero exit.
"""
from __future__ import annotations

import argparse
import hashlib
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from crowdbake.cli.common import CommandError, progress
from crowdbake.errors import InputError
from crowdbake.params import add_cli_options, option_for, params_from_args

DESCRIPTION = """\
Uploads CHAR.glb, the cloth (a PC2 cache with --cloth-mesh, or a zip of OBJ frames) and the textures
(--textures DIR: diffuse_*.png and outfits.png), starts a bake of NAME/VERSION and prints its id.
With --wait, follows it until it ends (non-zero exit with the bake's error if it fails); with
--download DIR, also fetches the published bundle to DIR/NAME/VERSION, checks every sha256 while
downloading and verifies the whole bundle (crowdbake.formats.bundle.verify_bundle).

The key comes from --key or CROWDBAKE_API_KEY (better in CI: it stays out of the process list)."""

# Exit codes: 2 usage or request errors (CommandError's default), 1 the bake itself failed.
EXIT_BAKE_FAILED = 1
CHUNK = 1 << 20


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("submit", help="upload, bake on a server, follow and download (for CI)",
                                   description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("character", metavar="CHAR.glb", help="the skinned, animated character (.glb or .gltf)")
    parser.add_argument("--server", required=True, metavar="URL", help="the crowdbake server, e.g. http://127.0.0.1:8000")
    parser.add_argument("--key", metavar="KEY", default=os.environ.get("CROWDBAKE_API_KEY"), help="API key (default CROWDBAKE_API_KEY)")
    parser.add_argument("--cloth", required=True, metavar="CLOTH.pc2", help="the cloth cache (.pc2 with --cloth-mesh, or a .zip of OBJ frames)")
    parser.add_argument("--cloth-mesh", metavar="CLOTH.obj", help="the cloth's rest mesh (OBJ, PC2 point order)")
    parser.add_argument("--textures", metavar="DIR", help="folder with diffuse_*.png and outfits.png")
    parser.add_argument("--name", required=True, help="bundle name ([a-z0-9._-])")
    parser.add_argument("--version", required=True, dest="bundle_version", metavar="VERSION", help="bundle version; a published version never changes")
    parser.add_argument("--wait", action="store_true", help="follow the bake until it ends")
    parser.add_argument("--download", metavar="DIR", help="download and verify the bundle into DIR/NAME/VERSION (implies --wait)")
    parser.add_argument("--no-publish", action="store_true", help="bake without publishing (publish later with the API)")
    parser.add_argument("--public", action="store_true", help="make the bundle readable without a key")
    params = parser.add_argument_group("bake parameters (server defaults when omitted)")
    add_cli_options(params, server_defaults=True)
    parser.add_argument("--poll", type=float, default=1.0, metavar="S", help="seconds between status checks (default 1)")
    parser.add_argument("--timeout", type=float, default=3600.0, metavar="S", help="give up waiting after S seconds (default 3600)")
    parser.set_defaults(func=run)


# ------------------------------------------------------------------------------------------- HTTP


def problem_line(response) -> str:
    """One line from an error response: the problem's title and detail and its first error entry."""
    try:
        body = response.json()
    except ValueError:
        return f"HTTP {response.status_code}: {response.text.strip()[:200]}"
    if not isinstance(body, dict):
        return f"HTTP {response.status_code}"
    line = f"{body.get('title', 'HTTP ' + str(response.status_code))}: {body.get('detail', '')}".rstrip(": ")
    errors = body.get("errors") or []
    if errors:
        first = errors[0]
        where = " ".join(str(first[key]) for key in ("file", "where") if first.get(key))
        line += f" [{first.get('field', '?')}{' ' + where if where else ''}: {first.get('message', '')}]"
        if len(errors) > 1:
            line += f" (+{len(errors) - 1} more)"
    return line


def _check(response, what: str):
    if response.status_code >= 400:
        raise CommandError(f"{what}: {problem_line(response)}")
    return response


def _upload(client, endpoint: str, files: dict[str, Path], what: str, data: dict[str, str] | None = None) -> dict[str, Any]:
    handles = {field: open(path, "rb") for field, path in files.items()}
    try:
        response = client.post(endpoint, files={field: (Path(path).name, handles[field]) for field, path in files.items()}, data=data or {})
    finally:
        for handle in handles.values():
            handle.close()
    asset = _check(response, f"uploading {what}").json()
    state = "stored" if response.status_code == 201 else "already stored"
    print(f"{what}: {asset['id']} ({state}, sha256 {asset['digest'][:12]})", file=sys.stderr)
    return asset


def _params(args: argparse.Namespace) -> dict[str, Any]:
    """The bake parameters given on the command line (crowdbake.params); the server fills in the rest."""
    try:
        return params_from_args(args, given_only=True)
    except InputError as error:
        raise CommandError(f"{option_for(error.field)}: {error.message.split(': ', 1)[-1]}") from None


def _texture_files(folder: str | None) -> dict[str, Path]:
    if not folder:
        return {}
    root = Path(folder)
    if not root.is_dir():
        raise CommandError(f"--textures {folder}: not a folder")
    files = {path.name: path for path in sorted(root.glob("*.png")) if path.name.startswith("diffuse_") or path.name == "outfits.png"}
    if not any(name.startswith("diffuse_") for name in files):
        raise CommandError(f"--textures {folder}: no diffuse_*.png in the folder")
    return files


# ---------------------------------------------------------------------------------------- follow


def follow(client, bake_id: str, poll: float, timeout: float) -> dict[str, Any]:
    """Poll the bake until it ends; a progress bar on a terminal, else a line per change on stderr."""
    deadline = time.monotonic() + timeout
    last_line = ""
    interactive = sys.stderr.isatty()
    with progress(100, f"bake {bake_id}") as bar:
        while True:
            bake = _check(client.get(f"/v1/bakes/{bake_id}"), f"following bake {bake_id}").json()
            running = [stage for stage in bake["stages"] if stage["state"] in ("running", "retrying")]
            where = ", ".join(f"{stage['stage']} {stage['done']}/{stage['total']}" if stage["total"] else stage["stage"] for stage in running)
            percent = int(round(100 * bake["progress"]))
            if interactive:
                bar.set_description(f"bake {bake['state']}{': ' + where if where else ''}")
                bar.update(percent - bar.n)
            else:
                line = f"bake {bake_id}: {bake['state']} {percent}%{' (' + where + ')' if where else ''}"
                if line != last_line:
                    print(line, file=sys.stderr, flush=True)
                    last_line = line
            if bake["state"] in ("succeeded", "failed", "cancelled"):
                return bake
            if time.monotonic() > deadline:
                raise CommandError(f"bake {bake_id} still {bake['state']} after {timeout:.0f} s (it keeps running on the server)")
            time.sleep(poll)


def bake_error_line(bake: dict[str, Any]) -> str:
    error = bake.get("error") or {}
    if bake["state"] == "cancelled":
        return f"bake {bake['id']} was cancelled"
    field = f" [{error['field']}]" if error.get("field") else ""
    return f"bake {bake['id']} failed in {error.get('stage', '?')}: {error.get('title', 'error')}: {error.get('detail', '')}{field}"


# -------------------------------------------------------------------------------------- download


def _fetch(client, url: str, target: Path, sha256: str | None, what: str) -> str:
    """Stream `url` to `target`, hashing; refuse it when `sha256` is given and differs."""
    digest = hashlib.sha256()
    target.parent.mkdir(parents=True, exist_ok=True)
    with client.stream("GET", url) as response:
        if response.status_code >= 400:
            response.read()
            raise CommandError(f"downloading {what}: {problem_line(response)}")
        with open(target, "wb") as handle:
            for chunk in response.iter_bytes(CHUNK):
                digest.update(chunk)
                handle.write(chunk)
    actual = digest.hexdigest()
    if sha256 is not None and actual != sha256:
        raise CommandError(f"downloading {what}: sha256 {actual} differs from the manifest's {sha256}")
    return actual


def download_bundle(client, name: str, version: str, out_root: Path) -> Path:
    """Download name/version into out_root/name/version (atomically: a temp folder, then a rename)
    and verify it; an identical bundle already there is kept."""
    import json

    from crowdbake.formats.bundle import check_path, verify_bundle
    from crowdbake.formats.errors import FormatError

    destination = out_root / name / version
    destination.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{version}.", dir=destination.parent))
    try:
        base = f"/v1/bundles/{name}/{version}"
        _fetch(client, f"{base}/manifest.json", staging / "manifest.json", None, "manifest.json")
        manifest = json.loads((staging / "manifest.json").read_bytes())
        entries = manifest.get("files", [])
        with progress(len(entries), f"download {name}/{version}") as bar:
            for entry in entries:
                try:
                    check_path(entry["path"])
                except FormatError as error:
                    raise CommandError(f"the manifest lists an unsafe path: {error}") from None
                _fetch(client, f"{base}/files/{entry['path']}", staging / entry["path"], entry["sha256"], entry["path"])
                bar.update(1)
        try:
            verify_bundle(staging)
        except FormatError as error:
            raise CommandError(f"the downloaded bundle does not verify: {error}") from None
        if destination.exists():
            if (destination / "manifest.json").read_bytes() == (staging / "manifest.json").read_bytes():
                verify_bundle(destination)
                shutil.rmtree(staging)
                return destination
            raise CommandError(f"{destination} already holds another bundle; remove it or choose another --download folder")
        os.rename(staging, destination)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return destination


# ------------------------------------------------------------------------------------------- main


def run(args: argparse.Namespace) -> int:
    import httpx

    if not args.key:
        raise CommandError("no API key: pass --key or set CROWDBAKE_API_KEY")
    character = Path(args.character)
    cloth = Path(args.cloth)
    for path in (character, cloth, *([Path(args.cloth_mesh)] if args.cloth_mesh else [])):
        if not path.is_file():
            raise CommandError(f"{path}: no such file")
    is_sequence = cloth.suffix.lower() == ".zip"
    if not is_sequence and not args.cloth_mesh:
        raise CommandError("--cloth CLOTH.pc2 needs --cloth-mesh CLOTH.obj (or give a .zip of OBJ frames)")
    textures = _texture_files(args.textures)
    params = _params(args)

    headers = {"Authorization": f"Bearer {args.key}"}
    timeout = httpx.Timeout(60.0, read=600.0)
    try:
        with httpx.Client(base_url=args.server.rstrip("/"), headers=headers, timeout=timeout) as client:
            character_asset = _upload(client, "/v1/assets/characters", {"file": character}, f"character {character.name}")
            cloth_files = {"sequence": cloth} if is_sequence else {"cache": cloth, "mesh": Path(args.cloth_mesh)}
            cloth_data = {"cycle_frames": str(args.cycle_frames)} if args.cycle_frames else None
            cloth_asset = _upload(client, "/v1/assets/cloth", cloth_files, f"cloth {cloth.name}", cloth_data)
            texture_ids = {name: _upload(client, "/v1/assets/textures", {"file": path}, f"texture {name}")["id"] for name, path in textures.items()}

            body = {
                "name": args.name, "version": args.bundle_version, "character": character_asset["id"], "cloth": cloth_asset["id"],
                "textures": texture_ids, "params": params, "publish": not args.no_publish, "public": args.public,
            }
            response = _check(client.post("/v1/bakes", json=body), "starting the bake")
            bake = response.json()
            reused = " (same inputs as an earlier bake: reusing it)" if response.status_code == 200 else ""
            print(f"bake {bake['id']} {bake['state']}{reused}", file=sys.stderr)
            print(bake["id"], flush=True)

            if not (args.wait or args.download):
                return 0
            bake = follow(client, bake["id"], args.poll, args.timeout)
            if bake["state"] != "succeeded":
                raise CommandError(bake_error_line(bake), exit_code=EXIT_BAKE_FAILED)
            seconds = ", ".join(f"{stage['stage']} {stage['seconds']:.1f} s" for stage in bake["stages"] if stage.get("seconds") is not None)
            print(f"bake {bake['id']} succeeded ({seconds})", file=sys.stderr)
            if args.download:
                if args.no_publish:
                    raise CommandError("--download needs a published bundle; drop --no-publish")
                folder = download_bundle(client, args.name, args.bundle_version, Path(args.download))
                print(f"bundle verified: {folder}", file=sys.stderr)
                print(folder, flush=True)
    except httpx.HTTPError as error:
        raise CommandError(f"cannot reach {args.server}: {type(error).__name__}: {error}") from None
    return 0
