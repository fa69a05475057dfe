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

import math

import numpy as np
import sqlalchemy as sa
from alembic import op
from scipy.optimize import brentq
from scipy.special import erf, erfinv

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
    conn = op.get_bind()
    poses = sa.table("pose_estimates", sa.column("id"), sa.column("cov_xx"),
                     sa.column("cov_xy"), sa.column("cov_yx"), sa.column("cov_yy"),
                     sa.column("horizontal_accuracy_m"))
    rows = conn.execute(sa.select(poses.c.id, poses.c.cov_xx, poses.c.cov_xy, poses.c.cov_yx,
                                  poses.c.cov_yy)).all()
    if rows:
        conn.execute(poses.update().where(poses.c.id == sa.bindparam("b_id"))
                     .values(horizontal_accuracy_m=sa.bindparam("b_acc")),
                     [{"b_id": r[0], "b_acc": _horizontal_accuracy(r[1:])} for r in rows])


# The accuracy as workers/core/accuracy.py computed it when this revision was written, kept
# here so that what the migration stores never changes with the core: the radius of the
# circle about the estimate holding the position with probability 68 %, exact for a
# bivariate normal error (the integral by Gauss-Legendre, the root by Brent's method).
_CONFIDENCE = 0.68
_NODES, _WEIGHTS = np.polynomial.legendre.leggauss(48)


def _horizontal_accuracy(cov) -> float:
    """Radius (metres) for a (2, 2) covariance given as 4 floats, row-major; 0 for a zero
    covariance, NaN when it is not finite."""
    p = _CONFIDENCE
    c = np.asarray(cov, np.float64).reshape(2, 2)
    if not np.all(np.isfinite(c)):
        return math.nan
    lam = np.clip(np.linalg.eigvalsh((c + c.T) / 2.0), 0.0, None)
    l2, l1 = float(lam[0]), float(lam[1])
    if l1 == 0.0:
        return 0.0
    if l2 <= 1e-12 * l1:
        return float(math.sqrt(2.0 * l1) * erfinv(p))
    k = math.sqrt(-2.0 * math.log1p(-p))
    lo, hi = k * math.sqrt(l2), k * math.sqrt(l1)
    if hi - lo <= 1e-12 * hi:
        return hi
    return float(brentq(lambda r: _within(r, l1, l2) - p, lo, hi, xtol=1e-12 * hi,
                        rtol=1e-12))


def _within(r: float, l1: float, l2: float) -> float:
    """P(l1 Z1^2 + l2 Z2^2 < r^2), by Gauss-Legendre after z1 = (r / sqrt(l1)) sin t."""
    a = r / math.sqrt(l1)
    t = 0.5 * math.pi * _NODES
    z = a * np.sin(t)
    phi = np.exp(-0.5 * z * z) / math.sqrt(2.0 * math.pi)
    inner = erf(r * np.cos(t) / math.sqrt(2.0 * l2))
    return float(0.5 * math.pi * a * np.sum(_WEIGHTS * phi * inner * np.cos(t)))


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
