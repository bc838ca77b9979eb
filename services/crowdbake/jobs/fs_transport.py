"""kombu's filesystem transport with messages that appear whole.

kombu writes a message file in place under its final name, so a consumer listing the folder can claim
(rename) and read it while the producer is still writing: it reads a partial or empty payload and the
message is lost. A burst of messages (a bake's fan-out of impostor tasks) makes that likely. Here the
payload is written to a hidden name that no consumer matches, flushed, then renamed into the queue
folder: a rename within one file system is atomic, so a consumer sees no file or the whole file.
"""
from __future__ import annotations

import os
import uuid
from time import monotonic

from kombu.exceptions import ChannelError
from kombu.transport import filesystem
from kombu.utils.encoding import str_to_bytes
from kombu.utils.json import dumps


class Channel(filesystem.Channel):
    def _put(self, queue, payload, **kwargs):
        """Put `payload` onto `queue`: write it under a hidden name, then rename it into place."""
        # The name sorts like kombu's own (milliseconds first), so messages keep their order.
        name = f"{int(round(monotonic() * 1000))}_{uuid.uuid4()}.{queue}.msg"
        final = os.path.join(self.data_folder_out, name)
        # A leading dot: kombu's consumer takes only names whose text after the first dot is
        # "<queue>.msg", and this one's is "partial-<name>".
        partial = os.path.join(self.data_folder_out, f".partial-{name}")
        try:
            with open(partial, "wb") as handle:
                handle.write(str_to_bytes(dumps(payload)))
            os.replace(partial, final)
        except OSError as exc:
            try:
                os.unlink(partial)
            except OSError:
                pass
            raise ChannelError(f"Cannot add file {final!r} to directory") from exc


class Transport(filesystem.Transport):
    Channel = Channel
