"""Settings from the environment and the admin key of the embedded default."""

from __future__ import annotations

import stat

from vloc.app.config import ADMIN_KEY_FILE, Settings, ensure_admin_key


def test_settings_read_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("VLOC_DATA_DIR", str(tmp_path))
    monkeypatch.setenv("VLOC_WORKERS", "3")
    monkeypatch.setenv("VLOC_MAX_FRAME_BYTES", "1234")
    monkeypatch.setenv("VLOC_DATABASE_URL", "postgresql+psycopg://u@h/db")
    s = Settings()
    assert (s.data_dir, s.worker_count, s.max_frame_bytes) == (tmp_path, 3, 1234)
    assert s.resolved_database_url == "postgresql+psycopg://u@h/db"
    assert not s.embedded_database


def test_default_database_is_a_sqlite_file_in_the_data_dir(tmp_path):
    s = Settings(data_dir=tmp_path)
    assert s.embedded_database
    assert s.resolved_database_url == f"sqlite:///{tmp_path.resolve()}/vloc.sqlite3"
    assert s.worker_count >= 1


def test_admin_key_is_generated_once_stored_and_announced_once(tmp_path):
    announced = []
    s = Settings(data_dir=tmp_path / "d")
    key = ensure_admin_key(s, announce=lambda k, p: announced.append((k, p)))
    assert len(key) >= 40 and announced == [(key, tmp_path / "d" / ADMIN_KEY_FILE)]
    path = tmp_path / "d" / ADMIN_KEY_FILE
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert ensure_admin_key(s, announce=lambda k, p: announced.append(k)) == key
    assert len(announced) == 1


def test_admin_key_from_the_environment_wins(tmp_path, monkeypatch):
    monkeypatch.setenv("VLOC_ADMIN_KEY", "k" * 32)
    s = Settings(data_dir=tmp_path)
    assert ensure_admin_key(s, announce=lambda k, p: (_ for _ in ()).throw(AssertionError)) \
        == "k" * 32
    assert not (tmp_path / ADMIN_KEY_FILE).exists()


def test_the_engine_is_chosen_by_the_settings(monkeypatch, tmp_path):
    import pytest
    from pydantic import ValidationError

    from vloc.app.engine import Engine, engine_for
    from vloc.workers.engine import LocalEngine

    local = engine_for(Settings(data_dir=tmp_path, workers=3))
    assert isinstance(local, LocalEngine) and isinstance(local, Engine)
    assert (local.n_workers, local.shared) == (3, False)
    pytest.importorskip("ray")
    from vloc.workers.engine.ray_engine import RayEngine

    monkeypatch.setenv("VLOC_ENGINE", "ray")
    monkeypatch.setenv("VLOC_RAY_ADDRESS", "head:6379")
    monkeypatch.setenv("VLOC_RAY_NAMESPACE", "fleet-a")
    ray = engine_for(Settings(data_dir=tmp_path, workers=3))
    # Not started: nothing is reached until the application starts.
    assert isinstance(ray, RayEngine) and isinstance(ray, Engine) and ray.shared
    assert (ray.n_workers, ray.address, ray.namespace) == (3, "head:6379", "fleet-a")
    monkeypatch.setenv("VLOC_RAY_SHARDS", "8")
    assert engine_for(Settings(data_dir=tmp_path, workers=3)).n_workers == 8
    monkeypatch.setenv("VLOC_ENGINE", "spark")
    with pytest.raises(ValidationError, match="engine"):
        Settings(data_dir=tmp_path)


def test_serve_processes_needs_a_shared_engine_database_and_redis(monkeypatch, tmp_path):
    from click.testing import CliRunner

    from vloc.clients.commands.serve import serve_cmd

    monkeypatch.setenv("VLOC_DATA_DIR", str(tmp_path))
    for var in ("VLOC_ENGINE", "VLOC_DATABASE_URL", "VLOC_REDIS_URL"):
        monkeypatch.delenv(var, raising=False)
    result = CliRunner().invoke(serve_cmd, ["--processes", "2"])
    assert result.exit_code == 2
    for needed in ("VLOC_ENGINE=ray", "VLOC_DATABASE_URL", "VLOC_REDIS_URL"):
        assert needed in result.output
    monkeypatch.setenv("VLOC_ENGINE", "ray")
    monkeypatch.setenv("VLOC_DATABASE_URL", "postgresql+psycopg://u@h/db")
    result = CliRunner().invoke(serve_cmd, ["--processes", "2"])
    assert result.exit_code == 2 and "VLOC_REDIS_URL" in result.output
    assert "VLOC_ENGINE" not in result.output


def test_the_generated_key_is_not_written_where_the_logs_go(tmp_path, capsys):
    key = ensure_admin_key(Settings(data_dir=tmp_path / "d"))
    err = capsys.readouterr().err
    assert key not in err and str(tmp_path / "d" / ADMIN_KEY_FILE) in err
