"""A bake's inputs for its stages: the input blobs linked into the work folder, and the BakeInputs the
validate stage reads."""
from __future__ import annotations

import shutil
from pathlib import Path, PurePosixPath

from sqlalchemy.orm import Session

from crowdbake.errors import InputError
from crowdbake.params import BakeParams
from crowdbake.storage import records
from crowdbake.storage.blobs import BlobStore
from crowdbake.storage.models import Asset, Bake


def materialize_inputs(blobs: BlobStore, work: Path, bake: Bake, session: Session):
    """Link the bake's input blobs into work/sources and build the stages' BakeInputs.

    Not work/inputs: stage_validate copies its inputs there and clears that folder first. The manifest's
    `created` is the time the newest input was uploaded (`inputs_created`): a property of the inputs
    that every machine reads alike from the database (a file's modification time would be the time a
    machine downloaded it), so every attempt of a bake, wherever it runs, produces the same bytes. A `created` given with the
    bake request (`bake.inputs["created"]`) wins over both."""
    from crowdbake.stages.validate import BakeInputs  # the stages' imports are heavy: only where a stage runs

    inputs_dir = work / "sources"
    if inputs_dir.exists():
        shutil.rmtree(inputs_dir)
    character = session.get(Asset, bake.inputs["character"])
    cloth = session.get(Asset, bake.inputs["cloth"]) if bake.inputs.get("cloth") else None  # none: the body alone
    if character is None or (cloth is None and bake.inputs.get("cloth")):
        raise InputError("an input asset no longer exists", "character" if character is None else "cloth")
    character_path = blobs.materialize(character.files["file"]["sha256"], inputs_dir / f"character.{character.info.get('format', 'glb')}")
    cloth_path = mesh_path = None
    if cloth is not None:
        # The cache keeps its format's extension (.pc2, .mdd, .abc): the validate stage reads it by extension.
        cache_suffix = PurePosixPath(cloth.files["cache"].get("filename") or "cloth.pc2").suffix.lower() or ".pc2"
        cloth_path = blobs.materialize(cloth.files["cache"]["sha256"], inputs_dir / f"cloth{cache_suffix}")
        mesh_path = blobs.materialize(cloth.files["mesh"]["sha256"], inputs_dir / "cloth.obj") if "mesh" in cloth.files else None
    textures_dir = None
    assets = [character] + ([cloth] if cloth is not None else [])
    if bake.inputs.get("textures"):
        textures_dir = inputs_dir / "textures"
        for name, asset_id in sorted(bake.inputs["textures"].items()):
            texture = session.get(Asset, asset_id)
            if texture is None:
                raise InputError(f"texture {name} no longer exists", f"textures.{name}")
            blobs.materialize(texture.files["file"]["sha256"], textures_dir / name)
            assets.append(texture)
    cycle_path = None
    if bake.inputs.get("cycle"):
        cycle = session.get(Asset, bake.inputs["cycle"])
        if cycle is None:
            raise InputError("the cycle asset no longer exists", "cycle")
        # looped.pc2 beside cycle.json: the validate stage takes it from there, as for `crowdbake bake --cycle`.
        cycle_path = blobs.materialize(cycle.files["file"]["sha256"], inputs_dir / "cycle" / "cycle.json")
        if "looped" in cycle.files:
            blobs.materialize(cycle.files["looped"]["sha256"], inputs_dir / "cycle" / "looped.pc2")
        assets.append(cycle)
    timeline_path = None
    if bake.inputs.get("timeline"):
        timeline = session.get(Asset, bake.inputs["timeline"])
        if timeline is None:
            raise InputError("the timeline asset no longer exists", "timeline")
        timeline_path = blobs.materialize(timeline.files["file"]["sha256"], inputs_dir / "timeline.json")
        assets.append(timeline)
    if bake.inputs.get("clip_cloth"):  # one cache per clip: joined into one cache and its timeline, as `crowdbake bake --clip-cloth`
        cloth_path, mesh_path, timeline_path = _join_clip_cloth(blobs, session, bake, inputs_dir, character_path, assets)
    return BakeInputs(
        character=character_path, cloth=cloth_path, cloth_mesh=mesh_path, textures=textures_dir, cycle=cycle_path,
        name=bake.name, version=bake.version, params=BakeParams.from_dict(bake.params),
        created=bake.inputs.get("created") or inputs_created(assets), timeline=timeline_path,
    )


def _join_clip_cloth(blobs: BlobStore, session: Session, bake: Bake, inputs_dir: Path, character_path: Path, assets: list[Asset]):
    """Every clip's cloth asset linked under inputs_dir/clips/K, joined (crowdbake.ingest.clip_caches) into
    inputs_dir/joined: (cloth.pc2, cloth.obj, timeline.json). InputError("clip_cloth") as the CLI's."""
    from crowdbake.ingest.clip_caches import ClipCloth, write_joined_inputs

    entries = []
    for k, (clip, asset_id) in enumerate(bake.inputs["clip_cloth"]):
        cloth = session.get(Asset, asset_id)
        if cloth is None:
            raise InputError(f"the cloth asset of clip {clip!r} no longer exists", "clip_cloth")
        suffix = PurePosixPath(cloth.files["cache"].get("filename") or "cloth.pc2").suffix.lower() or ".pc2"
        cache = blobs.materialize(cloth.files["cache"]["sha256"], inputs_dir / "clips" / str(k) / f"cloth{suffix}")
        mesh = blobs.materialize(cloth.files["mesh"]["sha256"], inputs_dir / "clips" / str(k) / "cloth.obj") if "mesh" in cloth.files else None
        entries.append(ClipCloth(clip, cache, mesh))
        assets.append(cloth)
    return write_joined_inputs(entries, character_path, (bake.params or {}).get("fps"), inputs_dir / "joined")


def inputs_created(assets: list[Asset]) -> str:
    """RFC 3339 UTC time (whole seconds) the newest of `assets` was uploaded: the bundle's `created`."""
    newest = max(records.to_utc(asset.created_at) for asset in assets)
    return newest.strftime("%Y-%m-%dT%H:%M:%SZ")
