"""Alembic migrations upgrade and downgrade on SQLite and PostgreSQL, and match the models."""

from __future__ import annotations

from alembic.autogenerate import compare_metadata
from alembic.runtime.migration import MigrationContext
from sqlalchemy import inspect

from app import migrate
from app.db import make_engine
from app.models import Base

TABLES_AT = {
    None: set(),
    "0001": {"maps", "map_images"},
    "0002": {"maps", "map_images", "image_global_features", "image_sift"},
    "0003": {"maps", "map_images", "image_global_features", "image_sift", "build_jobs"},
    "0004": {"maps", "map_images", "image_global_features", "image_sift", "build_jobs",
             "sessions", "pose_estimates"},
    "0005": {"maps", "map_images", "image_global_features", "image_sift", "build_jobs",
             "sessions", "pose_estimates", "frames"},
    "0006": {"maps", "map_images", "image_global_features", "image_sift", "build_jobs",
             "sessions", "pose_estimates", "frames", "image_orb", "map_vocabularies"},
}


def _tables(engine) -> set[str]:
    return set(inspect(engine).get_table_names()) - {"alembic_version"}


def test_upgrade_to_head_matches_the_models(database_url):
    engine = make_engine(database_url)
    try:
        migrate.upgrade(engine)
        assert migrate.current_revision(engine) == migrate.head_revision() == "0006"
        assert _tables(engine) == TABLES_AT["0006"]
        with engine.connect() as conn:
            diff = compare_metadata(MigrationContext.configure(
                conn, opts={"compare_type": True}), Base.metadata)
        assert diff == []
    finally:
        engine.dispose()


def test_each_step_downgrades_and_upgrades_again(database_url):
    engine = make_engine(database_url)
    try:
        migrate.upgrade(engine)
        for revision in ("0005", "0004", "0003", "0002", "0001", None):
            migrate.downgrade(engine, revision or "base")
            assert migrate.current_revision(engine) == revision
            assert _tables(engine) == TABLES_AT[revision]
        for revision in ("0001", "0002", "0003", "0004", "0005", "0006"):
            migrate.upgrade(engine, revision)
            assert _tables(engine) == TABLES_AT[revision]
        names = {c["name"] for c in inspect(engine).get_unique_constraints("map_images")}
        assert names == {"uq_map_images_map_id_file_hash"}
        pk = inspect(engine).get_pk_constraint("frames")
        assert pk["constrained_columns"] == ["session_id", "seq"]
        assert {i["name"] for i in inspect(engine).get_indexes("frames")} == {
            "ix_frames_status"}
    finally:
        engine.dispose()
