"""What a new user of the ``vloc`` command line meets: one image localised, a session with
its time to live, a forced rebuild, advice given as commands of this CLI rather than HTTP
routes, and hints for a missing or refused admin key that say where the key is read from."""

from __future__ import annotations

import json

import pytest
from click.testing import CliRunner

from tests.clients.conftest import ADMIN_KEY
from vloc.clients.cli import main as cli
from vloc.clients.sdk import Client


@pytest.fixture
def vloc(live_server, monkeypatch, tmp_path):
    """``vloc`` against the live server, run in an empty folder; VLOC_ADMIN_KEY unless
    ``key=None``."""
    monkeypatch.chdir(tmp_path)
    for name in ("VLOC_DATA_DIR", "VLOC_SESSION_TOKEN", "VLOC_ADMIN_KEY"):
        monkeypatch.delenv(name, raising=False)

    def run(*args: str, code: int = 0, key: str | None = ADMIN_KEY):
        env = {"VLOC_URL": live_server} | ({"VLOC_ADMIN_KEY": key} if key else {})
        result = CliRunner().invoke(cli, list(args), env=env, prog_name="vloc")
        assert result.exit_code == code, (result.output, result.exception)
        return result

    return run


@pytest.fixture(scope="module")
def built(live_server, shots) -> str:
    sdk = Client(live_server, admin_key=ADMIN_KEY)
    m = sdk.create_map("first use")
    sdk.upload_images(m.id, [(s.name, s.jpeg) for s in shots[0]])
    sdk.wait_for_job(sdk.build_map(m.id).id, timeout=120, poll_interval=0.1)
    return m.id


def test_localize_one_image_and_json(vloc, built, shots, tmp_path):
    query = shots[1][2]
    path = tmp_path / "q.jpg"
    path.write_bytes(query.jpeg)
    line = vloc("localize", built, str(path)).output.strip()
    assert line.startswith("q.jpg: ") and " m" in line and "best match" in line
    got = json.loads(vloc("localize", built, str(path), "--json").output)
    assert got["file"] == "q.jpg" and got["type"] == "localization"
    assert abs(got["lat"] - query.lat) < 1e-3 and abs(got["lon"] - query.lon) < 1e-3
    assert "--prior-sigma" in vloc("localize", built, str(path), "--prior", "41,-83",
                                   code=1).output


def test_session_create_takes_a_time_to_live(vloc, built, live_server):
    session_id, _ = vloc("session", "create", built, "--ttl", "120").output.split()
    shown = json.loads(vloc("session", "show", session_id, "--json").output)
    assert shown["ttl_s"] == 120
    vloc("session", "delete", session_id)


def test_build_force_packs_a_map_with_nothing_new(vloc, built):
    up_to_date = vloc("map", "build", built, "--quiet")
    assert f"vloc map build --force {built}" in up_to_date.output
    before = json.loads(vloc("map", "show", built, "--json").output)["revision"]
    vloc("map", "build", built, "--force", "--quiet")
    assert json.loads(vloc("map", "show", built, "--json").output)["revision"] == before + 1


def test_advice_names_cli_commands_not_http_routes(vloc):
    empty = vloc("map", "create", "never built").output.strip()
    out = vloc("session", "create", empty, code=1).output
    assert f"vloc map build {empty}" in out and "POST /v1" not in out


def test_key_hints_say_where_the_key_is_read_from(vloc, built, tmp_path):
    missing = vloc("map", "list", key=None, code=1).output
    assert str(tmp_path / "data" / "admin_key") in missing
    assert "--admin-key" in missing and "VLOC_ADMIN_KEY" in missing
    wrong = vloc("map", "list", key="not-the-key", code=1).output
    assert "403" in wrong and "refused the key from --admin-key / VLOC_ADMIN_KEY" in wrong
    # the key `vloc serve` would have stored where the command runs is used, and named
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "admin_key").write_text("stale-key\n")
    stale = vloc("map", "list", key=None, code=1).output
    assert f"refused the key from {tmp_path / 'data' / 'admin_key'}" in stale


def test_help_says_where_the_key_is_and_that_it_is_never_printed():
    text = " ".join(CliRunner().invoke(cli, ["serve", "--help"]).output.split())
    assert "never printed" in text and "printed once" not in text
    assert "/ui/" in text and "/docs" in text
    key_help = " ".join(CliRunner().invoke(cli, ["map", "list", "--help"]).output.split())
    assert "./data/admin_key of the current folder" in key_help


def test_eval_pins_the_threads_and_reports_cpu_beside_wall_time(dataset_dir, monkeypatch):
    """The timings of ``vloc eval`` come from one thread of OpenCV and of the BLAS (the
    service workers' setting), and the run's CPU time is reported beside its wall time."""
    import cv2
    from threadpoolctl import threadpool_info

    import vloc.workers.core.evaluation.evaluate as evaluate_module

    seen = {}
    real = evaluate_module.evaluate

    def watched(*args, **kwargs):
        seen["cv2"] = cv2.getNumThreads()
        seen["blas"] = {p["num_threads"] for p in threadpool_info()
                        if p["user_api"] == "blas"}
        return real(*args, **kwargs)

    monkeypatch.setattr(evaluate_module, "evaluate", watched)
    args = ["eval", str(dataset_dir), "--starts", "1", "--modes", "global", "--skip", "2"]
    result = CliRunner().invoke(cli, [*args, "--json"])
    assert result.exit_code == 0, result.output
    timing = json.loads(result.stdout)["timing"]
    assert seen["cv2"] == 1 and seen["blas"] <= {1}
    assert timing["threads"] == 1 and timing["wall_s"] > 0 and timing["cpu_s"] > 0
    table = CliRunner().invoke(cli, args).output
    assert "s wall clock" in table and "s CPU, 1 thread" in table


def test_build_full_forgets_the_kept_reconstruction_and_packs_anew(vloc, built, monkeypatch):
    from vloc.app.maps import router

    forgotten = []
    real = router.forget_reconstruction
    monkeypatch.setattr(router, "forget_reconstruction",
                        lambda tie_dir: (forgotten.append(tie_dir), real(tie_dir)))
    before = json.loads(vloc("map", "show", built, "--json").output)["revision"]
    vloc("map", "build", built, "--full", "--quiet")  # nothing new: full implies force
    assert json.loads(vloc("map", "show", built, "--json").output)["revision"] == before + 1
    assert len(forgotten) == 1 and forgotten[0].parent.name == built
