"""The probes stage (the impostor plan's probes drawn side by side): a stage row for every bake made before it.

Revision ID: 0005
Revises: 0004
Create Date: 2026-12-07

Data only. Every bake gets a `probes` row after `cycle` (the later rows move one position down): pending
where the bake has not reached its poses stage yet, so that it runs when the bake gets there, else skipped
(the poses stage draws any probe not drawn yet itself). Without the row a queued or retried bake could not go on.
"""
from __future__ import annotations

from alembic import op
import sqlalchemy as sa


revision = '0005'
down_revision = '0004'
branch_labels = None
depends_on = None

STAGE = 'probes'


def _stages():
    return sa.table('bake_stages', sa.column('bake_id'), sa.column('stage'), sa.column('position'), sa.column('state'),
                    sa.column('done'), sa.column('total'), sa.column('retries'))


def upgrade() -> None:
    stages = _stages()
    connection = op.get_bind()
    have = {row.bake_id for row in connection.execute(sa.select(stages.c.bake_id).where(stages.c.stage == STAGE))}
    cycles = {row.bake_id: row.position for row in connection.execute(sa.select(stages.c.bake_id, stages.c.position).where(stages.c.stage == 'cycle'))}
    poses = dict(connection.execute(sa.select(stages.c.bake_id, stages.c.state).where(stages.c.stage == 'poses')).all())
    for bake_id, cycle_position in cycles.items():
        if bake_id in have:
            continue
        connection.execute(stages.update().where(stages.c.bake_id == bake_id, stages.c.position > cycle_position)
                           .values(position=stages.c.position + 1))
        connection.execute(stages.insert().values(bake_id=bake_id, stage=STAGE, position=cycle_position + 1, done=0, total=0, retries=0,
                                                  state='pending' if poses.get(bake_id) == 'pending' else 'skipped'))


def downgrade() -> None:
    stages = _stages()
    connection = op.get_bind()
    rows = connection.execute(sa.select(stages.c.bake_id, stages.c.position).where(stages.c.stage == STAGE)).all()
    connection.execute(stages.delete().where(stages.c.stage == STAGE))
    for bake_id, position in rows:
        connection.execute(stages.update().where(stages.c.bake_id == bake_id, stages.c.position > position)
                           .values(position=stages.c.position - 1))
    op.execute(sa.text("DELETE FROM bake_parts WHERE stage = 'probes'"))
