"""The bake, stage by stage: validate → loops (fan-out) → cycle → poses → impostors (fan-out) → pack → publish.

One module per stage, each a plain function over a per-job work folder (crowdbake.stages.workdir). A
stage reads the typed record the stage before it wrote (crowdbake.stages.records) and writes its own;
progress goes to a callback, never into the records. crowdbake.stages.runner runs them all in one
process (`crowdbake bake`); crowdbake.jobs.tasks wraps each one in a Celery task.

The stage names themselves are crowdbake.stage_names', which the database layer reads too.
"""

from crowdbake.stage_names import STAGES  # noqa: F401 (the stages' own name for them)
