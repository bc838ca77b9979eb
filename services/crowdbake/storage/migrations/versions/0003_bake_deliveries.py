"""Bake deliveries: reservations (live_key, publish_slot), stage and part heartbeats, sent marks.

Revision ID: 0003
Revises: 0002
Create Date: 2026-11-23
"""
from __future__ import annotations

from alembic import op
import sqlalchemy as sa


revision = '0003'
down_revision = '0002'
branch_labels = None
depends_on = None

DELIVERY_COLUMNS = ('queued_at', 'sent_at', 'owner', 'heartbeat_at')


def _delivery_columns():
    return [
        sa.Column('queued_at', sa.DateTime(timezone=True), nullable=True),
        sa.Column('sent_at', sa.DateTime(timezone=True), nullable=True),
        sa.Column('owner', sa.String(length=160), nullable=True),
        sa.Column('heartbeat_at', sa.DateTime(timezone=True), nullable=True),
    ]


def upgrade() -> None:
    with op.batch_alter_table('bakes', schema=None) as batch_op:
        batch_op.add_column(sa.Column('live_key', sa.String(length=64), nullable=True))
        batch_op.add_column(sa.Column('publish_slot', sa.String(length=130), nullable=True))
    # Reserve for the bakes queued or running already: the newest one per input key and per version
    # (older duplicates, which the unique columns now prevent, keep NULL).
    bakes = sa.table('bakes', sa.column('id'), sa.column('state'), sa.column('input_key'), sa.column('name'), sa.column('version'),
                     sa.column('publish'), sa.column('created_at'), sa.column('live_key'), sa.column('publish_slot'))
    connection = op.get_bind()
    keys, slots = set(), set()
    rows = connection.execute(sa.select(bakes.c.id, bakes.c.input_key, bakes.c.name, bakes.c.version, bakes.c.publish)
                              .where(bakes.c.state.in_(('queued', 'running'))).order_by(bakes.c.created_at.desc())).all()
    for bake_id, input_key, name, version, publish in rows:
        values = {}
        if input_key not in keys:
            keys.add(input_key)
            values['live_key'] = input_key
        slot = f'{name}/{version}'
        if publish and slot not in slots:
            slots.add(slot)
            values['publish_slot'] = slot
        if values:
            connection.execute(bakes.update().where(bakes.c.id == bake_id).values(**values))
    with op.batch_alter_table('bakes', schema=None) as batch_op:
        batch_op.create_unique_constraint(batch_op.f('uq_bakes_live_key'), ['live_key'])
        batch_op.create_unique_constraint(batch_op.f('uq_bakes_publish_slot'), ['publish_slot'])
    with op.batch_alter_table('bake_stages', schema=None) as batch_op:
        for column in _delivery_columns():
            batch_op.add_column(column)
    with op.batch_alter_table('bake_parts', schema=None) as batch_op:
        batch_op.add_column(sa.Column('retries', sa.Integer(), nullable=False, server_default='0'))
        for column in _delivery_columns():
            batch_op.add_column(column)


def downgrade() -> None:
    with op.batch_alter_table('bake_parts', schema=None) as batch_op:
        for name in DELIVERY_COLUMNS + ('retries',):
            batch_op.drop_column(name)
    with op.batch_alter_table('bake_stages', schema=None) as batch_op:
        for name in DELIVERY_COLUMNS:
            batch_op.drop_column(name)
    with op.batch_alter_table('bakes', schema=None) as batch_op:
        batch_op.drop_constraint(batch_op.f('uq_bakes_publish_slot'), type_='unique')
        batch_op.drop_constraint(batch_op.f('uq_bakes_live_key'), type_='unique')
        batch_op.drop_column('publish_slot')
        batch_op.drop_column('live_key')
