"""map revisions

``map_revisions``: one row per packed revision of a map (what it holds, what changed since
the revision it was built on, its local frame and geometry report, when it was dropped), so
that a map can be restored to an earlier revision and old revisions dropped. A built map's current revision
gets its row from ``maps``; revisions packed before this migration and since replaced have
no record of their frame and are not listed (their folders stay until the map is deleted).

Revision ID: 0010
Revises: 0009
Create Date: 2026-11-27
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0010"
down_revision = "0009"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "map_revisions",
        sa.Column("map_id", sa.Uuid(), sa.ForeignKey("maps.id", ondelete="CASCADE"),
                  primary_key=True),
        sa.Column("revision", sa.Integer(), primary_key=True),
        sa.Column("built_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("job_id", sa.Uuid(), nullable=True),
        sa.Column("base_revision", sa.Integer(), nullable=False),
        sa.Column("image_count", sa.Integer(), nullable=False),
        sa.Column("added", sa.Integer(), nullable=False),
        sa.Column("removed", sa.Integer(), nullable=False),
        sa.Column("origin_lat", sa.Float(), nullable=False),
        sa.Column("origin_lon", sa.Float(), nullable=False),
        sa.Column("origin_alt", sa.Float(), nullable=True),
        sa.Column("geometry", sa.JSON(), nullable=True),
        sa.Column("dropped_at", sa.DateTime(timezone=True), nullable=True),
    )
    # the current revision of every built map, from what the map row holds of it
    op.execute("""
        INSERT INTO map_revisions (map_id, revision, built_at, job_id, base_revision,
                                   image_count, added, removed, origin_lat, origin_lon,
                                   origin_alt, geometry)
        SELECT m.id, m.revision, COALESCE(m.built_at, m.created_at), NULL, m.revision - 1,
               (SELECT count(*) FROM map_images i
                 WHERE i.map_id = m.id AND i.built_revision IS NOT NULL),
               (SELECT count(*) FROM map_images i
                 WHERE i.map_id = m.id AND i.built_revision = m.revision),
               0, m.origin_lat, m.origin_lon, m.origin_alt, m.geometry
          FROM maps m
         WHERE m.revision > 0 AND m.origin_lat IS NOT NULL AND m.origin_lon IS NOT NULL
    """)


def downgrade() -> None:
    op.drop_table("map_revisions")
