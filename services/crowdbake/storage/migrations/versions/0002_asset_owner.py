"""Assets are unique per owner: (kind, digest, created_by) instead of (kind, digest).

Two keys that upload the same bytes each get an asset of their own (the blobs, addressed by sha256,
are stored once), so no key is handed an asset it cannot read.

Revision ID: 0002
Revises: 0001
Create Date: 2026-11-23
"""
from __future__ import annotations

from alembic import op


revision = '0002'
down_revision = '0001'
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table('assets') as batch:
        batch.drop_constraint('uq_assets_kind_digest', type_='unique')
        batch.create_unique_constraint('uq_assets_kind_digest_owner', ['kind', 'digest', 'created_by'])


def downgrade() -> None:
    with op.batch_alter_table('assets') as batch:
        batch.drop_constraint('uq_assets_kind_digest_owner', type_='unique')
        batch.create_unique_constraint('uq_assets_kind_digest', ['kind', 'digest'])
