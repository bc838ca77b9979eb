"""Stage 2a, loops: one clip's loop per item, so that a bake of several clips searches them side by side
(the local runner's worker processes, the service's workers). The cycle stage (crowdbake.stages.cycle)
then joins them: it reads every clip's loop, finds the transitions (they need both loops) and writes
cycle.json and the report as a search of every clip in one go would.

    loop_items(work) -> [{"id": "0-idle", "clip": "Idle"}, ...]    # none for a bake of one clip
    stage_clip_loop(work, item) -> work/cycle/loops/<id>.npz       # + <id>.json: its key and the result's tree
    load_clip_loops(work) -> [ClipLoop, ...]                       # in the timeline's order

A bake of one clip (no timeline), of a given cycle.json or of the body alone has no items: its cycle
stage does the whole search, as there is nothing to search side by side. Each item runs
crowdbake.bake.clips.find_clip_loop on exactly the inputs the cycle job (crowdbake.stages.cycle_job)
searches every clip of (crowdbake.stages.cycle_inputs), so the joined outputs are the same bytes.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from crowdbake.bake.clips import ClipLoop
from crowdbake.errors import InputError, StageOrderError
from crowdbake.stages.cycle_job import file_stem
from crowdbake.stages.result_files import from_tree, to_tree
from crowdbake.stages.workdir import WorkDir, npz_bytes, read_json, stage_key, write_bytes_atomic, write_json_atomic

LOOPS_FOLDER = "cycle/loops"


def loop_items(work: Path) -> list[dict]:
    """One item per clip of the bake's timeline, in its order ({"id", "clip"}; the id, a file stem, starts
    with the clip's position so that two clips whose names differ only in case stay apart); none for a
    bake without a timeline."""
    from crowdbake.ingest.timeline import read_timeline
    from crowdbake.stages.validate import load_job

    folder = WorkDir(work)
    names = load_job(work).inputs
    if "timeline" not in names or "cloth" not in names or "cycle" in names:
        return []
    clips = read_timeline(folder.inputs / names["timeline"]).clips()
    return [{"id": f"{k}-{file_stem(clip)}", "clip": clip} for k, clip in enumerate(clips)]


def item_files(item: dict) -> tuple[str, str]:
    """The files an item writes under the work folder: its arrays, then its JSON (key and tree; written last)."""
    return f"{LOOPS_FOLDER}/{item['id']}.npz", f"{LOOPS_FOLDER}/{item['id']}.json"


def loop_key(work: Path, item: dict) -> str:
    """What decides an item's loop: the checked job (the validate stage's key) and the clip."""
    return stage_key("clip-loop", WorkDir(work).key_of("validate"), item["clip"])


def stage_clip_loop(work: Path, item: dict) -> Path:
    """Search the loop of item["clip"] (pass 1, pass 2, closing, quality) and store it; returns its .npz.
    Kept when the stored one has this item's key. InputError("cloth") when the clip holds no loop."""
    from crowdbake.bake.clips import find_clip_loop
    from crowdbake.bake.cycle import CycleParams
    from crowdbake.render.cloth_views import ClothViewRenderer
    from crowdbake.stages.cycle_inputs import load_cycle_inputs
    from crowdbake.stages.validate import load_job

    work = Path(work)
    arrays_path, json_path = (work / name for name in item_files(item))
    key = loop_key(work, item)
    if arrays_path.is_file() and json_path.is_file() and read_json(json_path).get("key") == key:
        return arrays_path
    started = time.perf_counter()
    job, inputs = load_job(work), WorkDir(work).inputs
    names, params = job.inputs, job.bake_params
    cycle_params = CycleParams(max_candidates=params.candidates, views=params.cycle_views, close=params.close)
    character = inputs / names["character"]
    try:
        # As crowdbake.stages.cycle_job.run_cycle_job reads them for every clip, the body posed for this clip alone.
        loaded = load_cycle_inputs(inputs / names["cloth"], inputs / names["cloth_mesh"], character, fps=job.fps,
                                   animation=params.animation, timeline=inputs / names["timeline"], clip=item["clip"])
        render_views = ClothViewRenderer(loaded.cloth_faces, loaded.body_faces, cycle_params.views, cycle_params.image_size,
                                         cycle_params.elevation_deg)
        loop = find_clip_loop(np.asarray(loaded.cloth), loaded.cloth_faces, loaded.timeline, item["clip"], cycle_params, render_views,
                              loaded.body, loaded.body_faces, loaded.body_normals)
    except ValueError as error:
        raise InputError(f"cycle search: {error}", "cloth") from None
    tree, arrays = to_tree(loop)
    write_bytes_atomic(arrays_path, npz_bytes(arrays))
    write_json_atomic(json_path, {"key": key, "clip": item["clip"], "seconds": time.perf_counter() - started, "loop": tree})
    return arrays_path


def load_clip_loops(work: Path) -> list[ClipLoop]:
    """Every item's loop, in the timeline's order; StageOrderError naming the clip whose loop the loops
    stage has not stored."""
    loops = []
    for item in loop_items(work):
        arrays_path, json_path = (Path(work) / name for name in item_files(item))
        if not (arrays_path.is_file() and json_path.is_file()):
            raise StageOrderError(f"{work}: the loops stage has not stored the loop of clip {item['clip']!r} ({json_path.name})")
        document = json.loads(json_path.read_text(encoding="utf-8"))
        with np.load(arrays_path, allow_pickle=False) as data:
            arrays = {name: data[name] for name in data.files}
        loops.append(from_tree(document["loop"], arrays))
    return loops
