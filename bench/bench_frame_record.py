"""What recording an accepted frame costs: one ``frames`` row written and committed.

A frame reaches its worker only once its record is stored (crash durability), so this
write is on every frame's path; the rest of that path is measured by ``bench_service.py``.
The write is timed the way the writer thread does it, one frame per transaction (the case
of a single session), on a SQLite file and, when reachable, on PostgreSQL.

    python bench/bench_frame_record.py [--frames 2000] [--postgres URL]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
from _common import repo_on_path

repo_on_path()

from vloc.app import migrate  # noqa: E402
from vloc.app.db import make_engine, make_session_factory  # noqa: E402
from vloc.app.maps.models import Map  # noqa: E402
from vloc.app.sessions.models import LocalisationSession  # noqa: E402
from vloc.app.sessions.store import FrameRecord, FrameStore  # noqa: E402


def time_records(url: str, n: int) -> np.ndarray:
    """Milliseconds per ``FrameStore.write`` of one record, ``n`` frames of one session."""
    engine = make_engine(url)
    try:
        migrate.upgrade(engine)
        sessions = make_session_factory(engine)
        with sessions() as db:
            map_ = Map(name="bench")
            db.add(map_)
            db.flush()
            row = LocalisationSession(map_id=map_.id, map_revision=1, mode="hybrid",
                                      params={}, seed=0, token_hash="-", frames_processed=0,
                                      frames_failed=0)
            db.add(row)
            db.commit()
            session_id = str(row.id)
        store = FrameStore(sessions, owner="bench")
        times = np.empty(n)
        for seq in range(n):
            record = FrameRecord(session_id, seq, datetime.now(UTC), None)
            t0 = time.perf_counter()
            if store.write([record]):
                raise SystemExit(f"frame {seq} was not recorded")
            times[seq] = (time.perf_counter() - t0) * 1e3
        return times
    finally:
        engine.dispose()


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=2000)
    p.add_argument("--postgres", default=None,
                   help="a PostgreSQL URL whose database may get the vloc tables")
    args = p.parse_args()
    targets = [("SQLite (WAL, synchronous=NORMAL)",
                f"sqlite:///{Path(tempfile.mkdtemp(prefix='vloc-bench-')) / 'vloc.sqlite3'}")]
    if args.postgres:
        targets.append(("PostgreSQL", args.postgres))
    print("| database | frames | p50 (ms) | p90 (ms) | p99 (ms) |\n|---|---|---|---|---|")
    for name, url in targets:
        t = time_records(url, args.frames)
        print(f"| {name} | {args.frames} | {np.percentile(t, 50):.2f} "
              f"| {np.percentile(t, 90):.2f} | {np.percentile(t, 99):.2f} |")


if __name__ == "__main__":
    main()
