"""What checkpoints cost the database: the growth of PostgreSQL's ``sessions`` table while
sessions stream, with every filter state stored (``VLOC_CHECKPOINT_INTERVAL_S=0``, the old
behaviour) and at the default bounded rate.

Runs the app in this process (its worker pool in subprocesses) on a fresh PostgreSQL
schema per setting, autovacuum off for the table so that its size counts every row
version written; several sessions post frames at a steady rate, one at a time each.

    python bench/bench_checkpoints.py [--sessions 5] [--fps 5] [--seconds 30]
                                      [--out bench/results/checkpoints.md]
"""

from __future__ import annotations

import argparse
import concurrent.futures
import os
import platform
import tempfile
import time
from pathlib import Path

from _common import RESULTS, repo_on_path, write_result
from fastapi.testclient import TestClient
from sqlalchemy import text

repo_on_path()

from tests.app.conftest import ADMIN, build_map, service_settings  # noqa: E402
from tests.app.imagery import map_and_queries  # noqa: E402
from tests.conftest import postgres_schema_url  # noqa: E402
from vloc.app.main import create_app  # noqa: E402


def table_mib(client: TestClient) -> float:
    with client.app.state.ctx.db_engine.connect() as conn:
        return conn.scalar(text("SELECT pg_total_relation_size('sessions')")) / 2**20


def run(interval: float, args) -> dict:
    maps, queries = map_and_queries(8)
    with tempfile.TemporaryDirectory() as tmp, postgres_schema_url() as url:
        settings = service_settings(Path(tmp) / "data", url, workers=2,
                                    checkpoint_interval_s=interval, max_frame_bytes=10**6)
        with TestClient(create_app(settings)) as c:
            with c.app.state.ctx.db_engine.begin() as conn:
                conn.execute(text("ALTER TABLE sessions SET (autovacuum_enabled = false)"))
            map_id = build_map(c, maps)
            sessions = []
            for _ in range(args.sessions):
                r = c.post("/v1/sessions", headers=ADMIN,
                           json={"map_id": map_id, "params": {"n_particles": 300}})
                sessions.append((r.json()["id"], {"Authorization": f"Bearer {r.json()['token']}",
                                                  "Content-Type": "image/jpeg"}))
            before = table_mib(c)
            t_end = time.monotonic() + args.seconds

            def device(sid, headers) -> int:
                n = 0
                while time.monotonic() < t_end:
                    t = time.monotonic()
                    r = c.post(f"/v1/sessions/{sid}/frames", headers=headers,
                               params={"wait": "true"}, content=queries[n % len(queries)].jpeg)
                    assert r.status_code == 200, r.text
                    n += 1
                    time.sleep(max(0.0, 1 / args.fps - (time.monotonic() - t)))
                return n

            with concurrent.futures.ThreadPoolExecutor(args.sessions) as pool:
                frames = sum(pool.map(lambda s: device(*s), sessions))
            after = table_mib(c)
        return {"interval": interval, "frames": frames, "before": before, "after": after}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sessions", type=int, default=5)
    ap.add_argument("--fps", type=float, default=5.0)
    ap.add_argument("--seconds", type=float, default=30.0)
    ap.add_argument("--out", type=Path, default=RESULTS / "checkpoints.md")
    args = ap.parse_args()
    rows = [run(interval, args) for interval in (0.0, 2.0)]
    lines = [
        "# Checkpoint writes in PostgreSQL",
        "",
        f"`python bench/bench_checkpoints.py --sessions {args.sessions} --fps {args.fps:g} "
        f"--seconds {args.seconds:g}` on {platform.machine()}, {os.cpu_count()} CPUs: "
        f"{args.sessions} sessions (300 particles) each posting a frame every "
        f"{1 / args.fps:g} s for {args.seconds:g} s; autovacuum off for `sessions`, so its "
        "size counts every row version written.",
        "",
        "| VLOC_CHECKPOINT_INTERVAL_S | frames | `sessions` before | after | growth per 1,000 "
        "frames |",
        "|---|---|---|---|---|",
    ]
    for r in rows:
        per = (r["after"] - r["before"]) / r["frames"] * 1000
        lines.append(f"| {r['interval']:g} | {r['frames']} | {r['before']:.2f} MiB | "
                     f"{r['after']:.2f} MiB | {per:.2f} MiB |")
    lines.append("")
    write_result(args.out, "\n".join(lines))


if __name__ == "__main__":
    main()
