"""A frame's path through the service, counted: the cross-file hops from its request to the
socket write of its pose, outside the filter step, and how often its image header, its
metadata and its estimate are parsed or encoded on the way.

    python bench/frame_path.py [--transport http|websocket|both] [--out bench/results/frame_path.md]

How it counts. A live app (SQLite, the local engine, one worker) holds a ten-image map and a
session whose stream is open. A profile hook (``sys.setprofile`` and ``threading.setprofile``,
in place before the app starts its threads) records, while one frame goes from its request
to the pose written on the socket, every call of a function defined in a vloc file. Each
call is attributed to the nearest vloc function below it on its thread's stack (framework
frames between them are skipped: a route called by FastAPI is attributed to the middleware
that called FastAPI). A (caller, callee) pair in two different files is a cross-file call,
however often it is made; it is a hop on the frame's path when the frame passes through it,
either way: the callee is handed the frame (its bytes, its arrival, record, task, outcome,
estimate or message) or returns it. A function reached with the frame from no vloc caller
(through a queue, a thread or the event loop) is a hop too: a hand-off. The worker's part is counted the same way in this process, on the same map
and session: a worker process runs the same ``WorkerState.handle`` on the task it is sent.
The filter step is one hop (into ``workers/core/stepping.step_image``); what it calls is the
filter's, not the path's. The app's periodic loops (idle sessions, following maps) are not
the frame's and are left out; so are calls made by the test client.

Parses and encodings are counted on the same run (the frame carries metadata: an altitude):
a read of its image header (Pillow's ``Image.open``), a ``FrameMetadata`` made, and its
estimate turned from one form into another (``Estimate.to_dict``, a pydantic pose built or
dumped, JSON written or read).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import threading
import time
from collections import OrderedDict
from pathlib import Path

from _common import repo_on_path, write_result

repo_on_path()

import vloc.app  # noqa: E402
from vloc.workers.engine.messages import FrameTask, OpenSession  # noqa: E402
from vloc.workers.engine.worker import WorkerState  # noqa: E402

SOURCE = Path(vloc.app.__file__).resolve().parents[1]
"""Where the installed vloc's files are (the repository, for an editable install)."""

STEP = ("workers/core/stepping.py", "step_image")
CORE = "workers/core/"
LEFT_OUT = {"_every"}
"""Functions whose calls are not the frame's (the app's periodic loops)."""


def _ours(filename: str) -> str | None:
    """The file's path in the repository, or None for a file that is not vloc's."""
    try:
        rel = Path(filename).resolve().relative_to(SOURCE)
    except ValueError:
        return None
    top = rel.parts[0] if rel.parts else ""
    return rel.as_posix() if top in ("app", "workers", "clients") else None


def _carries(value, data: bytes) -> bool:
    """Whether an argument is the frame or something made of it: its bytes, its arrival,
    record, task, outcome, estimate or message (a list of them counts too)."""
    from vloc.app.sessions.live import Arrival
    from vloc.app.sessions.store import FrameRecord, OutcomeRecord
    from vloc.app.sessions.writer import Accepted
    from vloc.workers.core.estimate import Estimate
    from vloc.workers.core.stepping import StepRecord
    from vloc.workers.engine.messages import FrameDone, FrameFailed, FrameTask

    if isinstance(value, bytes | bytearray | memoryview):
        return len(value) == len(data) and bytes(value) == data
    if isinstance(value, Arrival | Accepted | FrameRecord | OutcomeRecord | FrameTask
                  | FrameDone | FrameFailed | Estimate | StepRecord):
        return True
    if isinstance(value, dict):
        return value.get("type") in ("pose", "frame_error") or {"cov", "status"} <= value.keys()
    if type(value).__name__ in ("PoseEstimate", "FrameError"):
        return True
    if isinstance(value, list | tuple) and value and len(value) < 50:
        return any(_carries(v, data) for v in value)
    return False


def _thread() -> str:
    """The thread's part in the path (the test client runs the app's event loop in a
    thread of its own, named after its portal)."""
    name = threading.current_thread().name
    if name.startswith("asyncio-portal"):
        return "event loop"
    return "request thread" if name.startswith("AnyIO worker") else name


def _work(frame, event: str, arg, data: bytes) -> str | None:
    """Which of the frame's parses or encodings a call is, if any: its image header read
    (Pillow's ``Image.open``, simplejpeg's header), its metadata made (a ``FrameMetadata``),
    its estimate encoded or decoded (``Estimate.to_dict``, a pydantic model of it built or
    dumped, JSON written or read)."""
    if event == "c_call":
        name = getattr(arg, "__name__", "")
        if name == "decode_jpeg_header":
            return "header"
        return None
    code = frame.f_code
    where = code.co_filename.replace("\\", "/")
    if code.co_name == "open" and where.endswith("PIL/Image.py"):
        return "header"
    if code.co_name == "__post_init__" and where.endswith("workers/core/metadata.py"):
        return "metadata"
    if code.co_name == "to_dict" and where.endswith("workers/core/estimate.py"):
        return "estimate"
    if where.endswith("pydantic/main.py") and code.co_name in (
            "__init__", "model_dump", "model_dump_json", "model_validate",
            "model_validate_json"):
        this = frame.f_locals.get("self", frame.f_locals.get("cls"))
        kind = this if isinstance(this, type) else type(this)
        return "estimate" if kind.__name__ in ("PoseEstimate", "FrameError") else None
    if where.endswith("json/__init__.py") and code.co_name in ("dumps", "loads"):
        value = frame.f_locals.get("obj", frame.f_locals.get("s"))
        if isinstance(value, str | bytes):
            return "estimate" if b'"seq"' in (value if isinstance(value, bytes)
                                              else value.encode()) else None
        return "estimate" if _carries(value, data) else None
    return None


class HopRecorder:
    """The profile hook: (caller, callee) pairs of vloc functions in different files, and
    which of them hand the callee the frame (:func:`_carries`); and how often the frame's
    header, metadata and estimate are parsed or encoded (:func:`_work`)."""

    def __init__(self) -> None:
        self.on = False
        self.data = b""
        self.hops: OrderedDict[tuple, str] = OrderedDict()
        self.carrying: set[tuple] = set()
        self.work: list[tuple[str, str, str]] = []
        """(what, where, thread) for each parse or encoding, in order."""
        self._lock = threading.Lock()

    def __call__(self, frame, event, arg) -> None:
        if not self.on:
            return
        if event in ("call", "c_call"):
            what = _work(frame, event, arg, self.data)
            if what is not None:
                self._tally(what, frame)
        if event not in ("call", "return"):
            return
        callee = _ours(frame.f_code.co_filename)
        if callee is None or frame.f_code.co_name == "<module>":
            return
        caller, inside_step, f = None, False, frame.f_back
        while f is not None:
            where = _ours(f.f_code.co_filename)
            if where is not None:
                if caller is None:
                    caller = (where, f.f_code.co_qualname)
                if (where, f.f_code.co_name) == STEP:
                    inside_step = True
                if f.f_code.co_name in LEFT_OUT:
                    return
            f = f.f_back
        if inside_step or (caller is not None and caller[0] == callee):
            return
        if caller is not None and caller[0].startswith(CORE) and callee.startswith(CORE):
            return  # the core library's own calls: entering it is the hop
        key = (caller, (callee, frame.f_code.co_qualname))
        code = frame.f_code
        if event == "return":
            # the frame handed back: read_body's bytes, a subscription's message
            if caller is None or not _carries(arg, self.data):
                return
            carries = True
        else:
            n_args = code.co_argcount + code.co_kwonlyargcount
            carries = any(_carries(frame.f_locals.get(name), self.data)
                          for name in code.co_varnames[:n_args])
        if caller is None:
            if not carries:
                return
            # reached through a queue, a thread or the event loop: a hand-off
            key = (("(hand-off)", ""), key[1])
        with self._lock:
            self.hops.setdefault(key, _thread())
            if carries:
                self.carrying.add(key)

    def _tally(self, what: str, frame) -> None:
        f = frame
        while f is not None and _ours(f.f_code.co_filename) is None:
            f = f.f_back
        if f is None or f.f_code.co_name in LEFT_OUT:
            return  # the test client's (reading the pose), or a periodic loop's
        where = f"{_ours(f.f_code.co_filename)} {f.f_code.co_qualname}"
        with self._lock:
            self.work.append((what, where, _thread()))

    def install(self) -> None:
        sys.setprofile(self)
        threading.setprofile(self)

    def remove(self) -> None:
        sys.setprofile(None)
        threading.setprofile(None)


def _frame_through_the_service(transport: str, recorder: HopRecorder, work: Path):
    """One frame over ``transport``, recorded; the worker's task, for :func:`_worker_part`."""
    from fastapi.testclient import TestClient

    from tests.app.conftest import ADMIN, build_map, service_settings
    from tests.app.imagery import map_and_queries
    from vloc.app.main import create_app

    shots, queries = map_and_queries(10)
    settings = service_settings(work / "data", f"sqlite:///{work / 'vloc.sqlite3'}")
    recorder.install()  # before the app starts its threads
    try:
        with TestClient(create_app(settings)) as client:
            map_id = build_map(client, shots)
            created = client.post("/v1/sessions", json={"map_id": map_id}, headers=ADMIN)
            created.raise_for_status()
            sid, token = created.json()["id"], created.json()["token"]
            auth = {"Authorization": f"Bearer {token}"}
            ctx = client.app.state.ctx
            spec = ctx.engine._specs[sid]
            data = queries[0].jpeg
            sent: dict = {}
            submit = ctx.engine.submit_frame

            def spy(session_id, seq, frame, **kwargs):
                sent.update(kwargs)  # what the worker's task carries
                return submit(session_id, seq, frame, **kwargs)

            ctx.engine.submit_frame = spy
            with client.websocket_connect(f"/v1/sessions/{sid}/stream", headers=auth) as ws:
                assert ws.receive_json()["type"] == "hello"
                time.sleep(0.5)
                recorder.data, recorder.on = data, True
                if transport == "http":
                    r = client.post(f"/v1/sessions/{sid}/frames?seq=0&altitude_m=285.0",
                                    content=data,
                                    headers=auth | {"Content-Type": "image/jpeg"})
                    r.raise_for_status()
                else:
                    ws.send_text('{"type": "frame_meta", "seq": 0, '
                                 '"metadata": {"altitude_m": 285.0}}')
                    ws.send_bytes(data)
                msg = ws.receive_json()
                deadline = time.monotonic() + 30
                while ctx.intake.pending_total() and time.monotonic() < deadline:
                    time.sleep(0.01)  # until its pose is stored too
                recorder.on = False
                if msg.get("type") != "pose":
                    raise SystemExit(f"expected a pose, got {msg}")
    finally:
        recorder.remove()
    return spec, data, sent


def _worker_part(spec, data: bytes, sent: dict, recorder: HopRecorder) -> None:
    """The worker's part, on the task the API process sent it (as pickling leaves it)."""
    import pickle

    task = pickle.loads(pickle.dumps(FrameTask(spec.session_id, 0, data, checkpoint=True,
                                               **sent)))
    state = WorkerState(max_pixels=2_000_000)
    state.handle(OpenSession(spec, None, 1))
    recorder.install()
    recorder.data, recorder.on = data, True
    try:
        done = state.handle(task)
    finally:
        recorder.on = False
        recorder.remove()
    if type(done).__name__ != "FrameDone":
        raise SystemExit(f"the worker did not step the frame: {done}")


def count(transport: str) -> tuple[list, list]:
    """One frame sent over ``transport``: its hops (caller, callee, thread, whether it hands
    on the frame) in the order first made, the API process's then the worker's; and its
    parses and encodings (what, where, thread), in order."""
    api, worker = HopRecorder(), HopRecorder()
    with tempfile.TemporaryDirectory() as tmp:
        spec, data, sent = _frame_through_the_service(transport, api, Path(tmp))
        _worker_part(spec, data, sent, worker)
    hops = ([(a, b, t, (a, b) in api.carrying) for (a, b), t in api.hops.items()]
            + [(a, b, "worker process", (a, b) in worker.carrying) for (a, b) in worker.hops])
    work = api.work + [(what, where, "worker process") for what, where, _ in worker.work]
    return hops, work


def report(results: dict[str, tuple[list, list]]) -> str:
    lines = ["# A frame's path: cross-file hops, parses and encodings", "",
             "`python bench/frame_path.py` (how it counts: the module's docstring). A hop",
             "that hands on the frame (its bytes, arrival, record, task, outcome, estimate or",
             "message) is on the frame's path; the others are the checks and helpers the",
             "path calls on the way.", ""]
    for transport, (hops, work) in results.items():
        on_path = sum(h[3] for h in hops)
        tally = {what: sum(w[0] == what for w in work)
                 for what in ("header", "metadata", "estimate")}
        lines += [f"## {transport}: {on_path} hops on the frame's path, {len(hops)} "
                  "cross-file calls in all", "",
                  "Parsed or encoded: " + ", ".join(f"{what} {n}x" for what, n in tally.items())
                  + " (the frame sent with metadata: its altitude).", "",
                  "| # | on the path | thread | from | to |", "|---|---|---|---|---|"]
        for i, (a, b, thread, carries) in enumerate(hops, 1):
            lines.append(f"| {i} | {'yes' if carries else ''} | {thread} | `{a[0]}` {a[1]} "
                         f"| `{b[0]}` {b[1]} |")
        lines += ["", "| parse or encoding | where | thread |", "|---|---|---|"]
        lines += [f"| {what} | `{where}` | {thread} |" for what, where, thread in work]
        lines.append("")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--transport", choices=["http", "websocket", "both"], default="both")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    transports = ["http", "websocket"] if args.transport == "both" else [args.transport]
    results = {t: count(t) for t in transports}
    text = report(results)
    print(text)
    if args.out is not None:
        write_result(args.out, text + "\n", echo=False)


if __name__ == "__main__":
    main()
