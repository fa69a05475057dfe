"""Simulated devices: play a data set's query pass into a running server and score the poses.

Each device opens a session on the map, subscribes to its pose stream, and sends the frames
in order with explicit sequence numbers, over HTTP (``POST .../frames``) or on the stream's
own socket, at the recorded rate or as fast as the server answers. At most ``window``
frames are in flight per device, as a device with a bounded send queue would have. Several
devices run at once (one asyncio task each) to load the server.

Scoring reuses :class:`workers.core.evaluation.evaluate.ModeSummary`, so a replay's mean/median error,
SIFT share and ms per frame are defined exactly as those of ``vloc eval``: errors in the
map's local frame over the frames after the first ``skip``, truth from the CSV else EXIF.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from vloc.clients._replay_data import DeviceFrame
from vloc.clients.sdk import (
    APIError,
    AsyncClient,
    FrameError,
    FrameRejected,
    Pose,
    VlocError,
    WaitTimeout,
)

RATES = ("recorded", "max")
TRANSPORTS = ("http", "ws")


@dataclass
class DeviceRun:
    """What one simulated device sent and got back.

    Attributes
    ----------
    poses : dict seq -> Pose
    failed : dict seq -> str
        Frames the server accepted but could not localise (``frame_error``).
    refused : list of str
        Frames the server refused outright (a 4xx on the POST, or an ``error`` message on
        the socket), and frames never answered.
    latency_ms : dict seq -> float
        As the device sees it: from just before sending to the pose's arrival.
    """

    mode: str
    device: int
    seed: int
    session_id: str
    n_frames: int
    poses: dict[int, Pose] = field(default_factory=dict)
    failed: dict[int, str] = field(default_factory=dict)
    refused: list[str] = field(default_factory=list)
    latency_ms: dict[int, float] = field(default_factory=dict)
    wall_s: float = 0.0

    @property
    def answered(self) -> int:
        return len(self.poses) + len(self.failed) + len(self.refused)


OnAnswer = Callable[[DeviceRun, Any], None]


async def run_device(client: AsyncClient, map_id: str, frames: list[DeviceFrame], *,
                     mode: str, device: int = 0, seed: int = 0,
                     params: dict[str, Any] | None = None, rate: str = "max",
                     speed: float = 1.0, transport: str = "http", window: int = 8,
                     idle_timeout: float = 120.0, on_answer: OnAnswer | None = None,
                     ) -> DeviceRun:
    """One device: open a session, replay ``frames``, collect every answer, close it.

    Parameters
    ----------
    rate : {"recorded", "max"}
        Keep the capture times' spacing (divided by ``speed``), or send as soon as the
        window allows.
    transport : {"http", "ws"}
    window : int
        Frames sent and not yet answered, at most.
    idle_timeout : float
        Give up on the frames still unanswered after this long without any message.
    on_answer : callable, optional
        ``on_answer(run, message)`` after every answer (progress display).
    """
    if rate not in RATES or transport not in TRANSPORTS:
        raise ValueError(f"rate must be one of {RATES}, transport one of {TRANSPORTS}")
    if rate == "recorded" and any(f.captured_at is None for f in frames):
        raise ValueError("--rate recorded needs a capture time for every frame; use max")
    session = await client.create_session(map_id, mode=mode, params=params, seed=seed)
    run = DeviceRun(mode, device, seed, session.id, len(frames))
    t_start = time.perf_counter()
    try:
        async with await client.stream(session, timeout=idle_timeout) as stream:
            await _exchange(client, session, stream, frames, run, rate=rate, speed=speed,
                            transport=transport, window=window, on_answer=on_answer)
    finally:
        run.wall_s = time.perf_counter() - t_start
        # The results are what matter; a session left behind is only a row on the server.
        with contextlib.suppress(VlocError):
            await client.delete_session(session)
    return run


async def _exchange(client, session, stream, frames, run: DeviceRun, *, rate, speed,
                    transport, window, on_answer) -> None:
    slots = asyncio.Semaphore(max(1, window))
    sent_at: dict[int, float] = {}

    async def send_all() -> None:
        t0 = time.monotonic()
        first = frames[0].captured_at if frames else None
        for f in frames:
            if rate == "recorded":
                due = t0 + (f.captured_at - first).total_seconds() / speed
                await asyncio.sleep(max(0.0, due - time.monotonic()))
            await slots.acquire()
            sent_at[f.index] = time.perf_counter()
            try:
                if transport == "ws":
                    await stream.send_frame(f.data, seq=f.index, captured_at=f.captured_at,
                                            metadata=f.metadata)
                else:
                    await client.send_frame(session, f.data, seq=f.index,
                                            captured_at=f.captured_at,
                                            content_type=f.content_type,
                                            metadata=f.metadata)
            except APIError as exc:
                run.refused.append(f"frame {f.index}: {exc}")
                slots.release()

    sender = asyncio.create_task(send_all())
    receiver = asyncio.ensure_future(stream.receive())
    try:
        while run.answered < run.n_frames:
            pending = {receiver} if sender.done() else {receiver, sender}
            done, _ = await asyncio.wait(pending, return_when=asyncio.FIRST_COMPLETED)
            if sender in done:
                sender.result()  # a transport failure ends the run here
            if receiver not in done:
                continue
            try:
                msg = receiver.result()
            except WaitTimeout:
                run.refused += ["no answer"] * (run.n_frames - run.answered)
                break
            if msg is None:
                run.refused += ["stream ended"] * (run.n_frames - run.answered)
                break
            _record(run, msg, sent_at)
            slots.release()
            if on_answer is not None:
                on_answer(run, msg)
            if run.answered < run.n_frames:
                receiver = asyncio.ensure_future(stream.receive())
    finally:
        for task in (receiver, sender):
            if not task.done():
                task.cancel()
        await asyncio.gather(receiver, sender, return_exceptions=True)


def _record(run: DeviceRun, msg, sent_at: dict[int, float]) -> None:
    now = time.perf_counter()
    if isinstance(msg, Pose):
        run.poses[msg.seq] = msg
    elif isinstance(msg, FrameError):
        run.failed[msg.seq] = f"{msg.kind}: {msg.reason}"
    elif isinstance(msg, FrameRejected):
        run.refused.append(str(msg.error))
        return
    if msg.seq in sent_at:
        run.latency_ms[msg.seq] = (now - sent_at[msg.seq]) * 1e3


async def replay_async(client: AsyncClient, map_id: str, frames: list[DeviceFrame], *,
                       modes: list[str], devices: int = 1, seed: int = 0,
                       params: dict[str, Any] | None = None, **options) -> list[DeviceRun]:
    """Every mode in turn; within a mode, ``devices`` devices at once, device ``d`` with
    seed ``seed + d``. ``options`` go to :func:`run_device`."""
    runs: list[DeviceRun] = []
    for mode in modes:
        runs += await asyncio.gather(*(
            run_device(client, map_id, frames, mode=mode, device=d, seed=seed + d,
                       params=params, **options) for d in range(devices)))
    return runs


def replay(base_url: str, admin_key: str | None, map_id: str, frames: list[DeviceFrame],
           **kwargs) -> list[DeviceRun]:
    """Blocking :func:`replay_async` on a new :class:`~clients.sdk.AsyncClient`."""
    async def main() -> list[DeviceRun]:
        async with AsyncClient(base_url, admin_key=admin_key) as client:
            return await replay_async(client, map_id, frames, **kwargs)

    return asyncio.run(main())


# -- scoring ---------------------------------------------------------------------------------

def as_eval_run(run: DeviceRun, truth_xy: np.ndarray, *, config: str = "replay"):
    """The device's answered frames as a :class:`workers.core.evaluation.evaluate.Run`.

    Parameters
    ----------
    truth_xy : (n_frames, 2) float64 ndarray
        True east/north of every frame in the map's local frame.
    """
    from vloc.workers.core.evaluation.evaluate import Run

    seqs = np.array(sorted(run.poses), dtype=np.int64)
    poses = [run.poses[s] for s in seqs]
    return Run(
        mode=run.mode, config=config, start=0, frames=seqs,
        truth=np.asarray(truth_xy, dtype=np.float64)[seqs].reshape(-1, 2),
        estimate=np.array([(p.x, p.y) for p in poses], dtype=np.float64).reshape(-1, 2),
        sigma=np.array([(p.sigma_x, p.sigma_y) for p in poses], dtype=np.float64).reshape(-1, 2),
        feature=["sift" if p.feature == "sift" else "global" for p in poses],
        status=[p.status for p in poses],
        ms=np.array([p.processing_ms for p in poses], dtype=np.float64))


def truth_in_map_frame(frames: list[DeviceFrame], origin) -> np.ndarray:
    """(n, 2) east/north of the frames' true positions relative to ``origin``
    (a :class:`workers.core.geo.GeoOrigin`, the map's own)."""
    east, north = origin.to_local([f.truth_lat for f in frames], [f.truth_lon for f in frames])
    return np.column_stack([np.atleast_1d(east), np.atleast_1d(north)])
