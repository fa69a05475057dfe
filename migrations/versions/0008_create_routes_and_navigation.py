"""create route maps (images, nodes, arcs) and the navigation of sessions and poses

A route is a taught image sequence of a map with odometry (Li et al.): ``routes`` holds it,
``route_images`` its images in driving order with their odometry and relaxed poses,
``route_nodes`` and ``route_arcs`` the topological map. A session that follows a route keeps
the route's path in ``sessions.navigation``; each pose of it says how the path following
went in ``pose_estimates.navigation``.

Revision ID: 0008
Revises: 0006
Create Date: 2026-11-24
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0008"
down_revision = "0007"
branch_labels = None
depends_on = None

_IMAGE_ID = sa.BigInteger().with_variant(sa.Integer(), "sqlite")
_TIME = sa.DateTime(timezone=True)


def _route_fk(table: str) -> sa.ForeignKeyConstraint:
    return sa.ForeignKeyConstraint(["route_id"], ["routes.id"], ondelete="CASCADE",
                                   name=op.f(f"fk_{table}_route_id_routes"))


def upgrade() -> None:
    op.create_table(
        "routes",
        sa.Column("id", sa.Uuid(), nullable=False),
        sa.Column("map_id", sa.Uuid(), nullable=False),
        sa.Column("name", sa.String(200), nullable=False),
        sa.Column("status", sa.String(16), nullable=False),
        sa.Column("error", sa.Text(), nullable=True),
        sa.Column("params", sa.JSON(), nullable=False),
        sa.Column("n_images", sa.Integer(), nullable=False),
        sa.Column("n_nodes", sa.Integer(), nullable=True),
        sa.Column("n_loops", sa.Integer(), nullable=True),
        sa.Column("length_m", sa.Float(), nullable=True),
        sa.Column("sweeps", sa.Integer(), nullable=True),
        sa.Column("created_at", _TIME, nullable=False),
        sa.Column("built_at", _TIME, nullable=True),
        sa.ForeignKeyConstraint(["map_id"], ["maps.id"], ondelete="CASCADE",
                                name=op.f("fk_routes_map_id_maps")),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_routes")),
    )
    op.create_index(op.f("ix_routes_map_id"), "routes", ["map_id"])
    op.create_table(
        "route_images",
        sa.Column("route_id", sa.Uuid(), nullable=False),
        sa.Column("seq", sa.Integer(), autoincrement=False, nullable=False),
        sa.Column("image_id", _IMAGE_ID, nullable=True),
        sa.Column("filename", sa.String(255), nullable=False),
        sa.Column("odom_x", sa.Float(), nullable=False),
        sa.Column("odom_y", sa.Float(), nullable=False),
        sa.Column("odom_theta", sa.Float(), nullable=False),
        sa.Column("lat", sa.Float(), nullable=True),
        sa.Column("lon", sa.Float(), nullable=True),
        sa.Column("node", sa.Integer(), nullable=True),
        sa.Column("x", sa.Float(), nullable=True),
        sa.Column("y", sa.Float(), nullable=True),
        sa.Column("theta", sa.Float(), nullable=True),
        _route_fk("route_images"),
        sa.ForeignKeyConstraint(["image_id"], ["map_images.id"], ondelete="SET NULL",
                                name=op.f("fk_route_images_image_id_map_images")),
        sa.PrimaryKeyConstraint("route_id", "seq", name=op.f("pk_route_images")),
    )
    op.create_table(
        "route_nodes",
        sa.Column("route_id", sa.Uuid(), nullable=False),
        sa.Column("idx", sa.Integer(), autoincrement=False, nullable=False),
        sa.Column("first_seq", sa.Integer(), nullable=False),
        sa.Column("last_seq", sa.Integer(), nullable=False),
        sa.Column("odom_x", sa.Float(), nullable=False),
        sa.Column("odom_y", sa.Float(), nullable=False),
        sa.Column("odom_theta", sa.Float(), nullable=False),
        sa.Column("x", sa.Float(), nullable=False),
        sa.Column("y", sa.Float(), nullable=False),
        sa.Column("theta", sa.Float(), nullable=False),
        sa.Column("variance", sa.Float(), nullable=False),
        _route_fk("route_nodes"),
        sa.PrimaryKeyConstraint("route_id", "idx", name=op.f("pk_route_nodes")),
    )
    op.create_table(
        "route_arcs",
        sa.Column("route_id", sa.Uuid(), nullable=False),
        sa.Column("idx", sa.Integer(), autoincrement=False, nullable=False),
        sa.Column("node_a", sa.Integer(), nullable=False),
        sa.Column("node_b", sa.Integer(), nullable=False),
        sa.Column("dx", sa.Float(), nullable=False),
        sa.Column("dy", sa.Float(), nullable=False),
        sa.Column("dtheta", sa.Float(), nullable=False),
        sa.Column("variance", sa.Float(), nullable=False),
        sa.Column("kind", sa.String(16), nullable=False),
        _route_fk("route_arcs"),
        sa.PrimaryKeyConstraint("route_id", "idx", name=op.f("pk_route_arcs")),
    )
    with op.batch_alter_table("sessions") as batch:
        batch.add_column(sa.Column("navigation", sa.JSON(), nullable=True))
    with op.batch_alter_table("pose_estimates") as batch:
        batch.add_column(sa.Column("navigation", sa.JSON(), nullable=True))


def downgrade() -> None:
    # A plain column drop: a batch copy of ``sessions`` would drop the table, and with it
    # (ON DELETE CASCADE) every stored pose on SQLite.
    op.drop_column("pose_estimates", "navigation")
    op.drop_column("sessions", "navigation")
    op.drop_table("route_arcs")
    op.drop_table("route_nodes")
    op.drop_table("route_images")
    op.drop_index(op.f("ix_routes_map_id"), table_name="routes")
    op.drop_table("routes")
