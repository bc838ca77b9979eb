"""The filesystem broker of the one-command demo under a burst: every message arrives whole.

kombu's own filesystem transport writes a message in place, so a consumer polling at the same time can
claim a half-written file and lose the message (a JSONDecodeError in the worker). A bake's fan-out of
impostor tasks is such a burst."""
from __future__ import annotations

import threading
import time
from queue import Empty

from crowdbake.jobs.celery_app import make_celery
from crowdbake.jobs.fs_transport import Transport
from crowdbake.settings import Settings

MESSAGES = 300


def test_a_burst_of_messages_reaches_two_polling_consumers_whole(tmp_path):
    settings = Settings(data_dir=tmp_path)
    settings.ensure_dirs()
    app = make_celery(settings)
    with app.connection_for_write() as connection:
        assert isinstance(connection.transport, Transport)
    received, errors = [], []

    def produce():
        for index in range(MESSAGES):
            app.send_task("crowdbake.test.burst", args=[index, "x" * 20_000], queue=settings.queue)

    def consume():
        with app.connection_for_read() as connection:
            channel = connection.default_channel
            deadline = time.monotonic() + 60
            while len(received) < MESSAGES and time.monotonic() < deadline:
                try:
                    received.append(channel._get(settings.queue))
                except Empty:
                    time.sleep(0.001)
                except Exception as error:  # a half-written message: JSONDecodeError
                    errors.append(repr(error))

    threads = [threading.Thread(target=consume) for _ in range(2)] + [threading.Thread(target=produce)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert errors == []
    indices = sorted(message["headers"]["argsrepr"] for message in received)
    assert len(indices) == MESSAGES and len(set(indices)) == MESSAGES
    # Nothing is left half-written beside the queue.
    assert not list((settings.broker_dir / "queue").glob(".partial-*"))
