"""The bake, stage by stage: validate → loops (fan-out) → cycle → poses → impostors (fan-out) → pack → publish.

One module per stage, each a plain function over a per-job work folder (crowdbake.stages.workdir). A
stage reads the typed record the stage before it wrote (crowdbake.stages.records) and writes its own;
progress goes to a callback, never into the records. crowdbake.stages.runner runs them all in one
process (`crowdbake bake`); crowdbake.jobs.tasks wraps each one in a Celery task.

This package's __init__ stays free of heavy imports: the API and the database layer read STAGES.
"""

STAGES = ("validate", "loops", "cycle", "poses", "impostors", "pack", "publish")
