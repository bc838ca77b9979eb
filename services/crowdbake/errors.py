"""The errors a bake reports: bad input, a version clash with a published bundle, stages out of order."""
from __future__ import annotations


class InputError(ValueError):
    """Bad input, reported to the user: `field` names the input or parameter at fault (None: general)."""

    def __init__(self, message: str, field: str | None = None):
        super().__init__(message)
        self.message = message
        self.field = field


class VersionConflict(Exception):
    """The bundle <name>/<version> is already published with other bytes; published bundles never change."""


class ExportConflict(VersionConflict):
    """An export home already holds the export of other bundle bytes under the same name and version."""


class StageOrderError(RuntimeError):
    """A stage ran before the stage it depends on produced its outputs in this work directory."""


class OutOfBoundsError(InputError):
    """A loop or transition of the bake breaks a quality bound (crowdbake.bake.bounds) and the bake did not
    accept it (the accept_out_of_bounds parameter): the message names the clip, cache frames, figure and bound."""
