"""Benchmark: what turning a worker's estimate into its message costs the API process.

A frame's estimate becomes its pose message, the JSON text its stream's sockets (and Redis,
and a waiting request) send, and its row in ``pose_estimates``. Today that is one assembled
pose (:func:`app.sessions.pose.from_estimate`), written as JSON once
(:class:`app.stream.hub.Encoded`), the row read from the same object. Beside it, the way it
went before, as a reference: the pose validated from the fields, dumped to a dict, that dict
written as JSON for the socket (and again for Redis), and the row parsed back from the dict.
Both run side by side on the same estimates, in one run, on the engine-reader thread's core:
medians of repeated runs.

Usage::

    .venv/bin/python bench/bench_pose_message.py [--repeats 2000] [--out bench/results/pose_message.md]
"""

from __future__ import annotations

from _common import one_thread, repo_on_path, write_result

one_thread()

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402
import uuid  # noqa: E402
from datetime import UTC, datetime  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

repo_on_path()

from vloc.app.sessions import pose  # noqa: E402
from vloc.app.sessions.schemas import PoseEstimate  # noqa: E402
from vloc.app.stream.hub import Encoded  # noqa: E402
from vloc.workers.core.estimate import Estimate, Status  # noqa: E402
from vloc.workers.core.metadata import FrameMetadata  # noqa: E402


def _estimate(k: int) -> Estimate:
    rng = np.random.default_rng(k)
    cloud = tuple((float(x), float(y)) for x, y in rng.normal(0, 5, (64, 2)))
    return Estimate(x=float(rng.normal()), y=float(rng.normal()), lat=42.1, lon=-76.8,
                    sigma_x=2.0, sigma_y=2.5, cov=(4.0, 0.3, 0.3, 6.25), feature="global",
                    next_feature="global", n_particles=300, status=Status.TRACKING,
                    processing_ms=12.5, best_image=3, measurement="global+registered",
                    heading_deg=81.0, heading_sigma_deg=4.0, metadata_used="altitude",
                    cloud=cloud)


def _context(k: int) -> pose.FrameContext:
    return pose.FrameContext(
        session_id=str(uuid.UUID(int=k + 1)), seq=k, map_id=str(uuid.UUID(int=7)),
        map_revision=2, map_folder="", captured_at=datetime(2026, 11, 28, 12, 0, 0, tzinfo=UTC),
        received_at=datetime(2026, 11, 28, 12, 0, 1, tzinfo=UTC),
        metadata=FrameMetadata(altitude_m=250.0), decode_ms=4.1, latency_ms=30.2)


def now(estimate: Estimate, ctx: pose.FrameContext) -> tuple[str, dict]:
    """Today's path: the pose assembled, written once, its row read from it."""
    message, row = pose.from_estimate(estimate, ctx, bound_m=25.0, converged_before=True)
    return Encoded.of(message).after(ctx.seq - 1).text, row


def before(estimate: Estimate, ctx: pose.FrameContext) -> tuple[str, dict]:
    """The path before, as a reference: validated, dumped, written twice (socket and
    Redis), the row parsed back from the dumped dict."""
    fields = pose.pose_fields(estimate, map_id=uuid.UUID(ctx.map_id),
                              map_revision=ctx.map_revision, map_folder=ctx.map_folder,
                              metadata=ctx.metadata, decode_ms=ctx.decode_ms, bound_m=25.0,
                              converged_before=True)
    validated = PoseEstimate(**fields, session_id=ctx.session_id, seq=ctx.seq,
                             captured_at=ctx.captured_at, received_at=ctx.received_at,
                             latency_ms=ctx.latency_ms, navigation=None)
    message = validated.model_dump(mode="json") | {"prev_seq": ctx.seq - 1}
    text = json.dumps(message)
    json.dumps(message)  # the Redis copy
    row = {"map_revision": message["map_revision"]}
    for name in pose.stored_fields():
        value = message[name]
        if name == "cov":
            row.update(zip(pose.COV_COLUMNS, value, strict=True))
        elif name in ("captured_at", "received_at") and value is not None:
            row[name] = datetime.fromisoformat(value)
        else:
            row[name] = value
    return text, row


def _median_us(fn, cases, repeats: int) -> float:
    times = []
    for r in range(repeats):
        estimate, ctx = cases[r % len(cases)]
        t0 = time.perf_counter()
        fn(estimate, ctx)
        times.append(time.perf_counter() - t0)
    return float(np.median(times) * 1e6)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=2000)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    cases = [(_estimate(k), _context(k)) for k in range(16)]
    for estimate, ctx in cases:  # the same message and row both ways
        new_text, new_row = now(estimate, ctx)
        old_text, old_row = before(estimate, ctx)
        assert json.loads(new_text) == json.loads(old_text) and new_row == old_row
    rounds = [(_median_us(now, cases, args.repeats), _median_us(before, cases, args.repeats))
              for _ in range(3)]
    today = float(np.median([r[0] for r in rounds]))
    earlier = float(np.median([r[1] for r in rounds]))
    lines = ["# A worker's estimate to its message and row, in the API process", "",
             f"`python bench/bench_pose_message.py`: 16 estimates with a 64-particle cloud, "
             f"one core; medians of {args.repeats} runs, median of 3 rounds side by side.", "",
             "| path | us per estimate |", "|---|---|",
             f"| assembled, written as JSON once, row read from the pose | {today:.0f} |",
             f"| before: validated, dumped, JSON twice, row parsed back | {earlier:.0f} |", "",
             f"{earlier / today:.2f}x; both give the same JSON (parsed) and the same row."]
    text = "\n".join(lines)
    print(text)
    if args.out is not None:
        write_result(args.out, text + "\n", echo=False)


if __name__ == "__main__":
    main()
