"""Progress for a log (crowdbake.cli.common.StageLines): a bake whose stderr is no terminal (a CI job)
prints one line as each stage starts and one as it ends, not nothing for a minute."""
from __future__ import annotations

import io

from crowdbake.cli.common import StageLines


def test_one_line_when_a_stage_starts_and_one_when_it_has_done_every_item():
    stream = io.StringIO()
    lines = StageLines("bake", stream)
    for stage, done, total in [("cycle", 0, 1), ("impostors", 0, 3), ("impostors", 1, 3), ("cycle", 1, 1),
                               ("impostors", 2, 3), ("impostors", 3, 3), ("impostors", 3, 3)]:
        lines(stage, done, total)
    printed = stream.getvalue().splitlines()
    assert [line.split(" done in")[0] for line in printed] == [
        "bake: cycle started (1 item)", "bake: impostors started (3 items)", "bake: cycle", "bake: impostors"]
    assert all(line.endswith(" s") for line in printed[2:])


def test_a_stage_of_one_finished_item_starts_and_ends_at_once():
    stream = io.StringIO()
    StageLines("export", stream)("publish", 1, 1)
    assert stream.getvalue().splitlines()[0] == "export: publish started (1 item)"
    assert stream.getvalue().splitlines()[1].startswith("export: publish done in ")


def test_a_cancelled_outcome_takes_its_late_result_quietly(caplog):
    """Regression: when a bake failed while pool items still ran, the runner cancelled their outcomes and
    each late result raised InvalidStateError in the pool's done-callback (a logged traceback before the
    bake's one-line error)."""
    import threading
    from concurrent.futures import ThreadPoolExecutor

    from crowdbake.stages.worker_pool import submit_in_background

    started, release = threading.Event(), threading.Event()
    with caplog.at_level("ERROR", logger="concurrent.futures"), ThreadPoolExecutor(1) as pool:
        late = submit_in_background(pool, lambda: (started.set(), release.wait(10)))
        assert started.wait(10)  # running in the pool: its result comes after the cancel
        assert late.cancel()
        release.set()
    assert late.cancelled()
    assert not [record for record in caplog.records if "exception calling callback" in record.getMessage()], caplog.text
