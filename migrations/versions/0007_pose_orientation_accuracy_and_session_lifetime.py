"""pose orientation, accuracy, convergence and matched image; session state and lifetime

``pose_estimates`` gains what a positioning client expects of a pose: the heading (and its
source), the device's altitude, one horizontal accuracy figure (68 %, from the covariance,
computed here for the poses stored before), the converged flag, what the step measured and
used, and the matched image by id and file name in place of its index in the packed map.
``sessions`` gains a state (``active``, ``expired``), a time to live and the time of its last
activity.

Revision ID: 0007
Revises: 0006
Create Date: 2026-11-24
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0007"
down_revision = "0006"
branch_labels = None
depends_on = None

_IMAGE_ID = sa.BigInteger().with_variant(sa.Integer(), "sqlite")
_TIME = sa.DateTime(timezone=True)
DEFAULT_TTL_S = 3600


def upgrade() -> None:
    with op.batch_alter_table("pose_estimates") as batch:
        batch.add_column(sa.Column("converged", sa.Boolean(), nullable=False,
                                   server_default=sa.false()))
        batch.add_column(sa.Column("altitude_m", sa.Float(), nullable=True))
        batch.add_column(sa.Column("horizontal_accuracy_m", sa.Float(), nullable=False,
                                   server_default="0"))
        batch.add_column(sa.Column("heading_deg", sa.Float(), nullable=True))
        batch.add_column(sa.Column("heading_sigma_deg", sa.Float(), nullable=True))
        batch.add_column(sa.Column("heading_source", sa.String(16), nullable=True))
        for name in ("measurement", "metadata_used"):
            batch.add_column(sa.Column(name, sa.String(64), nullable=False, server_default=""))
        batch.add_column(sa.Column("gps_gate", sa.String(16), nullable=False, server_default=""))
        batch.add_column(sa.Column("image_id", _IMAGE_ID, nullable=True))
        batch.add_column(sa.Column("image_filename", sa.String(255), nullable=True))
        batch.drop_column("best_image")
    _fill_accuracy()
    # Plain ADD COLUMN: rebuilding ``sessions`` (a batch on SQLite) would drop it, and its
    # frames and poses with it through their ON DELETE CASCADE.
    op.add_column("sessions", sa.Column("status", sa.String(16), nullable=False,
                                        server_default="active"))
    op.add_column("sessions", sa.Column("ttl_s", sa.Integer(), nullable=False,
                                        server_default=str(DEFAULT_TTL_S)))
    op.add_column("sessions", sa.Column("last_active_at", _TIME, nullable=True))
    op.execute("UPDATE sessions SET last_active_at = updated_at")
    op.create_index(op.f("ix_sessions_status"), "sessions", ["status"])


def _fill_accuracy() -> None:
    """The accuracy of the poses stored before, from their covariance."""
    from vloc.workers.core.accuracy import horizontal_accuracy

    conn = op.get_bind()
    poses = sa.table("pose_estimates", sa.column("id"), sa.column("cov_xx"),
                     sa.column("cov_xy"), sa.column("cov_yx"), sa.column("cov_yy"),
                     sa.column("horizontal_accuracy_m"))
    rows = conn.execute(sa.select(poses.c.id, poses.c.cov_xx, poses.c.cov_xy, poses.c.cov_yx,
                                  poses.c.cov_yy)).all()
    if rows:
        conn.execute(poses.update().where(poses.c.id == sa.bindparam("b_id"))
                     .values(horizontal_accuracy_m=sa.bindparam("b_acc")),
                     [{"b_id": r[0], "b_acc": horizontal_accuracy(r[1:])} for r in rows])


def downgrade() -> None:
    op.drop_index(op.f("ix_sessions_status"), table_name="sessions")
    for name in ("last_active_at", "ttl_s", "status"):
        op.drop_column("sessions", name)
    with op.batch_alter_table("pose_estimates") as batch:
        batch.add_column(sa.Column("best_image", sa.Integer(), nullable=False,
                                   server_default="-1"))
        for name in ("image_filename", "image_id", "gps_gate", "metadata_used",
                     "measurement", "heading_source", "heading_sigma_deg", "heading_deg",
                     "horizontal_accuracy_m", "altitude_m", "converged"):
            batch.drop_column(name)
