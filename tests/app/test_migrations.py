"""Alembic migrations upgrade and downgrade on SQLite and PostgreSQL, and match the models."""

from __future__ import annotations

from alembic.autogenerate import compare_metadata
from alembic.runtime.migration import MigrationContext
from sqlalchemy import inspect

from vloc.app import migrate
from vloc.app.db import make_engine
from vloc.app.models import Base

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
TABLES_AT["0007"] = TABLES_AT["0006"]
TABLES_AT["0008"] = TABLES_AT["0006"] | {"routes", "route_images", "route_nodes", "route_arcs"}
TABLES_AT["0009"] = TABLES_AT["0008"]
TABLES_AT["0010"] = TABLES_AT["0009"] | {"map_revisions"}
TABLES_AT["0011"] = TABLES_AT["0010"]
TABLES_AT["0012"] = TABLES_AT["0011"]
TABLES_AT["0013"] = TABLES_AT["0012"]
TABLES_AT["0014"] = TABLES_AT["0013"]


def _tables(engine) -> set[str]:
    return set(inspect(engine).get_table_names()) - {"alembic_version"}


def test_upgrade_to_head_matches_the_models(database_url):
    engine = make_engine(database_url)
    try:
        migrate.upgrade(engine)
        assert migrate.current_revision(engine) == migrate.head_revision() == "0014"
        assert _tables(engine) == TABLES_AT["0014"]
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
        for revision in ("0006", "0005", "0004", "0003", "0002", "0001", None):
            migrate.downgrade(engine, revision or "base")
            assert migrate.current_revision(engine) == revision
            assert _tables(engine) == TABLES_AT[revision]
        for revision in ("0001", "0002", "0003", "0004", "0005", "0006", "0007", "0008",
                         "0009", "0010", "0011"):
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


def _a_session_with_a_pose_at_0006(engine, sid, mid, now) -> None:
    """Upgrade to 0006 and store a map, a session on it and one pose as 0006 had them."""
    from sqlalchemy import text

    ids = (lambda u: u.hex) if engine.dialect.name == "sqlite" else (lambda u: u)
    migrate.upgrade(engine, "0006")
    with engine.begin() as conn:
        conn.execute(text("INSERT INTO maps (id, name, status, revision, created_at) "
                          "VALUES (:id, 'm', 'ready', 1, :t)"), {"id": ids(mid), "t": now})
        conn.execute(text(
            "INSERT INTO sessions (id, map_id, map_revision, mode, params, seed, token_hash,"
            " frames_processed, frames_failed, created_at, updated_at) VALUES (:id, :m, 1,"
            " 'hybrid', '{}', 1, 'h', 1, 0, :t, :t)"), {"id": ids(sid), "m": ids(mid), "t": now})
        conn.execute(text(
            "INSERT INTO pose_estimates (session_id, seq, received_at, x, y, lat, lon, "
            "sigma_x, sigma_y, cov_xx, cov_xy, cov_yx, cov_yy, feature, next_feature, "
            "n_particles, status, best_image, decode_ms, processing_ms, latency_ms) VALUES "
            "(:s, 0, :t, 0, 0, 41, -83, 2, 2, 4, 0, 0, 4, 'sift', 'sift', 60, 'tracking', 3,"
            " 1, 1, 1)"), {"s": ids(sid), "t": now})


def test_0007_keeps_stored_poses_and_gives_them_an_accuracy(database_url):
    """A pose stored at 0006 is still there at 0007, with the 68 % radius of its
    covariance, no heading and an active session with the default time to live."""
    import math
    import uuid
    from datetime import UTC, datetime

    from sqlalchemy import text

    engine = make_engine(database_url)
    sid, mid = uuid.uuid4(), uuid.uuid4()
    now = datetime.now(UTC)
    try:
        _a_session_with_a_pose_at_0006(engine, sid, mid, now)
        migrate.upgrade(engine)
        with engine.connect() as conn:
            pose = conn.execute(text("SELECT horizontal_accuracy_m, heading_deg, image_id, "
                                     "converged, gps_gate FROM pose_estimates")).one()
            session = conn.execute(text("SELECT status, ttl_s, last_active_at FROM sessions"))\
                .one()
        assert math.isclose(pose[0], 2.0 * math.sqrt(-2.0 * math.log(0.32)), rel_tol=1e-9)
        assert pose[1:] == (None, None, False, "")
        assert session[0] == "active" and session[1] == 3600 and session[2] is not None
        migrate.downgrade(engine, "0006")
        with engine.connect() as conn:
            assert conn.execute(text("SELECT best_image FROM pose_estimates")).scalar() == -1
    finally:
        engine.dispose()


def test_0009_adds_the_geometry_report_and_build_stage_and_keeps_every_map(database_url):
    """Maps and their images stored at 0008 survive 0009 both ways (no table rebuilt, so no
    cascade), with a NULL geometry report and build stage until built again."""
    import uuid
    from datetime import UTC, datetime

    from sqlalchemy import text

    engine = make_engine(database_url)
    mid = uuid.uuid4()
    now = datetime.now(UTC)
    try:
        migrate.upgrade(engine, "0008")
        with engine.begin() as conn:
            conn.execute(text("INSERT INTO maps (id, name, status, revision, created_at) "
                              "VALUES (:id, 'm', 'ready', 1, :now)"),
                         {"id": mid.hex if engine.dialect.name == "sqlite" else mid,
                          "now": now})
        migrate.upgrade(engine)
        columns = {c["name"] for c in inspect(engine).get_columns("maps")}
        assert "geometry" in columns
        assert "stage" in {c["name"] for c in inspect(engine).get_columns("build_jobs")}
        with engine.connect() as conn:
            assert conn.execute(text("SELECT name, geometry FROM maps")).all() == [("m", None)]
        migrate.downgrade(engine, "0008")
        assert "geometry" not in {c["name"] for c in inspect(engine).get_columns("maps")}
        with engine.connect() as conn:
            assert conn.execute(text("SELECT name FROM maps")).all() == [("m",)]
    finally:
        engine.dispose()


def test_0010_lists_the_current_revision_of_every_built_map(database_url):
    """A map built twice before 0010 gets one revision row, its current one, with the
    frame, the geometry report and the image counts the map row and its images hold; an
    unbuilt map gets none. Downgrading drops the table and nothing else."""
    import json
    import uuid
    from datetime import UTC, datetime

    from sqlalchemy import text

    engine = make_engine(database_url)
    built, unbuilt = uuid.uuid4(), uuid.uuid4()
    now = datetime.now(UTC)
    ids = (lambda u: u.hex) if engine.dialect.name == "sqlite" else (lambda u: u)
    try:
        migrate.upgrade(engine, "0009")
        with engine.begin() as conn:
            conn.execute(text(
                "INSERT INTO maps (id, name, status, revision, origin_lat, origin_lon, "
                "origin_alt, created_at, built_at, geometry) VALUES (:id, 'm', 'unbuilt', 2, "
                "42.1, -76.5, 300.0, :now, :now, :g)"),
                {"id": ids(built), "now": now, "g": json.dumps({"status": "accepted"})})
            conn.execute(text("INSERT INTO maps (id, name, status, revision, created_at) "
                              "VALUES (:id, 'n', 'unbuilt', 0, :now)"),
                         {"id": ids(unbuilt), "now": now})
            for k, rev in enumerate([1, 1, 2, None]):
                conn.execute(text(
                    "INSERT INTO map_images (map_id, filename, file_hash, content_type, "
                    "byte_size, width, height, lat, lon, position_source, built_revision, "
                    "created_at) VALUES (:m, :f, :h, 'image/jpeg', 1, 1, 1, 42.1, -76.5, "
                    "'exif', :r, :now)"),
                    {"m": ids(built), "f": f"{k}.jpg", "h": f"{k:064d}", "r": rev, "now": now})
        migrate.upgrade(engine)
        with engine.connect() as conn:
            rows = conn.execute(text(
                "SELECT revision, base_revision, image_count, added, removed, origin_lat, "
                "origin_lon, origin_alt, job_id, geometry FROM map_revisions")).all()
        assert len(rows) == 1
        assert tuple(rows[0][:9]) == (2, 1, 3, 1, 0, 42.1, -76.5, 300.0, None)
        geometry = rows[0][9]
        assert (json.loads(geometry) if isinstance(geometry, str) else geometry) == {
            "status": "accepted"}
        migrate.downgrade(engine, "0009")
        assert "map_revisions" not in _tables(engine)
        with engine.connect() as conn:
            assert conn.execute(text("SELECT count(*) FROM map_images")).scalar() == 4
    finally:
        engine.dispose()


def test_0011_keeps_earlier_sessions_on_their_revision_and_their_poses(database_url):
    """Sessions created before 0011 were fixed to their revision and stay so (they do not
    follow their map); their poses name no revision of their own (they read back with
    the session's). Downgrading drops the two columns and nothing else."""
    import uuid
    from datetime import UTC, datetime

    from sqlalchemy import text

    engine = make_engine(database_url)
    sid, mid = uuid.uuid4(), uuid.uuid4()
    now = datetime.now(UTC)
    try:
        _a_session_with_a_pose_at_0006(engine, sid, mid, now)
        migrate.upgrade(engine, "0010")
        migrate.upgrade(engine)
        with engine.connect() as conn:
            assert conn.execute(text("SELECT follows_map FROM sessions")).scalar() in (False, 0)
            assert conn.execute(text("SELECT map_revision FROM pose_estimates")).one() == (
                None,)
        migrate.downgrade(engine, "0010")
        with engine.connect() as conn:
            assert conn.execute(text("SELECT count(*) FROM pose_estimates")).scalar() == 1
            assert conn.execute(text("SELECT map_revision FROM sessions")).scalar() == 1
        assert "follows_map" not in {c["name"] for c in inspect(engine).get_columns("sessions")}
    finally:
        engine.dispose()


def _a_map_with_one_image(engine, map_key, now) -> None:
    """Store an unbuilt map with one image, 'a.jpg', as the tables have had them since 0001
    (``map_key``: the map's id as the dialect stores it)."""
    from sqlalchemy import text

    with engine.begin() as conn:
        conn.execute(text("INSERT INTO maps (id, name, status, revision, created_at) "
                          "VALUES (:id, 'm', 'unbuilt', 0, :now)"), {"id": map_key, "now": now})
        conn.execute(text(
            "INSERT INTO map_images (map_id, filename, file_hash, content_type, byte_size, "
            "width, height, lat, lon, position_source, created_at) VALUES (:id, 'a.jpg', "
            "'ab', 'image/jpeg', 10, 4, 3, 41.0, -83.0, 'exif', :now)"),
            {"id": map_key, "now": now})


def test_0012_gives_map_images_a_flight_and_keeps_every_image(database_url):
    """Images stored at 0011 survive 0012 both ways (no table rebuilt, so no cascade to
    their features), with no flight named: grouped by capture time, as before."""
    import uuid
    from datetime import UTC, datetime

    from sqlalchemy import text

    engine = make_engine(database_url)
    mid = uuid.uuid4()
    now = datetime.now(UTC)
    key = mid.hex if engine.dialect.name == "sqlite" else mid
    try:
        migrate.upgrade(engine, "0011")
        _a_map_with_one_image(engine, key, now)
        migrate.upgrade(engine)
        with engine.connect() as conn:
            assert conn.execute(text("SELECT filename, flight FROM map_images")).all() == \
                [("a.jpg", None)]
        migrate.downgrade(engine, "0011")
        assert "flight" not in {c["name"] for c in inspect(engine).get_columns("map_images")}
        with engine.connect() as conn:
            assert conn.execute(text("SELECT filename FROM map_images")).all() == [("a.jpg",)]
    finally:
        engine.dispose()


def test_0013_says_earlier_build_jobs_were_not_full_and_keeps_them(database_url):
    """Jobs stored at 0012 survive 0013 both ways and read as builds that were not full."""
    import uuid
    from datetime import UTC, datetime

    from sqlalchemy import text

    engine = make_engine(database_url)
    mid, jid = uuid.uuid4(), uuid.uuid4()
    now = datetime.now(UTC)
    sqlite = engine.dialect.name == "sqlite"
    keys = {"id": mid.hex if sqlite else mid, "job": jid.hex if sqlite else jid, "now": now}
    try:
        migrate.upgrade(engine, "0012")
        with engine.begin() as conn:
            conn.execute(text("INSERT INTO maps (id, name, status, revision, created_at) "
                              "VALUES (:id, 'm', 'ready', 1, :now)"), keys)
            conn.execute(text(
                "INSERT INTO build_jobs (id, map_id, status, progress, n_images, n_extracted, "
                "revision, created_at) VALUES (:job, :id, 'done', 1.0, 3, 3, 1, :now)"), keys)
        migrate.upgrade(engine)
        with engine.connect() as conn:
            assert conn.execute(text('SELECT revision, "full" FROM build_jobs')).all() == \
                [(1, False)]
        migrate.downgrade(engine, "0012")
        assert "full" not in {c["name"] for c in inspect(engine).get_columns("build_jobs")}
        with engine.connect() as conn:
            assert conn.execute(text("SELECT revision FROM build_jobs")).all() == [(1,)]
    finally:
        engine.dispose()


def test_0014_indexes_the_file_hash_that_finds_other_maps_images_of_a_file(database_url):
    """The index a build's search for other maps' images of its files runs on
    (``same_files_elsewhere``): SQLite looks each image up by it rather than scanning every
    image of the database for each; it goes with a downgrade, the images staying."""
    import uuid
    from datetime import UTC, datetime

    from sqlalchemy import text

    from vloc.app.jobs.service import same_files_elsewhere

    engine = make_engine(database_url)
    mid = uuid.uuid4()
    sqlite = engine.dialect.name == "sqlite"
    try:
        migrate.upgrade(engine, "0013")
        _a_map_with_one_image(engine, mid.hex if sqlite else mid, datetime.now(UTC))
        migrate.upgrade(engine)
        assert "ix_map_images_file_hash" in {
            i["name"] for i in inspect(engine).get_indexes("map_images")}
        if sqlite:
            query = same_files_elsewhere(mid).compile(
                engine, compile_kwargs={"literal_binds": True})
            with engine.connect() as conn:
                plan = " ".join(str(row[-1]) for row in conn.execute(
                    text(f"EXPLAIN QUERY PLAN {query}")))
            assert "USING INDEX ix_map_images_file_hash" in plan, plan
        migrate.downgrade(engine, "0013")
        assert "ix_map_images_file_hash" not in {
            i["name"] for i in inspect(engine).get_indexes("map_images")}
        with engine.connect() as conn:
            assert conn.execute(text("SELECT filename FROM map_images")).all() == [("a.jpg",)]
    finally:
        engine.dispose()
