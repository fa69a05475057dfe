"""Settings from the environment and the admin key of the embedded default."""

from __future__ import annotations

import stat

from app.config import ADMIN_KEY_FILE, Settings, ensure_admin_key


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
