"""sessions follow their maps

``sessions`` gains ``follows_map``: whether the session moves to its map's new revision
when the map is rebuilt or restored. Sessions created before were fixed to the revision
they were created on and keep that (false); new ones follow unless they pin a revision.
``pose_estimates`` gains ``map_revision``: the revision each estimate was made on (NULL for
the poses stored before, made on their session's revision).

Revision ID: 0011
Revises: 0010
Create Date: 2026-11-28
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0011"
down_revision = "0010"
branch_labels = None
depends_on = None


def upgrade() -> None:
    # Plain ADD COLUMN: rebuilding a table (a batch on SQLite) would drop it, and what
    # refers to it with it through ON DELETE CASCADE.
    op.add_column("sessions", sa.Column("follows_map", sa.Boolean(), nullable=False,
                                        server_default=sa.false()))
    op.add_column("pose_estimates", sa.Column("map_revision", sa.Integer(), nullable=True))


def downgrade() -> None:
    # Plain DROP COLUMN (SQLite 3.35+), for the same reason: no table is rebuilt.
    op.drop_column("pose_estimates", "map_revision")
    op.drop_column("sessions", "follows_map")
