"""What ``vloc serve`` says on start: where the viewer and the API docs are (never the admin
key), in plain lines on a terminal and JSON lines into a file."""

from __future__ import annotations

import json
import sys

import pytest

from vloc.app import main as app_main


def test_serve_prints_the_viewer_and_docs_addresses(server):
    text = server.stderr_path.read_text()
    assert f"web viewer  {server.base_url}/ui/" in text
    assert f"API docs    {server.base_url}/docs" in text
    assert server.admin_key() not in text
    # stderr is a file here: the logs stay JSON lines
    assert any(json.loads(line).get("msg") == "vloc ready"
               for line in text.splitlines() if line.startswith("{"))


@pytest.mark.parametrize(("tty", "setting", "json_lines"), [
    (True, None, False), (False, None, True), (True, True, True), (False, False, False)])
def test_logs_are_plain_on_a_terminal_unless_asked(monkeypatch, tmp_path, tty, setting,
                                                   json_lines):
    from tests.app.conftest import service_settings

    chosen = {}
    monkeypatch.setattr(sys.stderr, "isatty", lambda: tty)
    monkeypatch.setattr(app_main.logs, "configure",
                        lambda level, json_lines, native: chosen.update(json_lines=json_lines,
                                                                        native=native))
    settings = service_settings(tmp_path / "data", f"sqlite:///{tmp_path / 'db.sqlite3'}",
                                log_json=setting)
    app_main.create_app(settings, configure_logging=True)
    # the server's own process also turns what C libraries write to stderr into records
    assert chosen == {"json_lines": json_lines, "native": True}
