"""What a bake is baked from, described once: the inputs a request names and the mode they make.

A bake reads a character and one of five sets of cloth inputs (docs/inputs.md):

    body_only    no cloth: the body's own animation loop (crowdbake.stages.body_only)
    cloth        one cache, its cycle searched
    cycle        one cache and a cycle chosen beforehand (`crowdbake cycle`)
    timeline     one cache playing several clips: a loop per clip and the transitions between them
    clip_cloth   one cache per clip, each a separate simulation: a loop per clip, no transitions

`BakeInputSet` holds the inputs by reference, whatever names them: an asset id in a REST request, a local
file (or a multipart form of files) on the command line, an Asset row on the server. `mode()` checks the
combination, and `cycle_frames`, which only a single searched or chosen cycle takes, once for every
boundary: POST /v1/bakes, `crowdbake bake` and `crowdbake submit` refuse the same requests, each wording
the refusal its own way (InputConflict: problem fields for REST, option names for the command line).

Standard library only: `crowdbake submit` runs without the bake stack (services/tests/test_client_package.py).
"""
from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from typing import Any, Callable, Generic, Iterable, Mapping, TypeVar

from crowdbake.errors import InputError
from crowdbake.params import option_for

Ref = TypeVar("Ref")
Other = TypeVar("Other")

# The command line's names of the inputs (`crowdbake bake` and `crowdbake submit` share them); the
# parameters' flags come from crowdbake.params.
INPUT_OPTIONS = {
    "character": "CHAR.glb",
    "cloth": "--cloth",
    "cycle": "--cycle",
    "timeline": "--timeline",
    "clip_cloth": "--clip-cloth",
    "textures": "--textures",
}


class InputMode(str, Enum):
    BODY_ONLY = "body_only"
    CLOTH = "cloth"
    CYCLE = "cycle"
    TIMELINE = "timeline"
    CLIP_CLOTH = "clip_cloth"


def option_name(name: str) -> str:
    """An input's or a parameter's command-line option (`cycle_frames` -> `--cycle-frames`)."""
    return option_for(name) or INPUT_OPTIONS.get(name, name)


class InputConflict(InputError):
    """Inputs (or cycle_frames) that do not go together. `field`: the request field to leave out, as REST
    names it (`cloth`, `params.cycle_frames`); `title` and `message`: the problem's wording. A command
    line reports `command_line()`: the option of `lead` first, then `advice` with its {names} spelled as options."""

    def __init__(self, field: str, title: str, message: str, lead: str, advice: str):
        super().__init__(message, field)
        self.title = title
        self.lead = lead
        self.advice = advice

    def command_line(self) -> str:
        spelled = {name: option_name(name) for name in (*INPUT_OPTIONS, "cycle_frames")}
        return f"{option_name(self.lead)}: {self.advice.format(**spelled)}"


def _leave_out_for_clip_cloth(role: str) -> InputConflict:
    return InputConflict(role, "one cache per clip stands alone",
                         f"clip_cloth gives every clip its own cache (separate simulations): leave out {role}",
                         "clip_cloth", f"gives every clip its own cache (separate simulations): leave out {{{role}}}")


# InputConflict's arguments: the field to leave out, the problem's title and message, the command line's lead and advice.
_NO_PERIOD_WITH_CLIP_CLOTH = ("params.cycle_frames", "each clip's animation gives its period",
                              "with clip_cloth each clip's period is its animation's: drop cycle_frames",
                              "clip_cloth", "each clip's period is its animation's: drop {cycle_frames}")
_TIMELINE_WITHOUT_CLOTH = ("cloth", "the timeline does not go with these inputs", "a timeline says which clip plays at each frame of a cloth cache",
                           "timeline", "a timeline says which clip plays at each frame of a cloth cache: give {cloth} too")
_TIMELINE_AND_CYCLE = ("cycle", "the timeline does not go with these inputs", "a cycle chooses one loop; a timeline asks for a loop per clip",
                       "cycle", "a cycle chooses one loop; {timeline} asks for a loop per clip: give one of them")
_NO_PERIOD_WITH_TIMELINE = ("params.cycle_frames", "the timeline gives each clip's period", "the timeline gives each clip's period: drop cycle_frames",
                            "cycle_frames", "the timeline gives each clip's period: drop cycle_frames")
_CYCLE_WITHOUT_CLOTH = ("cycle", "a cycle applies to a cloth cache", "without cloth the cycle is the animation's own loop",
                        "cycle", "a cycle chooses a loop of a cloth cache: give {cloth} too")
_PERIOD_WITHOUT_CLOTH = ("params.cycle_frames", "a cycle applies to a cloth cache", "without cloth the cycle is the animation's own loop",
                         "cycle_frames", "without {cloth} the cycle is the animation's own loop")


def _pairs(value: Mapping[str, Any] | Iterable[tuple[str, Any]]) -> tuple[tuple[str, Any], ...]:
    return tuple((str(name), ref) for name, ref in (value.items() if isinstance(value, Mapping) else value))


@dataclass(frozen=True)
class BakeInputSet(Generic[Ref]):
    """The inputs of one bake, each named by a Ref. textures: (file name, Ref), sorted by name whatever
    order they are given in (a mapping or pairs); clip_cloth: (clip, its cache's Ref), in the order given
    (the order the clips join in, crowdbake.ingest.clip_caches)."""

    character: Ref
    cloth: Ref | None = None
    cycle: Ref | None = None
    timeline: Ref | None = None
    textures: tuple[tuple[str, Ref], ...] = ()
    clip_cloth: tuple[tuple[str, Ref], ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "textures", tuple(sorted(_pairs(self.textures), key=lambda pair: pair[0])))
        object.__setattr__(self, "clip_cloth", _pairs(self.clip_cloth))

    def mode(self, cycle_frames: int | None = None) -> InputMode:
        """The bake's mode; InputConflict for an input, or a cycle_frames, the mode does not take (the
        first found, in the order the REST API has always reported them)."""
        if self.clip_cloth:
            for role in ("cloth", "timeline", "cycle"):
                if getattr(self, role) is not None:
                    raise _leave_out_for_clip_cloth(role)
            if cycle_frames is not None:
                raise InputConflict(*_NO_PERIOD_WITH_CLIP_CLOTH)
            return InputMode.CLIP_CLOTH
        if self.timeline is not None:
            if self.cloth is None:
                raise InputConflict(*_TIMELINE_WITHOUT_CLOTH)
            if self.cycle is not None:
                raise InputConflict(*_TIMELINE_AND_CYCLE)
            if cycle_frames is not None:
                raise InputConflict(*_NO_PERIOD_WITH_TIMELINE)
            return InputMode.TIMELINE
        if self.cloth is not None:
            return InputMode.CYCLE if self.cycle is not None else InputMode.CLOTH
        if self.cycle is not None:
            raise InputConflict(*_CYCLE_WITHOUT_CLOTH)
        if cycle_frames is not None:
            raise InputConflict(*_PERIOD_WITHOUT_CLOTH)
        return InputMode.BODY_ONLY

    def map(self, convert: Callable[[str, Ref], Other]) -> "BakeInputSet[Other]":
        """The same inputs with every Ref converted by `convert(role, ref)` (roles as in `roles()`), called in
        the order character, cloth, textures, cycle, timeline, clip_cloth."""
        return BakeInputSet(
            character=convert("character", self.character),
            cloth=None if self.cloth is None else convert("cloth", self.cloth),
            textures=tuple((name, convert(f"textures.{name}", ref)) for name, ref in self.textures),
            cycle=None if self.cycle is None else convert("cycle", self.cycle),
            timeline=None if self.timeline is None else convert("timeline", self.timeline),
            clip_cloth=tuple((clip, convert(f"clip_cloth.{k}", ref)) for k, (clip, ref) in enumerate(self.clip_cloth)),
        )

    def roles(self) -> dict[str, Ref]:
        """Input role -> Ref for every input given: character, cloth, textures.NAME, cycle, timeline and
        clip_cloth.K (the K-th clip's cache), the roles POST /v1/bakes/check compares."""
        found: dict[str, Ref] = {}

        def note(role: str, ref: Ref) -> Ref:
            found[role] = ref
            return ref

        self.map(note)
        return {role: ref for role, ref in found.items() if ref is not None}

    def record(self) -> dict[str, Any]:
        """The inputs as a bake records them (Bake.inputs, and the input key's digests): a role only when
        given, textures always, clip_cloth as [clip, ref] lists."""
        return {
            "character": self.character,
            **({"cloth": self.cloth} if self.cloth is not None else {}),
            "textures": dict(self.textures),
            **({"cycle": self.cycle} if self.cycle is not None else {}),
            **({"timeline": self.timeline} if self.timeline is not None else {}),
            **({"clip_cloth": [[clip, ref] for clip, ref in self.clip_cloth]} if self.clip_cloth else {}),
        }

    @classmethod
    def from_record(cls, inputs: Mapping[str, Any]) -> "BakeInputSet[Any]":
        """The inputs of a bake record (`record()`, and the `inputs` of GET /v1/bakes/{id})."""
        return cls(character=inputs.get("character"), cloth=inputs.get("cloth") or None, cycle=inputs.get("cycle") or None,
                   timeline=inputs.get("timeline") or None, textures=inputs.get("textures") or {},
                   clip_cloth=[(clip, ref) for clip, ref in inputs.get("clip_cloth") or []])

    def request_fields(self) -> dict[str, Any]:
        """The inputs' fields of a POST /v1/bakes body (crowdbake.api.schemas.BakeCreate)."""
        return {
            "character": self.character, "cloth": self.cloth, "textures": dict(self.textures),
            **({"cycle": self.cycle} if self.cycle is not None else {}),
            **({"timeline": self.timeline} if self.timeline is not None else {}),
            **({"clip_cloth": [{"clip": clip, "cloth": ref} for clip, ref in self.clip_cloth]} if self.clip_cloth else {}),
        }


def command_line_inputs(args: Any) -> BakeInputSet[str]:
    """The inputs given to `crowdbake bake` or `crowdbake submit` (the same option names), as typed: a
    --clip-cloth NAME=CACHE[,MESH] under its NAME (crowdbake.ingest.clip_caches parses the files). The
    textures are a folder there, read once the mode is known, so none are listed."""
    return BakeInputSet(character=args.character, cloth=args.cloth or None, cycle=args.cycle or None, timeline=args.timeline or None,
                        clip_cloth=[(value.partition("=")[0].strip(), value) for value in args.clip_cloth or []])
