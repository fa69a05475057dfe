"""create image feature tables (global vectors and raw SIFT)

Revision ID: 0002
Revises: 0001
Create Date: 2026-11-22
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0002"
down_revision = "0001"
branch_labels = None
depends_on = None

_IMAGE_ID = sa.BigInteger().with_variant(sa.Integer(), "sqlite")


def upgrade() -> None:
    op.create_table(
        "image_global_features",
        sa.Column("image_id", _IMAGE_ID, nullable=False),
        sa.Column("name", sa.String(32), nullable=False),
        sa.Column("dim", sa.Integer(), nullable=False),
        sa.Column("data", sa.LargeBinary(), nullable=False),
        sa.ForeignKeyConstraint(["image_id"], ["map_images.id"], ondelete="CASCADE",
                                name=op.f("fk_image_global_features_image_id_map_images")),
        sa.PrimaryKeyConstraint("image_id", "name", name=op.f("pk_image_global_features")),
    )
    op.create_table(
        "image_sift",
        sa.Column("image_id", _IMAGE_ID, nullable=False),
        sa.Column("n_keypoints", sa.Integer(), nullable=False),
        sa.Column("keypoints", sa.LargeBinary(), nullable=False),
        sa.Column("descriptors", sa.LargeBinary(), nullable=False),
        sa.ForeignKeyConstraint(["image_id"], ["map_images.id"], ondelete="CASCADE",
                                name=op.f("fk_image_sift_image_id_map_images")),
        sa.PrimaryKeyConstraint("image_id", name=op.f("pk_image_sift")),
    )


def downgrade() -> None:
    op.drop_table("image_sift")
    op.drop_table("image_global_features")
