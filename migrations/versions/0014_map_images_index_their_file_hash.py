"""map images index their file's hash

``map_images`` gains an index on ``file_hash``. A build looks for other maps' images of the
same file (their tie points are lent, not extracted again) with one join on the hash, and
the unique constraint on (map_id, file_hash) cannot serve a join across maps: SQLite then
scans every map image for each of the map's own, 10.4 s for a 12,000-image database and
growing with its square; with the index, 0.05 s.

Revision ID: 0014
Revises: 0013
Create Date: 2026-12-08
"""

from __future__ import annotations

from alembic import op

revision = "0014"
down_revision = "0013"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_index(op.f("ix_map_images_file_hash"), "map_images", ["file_hash"])


def downgrade() -> None:
    op.drop_index(op.f("ix_map_images_file_hash"), table_name="map_images")
