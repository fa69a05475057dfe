"""The ``vloc`` command line against the real app over real HTTP: every client command,
its output, its errors and exit codes, and configuration from flags or environment."""

from __future__ import annotations

import json
import re
import threading
import time

import pytest
from click.testing import CliRunner

from tests.clients.conftest import ADMIN_KEY, FAST
from vloc.clients.cli import COMMANDS
from vloc.clients.cli import main as cli
from vloc.clients.demo import free_port
from vloc.clients.sdk import Client

UUID = re.compile(r"^[0-9a-f]{8}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{12}$")


@pytest.fixture
def vloc(live_server, monkeypatch, tmp_path):
    """``vloc`` with VLOC_URL / VLOC_ADMIN_KEY set, run in an empty folder."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("VLOC_DATA_DIR", raising=False)
    monkeypatch.delenv("VLOC_SESSION_TOKEN", raising=False)
    env = {"VLOC_URL": live_server, "VLOC_ADMIN_KEY": ADMIN_KEY}

    def run(*args: str, code: int = 0, env_extra: dict | None = None):
        result = CliRunner().invoke(cli, list(args), env=env | (env_extra or {}),
                                    prog_name="vloc")
        assert result.exit_code == code, (result.output, result.exception)
        return result

    return run


@pytest.fixture(scope="module")
def sdk(live_server) -> Client:
    return Client(live_server, admin_key=ADMIN_KEY)


def test_help_for_every_command():
    top = CliRunner().invoke(cli, ["--help"])
    assert top.exit_code == 0
    for name in ("map", "session", "replay", "demo", "eval", "serve", "world"):
        assert name in top.output and name in COMMANDS
    for args in (["map", "--help"], ["map", "import", "--help"], ["map", "build", "-h"],
                 ["session", "--help"], ["session", "send", "--help"], ["replay", "--help"],
                 ["demo", "--help"]):
        result = CliRunner().invoke(cli, args, prog_name="vloc")
        assert result.exit_code == 0 and "Usage: vloc" in result.output, args
    replay_help = CliRunner().invoke(cli, ["replay", "--help"]).output
    for option in ("--map-id", "--build-map", "--rate", "--transport", "--devices",
                   "--photometric", "VLOC_URL", "VLOC_ADMIN_KEY"):
        assert option in replay_help


def test_map_commands(vloc, dataset_dir):
    map_id = vloc("map", "create", "cli map").stdout.strip()
    assert UUID.match(map_id)
    assert map_id in vloc("map", "list").stdout
    shown = json.loads(vloc("map", "show", map_id, "--json").stdout)
    assert (shown["name"], shown["status"], shown["image_count"]) == ("cli map", "empty", 0)
    imported = vloc("map", "import", str(dataset_dir), "--map", map_id, "--pass", "1",
                    "--build", "--quiet")
    assert imported.stdout.strip() == map_id
    assert "10 of 10 images added" in imported.stderr
    assert "revision 1, 10 images extracted" in imported.stderr
    text = vloc("map", "show", map_id).stdout
    assert "status: ready, revision 1, 10 images (0 not yet built)" in text
    # The same images again: every one a duplicate, nothing added, a failure.
    again = vloc("map", "import", str(dataset_dir), "--map", map_id, "--pass", "1", "--quiet",
                 code=1)
    assert "duplicate" in again.stderr and "no image was accepted" in again.stderr
    vloc("map", "delete", map_id)
    assert map_id not in vloc("map", "list").stdout


def test_map_revision_commands(vloc, sdk, dataset_dir):
    map_id = vloc("map", "import", str(dataset_dir), "--pass", "1", "--build",
                  "--quiet").stdout.strip()
    assert "has no revision" not in vloc("map", "revisions", map_id).stdout
    vloc("map", "build", map_id, "--force", "--quiet")
    listed = vloc("map", "revisions", map_id).stdout.splitlines()
    assert len(listed) == 2
    assert listed[0].startswith("* rev 2") and "10 images (+0 -0 on rev 1)" in listed[0]
    assert listed[1].startswith("  rev 1") and "(+10 -0 on rev 0)" in listed[1]
    assert "MiB" in listed[1]
    # packed again with the same images: revision 1's vocabularies kept, and the files
    # that came out the same shared by the two revisions
    assert "vocabularies of rev 1" in listed[0] and "vocabularies of" not in listed[1]
    assert all(" shared)" in line for line in listed)
    as_json = json.loads(vloc("map", "revisions", map_id, "--json").stdout)
    assert [(r["revision"], r["current"], r["vocabularies_from"]) for r in as_json] == [
        (2, True, 1), (1, False, 1)]
    assert all(0 < r["shared_bytes"] < r["disk_bytes"] for r in as_json)
    # the current revision cannot go: the CLI says how to choose another
    refused = vloc("map", "drop-revision", map_id, "2", code=1)
    assert "409" in refused.stderr and f"vloc map restore {map_id} REVISION" in refused.stderr
    restored = vloc("map", "restore", map_id, "1").stdout
    assert f"map {map_id} is at revision 1 (ready, 0 image(s) waiting" in restored
    assert vloc("map", "drop-revision", map_id, "2").stdout.strip() == (
        f"dropped revision 2 of map {map_id}")
    revisions = sdk.list_revisions(map_id)
    assert [(r.revision, r.current, r.dropped_at is not None) for r in revisions] == [
        (2, False, True), (1, True, False)]
    assert "dropped" in vloc("map", "revisions", map_id).stdout.splitlines()[0]
    assert sdk.restore_revision(map_id, 1).revision == 1
    vloc("map", "restore", map_id, "0", code=2)  # not a revision: click refuses it
    vloc("map", "delete", map_id)


def test_map_import_into_a_new_map_and_build_later(vloc, sdk, dataset_dir):
    out = vloc("map", "import", str(dataset_dir), "--pass", "2", "--quiet")
    map_id = out.stdout.strip()
    assert "created map" in out.stderr and "9 of 9 images added" in out.stderr
    assert json.loads(vloc("map", "show", map_id, "--json").stdout)["name"] == \
        dataset_dir.name
    job_id = vloc("map", "build", map_id, "--no-wait").stdout.strip()
    assert sdk.wait_for_job(job_id, timeout=120, poll_interval=0.1).n_images == 9
    empty = vloc("map", "create", "empty").stdout.strip()
    assert "no images to build from" in vloc("map", "build", empty, "--quiet", code=1).stderr
    assert "no images of pass 7" in vloc("map", "import", str(dataset_dir), "--pass", "7",
                                         code=1).stderr


def test_map_import_names_the_flights(vloc, sdk, dataset_dir):
    """``--flight-per-pass`` names each image's flight after its CSV pass, ``--flight`` names
    one flight for all; the images say so once uploaded."""
    per_pass = vloc("map", "import", str(dataset_dir), "--flight-per-pass", "--build",
                    "--quiet")
    map_id = per_pass.stdout.strip()
    images = sdk.list_images(map_id)
    assert [i.flight for i in images] == ["pass 1"] * 10 + ["pass 2"] * 9
    # the built revision's self-check, per named flight, in the API and in the listing
    flights = sdk.get_map(map_id).geometry.self_check.flights
    assert [(f.flight, f.name) for f in flights] == [(0, "pass 1"), (1, "pass 2")]
    listed = vloc("map", "revisions", map_id).stdout
    assert re.search(r"self-check median [\d.]+ m; pass 1 [\d.]+ m; pass 2 [\d.]+ m", listed), \
        listed
    one = vloc("map", "import", str(dataset_dir), "--pass", "2", "--flight", "dusk", "--quiet")
    assert {i.flight for i in sdk.list_images(one.stdout.strip())} == {"dusk"}
    unnamed = vloc("map", "import", str(dataset_dir), "--pass", "1", "--quiet")
    assert {i.flight for i in sdk.list_images(unnamed.stdout.strip())} == {None}
    both = vloc("map", "import", str(dataset_dir), "--flight", "a", "--flight-per-pass", code=2)
    assert "not both" in both.output


def test_map_import_positions_from_a_csv(vloc, sdk, tmp_path):
    """Images without EXIF GPS go up one at a time, placed by the folder's CSV."""
    from tests.app.imagery import plain_jpeg

    folder = tmp_path / "csv-only"
    folder.mkdir()
    rows = ["filename,lat,lon,alt_m"]
    for i in range(3):
        (folder / f"img{i}.jpg").write_bytes(plain_jpeg(level=60 + 40 * i))
        rows.append(f"img{i}.jpg,{41.0 + i * 1e-4},{-83.0},{200 + i}")
    (folder / "unplaced.jpg").write_bytes(plain_jpeg(level=250))
    (folder / "positions.csv").write_text("\n".join(rows) + "\n")
    out = vloc("map", "import", str(folder), "--quiet")
    assert "3 of 3 images added" in out.stderr and "skipped unplaced.jpg" in out.stderr
    images = sdk.list_images(out.stdout.strip())
    assert [(i.filename, i.position_source, i.lat, i.alt) for i in images] == \
        [(f"img{k}.jpg", "form", 41.0 + k * 1e-4, 200.0 + k) for k in range(3)]
    # a CSV without a pass column names no flight per pass
    assert "have no pass" in vloc("map", "import", str(folder), "--flight-per-pass",
                                  code=1).stderr


def _subscribed(sdk: Client, n: int) -> bool:
    metrics = sdk.request("GET", "/metrics").text
    found = re.search(r"^vloc_stream_subscribers\S* (\S+)$", metrics, re.M)
    return found is not None and float(found.group(1)) >= n


def test_session_commands(vloc, sdk, shots, dataset_dir, tmp_path):
    maps, queries = shots
    m = sdk.create_map("sessions")
    sdk.upload_images(m.id, [(s.name, s.jpeg) for s in maps])
    sdk.wait_for_job(sdk.build_map(m.id).id, timeout=120, poll_interval=0.1)

    created = vloc("session", "create", m.id, "--mode", "hybrid", "--seed", "4",
                   "--param", f"n_particles={FAST['n_particles']}").stdout.split()
    session_id, token = created
    assert UUID.match(session_id) and len(token) > 20
    assert session_id in vloc("session", "list").stdout

    images = [tmp_path / f"q{i}.jpg" for i in range(3)]
    for path, q in zip(images, queries, strict=False):
        path.write_bytes(q.jpeg)
    sent = vloc("session", "send", session_id, *map(str, images), "--seq", "0",
                env_extra={"VLOC_SESSION_TOKEN": token}).stdout.splitlines()
    poses = [json.loads(line) for line in sent]
    assert [(p["seq"], p["type"], p["file"]) for p in poses] == \
        [(0, "pose", "q0.jpg"), (1, "pose", "q1.jpg"), (2, "pose", "q2.jpg")]
    queued = json.loads(vloc("session", "send", session_id, str(images[0]), "--no-wait")
                        .stdout)
    assert queued["seq"] == 3
    # Let frame 3's pose go by before watching: the watch below must see frame 10 first.
    deadline = time.monotonic() + 60
    while not any(p.seq == 3 for p in sdk.list_poses(session_id)) and time.monotonic() < deadline:
        time.sleep(0.02)

    # watch: a frame sent once the stream is subscribed comes out as one JSON line.
    def send_when_watched() -> None:
        deadline = time.monotonic() + 60
        while not _subscribed(sdk, 1) and time.monotonic() < deadline:
            time.sleep(0.02)
        sdk.send_frame(session_id, queries[4].jpeg, seq=10, token=token)

    sender = threading.Thread(target=send_when_watched)
    sender.start()
    watched = vloc("session", "watch", session_id, "--count", "1", "--token", token)
    sender.join()
    assert json.loads(watched.stdout)["seq"] == 10
    # Answered once stored, after the frames before it: `show` sees all six.
    sdk.send_frame(session_id, queries[5].jpeg, seq=11, wait=True, token=token)

    shown = vloc("session", "show", session_id, "--token", token).stdout
    assert "mode hybrid" in shown and "last pose: seq 11" in shown
    assert "(revision 1, follows the map)" in shown
    pinned, _ = vloc("session", "create", m.id, "--revision", "1").stdout.split()
    stays, _ = vloc("session", "create", m.id, "--no-follow").stdout.split()
    assert [(sdk.get_session(s).map_revision, sdk.get_session(s).follows_map)
            for s in (pinned, stays)] == [(1, False), (1, False)]
    assert "(revision 1, stays on it)" in vloc("session", "show", pinned).stdout
    vloc("session", "create", m.id, "--revision", "7", code=1)
    stats = json.loads(vloc("session", "show", session_id, "--json").stdout)
    assert stats["frames_processed"] == 6 and stats["seed"] == 4
    vloc("session", "reset", session_id)
    vloc("session", "initial-pose", session_id, "--lat", str(maps[0].lat), "--lon",
         str(maps[0].lon), "--sigma", "3")
    vloc("session", "initial-pose", session_id, "--x", "1", "--y", "2")
    vloc("session", "initial-pose", session_id, "--lat", "41.0", code=2)
    vloc("session", "initial-pose", session_id, code=2)
    bad = vloc("session", "send", session_id, str(images[0]), "--seq", "1", code=1)
    assert "409" in bad.stderr and "not after the last accepted seq" in bad.stderr
    vloc("session", "delete", session_id)
    vloc("session", "show", session_id, code=1)


def test_errors_and_exit_codes(vloc, live_server, dataset_dir, tmp_path):
    missing = vloc("map", "show", "00000000-0000-0000-0000-000000000000", code=1)
    assert "404" in missing.stderr and "does not exist" in missing.stderr
    wrong = vloc("map", "list", env_extra={"VLOC_ADMIN_KEY": "not-the-admin-key"}, code=1)
    assert "403" in wrong.stderr
    nokey = vloc("map", "list", env_extra={"VLOC_ADMIN_KEY": ""}, code=1)
    assert "401" in nokey.stderr and "--admin-key" in nokey.stderr
    port = free_port()  # nothing listens there
    down = vloc("map", "list", "--server", f"http://127.0.0.1:{port}", code=3)
    assert "cannot reach" in down.stderr and "vloc serve" in down.stderr
    # Replay: usage errors exit 2, bad inputs 1.
    usage = vloc("replay", str(dataset_dir), code=2)
    assert "--map-id" in usage.output
    vloc("replay", str(dataset_dir), "--build-map", "--mode", "teleport", code=2)
    vloc("replay", str(dataset_dir), "--build-map", "--param", "oops", code=2)
    unbuilt = vloc("map", "create", "unbuilt").stdout.strip()
    not_built = vloc("replay", str(dataset_dir), "--map-id", unbuilt, "--quiet", code=1)
    assert "not built" in not_built.stderr
    flat = tmp_path / "flat"
    flat.mkdir()
    (flat / "a.jpg").write_bytes((dataset_dir / "images" / "map_000.jpg").read_bytes())
    no_pass = vloc("replay", str(flat), "--build-map", code=1)
    assert "pass" in no_pass.stderr


def test_flags_override_the_environment_and_the_stored_key(vloc, live_server, tmp_path):
    # Flags win over the environment.
    listed = vloc("map", "list", "--json", "--server", live_server, "--admin-key", ADMIN_KEY,
                  env_extra={"VLOC_URL": "http://127.0.0.1:9", "VLOC_ADMIN_KEY": "x"})
    assert isinstance(json.loads(listed.stdout), list)
    # Without a key anywhere else, the key `vloc serve` stored in the data folder.
    (tmp_path / "data").mkdir(exist_ok=True)
    (tmp_path / "data" / "admin_key").write_text(ADMIN_KEY + "\n")
    vloc("map", "list", env_extra={"VLOC_ADMIN_KEY": ""})
    other = tmp_path / "elsewhere"
    other.mkdir()
    (other / "admin_key").write_text("wrong-key\n")
    vloc("map", "list", env_extra={"VLOC_ADMIN_KEY": "", "VLOC_DATA_DIR": str(other)},
         code=1)


def test_import_of_a_folder_without_a_usable_image_says_why(vloc, shots, tmp_path):
    import cv2
    import numpy as np

    folder = tmp_path / "unusable"
    folder.mkdir()
    grey = cv2.imdecode(np.frombuffer(shots[0][0].jpeg, np.uint8), cv2.IMREAD_COLOR)
    (folder / "no_gps.jpg").write_bytes(cv2.imencode(".jpg", grey)[1].tobytes())
    (folder / "broken.jpg").write_bytes(b"this is not an image at all")
    out = vloc("map", "import", str(folder), code=1)
    assert "no_gps.jpg" in out.stderr and "broken.jpg" in out.stderr
    assert "no usable image" in out.stderr and "all 2 were skipped" in out.stderr
    assert "pass None" not in out.stderr and "object at 0x" not in out.stderr


def test_no_progress_bar_when_stderr_is_not_a_terminal(vloc, dataset_dir):
    out = vloc("map", "import", str(dataset_dir), "--pass", "1", "--build")
    assert "%|" not in out.stderr and "img/s" not in out.stderr
    map_id = out.stdout.strip()
    # nothing new: no empty revision, and the command says so
    again = vloc("map", "build", map_id)
    assert "up to date: revision 1" in again.stderr
    assert json.loads(vloc("map", "show", map_id, "--json").stdout)["revision"] == 1
    vloc("map", "delete", map_id)


def test_send_with_capture_times_and_watch_that_gives_up(vloc, sdk, shots, tmp_path):
    maps, queries = shots
    m = sdk.create_map("times")
    sdk.upload_images(m.id, [(s.name, s.jpeg) for s in maps])
    sdk.wait_for_job(sdk.build_map(m.id).id, timeout=120, poll_interval=0.1)
    session_id, token = vloc("session", "create", m.id, "--param",
                             f"n_particles={FAST['n_particles']}").stdout.split()
    images = [tmp_path / f"t{i}.jpg" for i in range(3)]
    for path, q in zip(images, queries, strict=False):
        path.write_bytes(q.jpeg)
    env = {"VLOC_SESSION_TOKEN": token}
    sent = [json.loads(line) for line in vloc(
        "session", "send", session_id, *map(str, images[:2]), "--captured-at",
        "2013-06-04T13:45:09Z", "--interval", "0.5", env_extra=env).stdout.splitlines()]
    assert [p["captured_at"] for p in sent] == ["2013-06-04T13:45:09Z",
                                                "2013-06-04T13:45:09.500000Z"]
    exif = json.loads(vloc("session", "send", session_id, str(images[2]), "--captured-at",
                           "exif", env_extra=env).stdout)
    assert exif["captured_at"].startswith(queries[2].captured_at.strftime("%Y-%m-%dT%H:%M:%S"))
    vloc("session", "send", session_id, *map(str, images), "--captured-at", "1370353509",
         "--captured-at", "1370353510", code=2, env_extra=env)
    vloc("session", "send", session_id, str(images[0]), "--captured-at", "yesterday",
         code=2, env_extra=env)
    # two messages wanted, none comes: it gives up instead of hanging
    out = vloc("session", "watch", session_id, "--count", "2", "--timeout", "0.5",
               env_extra=env, code=1)
    assert "no message for 0.5 s after 0 of 2 messages" in out.stderr
    vloc("session", "delete", session_id, env_extra=env)


def test_demo_takes_a_port():
    assert "--port" in CliRunner().invoke(cli, ["demo", "--help"]).output


def test_replay_build_map_reuses_the_map_it_built(sdk, shots):
    from vloc.clients.commands.replay import _existing_map

    maps, _ = shots
    m = sdk.create_map("replayed pass 1")
    sdk.upload_images(m.id, [(s.name, s.jpeg) for s in maps])
    assert _existing_map(sdk, "replayed pass 1", len(maps)) is None  # not built yet
    sdk.wait_for_job(sdk.build_map(m.id).id, timeout=120, poll_interval=0.1)
    assert _existing_map(sdk, "replayed pass 1", len(maps)) == m.id
    assert _existing_map(sdk, "replayed pass 1", len(maps) + 1) is None
    sdk.delete_map(m.id)
