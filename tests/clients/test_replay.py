"""Simulated devices: the send/receive loop on a scripted server, scoring against a
hand-computed answer, and replays on the real app that must reproduce ``vloc eval``."""

from __future__ import annotations

import asyncio
import json
import math
from datetime import UTC, datetime, timedelta

import numpy as np
import pytest
from click.testing import CliRunner

from tests.clients.conftest import ADMIN_KEY, FAST
from vloc.clients._replay_data import DeviceFrame, load_replay_data
from vloc.clients._replay_report import mode_table, replay_table, summarise
from vloc.clients.cli import main as cli
from vloc.clients.replay import DeviceRun, run_device, truth_in_map_frame
from vloc.clients.sdk import Conflict, FrameError, Pose, Session
from vloc.workers.core.geo import GeoOrigin

ORIGIN = GeoOrigin(41.0, -83.0, 0.0)
T0 = datetime(2024, 1, 1, tzinfo=UTC)


def frames_at(xy: list[tuple[float, float]], *, spacing_s: float = 1.0) -> list[DeviceFrame]:
    """Frames whose true positions are the given east/north points of ORIGIN's frame."""
    lat, lon = ORIGIN.to_wgs84([p[0] for p in xy], [p[1] for p in xy])
    return [DeviceFrame(i, f"f{i}.jpg", b"\xff\xd8\xff" + bytes([i]), "image/jpeg",
                        T0 + timedelta(seconds=spacing_s * i), float(lat[i]), float(lon[i]))
            for i in range(len(xy))]


def pose(seq: int, x: float, y: float, feature: str = "global", ms: float = 5.0) -> Pose:
    return Pose(seq=seq, x=x, y=y, lat=0.0, lon=0.0, sigma_x=1.0, sigma_y=1.0,
                cov=(1.0, 0.0, 0.0, 1.0), feature=feature, status="tracking",
                processing_ms=ms)


# -- a scripted server -----------------------------------------------------------------------


class FakeStream:
    def __init__(self, server: FakeServer) -> None:
        self.server = server

    async def receive(self, timeout=None):
        return await self.server.outbox.get()

    async def send_frame(self, data, *, seq=None, captured_at=None, metadata=None):
        self.server.metadata[seq] = metadata
        self.server.take(seq, data, via="ws")

    async def __aenter__(self):
        return self

    async def __aexit__(self, *exc):
        self.server.closed = True


class FakeServer:
    """Answers each frame with a pose at (seq, 2 seq), after the frames already queued;
    ``refuse`` lists seqs to answer 409 on the POST, ``fail`` seqs to answer frame_error."""

    def __init__(self, *, refuse=(), fail=(), end_after=None) -> None:
        self.outbox: asyncio.Queue = asyncio.Queue()
        self.refuse, self.fail, self.end_after = set(refuse), set(fail), end_after
        self.sent: list[tuple[int, str, float]] = []
        self.in_flight = 0
        self.max_in_flight = 0
        self.deleted = False
        self.closed = False
        self.metadata: dict[int, dict | None] = {}

    def take(self, seq, data, via) -> None:
        loop = asyncio.get_running_loop()
        self.sent.append((seq, via, loop.time()))
        self.in_flight += 1
        self.max_in_flight = max(self.max_in_flight, self.in_flight)
        loop.call_later(0.001, self._answer, seq)

    def _answer(self, seq) -> None:
        self.in_flight -= 1
        if self.end_after is not None and seq >= self.end_after:
            self.outbox.put_nowait(None)
        elif seq in self.fail:
            self.outbox.put_nowait(FrameError(seq=seq, kind="bad_image", reason="corrupt"))
        else:
            self.outbox.put_nowait(pose(seq, float(seq), 2.0 * seq))

    # the AsyncClient calls run_device makes
    async def create_session(self, map_id, *, mode, params, seed):
        self.opened_at = asyncio.get_running_loop().time()
        return Session(id="s1", map_id=map_id, mode=mode, seed=seed, token="t")

    async def stream(self, session, timeout=None):
        return FakeStream(self)

    async def send_frame(self, session, data, *, seq, captured_at, content_type, metadata=None):
        self.metadata[seq] = metadata
        if seq in self.refuse:
            raise Conflict(409, type="urn:vloc:problem:stale-seq", detail="no")
        self.take(seq, data, via="http")

    async def delete_session(self, session):
        self.deleted = True


def run_fake(server: FakeServer, frames, **options) -> DeviceRun:
    return asyncio.run(run_device(server, "m1", frames, mode="hybrid", **options))


def test_every_frame_sent_in_order_and_answered():
    frames = frames_at([(i, 0) for i in range(20)])
    server = FakeServer()
    run = run_fake(server, frames, window=3)
    assert [s[0] for s in server.sent] == list(range(20))
    assert sorted(run.poses) == list(range(20)) and not run.failed and not run.refused
    assert 1 <= server.max_in_flight <= 3
    assert set(run.latency_ms) == set(range(20)) and min(run.latency_ms.values()) >= 0
    assert server.deleted and server.closed and run.session_id == "s1"


def test_frames_over_the_socket():
    server = FakeServer()
    run = run_fake(server, frames_at([(0, 0)] * 5), transport="ws", window=1)
    assert [s[1] for s in server.sent] == ["ws"] * 5
    assert server.max_in_flight == 1 and len(run.poses) == 5


def test_refused_and_failed_frames_are_counted_and_the_run_ends():
    server = FakeServer(refuse={4, 9}, fail={2})
    run = run_fake(server, frames_at([(0, 0)] * 10), window=2)
    assert sorted(run.poses) == [0, 1, 3, 5, 6, 7, 8]
    assert list(run.failed) == [2] and "bad_image" in run.failed[2]
    assert len(run.refused) == 2 and "frame 4" in run.refused[0]


def test_a_stream_that_ends_early_leaves_the_rest_unanswered():
    server = FakeServer(end_after=3)
    run = run_fake(server, frames_at([(0, 0)] * 8), window=8)
    assert sorted(run.poses) == [0, 1, 2]
    assert run.answered == 8 and run.refused.count("stream ended") == 5


def test_recorded_rate_keeps_the_capture_spacing():
    server = FakeServer()
    run_fake(server, frames_at([(0, 0)] * 4, spacing_s=2.0), rate="recorded", speed=40.0)
    since_open = [s[2] - server.opened_at for s in server.sent]
    # 2 s apart, played 40 times faster: frame k leaves no earlier than k x 50 ms.
    assert all(t >= 0.05 * k - 1e-3 for k, t in enumerate(since_open))


def test_recorded_rate_needs_capture_times():
    frames = [DeviceFrame(0, "a", b"", "image/jpeg", None, 41.0, -83.0)]
    with pytest.raises(ValueError, match="capture time"):
        run_fake(FakeServer(), frames, rate="recorded")


# -- scoring ---------------------------------------------------------------------------------


def test_summary_against_hand_computed_errors():
    # Truth along the east axis; estimates off by 3-4-5 triangles and known amounts.
    truth = [(0, 0), (10, 0), (20, 0), (30, 0), (40, 0)]
    frames = frames_at(truth)
    run = DeviceRun("hybrid", 0, 0, "s", 5)
    offsets = [(100, 0), (3, 4), (0, 1), (6, 8), (0, 0)]  # errors 100, 5, 1, 10, 0
    for i, ((tx, ty), (dx, dy)) in enumerate(zip(truth, offsets, strict=True)):
        run.poses[i] = pose(i, tx + dx, ty + dy, feature="sift" if i < 2 else "global",
                            ms=10.0 * (i + 1))
        run.latency_ms[i] = float(i)
    sift = DeviceRun("sift", 0, 0, "s2", 5)
    for i, (tx, ty) in enumerate(truth):
        sift.poses[i] = pose(i, tx, ty + 2.0, feature="sift", ms=100.0)
    data = summarise([run, sift], frames, ORIGIN, skip=1)
    h = data["modes"]["hybrid"]
    # After skipping frame 0: errors 5, 1, 10, 0.
    assert h["mean_error_m"] == pytest.approx(4.0, abs=1e-6)
    assert h["median_error_m"] == pytest.approx(3.0, abs=1e-6)
    assert h["sift_step_share"] == pytest.approx(2 / 5)   # over every frame, as eval
    assert h["ms_per_frame"] == pytest.approx(30.0)
    assert h["speedup_vs_sift"] == pytest.approx(100.0 / 30.0)
    assert h["latency_ms_p50"] == pytest.approx(2.0)
    assert (h["frames_sent"], h["frames_answered"]) == (5, 5)
    assert data["modes"]["sift"]["mean_error_m"] == pytest.approx(2.0, abs=1e-6)
    assert [r["mode"] for r in data["runs"]] == ["hybrid", "sift"]
    table = replay_table(data)
    assert "| hybrid | 0 | 5 | 4.0 | 3.0 | 40.0 % | 30.0 | 3.33 | 2 |" in table
    assert "| sift | 2.0 | 2.0 | 100.0 % | 100.0 | 1.00 |" in mode_table(data)


def test_truth_matches_a_slow_reference():
    rng = np.random.default_rng(4)
    xy = rng.uniform(-300, 300, (12, 2))
    frames = frames_at([tuple(p) for p in xy])
    got = truth_in_map_frame(frames, ORIGIN)
    ref = np.array([[float(v) for v in ORIGIN.to_local(f.truth_lat, f.truth_lon)]
                    for f in frames])
    np.testing.assert_allclose(got, ref, atol=1e-9)
    np.testing.assert_allclose(got, xy, atol=1e-6)


def test_a_run_without_estimates_scores_nan():
    run = DeviceRun("global", 0, 0, "s", 3, refused=["no answer"] * 3)
    data = summarise([run], frames_at([(0, 0)] * 3), ORIGIN, skip=0)
    assert math.isnan(data["modes"]["global"]["mean_error_m"])
    assert "| global | 0 | 0 (3 lost) | - | - | - |" in replay_table(data)


# -- the frames a device sends ---------------------------------------------------------------


def test_relit_frames_are_the_pixels_eval_uses(dataset_dir):
    from vloc.workers.core.evaluation.experiment import load_experiment
    from vloc.workers.core.image import load_frame

    data = load_replay_data(dataset_dir, map_pass=1, query_pass=2, photometric="dusk",
                            seed=3, limit=4)
    exp = load_experiment(dataset_dir, map_pass=1, query_pass=2, photometric="dusk", seed=3)
    assert [f.content_type for f in data.frames] == ["image/png"] * 4
    for f, q in zip(data.frames, exp.queries, strict=False):
        np.testing.assert_array_equal(load_frame(f.data).grey, q.frame.grey)
    plain = load_replay_data(dataset_dir, map_pass=1, query_pass=2)
    assert plain.frames[0].data == (dataset_dir / "images" / "query_000.jpg").read_bytes()
    assert [im.name for im in plain.map_images] == [f"map_{i:03d}.jpg" for i in range(10)]
    with pytest.raises(ValueError, match="photometric"):
        load_replay_data(dataset_dir, photometric="neon")


def test_metadata_goes_with_each_frame(dataset_dir):
    from vloc.workers.core.geo import GeoOrigin

    data = load_replay_data(dataset_dir, metadata=("gps", "altitude"), gps_accuracy=5.0)
    again = load_replay_data(dataset_dir, metadata=("gps", "altitude"), gps_accuracy=5.0)
    assert [f.metadata for f in data.frames] == [f.metadata for f in again.frames]  # seeded
    offsets = []
    for f in data.frames:
        assert f.metadata["gps_accuracy_m"] == 5.0 and "altitude_m" in f.metadata
        e, n = GeoOrigin(f.truth_lat, f.truth_lon).to_local(f.metadata["gps_lat"],
                                                            f.metadata["gps_lon"])
        offsets.append(float(np.hypot(e, n)))
    assert 0.0 < np.median(offsets) < 20.0  # about 5 m per axis off the truth
    for transport in ("http", "ws"):
        server = FakeServer()
        run_fake(server, data.frames, transport=transport)
        assert [server.metadata[f.index] for f in data.frames] == [f.metadata
                                                                   for f in data.frames]
    with pytest.raises(ValueError, match="give a GPS accuracy"):
        load_replay_data(dataset_dir, metadata=("gps",))
    with pytest.raises(ValueError, match="no heading columns"):
        load_replay_data(dataset_dir, metadata=("heading",))
    with pytest.raises(ValueError, match="unknown metadata kinds"):
        load_replay_data(dataset_dir, metadata=("compass",))


# -- against the real app: the same numbers as vloc eval -------------------------------------


SMALL = ("--skip", "2", "--param", f"n_particles={FAST['n_particles']}")
"""Scoring and filter size for the 9-frame data set (later options override --skip)."""


def replay_json(server, dataset, *args, key: str = ADMIN_KEY) -> dict:
    result = CliRunner().invoke(cli, ["replay", str(dataset), "--server", server,
                                      "--admin-key", key, "--json", *args])
    assert result.exit_code == 0, result.output
    return json.loads(result.stdout)


def eval_json(dataset, *args) -> dict:
    result = CliRunner().invoke(cli, ["eval", str(dataset), "--starts", "1", "--json", *args])
    assert result.exit_code == 0, result.output
    return json.loads(result.stdout)


FIGURES = ("mean_error_m", "median_error_m", "sift_step_share", "within_25m")


def test_eval_takes_several_map_passes_and_refuses_what_is_not_one(dataset_dir):
    bad = CliRunner().invoke(cli, ["eval", str(dataset_dir), "--map-pass", "1,x"])
    assert bad.exit_code == 2 and "pass numbers separated by commas" in bad.output
    both = CliRunner().invoke(cli, ["eval", str(dataset_dir), "--map-pass", "1,2",
                                    "--query-pass", "2"])
    assert both.exit_code == 1 and "pass 2 is both a map pass and the query pass" in \
        both.output


@pytest.fixture(scope="module")
def replayed(live_server, dataset_dir) -> dict:
    """hybrid and sift replayed over HTTP on a map built by the replay itself."""
    return replay_json(live_server, dataset_dir, *SMALL, "--build-map", "--map-pass", "1",
                       "--query-pass", "2", "--mode", "hybrid,sift", "--seed", "0")


def test_replay_reproduces_eval(replayed, dataset_dir):
    offline = eval_json(dataset_dir, *SMALL, "--modes", "hybrid,sift", "--seed", "0")
    for mode in ("hybrid", "sift"):
        for key in FIGURES:
            assert replayed["modes"][mode][key] == pytest.approx(
                offline["modes"][mode][key], abs=1e-6), (mode, key)
    assert replayed["query_frames"] == 9 and replayed["map_images"] == 10
    assert replayed["modes"]["hybrid"]["frames_answered"] == 9
    # the tracks for the web viewer: the same frames, truth and estimates on both sides
    assert len(replayed["map_xy"]) == len(offline["map_xy"]) == 10
    online = {t["mode"]: t for t in replayed["tracks"]}
    for t in offline["tracks"]:
        r = online[t["mode"]]
        assert r["frames"] == t["frames"] == list(range(9))
        assert r["feature"] == t["feature"]
        for key in ("truth", "estimate"):
            assert np.allclose(r[key], t[key], atol=0.011), (t["mode"], key)
        assert np.allclose(r["error_m"], t["error_m"], atol=0.021)
        assert np.allclose(t["error_m"], np.linalg.norm(np.subtract(t["estimate"], t["truth"]),
                                                        axis=1), atol=0.021)


def test_replay_over_the_socket_with_two_devices(live_server, dataset_dir, replayed):
    got = replay_json(live_server, dataset_dir, *SMALL, "--map-id", replayed["map_id"],
                      "--mode", "hybrid", "--transport", "ws", "--devices", "2",
                      "--window", "2")
    runs = got["runs"]
    assert [(r["device"], r["seed"]) for r in runs] == [(0, 0), (1, 1)]
    # Device 0 has the seed of the single HTTP device: the same estimates.
    for key in FIGURES:
        assert runs[0][key] == pytest.approx(replayed["modes"]["hybrid"][key], abs=1e-6)
    assert got["modes"]["hybrid"]["frames_answered"] == 18
    assert got["modes"]["hybrid"]["devices"] == 2


def test_relit_replay_reproduces_eval(live_server, dataset_dir, replayed, tmp_path):
    got = replay_json(live_server, dataset_dir, *SMALL, "--map-id", replayed["map_id"],
                      "--mode", "hybrid", "--photometric", "dusk", "--seed", "5",
                      "--rate", "recorded", "--speed", "200", "--plot",
                      str(tmp_path / "t.png"))
    offline = eval_json(dataset_dir, *SMALL, "--modes", "hybrid", "--photometric", "dusk",
                        "--seed", "5")
    for key in FIGURES:
        assert got["modes"]["hybrid"][key] == pytest.approx(offline["modes"]["hybrid"][key],
                                                            abs=1e-6)
    assert (tmp_path / "t.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
