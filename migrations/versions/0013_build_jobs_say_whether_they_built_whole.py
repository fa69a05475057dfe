"""build jobs say whether they built the map whole

``build_jobs`` gains ``full``: the build reconstructs the map's geometry whole and trains
its place vocabularies afresh instead of carrying over what the revision before worked out
(``POST /v1/maps/{id}/build?full=true``). Jobs before it were not asked: false.

Revision ID: 0013
Revises: 0012
Create Date: 2026-12-01
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0013"
down_revision = "0012"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.add_column("build_jobs", sa.Column("full", sa.Boolean(), nullable=False,
                                          server_default=sa.false()))


def downgrade() -> None:
    op.drop_column("build_jobs", "full")
