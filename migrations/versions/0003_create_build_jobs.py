"""create build jobs

Revision ID: 0003
Revises: 0002
Create Date: 2026-11-22
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0003"
down_revision = "0002"
branch_labels = None
depends_on = None

_TIME = sa.DateTime(timezone=True)


def upgrade() -> None:
    op.create_table(
        "build_jobs",
        sa.Column("id", sa.Uuid(), nullable=False),
        sa.Column("map_id", sa.Uuid(), nullable=False),
        sa.Column("status", sa.String(16), nullable=False),
        sa.Column("progress", sa.Float(), nullable=False),
        sa.Column("error", sa.Text(), nullable=True),
        sa.Column("n_images", sa.Integer(), nullable=False),
        sa.Column("n_extracted", sa.Integer(), nullable=False),
        sa.Column("revision", sa.Integer(), nullable=True),
        sa.Column("created_at", _TIME, nullable=False),
        sa.Column("started_at", _TIME, nullable=True),
        sa.Column("finished_at", _TIME, nullable=True),
        sa.ForeignKeyConstraint(["map_id"], ["maps.id"], ondelete="CASCADE",
                                name=op.f("fk_build_jobs_map_id_maps")),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_build_jobs")),
    )
    op.create_index(op.f("ix_build_jobs_map_id"), "build_jobs", ["map_id"])


def downgrade() -> None:
    op.drop_index(op.f("ix_build_jobs_map_id"), table_name="build_jobs")
    op.drop_table("build_jobs")
