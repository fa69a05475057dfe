"""create localisation sessions and pose estimates

Revision ID: 0004
Revises: 0003
Create Date: 2026-11-22
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0004"
down_revision = "0003"
branch_labels = None
depends_on = None

_ID = sa.BigInteger().with_variant(sa.Integer(), "sqlite")
_TIME = sa.DateTime(timezone=True)


def upgrade() -> None:
    op.create_table(
        "sessions",
        sa.Column("id", sa.Uuid(), nullable=False),
        sa.Column("map_id", sa.Uuid(), nullable=False),
        sa.Column("map_revision", sa.Integer(), nullable=False),
        sa.Column("mode", sa.String(16), nullable=False),
        sa.Column("params", sa.JSON(), nullable=False),
        sa.Column("seed", sa.BigInteger(), nullable=False),
        sa.Column("token_hash", sa.String(64), nullable=False),
        sa.Column("last_seq", sa.BigInteger(), nullable=True),
        sa.Column("state", sa.LargeBinary(), nullable=True),
        sa.Column("state_seq", sa.BigInteger(), nullable=True),
        sa.Column("frames_processed", sa.Integer(), nullable=False),
        sa.Column("frames_failed", sa.Integer(), nullable=False),
        sa.Column("created_at", _TIME, nullable=False),
        sa.Column("updated_at", _TIME, nullable=False),
        sa.ForeignKeyConstraint(["map_id"], ["maps.id"], ondelete="CASCADE",
                                name=op.f("fk_sessions_map_id_maps")),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_sessions")),
    )
    op.create_index(op.f("ix_sessions_map_id"), "sessions", ["map_id"])
    op.create_table(
        "pose_estimates",
        sa.Column("id", _ID, autoincrement=True, nullable=False),
        sa.Column("session_id", sa.Uuid(), nullable=False),
        sa.Column("seq", sa.BigInteger(), nullable=False),
        sa.Column("captured_at", _TIME, nullable=True),
        sa.Column("received_at", _TIME, nullable=False),
        *(sa.Column(name, sa.Float(), nullable=False)
          for name in ("x", "y", "lat", "lon", "sigma_x", "sigma_y",
                       "cov_xx", "cov_xy", "cov_yx", "cov_yy")),
        sa.Column("feature", sa.String(32), nullable=False),
        sa.Column("next_feature", sa.String(32), nullable=False),
        sa.Column("n_particles", sa.Integer(), nullable=False),
        sa.Column("status", sa.String(16), nullable=False),
        sa.Column("best_image", sa.Integer(), nullable=False),
        sa.Column("decode_ms", sa.Float(), nullable=False),
        sa.Column("processing_ms", sa.Float(), nullable=False),
        sa.Column("latency_ms", sa.Float(), nullable=False),
        sa.ForeignKeyConstraint(["session_id"], ["sessions.id"], ondelete="CASCADE",
                                name=op.f("fk_pose_estimates_session_id_sessions")),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_pose_estimates")),
        sa.UniqueConstraint("session_id", "seq", name=op.f("uq_pose_estimates_session_id_seq")),
    )
    op.create_index(op.f("ix_pose_estimates_session_id"), "pose_estimates", ["session_id"])


def downgrade() -> None:
    op.drop_index(op.f("ix_pose_estimates_session_id"), table_name="pose_estimates")
    op.drop_table("pose_estimates")
    op.drop_index(op.f("ix_sessions_map_id"), table_name="sessions")
    op.drop_table("sessions")
