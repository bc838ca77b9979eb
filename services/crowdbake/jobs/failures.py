"""What a failed stage says: a problem record for the bake (type, title, one-line detail, field), and
whether the error is worth another attempt."""
from __future__ import annotations

import errno
from typing import Any

from kombu.exceptions import OperationalError as KombuOperationalError
from sqlalchemy.exc import OperationalError

from crowdbake.errors import InputError, VersionConflict
from crowdbake.storage.bundles import BundleConflict

# OS errors a later attempt can get past; others (a missing file, a permission) would fail again.
TRANSIENT_ERRNOS = frozenset({errno.ENOSPC, errno.EIO, errno.EAGAIN, errno.EBUSY, errno.ETIMEDOUT, errno.EMFILE, errno.ENFILE, errno.EINTR})


def is_transient(error: BaseException) -> bool:
    if isinstance(error, (OperationalError, KombuOperationalError)):  # database busy, broker unreachable
        return True
    return isinstance(error, OSError) and error.errno in TRANSIENT_ERRNOS


def describe_error(error: BaseException, stage: str) -> dict[str, Any]:
    """A bake's error record: a problem type, a title, a one-line detail and the input field if known."""
    detail = " ".join(str(error).split()) or type(error).__name__
    if isinstance(error, OSError) and error.errno is not None and error.filename is not None:
        # The file name is a path in the server's work folder: the log has it, the API user gets the reason.
        detail = f"[Errno {error.errno}] {error.strerror}"
    if isinstance(error, InputError):
        record = {"type": "invalid-input", "title": "the inputs cannot be baked", "detail": detail}
        field = getattr(error, "field", None)
        if field:
            record["field"] = str(field)
        return record
    if isinstance(error, KombuOperationalError):
        return {"type": "not-ready", "title": "the job queue is unreachable",
                "detail": f"the {stage} stage could not queue what comes next: {detail}; retry the bake once the broker is back"}
    if isinstance(error, (BundleConflict, VersionConflict)):
        return {"type": "version-conflict", "title": "this version is already published with other bytes", "detail": detail}
    return {"type": "stage-failed", "title": f"the {stage} stage failed", "detail": f"{type(error).__name__}: {detail}"}
