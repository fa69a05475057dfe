"""The Ray engine: sessions in long-lived shard actors of a Ray cluster that every API
process shares (``pip install 'vloc[ray]'``).

Shape
-----
- ``n_shards`` named, detached shard actors (``vloc-shard-<i>`` in the ``vloc`` namespace),
  each a process that holds many sessions, spread over the cluster's nodes. A session's shard is a hash of its id, so every
  API process finds it by name with no table to share. One actor per session would cost a
  process per session; a shard holds hundreds.
- A shard is an async actor: its event loop orders the work, one thread of its own runs
  it (decoding, the localiser's step), so frames of all its sessions take turns on one core
  while cheap calls (numbering, pings) are answered between them.
- A shared engine numbers each session's frames itself (:meth:`RayEngine.reserve_seq`):
  whichever API process receives a frame asks the shard for its seq, and the shard steps
  the session's frames in seq order, holding a frame until every seq reserved before it
  has been stepped, given up (:meth:`release_seq`) or waited for ``hold_s``.
- Map data goes into the object store once, through one ``vloc-maps`` actor that loads a
  packed revision and ``ray.put``-s it; each shard reads it from its node's store, and
  numpy arrays come back as zero-copy views of the store's shared memory.
- ``max_task_retries=0``: a frame runs at most once. A shard that dies comes back empty
  (``max_restarts=-1`` re-runs only the constructor); the frames it held are reported as
  failed (``worker_died``) and its sessions are reopened by the service from their
  checkpoints in the database, which is the only state that counts.
- Build work (:meth:`RayEngine.call`) runs as Ray tasks, in parallel over the cluster.
  They reserve no CPU from the scheduler, so that they always find room beside the shards
  whatever those reserve; the engine itself keeps no more of them running than the
  cluster has CPUs.
- The cluster is the one ``address`` names, or a private one started inside this process
  (never one that happens to run on the machine: Ray's default would join it). Shards
  found by name must run this code version (:data:`.ray_actors.CODE_VERSION`) for this
  deployment; others are refused at the start.

The actors themselves are in :mod:`.ray_actors`. Nothing here imports the service: it works
with the same messages as the local engine (:mod:`workers.engine.messages`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from vloc.workers.core.image import Header
    from vloc.workers.core.metadata import FrameMetadata

import collections
import contextlib
import hashlib
import logging
import math
import os
import socket
import threading
import time
import uuid
from collections.abc import Callable
from concurrent.futures import Future

import ray
from ray.exceptions import GetTimeoutError, RayActorError, WorkerCrashedError

from .messages import (
    Checkpoint,
    FrameDone,
    FrameFailed,
    Outcome,
    SessionSpec,
)
from .pool import _settle
from .protocol import SeqRefused
from .ray_actors import CODE_VERSION, HOLD_S, LEASE_S, MAP_STORE, NAMESPACE, MapStore, Shard
from .slots import EngineClosed, WorkerDied, remote_error
from .worker import _function

log = logging.getLogger(__name__)

PING_TIMEOUT_S = 2.0


def shard_name(index: int) -> str:
    return f"vloc-shard-{index}"


def shard_of(session_id: str, n_shards: int) -> int:
    """The shard that holds a session: the same in every process (not Python's ``hash``,
    which is salted per process)."""
    digest = hashlib.blake2b(session_id.encode(), digest_size=8).digest()
    return int.from_bytes(digest, "big") % n_shards


# -- the engine as an API process sees it -----------------------------------------------------

class RayEngine:
    """Sessions in shard actors of a Ray cluster; see the module's doc.

    Parameters
    ----------
    n_shards : int
        Shard actors; every API process of the cluster must use the same number.
    address : str or None
        The cluster (``ray.init(address=...)``); None uses the cluster this process is
        already connected to, or starts a private one inside it.
    on_outcome, checkpoint_every, max_pixels
        As for :class:`~workers.engine.pool.LocalEngine`; the shard counts the frames of a
        session for its checkpoints, whichever process sent them.
    shard_cpus : float
        CPUs the scheduler reserves for each shard actor.
    hold_s : float
        How long a shard waits for a reserved seq's frame before stepping later ones (while
        this engine's lease on the shard lasts: the seqs of a dead process are given up
        within :data:`~.ray_actors.LEASE_S`).
    instance : str or None
        This API process's instance name, the owner of the frames it records: the shards
        tell every process which instances hold leases (:meth:`live_instances`).
    deployment : str
        What the API processes sharing the shards have in common (their database); shards
        of another deployment, or of another code version, are refused.
    """

    shared = True

    def __init__(self, n_shards: int, *, address: str | None = None,
                 on_outcome: Callable[[Outcome], None] | None = None,
                 checkpoint_every: int = 1, max_pixels: int = 50_000_000,
                 shard_cpus: float = 1.0, namespace: str = NAMESPACE,
                 hold_s: float = HOLD_S, instance: str | None = None,
                 deployment: str = "") -> None:
        if n_shards < 1:
            raise ValueError("n_shards must be at least 1")
        self.n_workers = n_shards
        self.address = address
        self.on_outcome = on_outcome
        self.checkpoint_every = checkpoint_every
        self.max_pixels = max_pixels
        self.shard_cpus = shard_cpus
        self.namespace = namespace
        self.hold_s = hold_s
        self.lease = (uuid.uuid4().hex, instance or socket.gethostname())
        self.identity = f"{CODE_VERSION}:{deployment}"
        self.restarts = 0
        self._renewing = threading.Event()
        self._lock = threading.Lock()
        self._running = False
        self._initialised_here = False
        self._shards: list = []
        self._stamps: dict[int, float] = {}
        self._open: set[str] = set()
        self._states: dict[str, bytes] = {}
        self._pending: dict[tuple[str, int], ray.ObjectRef] = {}
        self._remote_fns: dict[Callable, object] = {}
        self._calls_waiting: collections.deque = collections.deque()
        self._calls_running = 0
        self._call_slots = 1

    # -- life cycle -------------------------------------------------------------------------

    def start(self, timeout: float = 120.0) -> None:
        """Join the cluster, find or create the shards and the map store, wait for them."""
        if not ray.is_initialized():
            if self.address:
                ray.init(address=self.address, namespace=self.namespace,
                         include_dashboard=False, log_to_driver=False)
            else:
                # "local": a new cluster for this process, whatever runs on the machine
                cpus = max(os.cpu_count() or 1, math.ceil(self.shard_cpus * self.n_workers))
                ray.init(address="local", num_cpus=cpus, namespace=self.namespace,
                         include_dashboard=False, log_to_driver=False)
            self._initialised_here = True
        self._call_slots = max(1, int(ray.cluster_resources().get("CPU", 1)))
        common = {"namespace": self.namespace, "lifetime": "detached",
                  "get_if_exists": True, "max_restarts": -1, "max_task_retries": 0}
        ray.remote(MapStore).options(name=MAP_STORE, num_cpus=0, **common).remote()
        shard_cls = ray.remote(Shard)
        self._shards = [
            shard_cls.options(name=shard_name(i), num_cpus=self.shard_cpus,
                              max_concurrency=1000, scheduling_strategy="SPREAD", **common)
            .remote(i, max_pixels=self.max_pixels, checkpoint_every=self.checkpoint_every,
                    namespace=self.namespace, hold_s=self.hold_s, version=self.identity)
            for i in range(self.n_workers)]
        try:
            stamps = ray.get([s.ping.remote() for s in self._shards], timeout=timeout)
        except GetTimeoutError:
            raise RuntimeError(f"the Ray shards did not start in {timeout:g} s (are there "
                               "CPUs free for them?)") from None
        for i, (_, _, identity) in enumerate(stamps):
            if identity != self.identity:
                raise RuntimeError(
                    f"shard {shard_name(i)} of Ray namespace {self.namespace!r} runs code "
                    f"version and deployment {identity}, this server {self.identity}: give "
                    "this deployment its own VLOC_RAY_NAMESPACE, or remove the other's shards")
        self._stamps = {i: started for i, (_, started, _) in enumerate(stamps)}
        self._running = True
        self._renewing.set()
        threading.Thread(target=self._renew_leases, name="ray-leases", daemon=True).start()

    def _renew_leases(self) -> None:
        """Renew this process's lease on every shard, four times per lease period, from a
        thread of its own (a busy event loop must not look like a dead process)."""
        while self._renewing.is_set():
            for shard in self._shards:
                with contextlib.suppress(Exception):  # a dead shard comes back by itself
                    shard.lease.remote(*self.lease)
            time.sleep(LEASE_S / 4)

    def close(self, timeout: float = 10.0) -> None:
        """Stop taking work, wait (up to ``timeout``) for the frames sent, report the rest
        as failed. The shards stay: other API processes use them."""
        with self._lock:
            if not self._running:
                return
            self._running = False
            refs = list(self._pending.values())
        if refs:
            ray.wait(refs, num_returns=len(refs), timeout=timeout)
            time.sleep(0.05)  # let the done callbacks of the last ones run
        self._renewing.clear()
        ends = [s.end_lease.remote(self.lease[0]) for s in self._shards]
        with contextlib.suppress(Exception):
            ray.wait(ends, num_returns=len(ends), timeout=PING_TIMEOUT_S)
        with self._lock:
            left, self._pending = list(self._pending), {}
            calls, self._calls_waiting = list(self._calls_waiting), collections.deque()
        for out, *_ in calls:
            _settle(out, error=EngineClosed("the engine stopped"))
        for sid, seq in left:
            self._emit(FrameFailed(sid, seq, "worker_died", "the engine stopped"))
        if self._initialised_here:
            ray.shutdown()
            self._initialised_here = False

    def remove_actors(self) -> None:
        """Kill the shards and the map store of this namespace: every API process loses its
        sessions (they reopen from their checkpoints). For tearing a deployment down."""
        for name in [*(shard_name(i) for i in range(self.n_workers)), MAP_STORE]:
            with contextlib.suppress(ValueError):  # not there
                ray.kill(ray.get_actor(name, namespace=self.namespace), no_restart=True)

    @property
    def running(self) -> bool:
        return self._running

    def _pings(self) -> list[bool]:
        refs = [s.ping.remote() for s in self._shards]
        ready, _ = ray.wait(refs, num_returns=len(refs), timeout=PING_TIMEOUT_S)
        ok = []
        for i, ref in enumerate(refs):
            if ref not in ready:
                ok.append(False)
                continue
            try:
                _, started, _ = ray.get(ref)
            except RayActorError:
                ok.append(False)
                continue
            self._saw_start(i, started)
            ok.append(True)
        return ok

    def _saw_start(self, index: int, started: float) -> None:
        with self._lock:
            if self._stamps.get(index, started) != started:
                self.restarts += 1
                log.error("ray engine: shard %d was restarted; its sessions reopen from "
                          "their checkpoints", index)
            self._stamps[index] = started

    def alive(self) -> bool:
        return self._running and all(self._pings())

    def alive_count(self) -> int:
        return sum(self._pings()) if self._running else 0

    def shard(self, session_id: str):
        """The actor handle of the session's shard."""
        return self._shards[shard_of(session_id, self.n_workers)]

    # -- sessions ---------------------------------------------------------------------------

    def open_session(self, spec: SessionSpec, *, state: bytes | None = None,
                     last_seq: int | None = None) -> Future:
        """Open the session in its shard (kept as it is when another process opened it)."""
        self._check_running()
        sid = spec.session_id

        def opened(reply: tuple) -> str:
            if reply[0] == "error":
                raise remote_error(reply[1], reply[2])
            with self._lock:
                self._open.add(sid)
            return reply[0]

        return self._future(self.shard(sid).open.remote(spec, state, last_seq), opened)

    def is_open(self, session_id: str) -> bool:
        with self._lock:
            return session_id in self._open

    def reserve_seq(self, session_id: str, seq: int | None) -> Future:
        self._check_running()

        def reserved(reply: tuple) -> int:
            if reply[0] == "not_open":
                raise KeyError(session_id)
            if reply[0] == "refused":
                raise SeqRefused(reply[1], seq, reply[2])
            return reply[1]

        return self._future(self.shard(session_id).reserve.remote(session_id, seq, self.lease),
                            reserved)

    def release_seq(self, session_id: str, seq: int) -> None:
        if self._running:
            self.shard(session_id).release.remote(session_id, seq)

    def submit_frame(self, session_id: str, seq: int, data: bytes, *,
                     captured_at: float | None = None,
                     metadata: FrameMetadata | None = None,
                     header: Header | None = None) -> None:
        self._check_running()
        ref = self.shard(session_id).frame.remote(session_id, seq, data, captured_at, metadata,
                                                  header)
        with self._lock:
            self._pending[(session_id, seq)] = ref
        ref.future().add_done_callback(lambda f: self._frame_done(session_id, seq, f))

    def _frame_done(self, session_id: str, seq: int, fut: Future) -> None:
        with self._lock:
            if self._pending.pop((session_id, seq), None) is None:
                return  # reported already, when the engine stopped
        try:
            outcome = fut.result()
        except RayActorError as exc:
            outcome = FrameFailed(session_id, seq, "worker_died",
                                  f"the session's shard died before answering: "
                                  f"{type(exc).__name__}")
        except Exception as exc:  # noqa: BLE001 - reported as the frame's error
            outcome = FrameFailed(session_id, seq, "error", f"{type(exc).__name__}: {exc}")
        if isinstance(outcome, FrameDone) and outcome.state is not None:
            with self._lock:
                if session_id in self._open:
                    self._states[session_id] = outcome.state
        self._emit(outcome)

    def live_instances(self, within_s: float) -> set[str] | None:
        """Instance names of the API processes that renewed their lease on a shard in the
        last ``within_s`` seconds, as the shards saw them; None when no shard has been up
        that long (an answer could miss a live one)."""
        if not self._running:
            return None
        refs = [s.instances.remote(within_s) for s in self._shards]
        ready, _ = ray.wait(refs, num_returns=len(refs), timeout=PING_TIMEOUT_S)
        seen: set[str] | None = None
        for ref in ready:
            try:
                found = ray.get(ref)
            except RayActorError:
                continue
            if found is not None:
                seen = (seen or set()) | set(found)
        return seen

    def pending_frames(self, session_id: str) -> int:
        with self._lock:
            return sum(1 for sid, _ in self._pending if sid == session_id)

    def control(self, session_id: str, op: str, **kwargs) -> Future:
        self._check_running()

        def ran(reply: tuple):
            if reply[0] == "not_open":
                raise KeyError(session_id)
            if reply[0] == "error":
                raise remote_error(reply[1], reply[2])
            _, value, state = reply
            if state is not None:
                with self._lock:
                    self._states[session_id] = state
                self._emit(Checkpoint(session_id, state))
            return value

        return self._future(self.shard(session_id).control.remote(session_id, op, kwargs), ran)

    def close_session(self, session_id: str) -> None:
        with self._lock:
            self._open.discard(session_id)
            self._states.pop(session_id, None)
        if self._running:
            self.shard(session_id).close.remote(session_id)

    def last_state(self, session_id: str) -> bytes | None:
        with self._lock:
            return self._states.get(session_id)

    # -- calls ------------------------------------------------------------------------------

    def call(self, fn: Callable | str, *args, **kwargs) -> Future:
        """Run ``fn`` as a Ray task (never retried), once fewer calls of this engine run
        than the cluster has CPUs.

        The task reserves no CPU: shards may hold every CPU the scheduler counts, and a
        task that waited for one would wait for ever.
        """
        self._check_running()
        fn = _function(fn)
        out: Future = Future()
        with self._lock:
            remote = self._remote_fns.get(fn)
            if remote is None:
                remote = self._remote_fns[fn] = ray.remote(fn).options(num_cpus=0,
                                                                       max_retries=0)
            self._calls_waiting.append((out, remote, args, kwargs))
        self._start_calls()
        return out

    def _start_calls(self) -> None:
        while True:
            with self._lock:
                if not self._calls_waiting or self._calls_running >= self._call_slots:
                    return
                out, remote, args, kwargs = self._calls_waiting.popleft()
                self._calls_running += 1
            try:
                inner = self._future(remote.remote(*args, **kwargs), lambda v: v)
            except BaseException as exc:  # noqa: BLE001 - handed to the caller
                inner = Future()
                inner.set_exception(exc)
            inner.add_done_callback(lambda f, out=out: self._call_done(f, out))

    def _call_done(self, inner: Future, out: Future) -> None:
        with self._lock:
            self._calls_running -= 1
        if inner.exception() is not None:
            _settle(out, error=inner.exception())
        else:
            _settle(out, value=inner.result())
        self._start_calls()

    # -- internals --------------------------------------------------------------------------

    def _check_running(self) -> None:
        if not self._running:
            raise EngineClosed("the engine is not running")

    def _future(self, ref, convert: Callable) -> Future:
        """A future of ``convert(ray.get(ref))``; a dead actor or worker -> WorkerDied."""
        out: Future = Future()

        def done(f: Future) -> None:
            try:
                value = convert(f.result())
            except (RayActorError, WorkerCrashedError) as exc:
                _settle(out, error=WorkerDied(f"{type(exc).__name__}: {exc}"))
            except BaseException as exc:  # noqa: BLE001 - handed to the caller
                _settle(out, error=exc)
            else:
                _settle(out, value=value)

        ref.future().add_done_callback(done)
        return out

    def _emit(self, outcome: Outcome) -> None:
        if self.on_outcome is None:
            return
        try:
            self.on_outcome(outcome)
        except Exception:  # noqa: BLE001 - a broken consumer must not stop the engine
            log.exception("ray engine: frame consumer failed")
