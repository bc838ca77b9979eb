"""Checks `crowdbake submit` makes before uploading anything: the character is what its name says, and
NAME/VERSION is not already published from other inputs (bundles never change, so the server would
refuse the bake with a 409, but only after every upload).

The server answers the second itself (POST /v1/bakes/check: the sha256 of each local file, the
parameters and the manifest time in, 204 or the 409 out), whoever published the version. Against a
server without that endpoint the client reads what its key can (below), which cannot see a version
another workspace published.

A published version is baked again only as a reuse: the same key's bake of the same bytes, parameters
and manifest time (crowdbake.api.routes.bakes.create_bake). So the check reads the bundle
(GET /v1/bundles/{name}/{version}), the bake that published it (GET /v1/bakes/{id}) and its input
assets (GET /v1/assets/{id}), and compares their sha256 and parameters with the local files and options.
Any difference, or a publisher this key cannot read, is the 409 the server would give, told now."""
from __future__ import annotations

from pathlib import Path
from typing import Any

from crowdbake.client.http import ClientError, Exit, Server
from crowdbake.files import sha256_file
from crowdbake.ingest.input_modes import BakeInputSet

GLB_MAGIC = b"glTF"  # the first 4 bytes of every glTF binary (glTF 2.0 spec, "GLB File Format Specification")


def check_glb_magic(path: Path) -> str | None:
    """Why `path`, named .glb, is not a glTF binary, or None when it starts as one."""
    if path.suffix.lower() != ".glb":
        return None
    with open(path, "rb") as handle:
        head = handle.read(4)
    if head == GLB_MAGIC:
        return None
    return f"{path}: not a glTF binary (a .glb starts with the bytes 'glTF'; this file starts with {head!r})"


def _asset_digests(asset: dict[str, Any]) -> set[str]:
    """Every sha256 an asset carries: its digest, its stored files, the source it was converted from."""
    found = {asset.get("digest")} | {entry.get("sha256") for entry in (asset.get("files") or {}).values()}
    found.add(((asset.get("info") or {}).get("source") or {}).get("sha256"))
    return {value for value in found if value}


def published_difference(server: Server, name: str, version: str, local: dict[str, list[Path]], params: dict[str, Any],
                         created: str | None) -> str | None:
    """What differs between this submit and the bake that published name/version, or None when the version
    is not published or the submit would reuse that bake. `local`: input role ("character", "cloth",
    "cycle", "timeline", "textures.NAME", "clip_cloth.K") -> its local files."""
    bundle = server.request("GET", f"/v1/bundles/{name}/{version}", f"checking whether {name}/{version} is published",
                            accept=frozenset({403, 404}))
    if bundle.status_code in (403, 404):
        return None  # not published (or not readable with this key: then not this key's to reuse either)
    bake_id = bundle.json().get("bake_id")
    if not bake_id:
        return "it was published without a bake on this server"
    bake = server.request("GET", f"/v1/bakes/{bake_id}", f"reading bake {bake_id}", accept=frozenset({403, 404}))
    if bake.status_code != 200:
        return f"bake {bake_id} published it, from inputs this key cannot reuse"
    record = bake.json()
    inputs = record.get("inputs", {})
    published = BakeInputSet.from_record(inputs).roles()
    for role in sorted(set(published) | set(local)):
        if role not in local or role not in published:
            return f"{role} is {'not ' if role not in local else ''}among its inputs"
        asset = server.request("GET", f"/v1/assets/{published[role]}", f"reading asset {published[role]}", accept=frozenset({403, 404}))
        if asset.status_code != 200:
            return f"its {role} is an asset this key cannot read"
        known = _asset_digests(asset.json())
        for path in local[role]:
            if sha256_file(path) not in known:
                return f"{path.name} differs from its {role}"
    defaults = _server_defaults(server)
    for parameter, value in sorted(record.get("params", {}).items()):
        wanted = params.get(parameter, defaults.get(parameter, value))
        if wanted != value:
            return f"parameter {parameter} was {value!r}, this bake asks for {wanted!r}"
    if created != inputs.get("created"):
        return f"its manifest time was {inputs.get('created') or 'the default'}, this bake asks for {created or 'the default'}"
    return None


def _server_defaults(server: Server) -> dict[str, Any]:
    """The server's parameter defaults (GET /v1/params); none from a server without that endpoint."""
    response = server.request("GET", "/v1/params", "reading the server's parameter defaults", accept=frozenset({404}))
    return {} if response.status_code == 404 else {item["name"]: item["default"] for item in response.json()}


def check_name_and_version(server: Server, name: str, version: str, local: dict[str, list[Path]], params: dict[str, Any],
                           created: str | None, publish: bool = True) -> None:
    """Raise the server's 409 (Exit.REJECTED) when name/version is already published (or being baked)
    from other inputs, before anything is uploaded. `local`: input role -> its local files."""
    body = {"name": name, "version": version, "inputs": {role: [sha256_file(path) for path in paths] for role, paths in local.items()},
            "params": params, "publish": publish, **({"created": created} if created else {})}
    response = server.request("POST", "/v1/bakes/check", f"checking whether {name}/{version} is free", json=body,
                              accept=frozenset({404, 405}))
    if response.status_code in (404, 405):  # a server that predates the check: read what this key can
        check_not_published_otherwise(server, name, version, local, params, created)


def check_not_published_otherwise(server: Server, name: str, version: str, local: dict[str, list[Path]], params: dict[str, Any],
                                  created: str | None) -> None:
    difference = published_difference(server, name, version, local, params, created)
    if difference is not None:
        message = f"{name}/{version} is already published from other inputs ({difference}); bundles never change, choose a new version"
        raise ClientError(message, Exit.REJECTED, {"type": "about:blank", "title": "Conflict", "status": 409, "detail": message})
