"""create map vocabularies and the map images' ORB features

The place descriptors (VLAD, bag of words) need a vocabulary trained on each map revision's
own local features: ``map_vocabularies`` keeps it per revision, ``image_orb`` the ORB
features of every map image it is trained on (RootSIFT comes from ``image_sift``).

Revision ID: 0006
Revises: 0005
Create Date: 2026-11-23
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0006"
down_revision = "0005"
branch_labels = None
depends_on = None

_IMAGE_ID = sa.BigInteger().with_variant(sa.Integer(), "sqlite")


def upgrade() -> None:
    op.create_table(
        "image_orb",
        sa.Column("image_id", _IMAGE_ID, nullable=False),
        sa.Column("n_keypoints", sa.Integer(), nullable=False),
        sa.Column("keypoints", sa.LargeBinary(), nullable=False),
        sa.Column("descriptors", sa.LargeBinary(), nullable=False),
        sa.ForeignKeyConstraint(["image_id"], ["map_images.id"], ondelete="CASCADE",
                                name=op.f("fk_image_orb_image_id_map_images")),
        sa.PrimaryKeyConstraint("image_id", name=op.f("pk_image_orb")),
    )
    op.create_table(
        "map_vocabularies",
        sa.Column("map_id", sa.Uuid(), nullable=False),
        sa.Column("revision", sa.Integer(), nullable=False),
        sa.Column("name", sa.String(32), nullable=False),
        sa.Column("branching", sa.Integer(), nullable=False),
        sa.Column("depth", sa.Integer(), nullable=False),
        sa.Column("binary", sa.Boolean(), nullable=False),
        sa.Column("dim", sa.Integer(), nullable=False),
        sa.Column("centroids", sa.LargeBinary(), nullable=False),
        sa.Column("idf", sa.LargeBinary(), nullable=False),
        sa.Column("projection", sa.LargeBinary(), nullable=True),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(["map_id"], ["maps.id"], ondelete="CASCADE",
                                name=op.f("fk_map_vocabularies_map_id_maps")),
        sa.PrimaryKeyConstraint("map_id", "revision", "name", name=op.f("pk_map_vocabularies")),
    )


def downgrade() -> None:
    op.drop_table("map_vocabularies")
    op.drop_table("image_orb")
