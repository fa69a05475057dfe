"""map images name their flight

``map_images`` gains ``flight``: the flight (or pass) an image was uploaded as part of, where
the upload said so (NULL otherwise: such images are grouped into flights by their capture
times, as every image was before).

Revision ID: 0012
Revises: 0011
Create Date: 2026-11-28
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0012"
down_revision = "0011"
branch_labels = None
depends_on = None


def upgrade() -> None:
    # Plain ADD COLUMN: rebuilding the table (a batch on SQLite) would drop it, and its
    # features with it through ON DELETE CASCADE.
    op.add_column("map_images", sa.Column("flight", sa.String(64), nullable=True))


def downgrade() -> None:
    op.drop_column("map_images", "flight")
