"""``vloc navigate`` end to end on a small robot world, against a real uvicorn server."""

from __future__ import annotations

import json

from click.testing import CliRunner

from tests.clients.conftest import ADMIN_KEY
from vloc.clients.cli import main as cli


def test_navigate_teaches_repeats_and_arrives(live_server, tmp_path):
    out = tmp_path / "nav"
    result = CliRunner().invoke(cli, ["navigate", "--url", live_server, "--admin-key",
                                      ADMIN_KEY, "--length", "24", "--out", str(out),
                                      "--quiet"], prog_name="vloc")
    assert result.exit_code == 0, result.output
    assert "route:" in result.output and "repeat:" in result.output
    results = json.loads((out / "results.json").read_text())
    repeat = results["repeat"]
    # the session led the robot round the block and said so; a smaller block than the
    # benchmark's, so the bound is loose, but a robot that lost the path ends metres off
    assert repeat["arrived"]
    assert repeat["travel_m"] > 15.0
    assert repeat["mean_cross_track_m"] < 1.5
    assert (out / "navigate.png").stat().st_size > 10_000


def test_navigate_help():
    result = CliRunner().invoke(cli, ["navigate", "--help"], prog_name="vloc")
    assert result.exit_code == 0 and "Usage: vloc navigate" in result.output
    for option in ("--length", "--starts", "--drift", "--nav", "--url"):
        assert option in result.output
