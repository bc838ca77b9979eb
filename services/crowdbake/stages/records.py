"""The typed records the stages hand each other through the work folder.

Each stage reads the record of the stage before it and writes its own (work/<stage>/record.json, see
crowdbake.stages.workdir). A record is a dataclass with to_json/from_json; its JSON carries
`record_version`, and reading a record of another version fails loudly (StageOrderError: rerun the
stage) instead of being half understood. Progress is not part of any record: it goes to the callback.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields
from typing import Any, ClassVar

from crowdbake.bake.atlas import AtlasLayout
from crowdbake.formats.ranges import Ranges, read_ranges
from crowdbake.errors import StageOrderError
from crowdbake.params import BakeParams


def ranges_of(sections: dict[str, Any]) -> Ranges:
    """Ranges from a record's v2 sections (pose_frames, clips, transitions), checked as a reader checks them."""
    return read_ranges({"format_version": 2, **sections})


class Record:
    """to_json/from_json for flat dataclasses; nested ones override `_nested`."""

    RECORD_VERSION: ClassVar[int] = 1
    _nested: ClassVar[dict[str, type]] = {}

    def to_json(self) -> dict[str, Any]:
        data = asdict(self)  # type: ignore[call-overload]
        data["record_version"] = self.RECORD_VERSION
        return data

    @classmethod
    def from_json(cls, data: dict[str, Any]):
        if not isinstance(data, dict):
            raise StageOrderError(f"{cls.__name__}: not a JSON object")
        version = data.get("record_version", cls.RECORD_VERSION)
        if version != cls.RECORD_VERSION:
            raise StageOrderError(f"{cls.__name__} has record version {version}, this code reads {cls.RECORD_VERSION}: rerun the stage")
        names = {f.name for f in fields(cls)}  # type: ignore[arg-type]
        values = {k: v for k, v in data.items() if k in names}
        for name, item_type in cls._nested.items():
            if name in values:
                values[name] = [item_type.from_json(item) for item in values[name]]
        return cls(**values)


@dataclass
class JobRecord(Record):
    """validate → every later stage: the checked job (the inputs as copied into work/inputs)."""

    key: str
    name: str
    version: str
    created: str
    created_from: str
    params: dict[str, Any]
    inputs: dict[str, str]  # role -> path under work/inputs (character, cloth, cloth_mesh, cycle, cycle_looped, textures)
    hashes: dict[str, str]
    garment_part: str
    textures: dict[str, Any] | None
    producer: str
    body_vertices: int
    body_triangles: int
    garment_vertices: int
    garment_triangles: int
    cache_frames: int
    cycle_frames: int
    # The cloth cache's frame rate (crowdbake.params.cache_fps) and the format it came in; a record
    # without them reads as None/"pc2".
    fps: float | None = None
    cloth_format: str = "pc2"
    # The animation the bake picked when not told (crowdbake.ingest.clip_choice.ClipChoice: index, name,
    # frames, reason); None when `animation` was given or the character has one.
    animation_choice: dict[str, Any] | None = None

    @property
    def bake_params(self) -> BakeParams:
        return BakeParams.from_dict(self.params)


@dataclass
class CycleRecord(Record):
    """cycle → poses, pack: the chosen cycle [start_frame, end_frame) of the source cache and its seam.
    The looped cache (exactly cycle_frames frames, frame 0 = start_frame) is work/cycle/looped.pc2."""

    start_frame: int
    end_frame: int
    cycle_frames: int
    closing: str
    position_jump_ratio: float | None
    velocity_jump_ratio: float | None
    fps: float
    root_motion_removed: bool
    # Where the cycle came from: "search" (the cloth's, paper section 3), "given" (a cycle.json), or
    # crowdbake.stages.body_only.ANIMATION_LOOP (no cloth: the animation's own loop).
    source: str = "search"
    # Several clips (crowdbake.stages.cycle_job): the clip frame at start_frame, where the body's pose
    # starts (the cache frame number is not the clip's time); None: frame f is at time f / fps.
    clip_phase: int | None = None
    # A bundle of several clips (format v2; crowdbake.stages.cycle_job.bundle_ranges): pose_frames, the
    # manifest's clips and transitions, clip_phases (per clip) and the pose-frame cloth's file under
    # work/cycle. None: one clip, the cycle above is the bundle's (v1).
    ranges: dict[str, Any] | None = None

    def bundle_ranges(self) -> Ranges | None:
        """The clips and transitions of a several-clip bundle (crowdbake.formats.ranges), None for one clip."""
        return None if self.ranges is None else ranges_of(self.ranges)

    @property
    def pose_frames(self) -> int:
        """Frames of every pose cache: the cycle's, or every clip's and transition's together."""
        return self.cycle_frames if self.ranges is None else int(self.ranges["pose_frames"])


@dataclass
class PosePart(Record):
    """One pose cache the poses stage wrote (work/poses/<file>); low LODs carry the simplifier's figures."""

    part: str
    kind: str
    lod: int
    file: str
    material: int
    vertex_count: int
    triangle_count: int
    target_triangles: int | None = None
    relative_error: float | None = None
    locked_border: bool | None = None


@dataclass
class MaterialInfo(Record):
    """A material's diffuse texture array as baked (the layers are in work/poses/textures.npz)."""

    name: str
    variations: int
    width: int
    height: int
    pixel_format: str


@dataclass
class TexturesRecord(Record):
    """The poses stage's textures (work/poses/textures.npz), written as soon as the job is validated: the
    materials' diffuse arrays as baked and the outfit map's size."""

    materials: list[MaterialInfo]
    outfit_count: int

    _nested: ClassVar[dict[str, type]] = {"materials": MaterialInfo}


@dataclass
class PoseCachesRecord(Record):
    """pose caches → poses: the parts and materials the pose caches stage wrote, before the impostor framing."""

    frames_per_second: float
    cycle_frames: int
    parts: list[PosePart]
    materials: list[MaterialInfo]
    outfit_count: int
    ranges: dict[str, Any] | None = None
    _nested: ClassVar[dict[str, type]] = {"parts": PosePart, "materials": MaterialInfo}


@dataclass
class PosesRecord(Record):
    """poses → impostors, pack: the parts, materials, the impostor framing (layout, bounds) and frames."""

    frames_per_second: float
    cycle_frames: int
    parts: list[PosePart]
    materials: list[MaterialInfo]
    outfit_count: int
    bounds: dict[str, Any]  # {"center": [x, y, z], "radius": r}
    layout: dict[str, Any]  # AtlasLayout.to_manifest()
    frame_indices: list[int]
    fidelity_frame: int
    # The memory budget's choice (crowdbake.bake.impostor_budget.BudgetChoice as budget_document gives it).
    budget: dict[str, Any] | None = None
    # Several clips: CycleRecord.ranges (cycle_frames is then every pose frame); None for one clip.
    ranges: dict[str, Any] | None = None
    _nested: ClassVar[dict[str, type]] = {"parts": PosePart, "materials": MaterialInfo}

    def bundle_ranges(self) -> Ranges | None:
        return None if self.ranges is None else ranges_of(self.ranges)

    def atlas_layout(self) -> AtlasLayout:
        """The impostor atlas layout (crowdbake.bake.atlas.AtlasLayout) these poses were framed for."""
        return AtlasLayout.from_manifest(self.layout)

    @property
    def center(self) -> list[float]:
        return self.bounds["center"]

    @property
    def radius(self) -> float:
        return self.bounds["radius"]

    def summary(self) -> dict[str, Any]:
        """Meshes and low-LOD figures, as run_bake reports them."""
        return {
            "meshes": [{"part": p.part, "lod": p.lod, "vertex_count": p.vertex_count, "triangle_count": p.triangle_count} for p in self.parts],
            "lod": [
                {"part": p.part, "triangle_count": p.triangle_count, "target_triangles": p.target_triangles,
                 "relative_error": p.relative_error, "locked_border": p.locked_border}
                for p in self.parts if p.lod == 1
            ],
        }


@dataclass
class ImpostorPlan(Record):
    """impostor plan → impostor tasks, pack: the impostors' framing (layout, bounds) and baked frames, drawn
    from the cycle's output alone so that the impostor tasks need not wait for the poses stage. The high
    LOD at those frames and the textures the tasks draw with are in work/impostor/scene.npz."""

    bounds: dict[str, Any]  # {"center": [x, y, z], "radius": r}, as PosesRecord.bounds
    layout: dict[str, Any]  # AtlasLayout.to_manifest(), as PosesRecord.layout
    frame_indices: list[int]
    fidelity_frame: int
    material_count: int
    ranges: dict[str, Any] | None = None  # as PosesRecord.ranges
    budget: dict[str, Any] | None = None  # as PosesRecord.budget: how the frames were chosen

    def bundle_ranges(self) -> Ranges | None:
        return None if self.ranges is None else ranges_of(self.ranges)

    @property
    def center(self) -> list[float]:
        return self.bounds["center"]

    @property
    def radius(self) -> float:
        return self.bounds["radius"]


@dataclass
class ImpostorTask(Record):
    """One unit of the impostor fan-out: the views of one elevation ring at one baked frame.
    references: this is the fidelity frame, so the task also renders the mesh references."""

    id: str
    frame: int
    elevation: int
    views: list[list[int]]
    references: bool

    def to_json(self) -> dict[str, Any]:
        # The spec a Celery part carries (crowdbake.storage.records.record_fan_out): no record_version.
        return asdict(self)


@dataclass
class ImpostorPartRecord(Record):
    """An impostor task's sidecar (work/impostor/parts/<id>.json): its key and statistics."""

    key: str
    views: int
    seconds: dict[str, float] = field(default_factory=dict)  # render, maps, references
    # The GL context that drew the part (crowdbake.render.gl_device.GlContextInfo.to_json); None in a
    # sidecar written before it was recorded.
    gl: dict[str, Any] | None = None


@dataclass
class ImpostorStatistics(Record):
    """Views, renders and seconds summed over the written impostor parts."""

    tasks: int = 0
    views: int = 0
    render_seconds: float = 0.0
    maps_seconds: float = 0.0
    reference_seconds: float = 0.0


@dataclass
class PackRecord(Record):
    """pack → publish, run_bake: the packed bundle's files and what was measured on it."""

    files: dict[str, int]
    fidelity: dict[str, Any]
    uv_precision: dict[str, Any]
    compression: dict[str, Any]
    texture_memory: dict[str, Any]
    # Each GL context that drew impostor parts, with how many (crowdbake.stages.impostors.gl_renderers).
    gl_renderers: list[dict[str, Any]] = field(default_factory=list)
