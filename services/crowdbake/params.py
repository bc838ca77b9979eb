"""Bake parameters and limits, declared once.

PARAMS is a table of field specs (name, type, default, bounds, choices, help, CLI flag). From it come

- BakeParams, the frozen dataclass the stages read (its validate() walks the table);
- the REST request model (crowdbake.api.schemas.BakeParamsIn, built by `pydantic_fields`);
- the command-line options of `crowdbake bake`, `crowdbake submit` and the shared ones of
  `crowdbake cycle` (`add_cli_options`, `params_from_args`),

so every parameter that shapes a bundle has one default and one bound everywhere.
services/tests/test_params.py walks the table and checks the CLI parser and the pydantic model agree.
"""
from __future__ import annotations

import argparse
import math
import numbers
import re
from dataclasses import asdict, dataclass, fields
from typing import Any, Iterable

from crowdbake.errors import InputError

# Seam closings (crowdbake.bake.loop_closing.CLOSE_METHODS, kept equal by test_params): crossfade, the
# default, blends only a window around the seam and restores edge lengths, so real simulator caches do not
# tear; linear is the paper's blend; hermite also matches velocity but spreads the correction over the loop.
CLOSE_METHODS = ("crossfade", "none", "linear", "hermite")
DEFAULT_CLOSE = "crossfade"
IMPOSTOR_CHOICES = ("measured", "rule")  # how a bake chooses its impostor's tile, azimuths and frames; the first is the default
UV_FORMATS = ("uvblock", "uv32", "rgba16")  # impostor UV map pixel formats a bake can write (SPEC.md); the first is the default
# The cloth cache's frame as exported (crowdbake.bake.placement.UP_AXES / UNITS, kept equal by test_params):
# None leaves it to placement's detection, which refuses a cache that fits only another frame.
UP_AXES = ("y", "z")
UNIT_CHOICES = ("m", "cm", "mm", "in")
# The one sane frame-rate range every input's rate must lie in (the fps parameter of the CLI and REST,
# MDD frame times, Alembic time sampling, a PC2's or OBJ sequence's 24 / sample interval, a cycle
# document's input.fps). Slower than 1 frame a second is a slideshow, not a walk (and 1e-30 published as
# is, or 1e-300 divided into seconds, overflowed later); faster than 1000 is no animation a crowd plays
# (film is 24, high-frame-rate capture 240), and a bigger rate turns seconds into frame counts that
# overflow ("Python int too large" at 1e30).
MIN_FPS = 1.0
MAX_FPS = 1000.0


class FrameRateError(InputError):
    """A frame rate outside MIN_FPS..MAX_FPS (cache_fps); `field` is "params.fps" or "cloth"."""


def fps_problem(value: Any) -> str | None:
    """Why `value` is not a frame rate a bake takes (see MIN_FPS / MAX_FPS), or None."""
    shown = f"{value!r}"[:40]
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        return f"{shown} is not a number of frames per second (the sane range is {MIN_FPS:g}..{MAX_FPS:g})"
    if not math.isfinite(value) or not MIN_FPS <= value <= MAX_FPS:
        return f"{shown} frames per second is outside the sane range {MIN_FPS:g}..{MAX_FPS:g}"
    return None
# glTF animation names are free text; one longer than this is no name a person chose.
MAX_ANIMATION_NAME = 256

# The bundle spec's name and version rules (shared_formats/SPEC.md, "manifest.json").
NAME_PATTERN = r"^[a-z0-9][a-z0-9._-]{0,63}$"
VERSION_PATTERN = r"^[0-9A-Za-z][0-9A-Za-z.+_-]{0,63}$"
NAME_RULE = re.compile(NAME_PATTERN)
VERSION_RULE = re.compile(VERSION_PATTERN)
CREATED_RULE = re.compile(r"^\d{4}-\d{2}-\d{2}T\d{2}:\d{2}:\d{2}Z$")
PART_RULE = re.compile(r"^[a-z0-9_-]{1,32}$")

# PC2 stores the interval between samples in frames, not a rate: the cache's rate is this over
# sample_rate unless the cycle search recorded one (the film rate).
BASE_FPS = 24.0
# Upper limits that keep one bake within a worker's memory: 64 azimuths x 9 elevations x 1024² tiles is
# already a 64k-wide atlas; the runtime's texture limits are lower still.
MAX_TILE_SIZE = 1024
MAX_AZIMUTHS = 64
MAX_ELEVATIONS = 9
MAX_IMPOSTOR_FRAMES = 256
# Texels of one impostor map set: impostor_frames x views (azimuths x elevation rings) x tile_size².
# Each texel is rendered as a normal, a detail and a UV map and held while packing (4 bytes each as
# rgba8 before compression), so 2^27 texels is 1.5 GiB of maps: 4.6 times the most the defaults ask
# for (24 frames x 32 x 3 views x 112², before the memory budget), and the most a 4 GiB worker should be asked for. Each parameter alone is within its bound; together they may not be.
MAX_IMPOSTOR_TEXELS = 1 << 27
# The cycle search's cost grows with candidates x views renders; these bound one request's work.
MAX_CANDIDATES = 50
MAX_CYCLE_VIEWS = 32
# About 70 minutes of walk at 24 fps: far beyond any walk cycle, small enough for 64-bit arithmetic.
MAX_CYCLE_FRAMES = 100_000


# Each cycle needs at least two frames (crowdbake.bake.cycle), and the search needs two cycles (paper
# section 3 compares frames one cycle apart).
MIN_CYCLE_FRAMES = 2
CYCLES_NEEDED = 2


def min_cloth_frames(cycle_frames: int | None) -> int:
    """Frames a cloth cache needs for the cycle search: two cycles of `cycle_frames` (None: of the
    shortest cycle, MIN_CYCLE_FRAMES)."""
    return CYCLES_NEEDED * max(int(cycle_frames or MIN_CYCLE_FRAMES), MIN_CYCLE_FRAMES)


def cache_fps(given: float | None, file_fps: float | None, sample_rate: float | None = 1.0) -> float:
    """The cloth cache's frame rate, one rule for every entry point: the `fps` parameter when given, else
    the rate the file states (MDD frame times, Alembic time sampling), else BASE_FPS / the PC2 sample
    interval (PC2 stores the spacing of samples in frames, not a rate).
    Raises InputError when the rate is outside MIN_FPS..MAX_FPS, naming where it came from (field
    "params.fps" for the parameter, "cloth" for the cache's own)."""
    if given is not None:
        rate, source, field = given, "the fps parameter", "params.fps"
    elif file_fps is not None and file_fps > 0:
        rate, source, field = file_fps, "the cloth cache's frame rate", "cloth"
    else:
        rate, field = BASE_FPS / float(sample_rate or 1.0), "cloth"
        source = f"the cloth cache's frame rate ({BASE_FPS:g} / its sample interval {sample_rate!r})"
    problem = fps_problem(rate)
    if problem is not None:
        raise FrameRateError(f"{source}: {problem}", field)
    return float(rate)


def cycle_frames_from_animation(animation_seconds: float, fps: float) -> int:
    """The walk cycle's length in cache frames: the animation's duration at the cache's rate `fps`
    (crowdbake.params.cache_fps). 0 when there is no animation."""
    if not animation_seconds or animation_seconds <= 0:
        return 0
    return int(round(float(animation_seconds) * float(fps)))


@dataclass(frozen=True)
class ParamSpec:
    """One bake parameter: its type, default, bounds, help and command-line flag.

    kind: "int", "float", "str", "bool", "floats" (a list of floats) or "name_or_index" (a glTF name or a
    0-based index; on the command line digits are an index); optional: None is allowed and means
    "derived", as `derived` says. help: what the parameter is, without its default (the REST model,
    the CLI and the web page add it, once). off_help: for a default-on "bool", what its `--no-…` flag
    does when given (the flag turns the parameter off, so its help must say so). minimum/maximum: inclusive bounds (of each item for "floats"); above_zero: the
    value must be > 0 instead of >= minimum. flags: the `crowdbake bake` flag first, aliases after.
    """

    name: str
    kind: str
    default: Any
    help: str
    flags: tuple[str, ...]
    metavar: str | None = None
    optional: bool = False
    minimum: float | None = None
    maximum: float | None = None
    above_zero: bool = False
    multiple_of: int | None = None
    choices: tuple[str, ...] | None = None
    min_items: int | None = None
    max_items: int | None = None
    distinct: bool = False
    exclusive_group: str | None = None
    derived: str | None = None
    off_help: str | None = None

    @property
    def flag(self) -> str:
        return self.flags[0]

    def problem(self, value: Any) -> str | None:
        """Why `value` is not acceptable for this parameter, or None when it is."""
        if value is None:
            return None if self.optional else "must be given"
        if self.kind == "bool":
            return None if isinstance(value, bool) else "must be true or false"
        if self.kind == "str":
            return None if value in (self.choices or ()) else f"must be one of {', '.join(self.choices or ())}"
        if self.kind == "name_or_index":
            if _is_integer(value):
                return None if value >= 0 else "an index must be 0 or more"
            if isinstance(value, str) and 0 < len(value) <= MAX_ANIMATION_NAME:
                return None
            return f"must be a name (1..{MAX_ANIMATION_NAME} characters) or an index (0 or more)"
        if self.kind == "floats":
            if not isinstance(value, (tuple, list)) or not self.min_items <= len(value) <= self.max_items:
                return f"needs {self.min_items}..{self.max_items} values"
            if not all(_is_number(v) and self.minimum <= v <= self.maximum for v in value):
                return f"values must lie in {self.minimum:g}..{self.maximum:g} degrees"
            if self.distinct and len(set(value)) != len(value):
                return "values must be distinct"
            return None
        number_ok = _is_integer(value) if self.kind == "int" else _is_number(value)
        if not number_ok or not self._in_range(value):
            return self.range_text()
        if self.multiple_of and value % self.multiple_of:
            return self.range_text()
        return None

    def _in_range(self, value: float) -> bool:
        if self.above_zero and not value > 0:
            return False
        if self.minimum is not None and value < self.minimum:
            return False
        return self.maximum is None or value <= self.maximum

    def range_text(self) -> str:
        what = "an integer" if self.kind == "int" else "a number"
        if self.multiple_of:
            return f"must be a multiple of {self.multiple_of} in {self.minimum:g}..{self.maximum:g}"
        if self.above_zero:
            return f"must lie in (0, {self.maximum:g}]"
        if self.maximum is None:
            return f"must be {what} of at least {self.minimum:g}"
        return f"must be {what} in {self.minimum:g}..{self.maximum:g}"


def _is_integer(value: Any) -> bool:
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def _is_number(value: Any) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(float(value))


PARAMS: tuple[ParamSpec, ...] = (
    ParamSpec("cycle_frames", "int", None, "walk cycle length in frames",
              ("--cycle-frames",), "L", derived="the character's animation", optional=True, minimum=2, maximum=MAX_CYCLE_FRAMES),
    ParamSpec("close", "str", DEFAULT_CLOSE, "how the cycle's seam is closed: crossfade (a window around the seam, edge lengths kept), "
              "none, linear (the paper's blend) or hermite (also matches velocity, spreads the change over the loop)",
              ("--close",), choices=CLOSE_METHODS),
    ParamSpec("fps", "float", None, "the cloth cache's frame rate", ("--fps",), "FPS",
              derived="what the cache says: MDD frame times, Alembic time sampling; else 24 / the PC2 sample interval", optional=True, minimum=MIN_FPS, maximum=MAX_FPS),
    ParamSpec("up", "str", None, "the cloth cache's up axis as exported: y (glTF, Maya) or z (Blender, 3ds Max), converted to Y-up",
              ("--up",), derived="detect, and refuse a cache that is not Y-up", optional=True, choices=UP_AXES),
    ParamSpec("units", "str", None, "the cloth cache's length unit as exported: m, cm, mm or in, converted to metres",
              ("--units",), derived="detect, and refuse a cache that is not in metres", optional=True, choices=UNIT_CHOICES),
    ParamSpec("fit", "bool", True,
              "refuse a garment that does not follow the character over the cache (simulated on another character)",
              ("--no-fit",), off_help="do not check the garment's fit on the character over the cache: bake one made for another character anyway"),
    ParamSpec("animation", "name_or_index", None, "the character's walk: a glTF animation name or index",
              ("--animation",), "NAME|INDEX", optional=True,
              derived="the only animation, else the one the cloth cache repeats after (crowdbake.ingest.clip_choice)"),
    ParamSpec("accept_out_of_bounds", "bool", False, "publish loops and transitions that break their quality bounds "
              "(stretch, deviation, seam acceleration: docs/cycle.md) instead of failing the bake; the manifest lists what was accepted",
              ("--accept-out-of-bounds",), off_help="publish loops and transitions that break their quality bounds instead of "
              "failing; the manifest lists what was accepted"),
    ParamSpec("candidates", "int", 5, "cycle candidates kept by pass 1 and compared by the pass-2 edge metric (paper section 3)",
              ("--candidates",), "K", minimum=1, maximum=MAX_CANDIDATES),
    ParamSpec("cycle_views", "int", 5, "views of the pass-2 edge metric (paper: 5)",
              ("--cycle-views",), "N", minimum=1, maximum=MAX_CYCLE_VIEWS),
    ParamSpec("impostor_frames", "int", 24, "the most cycle frames baked into impostors (paper: 10); fewer where the "
              "character moves little (impostor_motion_texels) or the memory budget says so",
              ("--frames", "--impostor-frames"), "N", minimum=1, maximum=MAX_IMPOSTOR_FRAMES),
    ParamSpec("impostor_motion_texels", "float", 7.1, "bake the fewest frames between which the character (95 percent of its vertices) "
              "moves at most this many tile texels, up to impostor_frames (docs/bake.md 'Memory')",
              ("--frame-motion",), "TEXELS", optional=True, above_zero=True, maximum=1024.0,
              derived="none: impostor_frames as given"),
    ParamSpec("azimuths", "int", 32, "impostor views per elevation ring (32: docs/figures.md, impostor views against memory)",
              ("--azimuths",), "N", minimum=1, maximum=MAX_AZIMUTHS),
    ParamSpec("elevations_deg", "floats", (0.0, 20.0, 40.0), "impostor view elevations in degrees, one ring each",
              ("--elevations",), "DEG,...", minimum=-90.0, maximum=90.0, min_items=1, max_items=MAX_ELEVATIONS, distinct=True),
    ParamSpec("tile_size", "int", 88, "texels per impostor view side (a multiple of 4: BC1/BC2 blocks are 4x4 texels)",
              ("--tile", "--tile-size"), "PX", minimum=4, maximum=MAX_TILE_SIZE, multiple_of=4),
    ParamSpec("impostor_budget_mib", "float", 16.0, "memory for one clip's impostor maps in MiB (the paper's 15), within which "
              "impostor_choice picks the tile, azimuths and frames (docs/bake.md 'Memory')",
              ("--impostor-budget",), "MIB", optional=True, above_zero=True, maximum=4096.0),
    ParamSpec("impostor_archetype_mib", "float", 32.0, "MiB of impostor maps for all clips and transitions of a character of several "
              "clips, split among them by measuring (docs/bake.md 'Several clips'); null: impostor_budget_mib per clip",
              ("--impostor-archetype-budget",), "MIB", optional=True, above_zero=True, maximum=4096.0,
              derived="none: impostor_budget_mib for each clip, transitions at their clips' spacing"),
    ParamSpec("impostor_choice", "str", "measured", "how the impostor's tile, azimuths and frames are chosen within the budget: "
              "measured (probed with crowdview's shader: docs/bake.md 'Memory') or rule (tile as asked; azimuths, then frames, cut to fit)",
              ("--impostor-choice",), choices=IMPOSTOR_CHOICES),
    ParamSpec("crop", "bool", True, "store each impostor view cropped to the box the character covers over every view and frame "
              "(SPEC.md: about half the maps' memory, the same pictures)",
              ("--no-crop",), off_help="do not crop the impostor tiles: store them whole (square)"),
    ParamSpec("detail_map", "bool", False, "also store detail-mapped impostors (the paper's figure 3 comparison: 1 byte a texel "
              "more; crowdview --lod detail)",
              ("--detail-map",), off_help="also store detail maps (the diffuse texture baked into each view: figure 3's "
              "detail-mapped impostor, crowdview --lod detail), 1 byte a texel more"),
    ParamSpec("lod_ratio", "float", None, "low LOD as a fraction of the high one",
              ("--lod-ratio",), "R", derived="the paper's 1899/13056", optional=True, maximum=1.0, above_zero=True, exclusive_group="lod"),
    ParamSpec("lod_triangles", "int", None, "low LOD triangles for the whole character (instead of lod_ratio)",
              ("--lod-triangles",), "N", derived="from lod_ratio", optional=True, minimum=2, exclusive_group="lod"),
    ParamSpec("compress", "bool", True,
              "block-compress normal maps (BC5), surface maps, detail maps and diffuse textures (DXT3); false: rgba8",
              ("--no-compress",), off_help="do not block-compress the maps: store normal, surface, detail maps and diffuse textures as rgba8"),
    ParamSpec("uv_format", "str", "uvblock", "impostor UV map format: uvblock (1.5 bytes a texel, block-coded 12-bit coordinates), "
              "uv32 (4 bytes, 14-bit coordinates) or rgba16 (8 bytes)",
              ("--uv-format",), choices=UV_FORMATS),
    ParamSpec("skinning", "bool", True, "store a body posed by a skinned glTF as skinning: its rest mesh, joint weights and joint "
              "matrices per frame, skinned by the runtime (SPEC.md 'Skinned pose cache', bundle format 4: 48 bytes a joint a frame "
              "instead of every vertex); false: vertex frames, as a garment's",
              ("--no-skinning",), off_help="do not keep the body's skinning (joint matrices the runtime skins): store its vertex "
              "frames, as a garment's"),
    ParamSpec("export", "bool", True, "publish an engine export beside the bundle (glTF, KTX2, VATs: docs/export.md); false: the bundle only",
              ("--no-export",), off_help="do not publish an engine export (glTF, KTX2, VATs: docs/export.md) beside the bundle: the bundle only"),
)
SPECS = {spec.name: spec for spec in PARAMS}
# Parameters of the cycle search that `crowdbake cycle` shares with `crowdbake bake` (its own flag names).
CYCLE_SHARED = {"cycle_frames": "--cycle-frames", "close": "--close", "fps": "--fps", "up": "--up", "units": "--units",
                "animation": "--animation", "candidates": "--candidates", "cycle_views": "--views", "fit": "--no-fit",
                "accept_out_of_bounds": "--accept-out-of-bounds"}


def impostor_texels(values: dict[str, Any]) -> int | None:
    """impostor_frames x azimuths x len(elevations_deg) x tile_size², or None when a value is missing or
    not a number (each field's own check reports that)."""
    try:
        frames, azimuths, tile = (int(values.get(name, SPECS[name].default)) for name in ("impostor_frames", "azimuths", "tile_size"))
        rings = len(values.get("elevations_deg", SPECS["elevations_deg"].default))
    except (TypeError, ValueError):
        return None
    return frames * azimuths * rings * tile * tile


def cross_field_problem(values: dict[str, Any]) -> tuple[str, str] | None:
    """(field, message) for a combination of parameters that cannot go together, else None. The field
    is None when the problem is the combination of several (the message names them)."""
    if values.get("lod_ratio") is not None and values.get("lod_triangles") is not None:
        return "lod_ratio", "give lod_ratio or lod_triangles, not both"
    texels = impostor_texels(values)
    if texels is not None and texels > MAX_IMPOSTOR_TEXELS:
        return None, (f"impostor_frames x azimuths x elevations_deg (rings) x tile_size² = {values.get('impostor_frames', SPECS['impostor_frames'].default)}"
                      f" x {values.get('azimuths', SPECS['azimuths'].default)} x {len(values.get('elevations_deg', SPECS['elevations_deg'].default))}"
                      f" x {values.get('tile_size', SPECS['tile_size'].default)}² = {texels:,} texels, more than {MAX_IMPOSTOR_TEXELS:,} "
                      "(MAX_IMPOSTOR_TEXELS); lower one of them")
    return None


@dataclass(frozen=True)
class BakeParams:
    """Everything that shapes a bake besides the input files (JSON-serialisable: to_dict/from_dict).

    The meaning, default and bounds of each field are in PARAMS above; the defaults here are checked
    against that table by services/tests/test_params.py.
    """

    cycle_frames: int | None = None
    close: str = DEFAULT_CLOSE
    fps: float | None = None
    up: str | None = None
    units: str | None = None
    fit: bool = True
    animation: int | str | None = None
    accept_out_of_bounds: bool = False
    candidates: int = 5
    cycle_views: int = 5
    impostor_frames: int = 24
    impostor_motion_texels: float | None = 7.1
    azimuths: int = 32
    elevations_deg: tuple[float, ...] = (0.0, 20.0, 40.0)
    tile_size: int = 88
    impostor_budget_mib: float | None = 16.0
    impostor_archetype_mib: float | None = 32.0
    impostor_choice: str = "measured"
    crop: bool = True
    detail_map: bool = False
    lod_ratio: float | None = None
    lod_triangles: int | None = None
    compress: bool = True
    uv_format: str = "uvblock"
    skinning: bool = True
    export: bool = True

    def validate(self) -> None:
        """Raise InputError(message, field) for the first parameter out of range."""
        values = asdict(self)
        for spec in PARAMS:
            problem = spec.problem(values[spec.name])
            if problem is not None:
                raise InputError(f"{spec.name}: {problem}", spec.name)
        clash = cross_field_problem(values)
        if clash is not None:
            raise InputError(f"{clash[0]}: {clash[1]}" if clash[0] else clash[1], clash[0])

    def to_dict(self) -> dict[str, Any]:
        data = asdict(self)
        data["elevations_deg"] = [float(e) for e in self.elevations_deg]
        return data

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "BakeParams":
        """Parameters from JSON; unknown keys and bad values raise InputError."""
        if not isinstance(data, dict):
            raise InputError("parameters must be a JSON object", None)
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise InputError(f"unknown parameter {unknown[0]!r}", unknown[0])
        values = dict(data)
        if "elevations_deg" in values and isinstance(values["elevations_deg"], list):
            values["elevations_deg"] = tuple(values["elevations_deg"])
        params = cls(**values)
        params.validate()
        return params


# ------------------------------------------------------------------------------------ REST (pydantic)


def pydantic_fields() -> dict[str, tuple[Any, Any]]:
    """create_model field definitions, name -> (annotation, FieldInfo), one per PARAMS entry."""
    from typing import Literal, Optional

    from pydantic import Field

    definitions: dict[str, tuple[Any, Any]] = {}
    for spec in PARAMS:
        bounds: dict[str, Any] = {}
        if spec.kind in ("int", "float"):
            if spec.above_zero:
                bounds["gt"] = 0
            elif spec.minimum is not None:
                bounds["ge"] = spec.minimum
            if spec.maximum is not None:
                bounds["le"] = spec.maximum
            if spec.multiple_of:
                bounds["multiple_of"] = spec.multiple_of
            annotation: Any = int if spec.kind == "int" else float
        elif spec.kind == "str":
            annotation = Literal[spec.choices]  # type: ignore[valid-type]
        elif spec.kind == "bool":
            annotation = bool
        elif spec.kind == "name_or_index":
            from typing import Annotated, Union

            annotation = Union[Annotated[int, Field(ge=0)], Annotated[str, Field(min_length=1, max_length=MAX_ANIMATION_NAME)]]
        else:
            # Item bounds and distinctness: ParamSpec.problem, in the model's validator (one error for the field).
            annotation = list[float]
            bounds.update(min_length=spec.min_items, max_length=spec.max_items)
        if spec.optional:
            annotation = Optional[annotation]
        default = list(spec.default) if isinstance(spec.default, tuple) else spec.default
        if isinstance(default, list):
            info = Field(default_factory=lambda d=tuple(default): list(d), description=_sentence(rest_help(spec)), **bounds)
        else:
            info = Field(default, description=_sentence(rest_help(spec)), **bounds)
        definitions[spec.name] = (annotation, info)
    return definitions


def rest_help(spec: ParamSpec) -> str:
    """The parameter's help for the REST model: what a null value (the default) means, said once."""
    return f"{spec.help} (default: {spec.derived})" if spec.derived else spec.help


def _sentence(text: str) -> str:
    return text[0].upper() + text[1:] + "."


# --------------------------------------------------------------------------------------- command line


def parse_floats(text: str, name: str) -> tuple[float, ...]:
    """Comma-separated numbers of a list option; InputError(name) when they are not."""
    try:
        values = tuple(float(part) for part in str(text).split(",") if part.strip())
    except ValueError:
        raise InputError(f"{name}: must be numbers separated by commas, got {text!r}", name) from None
    if not values:
        raise InputError(f"{name}: needs at least one value", name)
    return values


def add_cli_options(parser, names: Iterable[str] | None = None, *, server_defaults: bool = False,
                    flags: dict[str, str] | None = None) -> None:
    """Add one argparse option per parameter (all of PARAMS, or `names`), dest = the parameter's name.

    server_defaults: every option defaults to None ("leave it to the server"), for `crowdbake submit`.
    flags: name -> flag to use instead of the table's (the table's aliases are then not added).
    """
    wanted = [SPECS[name] for name in names] if names is not None else list(PARAMS)
    groups: dict[str, Any] = {}
    for spec in wanted:
        target = parser
        if spec.exclusive_group is not None:
            if spec.exclusive_group not in groups:
                groups[spec.exclusive_group] = parser.add_mutually_exclusive_group()
            target = groups[spec.exclusive_group]
        option_flags = (flags[spec.name],) if flags and spec.name in flags else spec.flags
        default = None if server_defaults or spec.default is None else spec.default
        if spec.kind == "bool":
            # A flag that turns off a default-on parameter (--no-compress): stored as the parameter's value,
            # and described by what giving it does (off_help), not by what the parameter does when on.
            target.add_argument(*option_flags, dest=spec.name, action="store_const", const=not spec.default,
                                default=None if server_defaults else spec.default, help=spec.off_help)
            continue
        shown = default_text(spec)
        if server_defaults:
            shown = f"the server's, {shown} in this release"
        kwargs: dict[str, Any] = {"dest": spec.name, "default": default, "help": f"{spec.help} (default: {shown})"}
        if spec.kind == "str":
            kwargs["choices"] = list(spec.choices or ())
        elif spec.kind == "name_or_index":
            kwargs["metavar"] = spec.metavar
            kwargs["type"] = name_or_index
        else:
            kwargs["metavar"] = spec.metavar
            # A list stays text here and is parsed by params_from_args, so a bad one is a one-line error.
            kwargs["type"] = {"int": int, "float": float, "floats": str}[spec.kind]
            if spec.optional and spec.default is not None:
                # A parameter on by default that null turns off (REST): `none` on the command line.
                kwargs["type"] = optional_number(kwargs["type"])
                kwargs["metavar"] = f"{spec.metavar or 'N'}|none"
        target.add_argument(*option_flags, **kwargs)


NONE_GIVEN = "none"


def optional_number(parse):
    """An argparse type: `none` (any case) stays NONE_GIVEN, which params_from_args turns into null;
    anything else is `parse`d."""
    def parsed(text: str):
        return NONE_GIVEN if text.strip().lower() == NONE_GIVEN else parse(text)
    parsed.__name__ = getattr(parse, "__name__", "number")
    return parsed


def name_or_index(text: str) -> int | str:
    """A command-line NAME|INDEX: digits are an index, anything else a name."""
    return int(text) if text.isdigit() else text


def default_text(spec: ParamSpec) -> str:
    """The default as a person reads it: the value as typed on the command line, or what `derived` says."""
    if spec.default is None:
        return spec.derived or "none"
    if spec.kind == "floats":
        return ",".join(f"{v:g}" for v in spec.default)
    if spec.kind == "bool":
        return "on" if spec.default else "off"
    return str(spec.default)


def params_from_args(args: argparse.Namespace, names: Iterable[str] | None = None, *, given_only: bool = False) -> dict[str, Any]:
    """The parameters set on the command line, name -> JSON value (lists for "floats").

    given_only: leave out options that were not given (None), so the server applies its defaults.
    Raises InputError(field) for a list option that is not comma-separated numbers."""
    values: dict[str, Any] = {}
    for spec in (SPECS[name] for name in names) if names is not None else PARAMS:
        value = getattr(args, spec.name, None)
        if value is None and given_only:
            continue
        if value == NONE_GIVEN:
            values[spec.name] = None
            continue
        if spec.kind == "floats" and isinstance(value, str):
            value = parse_floats(value, spec.name)
        values[spec.name] = list(value) if isinstance(value, tuple) else value
    return values


def option_for(field: str | None) -> str | None:
    """The `crowdbake bake` flag of a parameter (for one-line CLI errors), or None."""
    spec = SPECS.get(field or "")
    return spec.flag if spec is not None else None
