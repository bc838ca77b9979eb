"""The bake's stages by name, in order, and which of them fan out: the words the stages
(crowdbake.stages), the service's tasks (crowdbake.jobs) and the database (crowdbake.storage) share.
Plain data at the bottom of the house, so the database layer reads it without importing the stages.
"""

STAGES = ("validate", "loops", "cycle", "probes", "poses", "impostors", "pack", "publish")

# The stages that are one fan-out node alone: the service runs their items as parallel tasks, their
# own rows are never sent, and their seconds add up over the parts. crowdbake.stages.plan.plan_problems
# checks this against the plan.
FAN_OUT_STAGES = ("loops", "probes", "impostors")
