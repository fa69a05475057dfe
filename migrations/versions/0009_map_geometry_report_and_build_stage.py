"""map geometry report and build stage

``maps`` gains ``geometry``: what the current revision's reconstruction placed and what the
map measured of itself when it was built (JSON; NULL for maps built before, until they are
built again). ``build_jobs`` gains ``stage``: what a build is doing now.

Revision ID: 0009
Revises: 0008
Create Date: 2026-11-27
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0009"
down_revision = "0008"
branch_labels = None
depends_on = None


def upgrade() -> None:
    # Plain ADD COLUMN: rebuilding ``maps`` (a batch on SQLite) would drop it, and every
    # image and session with it through their ON DELETE CASCADE.
    op.add_column("maps", sa.Column("geometry", sa.JSON(), nullable=True))
    op.add_column("build_jobs", sa.Column("stage", sa.String(32), nullable=True))


def downgrade() -> None:
    # Plain DROP COLUMN (SQLite 3.35+), for the same reason: no table is rebuilt.
    op.drop_column("build_jobs", "stage")
    op.drop_column("maps", "geometry")
