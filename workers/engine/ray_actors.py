"""The actors of the Ray engine (:mod:`.ray_engine`): the map store and the shards.

- :class:`MapStore`, one per cluster (``vloc-maps``): loads a packed map revision and
  ``ray.put``-s it once; every shard reads it from its node's object store, numpy arrays as
  zero-copy views of the store's shared memory.
- :class:`Shard`, one per shard (``vloc-shard-<i>``): an async actor holding many sessions.
  Its event loop orders the work (numbering, turn-taking, pings) and one thread of its own
  runs it (decoding, the localiser's step), so the frames of its sessions take turns on one
  core. A session's frames are stepped in seq order whichever API process sent them: a
  frame waits until every seq reserved before it has been stepped, given up
  (:meth:`Shard.release`), left unsent for ``hold_s``, or its API process's lease lapsed
  (:data:`LEASE_S`: the process died).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from vloc.workers.core.image import Header
    from vloc.workers.core.metadata import FrameMetadata

import asyncio
import contextlib
import hashlib
import os
import time
from collections import OrderedDict
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import ray

from .messages import (
    CloseSession,
    ControlTask,
    FrameDone,
    FrameFailed,
    FrameTask,
    OpenSession,
    SessionSpec,
)
from .worker import THREAD_ENV, WorkerState, _single_threaded

NAMESPACE = "vloc"
MAP_STORE = "vloc-maps"


def _code_version() -> str:
    """A digest of the engine's and the core's source: shards must run the code of the API
    processes that send them work (messages and checkpoints are pickled)."""
    root = Path(__file__).resolve().parents[1]
    digest = hashlib.blake2b(digest_size=8)
    for path in sorted(root.rglob("*.py")):
        digest.update(str(path.relative_to(root)).encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()


CODE_VERSION = _code_version()
HOLD_S = 30.0
"""How long a shard holds a session's frame for a seq reserved before it that has not come,
while the API process that reserved it is alive (its lease renewed): long enough for a busy
process to store the frame's record and send it. A dead process's seqs are given up as soon
as its lease lapses (:data:`LEASE_S`)."""
LEASE_S = 0.8
"""An API process renews its lease on every shard four times in this time; once it has not
for this long it is taken for dead, and the seqs it reserved and never sent are given up at
once, so the frames after them wait no longer (not ``hold_s``)."""
LEASE_KEPT_S = 600.0
"""A lapsed lease is forgotten after this long."""
MAPS_KEPT = 8
"""Map revisions the map store keeps in the object store at once."""


# -- the map store (one actor per cluster) ----------------------------------------------------

class MapStore:
    """Packed map revisions in the object store, each put once."""

    def __init__(self, kept: int = MAPS_KEPT) -> None:
        self.kept = kept
        self.refs: OrderedDict[tuple[str, int], ray.ObjectRef] = OrderedDict()
        self.loads = 0

    def get(self, folder: str, map_id: str, revision: int) -> list:
        """``[ref]`` of the revision's :class:`~workers.core.mapdata.MapData` (in a list, so
        that the caller receives the reference rather than the data)."""
        key = (map_id, revision)
        if key not in self.refs:
            from vloc.workers.core.mapdata import MapData

            # Read into memory, not memory-mapped: Ray serialises plain arrays out of band
            # (one copy into the store, zero-copy views for its readers), memory maps not.
            self.refs[key] = ray.put(MapData.load(folder, mmap=False))
            self.loads += 1
            while len(self.refs) > self.kept:
                # Shards that already read an evicted revision keep their view of it.
                self.refs.popitem(last=False)
        self.refs.move_to_end(key)
        return [self.refs[key]]

    def stats(self) -> dict:
        return {"loads": self.loads, "held": [list(k) for k in self.refs]}


# -- a shard actor ------------------------------------------------------------------------------

class _ShardState(WorkerState):
    """The local worker's session handling, with maps read from the object store."""

    def __init__(self, *, max_pixels: int, namespace: str) -> None:
        super().__init__(max_pixels=max_pixels)
        self.namespace = namespace

    def _map(self, spec: SessionSpec):
        key = (spec.map_id, spec.revision)
        if key not in self.maps:
            store = ray.get_actor(MAP_STORE, namespace=self.namespace)
            (ref,) = ray.get(store.get.remote(spec.map_folder, spec.map_id, spec.revision))
            self.maps[key] = ray.get(ref)
        return self.maps[key]


@dataclass(eq=False)
class _Order:
    """A session's numbering and turn-taking in its shard."""

    last: int | None
    """Highest seq reserved (or given at the open)."""
    started: int | None = None
    """Highest seq whose step has begun."""
    held: dict[int, tuple[float, str | None]] = field(default_factory=dict)
    """Reserved seqs not stepped yet -> (when the shard stops waiting for them, the lease
    owner that reserved them; None once the frame is here)."""
    count: int = 0
    opened: asyncio.Future | None = None
    turn: asyncio.Condition = field(default_factory=asyncio.Condition)


class Shard:
    """Sessions of one shard; run as an async Ray actor (see the module's doc)."""

    def __init__(self, index: int, *, max_pixels: int, checkpoint_every: int,
                 namespace: str = NAMESPACE, hold_s: float = HOLD_S,
                 version: str = CODE_VERSION) -> None:
        for var in THREAD_ENV:
            os.environ.setdefault(var, "1")
        _single_threaded()
        self.index = index
        self.checkpoint_every = checkpoint_every
        self.hold_s = hold_s
        self.state = _ShardState(max_pixels=max_pixels, namespace=namespace)
        self.orders: dict[str, _Order] = {}
        self.pool = ThreadPoolExecutor(1, thread_name_prefix=f"shard-{index}")
        self.started = time.time()
        self.version = version
        self.leases: dict[str, tuple[float, str]] = {}
        """Lease owner (one per API process) -> (last renewal, monotonic; instance name)."""
        self.up_since = time.monotonic()

    async def ping(self) -> tuple[int, float, str]:
        """(pid, start time, version): a new start time means the actor was restarted; the
        version is the code version and deployment it was started for."""
        return os.getpid(), self.started, self.version

    async def node(self) -> str:
        """The id of the Ray node this shard runs on."""
        return ray.get_runtime_context().get_node_id()

    async def lease(self, owner: str, instance: str) -> None:
        """Renew an API process's lease; a renewal after a lapse counts as a new one."""
        self.leases[owner] = (time.monotonic(), instance)

    async def end_lease(self, owner: str) -> None:
        """The API process stops: what it reserved and did not send is given up now."""
        self.leases.pop(owner, None)
        for order in list(self.orders.values()):
            async with order.turn:
                order.turn.notify_all()

    async def instances(self, within_s: float) -> list[str] | None:
        """Instance names of the API processes whose lease was renewed in the last
        ``within_s`` seconds; None when this shard has not been up that long (it may not
        have heard from every live one yet)."""
        now = time.monotonic()
        for owner in [o for o, (seen, _) in self.leases.items() if now - seen > LEASE_KEPT_S]:
            del self.leases[owner]  # long dead: its reservations lapsed long ago
        if now - self.up_since < within_s:
            return None
        return sorted({inst for seen, inst in self.leases.values() if now - seen <= within_s})

    def _expiry(self, deadline: float, owner: str | None) -> float:
        """When the shard stops waiting for a reserved seq: its deadline, or earlier, once
        its owner's lease lapses."""
        if owner is None:
            return deadline
        seen = self.leases.get(owner)
        return min(deadline, (seen[0] if seen else 0.0) + LEASE_S)

    async def held(self) -> list[str]:
        return sorted(sid for sid, o in self.orders.items() if o.opened.done())

    async def _run(self, task):
        return await asyncio.get_running_loop().run_in_executor(self.pool, self.state.handle,
                                                                 task)

    async def open(self, spec: SessionSpec, state: bytes | None,
                   last_seq: int | None) -> tuple:
        """``("opened",)``, ``("kept",)`` when the session is already open here (another
        API process opened it; its localiser is not touched), or ``("error", type, text)``."""
        sid = spec.session_id
        order = self.orders.get(sid)
        if order is not None:
            return await asyncio.shield(order.opened)
        order = self.orders[sid] = _Order(last=last_seq)
        order.opened = asyncio.get_running_loop().create_future()
        done = await self._run(OpenSession(spec, state, call_id=0))
        if done.ok:
            order.opened.set_result(("kept",))
            return ("opened",)
        self.orders.pop(sid, None)
        failed = ("error", done.error_type, done.error)
        order.opened.set_result(failed)
        return failed

    def _ready(self, sid: str) -> _Order | None:
        order = self.orders.get(sid)
        if order is None or not order.opened.done() or order.opened.result()[0] == "error":
            return None
        return order

    async def reserve(self, sid: str, seq: int | None,
                      lease: tuple[str, str] | None = None) -> tuple:
        """``("ok", seq)``, ``("refused", kind, last_seq)`` or ``("not_open",)``; the seq is
        held for ``hold_s``, or while the lease ``(owner, instance)`` lasts (a reservation
        renews it)."""
        owner = None
        if lease is not None:
            owner = lease[0]
            await self.lease(*lease)
        order = self._ready(sid)
        if order is None:
            return ("not_open",)
        if seq is None:
            seq = 0 if order.last is None else order.last + 1
        elif order.last is not None and seq <= order.last:
            return ("refused", "duplicate-seq" if seq == order.last else "stale-seq",
                    order.last)
        order.last = seq
        order.held[seq] = (time.monotonic() + self.hold_s, owner)
        return ("ok", seq)

    async def release(self, sid: str, seq: int) -> None:
        order = self.orders.get(sid)
        if order is not None:
            async with order.turn:
                order.held.pop(seq, None)
                order.turn.notify_all()

    async def _wait_turn(self, order: _Order, before: int) -> None:
        """Until no seq below ``before`` is held (or the ones held are given up)."""
        async with order.turn:
            while True:
                now = time.monotonic()
                expiries = {s: self._expiry(*h) for s, h in order.held.items()}
                for s in [s for s, t in expiries.items() if t <= now]:
                    del order.held[s]
                earlier = [t for s, t in expiries.items() if s < before and t > now]
                if not earlier:
                    return
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(order.turn.wait(), max(min(earlier) - now, 0.001))

    async def frame(self, sid: str, seq: int, data: bytes, captured_at: float | None,
                    metadata: FrameMetadata | None,
                    header: Header | None = None) -> FrameDone | FrameFailed:
        order = self._ready(sid)
        if order is None:
            return FrameFailed(sid, seq, "not_open", "the session is not open in its shard")
        # The frame is here: frames after it wait for it however long its turn takes; only a
        # seq reserved and never sent is given up after hold_s.
        order.held[seq] = (float("inf"), None)
        await self._wait_turn(order, seq)
        if self.orders.get(sid) is not order:
            return FrameFailed(sid, seq, "not_open", "the session was closed")
        if order.started is not None and seq < order.started:
            # Its seq was given up and a later frame went first: stepping it now would put
            # the filter's steps out of order.
            order.held.pop(seq, None)
            return FrameFailed(sid, seq, "error", f"the frame came after frame {order.started} "
                               "had been processed, too late to take its turn")
        order.started = seq
        order.count += 1
        try:
            return await self._run(FrameTask(
                sid, seq, data, captured_at, metadata=metadata, header=header,
                checkpoint=order.count % self.checkpoint_every == 0))
        finally:
            async with order.turn:
                order.held.pop(seq, None)
                order.turn.notify_all()

    async def control(self, sid: str, op: str, kwargs: dict) -> tuple:
        """After the frames reserved before it: ``("ok", value, state)``,
        ``("error", type, text)`` or ``("not_open",)``."""
        order = self._ready(sid)
        if order is None:
            return ("not_open",)
        await self._wait_turn(order, (order.last if order.last is not None else -1) + 1)
        done = await self._run(ControlTask(0, sid, op, dict(kwargs)))
        if not done.ok:
            return ("error", done.error_type, done.error)
        return ("ok", done.value, done.state)

    async def close(self, sid: str) -> None:
        if self.orders.pop(sid, None) is not None:
            await self._run(CloseSession(sid))
