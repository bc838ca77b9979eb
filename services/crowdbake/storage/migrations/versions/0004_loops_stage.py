"""The loops stage (a timeline's clips searched side by side): a stage row for every bake made before it.

Revision ID: 0004
Revises: 0003
Create Date: 2026-11-27

Data only. Every bake gets a `loops` row after `validate` (the later rows move one position down): pending
where the bake has not reached its cycle stage yet, so that it runs when the bake gets there, else skipped
(the cycle stage searched every clip itself). Without the row a queued or retried bake could not go on.
"""
from __future__ import annotations

from alembic import op
import sqlalchemy as sa


revision = '0004'
down_revision = '0003'
branch_labels = None
depends_on = None

STAGE = 'loops'


def _stages():
    return sa.table('bake_stages', sa.column('bake_id'), sa.column('stage'), sa.column('position'), sa.column('state'),
                    sa.column('done'), sa.column('total'), sa.column('retries'))


def upgrade() -> None:
    stages = _stages()
    connection = op.get_bind()
    have = {row.bake_id for row in connection.execute(sa.select(stages.c.bake_id).where(stages.c.stage == STAGE))}
    cycles = connection.execute(sa.select(stages.c.bake_id, stages.c.state).where(stages.c.stage == 'cycle')).all()
    for bake_id, cycle_state in cycles:
        if bake_id in have:
            continue
        connection.execute(stages.update().where(stages.c.bake_id == bake_id, stages.c.stage != 'validate')
                           .values(position=stages.c.position + 1))
        connection.execute(stages.insert().values(bake_id=bake_id, stage=STAGE, position=1, done=0, total=0, retries=0,
                                                  state='pending' if cycle_state == 'pending' else 'skipped'))


def downgrade() -> None:
    stages = _stages()
    connection = op.get_bind()
    bakes = [row.bake_id for row in connection.execute(sa.select(stages.c.bake_id).where(stages.c.stage == STAGE))]
    connection.execute(stages.delete().where(stages.c.stage == STAGE))
    for bake_id in bakes:
        connection.execute(stages.update().where(stages.c.bake_id == bake_id, stages.c.stage != 'validate')
                           .values(position=stages.c.position - 1))
    op.execute(sa.text("DELETE FROM bake_parts WHERE stage = 'loops'"))
